//! The decoder alone, fitted to one joint heatmap volume: each person read at their true root and
//! heading (no detection, no facing head, a zero image-feature volume) and trained on their body
//! rotations, then scored on held-out people by the mean angle of the 21 body rotations from the truth.
//! It says in seconds how much of the pose a joint volume lets the decoder learn, and whether the
//! training loss lets it (docs/architecture.md, What the decoder learns from perfect maps): the volume
//! is the truth's own (the heatmap targets fused, what a perfect HRNet would give), a run's HRNet's, or
//! zeros.
use std::path::Path;

use burn::data::dataloader::batcher::Batcher;
use burn::module::Module;
use burn::optim::GradientsParams;
use burn::tensor::{Bool, Device, Tensor, TensorData};

use mvmp_data::dataset::FrameDataset;
use mvmp_data::loader::{FrameBatch, FrameBatcher, Split, ViewChoice};
use mvmp_decoder::{Decoder, QueryInputs};
use mvmp_geom::rotation::{axis_angle_to_matrix, rot6d_to_matrix};
use mvmp_losses::parameter_loss;
use mvmp_model::facing::turn_to_heading;
use mvmp_model::{ModelConfig, MvmpHmr};
use mvmp_smplx::names::{NUM_BETAS, NUM_BODY, NUM_EXPRESSION, NUM_REGRESSED, REGRESSED_TO_JOINT};

use crate::TrainError;
use crate::probe::headed_people;
use crate::step::{batch_grids, truth_joint_volume};

/// Where the joint volume comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum JointMaps {
    /// The heatmap loss's targets at the true 2D joints, fused as the model fuses its maps.
    Truth,
    /// The model's own HRNet maps, fused.
    Model,
    /// A volume of zeros: what the decoder learns from the root's height and the heading alone.
    Zero,
}

/// What the decoder is trained on.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum FitLoss {
    /// The L1 of the 21 body rotations' matrices alone.
    Body,
    /// The parameter loss as training has it: all 53 rotations (the global one turned with the
    /// heading), the betas and the expression.
    Parameters,
}

#[derive(Debug, Clone)]
pub struct FitOptions {
    pub maps: JointMaps,
    pub loss: FitLoss,
    /// One-frame steps, through the training frames in a fixed shuffled order.
    pub steps: usize,
    pub lr: f64,
    /// Cameras per frame (the first ones of each rig).
    pub views: usize,
    /// Held-out frames scored, spread over the split (0: all).
    pub test_frames: usize,
    /// Width of the truth's Gaussians, map pixels (the training's `heatmap_sigma`).
    pub sigma: f32,
    pub seed: u64,
    /// Score every this many steps (and at the end).
    pub every: usize,
}

/// One frame as the decoder reads it, on the plain device.
pub struct FitFrame {
    joints: Tensor<5>,
    roots: Tensor<3>,
    headings: Tensor<3>,
    /// `[1, K, 53, 3, 3]` the regressed rotations (the global one in the world).
    rotations: Tensor<5>,
    betas: Tensor<3>,
    expression: Tensor<3>,
    people: usize,
}

/// The held-out error after a number of steps.
#[derive(Debug, Clone, Copy, serde::Serialize)]
pub struct FitPoint {
    pub step: usize,
    /// Mean angle of the 21 body rotations from the truth, degrees: held out, and on the training
    /// frames' first people scored the same way.
    pub held_out_deg: f64,
    pub train_deg: f64,
}

/// The frames of a split (at most `max`, spread over it; 0: all) as the decoder reads them. People
/// whose heading the annotation does not give are left out, and frames without any.
pub fn frames(
    model: &MvmpHmr,
    data: &Path,
    split: Split,
    max: usize,
    opts: &FitOptions,
    device: &Device,
) -> Result<Vec<FitFrame>, TrainError> {
    let cfg = &model.config;
    let views = ViewChoice::Fixed((0..opts.views).collect());
    let ds = FrameDataset::open(data, split, views, cfg.image_size)?;
    let n = match max {
        0 => ds.len(),
        m => m.min(ds.len()),
    };
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        let batch = FrameBatcher::default().batch(vec![ds.load(i * ds.len() / n)?], device);
        out.extend(fit_frame(model, &batch, opts, device));
    }
    Ok(out)
}

