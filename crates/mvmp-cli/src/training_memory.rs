//! `mvmp model summary --training`: an estimate of a training step's peak memory on flex, per stage.
//!
//! What autodiff keeps and what a backward works in grow with the pixels of the views (ViT, HRNet) and the
//! voxels of the grid (fusion, RootNet, decoder tokens); the weights, the body model and the people's
//! losses do not. The estimate runs one real training step's loss (`stage1_loss`, `stage2_loss` at the
//! true roots) and its backward on the config's own model at three reduced scales (input side and grid
//! side at a quarter or half, an eighth or quarter above 512 px; the voxel size kept), counts the bytes
//! the process allocates beyond what was live before the loss (activations, the backward's working
//! memory, the parameters' gradients), fits `c0 + c1 pixels + c2 voxels` through them and evaluates it at
//! the config's scale. To that it adds what does not scale, counted exactly: the weights, Adam's two
//! moments of the trainable ones, the body model and its layer, the batch.
use anyhow::{Context, Result};
use burn::data::dataloader::batcher::Batcher;
use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Device, Tensor};

use mvmp_data::loader::{FrameBatcher, FrameSample, PersonGt};
use mvmp_losses::LossWeights;
use mvmp_model::ModelConfig;
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS, NUM_JOINTS_WITH_LANDMARKS};
use mvmp_smplx::{BodyModel, SmplxLayer};
use mvmp_train::Stage;

use crate::GLOBAL;

/// One stage's estimate.
pub struct StageEstimate {
    pub stage: Stage,
    /// Adam's two moments of the weights the stage trains.
    pub adam: f64,
    /// What a step allocates beyond the live weights at the config's scale (the fit).
    pub step: f64,
    /// Each probe's input side, grid shape and measured bytes.
    pub probes: Vec<(u32, [usize; 3], f64)>,
}

pub struct Estimate {
    pub weights: f64,
    /// The body model on the host, its layer on the device and one batch of `people` people.
    pub fixed: f64,
    pub stages: Vec<StageEstimate>,
}

impl Estimate {
    /// Peak of one stage: the weights, the fixed part, the stage's Adam moments and its step.
    pub fn total(&self, s: &StageEstimate) -> f64 {
        self.weights + self.fixed + s.adam + s.step
    }
}

/// The config with its input side and the X and Y of its grid scaled (voxel size kept).
fn scaled(cfg: &ModelConfig, image: f64, grid: f64) -> ModelConfig {
    let mut c = cfg.clone();
    // A multiple of 28 (the ViT's patch, and HRNet's stride 4) times HRNet's pooling factor.
    let unit = 28.0 * cfg.hrnet_downsample.max(1) as f64;
    c.image_size = ((cfg.image_size as f64 * image / unit).round().max(2.0) * unit) as u32;
    for a in 0..2 {
        let n = ((cfg.grid.shape[a] as f64 * grid / 4.0).round() as usize).max(2) * 4;
        c.grid.size[a] = cfg.grid.size[a] * n as f64 / cfg.grid.shape[a] as f64;
        c.grid.shape[a] = n;
    }
    c
}

/// Parameter bytes: all, and those that train (running statistics and frozen tensors do not).
fn parameter_bytes<M: Module>(m: &M) -> (f64, f64) {
    struct Count(f64, f64);
    impl ModuleVisitor for Count {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            let n = p.lazy_shape().num_elements() as f64 * 4.0;
            self.0 += n;
            if p.is_require_grad() {
                self.1 += n;
            }
        }
    }
    let mut c = Count(0.0, 0.0);
    m.visit(&mut c);
    (c.0, c.1)
}

/// `people` people standing on a circle of 1 m round the grid's centre, seen by every view at the
/// image's centre: the losses' tensors depend on their number, not on where they stand.
fn people(cfg: &ModelConfig, views: usize, people: usize) -> Vec<PersonGt> {
    let half = cfg.image_size as f32 / 2.0;
    crate::probe::ring_roots(&cfg.grid, people)
        .chunks(3)
        .enumerate()
        .map(|(i, r)| {
            let pelvis = [r[0], r[1], r[2]];
            PersonGt {
                id: i as u32,
                pose: vec![0.0; NUM_JOINTS * 3],
                betas: [0.0; NUM_BETAS],
                expression: [0.0; NUM_EXPRESSION],
                pelvis,
                joints_3d: vec![pelvis; NUM_JOINTS_WITH_LANDMARKS],
                joints_2d: vec![vec![[half, half, 1.0]; NUM_JOINTS_WITH_LANDMARKS]; views],
                joint_valid: vec![1.0; NUM_JOINTS_WITH_LANDMARKS],
                smplx: true,
            }
        })
        .collect()
}

