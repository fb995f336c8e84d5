//! Batch and group normalisation in training as host passes on flex, with their backward written out.
//!
//! burn differentiates both norms through generic tensor ops, which flex runs as a dozen passes over
//! the activation each way (for batch norm the channels are moved to the front, a copy, first). The
//! tiny HRNet's batch norms made up 60-100 ms of its 245 ms forward and backward (`mvmp bench model
//! --backward` with the norms made identities); with this operation the HRNet row went from 246-289
//! to 192-255 ms (three runs each). The tiny RootNet and the facing head normalise groups of channels
//! instead, with the same arithmetic over other sets of values.
//!
//! Both are one computation over the `(item, channel)` planes of the input: the planes that share
//! statistics form a set (batch norm: one channel's planes over the batch; group norm: one item's
//! planes of one group of channels). The statistics are one pass, the normalised output a second;
//! the backward sums `dy` and `dy * x_hat` per plane in one pass, gathers them per channel (gamma's
//! and beta's gradients) and per set, and writes the input gradient
//! `inv_std * (g - mean(g) - x_hat * mean(g * x_hat))` with `g = gamma * dy`, the means over the set.
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    Autodiff, AutodiffBackend, Backend, Dispatch, Flex, TensorMetadata, backend_extension,
};
use burn::nn::{BatchNorm, GroupNorm};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use crate::host::{HostF32, par_filled, read_f32};

static FUSED_NORM: AtomicBool = AtomicBool::new(true);

/// Whether training on flex normalises with these operations (the default) or with burn's own;
/// process-wide, so that a benchmark can time both.
pub fn set_fused_norm(on: bool) {
    FUSED_NORM.store(on, Ordering::Relaxed);
}

fn fused<const D: usize>(x: &Tensor<D>) -> bool {
    x.is_autodiff() && x.device() == Device::flex() && FUSED_NORM.load(Ordering::Relaxed)
}

/// Which planes share statistics.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Stats {
    /// Each channel over the batch and space (batch norm).
    Channel,
    /// Each item's groups of `channels / groups` consecutive channels (group norm).
    Group(usize),
}

/// `bn.forward(x)`: in training on flex, the fused pass (the same values, running statistics updated
/// alike); otherwise burn's own.
pub fn batch_norm<const D: usize>(bn: &BatchNorm, x: Tensor<D>) -> Tensor<D> {
    batch_norm_then(bn, x, false)
}

/// `relu(bn.forward(x))`: in training on flex one fused pass each way (see [`batch_norm`]); the
/// ReLU's mask is recomputed from the saved statistics in the backward rather than stored.
pub fn batch_norm_relu<const D: usize>(bn: &BatchNorm, x: Tensor<D>) -> Tensor<D> {
    batch_norm_then(bn, x, true)
}

fn batch_norm_then<const D: usize>(bn: &BatchNorm, x: Tensor<D>, relu: bool) -> Tensor<D> {
    if !(fused(&x) && bn.training.is_enabled()) {
        return maybe_relu(bn.forward(x), relu);
    }
    let moments = moments_of(&x, Stats::Channel);
    let (gamma, beta) = (bn.gamma.val(), bn.beta.val());
    let y = normalized(
        x,
        moments.clone(),
        [gamma, beta],
        Norm {
            stats: Stats::Channel,
            epsilon: bn.epsilon,
            relu,
        },
    );
    let device = y.device();
    let [mean, var] = [0, 1].map(|i| moments.clone().narrow(0, i, 1).squeeze_dim::<1>(0));
    let update = |state: &burn::module::RunningState<Tensor<1>>, stat: Tensor<1>| {
        let old = state.value_sync().to_device(&device);
        state.update(
            old.mul_scalar(1.0 - bn.momentum)
                .add(stat.mul_scalar(bn.momentum))
                .detach(),
        );
    };
    update(&bn.running_mean, mean);
    update(&bn.running_var, var);
    y
}

/// `gn.forward(x)`: in training on flex, the fused pass (the same values); otherwise burn's own.
pub fn group_norm<const D: usize>(gn: &GroupNorm, x: Tensor<D>) -> Tensor<D> {
    group_norm_then(gn, x, false)
}

