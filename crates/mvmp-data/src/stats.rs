//! Dataset statistics in the terms of the paper's dataset table, and a contact sheet of one frame.
use std::path::Path;

use serde::Serialize;

use crate::DataError;
use crate::layout::{Annotation, DatasetLayout};

/// Bins of the occlusion histogram: [0, 0.1), [0.1, 0.2), ..., [0.9, 1.0].
pub const OCCLUSION_BINS: usize = 10;

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct MinMaxMean {
    pub min: f64,
    pub max: f64,
    pub mean: f64,
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct DatasetStats {
    pub scenes: usize,
    pub frames: usize,
    /// Largest number of views of a scene.
    pub views: usize,
    /// Views per scene.
    pub views_per_scene: MinMaxMean,
    /// Capture area per scene (m^2).
    pub area_m2: MinMaxMean,
    /// Largest area side lengths (m).
    pub area_max: [f64; 2],
    pub people_per_frame: MinMaxMean,
    /// Mean over (person, view) pairs where the person's silhouette is in the image of the fraction hidden
    /// by others.
    pub occlusion_mean: f64,
    /// Counts of (person, view) pairs per occlusion bin of width 0.1.
    pub occlusion_histogram: Vec<usize>,
    /// Mean over people (per frame) of the number of views in which at least one pixel of them is visible.
    pub visible_views_mean: f64,
}

fn mmm(v: &[f64]) -> MinMaxMean {
    if v.is_empty() {
        return MinMaxMean {
            min: 0.0,
            max: 0.0,
            mean: 0.0,
        };
    }
    MinMaxMean {
        min: v.iter().cloned().fold(f64::MAX, f64::min),
        max: v.iter().cloned().fold(f64::MIN, f64::max),
        mean: v.iter().sum::<f64>() / v.len() as f64,
    }
}

/// Compute the statistics of a dataset (reads every annotation).
pub fn dataset_stats(root: &Path) -> Result<DatasetStats, DataError> {
    let layout = DatasetLayout::open(root)?;
    let mut people = Vec::new();
    let mut hist = vec![0usize; OCCLUSION_BINS];
    let (mut occ_sum, mut occ_n) = (0.0, 0usize);
    let (mut vis_sum, mut vis_n) = (0.0, 0usize);
    let mut frames = 0;
    for f in layout.frames() {
        let scene = &layout.scenes[f.scene];
        let ann = Annotation::read(&f.dir.join("annotation.json"), scene.rig.len())?;
        frames += 1;
        people.push(ann.people.len() as f64);
        for p in &ann.people {
            let mut seen = 0;
            for v in &p.views {
                if let Some(o) = v.occlusion() {
                    occ_sum += o;
                    occ_n += 1;
                    hist[((o * OCCLUSION_BINS as f64) as usize).min(OCCLUSION_BINS - 1)] += 1;
                }
                if v.visible_pixels > 0 {
                    seen += 1;
                }
            }
            vis_sum += seen as f64;
            vis_n += 1;
        }
    }
    let views: Vec<f64> = layout.scenes.iter().map(|s| s.rig.len() as f64).collect();
    let areas: Vec<f64> = layout
        .scenes
        .iter()
        .map(|s| s.index.area[0] * s.index.area[1])
        .collect();
    let area_max = layout.scenes.iter().fold([0.0f64; 2], |a, s| {
        [a[0].max(s.index.area[0]), a[1].max(s.index.area[1])]
    });
    Ok(DatasetStats {
        scenes: layout.scenes.len(),
        frames,
        views: views.iter().cloned().fold(0.0, f64::max) as usize,
        views_per_scene: mmm(&views),
        area_m2: mmm(&areas),
        area_max,
        people_per_frame: mmm(&people),
        occlusion_mean: if occ_n > 0 {
            occ_sum / occ_n as f64
        } else {
            0.0
        },
        occlusion_histogram: hist,
        visible_views_mean: if vis_n > 0 {
            vis_sum / vis_n as f64
        } else {
            0.0
        },
    })
}

/// A contact sheet: every view of one frame, tiled in a grid, each at most `tile` pixels wide.
pub fn contact_sheet(
    root: &Path,
    scene: usize,
    frame: usize,
    tile: u32,
    out: &Path,
) -> Result<(), DataError> {
    let layout = DatasetLayout::open(root)?;
    let s = layout.scenes.get(scene).ok_or_else(|| {
        DataError::file(
            root,
            format!(
                "scene index {scene} out of range ({} scenes)",
                layout.scenes.len()
            ),
        )
    })?;
    let fname = s.index.frames.get(frame).ok_or_else(|| {
        DataError::file(
            &s.dir,
            format!(
                "frame index {frame} out of range ({} frames)",
                s.index.frames.len()
            ),
        )
    })?;
    let fdir = s.dir.join(fname);
    let ann = Annotation::read(&fdir.join("annotation.json"), s.rig.len())?;
    let n = ann.images.len();
    let cols = (n as f64).sqrt().ceil() as u32;
    let rows = (n as u32).div_ceil(cols);
    let cam = &s.rig.cameras[0];
    let scale = tile as f64 / cam.width as f64;
    let th = ((cam.height as f64 * scale).round() as u32).max(1);
    let mut sheet = image::RgbImage::from_pixel(cols * tile, rows * th, image::Rgb([20, 20, 20]));
    for (i, name) in ann.images.iter().enumerate() {
        let path = fdir.join(name);
        let img = image::open(&path)
            .map_err(|e| DataError::file(&path, format!("unreadable image: {e}")))?
            .to_rgb8();
        let small = image::imageops::resize(&img, tile, th, image::imageops::FilterType::Triangle);
        let (x, y) = ((i as u32 % cols) * tile, (i as u32 / cols) * th);
        image::imageops::overlay(&mut sheet, &small, x as i64, y as i64);
    }
    mvmp_io::write_atomic_with(out, |w| {
        let mut buf = std::io::Cursor::new(Vec::new());
        sheet
            .write_to(&mut buf, image::ImageFormat::Png)
            .map_err(std::io::Error::other)?;
        std::io::Write::write_all(w, buf.get_ref())
    })?;
    Ok(())
}
