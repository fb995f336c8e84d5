//! Human3.6M read in place.
//!
//! The tree mvmp reads (README, "Human3.6M"): the dataset's own pose files and camera parameters, and
//! the frames of its videos extracted to JPEG:
//!
//! ```text
//! ROOT/camera-parameters.json                          the published camera parameters (below)
//! ROOT/S9/MyPoseFeatures/D3_Positions/<action>.cdf     32 joints per frame, world millimetres
//! ROOT/S9/Images/<action>.<camera>/000001.jpg          video frame 1 of S9/Videos/<action>.<camera>.mp4
//! ```
//!
//! Frame `n` (from 1, as `ffmpeg -i <video> %06d.jpg` numbers them) of a video is pose row `n - 1`: the
//! poses are sampled at the videos' 50 Hz. S11's "Directions" is left out, as the usual tool-chains do
//! (its video is damaged).
//!
//! Cameras as published (karfly/human36m-camera-parameters): the `camera-parameters.json` layout
//! generated from the official `metadata.xml` (intrinsics per camera id: `calibration_matrix`,
//! `distortion` = `[k1, k2, p1, p2, k3]`; extrinsics per subject and camera: `R`, `t` with
//! `x_cam = R X + t`, millimetres).
//! The world is z up in millimetres; it is read into metres.
//!
//! Tangential distortion: the coefficients come from the Human3.6M tool-chain, whose projection adds
//! `x (p1 y + p2 x) + p2 r^2` to x (and the mirror to y), where OpenCV adds `2 p1 x y + p2 (r^2 + 2 x^2)`.
//! mvmp's cameras use the OpenCV form everywhere, so these coefficients are read as OpenCV's. For points
//! in the capture volume the two forms differ by less than half a pixel (0.49 px at most, measured on all
//! four cameras of the seven protocol subjects by this crate's tests) on 1000-pixel images, far below the
//! 4-pixel heatmap stride; an exact tool-chain mode is not worth a second distortion model.
use std::path::{Path, PathBuf};

use nalgebra::{Matrix3, Vector3};
use serde::Deserialize;

use crate::DataError;
use crate::error::camera_error;
use mvmp_geom::{Camera, CameraPart, Rig};

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

/// The four cameras of `subject` (for example "S9") as a rig in metres. Every subject's cameras in the
/// file are checked, so that a bad value is refused wherever it is, not only in the subject read.
pub fn read_cameras(path: &Path, subject: &str) -> Result<Rig, DataError> {
    let text = std::fs::read_to_string(path).map_err(|e| DataError::io(path, e))?;
    let file: File = serde_json::from_str(&text).map_err(|e| {
        DataError::file(path, format!("not a Human3.6M camera-parameters file: {e}"))
    })?;
    if !file.extrinsics.contains_key(subject) {
        return Err(DataError::file(
            path,
            format!(
                "subject {subject:?} is not in `extrinsics` (it has {:?})",
                file.extrinsics.keys().collect::<Vec<_>>()
            ),
        ));
    }
    let mut found = None;
    for s in file.extrinsics.keys() {
        let rig = subject_rig(&file, path, s)?;
        if s == subject {
            found = Some(rig);
        }
    }
    found.ok_or_else(|| DataError::file(path, format!("subject {subject:?} has no cameras")))
}

/// The rig of one subject of the camera file.
fn subject_rig(file: &File, path: &Path, subject: &str) -> Result<Rig, DataError> {
    let ext = &file.extrinsics[subject];
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
        .map_err(|err| {
            let key = |part| h36m_key(part, subject, id);
            DataError::file(
                path,
                format!("camera {subject}/{id}: {}", camera_error(err, key)),
            )
        })?;
        cams.push(cam);
    }
    Ok(Rig::new(cams))
}