/// One frame of a ring rig with `n` people and mid-grey images.
fn sample(cfg: &ModelConfig, views: usize, n: usize) -> Result<FrameSample> {
    let (cameras, letterboxes) = crate::probe::ring_rig(cfg, views)?;
    let s = cfg.image_size as usize;
    Ok(FrameSample {
        scene: "probe".into(),
        frame: "0".into(),
        images: vec![0.1; views * 3 * s * s],
        size: s,
        cameras,
        letterboxes,
        people: people(cfg, views, n),
        cover: vec![true; NUM_JOINTS_WITH_LANDMARKS],
    })
}

/// Bytes a stage's loss and backward allocate beyond what was live before, for `cfg`'s model.
fn probe(cfg: &ModelConfig, shape: Shape, stage: Stage, body: &BodyModel) -> Result<f64> {
    let device = Device::flex().autodiff();
    let net = cfg
        .init(&device)
        .with_body(std::sync::Arc::new(body.clone()));
    // Built before the peak is reset, as `fixed_bytes` counts it.
    let _layer = net.body_layer(&device);
    let items = (0..shape.batch)
        .map(|_| sample(cfg, shape.views, shape.people))
        .collect::<Result<Vec<_>>>()?;
    let batch = FrameBatcher::with_vertices(body.clone()).batch(items, &device);
    // A model with a ViT heatmap head trains it, and the ViT, in both stages (its term is on with it).
    let w = LossWeights {
        vit_heatmap: if cfg.vit_heatmaps { 1.0 } else { 0.0 },
        ..Default::default()
    };
    let base = GLOBAL.reset_peak();
    let loss = match stage {
        Stage::Detection => mvmp_train::step::stage1_loss(&net, &batch, &w, &device),
        Stage::Whole => mvmp_train::step::stage2_loss(
            &net,
            &batch,
            &mvmp_train::step::Stage2::at_true_roots(&w),
            &device,
        ),
    };
    let grads = loss.total.backward();
    std::hint::black_box(&grads);
    Ok(GLOBAL.peak().saturating_sub(base) as f64)
}

/// Bytes live after building the body layer and one batch (what a step needs whatever the scale).
fn fixed_bytes(cfg: &ModelConfig, shape: Shape, body: &BodyModel) -> Result<f64> {
    let device = Device::flex().autodiff();
    let before = GLOBAL.reset_peak();
    let layer = SmplxLayer::new(body, &device);
    let items = (0..shape.batch)
        .map(|_| sample(cfg, shape.views, shape.people))
        .collect::<Result<Vec<_>>>()?;
    let batch = FrameBatcher::with_vertices(body.clone()).batch(items, &device);
    let live = GLOBAL.live().saturating_sub(before);
    std::hint::black_box((&layer, &batch));
    Ok(live as f64)
}

/// Solve `a x = b` for three unknowns (Cramer's rule); `None` when the probes do not separate pixels
/// from voxels.
fn solve3(a: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let det = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det(a);
    let scale = a.iter().flatten().map(|x| x.abs()).fold(0.0, f64::max);
    if d.abs() < 1e-9 * scale.powi(3) {
        return None;
    }
    Some(std::array::from_fn(|j| {
        let mut m = a;
        for row in m.iter_mut().zip(b) {
            row.0[j] = row.1;
        }
        det(m) / d
    }))
}

/// The step's shape: samples, views per sample, people per sample.
#[derive(Debug, Clone, Copy)]
pub struct Shape {
    pub batch: usize,
    pub views: usize,
    pub people: usize,
}

/// Pixels and voxels of a step of `cfg` at `shape`.
fn extent(cfg: &ModelConfig, shape: Shape) -> (f64, f64) {
    let b = shape.batch as f64;
    (
        b * shape.views as f64 * (cfg.image_size as f64).powi(2),
        b * cfg.grid.num_voxels() as f64,
    )
}

/// While alive, the convolution product's cap and the RootNet's slabs are scaled by how much smaller a
/// probe is than the config (its pixels and its voxels), so that every convolution of the probe takes
/// the path it takes at full scale and a slab's transient shrinks with the volume. Restored on drop.
struct ScaledThresholds {
    cap: usize,
    slab: usize,
}

impl ScaledThresholds {
    fn new(pixels: f64, voxels: f64) -> Self {
        let scale = |n: usize, r: f64| ((n as f64 * r).round() as usize).max(1);
        let cap = mvmp_kernels::conv::set_product_cap(scale(
            mvmp_kernels::conv::PRODUCT_MAX_ELEMENTS,
            pixels,
        ));
        let slab = mvmp_fusion::v2v::set_slab_voxels(scale(mvmp_fusion::v2v::SLAB_VOXELS, voxels));
        ScaledThresholds { cap, slab }
    }
}

impl Drop for ScaledThresholds {
    fn drop(&mut self) {
        mvmp_kernels::conv::set_product_cap(self.cap);
        mvmp_fusion::v2v::set_slab_voxels(self.slab);
    }
}

