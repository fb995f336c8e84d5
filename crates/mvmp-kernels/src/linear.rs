//! A linear layer, `x [.., K] . w [K, N] + b [N]`, in training on flex as one operation with its own
//! backward: the ViT's and the decoder's layers end in it.
//!
//! Burn's linear is a broadcast matmul and an addition of the bias: its output is written three times
//! (flex's matmul output, zeroed and then copied into an aligned buffer, then the bias's sum), and
//! autodiff's backward of the broadcast weight makes a gradient per batch item and sums them, with the
//! bias's gradient summed in another pass. Here the output starts as the bias, tile by tile in cache,
//! and the GEMM adds to it; the input's gradient is written once; the weight's and the bias's are summed
//! over a fixed number of chunks of rows, each in order, then the chunks in order, so that their bits
//! do not depend on the number of threads.
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use crate::cpu::SendPtr;
use crate::host::{HostF32, dims};
use crate::product::{Mat, gemm, written};

/// Rows per tile of the forward and the input gradient.
const TILE: usize = 128;
/// Chunks of rows whose weight and bias gradients are summed on their own, then in order.
const CHUNKS: usize = 8;

static FUSED_LINEAR: AtomicBool = AtomicBool::new(true);

/// Whether training on flex takes this operation (the default) or burn's linear; process-wide, so
/// that a benchmark can time both.
pub fn set_fused_linear(on: bool) {
    FUSED_LINEAR.store(on, Ordering::Relaxed);
}

/// `x . weight + bias` over the last axis of `x` (`weight [K, N]`, as `burn::nn::Linear` keeps it): in
/// training on flex one operation (see the module's notes), elsewhere burn's linear.
pub fn linear<const D: usize>(
    x: Tensor<D>,
    weight: Tensor<2>,
    bias: Option<Tensor<1>>,
) -> Tensor<D> {
    let fused =
        x.is_autodiff() && x.device() == Device::flex() && FUSED_LINEAR.load(Ordering::Relaxed);
    if !fused {
        return burn::tensor::module::linear(x, weight, bias);
    }
    let shape = x.dims();
    let [k, n] = weight.dims();
    let rows = shape[..D - 1].iter().product();
    // A missing bias is a constant zero: autodiff does not track it, so no gradient is summed for it.
    let bias = bias.unwrap_or_else(|| Tensor::zeros([n], &x.device()));
    let y = <Dispatch as LinearBackend>::fused_linear(
        x.reshape([rows, k]).into_dispatch(),
        weight.into_dispatch(),
        bias.into_dispatch(),
    );
    let mut out = shape;
    out[D - 1] = n;
    Tensor::<2>::from_dispatch(y).reshape(out)
}

/// `burn::nn::Linear::forward` through [`linear`].
pub fn linear_layer<const D: usize>(layer: &burn::nn::Linear, x: Tensor<D>) -> Tensor<D> {
    linear(x, layer.weight.val(), layer.bias.as_ref().map(|b| b.val()))
}

/// The backend side of [`linear`]; autodiff adds the backward.
#[backend_extension(Flex, Autodiff)]
pub trait LinearBackend: Backend {
    fn fused_linear(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let device = x.device();
        let [r, k]: [usize; 2] = dims(&x);
        let [kw, n]: [usize; 2] = dims(&w);
        assert_eq!(
            k, kw,
            "linear: {k} input features against a weight of {kw} rows"
        );
        assert_eq!(dims::<1>(&b), [n], "linear: the bias against {n} outputs");
        let x = HostF32::read::<Self>(x);
        let y = forward_host(
            &x,
            &HostF32::read::<Self>(w),
            &HostF32::read::<Self>(b),
            [r, k, n],
        );
        Self::float_from_data(TensorData::new(y, [r, n]), &device)
    }
}

impl LinearBackend for Flex {}

impl<B: Backend + LinearBackend, C: CheckpointStrategy> LinearBackend for Autodiff<B, C> {
    fn fused_linear(
        x: FloatTensor<Self>,
        w: FloatTensor<Self>,
        b: FloatTensor<Self>,
    ) -> FloatTensor<Self> {
        let guards = [x.node(), w.node(), b.node()];
        let (x, w, b) = (x.into_primitive(), w.into_primitive(), b.into_primitive());
        let y = B::fused_linear(x.clone(), w.clone(), b);
        match LinearBackward
            .prepare::<C>(guards)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((x, w), y),
            OpsKind::UnTracked(prep) => prep.finish(y),
        }
    }
}

#[derive(Debug)]
struct LinearBackward;

