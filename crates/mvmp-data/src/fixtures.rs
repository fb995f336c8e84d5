//! Small trees in the CMU Panoptic and Human3.6M layouts, read in place by the same code as the real
//! datasets: for tests and for trying a set-up before the real data is at hand. The values are made up
//! (grey images, people as vertical lines of joints); the layout, names and formats are the real ones.
use std::path::{Path, PathBuf};

use crate::DataError;
use crate::h36m::{CAMERAS, RESOLUTIONS, camera_file, image_file, pose_file};
use crate::panoptic::VOXELPOSE_CAMERAS;

/// Make the folder `path` goes in.
fn make_parent(path: &Path) -> Result<(), DataError> {
    match path.parent() {
        Some(dir) => std::fs::create_dir_all(dir).map_err(|e| DataError::io(dir, e)),
        None => Ok(()),
    }
}

fn write(path: &Path, bytes: impl AsRef<[u8]>) -> Result<(), DataError> {
    make_parent(path)?;
    std::fs::write(path, bytes).map_err(|e| DataError::io(path, e))
}

fn grey(path: &Path, w: u32, h: u32, level: [u8; 3]) -> Result<(), DataError> {
    make_parent(path)?;
    image::RgbImage::from_pixel(w, h, image::Rgb(level))
        .save(path)
        .map_err(|e| DataError::file(path, e.to_string()))
}

/// A Panoptic sequence `root/name` of `frames` frames: a calibration of the five VoxelPose cameras
/// (160 x 120, turned one radian apart about the vertical, 5 m away), two bodies of 19 joints per frame
/// (body 1's joint 2 unseen in frame 1) and grey JPEGs. Returns the sequence's directory.
pub fn panoptic_sequence(root: &Path, name: &str, frames: usize) -> Result<PathBuf, DataError> {
    let d = root.join(name);
    let cams: Vec<serde_json::Value> = VOXELPOSE_CAMERAS
        .iter()
        .enumerate()
        .map(|(i, n)| {
            let (c, s) = ((i as f64).cos(), (i as f64).sin());
            serde_json::json!({
                "name": n, "type": "hd", "resolution": [160, 120], "panel": 0, "node": i,
                "K": [[120.0, 0.0, 80.0], [0.0, 120.0, 60.0], [0.0, 0.0, 1.0]],
                "distCoef": [0.0, 0.0, 0.0, 0.0, 0.0],
                "R": [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]],
                "t": [[0.0], [50.0], [500.0]],
            })
        })
        .collect();
    let calib = serde_json::json!({"calibDataSource": "fixture", "cameras": cams});
    write(
        &d.join(format!("calibration_{name}.json")),
        calib.to_string(),
    )?;
    for f in 0..frames {
        let idx = format!("{f:08}");
        let bodies: Vec<serde_json::Value> = (0..2)
            .map(|k| {
                let mut j = Vec::new();
                for i in 0..19 {
                    let conf = if f == 1 && k == 1 && i == 2 { 0.0 } else { 0.8 };
                    j.extend([60.0 * k as f64, -90.0 - 3.0 * i as f64, 20.0, conf]);
                }
                serde_json::json!({"id": k, "joints19": j})
            })
            .collect();
        let scene = serde_json::json!({"version": 0.7, "bodies": bodies});
        let pose = d.join(format!("hdPose3d_stage1_coco19/body3DScene_{idx}.json"));
        write(&pose, scene.to_string())?;
        for c in VOXELPOSE_CAMERAS {
            let img = d.join("hdImgs").join(c).join(format!("{c}_{idx}.jpg"));
            grey(&img, 160, 120, [90, 120, 150])?;
        }
    }
    Ok(d)
}

/// A Human3.6M tree under `root` from `files`, a folder holding a `camera-parameters.json` and a
/// `pose_float_one_record.cdf` (this crate's `tests/fixtures/h36m`): the camera file, that pose file for
/// each `(subject, action)` of `sequences`, and grey images of the first `views` cameras for the first
/// sequence's 5 rows, at the dataset's sizes.
pub fn h36m_tree(
    root: &Path,
    files: &Path,
    sequences: &[(&str, &str)],
    views: usize,
) -> Result<(), DataError> {
    let read = |name: &str| {
        let p = files.join(name);
        std::fs::read(&p).map_err(|e| DataError::io(&p, e))
    };
    write(&camera_file(root), read("camera-parameters.json")?)?;
    let poses = read("pose_float_one_record.cdf")?;
    for (s, a) in sequences {
        write(&pose_file(root, s, a), &poses)?;
    }
    let Some((s, a)) = sequences.first() else {
        return Ok(());
    };
    for (cam, (w, h)) in CAMERAS.iter().zip(RESOLUTIONS).take(views) {
        for row in 0..5 {
            grey(&image_file(root, s, a, cam, row), w, h, [100, 110, 120])?;
        }
    }
    Ok(())
}
