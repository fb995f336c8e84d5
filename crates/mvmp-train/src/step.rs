//! One training step's losses: the ground truth of a batch turned into targets, the queries chosen
//! (detected roots matched to people, ground-truth roots, or both), and the weighted loss terms.
use burn::tensor::{Device, Int, Tensor, TensorData};

use mvmp_data::loader::FrameBatch;
use mvmp_fusion::roots::{gaussian_target, root_voxel_and_offset};
use mvmp_fusion::{FusionMode, Root, SamplingGrid, fuse_views};
use mvmp_geom::rotation::axis_angle_to_matrix;
use mvmp_geom::{Camera, Letterbox};
use mvmp_losses::{
    LossTerms, LossWeights, MeshFrame, body_pose_l2_loss, density_axis, density_loss,
    detection_loss_weighted, detection_positive_loss, facing_bin_loss, facing_loss, heatmap_loss,
    heatmap_target, mesh_2d_loss_views, mesh_3d_loss_weighted, orientation_loss, parameter_loss,
    to_body_frame, translation_loss,
};
use mvmp_model::facing::{bin_labels, facing_readout, relative_heading};
use mvmp_model::{Detection, ModelConfig, MvmpHmr, MvmpOutput, RigGrids, Upstream, roots_tensor};
use mvmp_smplx::names::{NUM_JOINTS, NUM_REGRESSED, REGRESSED_TO_JOINT};

use crate::config::QueryMode;

/// The weighted loss terms of a step and their sum.
#[derive(Debug, Clone)]
pub struct StepLoss {
    pub total: Tensor<1>,
    /// (name, weighted value) of every active term.
    pub terms: Vec<(&'static str, Tensor<1>)>,
    /// People decoded and people supervised (stage 2), for logs.
    pub queries: usize,
    /// Detection diagnostics (not losses): the highest root likelihood in the volume and the mean
    /// likelihood at the ground-truth root voxels; detection works once both pass the root threshold.
    pub root_peak: f32,
    pub root_at_gt: f32,
    /// The highest likelihood away from every person (where the Gaussian target is below 0.01): a
    /// detector that separates people from empty space keeps it below the threshold.
    pub root_background: f32,
}

/// The ground truth of a batch on the host, as the targets need it.
#[derive(Debug, Clone)]
pub struct HostGt {
    pub counts: Vec<usize>,
    /// Padded people per item.
    pub padded: usize,
    /// `[b][p][j]` world joints.
    pub joints: Vec<Vec<Vec<[f64; 3]>>>,
    /// `[b][v][p][j]` network-pixel joints with visibility.
    pub joints_2d: Vec<Vec<Vec<Vec<[f32; 3]>>>>,
    /// `[b][j]`: the joints each item's dataset annotates.
    pub cover: Vec<Vec<bool>>,
}

impl HostGt {
    /// The batch's ground truth as its samples held it, each person's joints padded to the batch's
    /// `J` with zeros (as the tensors are).
    pub fn new(batch: &FrameBatch) -> Self {
        let [_, p, j, _] = batch.joints_3d.dims();
        let v = batch.joints_2d.dims()[1];
        let padded = |x: &[[f32; 3]]| -> Vec<[f32; 3]> {
            let mut o = x.to_vec();
            o.resize(j, [0.0; 3]);
            o
        };
        let joints = (batch.people.iter())
            .map(|people| {
                (people.iter())
                    .map(|q| {
                        padded(&q.joints_3d)
                            .iter()
                            .map(|x| x.map(f64::from))
                            .collect()
                    })
                    .collect()
            })
            .collect();
        let joints_2d = (batch.people.iter())
            .map(|people| {
                (0..v)
                    .map(|vi| {
                        (people.iter())
                            .map(|q| padded(q.joints_2d.get(vi).map_or(&[], |x| x.as_slice())))
                            .collect()
                    })
                    .collect()
            })
            .collect();
        let cover = (batch.covers.iter())
            .map(|c| {
                let mut c = c.clone();
                c.resize(j, false);
                c
            })
            .collect();
        HostGt {
            cover,
            counts: batch.counts.clone(),
            padded: p,
            joints,
            joints_2d,
        }
    }