/// A frame's people, flattened, as they are gathered.
#[derive(Default)]
struct Rows {
    roots: Vec<f32>,
    headings: Vec<f32>,
    /// Axis-angle of the regressed rotations.
    rotations: Vec<f32>,
    betas: Vec<f32>,
    expression: Vec<f32>,
}

fn fit_frame(
    model: &MvmpHmr,
    batch: &FrameBatch,
    opts: &FitOptions,
    device: &Device,
) -> Option<FitFrame> {
    let cfg = &model.config;
    let mut rows = Rows::default();
    for (p, h) in headed_people(batch) {
        rows.roots.extend(p.joints_3d[cfg.primary_joint.joint()]);
        rows.headings.extend(h.map(|x| x as f32));
        rows.rotations.extend(
            REGRESSED_TO_JOINT
                .iter()
                .flat_map(|&j| p.pose[j * 3..j * 3 + 3].iter().copied()),
        );
        rows.betas.extend(p.betas);
        rows.expression.extend(p.expression);
    }
    let k = rows.headings.len() / 2;
    if k == 0 {
        return None;
    }
    let grids = batch_grids(cfg, batch, device);
    let joints = match opts.maps {
        JointMaps::Truth => truth_joint_volume(cfg, batch, &grids, opts.sigma, device),
        JointMaps::Model => model.detect_with_volume(batch.images.clone(), &grids).1,
        JointMaps::Zero => {
            let [x, y, z] = cfg.grid.shape;
            Tensor::zeros([1, cfg.heatmap_joints.len(), x, y, z], device)
        }
    };
    let t = |v: Vec<f32>, w: usize| Tensor::<3>::from_data(TensorData::new(v, [1, k, w]), device);
    let aa = Tensor::<2>::from_data(
        TensorData::new(rows.rotations, [k * NUM_REGRESSED, 3]),
        device,
    );
    Some(FitFrame {
        joints,
        roots: t(rows.roots, 3),
        headings: t(rows.headings, 2),
        rotations: axis_angle_to_matrix(aa).reshape([1, k, NUM_REGRESSED, 3, 3]),
        betas: t(rows.betas, NUM_BETAS),
        expression: t(rows.expression, NUM_EXPRESSION),
        people: k,
    })
}

/// The decoder's regressed rotations `[1, K, 53, 3, 3]` (the global one turned with the heading, as the
/// model turns it), betas and expression for a frame, on `device`.
fn decode(
    dec: &Decoder,
    cfg: &ModelConfig,
    f: &FitFrame,
    device: &Device,
) -> (Tensor<5>, Tensor<3>, Tensor<3>) {
    let [x, y, z] = cfg.grid.shape;
    let volume = Tensor::<5>::zeros([1, cfg.feature_channels, x, y, z], device);
    let k = f.people;
    let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true; k], [1, k]), device);
    let headings = f.headings.clone().to_device(device);
    let inputs = QueryInputs {
        heading: Some(headings.clone()),
        joints: Some(f.joints.clone().to_device(device)),
    };
    let roots = f.roots.clone().to_device(device);
    let out = dec.forward_with(volume, inputs, &cfg.grid, roots, present);
    let rot = rot6d_to_matrix(out.rot6d.reshape([k * NUM_REGRESSED, 6]));
    let rot = turn_to_heading(
        rot.reshape([k, NUM_REGRESSED, 3, 3]),
        headings.reshape([k, 2]),
    );
    let rot = rot.reshape([1, k, NUM_REGRESSED, 3, 3]);
    (rot, out.betas, out.expression)
}

/// Body rotations `[1, K, 21, 3, 3]` of the regressed ones.
fn body(rot: Tensor<5>) -> Tensor<5> {
    rot.narrow(2, 1, NUM_BODY)
}

fn loss(dec: &Decoder, cfg: &ModelConfig, f: &FitFrame, kind: FitLoss, d: &Device) -> Tensor<1> {
    let (rot, betas, expression) = decode(dec, cfg, f, d);
    let truth = f.rotations.clone().to_device(d);
    match kind {
        FitLoss::Body => (body(rot) - body(truth)).abs().mean(),
        FitLoss::Parameters => parameter_loss(
            rot,
            truth,
            betas,
            f.betas.clone().to_device(d),
            expression,
            f.expression.clone().to_device(d),
            Tensor::ones([1, f.people], d),
        ),
    }
}

