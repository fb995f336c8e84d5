//! Batch normalisation in training as one host pass on flex, with its backward written out.
//!
//! burn differentiates its batch norm as one operation, but flex computes both directions from generic
//! tensor ops: the channels are moved to the front (a copy), reduced, broadcast back and combined, a
//! dozen passes over the activation each way. The tiny HRNet's batch norms made up 60-100 ms of its
//! 245 ms forward and backward (`mvmp bench model --backward` with the norms made identities); with this
//! operation the HRNet row went from 246-289 to 192-255 ms (three runs each). Here the statistics
//! are one pass, the normalised output a second, and the backward two: the per-channel sums of the
//! output gradient and of its product with the normalised input, then the input gradient
//! `gamma / std * (dy - mean(dy) - x_hat * mean(dy * x_hat))`.
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    Autodiff, AutodiffBackend, Backend, Dispatch, Flex, TensorMetadata, backend_extension,
};
use burn::nn::BatchNorm;
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use crate::host::{HostF32, read_f32};

static FUSED_NORM: AtomicBool = AtomicBool::new(true);

/// Whether training on flex normalises batches with this operation (the default) or with burn's own;
/// process-wide, so that a benchmark can time both.
pub fn set_fused_norm(on: bool) {
    FUSED_NORM.store(on, Ordering::Relaxed);
}

