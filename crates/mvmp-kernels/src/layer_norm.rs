//! Layer normalisation over the last axis in training on flex, one host pass each way.
//!
//! Autodiff runs burn's layer norm as its decomposition (two means, a subtraction, a square root, a
//! division, the scale and the shift), each a pass with its own output, and about twice as many passes
//! back; the ViT normalises every block's tokens twice. Here a row's mean and inverse deviation are
//! computed once, in cache, and kept for the backward:
//! `dx = r (g - mean(g) - xhat mean(g xhat))` with `g = dy gamma`, `xhat = (x - mean) r`. The scale's
//! and shift's gradients are summed over a fixed number of chunks of rows, each in order, then the
//! chunks in order, so their bits do not depend on the number of threads.
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::nn::LayerNorm;
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use crate::host::{HostF32, dims, par_filled, par_zeroed};

/// Rows per parallel task.
const ROWS: usize = 64;
/// Chunks of rows whose scale and shift gradients are summed on their own, then in order.
const CHUNKS: usize = 8;

static FUSED_LAYER_NORM: AtomicBool = AtomicBool::new(true);

/// Whether training on flex takes this operation (the default) or burn's layer norm; process-wide,
/// so that a benchmark can time both.
pub fn set_fused_layer_norm(on: bool) {
    FUSED_LAYER_NORM.store(on, Ordering::Relaxed);
}

/// `norm` applied to `x` with its epsilon `eps` (burn's `LayerNorm` keeps its own private, so the
/// caller passes the one it configured): in training on flex one operation, elsewhere burn's.
pub fn layer_norm<const D: usize>(norm: &LayerNorm, x: Tensor<D>, eps: f64) -> Tensor<D> {
    let fused =
        x.is_autodiff() && x.device() == Device::flex() && FUSED_LAYER_NORM.load(Ordering::Relaxed);
    let beta = norm.beta.as_ref().map(|b| b.val());
    if !fused {
        return burn::tensor::module::layer_norm(x, norm.gamma.val(), beta, eps);
    }
    let shape = x.dims();
    let c = shape[D - 1];
    let rows = shape[..D - 1].iter().product();
    // A missing shift is a constant zero: autodiff does not track it, so no gradient is summed for it.
    let beta = beta.unwrap_or_else(|| Tensor::zeros([c], &x.device()));
    let y = <Dispatch as LayerNormBackend>::fused_layer_norm(
        x.reshape([rows, c]).into_dispatch(),
        norm.gamma.val().into_dispatch(),
        beta.into_dispatch(),
        eps,
    );
    Tensor::<2>::from_dispatch(y).reshape(shape)
}

/// The backend side of [`layer_norm`]; autodiff adds the backward.
#[backend_extension(Flex, Autodiff)]
pub trait LayerNormBackend: Backend {
    fn fused_layer_norm(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        eps: f64,
    ) -> FloatTensor<Self> {
        let device = x.device();
        let [r, c]: [usize; 2] = dims(&x);
        let (gamma, beta) = (HostF32::read::<Self>(gamma), HostF32::read::<Self>(beta));
        let (y, _) = forward_host(&HostF32::read::<Self>(x), &gamma, &beta, c, eps as f32);
        Self::float_from_data(TensorData::new(y, [r, c]), &device)
    }
}

impl LayerNormBackend for Flex {}

impl<B: Backend + LayerNormBackend, C: CheckpointStrategy> LayerNormBackend for Autodiff<B, C> {
    fn fused_layer_norm(
        x: FloatTensor<Self>,
        gamma: FloatTensor<Self>,
        beta: FloatTensor<Self>,
        eps: f64,
    ) -> FloatTensor<Self> {
        let guards = [x.node(), gamma.node(), beta.node()];
        let (x, gamma, beta) = (
            x.into_primitive(),
            gamma.into_primitive(),
            beta.into_primitive(),
        );
        let device = x.device();
        let [r, c]: [usize; 2] = dims(&x);
        let host_x = HostF32::read::<B>(x.clone());
        let host_gamma = HostF32::read::<B>(gamma.clone());
        let (y, stats) = forward_host(
            &host_x,
            &host_gamma,
            &HostF32::read::<B>(beta),
            c,
            eps as f32,
        );
        let y = B::float_from_data(TensorData::new(y, [r, c]), &device);
        match LayerNormBackward
            .prepare::<C>(guards)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((x, gamma, stats), y),
            OpsKind::UnTracked(prep) => prep.finish(y),
        }
    }
}

#[derive(Debug)]
struct LayerNormBackward;

impl<B: Backend> Backward<B, 3> for LayerNormBackward {
    /// The input, the scale, and each row's mean and inverse deviation.
    type State = (FloatTensor<B>, FloatTensor<B>, Vec<[f32; 2]>);

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dy = grads.consume::<B>(&ops.node);
        let [node_x, node_gamma, node_beta] = ops.parents;
        let (x, gamma, stats) = ops.state;
        let device = dy.device();
        let [r, c]: [usize; 2] = dims(&x);
        let (x, dy) = (HostF32::read::<B>(x), HostF32::read::<B>(dy));
        if node_gamma.is_some() || node_beta.is_some() {
            let (dgamma, dbeta) = parameter_gradients(&x, &dy, &stats, c);
            let register = |grads: &mut Gradients, id, g: Vec<f32>| {
                grads.register::<B>(id, B::float_from_data(TensorData::new(g, [c]), &device));
            };
            if let Some(node) = node_gamma {
                register(grads, node.id, dgamma);
            }
            if let Some(node) = node_beta {
                register(grads, node.id, dbeta);
            }
        }
        if let Some(node) = node_x {
            let dx = input_gradient(&x, &HostF32::read::<B>(gamma), &dy, &stats);
            let dx = B::float_from_data(TensorData::new(dx, [r, c]), &device);
            grads.register::<B>(node.id, dx);
        }
    }
}

