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
    // A joint a light-year away, one id twice, and more people than a dome holds are named.
    let write_bodies = |bodies: Vec<(i64, Vec<f64>)>| {
        let list: Vec<Value> = bodies
            .into_iter()
            .map(|(id, j)| serde_json::json!({"id": id, "joints19": j}))
            .collect();
        std::fs::write(&p, serde_json::json!({ "bodies": list }).to_string()).unwrap();
        read_bodies(&p).unwrap_err().to_string()
    };
    let mut far = joints.clone();
    far[9] = 1e300;
    let e = write_bodies(vec![(3, joints.clone()), (4, far)]);
    assert!(
        e.contains("bodies[1].joints19[9]") && e.contains("cm"),
        "{e}"
    );
    let e = write_bodies(vec![(3, joints.clone()), (3, joints.clone())]);
    assert!(e.contains("bodies[1].id 3 repeats bodies[0]"), "{e}");
    let many = (0..10_001).map(|i| (i, joints.clone())).collect();
    let e = write_bodies(many);
    assert!(e.contains("10001 people"), "{e}");
}

/// A calibration in Panoptic's layout with the five VoxelPose HD cameras plus one more (cm, y down).
fn fixture_calibration() -> Value {
    let cams: Vec<Value> = ["00_03", "00_06", "00_12", "00_13", "00_23", "00_30"]
        .iter()
        .enumerate()
        .map(|(i, name)| {
            let a = i as f64;
            // A rotation about Panoptic's vertical (y) axis, looking at the origin from 400 cm.
            let (c, s) = (a.cos(), a.sin());
            serde_json::json!({
                "name": name, "type": "hd", "resolution": [1920, 1080], "panel": 0, "node": i,
                "K": [[1400.0, 0.0, 960.0], [0.0, 1400.0, 540.0], [0.0, 0.0, 1.0]],
                "distCoef": [-0.2, 0.1, 0.001, -0.001, 0.0],
                "R": [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]],
                "t": [[0.0], [0.0], [400.0]],
            })
        })
        .collect();
    serde_json::json!({"calibDataSource": "fixture", "cameras": cams})
}

/// `n` people standing at x = 50 k cm; person 0 of frame 2 has an unannotated root.
fn fixture_bodies(frame: usize, n: usize) -> Value {
    let bodies: Vec<Value> = (0..n)
        .map(|k| {
            let mut j = Vec::new();
            for i in 0..19 {
                let conf = if frame == 2 && k == 0 && i == 2 {
                    0.05
                } else {
                    0.9
                };
                j.extend([50.0 * k as f64, -100.0 - i as f64, 10.0, conf]);
            }
            serde_json::json!({"id": k, "joints19": j})
        })
        .collect();
    serde_json::json!({"version": 0.7, "univTime": 0.0, "fpsType": "hd_29_97", "bodies": bodies})
}

/// A grey JPEG of the fixture cameras' 1920 x 1080, encoded once.
fn hd_jpeg() -> &'static [u8] {
    static JPEG: std::sync::OnceLock<Vec<u8>> = std::sync::OnceLock::new();
    JPEG.get_or_init(|| {
        let img = image::RgbImage::from_pixel(1920, 1080, image::Rgb([90, 90, 90]));
        let mut out = std::io::Cursor::new(Vec::new());
        img.write_to(&mut out, image::ImageFormat::Jpeg).unwrap();
        out.into_inner()
    })
}

fn fixture_sequence(root: &Path, name: &str, frames: usize, images: bool) -> PathBuf {
    let d = root.join(name);
    std::fs::create_dir_all(d.join("hdPose3d_stage1_coco19")).unwrap();
    std::fs::write(
        d.join(format!("calibration_{name}.json")),
        fixture_calibration().to_string(),
    )
    .unwrap();
    for f in 0..frames {
        let idx = format!("{:08}", 100 + f);
        std::fs::write(
            d.join(format!("hdPose3d_stage1_coco19/body3DScene_{idx}.json")),
            fixture_bodies(f, 3).to_string(),
        )
        .unwrap();
        if images {
            for c in VOXELPOSE_CAMERAS {
                let dir = d.join("hdImgs").join(c);
                std::fs::create_dir_all(&dir).unwrap();
                std::fs::write(dir.join(format!("{c}_{idx}.jpg")), hd_jpeg()).unwrap();
            }
        }
    }
    d
}