/// `relu(gn.forward(x))`, fused as [`batch_norm_relu`] is.
pub fn group_norm_relu<const D: usize>(gn: &GroupNorm, x: Tensor<D>) -> Tensor<D> {
    group_norm_then(gn, x, true)
}

fn group_norm_then<const D: usize>(gn: &GroupNorm, x: Tensor<D>, relu: bool) -> Tensor<D> {
    let c = x.dims()[1];
    let (Some(gamma), Some(beta)) = (&gn.gamma, &gn.beta) else {
        return maybe_relu(gn.forward(x), relu);
    };
    if !fused(&x) || gn.num_groups == 0 || !c.is_multiple_of(gn.num_groups) {
        return maybe_relu(gn.forward(x), relu);
    }
    let stats = Stats::Group(gn.num_groups);
    let moments = moments_of(&x, stats);
    let norm = Norm {
        stats,
        epsilon: gn.epsilon,
        relu,
    };
    normalized(x, moments, [gamma.val(), beta.val()], norm)
}

fn maybe_relu<const D: usize>(x: Tensor<D>, relu: bool) -> Tensor<D> {
    match relu {
        true => burn::tensor::activation::relu(x),
        false => x,
    }
}

/// What a normalisation computes besides its inputs: which planes share statistics, the variance's
/// epsilon, and whether a ReLU follows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Norm {
    pub stats: Stats,
    pub epsilon: f64,
    pub relu: bool,
}

/// `[2, sets]`: each set's mean and biased variance, as a constant.
fn moments_of<const D: usize>(x: &Tensor<D>, stats: Stats) -> Tensor<2> {
    Tensor::<2>::from_dispatch(<Dispatch as NormBackend>::set_moments(
        x.clone().detach().into_dispatch(),
        stats,
    ))
}

fn normalized<const D: usize>(
    x: Tensor<D>,
    moments: Tensor<2>,
    [gamma, beta]: [Tensor<1>; 2],
    norm: Norm,
) -> Tensor<D> {
    Tensor::from_dispatch(<Dispatch as NormBackend>::normalize(
        x.into_dispatch(),
        gamma.into_dispatch(),
        beta.into_dispatch(),
        moments.into_dispatch(),
        norm,
    ))
}

/// The backend side: host passes on any backend whose tensors can be read on the host; autodiff adds
/// the backward of `normalize` (the moments are constants to it: its backward is the whole norm's,
/// statistics included).
#[backend_extension(Flex, Autodiff)]
pub trait NormBackend: Backend {
    /// `x [B, C, ...]` -> `[2, sets]`: each set's mean and biased variance (see [`Stats`]).
    fn set_moments(x: FloatTensor<Self>, stats: Stats) -> FloatTensor<Self> {
        let device = x.device();
        let layout = Layout::of(&x, stats);
        let (mean, var) = moments(&HostF32::read::<Self>(x), layout);
        let values = mean.into_iter().chain(var).collect::<Vec<_>>();
        Self::float_from_data(TensorData::new(values, [2, layout.sets()]), &device)
    }

    /// `(x - mean) / sqrt(var + eps) * gamma + beta`, the statistics per set, gamma and beta per
    /// channel, with `moments` from [`NormBackend::set_moments`]; then a ReLU if `norm.relu`.
    fn normalize(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        moments: FloatTensor<Self>,
        norm: Norm,
    ) -> FloatTensor<Self> {
        forward::<Self>(x, gamma, beta, moments, norm).0
    }
}

impl NormBackend for Flex {}

impl<B: Backend + NormBackend, C: CheckpointStrategy> NormBackend for Autodiff<B, C> {
    fn set_moments(x: FloatTensor<Self>, stats: Stats) -> FloatTensor<Self> {
        <Self as AutodiffBackend>::from_inner(B::set_moments(x.into_primitive(), stats))
    }