/// `bn.forward(x)`: in training on flex, the fused pass (the same values, running statistics updated
/// alike); otherwise burn's own.
pub fn batch_norm<const D: usize>(bn: &BatchNorm, x: Tensor<D>) -> Tensor<D> {
    let fused = x.is_autodiff()
        && bn.training.is_enabled()
        && x.device() == Device::flex()
        && FUSED_NORM.load(Ordering::Relaxed);
    if !fused {
        return bn.forward(x);
    }
    let moments = Tensor::<2>::from_dispatch(<Dispatch as BatchNormBackend>::channel_moments(
        x.clone().detach().into_dispatch(),
    ));
    let y = Tensor::from_dispatch(<Dispatch as BatchNormBackend>::normalize(
        x.into_dispatch(),
        bn.gamma.val().into_dispatch(),
        bn.beta.val().into_dispatch(),
        moments.clone().into_dispatch(),
        bn.epsilon,
    ));
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

/// The backend side: host passes on any backend whose tensors can be read on the host; autodiff adds
/// the backward of `normalize` (the moments are constants to it: its backward is the whole batch
/// norm's, statistics included).
#[backend_extension(Flex, Autodiff)]
pub trait BatchNormBackend: Backend {
    /// `x [B, C, ...]` -> `[2, C]`: each channel's mean and biased variance over batch and space.
    fn channel_moments(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let device = x.device();
        let layout = Layout::of(&x);
        let (mean, var) = moments(&HostF32::read::<Self>(x), layout);
        let values = mean.into_iter().chain(var).collect::<Vec<_>>();
        Self::float_from_data(TensorData::new(values, [2, layout.c]), &device)
    }

    /// `(x - mean) / sqrt(var + eps) * gamma + beta`, per channel, with `moments` from
    /// [`BatchNormBackend::channel_moments`].
    fn normalize(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        moments: FloatTensor<Self>,
        epsilon: f64,
    ) -> FloatTensor<Self> {
        forward::<Self>(x, gamma, beta, moments, epsilon).0
    }
}

impl BatchNormBackend for Flex {}

impl<B: Backend + BatchNormBackend, C: CheckpointStrategy> BatchNormBackend for Autodiff<B, C> {
    fn channel_moments(x: FloatTensor<Self>) -> FloatTensor<Self> {
        <Self as AutodiffBackend>::from_inner(B::channel_moments(x.into_primitive()))
    }

    fn normalize(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        moments: FloatTensor<Self>,
        epsilon: f64,
    ) -> FloatTensor<Self> {
        let guards = [x.node(), gamma.node(), beta.node()];
        let (out, saved) = forward::<B>(
            x.into_primitive(),
            gamma.into_primitive(),
            beta.into_primitive(),
            moments.into_primitive(),
            epsilon,
        );
        match NormBackward.prepare::<C>(guards).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish(saved, out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

/// `[B, C, S]`: batch items, channels, and the values of one channel of one item (all other axes).
#[derive(Debug, Clone, Copy)]
struct Layout {
    b: usize,
    c: usize,
    s: usize,
}

impl Layout {
    fn of(t: &impl TensorMetadata) -> Layout {
        let shape = t.shape();
        let (b, c) = (shape[0], shape[1]);
        let s = shape.num_elements() / (b * c).max(1);
        Layout { b, c, s }
    }

    /// Channel `ch`'s values of every batch item, one slice per item.
    fn channel<'a>(&self, v: &'a [f32], ch: usize) -> impl Iterator<Item = &'a [f32]> {
        let (c, s) = (self.c, self.s);
        (0..self.b).map(move |bi| &v[(bi * c + ch) * s..(bi * c + ch + 1) * s])
    }

    fn count(&self) -> f64 {
        (self.b * self.s) as f64
    }
}

/// Each channel's mean and biased variance (two passes, accumulated in f64).
fn moments(x: &[f32], l: Layout) -> (Vec<f32>, Vec<f32>) {
    (0..l.c)
        .into_par_iter()
        .map(|ch| {
            let mean = l.channel(x, ch).flatten().map(|&v| v as f64).sum::<f64>() / l.count();
            let var = l
                .channel(x, ch)
                .flatten()
                .map(|&v| (v as f64 - mean).powi(2))
                .sum::<f64>()
                / l.count();
            (mean as f32, var as f32)
        })
        .unzip()
}

/// What the backward needs: the input, each channel's mean, 1 / std and gamma.
#[derive(Debug, Clone)]
struct Saved<B: Backend> {
    x: FloatTensor<B>,
    layout: Layout,
    shape: Vec<usize>,
    mean: Vec<f32>,
    inv_std: Vec<f32>,
    gamma: Vec<f32>,
}

fn forward<B: Backend>(
    x: FloatTensor<B>,
    gamma: FloatTensor<B>,
    beta: FloatTensor<B>,
    moments: FloatTensor<B>,
    epsilon: f64,
) -> (FloatTensor<B>, Saved<B>) {
    let device = x.device();
    let layout = Layout::of(&x);
    let shape = x.shape().to_vec();
    let moments = HostF32::read::<B>(moments);
    let (mean, var) = moments.split_at(layout.c);
    let inv_std: Vec<f32> = var
        .iter()
        .map(|&v| (1.0 / (v as f64 + epsilon).sqrt()) as f32)
        .collect();
    let (gamma, beta) = (read_f32::<B>(gamma), read_f32::<B>(beta));
    let input = HostF32::read::<B>(x.clone());
    let mut out = vec![0f32; input.len()];
    let plane = layout.s.max(1);
    (out.par_chunks_mut(plane).zip(input.par_chunks(plane)))
        .enumerate()
        .for_each(|(i, (dst, src))| {
            let ch = i % layout.c;
            let scale = inv_std[ch] * gamma[ch];
            let shift = beta[ch] - mean[ch] * scale;
            dst.iter_mut()
                .zip(src)
                .for_each(|(d, &v)| *d = v * scale + shift);
        });
    let y = B::float_from_data(TensorData::new(out, shape.clone()), &device);
    let saved = Saved {
        x,
        layout,
        shape,
        mean: mean.to_vec(),
        inv_std,
        gamma,
    };
    (y, saved)
}

#[derive(Debug)]
struct NormBackward;

impl<B: Backend> Backward<B, 3> for NormBackward {
    type State = Saved<B>;

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node_x, node_gamma, node_beta] = ops.parents;
        let dy = grads.consume::<B>(&ops.node);
        let device = dy.device();
        let s = ops.state;
        let (dy, x) = (HostF32::read::<B>(dy), HostF32::read::<B>(s.x));
        let l = s.layout;
        // Per channel: sum(dy) and sum(dy * x_hat).
        let (dbeta, dgamma): (Vec<f32>, Vec<f32>) = (0..l.c)
            .into_par_iter()
            .map(|ch| {
                let (m, r) = (s.mean[ch], s.inv_std[ch]);
                let (mut sum, mut dot) = (0f64, 0f64);
                for (g, v) in l.channel(&dy, ch).zip(l.channel(&x, ch)) {
                    for (&g, &v) in g.iter().zip(v) {
                        sum += g as f64;
                        dot += (g * (v - m) * r) as f64;
                    }
                }
                (sum as f32, dot as f32)
            })
            .unzip();
        let n = l.count() as f32;
        let plane = l.s.max(1);
        let mut dx = vec![0f32; dy.len()];
        (dx.par_chunks_mut(plane).zip(dy.par_chunks(plane)))
            .zip(x.par_chunks(plane))
            .enumerate()
            .for_each(|(i, ((dx, g), v))| {
                let ch = i % l.c;
                let (m, r) = (s.mean[ch], s.inv_std[ch]);
                let (mean_g, mean_gx) = (dbeta[ch] / n, dgamma[ch] / n);
                let k = s.gamma[ch] * r;
                for ((dx, &g), &v) in dx.iter_mut().zip(g).zip(v) {
                    *dx = k * (g - mean_g - (v - m) * r * mean_gx);
                }
            });
        let tensor = |values: Vec<f32>, shape: Vec<usize>| {
            B::float_from_data(TensorData::new(values, shape), &device)
        };
        for (node, g) in [
            (node_x, tensor(dx, s.shape)),
            (node_gamma, tensor(dgamma, vec![l.c])),
            (node_beta, tensor(dbeta, vec![l.c])),
        ] {
            if let Some(node) = node {
                grads.register::<B>(node.id, g);
            }
        }
    }
}
