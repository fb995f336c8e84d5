//! The synthetic rig and roots the model's summaries and benchmarks probe a config with.
use anyhow::Result;
use nalgebra::Vector3;

use mvmp_data::synth::look_at;
use mvmp_geom::{Camera, Letterbox};
use mvmp_model::ModelConfig;

/// `views` 1920 x 1080 cameras on a ring around the config's grid, looking at its centre, letterboxed to
/// the config's input size.
pub fn ring_rig(cfg: &ModelConfig, views: usize) -> Result<(Vec<Camera>, Vec<Letterbox>)> {
    let g = &cfg.grid;
    let cams: Vec<Camera> = (0..views)
        .map(|i| {
            let a = i as f64 / views as f64 * std::f64::consts::TAU;
            let r = 0.75 * g.size[0].max(g.size[1]);
            look_at(
                format!("cam{i}"),
                Vector3::new(g.center[0] + r * a.cos(), g.center[1] + r * a.sin(), 3.0),
                Vector3::new(g.center[0], g.center[1], 1.0),
                60.0,
                0.0,
                [1920, 1080],
                [0.0, 0.0],
            )
        })
        .collect::<Result<_, _>>()?;
    let lbs = cams
        .iter()
        .map(|_| Letterbox::new(1920, 1080, cfg.image_size))
        .collect::<Result<_, _>>()?;
    Ok((cams, lbs))
}

/// `k` roots on a circle of 1 m round the grid's centre, at pelvis height, `[k * 3]`.
pub fn ring_roots(g: &mvmp_geom::VoxelGrid, k: usize) -> Vec<f32> {
    (0..k)
        .flat_map(|i| {
            let a = i as f64 * 2.4;
            [
                (g.center[0] + a.cos()) as f32,
                (g.center[1] + a.sin()) as f32,
                0.9,
            ]
        })
        .collect()
}