impl<B: Backend> Backward<B, 3> for LinearBackward {
    /// The input and the weight.
    type State = (FloatTensor<B>, FloatTensor<B>);

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dy = grads.consume::<B>(&ops.node);
        let [node_x, node_w, node_b] = ops.parents;
        let (x, w) = ops.state;
        let device = dy.device();
        let [r, k]: [usize; 2] = dims(&x);
        let [_, n]: [usize; 2] = dims(&w);
        let dy = HostF32::read::<B>(dy);
        if node_w.is_some() || node_b.is_some() {
            let (dw, db) = parameter_gradients(&HostF32::read::<B>(x), &dy, [r, k, n]);
            if let Some(node) = node_w {
                let dw = B::float_from_data(TensorData::new(dw, [k, n]), &device);
                grads.register::<B>(node.id, dw);
            }
            if let Some(node) = node_b {
                let db = B::float_from_data(TensorData::new(db, [n]), &device);
                grads.register::<B>(node.id, db);
            }
        }
        if let Some(node) = node_x {
            let dx = input_gradient(&HostF32::read::<B>(w), &dy, [r, k, n]);
            let dx = B::float_from_data(TensorData::new(dx, [r, k]), &device);
            grads.register::<B>(node.id, dx);
        }
    }
}

/// The tiles of `r` rows: (first row, rows).
fn tiles(r: usize) -> Vec<(usize, usize)> {
    (0..r).step_by(TILE).map(|s| (s, TILE.min(r - s))).collect()
}

/// `y = x . w + b` for `x [r, k]`, `w [k, n]`.
fn forward_host(x: &[f32], w: &[f32], b: &[f32], [r, k, n]: [usize; 3]) -> Vec<f32> {
    assert!(x.len() == r * k && w.len() == k * n && b.len() == n);
    let write = |dst: SendPtr| {
        tiles(r).into_par_iter().for_each(|(s, t)| {
            let rows = dst.get().wrapping_add(s * n);
            for i in 0..t {
                // SAFETY: each tile writes its own rows s..s + t; the tiles cover every row.
                unsafe { std::ptr::copy_nonoverlapping(b.as_ptr(), rows.add(i * n), n) };
            }
            if k > 0 {
                let lhs = Mat::at(&x[s * k..], k, 1);
                // SAFETY: the tile's rows, just written, and reads within x's rows s..s + t.
                unsafe { gemm(rows, n, true, lhs, Mat::at(w, n, 1), t, k, n) };
            }
        })
    };
    // SAFETY: every row is first written with the bias (above), then added to.
    unsafe { written(r * n, write) }
}

/// `dx = dy . w^T` for `dy [r, n]`, `w [k, n]`.
fn input_gradient(w: &[f32], dy: &[f32], [r, k, n]: [usize; 3]) -> Vec<f32> {
    assert!(w.len() == k * n && dy.len() == r * n);
    if n == 0 {
        return vec![0f32; r * k];
    }
    let w_t = Mat::at(w, 1, n);
    let write = |dst: SendPtr| {
        tiles(r).into_par_iter().for_each(|(s, t)| {
            let lhs = Mat::at(&dy[s * n..], n, 1);
            // SAFETY: each tile writes rows s..s + t alone, without reading; the tiles cover all rows.
            unsafe { gemm(dst.get().add(s * k), k, false, lhs, w_t, t, n, k) };
        })
    };
    // SAFETY: the tiles write every value (above).
    unsafe { written(r * k, write) }
}

/// `dw = x^T . dy` and `db = the column sums of dy`, over [`CHUNKS`] chunks of rows, each summed in
/// order, then the chunks in order.
fn parameter_gradients(x: &[f32], dy: &[f32], [r, k, n]: [usize; 3]) -> (Vec<f32>, Vec<f32>) {
    assert!(x.len() == r * k && dy.len() == r * n);
    let per_chunk = r.div_ceil(CHUNKS).max(1);
    let partial = |s: usize| {
        let t = per_chunk.min(r - s);
        let mut dw = vec![0f32; k * n];
        let lhs = Mat::at(&x[s * k..], 1, k);
        // SAFETY: `dw` is this chunk's own; the reads lie within rows s..s + t of x and dy.
        unsafe {
            gemm(
                dw.as_mut_ptr(),
                n,
                true,
                lhs,
                Mat::at(&dy[s * n..], n, 1),
                k,
                t,
                n,
            )
        };
        let mut db = vec![0f32; n];
        for row in dy[s * n..(s + t) * n].chunks_exact(n.max(1)) {
            db.iter_mut().zip(row).for_each(|(a, v)| *a += v);
        }
        (dw, db)
    };
    let starts: Vec<usize> = (0..r).step_by(per_chunk).collect();
    let sums: Vec<(Vec<f32>, Vec<f32>)> = starts.into_par_iter().map(partial).collect();
    let mut dw = vec![0f32; k * n];
    let mut db = vec![0f32; n];
    for (w, b) in sums {
        dw.iter_mut().zip(&w).for_each(|(a, v)| *a += v);
        db.iter_mut().zip(&b).for_each(|(a, v)| *a += v);
    }
    (dw, db)
}