    /// Every person's primary joint (the root the detection branch finds), per item.
    pub fn roots(&self, primary: usize) -> Vec<Vec<[f64; 3]>> {
        self.joints
            .iter()
            .map(|people| people.iter().map(|j| j[primary]).collect())
            .collect()
    }
}

/// Sampling grids of each batch item's selected views.
pub fn batch_grids(cfg: &ModelConfig, batch: &FrameBatch, device: &Device) -> Vec<RigGrids> {
    RigGrids::for_batch(cfg, &batch.cameras, &batch.letterboxes, device)
}

/// The detection loss of a batch (Gaussian root volume + sub-voxel offsets of the ground-truth roots).
pub fn detection_term(
    det: &Detection,
    gt: &HostGt,
    cfg: &ModelConfig,
    weights: &LossWeights,
    device: &Device,
) -> (Tensor<1>, [f32; 3]) {
    let roots = gt.roots(cfg.primary_joint.joint());
    let target = gaussian_target(&cfg.grid, &roots, weights.detection_sigma, device);
    let b = roots.len();
    let r = roots.iter().map(Vec::len).max().unwrap_or(0).max(1);
    let mut vox = vec![0i64; b * r];
    let mut off = vec![0f32; b * r * 3];
    let mut mask = vec![0f32; b * r];
    for (bi, people) in roots.iter().enumerate() {
        for (pi, root) in people.iter().enumerate() {
            if let Some((v, o)) = root_voxel_and_offset(&cfg.grid, *root) {
                let k = bi * r + pi;
                vox[k] = cfg.grid.flat_index(v) as i64;
                for a in 0..3 {
                    off[k * 3 + a] = o[a] as f32;
                }
                mask[k] = 1.0;
            }
        }
    }
    let vox = Tensor::<2, Int>::from_data(TensorData::new(vox, [b, r]), device);
    let maskt = Tensor::<2>::from_data(TensorData::new(mask.clone(), [b, r]), device);
    let lik = det
        .likelihood
        .clone()
        .detach()
        .reshape([b, cfg.grid.num_voxels()]);
    let peak: f32 = mvmp_losses::mean_all(mvmp_losses::max_rows(lik.clone())).into_scalar();
    let at: f32 = mvmp_losses::sum_all(lik.clone().gather(1, vox.clone()) * maskt.clone())
        .into_scalar::<f32>()
        / mask.iter().sum::<f32>().max(1.0);
    let empty = target
        .clone()
        .reshape([b, cfg.grid.num_voxels()])
        .lower_elem(0.01);
    let background: f32 = lik
        .mask_fill(empty.bool_not(), f32::NEG_INFINITY)
        .max()
        .into_scalar();
    let positive = (weights.detection_positive > 0.0).then(|| {
        detection_positive_loss(det.likelihood.clone(), target.clone()) * weights.detection_positive
    });
    let loss = detection_loss_weighted(
        det.likelihood.clone(),
        target,
        det.offset.clone(),
        vox,
        Tensor::from_data(TensorData::new(off, [b, r, 3]), device),
        maskt,
        weights.detection_offset,
    );
    let loss = match positive {
        Some(p) => loss + p,
        None => loss,
    };
    (loss, [peak, at, background])
}

/// The 2D heatmap loss of the pose network: targets drawn at the visible ground-truth joints.
pub fn heatmap_term(
    det: &Detection,
    gt: &HostGt,
    cfg: &ModelConfig,
    sigma: f32,
    positive: f32,
    device: &Device,
) -> Tensor<1> {
    let stride = cfg.heatmap_stride() as f32;
    joint_heatmap_term(
        det.heatmaps.clone(),
        stride,
        gt,
        cfg,
        sigma,
        positive,
        device,
    )
}

/// The heatmap loss's targets `dims` (`[B, V, J, h, w]`, `stride` network pixels per map pixel):
/// per view and heatmap joint, the largest of the Gaussians (width `sigma`, map pixels) at the people's
/// visible ground-truth joints.
pub fn joint_heatmap_targets(
    dims: [usize; 5],
    stride: f32,
    gt: &HostGt,
    cfg: &ModelConfig,
    sigma: f32,
    device: &Device,
) -> Tensor<5> {
    let [b, v, j, h, w] = dims;
    let mut target = Vec::with_capacity(b * v * j * h * w);
    for bi in 0..b {
        for vi in 0..v {
            let mut map = vec![0f32; j * h * w];
            for person in &gt.joints_2d[bi][vi] {
                let pts: Vec<Option<[f32; 2]>> = cfg
                    .heatmap_joints
                    .iter()
                    .map(|&ji| {
                        let [u, vv, vis] = person[ji];
                        (vis > 0.5).then_some([u, vv])
                    })
                    .collect();
                let one = heatmap_target(&pts, [h, w], stride, sigma);
                for (m, x) in map.iter_mut().zip(one) {
                    *m = m.max(x);
                }
            }
            target.extend(map);
        }
    }
    Tensor::from_data(TensorData::new(target, dims), device)
}

/// The joint heatmap volume `[B, J, X, Y, Z]` a perfect HRNet would give: the heatmap loss's targets
/// (Gaussians of width `sigma`, map pixels) fused over the views as the model fuses its own maps.
pub fn truth_joint_volume(
    cfg: &ModelConfig,
    batch: &FrameBatch,
    grids: &[RigGrids],
    sigma: f32,
    device: &Device,
) -> Tensor<5> {
    let [b, v, _, _, _] = batch.images.dims();
    let [h, w] = grids[0].heatmaps.map_hw;
    let dims = [b, v, cfg.heatmap_joints.len(), h, w];
    let gt = HostGt::new(batch);
    let maps = joint_heatmap_targets(dims, cfg.heatmap_stride() as f32, &gt, cfg, sigma, device);
    let hgrids: Vec<SamplingGrid> = grids.iter().map(|g| g.heatmaps.clone()).collect();
    fuse_views(maps, &hgrids, FusionMode::Mean)
}

/// The heatmap loss of maps `[B, V, J, h, w]` of the heatmap joints, `stride` network pixels per map
/// pixel, against Gaussians of width `sigma` (map pixels) at the visible ground-truth joints, plus
/// `positive` times the error weighted by those Gaussians ([`detection_positive_loss`]).
pub fn joint_heatmap_term(
    maps: Tensor<5>,
    stride: f32,
    gt: &HostGt,
    cfg: &ModelConfig,
    sigma: f32,
    positive: f32,
    device: &Device,
) -> Tensor<1> {
    let target = joint_heatmap_targets(maps.dims(), stride, gt, cfg, sigma, device);
    let [b, v, j, _, _] = maps.dims();
    // A heatmap is supervised (towards zero where nobody shows the joint) only where the item's dataset
    // annotates that joint.
    let mut weight = Vec::with_capacity(b * v * j);
    for bi in 0..b {
        for _ in 0..v {
            weight.extend(cfg.heatmap_joints.iter().map(|&ji| {
                if gt.cover[bi].get(ji).copied().unwrap_or(false) {
                    1f32
                } else {
                    0.0
                }
            }));
        }
    }
    let weight = Tensor::from_data(TensorData::new(weight, [b, v, j]), device);
    let mse = heatmap_loss(maps.clone(), target.clone(), weight.clone());
    if positive <= 0.0 {
        return mse;
    }
    // Unsupervised joints drop out with their targets.
    let supervised = target * weight.reshape([b, v, j, 1, 1]);
    mse + detection_positive_loss(maps, supervised) * positive
}

/// SMPL-X joints of the torso, where the facing head is trained: pelvis, hips, spine1-3, neck, shoulders.
const TORSO: [usize; 9] = [0, 1, 2, 3, 6, 9, 12, 16, 17];

/// A person's heading from the joints `[j][3]` (z up): the horizontal direction ahead of them, at right
/// angles to the line from their right hip and shoulder to their left ones. `None` when those joints are
/// not annotated (`cover`) or the line is vertical.
pub fn joint_heading(joints: &[[f64; 3]], cover: &[bool]) -> Option<[f64; 2]> {
    let pairs = [(1, 2), (16, 17)];
    let seen = |j: usize| cover.get(j).copied().unwrap_or(false) && j < joints.len();
    if !pairs.iter().all(|&(l, r)| seen(l) && seen(r)) {
        return None;
    }
    let (mut lx, mut ly) = (0.0, 0.0);
    for (l, r) in pairs {
        lx += joints[l][0] - joints[r][0];
        ly += joints[l][1] - joints[r][1];
    }
    let n = (lx * lx + ly * ly).sqrt();
    // Ahead = left x up: (lx, ly, 0) x (0, 0, 1) = (ly, -lx, 0).
    (n > 1e-6).then(|| [ly / n, -lx / n])
}

/// The facing loss of a batch: per view, where each person's torso shows (Gaussians of `sigma` map
/// pixels at the visible torso joints; the strongest person owns a pixel), the person's heading relative
/// to the direction to that camera. `None` without a facing head or without a pixel to supervise.
pub fn facing_term(
    det: &Detection,
    gt: &HostGt,
    batch: &FrameBatch,
    sigma: f32,
    device: &Device,
) -> Option<Tensor<1>> {
    let facing = det.facing.clone()?;
    let [b, v, _, h, w] = facing.dims();
    // Network pixels per map pixel (4, or more when HRNet reads a pooled input).
    let stride = batch.images.dims()[3] as f32 / w as f32;
    let mut target = vec![0f32; b * v * 2 * h * w];
    let mut weight = vec![0f32; b * v * h * w];
    for bi in 0..b {
        for vi in 0..v {
            let centre: [f64; 3] = batch.cameras[bi][vi].centre().into();
            let at = (bi * v + vi) * h * w;
            for (pi, joints) in gt.joints[bi].iter().enumerate() {
                let Some(rel) = joint_heading(joints, &gt.cover[bi])
                    .and_then(|hd| relative_heading(hd, joints[0], centre))
                else {
                    continue;
                };
                let torso = torso_weight(&gt.joints_2d[bi][vi][pi], [h, w], stride, sigma);
                for (px, &m) in torso.iter().enumerate() {
                    if m > weight[at + px] {
                        weight[at + px] = m;
                        let t = (bi * v + vi) * 2 * h * w + px;
                        target[t] = rel[0];
                        target[t + h * w] = rel[1];
                    }
                }
            }
        }
    }
    // No torso with a heading in view (joint-annotated people without hips and shoulders apart, or
    // none visible): nothing to supervise, no term.
    if !weight.iter().any(|&w| w > 0.0) {
        return None;
    }
    let target = Tensor::from_data(TensorData::new(target, [b, v, 2, h, w]), device);
    let weight = Tensor::from_data(TensorData::new(weight, [b, v, h, w]), device);
    // Two channels are (cosine, sine); more are the logits of that many heading bins.
    Some(match facing.dims()[2] {
        2 => facing_loss(facing, target, weight),
        n => facing_bin_loss(facing, bin_labels(target, n), weight),
    })
}

/// Where a person's torso shows in one view `[h * w]` of `stride` network pixels per map pixel: the
/// largest of Gaussians (`sigma` map pixels) at the person's visible torso joints (network pixels with
/// visibility, `[j][3]`).
fn torso_weight(person: &[[f32; 3]], hw: [usize; 2], stride: f32, sigma: f32) -> Vec<f32> {
    let pts: Vec<Option<[f32; 2]>> = TORSO
        .iter()
        .map(|&j| person.get(j).filter(|p| p[2] > 0.5).map(|p| [p[0], p[1]]))
        .collect();
    let maps = heatmap_target(&pts, hw, stride, sigma);
    let n = hw[0] * hw[1];
    (0..n)
        .map(|px| {
            (0..TORSO.len())
                .map(|j| maps[j * n + px])
                .fold(0.0, f32::max)
        })
        .collect()
}

/// Roots at given world positions, as the decoder takes them (score 1).
fn exact_roots(items: impl Iterator<Item = Vec<[f64; 3]>>) -> Vec<Vec<Root>> {
    items
        .map(|r| {
            r.into_iter()
                .map(|position| Root {
                    position,
                    score: 1.0,
                    voxel: [0; 3],
                })
                .collect()
        })
        .collect()
}

/// Per annotated person, the angle (degrees) between the facing head's reading at the person's true
/// root (`facing_readout`) and their heading from the joints. Empty without a facing head.
pub fn facing_errors_deg(
    det: &Detection,
    grids: &[RigGrids],
    gt: &HostGt,
    cfg: &ModelConfig,
    device: &Device,
) -> Vec<f64> {
    let Some(facing) = det.facing.clone() else {
        return Vec::new();
    };
    let roots = gt.roots(cfg.primary_joint.joint());
    let k = roots.iter().map(Vec::len).max().unwrap_or(0);
    if k == 0 {
        return Vec::new();
    }
    let (rt, present) = roots_tensor(&exact_roots(roots.into_iter()), k, device);
    let read: Vec<f32> = facing_readout(facing, grids, &cfg.grid, rt, present)
        .into_data()
        .try_into_vec::<f32>()
        .unwrap_or_default();
    let mut out = Vec::new();
    for (bi, people) in gt.joints.iter().enumerate() {
        for (pi, joints) in people.iter().enumerate() {
            let Some(h) = joint_heading(joints, &gt.cover[bi]) else {
                continue;
            };
            let o = (bi * k + pi) * 2;
            let (x, y) = (read[o] as f64, read[o + 1] as f64);
            let turn = (h[0] * y - h[1] * x).atan2(h[0] * x + h[1] * y);
            out.push(turn.abs().to_degrees());
        }
    }
    out
}

/// Stage 1: HRNet and the RootNet alone.
pub fn stage1_loss(
    model: &MvmpHmr,
    batch: &FrameBatch,
    weights: &LossWeights,
    device: &Device,
) -> StepLoss {
    let cfg = &model.config;
    let gt = HostGt::new(batch);
    let grids = batch_grids(cfg, batch, device);
    let det = model.detect(batch.images.clone(), &grids);
    let (d, diag) = detection_term(&det, &gt, cfg, weights, device);
    let terms = LossTerms {
        detection: (weights.detection > 0.0).then(|| d * weights.detection),
        heatmap_2d: heatmap_2d_term(&det, &gt, cfg, weights, weights.heatmap_2d, device),
        facing: facing_weighted(&det, &gt, batch, weights, device),
        vit_heatmap: (weights.vit_heatmap > 0.0)
            .then(|| model.vit_joint_maps(batch.images.clone()))
            .flatten()
            .map(|maps| vit_heatmap_weighted(maps, &gt, cfg, weights, device)),
        ..Default::default()
    };
    finish(terms.named(), 0, diag, device)
}

/// The 2D heatmap term at `weight` (`None` at 0).
fn heatmap_2d_term(
    det: &Detection,
    gt: &HostGt,
    cfg: &ModelConfig,
    weights: &LossWeights,
    weight: f32,
    device: &Device,
) -> Option<Tensor<1>> {
    (weight > 0.0).then(|| {
        let (sigma, positive) = (weights.heatmap_sigma, weights.heatmap_2d_positive);
        heatmap_term(det, gt, cfg, sigma, positive, device) * weight
    })
}

/// The ViT features' heatmap term at its weight (`None` at 0 or for a model without the head).
fn vit_heatmap_term(
    out: &MvmpOutput,
    gt: &HostGt,
    cfg: &ModelConfig,
    weights: &LossWeights,
    device: &Device,
) -> Option<Tensor<1>> {
    let maps = out
        .vit_heatmaps
        .clone()
        .filter(|_| weights.vit_heatmap > 0.0)?;
    Some(vit_heatmap_weighted(maps, gt, cfg, weights, device))
}

/// The heatmap term of the ViT head's maps `[B, V, J, h, w]` (one pixel a patch) at its weight.
fn vit_heatmap_weighted(
    maps: Tensor<5>,
    gt: &HostGt,
    cfg: &ModelConfig,
    weights: &LossWeights,
    device: &Device,
) -> Tensor<1> {
    let stride = mvmp_backbone::vit::PATCH as f32;
    let sigma = weights.vit_heatmap_sigma;
    joint_heatmap_term(maps, stride, gt, cfg, sigma, 0.0, device) * weights.vit_heatmap
}

/// The facing term at its weight (`None` at 0 or for a model without a facing head).
fn facing_weighted(
    det: &Detection,
    gt: &HostGt,
    batch: &FrameBatch,
    weights: &LossWeights,
    device: &Device,
) -> Option<Tensor<1>> {
    if weights.facing <= 0.0 {
        return None;
    }
    facing_term(det, gt, batch, weights.heatmap_sigma, device).map(|f| f * weights.facing)
}

fn finish(
    terms: Vec<(&'static str, Tensor<1>)>,
    queries: usize,
    diag: [f32; 3],
    device: &Device,
) -> StepLoss {
    let total = terms
        .iter()
        .map(|(_, t)| t.clone())
        .reduce(|a, b| a + b)
        .unwrap_or_else(|| Tensor::zeros([1], device));
    StepLoss {
        total,
        terms,
        queries,
        root_peak: diag[0],
        root_at_gt: diag[1],
        root_background: diag[2],
    }
}

/// Where to decode people in a training step, and which ground-truth person each query is compared with.
/// Returns per item the (root, gt index) of each query.
pub fn choose_queries(
    detections: &[Vec<Root>],
    gt_roots: &[Vec<[f64; 3]>],
    mode: QueryMode,
    gate: f64,
) -> Vec<Vec<([f64; 3], usize)>> {
    detections
        .iter()
        .zip(gt_roots)
        .map(|(det, gt)| {
            let mut out: Vec<([f64; 3], usize)> = Vec::new();
            if mode != QueryMode::Gt {
                let pred: Vec<[f64; 3]> = det.iter().map(|r| r.position).collect();
                for (pi, gi) in mvmp_eval::match_people(&pred, gt, gate) {
                    out.push((pred[pi], gi));
                }
            }
            if mode != QueryMode::Detected {
                for (gi, g) in gt.iter().enumerate() {
                    if !out.iter().any(|&(_, m)| m == gi) {
                        out.push((*g, gi));
                    }
                }
            }
            out
        })
        .collect()
}

/// How stage 2 supervises a step: the loss weights, and where the queries are decoded (`queries`,
/// detections matched to the ground truth within `gate` metres).
#[derive(Debug, Clone, Copy)]
pub struct Stage2<'a> {
    pub weights: &'a LossWeights,
    pub queries: QueryMode,
    pub gate: f64,
}

impl<'a> Stage2<'a> {
    /// Queries at the true roots only.
    pub fn at_true_roots(weights: &'a LossWeights) -> Self {
        Stage2 {
            weights,
            queries: QueryMode::Gt,
            gate: 0.5,
        }
    }
}

/// Stage 2: the whole model and the five losses. The queries are chosen from the detections (see
/// [`Stage2`]), the ground truth is gathered per query ([`QueryTargets`]), and each term is one
/// function.
pub fn stage2_loss(
    model: &MvmpHmr,
    batch: &FrameBatch,
    setup: &Stage2,
    device: &Device,
) -> StepLoss {
    stage2_loss_with(model, batch, None, setup, device)
}

/// [`stage2_loss`] on what [`MvmpHmr::upstream`] gave for `batch` when `up` holds it (the stage that
/// keeps it per frame), else computing it.
pub fn stage2_loss_with(
    model: &MvmpHmr,
    batch: &FrameBatch,
    up: Option<Upstream>,
    setup: &Stage2,
    device: &Device,
) -> StepLoss {
    let cfg = &model.config;
    let Stage2 {
        weights,
        queries: mode,
        gate,
    } = *setup;
    let gt = HostGt::new(batch);
    let queries = (mode, gate);
    let (out, slots) = forward_at_queries(model, batch, up, queries, weights.mesh_pose, device);
    let queries: usize = slots.iter().map(Vec::len).sum();
    let t = QueryTargets::new(batch, &slots, out.roots.dims()[1], device);
    let det = Detection {
        heatmaps: out.heatmaps.clone(),
        likelihood: out.likelihood.clone(),
        offset: out.offset.clone(),
        facing: out.facing.clone(),
    };
    let (d, diag) = detection_term(&det, &gt, cfg, weights, device);
    let frames = BodyFrames::new(&out, batch, &t, weights.mesh_frame);
    let on = |w: f32| w > 0.0;
    let terms = LossTerms {
        detection: on(weights.detection).then(|| d * weights.detection),
        parameters: (on(weights.parameters) || on(weights.parameters_body_l2))
            .then(|| parameters_term(&out, batch, &t, weights, device)),
        mesh: (on(weights.mesh_3d) || on(weights.mesh_2d) || on(weights.translation))
            .then(|| mesh_term(&out, batch, &t, frames.as_ref(), weights))
            .flatten(),
        orientation: on(weights.orientation)
            .then(|| orientation_term(&out, &t) * weights.orientation),
        density: on(weights.density).then(|| {
            density_term(&out, batch, &t, frames.as_ref(), weights, device) * weights.density
        }),
        heatmap_2d: heatmap_2d_term(&det, &gt, cfg, weights, weights.heatmap_2d_stage2, device),
        facing: facing_weighted(&det, &gt, batch, weights, device),
        vit_heatmap: vit_heatmap_term(&out, &gt, cfg, weights, device),
        joint_offsets: joint_offsets_term(&out, batch, &t, weights),
    };
    finish(terms.named(), queries, diag, device)
}

/// The body joints' offsets from the pelvis that the decoder gives (`joint_offsets`) against the
/// truth's, each in its body's own frame (the truth turned by its own global rotation; people without
/// SMPL-X ground truth by the prediction's, as [`BodyFrames`] does): the L1 mean over the coordinates
/// of the joints annotated with their pelvis, weighted. `None` without the weight or the offsets.
fn joint_offsets_term(
    out: &MvmpOutput,
    batch: &FrameBatch,
    t: &QueryTargets,
    weights: &LossWeights,
) -> Option<Tensor<1>> {
    let pred = (out.joint_offsets.clone()).filter(|_| weights.joint_offsets > 0.0)?;
    let [b, k, n, _] = pred.dims();
    let (pred_rot, gt_rot) = BodyFrames::rotations(out, batch, t);
    let zero = Tensor::<3>::zeros([b, k, 3], &pred.device());
    let pred = to_body_frame(pred, zero.clone(), pred_rot.detach());
    let truth = t.joints.clone().narrow(2, 1, n) - t.joints.clone().narrow(2, 0, 1);
    let truth = to_body_frame(truth, zero, gt_rot);
    let w = t.joint_weight.clone();
    let weight = w.clone().narrow(2, 1, n) * w.narrow(2, 0, 1);
    Some(mesh_3d_loss_weighted(pred, truth, weight) * weights.joint_offsets)
}

/// A query: where it is decoded and the index of the ground-truth person it is compared with.
pub type Query = ([f64; 3], usize);

/// The model's forward at the queries `mode` chooses (detections matched to the ground truth within
/// `gate` metres, see [`choose_queries`]), posed as [`MvmpHmr::forward_posed`] with `pose_grad`, and each
/// query's (root, ground-truth index) per item. `up`: what [`MvmpHmr::upstream`] gave for `batch`, when
/// it is at hand.
pub fn forward_at_queries(
    model: &MvmpHmr,
    batch: &FrameBatch,
    up: Option<Upstream>,
    (mode, gate): (QueryMode, f64),
    pose_grad: bool,
    device: &Device,
) -> (MvmpOutput, Vec<Vec<Query>>) {
    let cfg = &model.config;
    let grids = batch_grids(cfg, batch, device);
    let gt_roots = HostGt::new(batch).roots(cfg.primary_joint.joint());
    let mut slots: Vec<Vec<([f64; 3], usize)>> = Vec::new();
    let select = |det: &[Vec<Root>]| {
        slots = choose_queries(det, &gt_roots, mode, gate);
        let roots = exact_roots(slots.iter().map(|s| s.iter().map(|q| q.0).collect()));
        let k = slots.iter().map(Vec::len).max().unwrap_or(0);
        roots_tensor(&roots, k, device)
    };
    let up = up.unwrap_or_else(|| model.upstream(batch.images.clone(), &grids));
    let out = model.decode_posed(up, &grids, select, pose_grad);
    (out, slots)
}

/// Where each query slot's ground truth sits among the batch's padded people.
struct Slots {
    b: usize,
    k: usize,
    /// Padded people per item in the batch.
    p: usize,
    /// The padded ground-truth row of each query `[B * K]` (0 for empty slots).
    rows: Tensor<1, Int>,
}

impl Slots {
    /// Per-person rows `[B, P]` gathered per query `[B, K]`.
    fn pick2(&self, x: Tensor<2>) -> Tensor<2> {
        x.reshape([self.b * self.p])
            .select(0, self.rows.clone())
            .reshape([self.b, self.k])
    }