/// One stage's fit through three probes, evaluated at `cfg`'s scale.
fn stage_estimate(
    cfg: &ModelConfig,
    shape: Shape,
    stage: Stage,
    body: &BodyModel,
) -> Result<StageEstimate> {
    let (lo, hi) = if cfg.image_size > 512 {
        (0.125, 0.25)
    } else {
        (0.25, 0.5)
    };
    let (full_pixels, full_voxels) = extent(cfg, shape);
    let mut probes = Vec::new();
    let mut a = [[0.0; 3]; 3];
    let mut b = [0.0; 3];
    for (i, (fi, fg)) in [(lo, lo), (hi, hi), (lo, hi)].into_iter().enumerate() {
        let c = scaled(cfg, fi, fg);
        c.validate().context("a probe's scaled config")?;
        let (pixels, voxels) = extent(&c, shape);
        let bytes = {
            let _scaled = ScaledThresholds::new(pixels / full_pixels, voxels / full_voxels);
            probe(&c, shape, stage, body)?
        };
        a[i] = [1.0, pixels, voxels];
        b[i] = bytes;
        probes.push((c.image_size, c.grid.shape, bytes));
    }
    let [c0, cp, cv] = solve3(a, b).context("the probes could not separate pixels from voxels")?;
    Ok(StageEstimate {
        stage,
        adam: 2.0 * stage_trainable(cfg, stage),
        step: c0 + cp * full_pixels + cv * full_voxels,
        probes,
    })
}

/// The estimate for `cfg` at `shape`, both stages. The body model is the stand-in, whose arrays have
/// the shapes of SMPL-X's.
pub fn estimate(cfg: &ModelConfig, shape: Shape) -> Result<Estimate> {
    let body = mvmp_smplx::standin_model(0);
    let (weights, _) = parameter_bytes(&cfg.init(&Device::flex().autodiff()));
    let fixed = fixed_bytes(cfg, shape, &body)? + body_bytes(&body);
    let stages = Stage::ALL
        .into_iter()
        .map(|s| stage_estimate(cfg, shape, s, &body))
        .collect::<Result<_>>()?;
    Ok(Estimate {
        weights,
        fixed,
        stages,
    })
}

/// Bytes of the weights `stage` trains (Adam keeps two moments of each): stage 1 trains detection (HRNet,
/// the facing head, the RootNet) and, with a ViT heatmap head, the ViT and the head; stage 2 everything.
fn stage_trainable(cfg: &ModelConfig, stage: Stage) -> f64 {
    let net = cfg.init(&Device::flex().autodiff());
    match stage {
        Stage::Detection => {
            let vit = match &net.vit_joints {
                Some(head) => {
                    parameter_bytes(&net.vit).1
                        + parameter_bytes(&net.reduce).1
                        + parameter_bytes(head).1
                }
                None => 0.0,
            };
            parameter_bytes(&net.hrnet).1
                + parameter_bytes(&net.rootnet).1
                + net.facing.as_ref().map_or(0.0, |f| parameter_bytes(f).1)
                + vit
        }
        Stage::Whole => parameter_bytes(&net).1,
    }
}

/// Bytes of the body model's arrays on the host (float64).
fn body_bytes(body: &BodyModel) -> f64 {
    let before = GLOBAL.reset_peak();
    let copy = body.clone();
    let live = GLOBAL.live().saturating_sub(before);
    std::hint::black_box(&copy);
    live as f64
}

#[cfg(test)]
mod tests {
    use super::{scaled, solve3};
    use mvmp_model::ModelConfig;

    #[test]
    fn three_probes_give_back_the_line_through_them() {
        // bytes = 5 + 2 pixels + 3 voxels, at three (pixels, voxels) points.
        let pts = [(1.0, 1.0), (4.0, 4.0), (1.0, 4.0)];
        let a = pts.map(|(p, v)| [1.0, p, v]);
        let b = pts.map(|(p, v)| 5.0 + 2.0 * p + 3.0 * v);
        let x = solve3(a, b).unwrap();
        for (got, want) in x.iter().zip([5.0, 2.0, 3.0]) {
            assert!((got - want).abs() < 1e-9, "{x:?}");
        }
        // Probes that scale pixels and voxels together cannot tell them apart.
        let a = [[1.0, 1.0, 1.0], [1.0, 2.0, 2.0], [1.0, 4.0, 4.0]];
        assert!(solve3(a, [1.0, 2.0, 3.0]).is_none());
    }

    #[test]
    fn a_probe_keeps_the_voxel_size_and_a_valid_input_side() {
        let cfg =
            ModelConfig::read(std::path::Path::new("../../configs/model/paper.toml")).unwrap();
        for f in [0.125, 0.25] {
            let c = scaled(&cfg, f, f);
            c.validate().unwrap();
            assert_eq!(c.image_size % 28, 0);
            for a in 0..3 {
                let vs = |g: &mvmp_geom::VoxelGrid| g.size[a] / g.shape[a] as f64;
                assert!((vs(&c.grid) - vs(&cfg.grid)).abs() < 1e-12);
            }
            assert_eq!(c.grid.shape[2], cfg.grid.shape[2]);
        }
    }
}
