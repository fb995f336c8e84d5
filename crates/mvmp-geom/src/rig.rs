//! The camera-rig file: every camera of a synchronized rig, in one JSON document.
//!
//! ```json
//! {
//!   "format": "mvmp-rig",
//!   "version": 1,
//!   "units": "m",
//!   "cameras": [
//!     { "name": "cam0",
//!       "K": [[fx, skew, cx], [0, fy, cy], [0, 0, 1]],
//!       "R": [[r00, r01, r02], [r10, r11, r12], [r20, r21, r22]],
//!       "t": [tx, ty, tz],
//!       "dist": [k1, k2, p1, p2, k3],
//!       "resolution": [width, height] }
//!   ]
//! }
//! ```
//! `R` and `t` map world to camera (`x_cam = R x_world + t`, OpenCV). `units` is the unit of `t` and of the
//! world: `m`, `cm` or `mm`; the reader converts to metres, so everything inside mvmp is in metres. `K` is in
//! pixels of the image of size `resolution`; `dist` follows OpenCV (`[k1, k2, p1, p2, k3]`, tangential with
//! the factor 2); `dist` may be omitted for an ideal pinhole, or given as `[k1, k2, p1, p2]` (k3 = 0), or
//! as OpenCV's longer vectors when their further terms are zero.
use std::path::Path;

use nalgebra::{Matrix3, Vector3};
use serde::{Deserialize, Serialize};

use crate::{Camera, GeomError};
use mvmp_io::write_atomic;

pub const RIG_FORMAT: &str = "mvmp-rig";
pub const RIG_VERSION: u32 = 1;