#[test]
fn a_fixture_sequence_walks_with_strides_and_validity() {
    use mvmp_data::panoptic::{
        PanopticSequence, ROOT_JOINT, VOXELPOSE_TRAIN, VOXELPOSE_VALIDATION, check_tree,
        split_by_name,
    };
    let root = tempfile::tempdir().unwrap();
    let seq_dir = fixture_sequence(root.path(), "160422_ultimatum1", 7, true);
    let seq = PanopticSequence::open(&seq_dir, &VOXELPOSE_CAMERAS, 3).unwrap();
    assert_eq!(seq.name, "160422_ultimatum1");
    assert_eq!(seq.rig.len(), 5);
    // Every 3rd of the 7 pose files, in frame order: 0, 3, 6.
    let idx: Vec<&str> = seq.frames.iter().map(|f| f.index.as_str()).collect();
    assert_eq!(idx, ["00000100", "00000103", "00000106"]);
    assert_eq!(
        seq.frames[1].images[2],
        seq_dir.join("hdImgs/00_12/00_12_00000103.jpg")
    );
    // Units and axes: (x, y, z) cm with y down -> (x, z, -y) / 100 m with z up.
    let all = PanopticSequence::open(&seq_dir, &VOXELPOSE_CAMERAS, 1).unwrap();
    let people = all.people(&all.frames[0]).unwrap();
    assert_eq!(people.len(), 3);
    let p = people[1].joints[ROOT_JOINT];
    assert!(
        (p[0] - 0.5).abs() < 1e-12 && (p[1] - 0.1).abs() < 1e-12 && (p[2] - 1.02).abs() < 1e-12,
        "{p:?}"
    );
    // Frame 2 has a person without an annotated root: dropped.
    assert_eq!(all.people(&all.frames[2]).unwrap().len(), 2);
    // Splits.
    assert_eq!(split_by_name("voxelpose-train"), Some(VOXELPOSE_TRAIN));
    assert_eq!(VOXELPOSE_VALIDATION.stride, 12);
    assert!(VOXELPOSE_TRAIN.sequences.contains(&"160422_ultimatum1"));
    assert!(split_by_name("panoptic-all").is_none());

    // The check finds the sequence and its counts, then names each broken file.
    let r = check_tree(root.path(), &VOXELPOSE_CAMERAS);
    assert_eq!(
        r.sequences,
        vec![("160422_ultimatum1".to_string(), 5, 7, 20)]
    );
    assert!(r.problems.is_empty(), "{:?}", r.problems);
    let missing = seq_dir.join("hdImgs/00_23/00_23_00000104.jpg");
    std::fs::remove_file(&missing).unwrap();
    let truncated = seq_dir.join("hdPose3d_stage1_coco19/body3DScene_00000105.json");
    let mut b = fixture_bodies(5, 1);
    b["bodies"][0]["joints19"]
        .as_array_mut()
        .unwrap()
        .truncate(70);
    std::fs::write(&truncated, b.to_string()).unwrap();
    // Images that are not images, or not of their camera's size, are named too.
    let garbage = seq_dir.join("hdImgs/00_03/00_03_00000100.jpg");
    std::fs::write(&garbage, b"jpeg").unwrap();
    let small = seq_dir.join("hdImgs/00_06/00_06_00000101.jpg");
    image::RgbImage::new(10, 10).save(&small).unwrap();
    let r = check_tree(root.path(), &VOXELPOSE_CAMERAS);
    assert_eq!(r.problems.len(), 4, "{:?}", r.problems);
    assert!(
        r.problems
            .iter()
            .any(|p| p.path == garbage && p.what.contains("not a readable image"))
    );
    assert!(
        r.problems
            .iter()
            .any(|p| p.path == small && p.what.contains("10 x 10"))
    );
    assert!(
        r.problems
            .iter()
            .any(|p| p.path == missing && p.what.contains("missing"))
    );
    assert!(
        r.problems
            .iter()
            .any(|p| p.path == truncated && p.what.contains("76"))
    );
    // Each problem's line names its file once: the path beside the message, not inside it too.
    for p in &r.problems {
        let name = p.path.file_name().unwrap().to_string_lossy();
        assert!(!p.what.contains(name.as_ref()), "{p:?}");
    }
    // A camera the calibration lacks is named.
    let e = PanopticSequence::open(&seq_dir, &["00_03", "00_31"], 1)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("00_31") && e.contains("calibration_160422_ultimatum1.json"),
        "{e}"
    );
    // No sequence at all.
    let empty = tempfile::tempdir().unwrap();
    let r = check_tree(empty.path(), &VOXELPOSE_CAMERAS);
    assert!(r.problems[0].what.contains("no Panoptic sequence"));
}
