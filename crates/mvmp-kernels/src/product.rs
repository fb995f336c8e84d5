//! The weight times each batch item's channels-first input, `w [Co, K] . x[b] [K, P]`, in training on
//! flex as one operation with its own backward: every convolution that training runs as a product
//! (a pointwise one on its input, the others on their columns) ends in it.
//!
//! Flex's matmul allocates its output as a zeroed byte buffer and then copies it into one aligned for
//! any element type (`FlexTensor::empty`), so every product's output was written three times; in a
//! `perf` profile of the tiny HRNet's forward and backward those zeroing and copying passes took about a
//! tenth of the samples, as much as half its GEMM time. Autodiff's backward of the broadcast weight
//! also produced a gradient per batch item and summed them. Here the output and both gradients are
//! written once, straight by the GEMM, over tiles of positions that run in parallel: the forward's
//! and the input gradient's tiles write disjoint columns, and the weight's gradient sums a fixed
//! number of chunks of tiles, each in order, then the chunks in order, so that it does not depend on
//! the number of threads.
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

/// Positions per tile: one tile's GEMM is large enough to keep the microkernel busy and small enough
/// for a batch of one to spread over the cores.
const TILE: usize = 512;
/// Chunks of tiles whose weight gradients are summed on their own, then in order.
const CHUNKS: usize = 8;

static FUSED_PRODUCT: AtomicBool = AtomicBool::new(true);

/// Whether training on flex takes this operation (the default) or burn's batched matmul;
/// process-wide, so that a benchmark can time both.
pub fn set_fused_product(on: bool) {
    FUSED_PRODUCT.store(on, Ordering::Relaxed);
}

/// `w [Co, K]` times each `x[b] [K, P]` -> `[B, Co, P]`: in training on flex one operation (see the
/// module's notes), elsewhere burn's matmul with the weight broadcast.
pub fn weight_product(w: Tensor<2>, x: Tensor<3>) -> Tensor<3> {
    let fused =
        x.is_autodiff() && x.device() == Device::flex() && FUSED_PRODUCT.load(Ordering::Relaxed);
    if !fused {
        let [co, k] = w.dims();
        return w.reshape([1, co, k]).matmul(x);
    }
    Tensor::from_dispatch(<Dispatch as ProductBackend>::weight_product(
        w.into_dispatch(),
        x.into_dispatch(),
    ))
}

/// The backend side of [`weight_product`]; autodiff adds the backward.
#[backend_extension(Flex, Autodiff)]
pub trait ProductBackend: Backend {
    fn weight_product(w: FloatTensor<Self>, x: FloatTensor<Self>) -> FloatTensor<Self> {
        let device = x.device();
        let [co, k]: [usize; 2] = dims(&w);
        let [b, kx, p]: [usize; 3] = dims(&x);
        assert_eq!(
            k, kx,
            "weight_product: the weight's {k} columns against {kx} input rows"
        );
        let y = forward_host(
            &HostF32::read::<Self>(w),
            &HostF32::read::<Self>(x),
            [b, co, k, p],
        );
        Self::float_from_data(TensorData::new(y, [b, co, p]), &device)
    }
}

impl ProductBackend for Flex {}

impl<B: Backend + ProductBackend, C: CheckpointStrategy> ProductBackend for Autodiff<B, C> {
    fn weight_product(w: FloatTensor<Self>, x: FloatTensor<Self>) -> FloatTensor<Self> {
        let guards = [w.node(), x.node()];
        let (w, x) = (w.into_primitive(), x.into_primitive());
        let y = B::weight_product(w.clone(), x.clone());
        match ProductBackward
            .prepare::<C>(guards)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((w, x), y),
            OpsKind::UnTracked(prep) => prep.finish(y),
        }
    }
}

#[derive(Debug)]
struct ProductBackward;

impl<B: Backend> Backward<B, 2> for ProductBackward {
    /// The weight and the input.
    type State = (FloatTensor<B>, FloatTensor<B>);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dy = grads.consume::<B>(&ops.node);
        let [node_w, node_x] = ops.parents;
        let (w, x) = ops.state;
        let device = dy.device();
        let [co, k]: [usize; 2] = dims(&w);
        let [b, _, p]: [usize; 3] = dims(&x);
        let shape = [b, co, k, p];
        let dy = HostF32::read::<B>(dy);
        if let Some(node) = node_w {
            let dw = weight_gradient(&HostF32::read::<B>(x), &dy, shape);
            let dw = B::float_from_data(TensorData::new(dw, [co, k]), &device);
            grads.register::<B>(node.id, dw);
        }
        if let Some(node) = node_x {
            let dx = input_gradient(&HostF32::read::<B>(w), &dy, shape);
            let dx = B::float_from_data(TensorData::new(dx, [b, k, p]), &device);
            grads.register::<B>(node.id, dx);
        }
    }
}

/// The tiles of `b` items of `p` positions: (item, first position, positions).
fn tiles(b: usize, p: usize) -> Vec<(usize, usize, usize)> {
    (0..b)
        .flat_map(|bi| (0..p).step_by(TILE).map(move |s| (bi, s, TILE.min(p - s))))
        .collect()
}

/// A matrix in memory: its first element and the distances between rows and between columns.
#[derive(Clone, Copy)]
pub(crate) struct Mat {
    pub ptr: *const f32,
    pub row: isize,
    pub col: isize,
}