    /// `[B, P, C]` -> `[B, K, C]`.
    fn pick3(&self, x: Tensor<3>) -> Tensor<3> {
        let c = x.dims()[2];
        x.reshape([self.b * self.p, c])
            .select(0, self.rows.clone())
            .reshape([self.b, self.k, c])
    }

    /// `[B, P, N, C]` -> `[B, K, N, C]`.
    fn pick4(&self, x: Tensor<4>) -> Tensor<4> {
        let [_, _, n, c] = x.dims();
        x.reshape([self.b * self.p, n, c])
            .select(0, self.rows.clone())
            .reshape([self.b, self.k, n, c])
    }
}

/// The ground truth each query is compared with: padded rows of the batch gathered per query slot, and
/// the supervision masks (SMPL-X terms only for people with SMPL-X ground truth, joint terms per
/// annotated joint, the orientation where its four joints are annotated; empty slots masked out).
pub struct QueryTargets {
    at: Slots,
    smplx: Tensor<2>,
    joint_weight: Tensor<3>,
    orientation: Tensor<2>,
    joints: Tensor<4>,
}

impl QueryTargets {
    fn new(
        batch: &FrameBatch,
        slots: &[Vec<([f64; 3], usize)>],
        k: usize,
        device: &Device,
    ) -> Self {
        let (b, p) = (slots.len(), batch.joints_3d.dims()[1]);
        let mut rows = vec![0i64; b * k];
        let mut present = vec![0f32; b * k];
        for (bi, s) in slots.iter().enumerate() {
            for (ki, &(_, gi)) in s.iter().enumerate() {
                rows[bi * k + ki] = (bi * p + gi) as i64;
                present[bi * k + ki] = 1.0;
            }
        }
        let at = Slots {
            b,
            k,
            p,
            rows: Tensor::from_data(TensorData::new(rows, [b * k]), device),
        };
        // 1 where a slot holds a query `[B, K]`.
        let present = Tensor::<2>::from_data(TensorData::new(present, [b, k]), device);
        let joint_weight = at.pick3(batch.joint_valid.clone()) * present.clone().reshape([b, k, 1]);
        QueryTargets {
            smplx: at.pick2(batch.smplx.clone()) * present.clone(),
            orientation: joint_weight
                .clone()
                .narrow(2, 0, 4)
                .min_dim(2)
                .reshape([b, k]),
            joints: at.pick4(batch.joints_3d.clone()),
            joint_weight,
            at,
        }
    }
}

/// The parameter loss (weighted): the regressed rotations, betas and expression against the ground
/// truth's, and the body rotations' squared error at `parameters_body_l2`.
fn parameters_term(
    out: &MvmpOutput,
    batch: &FrameBatch,
    t: &QueryTargets,
    weights: &LossWeights,
    device: &Device,
) -> Tensor<1> {
    let (b, k, p) = (t.at.b, t.at.k, t.at.p);
    let rot = axis_angle_to_matrix(batch.pose.clone().reshape([b * p * NUM_JOINTS, 3])).reshape([
        b * p,
        NUM_JOINTS,
        3,
        3,
    ]);
    let sel: Vec<i64> = REGRESSED_TO_JOINT.iter().map(|&j| j as i64).collect();
    let sel = Tensor::<1, Int>::from_data(TensorData::new(sel, [NUM_REGRESSED]), device);
    let gt_rot = rot
        .select(1, sel)
        .reshape([b * p, NUM_REGRESSED * 9])
        .select(0, t.at.rows.clone())
        .reshape([b, k, NUM_REGRESSED, 3, 3]);
    let l1 = parameter_loss(
        out.rotmats.clone(),
        gt_rot.clone(),
        out.betas.clone(),
        t.at.pick3(batch.betas.clone()),
        out.expression.clone(),
        t.at.pick3(batch.expression.clone()),
        t.smplx.clone(),
    ) * weights.parameters;
    match weights.parameters_body_l2 {
        w if w > 0.0 => l1 + body_pose_l2_loss(out.rotmats.clone(), gt_rot, t.smplx.clone()) * w,
        _ => l1,
    }
}

/// The mesh loss (weighted): 3D and reprojected 2D errors of the joints and, where the batch has ground
/// truth vertices, of the vertices, and the pelvis's translation error. The 3D errors are measured in the
/// world, or in each body's own frame when `frames` are given (`mesh_frame`). `None` when no weight is on.
fn mesh_term(
    out: &MvmpOutput,
    batch: &FrameBatch,
    t: &QueryTargets,
    frames: Option<&BodyFrames>,
    weights: &LossWeights,
) -> Option<Tensor<1>> {
    let points = mesh_points(out, batch, t);
    let mut mesh: Option<Tensor<1>> = None;
    let mut add = |x: Tensor<1>| mesh = Some(mesh.take().map_or(x.clone(), |m| m + x));
    if weights.mesh_3d > 0.0 {
        for (pred, g, w) in &points {
            let (pred, g, w) = match frames {
                Some(f) => (f.pred(pred.clone()), f.gt(g.clone()), w.clone() * f.ok3()),
                None => (pred.clone(), g.clone(), w.clone()),
            };
            add(mesh_3d_loss_weighted(pred, g, w) * weights.mesh_3d);
        }
    }
    if weights.mesh_2d > 0.0
        && let Some(s) = mesh_2d_sum(batch, &points)
    {
        let views = batch.cameras[0].len();
        add(s * (weights.mesh_2d / views as f32));
    }
    if weights.translation > 0.0 {
        let (b, k) = (t.at.b, t.at.k);
        let gt = t.joints.clone().narrow(2, 0, 1).reshape([b, k, 3]);
        let mask = t.joint_weight.clone().narrow(2, 0, 1).reshape([b, k]);
        add(translation_loss(out.transl.clone(), gt, mask) * weights.translation);
    }
    mesh
}

/// The (predicted, ground truth, weight per point) sets the mesh loss compares: the joints, and the
/// vertices where the batch has them.
fn mesh_points(
    out: &MvmpOutput,
    batch: &FrameBatch,
    t: &QueryTargets,
) -> Vec<(Tensor<4>, Tensor<4>, Tensor<3>)> {
    let mut points = vec![(out.joints.clone(), t.joints.clone(), t.joint_weight.clone())];
    if let Some(v) = &batch.vertices {
        let nv = v.dims()[2];
        let w = t
            .smplx
            .clone()
            .reshape([t.at.b, t.at.k, 1])
            .repeat_dim(2, nv);
        points.push((out.vertices.clone(), t.at.pick4(v.clone()), w));
    }
    points
}

/// Each query's body frame, predicted and true ([`MeshFrame`]): the pelvis (joint 0) and, for
/// [`MeshFrame::Body`], the global rotation (identity for [`MeshFrame::Pelvis`]). People without SMPL-X
/// ground truth have no true global rotation; their truth is turned by the prediction's (detached), so
/// that for them the frame takes out the translation alone.
struct BodyFrames {
    pred_pelvis: Tensor<3>,
    pred_rot: Tensor<4>,
    gt_pelvis: Tensor<3>,
    gt_rot: Tensor<4>,
    /// 1 where the true pelvis is annotated `[B, K]`: without it there is no frame to compare in.
    ok: Tensor<2>,
}

impl BodyFrames {
    /// `None` for [`MeshFrame::World`].
    fn new(
        out: &MvmpOutput,
        batch: &FrameBatch,
        t: &QueryTargets,
        frame: MeshFrame,
    ) -> Option<Self> {
        let (b, k) = (t.at.b, t.at.k);
        let pelvis = |j: Tensor<4>| j.narrow(2, 0, 1).reshape([b, k, 3]);
        let (pred_rot, gt_rot) = match frame {
            MeshFrame::World => return None,
            MeshFrame::Pelvis => {
                let eye = Tensor::<2>::eye(3, &out.joints.device()).reshape([1, 1, 3, 3]);
                let eye = eye.repeat_dim(0, b).repeat_dim(1, k);
                (eye.clone(), eye)
            }
            MeshFrame::Body => Self::rotations(out, batch, t),
        };
        Some(BodyFrames {
            pred_pelvis: pelvis(out.joints.clone()),
            pred_rot,
            gt_pelvis: pelvis(t.joints.clone()),
            gt_rot,
            ok: t.joint_weight.clone().narrow(2, 0, 1).reshape([b, k]),
        })
    }