/// The camera file's key for a camera's values.
fn h36m_key(part: CameraPart, subject: &str, id: &str) -> String {
    match part {
        CameraPart::Intrinsics => format!("intrinsics.{id}.calibration_matrix"),
        CameraPart::Distortion => format!("intrinsics.{id}.distortion"),
        CameraPart::Rotation => format!("extrinsics.{subject}.{id}.R"),
        CameraPart::Translation => format!("extrinsics.{subject}.{id}.t"),
        CameraPart::Placement => format!("extrinsics.{subject}.{id}.R` and `t"),
        CameraPart::ImageSize => format!("the image size of camera {id}"),
    }
}

/// Sequences the protocol leaves out: (subject, action).
pub const EXCLUDED: [(&str, &str); 1] = [("S11", "Directions")];

/// The 17 evaluation joints taken from the 32 of the pose files (VideoPose3D's list; joint 13, the
/// thorax, where some tool-chains take 16, nearly the same point), in the order of
/// `mvmp_eval::joint_sets::H36M17`: pelvis, right hip, knee, ankle, left hip, knee, ankle, spine, thorax,
/// neck/nose, head, left shoulder, elbow, wrist, right shoulder, elbow, wrist.
pub const JOINTS_17_OF_32: [usize; 17] =
    [0, 1, 2, 3, 6, 7, 8, 12, 13, 14, 15, 17, 18, 19, 25, 26, 27];
/// The pelvis among the 17.
pub const ROOT_JOINT: usize = 0;

/// Every frame of a D3_Positions file as 32 joints in metres (the dataset's world is z up already).
pub fn read_poses(path: &Path) -> Result<Vec<[[f64; 3]; 32]>, DataError> {
    let (values, dims) = crate::cdf_pose::read_variable(path, "Pose")?;
    if values.len() % 96 != 0
        || dims
            .last()
            .is_some_and(|&d| d == 0 || (96 % d != 0 && d % 96 != 0))
    {
        return Err(DataError::file(
            path,
            format!(
                "variable `Pose` holds {} values in records of {dims:?}; expected 96 per frame (32 joints x 3)",
                values.len()
            ),
        ));
    }
    // Millimetres in a capture room: anything past a kilometre is a damaged file, not a pose.
    if let Some(i) = values
        .iter()
        .position(|v| v.is_nan() || v.abs() > MAX_POSE_MM)
    {
        return Err(DataError::file(
            path,
            format!(
                "variable `Pose`: value {:?} (frame {}, joint {}) is not a coordinate within {MAX_POSE_MM} mm",
                values[i],
                i / 96,
                i % 96 / 3
            ),
        ));
    }
    Ok(values
        .chunks_exact(96)
        .map(|f| std::array::from_fn(|j| std::array::from_fn(|a| f[j * 3 + a] / 1000.0)))
        .collect())
}

/// The largest pose coordinate a Human3.6M file may hold (mm).
pub const MAX_POSE_MM: f64 = 1e6;

/// The camera-parameters file of a tree.
pub fn camera_file(root: &Path) -> PathBuf {
    root.join("camera-parameters.json")
}

/// The pose file of a sequence.
pub fn pose_file(root: &Path, subject: &str, action: &str) -> PathBuf {
    root.join(subject)
        .join("MyPoseFeatures/D3_Positions")
        .join(format!("{action}.cdf"))
}

/// The image of pose row `row` seen by `camera`.
pub fn image_file(root: &Path, subject: &str, action: &str, camera: &str, row: usize) -> PathBuf {
    root.join(subject)
        .join("Images")
        .join(format!("{action}.{camera}"))
        .join(format!("{:06}.jpg", row + 1))
}

/// The actions of a subject: the pose files present, sorted, without [`EXCLUDED`] ones.
pub fn actions(root: &Path, subject: &str) -> Result<Vec<String>, DataError> {
    let dir = root.join(subject).join("MyPoseFeatures/D3_Positions");
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .map_err(|e| DataError::io(&dir, e))?
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_str()?.strip_suffix(".cdf")?.to_string();
            Some(name)
        })
        .filter(|a| !EXCLUDED.contains(&(subject, a.as_str())))
        .collect();
    names.sort();
    Ok(names)
}

