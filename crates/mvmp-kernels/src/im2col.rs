//! The columns of a 2D convolution as a product (im2col) on flex, with a backward that adds each column
//! back into the input it was copied from (col2im) in one pass.
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

/// The shape of a convolution's columns: kernel and stride `[h, w]`, padding (top, left, bottom,
/// right) and the output size `[h, w]`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Columns {
    pub kernel: [usize; 2],
    pub stride: [usize; 2],
    pub pad: [usize; 4],
    pub out: [usize; 2],
}

/// `x [B, C, H, W]` -> `[B * Ho * Wo, kh * kw * C]`: row `(b, oy, ox)` holds the zero-padded input's
/// taps in the order `(i, j, c)` (the weight's `[Co, kh, kw, Ci]`).
pub fn columns(x: Tensor<4>, geometry: Columns) -> Tensor<2> {
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
        let dims = dims4(&x.shape());
        let cols = forward_host(&host::<Self>(x), dims, &geometry);
        let [b, c, _, _] = dims;
        let [ho, wo] = geometry.out;
        let [kh, kw] = geometry.kernel;
        Self::float_from_data(TensorData::new(cols, [b * ho * wo, kh * kw * c]), &device)
    }
}

impl Im2colBackend for Flex {}

impl<B: Backend + Im2colBackend, C: CheckpointStrategy> Im2colBackend for Autodiff<B, C> {
    fn im2col(x: FloatTensor<Self>, geometry: Columns) -> FloatTensor<Self> {
        let guards = [x.node()];
        let x = x.into_primitive();
        let dims = dims4(&x.shape());
        let out = B::im2col(x, geometry);
        // The state is two shapes: nothing a checkpointing strategy could save by recomputing.
        match Col2im.prepare::<C>(guards).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish((dims, geometry), out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

fn dims4(shape: &burn::tensor::Shape) -> [usize; 4] {
    std::array::from_fn(|i| shape[i])
}

/// A float tensor's values on the host.
fn host<B: Backend>(t: FloatTensor<B>) -> Vec<f32> {
    burn::tensor::try_read_sync(B::float_into_data(t))
        .expect("flex reads synchronously")
        .expect("a readable tensor")
        .convert::<f32>()
        .try_into_vec::<f32>()
        .expect("float32 after conversion")
}

#[derive(Debug)]
struct Col2im;

impl<B: Backend> Backward<B, 1> for Col2im {
    type State = ([usize; 4], Columns);

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let [parent] = ops.parents;
        let Some(node) = parent else { return };
        let (dims, geometry) = ops.state;
        let device = grad.device();
        let dx = backward_host(&host::<B>(grad), dims, &geometry);
        grads.register::<B>(
            node.id,
            B::float_from_data(TensorData::new(dx, dims), &device),
        );
    }
}

/// The input position `(y, x)` that output `(oy, ox)` reads at tap `(i, j)`, or `None` in the padding.
#[inline(always)]
fn source(
    g: &Columns,
    [h, w]: [usize; 2],
    [oy, ox]: [usize; 2],
    [i, j]: [usize; 2],
) -> Option<usize> {
    let y = (oy * g.stride[0] + i)
        .checked_sub(g.pad[0])
        .filter(|&y| y < h)?;
    let x = (ox * g.stride[1] + j)
        .checked_sub(g.pad[1])
        .filter(|&x| x < w)?;
    Some(y * w + x)
}

/// `[B][C][H*W]` <-> `[B][H*W][C]`, batch items in parallel.
fn transpose_items(src: &[f32], b: usize, rows: usize, cols: usize) -> Vec<f32> {
    use rayon::prelude::*;
    let mut dst = vec![0f32; b * rows * cols];
    dst.par_chunks_mut(rows * cols)
        .zip(src.par_chunks(rows * cols))
        .for_each(|(dst, src)| {
            for (r, row) in src.chunks_exact(cols).enumerate() {
                for (k, &v) in row.iter().enumerate() {
                    dst[k * rows + r] = v;
                }
            }
        });
    dst
}

fn forward_host(x: &[f32], [b, c, h, w]: [usize; 4], g: &Columns) -> Vec<f32> {
    use rayon::prelude::*;
    let last = transpose_items(x, b, c, h * w); // [B][H*W][C]
    let ([kh, kw], [ho, wo]) = (g.kernel, g.out);
    let width = kh * kw * c;
    let mut cols = vec![0f32; b * ho * wo * width];
    // One chunk per output row of one batch item.
    cols.par_chunks_mut(wo * width)
        .enumerate()
        .for_each(|(line, dst)| {
            let (bi, oy) = (line / ho, line % ho);
            let src = &last[bi * h * w * c..(bi + 1) * h * w * c];
            for (ox, row) in dst.chunks_exact_mut(width).enumerate() {
                for (t, tap) in row.chunks_exact_mut(c).enumerate() {
                    if let Some(p) = source(g, [h, w], [oy, ox], [t / kw, t % kw]) {
                        tap.copy_from_slice(&src[p * c..(p + 1) * c]);
                    }
                }
            }
        });
    cols
}

fn backward_host(grad: &[f32], [b, c, h, w]: [usize; 4], g: &Columns) -> Vec<f32> {
    use rayon::prelude::*;
    let ([kh, kw], [ho, wo]) = (g.kernel, g.out);
    let width = kh * kw * c;
    let mut acc = vec![0f32; b * h * w * c]; // [B][H*W][C]
    acc.par_chunks_mut(h * w * c)
        .enumerate()
        .for_each(|(bi, acc)| {
            let rows = &grad[bi * ho * wo * width..(bi + 1) * ho * wo * width];
            for (r, row) in rows.chunks_exact(width).enumerate() {
                let (oy, ox) = (r / wo, r % wo);
                for (t, tap) in row.chunks_exact(c).enumerate() {
                    if let Some(p) = source(g, [h, w], [oy, ox], [t / kw, t % kw]) {
                        let a = &mut acc[p * c..(p + 1) * c];
                        a.iter_mut().zip(tap).for_each(|(a, t)| *a += t);
                    }
                }
            }
        });
    transpose_items(&acc, b, h * w, c)
}