    /// The predicted and the true global rotations `[B, K, 3, 3]`.
    fn rotations(out: &MvmpOutput, batch: &FrameBatch, t: &QueryTargets) -> (Tensor<4>, Tensor<4>) {
        let (b, k, p) = (t.at.b, t.at.k, t.at.p);
        let pred_rot = out.rotmats.clone().narrow(2, 0, 1).reshape([b, k, 3, 3]);
        let global = batch
            .pose
            .clone()
            .reshape([b * p, NUM_JOINTS * 3])
            .narrow(1, 0, 3);
        let true_rot = axis_angle_to_matrix(global)
            .reshape([b * p, 9])
            .select(0, t.at.rows.clone())
            .reshape([b, k, 3, 3]);
        let s = t.smplx.clone().reshape([b, k, 1, 1]);
        let gt_rot = true_rot * s.clone() + pred_rot.clone().detach() * (s.neg() + 1.0);
        (pred_rot, gt_rot)
    }

    fn pred(&self, points: Tensor<4>) -> Tensor<4> {
        to_body_frame(points, self.pred_pelvis.clone(), self.pred_rot.clone())
    }

    fn gt(&self, points: Tensor<4>) -> Tensor<4> {
        to_body_frame(points, self.gt_pelvis.clone(), self.gt_rot.clone())
    }