/// Subjects of a named split: `train` (S1, S5, S6, S7, S8), `test` (S9, S11), or a comma-separated list.
pub fn split_subjects(name: &str) -> Vec<String> {
    match name {
        "train" => TRAIN_SUBJECTS.iter().map(|s| s.to_string()).collect(),
        "test" => TEST_SUBJECTS.iter().map(|s| s.to_string()).collect(),
        list => list.split(',').map(|s| s.trim().to_string()).collect(),
    }
}

/// One kept frame: its pose row and one image per selected camera.
#[derive(Debug, Clone, PartialEq)]
pub struct H36mFrame {
    pub row: usize,
    pub images: Vec<PathBuf>,
}

/// One subject's action read in place.
#[derive(Debug, Clone)]
pub struct H36mSequence {
    pub subject: String,
    pub action: String,
    /// The selected cameras of the subject in metres, in the order asked for.
    pub rig: Rig,
    pub frames: Vec<H36mFrame>,
    /// The 17 joints of each kept frame, metres.
    pub joints: Vec<[[f64; 3]; 17]>,
}

impl H36mSequence {
    /// Open `subject`/`action` of the tree at `root` with the named cameras (of [`CAMERAS`]), keeping every
    /// `stride`-th pose row from the first. Images are not opened.
    pub fn open(
        root: &Path,
        subject: &str,
        action: &str,
        cameras: &[&str],
        stride: usize,
    ) -> Result<Self, DataError> {
        let calib = camera_file(root);
        if !calib.exists() {
            return Err(DataError::file(
                &calib,
                "missing: put the published Human3.6M camera-parameters.json at the root of the tree",
            ));
        }
        let full = read_cameras(&calib, subject)?;
        let mut cams = Vec::with_capacity(cameras.len());
        for (i, c) in cameras.iter().enumerate() {
            if cameras[..i].contains(c) {
                return Err(DataError::file(
                    &calib,
                    format!("camera {c:?} is asked for twice: a rig's cameras are distinct"),
                ));
            }
            let cam = full.cameras.iter().find(|k| k.name == *c).ok_or_else(|| {
                DataError::file(
                    &calib,
                    format!("camera {c:?} is not a Human3.6M camera (they are {CAMERAS:?})"),
                )
            })?;
            cams.push(cam.clone());
        }
        let poses = read_poses(&pose_file(root, subject, action))?;
        let stride = stride.max(1);
        let rows: Vec<usize> = (0..poses.len()).step_by(stride).collect();
        Ok(H36mSequence {
            subject: subject.into(),
            action: action.into(),
            rig: Rig::new(cams),
            frames: rows
                .iter()
                .map(|&row| H36mFrame {
                    row,
                    images: cameras
                        .iter()
                        .map(|c| image_file(root, subject, action, c, row))
                        .collect(),
                })
                .collect(),
            joints: rows
                .iter()
                .map(|&r| std::array::from_fn(|k| poses[r][JOINTS_17_OF_32[k]]))
                .collect(),
        })
    }

    /// `S9/Directions 1`.
    pub fn name(&self) -> String {
        format!("{}/{}", self.subject, self.action)
    }
}

/// What `data check --format h36m` found.
#[derive(Debug, Clone, Default)]
pub struct H36mReport {
    /// (subject, action, cameras, frames with poses, frames with every camera's image)
    pub sequences: Vec<(String, String, usize, usize, usize)>,
    pub problems: Vec<crate::check::Problem>,
}

/// Validate a Human3.6M tree: the camera file, every subject directory (`S<n>`) present, every pose file,
/// and for every pose row an image per camera; each problem names its file. Missing images are
/// summarised per video directory (the first missing frame and the count), not listed one by one.
pub fn check_tree(root: &Path, cameras: &[&str]) -> H36mReport {
    check_tree_with(root, cameras, false)
}