    fn normalize(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        moments: FloatTensor<Self>,
        norm: Norm,
    ) -> FloatTensor<Self> {
        let guards = [x.node(), gamma.node(), beta.node()];
        let (out, saved) = forward::<B>(
            x.into_primitive(),
            gamma.into_primitive(),
            beta.into_primitive(),
            moments.into_primitive(),
            norm,
        );
        match NormBackward.prepare::<C>(guards).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish(saved, out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

/// `[B, C, S]` (batch items, channels, the values of one channel of one item: a plane) and which
/// planes share statistics.
#[derive(Debug, Clone, Copy)]
struct Layout {
    b: usize,
    c: usize,
    s: usize,
    stats: Stats,
}

impl Layout {
    fn of(t: &impl TensorMetadata, stats: Stats) -> Layout {
        let shape = t.shape();
        let (b, c) = (shape[0], shape[1]);
        let s = shape.num_elements() / (b * c).max(1);
        Layout { b, c, s, stats }
    }

    fn sets(&self) -> usize {
        match self.stats {
            Stats::Channel => self.c,
            Stats::Group(g) => self.b * g,
        }
    }

    /// The set of plane `p` (item `p / C`, channel `p % C`).
    fn set_of(&self, p: usize) -> usize {
        let ch = p % self.c;
        match self.stats {
            Stats::Channel => ch,
            Stats::Group(g) => (p / self.c) * g + ch / (self.c / g),
        }
    }

    /// The planes of set `k`.
    fn planes(&self, k: usize) -> Vec<usize> {
        match self.stats {
            Stats::Channel => (0..self.b).map(|bi| bi * self.c + k).collect(),
            Stats::Group(g) => {
                let per = self.c / g;
                let first = (k / g) * self.c + (k % g) * per;
                (first..first + per).collect()
            }
        }
    }

    fn plane<'a>(&self, v: &'a [f32], p: usize) -> &'a [f32] {
        &v[p * self.s..(p + 1) * self.s]
    }

    /// Values per set.
    fn count(&self) -> f64 {
        (self.b * self.c * self.s) as f64 / self.sets() as f64
    }
}

/// Each set's mean and biased variance (two passes, accumulated in f64).
fn moments(x: &[f32], l: Layout) -> (Vec<f32>, Vec<f32>) {
    (0..l.sets())
        .into_par_iter()
        .map(|k| {
            let planes = l.planes(k);
            let values = || planes.iter().flat_map(|&p| l.plane(x, p));
            let mean = values().map(|&v| v as f64).sum::<f64>() / l.count();
            let var = values().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / l.count();
            (mean as f32, var as f32)
        })
        .unzip()
}

/// What the backward needs: the input, each set's mean and 1 / std, gamma, and (for the ReLU's mask)
/// each plane's `scale` and `shift` of the forward's `x * scale + shift`.
#[derive(Debug, Clone)]
struct Saved<B: Backend> {
    x: FloatTensor<B>,
    layout: Layout,
    shape: Vec<usize>,
    mean: Vec<f32>,
    inv_std: Vec<f32>,
    gamma: Vec<f32>,
    affine: Vec<(f32, f32)>,
    relu: bool,
}

impl<B: Backend> Saved<B> {
    /// Plane `p`'s output gradient through the ReLU, if any: zero where the output `x * scale +
    /// shift` was at most zero, `g` elsewhere (burn's ReLU backward). The forward's own scale and
    /// shift, so the mask is the forward's bit for bit.
    fn gate(&self, p: usize) -> impl Fn(f32, f32) -> f32 {
        let (scale, shift) = self.affine[p];
        let relu = self.relu;
        move |g, v| {
            if relu && v * scale + shift <= 0.0 {
                0.0
            } else {
                g
            }
        }
    }
}

/// The ReLU as burn computes it: zero where `y <= 0`, `y` elsewhere (a NaN stays one).
fn positive(y: f32) -> f32 {
    if y <= 0.0 { 0.0 } else { y }
}

fn forward<B: Backend>(
    x: FloatTensor<B>,
    gamma: FloatTensor<B>,
    beta: FloatTensor<B>,
    moments: FloatTensor<B>,
    Norm {
        stats,
        epsilon,
        relu,
    }: Norm,
) -> (FloatTensor<B>, Saved<B>) {
    let device = x.device();
    let layout = Layout::of(&x, stats);
    let shape = x.shape().to_vec();
    let moments = HostF32::read::<B>(moments);
    let (mean, var) = moments.split_at(layout.sets());
    let inv_std: Vec<f32> = var
        .iter()
        .map(|&v| (1.0 / (v as f64 + epsilon).sqrt()) as f32)
        .collect();
    let (gamma, beta) = (read_f32::<B>(gamma), read_f32::<B>(beta));
    let affine: Vec<(f32, f32)> = (0..layout.b * layout.c)
        .map(|p| {
            let (ch, k) = (p % layout.c, layout.set_of(p));
            let scale = inv_std[k] * gamma[ch];
            (scale, beta[ch] - mean[k] * scale)
        })
        .collect();
    let input = HostF32::read::<B>(x.clone());
    let plane = layout.s.max(1);
    let out = par_filled(input.len(), plane, |p, dst| {
        let (scale, shift) = affine[p];
        let pairs = dst.iter_mut().zip(&input[p * plane..]);
        match relu {
            true => pairs.for_each(|(d, &v)| *d = positive(v * scale + shift)),
            false => pairs.for_each(|(d, &v)| *d = v * scale + shift),
        }
    });
    let y = B::float_from_data(TensorData::new(out, shape.clone()), &device);
    let saved = Saved {
        x,
        layout,
        shape,
        mean: mean.to_vec(),
        inv_std,
        gamma,
        affine,
        relu,
    };
    (y, saved)
}

#[derive(Debug)]
struct NormBackward;

/// Per plane: the sums of `dy` and of `dy * x_hat`.
fn plane_sums<B: Backend>(dy: &[f32], x: &[f32], s: &Saved<B>) -> Vec<(f64, f64)> {
    let l = s.layout;
    (0..l.b * l.c)
        .into_par_iter()
        .map(|p| {
            let k = l.set_of(p);
            let (m, r) = (s.mean[k], s.inv_std[k]);
            let pass = s.gate(p);
            let (mut sum, mut dot) = (0f64, 0f64);
            for (&g, &v) in l.plane(dy, p).iter().zip(l.plane(x, p)) {
                let g = pass(g, v);
                sum += g as f64;
                dot += (g * (v - m) * r) as f64;
            }
            (sum, dot)
        })
        .collect()
}

impl<B: Backend> Backward<B, 3> for NormBackward {
    type State = Saved<B>;

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node_x, node_gamma, node_beta] = ops.parents;
        let dy = grads.consume::<B>(&ops.node);
        let device = dy.device();
        let s = ops.state;
        let (dy, x) = (HostF32::read::<B>(dy), HostF32::read::<B>(s.x.clone()));
        let l = s.layout;
        let sums = plane_sums(&dy, &x, &s);
        // Gamma's and beta's gradients per channel; the means of g = gamma * dy and g * x_hat per set.
        let (mut dbeta, mut dgamma) = (vec![0f64; l.c], vec![0f64; l.c]);
        let (mut mean_g, mut mean_gx) = (vec![0f64; l.sets()], vec![0f64; l.sets()]);
        for (p, &(sum, dot)) in sums.iter().enumerate() {
            let (ch, k) = (p % l.c, l.set_of(p));
            dbeta[ch] += sum;
            dgamma[ch] += dot;
            mean_g[k] += s.gamma[ch] as f64 * sum / l.count();
            mean_gx[k] += s.gamma[ch] as f64 * dot / l.count();
        }
        let plane = l.s.max(1);
        let dx = par_filled(dy.len(), plane, |p, dx| {
            let (ch, k) = (p % l.c, l.set_of(p));
            let (m, r, gamma) = (s.mean[k], s.inv_std[k], s.gamma[ch]);
            let (mg, mgx) = (mean_g[k] as f32, mean_gx[k] as f32);
            let pass = s.gate(p);
            let (g, v) = (&dy[p * plane..], &x[p * plane..]);
            for ((dx, &g), &v) in dx.iter_mut().zip(g).zip(v) {
                *dx = r * (gamma * pass(g, v) - mg - (v - m) * r * mgx);
            }
        });
        let tensor = |values: Vec<f32>, shape: Vec<usize>| {
            B::float_from_data(TensorData::new(values, shape), &device)
        };
        let narrow = |v: Vec<f64>| v.into_iter().map(|v| v as f32).collect::<Vec<_>>();
        for (node, g) in [
            (node_x, tensor(dx, s.shape)),
            (node_gamma, tensor(narrow(dgamma), vec![l.c])),
            (node_beta, tensor(narrow(dbeta), vec![l.c])),
        ] {
            if let Some(node) = node {
                grads.register::<B>(node.id, g);
            }
        }
    }
}