    /// [`BodyFrames::ok`] as a weight per point `[B, K, 1]`.
    fn ok3(&self) -> Tensor<3> {
        let [b, k] = self.ok.dims();
        self.ok.clone().reshape([b, k, 1])
    }
}

/// The 2D mesh loss summed over views and point sets ([`mesh_2d_loss_views`]).
fn mesh_2d_sum(
    batch: &FrameBatch,
    points: &[(Tensor<4>, Tensor<4>, Tensor<3>)],
) -> Option<Tensor<1>> {
    let size = batch.images.dims()[3] as f32;
    let rigs: Vec<(&[Camera], &[Letterbox])> = batch
        .cameras
        .iter()
        .zip(&batch.letterboxes)
        .map(|(c, l)| (c.as_slice(), l.as_slice()))
        .collect();
    points
        .iter()
        .map(|(pred, g, wt)| mesh_2d_loss_views(pred.clone(), g.clone(), &rigs, size, wt.clone()))
        .reduce(|a, b| a + b)
}

/// The orientation loss on the joints that define a body's facing.
fn orientation_term(out: &MvmpOutput, t: &QueryTargets) -> Tensor<1> {
    orientation_loss(out.joints.clone(), t.joints.clone(), t.orientation.clone())
}

/// The 3D joint-density loss around each person's pelvis.
fn density_term(
    out: &MvmpOutput,
    batch: &FrameBatch,
    t: &QueryTargets,
    frames: Option<&BodyFrames>,
    weights: &LossWeights,
    device: &Device,
) -> Tensor<1> {
    let axis = density_axis(weights.density_grid, weights.density_extent, device);
    if let Some(f) = frames {
        let [b, k] = f.ok.dims();
        return density_loss(
            f.pred(out.joints.clone()),
            f.gt(t.joints.clone()),
            Tensor::zeros([b, k, 3], device),
            axis.clone(),
            weights.density_sigma,
            t.smplx.clone() * f.ok.clone(),
        );
    }
    density_loss(
        out.joints.clone(),
        t.joints.clone(),
        t.at.pick3(batch.pelvis.clone()),
        axis,
        weights.density_sigma,
        t.smplx.clone(),
    )
}

#[cfg(test)]
mod tests {
    use super::joint_heading;

