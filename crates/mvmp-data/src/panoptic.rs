//! CMU Panoptic Studio files (REFERENCE.md 1.2), converted once, at load time, into mvmp's conventions:
//! Panoptic's world is in centimetres with y pointing down; mvmp's is in metres with z up. A Panoptic point
//! `X_p` maps to `X = M X_p / 100` with `M = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]` (a proper rotation), so a
//! camera `x_cam = R X_p + t` (cm) becomes `x_cam = (R M^T) X + t / 100` (m). Skew and distortion are kept.
use std::path::Path;

use nalgebra::{Matrix3, Vector3};
use serde::Deserialize;

use crate::DataError;
use mvmp_geom::{Camera, Rig};

/// Panoptic world (cm, y down) to mvmp world (m, z up).
pub fn panoptic_to_world() -> Matrix3<f64> {
    Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, 1.0, 0.0, -1.0, 0.0) / 100.0
}

/// A point in Panoptic coordinates (cm) to mvmp's world (m).
pub fn point_to_world(p: [f64; 3]) -> [f64; 3] {
    (panoptic_to_world() * Vector3::from(p)).into()
}

/// The HD cameras VoxelPose uses (panel 0, nodes 3, 6, 12, 13, 23), in its order.
pub const VOXELPOSE_CAMERAS: [&str; 5] = ["00_03", "00_06", "00_12", "00_13", "00_23"];

#[derive(Deserialize)]
struct CalibFile {
    cameras: Vec<CalibCamera>,
}

#[derive(Deserialize)]
struct CalibCamera {
    name: String,
    resolution: [u32; 2],
    #[serde(rename = "K")]
    k: [[f64; 3]; 3],
    #[serde(rename = "distCoef")]
    dist: Vec<f64>,
    #[serde(rename = "R")]
    r: [[f64; 3]; 3],
    t: Vec<Vec<f64>>,
}

/// Read the named cameras (for example [`VOXELPOSE_CAMERAS`]) of a `calibration_<seq>.json` as a rig in
/// mvmp's world. A name the file does not hold is an error naming it.
pub fn read_calibration(path: &Path, names: &[&str]) -> Result<Rig, DataError> {
    let text = std::fs::read_to_string(path).map_err(|e| DataError::io(path, e))?;
    let file: CalibFile = serde_json::from_str(&text)
        .map_err(|e| DataError::file(path, format!("not a Panoptic calibration: {e}")))?;
    let mut cams = Vec::with_capacity(names.len());
    for &name in names {
        let c = file
            .cameras
            .iter()
            .find(|c| c.name == name)
            .ok_or_else(|| {
                DataError::file(path, format!("camera {name:?} is not in the calibration"))
            })?;
        if c.dist.len() != 5 {
            return Err(DataError::file(
                path,
                format!(
                    "camera {name}: key `distCoef` has {} values, expected 5",
                    c.dist.len()
                ),
            ));
        }
        let t: Vec<f64> = c.t.iter().flatten().copied().collect();
        if t.len() != 3 {
            return Err(DataError::file(
                path,
                format!("camera {name}: key `t` has {} values, expected 3", t.len()),
            ));
        }
        let r = Matrix3::from_fn(|i, j| c.r[i][j]);
        let k = Matrix3::from_fn(|i, j| c.k[i][j]);
        // x_cam = R X_p + t = R M^T (100 X) + t, in metres: (R M^T) X + t / 100.
        let m = panoptic_to_world() * 100.0;
        let cam = Camera::new(
            name,
            k,
            r * m.transpose(),
            Vector3::new(t[0], t[1], t[2]) / 100.0,
            [c.dist[0], c.dist[1], c.dist[2], c.dist[3], c.dist[4]],
            c.resolution[0],
            c.resolution[1],
        )
        .map_err(|e| DataError::file(path, e.to_string()))?;
        cams.push(cam);
    }
    Ok(Rig::new(cams))
}

/// One person of a `body3DScene_*.json`: the 19 joints in mvmp's world and their confidences.
#[derive(Debug, Clone, PartialEq)]
pub struct PanopticBody {
    pub id: i64,
    pub joints: Vec<[f64; 3]>,
    pub confidence: Vec<f64>,
}

#[derive(Deserialize)]
struct BodyFile {
    bodies: Vec<BodyEntry>,
}

#[derive(Deserialize)]
struct BodyEntry {
    id: i64,
    joints19: Vec<f64>,
}

/// Read the people of a `body3DScene_<frame>.json` (joints19: 19 x (x, y, z, confidence), cm).
pub fn read_bodies(path: &Path) -> Result<Vec<PanopticBody>, DataError> {
    let text = std::fs::read_to_string(path).map_err(|e| DataError::io(path, e))?;
    let file: BodyFile = serde_json::from_str(&text)
        .map_err(|e| DataError::file(path, format!("not a Panoptic body file: {e}")))?;
    file.bodies
        .into_iter()
        .enumerate()
        .map(|(i, b)| {
            if b.joints19.len() != 76 {
                return Err(DataError::file(
                    path,
                    format!(
                        "bodies[{i}].joints19 has {} values, expected 76 (19 x 4)",
                        b.joints19.len()
                    ),
                ));
            }
            let joints = b
                .joints19
                .chunks_exact(4)
                .map(|c| point_to_world([c[0], c[1], c[2]]))
                .collect();
            let confidence = b.joints19.chunks_exact(4).map(|c| c[3]).collect();
            Ok(PanopticBody {
                id: b.id,
                joints,
                confidence,
            })
        })
        .collect()
}