/// A row's mean and inverse deviation `1 / sqrt(var + eps)` (the biased variance, as burn's).
fn row_stats(row: &[f32], eps: f32) -> [f32; 2] {
    let n = row.len() as f32;
    let mean = row.iter().sum::<f32>() / n;
    let var = row.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / n;
    [mean, 1.0 / (var + eps).sqrt()]
}

/// The normalised, scaled and shifted rows of `x [r, c]`, and each row's statistics.
fn forward_host(
    x: &[f32],
    gamma: &[f32],
    beta: &[f32],
    c: usize,
    eps: f32,
) -> (Vec<f32>, Vec<[f32; 2]>) {
    assert!(gamma.len() == c && beta.len() == c && x.len().is_multiple_of(c.max(1)));
    let mut y = par_zeroed(x.len());
    let mut stats = vec![[0f32; 2]; x.len() / c.max(1)];
    if c == 0 {
        return (y, stats);
    }
    y.par_chunks_mut(ROWS * c)
        .zip(stats.par_chunks_mut(ROWS))
        .zip(x.par_chunks(ROWS * c))
        .for_each(|((y, stats), x)| {
            for ((yr, st), xr) in y.chunks_exact_mut(c).zip(stats).zip(x.chunks_exact(c)) {
                *st = row_stats(xr, eps);
                let [mean, inv] = *st;
                for (((o, &v), &g), &b) in yr.iter_mut().zip(xr).zip(gamma).zip(beta) {
                    *o = (v - mean) * inv * g + b;
                }
            }
        });
    (y, stats)
}

/// `dx` of every row (see the module's notes).
fn input_gradient(x: &[f32], gamma: &[f32], dy: &[f32], stats: &[[f32; 2]]) -> Vec<f32> {
    let c = gamma.len();
    if c == 0 {
        return vec![0f32; x.len()];
    }
    let n = c as f32;
    par_filled(x.len(), ROWS * c, |i, dx| {
        let (x, dy) = (&x[i * ROWS * c..], &dy[i * ROWS * c..]);
        let rows = dx
            .chunks_exact_mut(c)
            .zip(x.chunks_exact(c))
            .zip(dy.chunks_exact(c));
        for (((dxr, xr), dyr), &[mean, inv]) in rows.zip(&stats[i * ROWS..]) {
            let (mut sum_g, mut sum_gx) = (0f32, 0f32);
            for ((&v, &d), &g) in xr.iter().zip(dyr).zip(gamma) {
                let gd = d * g;
                sum_g += gd;
                sum_gx += gd * (v - mean) * inv;
            }
            let (mg, mgx) = (sum_g / n, sum_gx / n);
            for (((o, &v), &d), &g) in dxr.iter_mut().zip(xr).zip(dyr).zip(gamma) {
                *o = inv * (d * g - mg - (v - mean) * inv * mgx);
            }
        }
    })
}

/// A chunk's input and output-gradient rows.
type Rows<'a> = (&'a [f32], &'a [f32]);

/// The scale's gradient `sum dy xhat` and the shift's `sum dy` over the rows, in fixed chunks.
fn parameter_gradients(
    x: &[f32],
    dy: &[f32],
    stats: &[[f32; 2]],
    c: usize,
) -> (Vec<f32>, Vec<f32>) {
    let r = stats.len();
    if c == 0 {
        return (Vec::new(), Vec::new());
    }
    let per_chunk = r.div_ceil(CHUNKS).max(1) * c;
    let partial = |((x, dy), stats): (Rows, &[[f32; 2]])| {
        let (mut dg, mut db) = (vec![0f32; c], vec![0f32; c]);
        let rows = x.chunks_exact(c).zip(dy.chunks_exact(c));
        for ((xr, dyr), &[mean, inv]) in rows.zip(stats) {
            for (((g, b), &v), &d) in dg.iter_mut().zip(db.iter_mut()).zip(xr).zip(dyr) {
                *g += d * (v - mean) * inv;
                *b += d;
            }
        }
        (dg, db)
    };
    let sums: Vec<(Vec<f32>, Vec<f32>)> = x
        .par_chunks(per_chunk)
        .zip(dy.par_chunks(per_chunk))
        .zip(stats.par_chunks(per_chunk / c))
        .map(partial)
        .collect();
    let (mut dg, mut db) = (vec![0f32; c], vec![0f32; c]);
    for (g, b) in sums {
        dg.iter_mut().zip(&g).for_each(|(a, v)| *a += v);
        db.iter_mut().zip(&b).for_each(|(a, v)| *a += v);
    }
    (dg, db)
}