/// Mean angle (degrees) of the 21 body rotations from the truth over the frames' people.
pub fn body_error_deg(dec: &Decoder, cfg: &ModelConfig, frames: &[FitFrame], d: &Device) -> f64 {
    let (mut sum, mut n) = (0.0, 0usize);
    for f in frames {
        // trace(P^T G) per rotation: the angle between them.
        let (rot, _, _) = decode(dec, cfg, f, d);
        let prod = body(rot) * body(f.rotations.clone().to_device(d));
        let trace: Vec<f32> = (prod.sum_dim(3).sum_dim(4).into_data())
            .try_to_vec()
            .expect("float rotations");
        sum += trace.iter().map(|&t| angle_deg(f64::from(t))).sum::<f64>();
        n += trace.len();
    }
    sum / n.max(1) as f64
}

/// The angle (degrees) of the rotation between two whose product `P^T G` has trace `trace`.
fn angle_deg(trace: f64) -> f64 {
    ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
}

/// A fresh decoder of `cfg` (drawn from `opts.seed`) trained on `train` as `opts` says, scored on `test`
/// and on `train`'s first frames before the first step and every `opts.every` steps. A loss or a score
/// that is not finite (a rate too high for the decoder) stops the fit with an error naming the step.
pub fn fit(
    cfg: &ModelConfig,
    train: &[FitFrame],
    test: &[FitFrame],
    opts: &FitOptions,
    mut report: impl FnMut(FitPoint),
) -> Result<Vec<FitPoint>, TrainError> {
    let d = Device::flex().autodiff();
    d.seed(opts.seed);
    let mut dec = cfg.decoder_config().init(&d);
    let mut optim = crate::adam::adam();
    let plain = Device::flex();
    let seen = &train[..train.len().min(test.len().max(1))];
    let mut score = |dec: &Decoder, step: usize| {
        let valid = dec.valid();
        let p = FitPoint {
            step,
            held_out_deg: body_error_deg(&valid, cfg, test, &plain),
            train_deg: body_error_deg(&valid, cfg, seen, &plain),
        };
        report(p);
        p
    };
    let diverged = |step: usize, what: String| TrainError::Diverged {
        step,
        what,
        lr: opts.lr,
    };
    let mut points = vec![score(&dec, 0)];
    for s in 0..opts.steps {
        let f = &train[order(s, train.len())];
        let l = loss(&dec, cfg, f, opts.loss, &d);
        let value = l.clone().into_scalar::<f32>();
        if !value.is_finite() {
            return Err(diverged(s + 1, format!("the loss is {value}")));
        }
        let grads = GradientsParams::from_grads(l.backward(), &dec);
        dec = optim.step(opts.lr, dec, grads);
        if (s + 1) % opts.every.max(1) == 0 || s + 1 == opts.steps {
            let p = score(&dec, s + 1);
            if !(p.held_out_deg.is_finite() && p.train_deg.is_finite()) {
                return Err(diverged(
                    s + 1,
                    "the decoder's rotations are not finite".into(),
                ));
            }
            points.push(p);
        }
    }
    Ok(points)
}

/// The frame of step `s` among `n`: a fixed stride coprime with any `n` below it walks every frame once
/// per pass in a scattered order.
fn order(s: usize, n: usize) -> usize {
    const STRIDE: usize = 7919;
    match n % STRIDE {
        0 => s % n,
        _ => (s * STRIDE) % n,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_order_visits_every_frame_once_per_pass() {
        for n in [1, 2, 7, 288, 7919, 2 * 7919] {
            let mut seen: Vec<usize> = (0..n).map(|s| order(s, n)).collect();
            seen.sort_unstable();
            assert_eq!(seen, (0..n).collect::<Vec<_>>(), "{n} frames");
        }
    }

    #[test]
    fn the_angle_is_read_from_the_trace() {
        // A turn by a about any axis has trace 1 + 2 cos a.
        for a in [0.0f64, 5.0, 30.0, 90.0, 179.0] {
            let trace = 1.0 + 2.0 * a.to_radians().cos();
            assert!((angle_deg(trace) - a).abs() < 1e-9, "{a}");
        }
        // Rounding past the ends stays defined.
        assert_eq!(angle_deg(3.0 + 1e-6), 0.0);
        assert!((angle_deg(-1.0 - 1e-6) - 180.0).abs() < 1e-9);
    }
}