    /// Joints 0..18 with the hips and shoulders of a person whose left is `left` (horizontal).
    fn body(left: [f64; 2]) -> Vec<[f64; 3]> {
        let mut j = vec![[0.0, 0.0, 1.0]; 18];
        for (l, r, z) in [(1, 2, 0.9), (16, 17, 1.4)] {
            j[l] = [0.1 * left[0], 0.1 * left[1], z];
            j[r] = [-0.1 * left[0], -0.1 * left[1], z];
        }
        j
    }

    #[test]
    fn joint_heading_is_ahead_of_the_left_right_line() {
        let cover = vec![true; 18];
        // Left along +x: an upright SMPL-X body (left +x, forward +z in its frame) turned z-up faces -y.
        for (left, ahead) in [
            ([1.0, 0.0], [0.0, -1.0]),
            ([0.0, 1.0], [1.0, 0.0]),
            ([-0.6, -0.8], [-0.8, 0.6]),
        ] {
            let h = joint_heading(&body(left), &cover).unwrap();
            assert!((h[0] - ahead[0]).abs() < 1e-12 && (h[1] - ahead[1]).abs() < 1e-12);
        }
        let mut partial = cover.clone();
        partial[16] = false;
        assert_eq!(joint_heading(&body([1.0, 0.0]), &partial), None);
        assert_eq!(joint_heading(&body([0.0, 0.0]), &cover), None);
    }
}
