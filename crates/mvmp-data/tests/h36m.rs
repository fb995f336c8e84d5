//! Human3.6M cameras from the published parameters (when ../shared/data is present): a skeleton projected
//! by the reader's cameras lands on the pixels computed from the raw file in its own tool-chain form within
//! the stated bound, cameras sit above the floor around the capture area, and bad files are named.
use std::path::{Path, PathBuf};

use mvmp_data::h36m::{CAMERAS, TEST_SUBJECTS, TRAIN_SUBJECTS, read_cameras};
use nalgebra::Vector3;
use serde_json::Value;

fn shared(rel: &str) -> Option<PathBuf> {
    let p = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(rel);
    p.exists().then_some(p)
}

/// The Human3.6M tool-chain's projection (radial + its tangential form) from the raw file's numbers, mm.
fn raw_project(f: &Value, subject: &str, cam: &str, x: [f64; 3]) -> [f64; 2] {
    let g = |v: &Value| v.as_f64().unwrap();
    let e = &f["extrinsics"][subject][cam];
    let i = &f["intrinsics"][cam];
    let p: Vec<f64> = (0..3)
        .map(|r| (0..3).map(|c| g(&e["R"][r][c]) * x[c]).sum::<f64>() + g(&e["t"][r][0]))
        .collect();
    let (xn, yn) = (p[0] / p[2], p[1] / p[2]);
    let d: Vec<f64> = i["distortion"].as_array().unwrap().iter().map(g).collect();
    let r2 = xn * xn + yn * yn;
    let radial = 1.0 + d[0] * r2 + d[1] * r2 * r2 + d[4] * r2 * r2 * r2;
    // tan = p1 y + p2 x; x_d = x (radial + tan) + p2 r^2; y_d = y (radial + tan) + p1 r^2.
    let tan = d[2] * yn + d[3] * xn;
    let xd = xn * (radial + tan) + d[3] * r2;
    let yd = yn * (radial + tan) + d[2] * r2;
    let k = |r: usize, c: usize| g(&i["calibration_matrix"][r][c]);
    [k(0, 0) * xd + k(0, 2), k(1, 1) * yd + k(1, 2)]
}

#[test]
fn published_cameras_match_the_raw_numbers_within_the_stated_bound() {
    let Some(path) = shared("h36m/karfly_camera-parameters.json") else {
        eprintln!("../shared/data not present: skipped");
        return;
    };
    let raw: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let mut worst: f64 = 0.0;
    for subject in TRAIN_SUBJECTS.iter().chain(&TEST_SUBJECTS) {
        let rig = read_cameras(&path, subject).unwrap();
        assert_eq!(rig.len(), 4);
        for (cam, id) in rig.cameras.iter().zip(CAMERAS) {
            // Cameras stand around the capture area, 1.3-1.8 m above the floor (z up, metres).
            let c = cam.centre();
            assert!(c.z > 1.2 && c.z < 2.0, "{subject}/{id}: centre {c:?}");
            assert!(c.x.hypot(c.y) > 3.0, "{subject}/{id}: centre {c:?}");
            // A grid of points standing in the middle of the room (mm), projected both ways.
            for gx in -4..=4 {
                for gz in 0..=8 {
                    let x = [gx as f64 * 300.0, 500.0, gz as f64 * 230.0];
                    let want = raw_project(&raw, subject, id, x);
                    let (got, depth) = cam.project(&(Vector3::new(x[0], x[1], x[2]) / 1000.0));
                    assert!(depth > 0.0);
                    if cam.contains(got) {
                        let e = (got.x - want[0]).hypot(got.y - want[1]);
                        worst = worst.max(e);
                    }
                }
            }
        }
    }
    // The two tangential forms differ by less than half a pixel (the module's statement: 0.49 px).
    assert!(worst < 0.5, "worst difference {worst} px");
    assert!(worst > 1e-3, "the forms do differ: {worst} px");
}

#[test]
fn bad_camera_files_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("cams.json");
    std::fs::write(&p, r#"{"intrinsics": {}, "extrinsics": {"S1": {}}}"#).unwrap();
    let e = read_cameras(&p, "S2").unwrap_err().to_string();
    assert!(e.contains("cams.json") && e.contains("S2"), "{e}");
    let e = read_cameras(&p, "S1").unwrap_err().to_string();
    assert!(e.contains("54138969") && e.contains("intrinsics"), "{e}");
    std::fs::write(&p, "{").unwrap();
    let e = read_cameras(&p, "S1").unwrap_err().to_string();
    assert!(e.contains("not a Human3.6M"), "{e}");
}