/// [`check_tree`]; with `deep` every image is decoded whole (which finds files cut short after their
/// header).
pub fn check_tree_with(root: &Path, cameras: &[&str], deep: bool) -> H36mReport {
    let mut report = H36mReport::default();
    let subjects = match subject_dirs(root) {
        Ok(s) => s,
        Err(e) => {
            tree_problem(&mut report, root, e.to_string());
            return report;
        }
    };
    if subjects.is_empty() {
        tree_problem(
            &mut report,
            root,
            "no subject directory here (S1, S5, ..., each holding MyPoseFeatures/D3_Positions)"
                .into(),
        );
    }
    for subject in subjects {
        match actions(root, &subject) {
            Ok(acts) => {
                for action in acts {
                    check_sequence(&mut report, root, &subject, &action, cameras, deep);
                }
            }
            Err(e) => tree_problem(&mut report, &root.join(&subject), e.to_string()),
        }
    }
    report
}

fn tree_problem(r: &mut H36mReport, path: &Path, what: String) {
    r.problems.push(crate::check::Problem {
        path: path.into(),
        what,
    })
}

/// The subject directories (`S<n>`) under `root`, in subject order.
fn subject_dirs(root: &Path) -> std::io::Result<Vec<String>> {
    let mut subjects: Vec<String> = std::fs::read_dir(root)?
        .filter_map(|e| e.ok())
        .filter(|e| e.path().is_dir())
        .filter_map(|e| e.file_name().to_str().map(str::to_string))
        .filter(|n| {
            n.strip_prefix('S')
                .is_some_and(|d| d.parse::<u32>().is_ok())
        })
        .collect();
    subjects.sort_by_key(|s| s[1..].parse::<u32>().unwrap_or(0));
    Ok(subjects)
}

/// One action of one subject: its pose file and cameras, and an image per camera for every pose row
/// (missing ones summarised per camera: the first and the count).
fn check_sequence(
    report: &mut H36mReport,
    root: &Path,
    subject: &str,
    action: &str,
    cameras: &[&str],
    deep: bool,
) {
    let seq = match H36mSequence::open(root, subject, action, cameras, 1) {
        Ok(s) => s,
        Err(e) => {
            let fallback = pose_file(root, subject, action);
            return report
                .problems
                .push(crate::check::Problem::from_error(&fallback, &e));
        }
    };
    let mut complete = 0;
    // Per camera: the first frame whose image is missing, and how many are; the same for images that
    // are present but whose header is not a view of that camera (not an image, another size).
    let first = (usize::MAX, 0, String::new());
    let (mut missing, mut bad) = (
        vec![first.clone(); cameras.len()],
        vec![first; cameras.len()],
    );
    for f in &seq.frames {
        let mut all = true;
        for (c, (img, cam)) in f.images.iter().zip(&seq.rig.cameras).enumerate() {
            if !img.exists() {
                all = false;
                if missing[c].1 == 0 {
                    missing[c] = (f.row, 0, "missing image".into());
                }
                missing[c].1 += 1;
            } else if let Some(what) =
                crate::check::view_problem(img, (cam.width, cam.height), deep)
            {
                all = false;
                if bad[c].1 == 0 {
                    bad[c] = (f.row, 0, what);
                }
                bad[c].1 += 1;
            }
        }
        complete += all as usize;
    }
    let n = seq.frames.len();
    for (per_camera, verb) in [(missing, "are missing"), (bad, "have such images")] {
        for (c, (first, count, what)) in per_camera.into_iter().enumerate() {
            if count > 0 {
                let what = format!(
                    "{what} ({count} of the {n} frames of camera {} {verb}; this is the first)",
                    cameras[c]
                );
                let file = image_file(root, subject, action, cameras[c], first);
                tree_problem(report, &file, what);
            }
        }
    }
    report.sequences.push((
        subject.to_string(),
        action.to_string(),
        seq.rig.len(),
        seq.frames.len(),
        complete,
    ));
}
