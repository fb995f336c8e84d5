//! The columns of a 2D or 3D convolution as a product (im2col) on flex, with a backward that adds each
//! column back into the input it was copied from (col2im) in one pass. A 2D input is a 3D one of depth 1.
//!
//! As tensor ops (`conv::product` on other backends) the columns are a pad, one strided slice per
//! kernel tap and a concatenation, and autodiff's backward of them makes a zero tensor the size of the
//! padded input for every tap, assigns the tap's gradient into it and adds them all. Here the forward
//! copies every output position's taps from the channels-last input, and the backward scatters them
//! back: each batch item into its own gradient, in parallel, so the sums run in one order whatever the
//! number of threads.
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Tensor, TensorData};

use crate::host::{dims, read_f32, transpose_planes};

static FUSED_IM2COL: AtomicBool = AtomicBool::new(true);

/// Whether training on flex builds a product convolution's columns with this operation (the default)
/// or with tensor ops; process-wide, so that a benchmark can time both.
pub fn set_fused_im2col(on: bool) {
    FUSED_IM2COL.store(on, Ordering::Relaxed);
}

/// See [`set_fused_im2col`].
pub fn fused_im2col() -> bool {
    FUSED_IM2COL.load(Ordering::Relaxed)
}

/// The shape of a convolution's columns over three spatial axes (a 2D convolution: depth 1): kernel,
/// stride, the padding before each axis (what lies past the end follows from the output size) and the
/// output size.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Columns {
    pub kernel: [usize; 3],
    pub stride: [usize; 3],
    pub pad: [usize; 3],
    pub out: [usize; 3],
}

impl Columns {
    fn taps(&self) -> usize {
        self.kernel.iter().product()
    }

    fn outputs(&self) -> usize {
        self.out.iter().product()
    }

    /// The input position (flat over `size`) that output `o` (flat) reads at tap `t` (flat), or `None`
    /// in the padding.
    #[inline(always)]
    fn source(&self, size: [usize; 3], o: usize, t: usize) -> Option<usize> {
        let [_, oh, ow] = self.out;
        let [_, kh, kw] = self.kernel;
        let (o, k) = (
            [o / (oh * ow), o / ow % oh, o % ow],
            [t / (kh * kw), t / kw % kh, t % kw],
        );
        let mut flat = 0;
        for a in 0..3 {
            let i = (o[a] * self.stride[a] + k[a])
                .checked_sub(self.pad[a])
                .filter(|&i| i < size[a])?;
            flat = flat * size[a] + i;
        }
        Some(flat)
    }
}

/// `x [B, C, D, H, W]` -> `[B * Do * Ho * Wo, kd * kh * kw * C]`: row `(b, od, oy, ox)` holds the
/// zero-padded input's taps in the order `(kd, kh, kw, c)` (the weight's `[Co, kd, kh, kw, Ci]`).
pub fn columns(x: Tensor<5>, geometry: Columns) -> Tensor<2> {
    Tensor::from_dispatch(<Dispatch as Im2colBackend>::im2col(
        x.into_dispatch(),
        geometry,
    ))
}

/// The backend side of [`columns`]: a host pass on any backend whose tensors can be read on the host;
/// autodiff adds the col2im backward.
#[backend_extension(Flex, Autodiff)]
pub trait Im2colBackend: Backend {
    fn im2col(x: FloatTensor<Self>, geometry: Columns) -> FloatTensor<Self> {
        let device = x.device();
        let dims = dims(&x);
        let cols = forward_host(&read_f32::<Self>(x), dims, &geometry);
        let shape = [dims[0] * geometry.outputs(), geometry.taps() * dims[1]];
        Self::float_from_data(TensorData::new(cols, shape), &device)
    }
}

impl Im2colBackend for Flex {}

impl<B: Backend + Im2colBackend, C: CheckpointStrategy> Im2colBackend for Autodiff<B, C> {
    fn im2col(x: FloatTensor<Self>, geometry: Columns) -> FloatTensor<Self> {
        let guards = [x.node()];
        let x = x.into_primitive();
        let dims = dims(&x);
        let out = B::im2col(x, geometry);
        // The state is two shapes: nothing a checkpointing strategy could save by recomputing.
        match Col2im.prepare::<C>(guards).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish((dims, geometry), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

#[derive(Debug)]
struct Col2im;

impl<B: Backend> Backward<B, 1> for Col2im {
    type State = ([usize; 5], Columns);

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let [parent] = ops.parents;
        let Some(node) = parent else { return };
        let (dims, geometry) = ops.state;
        let device = grad.device();
        let dx = backward_host(&read_f32::<B>(grad), dims, &geometry);
        grads.register::<B>(
            node.id,
            B::float_from_data(TensorData::new(dx, dims), &device),
        );
    }
}

fn forward_host(x: &[f32], [b, c, d, h, w]: [usize; 5], g: &Columns) -> Vec<f32> {
    use rayon::prelude::*;
    let size = d * h * w;
    let last = transpose_planes(x, b, c, size); // [B][P][C]
    let (taps, outputs) = (g.taps(), g.outputs());
    let width = taps * c;
    let mut cols = vec![0f32; b * outputs * width];
    // Chunks of a whole number of rows of one batch item.
    let rows = g.out[2].max(1);
    cols.par_chunks_mut(rows * width)
        .enumerate()
        .for_each(|(chunk, dst)| {
            let bi = chunk * rows / outputs;
            let src = &last[bi * size * c..(bi + 1) * size * c];
            for (r, row) in dst.chunks_exact_mut(width).enumerate() {
                let o = (chunk * rows + r) % outputs;
                for (t, tap) in row.chunks_exact_mut(c).enumerate() {
                    if let Some(p) = g.source([d, h, w], o, t) {
                        tap.copy_from_slice(&src[p * c..(p + 1) * c]);
                    }
                }
            }
        });
    cols
}

fn backward_host(grad: &[f32], [b, c, d, h, w]: [usize; 5], g: &Columns) -> Vec<f32> {
    use rayon::prelude::*;
    let size = d * h * w;
    let width = g.taps() * c;
    let outputs = g.outputs();
    let mut acc = vec![0f32; b * size * c]; // [B][P][C]
    acc.par_chunks_mut(size * c)
        .enumerate()
        .for_each(|(bi, acc)| {
            let rows = &grad[bi * outputs * width..(bi + 1) * outputs * width];
            for (o, row) in rows.chunks_exact(width).enumerate() {
                for (t, tap) in row.chunks_exact(c).enumerate() {
                    if let Some(p) = g.source([d, h, w], o, t) {
                        let a = &mut acc[p * c..(p + 1) * c];
                        a.iter_mut().zip(tap).for_each(|(a, t)| *a += t);
                    }
                }
            }
        });
    transpose_planes(&acc, b, size, c)
}