/// A synchronized, calibrated set of cameras (metres).
#[derive(Debug, Clone, PartialEq)]
pub struct Rig {
    pub cameras: Vec<Camera>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct RigFile {
    format: String,
    version: u32,
    units: String,
    cameras: Vec<CameraEntry>,
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct CameraEntry {
    name: String,
    #[serde(rename = "K")]
    k: [[f64; 3]; 3],
    #[serde(rename = "R")]
    r: [[f64; 3]; 3],
    t: [f64; 3],
    /// Any length OpenCV writes (4, 5, 8, 12 or 14); see [`distortion`].
    #[serde(default)]
    dist: Vec<f64>,
    resolution: [u32; 2],
}

/// OpenCV's distortion vector as the five terms the camera model has: `[k1, k2, p1, p2]` (as many
/// calibration tools write it) gets `k3 = 0`; the longer vectors of OpenCV's rational, thin-prism and
/// tilted models are read when the terms beyond the fifth are zero, and refused otherwise (naming
/// them) rather than projected without them. None at all is an ideal pinhole.
fn distortion(dist: &[f64]) -> Result<[f64; 5], String> {
    match dist.len() {
        0 => Ok([0.0; 5]),
        4 | 5 | 8 | 12 | 14 => {
            if let Some(i) = (5..dist.len()).find(|&i| dist[i] != 0.0) {
                return Err(format!(
                    "`dist` term {i} is {} but only [k1, k2, p1, p2, k3] are modelled: the terms of OpenCV's rational, thin-prism and tilted models must be 0",
                    dist[i]
                ));
            }
            Ok(std::array::from_fn(|i| dist.get(i).copied().unwrap_or(0.0)))
        }
        n => Err(format!(
            "`dist` has {n} values; expected OpenCV's 4, 5, 8, 12 or 14 ([k1, k2, p1, p2, k3, ...])"
        )),
    }
}

fn mat(rows: &[[f64; 3]; 3]) -> Matrix3<f64> {
    Matrix3::from_fn(|i, j| rows[i][j])
}

fn rows(m: &Matrix3<f64>) -> [[f64; 3]; 3] {
    std::array::from_fn(|i| std::array::from_fn(|j| m[(i, j)]))
}

/// Metres per unit for a `units` string.
pub fn unit_scale(units: &str) -> Option<f64> {
    match units {
        "m" | "metre" | "metres" | "meter" | "meters" => Some(1.0),
        "cm" | "centimetre" | "centimetres" | "centimeter" | "centimeters" => Some(0.01),
        "mm" | "millimetre" | "millimetres" | "millimeter" | "millimeters" => Some(0.001),
        _ => None,
    }
}

impl Rig {
    pub fn new(cameras: Vec<Camera>) -> Self {
        Rig { cameras }
    }

    pub fn len(&self) -> usize {
        self.cameras.len()
    }

    pub fn is_empty(&self) -> bool {
        self.cameras.is_empty()
    }

    /// Parse a rig from JSON text; `path` is only used in messages.
    pub fn from_json_str(text: &str, path: &Path) -> Result<Self, GeomError> {
        let file: RigFile = mvmp_io::parse_json(text)
            .map_err(|e| GeomError::file(path, format!("not a valid rig file: {e}")))?;
        if file.format != RIG_FORMAT {
            return Err(GeomError::file(
                path,
                format!("key `format` is {:?}, expected {RIG_FORMAT:?}", file.format),
            ));
        }
        if file.version != RIG_VERSION {
            return Err(GeomError::file(
                path,
                format!(
                    "key `version` is {}, this build reads version {RIG_VERSION}",
                    file.version
                ),
            ));
        }
        let scale = unit_scale(&file.units).ok_or_else(|| {
            GeomError::file(
                path,
                format!(
                    "key `units` is {:?}, expected \"m\", \"cm\" or \"mm\"",
                    file.units
                ),
            )
        })?;
        if file.cameras.is_empty() {
            return Err(GeomError::file(path, "key `cameras` is empty"));
        }
        let mut cameras = Vec::with_capacity(file.cameras.len());
        for (i, c) in file.cameras.iter().enumerate() {
            // The same camera twice would count one view twice in every fusion.
            if let Some(j) = file.cameras[..i]
                .iter()
                .position(|o| o.name == c.name || (o.k == c.k && o.r == c.r && o.t == c.t))
            {
                return Err(GeomError::file(
                    path,
                    format!(
                        "cameras[{i}] ({:?}) repeats cameras[{j}] ({:?}): camera names and poses must differ",
                        c.name, file.cameras[j].name
                    ),
                ));
            }
        }
        for (i, c) in file.cameras.into_iter().enumerate() {
            let dist = distortion(&c.dist)
                .map_err(|e| GeomError::file(path, format!("cameras[{i}] ({:?}): {e}", c.name)))?;
            let cam = Camera::new(
                c.name.clone(),
                mat(&c.k),
                mat(&c.r),
                Vector3::from(c.t) * scale,
                dist,
                c.resolution[0],
                c.resolution[1],
            )
            .map_err(|e| GeomError::file(path, format!("cameras[{i}]: {e}")))?;
            cameras.push(cam);
        }
        Ok(Rig { cameras })
    }

    /// Read a rig file.
    pub fn read(path: &Path) -> Result<Self, GeomError> {
        let text = std::fs::read_to_string(path).map_err(|source| GeomError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        Self::from_json_str(&text, path)
    }

    /// The rig as JSON text (metres).
    pub fn to_json_string(&self) -> String {
        let file = RigFile {
            format: RIG_FORMAT.into(),
            version: RIG_VERSION,
            units: "m".into(),
            cameras: self
                .cameras
                .iter()
                .map(|c| CameraEntry {
                    name: c.name.clone(),
                    k: rows(&c.k),
                    r: rows(&c.r),
                    t: c.t.into(),
                    dist: c.dist.to_vec(),
                    resolution: [c.width, c.height],
                })
                .collect(),
        };
        serde_json::to_string_pretty(&file).expect("rig serialisation cannot fail")
    }

    /// Write the rig atomically.
    pub fn write(&self, path: &Path) -> Result<(), GeomError> {
        Ok(write_atomic(path, self.to_json_string().as_bytes())?)
    }
}
