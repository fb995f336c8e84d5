//! The columns of a 2D or 3D convolution as a product (im2col) on flex, with a backward that adds each
//! column back into the input it was copied from (col2im) in one pass. A 2D input is a 3D one of depth 1.
//! Training multiplies them by the weight in the same operation ([`crate::product`]); [`columns`] is the
//! columns alone.
//!
//! As tensor ops (`conv::product` on other backends) the columns are a pad, one strided slice per
//! kernel tap and a concatenation, and autodiff's backward of them makes a zero tensor the size of the
//! padded input for every tap, assigns the tap's gradient into it and adds them all. Here the forward
//! copies every output position's taps from the channels-last input, and the backward gathers them
//! back: every input position sums the taps that read it, positions in parallel, so the sums run in one
//! order whatever the number of threads or the batch size.
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Tensor, TensorData};

use crate::host::{HostF32, dims, transpose_planes};

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
    pub(crate) fn taps(&self) -> usize {
        self.kernel.iter().product()
    }

    pub(crate) fn outputs(&self) -> usize {
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

    /// The output position (flat) whose tap `t` (flat) reads input position `p` (flat over `size`), if
    /// any: the inverse of [`Self::source`].
    #[inline(always)]
    fn target(&self, size: [usize; 3], p: usize, t: usize) -> Option<usize> {
        let [_, h, w] = size;
        let [_, kh, kw] = self.kernel;
        let (p, k) = (
            [p / (h * w), p / w % h, p % w],
            [t / (kh * kw), t / kw % kh, t % kw],
        );
        let mut flat = 0;
        for a in 0..3 {
            let at = (p[a] + self.pad[a]).checked_sub(k[a])?;
            let o = at / self.stride[a];
            if at % self.stride[a] != 0 || o >= self.out[a] {
                return None;
            }
            flat = flat * self.out[a] + o;
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
        host_columns::<Self>(x, &geometry)
    }
}

/// The columns as a tensor of `x`'s backend, `[B * Do * Ho * Wo, taps * C]`, built on the host.
pub(crate) fn host_columns<B: Backend>(x: FloatTensor<B>, g: &Columns) -> FloatTensor<B> {
    let device = x.device();
    let dims = dims(&x);
    let cols = forward_host(&HostF32::read::<B>(x), dims, g);
    let shape = [dims[0] * g.outputs(), g.taps() * dims[1]];
    B::float_from_data(TensorData::new(cols, shape), &device)
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
        let dx = backward_host(&HostF32::read::<B>(grad), dims, &geometry);
        grads.register::<B>(
            node.id,
            B::float_from_data(TensorData::new(dx, dims), &device),
        );
    }
}

pub(crate) fn forward_host(x: &[f32], [b, c, d, h, w]: [usize; 5], g: &Columns) -> Vec<f32> {
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

/// The columns' gradient added back onto the input: gathered per input position (the taps that read
/// it, in the order of their output positions), so that positions run in parallel whatever the batch
/// size and every sum is taken in one order.
pub(crate) fn backward_host(grad: &[f32], [b, c, d, h, w]: [usize; 5], g: &Columns) -> Vec<f32> {
    use rayon::prelude::*;
    let size = d * h * w;
    let (taps, outputs) = (g.taps(), g.outputs());
    let width = taps * c;
    let mut acc = vec![0f32; b * size * c]; // [B][P][C]
    // Chunks of one row of positions of one batch item.
    let rows = w.max(1);
    acc.par_chunks_mut(rows * c)
        .enumerate()
        .for_each(|(chunk, dst)| {
            let bi = chunk * rows / size;
            let grad = &grad[bi * outputs * width..(bi + 1) * outputs * width];
            for (r, acc) in dst.chunks_exact_mut(c).enumerate() {
                let p = (chunk * rows + r) % size;
                // Taps from the last: their output positions ascend.
                for t in (0..taps).rev() {
                    if let Some(o) = g.target([d, h, w], p, t) {
                        let tap = &grad[o * width + t * c..o * width + (t + 1) * c];
                        acc.iter_mut().zip(tap).for_each(|(a, t)| *a += t);
                    }
                }
            }
        });
    transpose_planes(&acc, b, size, c)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The backward as the plain scatter it inverts: every column's tap added onto the input position
    /// it read, output positions in order.
    fn scatter(grad: &[f32], [b, c, d, h, w]: [usize; 5], g: &Columns) -> Vec<f32> {
        let (size, width) = (d * h * w, g.taps() * c);
        let mut acc = vec![0f32; b * size * c];
        for bi in 0..b {
            for o in 0..g.outputs() {
                for t in 0..g.taps() {
                    if let Some(p) = g.source([d, h, w], o, t) {
                        for ch in 0..c {
                            acc[(bi * size + p) * c + ch] +=
                                grad[(bi * g.outputs() + o) * width + t * c + ch];
                        }
                    }
                }
            }
        }
        transpose_planes(&acc, b, size, c)
    }

    /// The gathered backward is the scatter bit for bit (the same sums in the same order), for strides
    /// 1 and 2, padding, and kernels of one and three taps per axis.
    #[test]
    fn the_gathered_backward_is_the_scatter_bit_for_bit() {
        let cases = [
            ([2, 3, 4, 5, 6], [3, 3, 3], [1, 1, 1], [1, 1, 1]),
            ([1, 4, 5, 7, 6], [3, 3, 3], [2, 2, 2], [1, 1, 1]),
            ([3, 2, 1, 9, 8], [1, 3, 3], [1, 2, 1], [0, 1, 1]),
            ([1, 5, 2, 4, 4], [1, 1, 1], [1, 1, 1], [0, 0, 0]),
        ];
        for (dims, kernel, stride, pad) in cases {
            let [b, c, d, h, w] = dims;
            let mut out = [0; 3];
            for (a, n) in [d, h, w].into_iter().enumerate() {
                out[a] = (n + 2 * pad[a] - kernel[a]) / stride[a] + 1;
            }
            let g = Columns {
                kernel,
                stride,
                pad,
                out,
            };
            let n = b * g.outputs() * g.taps() * c;
            // Values of many magnitudes, so that a different order of the sums would show.
            let grad: Vec<f32> = (0..n)
                .map(|i| ((i * 7919 % 1013) as f32 - 506.0) * 10f32.powi((i % 7) as i32 - 3))
                .collect();
            assert_eq!(
                backward_host(&grad, dims, &g),
                scatter(&grad, dims, &g),
                "{dims:?} {g:?}"
            );
        }
    }
}
