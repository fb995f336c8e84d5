//! CMU Panoptic Studio files (as the panoptic-toolbox publishes them), converted once, at load time, into
//! mvmp's conventions: Panoptic's world is in centimetres with y pointing down; mvmp's is in metres with z
//! up. A Panoptic point `X_p = (x, y, z)` maps to `X = M X_p / 100 = (x, z, -y) / 100` with
//! `M = [[1, 0, 0], [0, 0, 1], [0, -1, 0]]` (a proper rotation), so a camera `x_cam = R X_p + t` (cm)
//! becomes `x_cam = (R M^T) X + t / 100` (m). Skew and distortion are kept.
use std::path::Path;

use nalgebra::{Matrix3, Vector3};
use serde::Deserialize;

use crate::DataError;
use crate::error::camera_error;
use mvmp_geom::{Camera, CameraPart, Rig};

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
    for (i, &name) in names.iter().enumerate() {
        if names[..i].contains(&name) {
            return Err(DataError::file(
                path,
                format!("camera {name:?} is asked for twice: a rig's cameras are distinct"),
            ));
        }
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
        .map_err(|e| DataError::file(path, camera_error(e, |p| panoptic_key(p).into())))?;
        cams.push(cam);
    }
    Ok(Rig::new(cams))
}

/// The calibration file's key for a camera's values.
fn panoptic_key(part: CameraPart) -> &'static str {
    match part {
        CameraPart::Intrinsics => "K",
        CameraPart::Rotation => "R",
        CameraPart::Translation => "t",
        CameraPart::Placement => "R` and `t",
        CameraPart::Distortion => "distCoef",
        CameraPart::ImageSize => "resolution",
    }
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

/// The most people one body file may hold (a capture dome holds a few dozen).
pub const MAX_BODIES: usize = 10_000;
/// The farthest a joint coordinate may lie from the dome's origin, in cm (1 km).
pub const MAX_JOINT_CM: f64 = 1.0e5;

