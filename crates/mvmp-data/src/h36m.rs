//! Human3.6M cameras as published (REFERENCE.md 1.4): the `camera-parameters.json` layout generated from the
//! official `metadata.xml` (intrinsics per camera id: `calibration_matrix`, `distortion` =
//! `[k1, k2, p1, p2, k3]`; extrinsics per subject and camera: `R`, `t` with `x_cam = R X + t`, millimetres).
//! The world is z up in millimetres; it is read into metres.
//!
//! Tangential distortion: the coefficients come from the Human3.6M tool-chain, whose projection adds
//! `x (p1 y + p2 x) + p2 r^2` to x (and the mirror to y), where OpenCV adds `2 p1 x y + p2 (r^2 + 2 x^2)`.
//! mvmp's cameras use the OpenCV form everywhere, so these coefficients are read as OpenCV's. For points
//! in the capture volume the two forms differ by less than half a pixel (0.49 px at most, measured on all
//! four cameras of the seven protocol subjects by this crate's tests) on 1000-pixel images, far below the
//! 4-pixel heatmap stride; an exact tool-chain mode is not worth a second distortion model.
use std::path::Path;

use nalgebra::{Matrix3, Vector3};
use serde::Deserialize;

use crate::DataError;
use mvmp_geom::{Camera, Rig};

/// The four camera ids, in the usual order.
pub const CAMERAS: [&str; 4] = ["54138969", "55011271", "58860488", "60457274"];
/// Image size of each camera (width, height), as the dataset's videos have them.
pub const RESOLUTIONS: [(u32, u32); 4] = [(1000, 1002), (1000, 1000), (1000, 1000), (1000, 1002)];
/// The standard protocol's subjects.
pub const TRAIN_SUBJECTS: [&str; 5] = ["S1", "S5", "S6", "S7", "S8"];
pub const TEST_SUBJECTS: [&str; 2] = ["S9", "S11"];

#[derive(Deserialize)]
struct File {
    intrinsics: std::collections::BTreeMap<String, Intrinsics>,
    extrinsics: std::collections::BTreeMap<String, std::collections::BTreeMap<String, Extrinsics>>,
}

#[derive(Deserialize)]
struct Intrinsics {
    calibration_matrix: [[f64; 3]; 3],
    distortion: Vec<f64>,
}

#[derive(Deserialize)]
struct Extrinsics {
    #[serde(rename = "R")]
    r: [[f64; 3]; 3],
    t: Vec<Vec<f64>>,
}

/// The four cameras of `subject` (for example "S9") as a rig in metres.
pub fn read_cameras(path: &Path, subject: &str) -> Result<Rig, DataError> {
    let text = std::fs::read_to_string(path).map_err(|e| DataError::io(path, e))?;
    let file: File = serde_json::from_str(&text).map_err(|e| {
        DataError::file(path, format!("not a Human3.6M camera-parameters file: {e}"))
    })?;
    let ext = file.extrinsics.get(subject).ok_or_else(|| {
        DataError::file(
            path,
            format!(
                "subject {subject:?} is not in `extrinsics` (it has {:?})",
                file.extrinsics.keys().collect::<Vec<_>>()
            ),
        )
    })?;
    let mut cams = Vec::with_capacity(4);
    for (id, (w, h)) in CAMERAS.iter().zip(RESOLUTIONS) {
        let i = file.intrinsics.get(*id).ok_or_else(|| {
            DataError::file(path, format!("camera {id:?} is not in `intrinsics`"))
        })?;
        let e = ext.get(*id).ok_or_else(|| {
            DataError::file(
                path,
                format!("camera {id:?} is not in `extrinsics.{subject}`"),
            )
        })?;
        if i.distortion.len() != 5 {
            return Err(DataError::file(
                path,
                format!(
                    "intrinsics.{id}.distortion has {} values, expected 5 [k1, k2, p1, p2, k3]",
                    i.distortion.len()
                ),
            ));
        }
        let t: Vec<f64> = e.t.iter().flatten().copied().collect();
        if t.len() != 3 {
            return Err(DataError::file(
                path,
                format!(
                    "extrinsics.{subject}.{id}.t has {} values, expected 3",
                    t.len()
                ),
            ));
        }
        let m = |a: &[[f64; 3]; 3]| Matrix3::from_fn(|r, c| a[r][c]);
        let d = &i.distortion;
        let cam = Camera::new(
            *id,
            m(&i.calibration_matrix),
            m(&e.r),
            Vector3::new(t[0], t[1], t[2]) / 1000.0,
            [d[0], d[1], d[2], d[3], d[4]],
            w,
            h,
        )
        .map_err(|err| DataError::file(path, format!("camera {subject}/{id}: {err}")))?;
        cams.push(cam);
    }
    Ok(Rig::new(cams))
}
