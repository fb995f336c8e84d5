//! Real calibrations from ../shared/data (CMU Panoptic, Human3.6M), read when that folder exists.
//! Expected pixels are derived by hand from each file's own numbers in its own convention.
use std::path::PathBuf;

use mvmp_geom::Camera;
use nalgebra::{Matrix3, Vector3};
use serde_json::Value;

fn shared(rel: &str) -> Option<PathBuf> {
    let p = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data")
        .join(rel);
    if p.exists() {
        Some(p)
    } else {
        eprintln!("skipping: {} is not present", p.display());
        None
    }
}

fn m3(v: &Value) -> Matrix3<f64> {
    Matrix3::from_fn(|i, j| v[i][j].as_f64().unwrap())
}

fn f(v: &Value) -> f64 {
    v.as_f64().unwrap()
}

/// Check a camera against hand-derived pixels: a point on the optical axis lands on the principal point;
/// the world origin lands where the file's numbers put it (`x_cam = t`, OpenCV distortion written out).
fn check(cam: &Camera, k: &Value, dist: &[f64], t_file: [f64; 3], unit: f64) {
    let (fx, s, cx) = (f(&k[0][0]), f(&k[0][1]), f(&k[0][2]));
    let (fy, cy) = (f(&k[1][1]), f(&k[1][2]));
    // On the optical axis, 3 m in front of the camera.
    let axis = cam.centre() + cam.r.transpose() * Vector3::new(0.0, 0.0, 3.0);
    let (uv, z) = cam.project(&axis);
    assert!((z - 3.0).abs() < 1e-9);
    assert!(
        (uv.x - cx).abs() < 1e-6 && (uv.y - cy).abs() < 1e-6,
        "{}: {uv} vs ({cx}, {cy})",
        cam.name
    );
    // The world origin: camera coordinates are t (in the file's units; the ratio is unit-free).
    let (x, y) = (t_file[0] / t_file[2], t_file[1] / t_file[2]);
    let r2 = x * x + y * y;
    let (k1, k2, p1, p2, k3) = (dist[0], dist[1], dist[2], dist[3], dist[4]);
    let radial = 1.0 + k1 * r2 + k2 * r2 * r2 + k3 * r2 * r2 * r2;
    let xd = x * radial + 2.0 * p1 * x * y + p2 * (r2 + 2.0 * x * x);
    let yd = y * radial + p1 * (r2 + 2.0 * y * y) + 2.0 * p2 * x * y;
    let want = (fx * xd + s * yd + cx, fy * yd + cy);
    let (uv, z) = cam.project(&Vector3::zeros());
    assert!((z - t_file[2] * unit).abs() < 1e-9);
    assert!(
        (uv.x - want.0).abs() < 1e-6 && (uv.y - want.1).abs() < 1e-6,
        "{}: {uv} vs {want:?}",
        cam.name
    );
}

#[test]
fn panoptic_hd_cameras_with_skew() {
    for file in [
        "panoptic/dance2_calibration.json",
        "panoptic/ultimatum1_calibration.json",
    ] {
        let Some(path) = shared(file) else { return };
        let v: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
        let mut n = 0;
        for c in v["cameras"]
            .as_array()
            .unwrap()
            .iter()
            .filter(|c| c["type"] == "hd")
        {
            let dist: Vec<f64> = c["distCoef"].as_array().unwrap().iter().map(f).collect();
            let t_cm = [0, 1, 2].map(|i| f(&c["t"][i][0]));
            let res = c["resolution"].as_array().unwrap();
            // Panoptic stores centimetres; mvmp works in metres.
            let cam = Camera::new(
                c["name"].as_str().unwrap(),
                m3(&c["K"]),
                m3(&c["R"]),
                Vector3::from(t_cm) * 0.01,
                [dist[0], dist[1], dist[2], dist[3], dist[4]],
                res[0].as_u64().unwrap() as u32,
                res[1].as_u64().unwrap() as u32,
            )
            .unwrap();
            check(&cam, &c["K"], &dist, t_cm, 0.01);
            n += 1;
        }
        assert!(n >= 31, "{file}: {n} HD cameras");
    }
}

#[test]
fn human36m_cameras() {
    let Some(path) = shared("h36m/karfly_camera-parameters.json") else {
        return;
    };
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let mut n = 0;
    for (subject, cams) in v["extrinsics"].as_object().unwrap() {
        for (id, ext) in cams.as_object().unwrap() {
            let intr = &v["intrinsics"][id];
            let dist: Vec<f64> = intr["distortion"]
                .as_array()
                .unwrap()
                .iter()
                .map(f)
                .collect();
            let t_mm = [0, 1, 2].map(|i| {
                let t = &ext["t"][i];
                t.as_f64().unwrap_or_else(|| f(&t[0]))
            });
            let cam = Camera::new(
                format!("{subject}/{id}"),
                m3(&intr["calibration_matrix"]),
                m3(&ext["R"]),
                Vector3::from(t_mm) * 0.001,
                [dist[0], dist[1], dist[2], dist[3], dist[4]],
                1000,
                1002,
            )
            .unwrap();
            check(&cam, &intr["calibration_matrix"], &dist, t_mm, 0.001);
            n += 1;
        }
    }
    assert!(n >= 28, "{n} subject cameras");
}