/// Read the people of a `body3DScene_<frame>.json` (joints19: 19 x (x, y, z, confidence), cm).
pub fn read_bodies(path: &Path) -> Result<Vec<PanopticBody>, DataError> {
    let text = std::fs::read_to_string(path).map_err(|e| DataError::io(path, e))?;
    let file: BodyFile = serde_json::from_str(&text)
        .map_err(|e| DataError::file(path, format!("not a Panoptic body file: {e}")))?;
    if file.bodies.len() > MAX_BODIES {
        return Err(DataError::file(
            path,
            format!(
                "key `bodies` holds {} people; at most {MAX_BODIES} per frame",
                file.bodies.len()
            ),
        ));
    }
    for (i, b) in file.bodies.iter().enumerate() {
        if let Some(j) = file.bodies[..i].iter().position(|o| o.id == b.id) {
            return Err(DataError::file(
                path,
                format!("bodies[{i}].id {} repeats bodies[{j}]'s", b.id),
            ));
        }
    }
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
            if let Some(k) = b
                .joints19
                .iter()
                .enumerate()
                .position(|(k, v)| !v.is_finite() || (k % 4 != 3 && v.abs() > MAX_JOINT_CM))
            {
                return Err(DataError::file(
                    path,
                    format!(
                        "bodies[{i}].joints19[{k}] = {:?}: {}",
                        b.joints19[k],
                        if b.joints19[k].is_finite() {
                            format!("a coordinate beyond {MAX_JOINT_CM} cm")
                        } else {
                            "not a number".into()
                        }
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

/// A joint counts as annotated when its confidence exceeds this (VoxelPose's rule).
pub const VALID_CONFIDENCE: f64 = 0.1;
/// The root joint of joints19 (BodyCenter, mid-hip).
pub const ROOT_JOINT: usize = 2;
/// The joints kept for evaluation (the first 15 of joints19, as VoxelPose).
pub const EVAL_JOINTS: usize = 15;

impl PanopticBody {
    /// Whether joint `i` is annotated (confidence above [`VALID_CONFIDENCE`]).
    pub fn valid(&self, i: usize) -> bool {
        self.confidence
            .get(i)
            .is_some_and(|&c| c > VALID_CONFIDENCE)
    }
}

/// A named split: sequences and the frame stride (every `stride`-th pose file of a sequence).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PanopticSplit {
    pub name: &'static str,
    pub sequences: &'static [&'static str],
    pub stride: usize,
}

/// VoxelPose's training sequences, every 3rd frame.
pub const VOXELPOSE_TRAIN: PanopticSplit = PanopticSplit {
    name: "voxelpose-train",
    sequences: &[
        "160422_ultimatum1",
        "160224_haggling1",
        "160226_haggling1",
        "161202_haggling1",
        "160906_ian1",
        "160906_ian2",
        "160906_ian3",
        "160906_band1",
        "160906_band2",
        "160906_band3",
    ],
    stride: 3,
};

/// VoxelPose's validation (test) sequences, every 12th frame.
pub const VOXELPOSE_VALIDATION: PanopticSplit = PanopticSplit {
    name: "voxelpose-val",
    sequences: &[
        "160906_pizza1",
        "160422_haggling1",
        "160906_ian5",
        "160906_band4",
    ],
    stride: 12,
};

/// A split by name: `voxelpose-train` or `voxelpose-val`.
pub fn split_by_name(name: &str) -> Option<PanopticSplit> {
    [VOXELPOSE_TRAIN, VOXELPOSE_VALIDATION]
        .into_iter()
        .find(|s| s.name == name)
}

/// One frame of a sequence: its pose file and one image per selected camera.
#[derive(Debug, Clone, PartialEq)]
pub struct PanopticFrame {
    /// The 8-digit HD frame index as in the file names.
    pub index: String,
    pub bodies: std::path::PathBuf,
    pub images: Vec<std::path::PathBuf>,
}

/// A Panoptic sequence read in place.
#[derive(Debug, Clone)]
pub struct PanopticSequence {
    pub name: String,
    pub dir: std::path::PathBuf,
    /// The selected cameras in mvmp's world, in the order asked for.
    pub rig: Rig,
    pub frames: Vec<PanopticFrame>,
}

impl PanopticSequence {
    /// Open `dir` (named `<seq>`, holding `calibration_<seq>.json`, `hdPose3d_stage1_coco19/` and `hdImgs/`)
    /// with the named HD cameras, keeping every `stride`-th pose file in frame order (VoxelPose's walk).
    /// Images are not opened; their paths follow `hdImgs/00_NN/00_NN_<frame>.jpg`.
    pub fn open(dir: &Path, cameras: &[&str], stride: usize) -> Result<Self, DataError> {
        let name = dir
            .file_name()
            .and_then(|n| n.to_str())
            .ok_or_else(|| DataError::file(dir, "not a sequence directory"))?
            .to_string();
        let calib = dir.join(format!("calibration_{name}.json"));
        if !calib.exists() {
            return Err(DataError::file(
                &calib,
                "missing: a Panoptic sequence holds calibration_<sequence>.json",
            ));
        }
        let rig = read_calibration(&calib, cameras)?;
        let poses = dir.join("hdPose3d_stage1_coco19");
        let mut files: Vec<(String, std::path::PathBuf)> = std::fs::read_dir(&poses)
            .map_err(|e| DataError::io(&poses, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter_map(|p| {
                let f = p.file_name()?.to_str()?;
                let idx = f.strip_prefix("body3DScene_")?.strip_suffix(".json")?;
                Some((idx.to_string(), p.clone()))
            })
            .collect();
        files.sort();
        let stride = stride.max(1);
        let frames = files
            .into_iter()
            .enumerate()
            .filter(|(i, _)| i % stride == 0)
            .map(|(_, (index, bodies))| PanopticFrame {
                images: cameras
                    .iter()
                    .map(|c| dir.join("hdImgs").join(c).join(format!("{c}_{index}.jpg")))
                    .collect(),
                index,
                bodies,
            })
            .collect();
        Ok(PanopticSequence {
            name,
            dir: dir.into(),
            rig,
            frames,
        })
    }

    /// The people of a frame whose root joint is annotated (VoxelPose drops the others).
    pub fn people(&self, frame: &PanopticFrame) -> Result<Vec<PanopticBody>, DataError> {
        Ok(read_bodies(&frame.bodies)?
            .into_iter()
            .filter(|b| b.valid(ROOT_JOINT))
            .collect())
    }
}

/// What `data check --format panoptic` found.
#[derive(Debug, Clone, Default)]
pub struct PanopticReport {
    /// (sequence, cameras, frames, people over the frames)
    pub sequences: Vec<(String, usize, usize, usize)>,
    pub problems: Vec<crate::check::Problem>,
}

/// Validate a Panoptic tree: `root` is one sequence directory or a directory of them. Every pose file is
/// parsed and every image of the selected cameras must be an image of its camera's size (its header is
/// read); each problem names its file.
pub fn check_tree(root: &Path, cameras: &[&str]) -> PanopticReport {
    check_tree_with(root, cameras, false)
}

/// [`check_tree`]; with `deep` every image is decoded whole (which finds files cut short after their
/// header).
pub fn check_tree_with(root: &Path, cameras: &[&str], deep: bool) -> PanopticReport {
    let mut report = PanopticReport::default();
    let is_seq = |d: &Path| {
        d.file_name()
            .and_then(|n| n.to_str())
            .is_some_and(|n| d.join(format!("calibration_{n}.json")).exists())
    };
    let mut dirs: Vec<std::path::PathBuf> = if is_seq(root) {
        vec![root.into()]
    } else {
        match std::fs::read_dir(root) {
            Ok(rd) => rd
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.is_dir() && is_seq(p))
                .collect(),
            Err(e) => {
                report.problems.push(crate::check::Problem {
                    path: root.into(),
                    what: e.to_string(),
                });
                return report;
            }
        }
    };
    dirs.sort();
    if dirs.is_empty() {
        report.problems.push(crate::check::Problem {
            path: root.into(),
            what: "no Panoptic sequence here (a directory <seq> holding calibration_<seq>.json)"
                .into(),
        });
    }
    for d in dirs {
        let seq = match PanopticSequence::open(&d, cameras, 1) {
            Ok(s) => s,
            Err(e) => {
                report
                    .problems
                    .push(crate::check::Problem::from_error(&d, &e));
                continue;
            }
        };
        let mut people = 0;
        for f in &seq.frames {
            match seq.people(f) {
                Ok(p) => people += p.len(),
                Err(e) => report
                    .problems
                    .push(crate::check::Problem::from_error(&f.bodies, &e)),
            }
            for (img, cam) in f.images.iter().zip(&seq.rig.cameras) {
                if let Some(what) = crate::check::view_problem(img, (cam.width, cam.height), deep) {
                    report.problems.push(crate::check::Problem {
                        path: img.clone(),
                        what,
                    });
                }
            }
        }
        if seq.frames.is_empty() {
            report.problems.push(crate::check::Problem {
                path: d.join("hdPose3d_stage1_coco19"),
                what: "no body3DScene_<frame>.json files".into(),
            });
        }
        report
            .sequences
            .push((seq.name.clone(), seq.rig.len(), seq.frames.len(), people));
    }
    report
}
