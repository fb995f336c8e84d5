//! The Panoptic reader: real calibrations (when ../shared/data is present) reproject a skeleton to the
//! pixels computed from the raw file in Panoptic's own convention; body files convert units and axes.
use std::path::{Path, PathBuf};

use mvmp_data::panoptic::{VOXELPOSE_CAMERAS, point_to_world, read_bodies, read_calibration};
use nalgebra::Vector3;
use serde_json::Value;

fn shared(rel: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(rel);
    p.exists().then_some(p)
}

/// Pixels of a Panoptic-convention point (cm, y down) computed directly from the raw camera entry.
fn raw_project(c: &Value, x: [f64; 3]) -> [f64; 2] {
    let f = |v: &Value| v.as_f64().unwrap();
    let r = |i: usize, j: usize| f(&c["R"][i][j]);
    let t = |i: usize| f(&c["t"][i][0]);
    let cam: Vec<f64> = (0..3)
        .map(|i| r(i, 0) * x[0] + r(i, 1) * x[1] + r(i, 2) * x[2] + t(i))
        .collect();
    let (xn, yn) = (cam[0] / cam[2], cam[1] / cam[2]);
    let d: Vec<f64> = c["distCoef"].as_array().unwrap().iter().map(f).collect();
    let r2 = xn * xn + yn * yn;
    let radial = 1.0 + d[0] * r2 + d[1] * r2 * r2 + d[4] * r2 * r2 * r2;
    let xd = xn * radial + 2.0 * d[2] * xn * yn + d[3] * (r2 + 2.0 * xn * xn);
    let yd = yn * radial + d[2] * (r2 + 2.0 * yn * yn) + 2.0 * d[3] * xn * yn;
    let k = |i: usize, j: usize| f(&c["K"][i][j]);
    [
        k(0, 0) * xd + k(0, 1) * yd + k(0, 2),
        k(1, 1) * yd + k(1, 2),
    ]
}

#[test]
fn real_calibrations_reproject_a_skeleton_like_the_raw_files() {
    for file in [
        "panoptic/ultimatum1_calibration.json",
        "panoptic/dance2_calibration.json",
    ] {
        let Some(path) = shared(file) else {
            eprintln!("skipping: ../shared/data/{file} is not present");
            return;
        };
        let raw: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        let rig = read_calibration(&path, &VOXELPOSE_CAMERAS).unwrap();
        assert_eq!(rig.len(), 5);
        // A standing skeleton in Panoptic coordinates: y down, so the head has the most negative y.
        let skeleton = [
            [0.0, -95.0, 10.0],
            [0.0, -150.0, 12.0],
            [0.0, -170.0, 15.0],
            [20.0, -90.0, 10.0],
            [-20.0, -5.0, 8.0],
        ];
        for (cam, name) in rig.cameras.iter().zip(VOXELPOSE_CAMERAS) {
            let c = raw["cameras"]
                .as_array()
                .unwrap()
                .iter()
                .find(|c| c["name"] == name)
                .unwrap();
            for p in skeleton {
                let want = raw_project(c, p);
                let w = point_to_world(p);
                let (uv, z) = cam.project(&Vector3::from(w));
                assert!(z > 0.0);
                assert!(
                    (uv.x - want[0]).abs() < 1e-6 && (uv.y - want[1]).abs() < 1e-6,
                    "{file} {name}: {uv} vs {want:?}"
                );
            }
        }
        // The world is z up: the head is above the pelvis.
        assert!(point_to_world(skeleton[2])[2] > point_to_world(skeleton[0])[2]);
        // A camera named in the split but absent from the file is an error naming it.
        let e = read_calibration(&path, &["00_03", "00_99"])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("00_99") && e.contains(file.rsplit('/').next().unwrap()),
            "{e}"
        );
    }
}

#[test]
fn body_files_convert_units_and_axes_and_reject_truncated_joints() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("body3DScene_00000123.json");
    let mut joints: Vec<f64> = Vec::new();
    for j in 0..19 {
        joints.extend([10.0 + j as f64, -150.0, 20.0, 0.5]);
    }
    let body = serde_json::json!({"version": 0.7, "univTime": 1.0, "fpsType": "hd_29_97",
        "bodies": [{"id": 3, "joints19": joints}]});
    std::fs::write(&p, body.to_string()).unwrap();
    let b = read_bodies(&p).unwrap();
    assert_eq!(b.len(), 1);
    assert_eq!(b[0].id, 3);
    // (10, -150, 20) cm -> (0.10, 0.20, 1.50) m: x kept, z = -y (up), y = z.
    let j0 = b[0].joints[0];
    assert!(
        (j0[0] - 0.10).abs() < 1e-12
            && (j0[1] - 0.20).abs() < 1e-12
            && (j0[2] - 1.50).abs() < 1e-12,
        "{j0:?}"
    );
    assert_eq!(b[0].confidence[5], 0.5);
    let truncated = serde_json::json!({"bodies": [{"id": 0, "joints19": [1.0, 2.0, 3.0]}]});
    std::fs::write(&p, truncated.to_string()).unwrap();
    let e = read_bodies(&p).unwrap_err().to_string();
    assert!(
        e.contains("body3DScene_00000123.json") && e.contains("joints19") && e.contains("76"),
        "{e}"
    );
    std::fs::write(&p, "{\"version\": 0.7}").unwrap();
    assert!(read_bodies(&p).unwrap_err().to_string().contains("bodies"));
}