impl Mat {
    /// The matrix that starts at `v`'s first value, rows `row` and columns `col` apart.
    pub fn at(v: &[f32], row: usize, col: usize) -> Mat {
        Mat {
            ptr: v.as_ptr(),
            row: row as isize,
            col: col as isize,
        }
    }
}

// SAFETY: a `Mat` is only read through, and only while the slice it was made from is borrowed.
unsafe impl Send for Mat {}
unsafe impl Sync for Mat {}

/// `dst [m, n] (+)= lhs [m, kk] . rhs [kk, n]`, `dst` rows `dst_row` apart; adds to `dst` if `add`.
///
/// # Safety
/// `lhs` and `rhs` must be valid for the reads their strides describe, `dst` for writes of `m` rows of
/// `n` values `dst_row` apart (and reads too if `add`) that nothing else accesses meanwhile.
#[allow(clippy::too_many_arguments)]
pub(crate) unsafe fn gemm(
    dst: *mut f32,
    dst_row: usize,
    add: bool,
    lhs: Mat,
    rhs: Mat,
    m: usize,
    kk: usize,
    n: usize,
) {
    // SAFETY: the caller vouches for every pointer and extent.
    unsafe {
        gemm::gemm(
            m,
            n,
            kk,
            dst,
            1,
            dst_row as isize,
            add,
            lhs.ptr,
            lhs.col,
            lhs.row,
            rhs.ptr,
            rhs.col,
            rhs.row,
            1.0,
            1.0,
            false,
            false,
            false,
            gemm::Parallelism::None,
        );
    }
}

/// A buffer of `n` floats that `write` fills in full through the pointer it is given.
///
/// # Safety
/// `write` must write every one of the `n` values (it may not read any): this saves a zeroing pass
/// over outputs that are mostly megabytes.
pub(crate) unsafe fn written(n: usize, write: impl FnOnce(SendPtr)) -> Vec<f32> {
    let mut v: Vec<f32> = Vec::with_capacity(n);
    write(SendPtr(v.spare_capacity_mut().as_mut_ptr().cast()));
    // SAFETY: the caller has written all `n` values.
    unsafe { v.set_len(n) };
    v
}

/// `y[b] = w . x[b]` for `[b, co, k, p]`.
fn forward_host(w: &[f32], x: &[f32], [b, co, k, p]: [usize; 4]) -> Vec<f32> {
    assert!(w.len() == co * k && x.len() == b * k * p);
    let w = Mat::at(w, k, 1);
    left_product(w, [co, k], x, [b, p])
}

/// `dx[b] = w^T . dy[b]` for `[b, co, k, p]`.
fn input_gradient(w: &[f32], dy: &[f32], [b, co, k, p]: [usize; 4]) -> Vec<f32> {
    assert!(w.len() == co * k && dy.len() == b * co * p);
    let w_t = Mat::at(w, 1, k);
    left_product(w_t, [k, co], dy, [b, p])
}

/// `dst[b] [m, p] = lhs [m, kk] . src[b] [kk, p]` for `b` items, over tiles of positions in parallel.
fn left_product(lhs: Mat, [m, kk]: [usize; 2], src: &[f32], [b, p]: [usize; 2]) -> Vec<f32> {
    assert_eq!(src.len(), b * kk * p);
    if kk == 0 {
        return vec![0f32; b * m * p];
    }
    let write = |dst: SendPtr| {
        tiles(b, p).into_par_iter().for_each(|(bi, s, t)| {
            let rhs = Mat::at(&src[bi * kk * p + s..], p, 1);
            // SAFETY: each tile writes columns s..s + t of item bi's rows, which no other tile
            // writes; the tiles cover every position of every item. `lhs` is the caller's `m x kk`.
            unsafe { gemm(dst.get().add(bi * m * p + s), p, false, lhs, rhs, m, kk, t) };
        })
    };
    // SAFETY: the tiles write all of it (above), without reading (`add = false`).
    unsafe { written(b * m * p, write) }
}

/// `dw = sum over b of dy[b] . x[b]^T` for `[b, co, k, p]`: a fixed number of chunks of tiles, each
/// summed in order, then the chunks in order.
fn weight_gradient(x: &[f32], dy: &[f32], [b, co, k, p]: [usize; 4]) -> Vec<f32> {
    assert!(x.len() == b * k * p && dy.len() == b * co * p);
    let tiles = tiles(b, p);
    let per_chunk = tiles.len().div_ceil(CHUNKS).max(1);
    let partial = |chunk: &[(usize, usize, usize)]| {
        let mut dw = vec![0f32; co * k];
        for &(bi, s, t) in chunk {
            let lhs = Mat::at(&dy[bi * co * p + s..], p, 1);
            let rhs = Mat::at(&x[bi * k * p + s..], 1, p);
            // SAFETY: `dw` is this chunk's own; the tile's reads lie within item bi's rows.
            unsafe { gemm(dw.as_mut_ptr(), k, true, lhs, rhs, co, t, k) };
        }
        dw
    };
    let sums: Vec<Vec<f32>> = tiles.par_chunks(per_chunk).map(partial).collect();
    let mut sums = sums.into_iter();
    let mut dw = sums.next().unwrap_or_else(|| vec![0f32; co * k]);
    for s in sums {
        dw.iter_mut().zip(&s).for_each(|(a, b)| *a += b);
    }
    dw
}
