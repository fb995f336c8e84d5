//! A 3D convolution whose gradients are products of tiled columns, for the RootNet in training on flex.
//!
//! burn derives a convolution's weight gradient as another convolution, with the output gradient as its
//! kernel (`conv3d_weight_backward`), and the input's as a transposed convolution; for the tiny
//! RootNet's 7^3 front (17 channels in, 8 out, a 32 x 32 x 8 volume) they took about 90 and 50 of the
//! 160 ms of the layer's forward and backward, against 21 ms for flex's forward (tiled im2col and a
//! GEMM). Here the forward stays burn's. The weight gradient is `dy . columns` over tiles of output
//! positions: each tile's columns (transposed, one row per kernel tap and input channel) are built in a
//! small buffer and multiplied at once, so no tile holds more than [`TILE`] positions' columns. Tiles go
//! to a fixed number of chunks, each summing its tiles in order, and the chunks are added in order: the
//! result does not depend on the number of threads. The input's gradient is the forward's counterpart:
//! the output gradient's columns, over tiles of input positions, times the kernel flipped and with its
//! channel axes swapped; every tile writes its own positions.
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::ops::ConvOptions;
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use crate::cpu::SendPtr;
use crate::host::{HostF32, dims, par_zeroed};
use crate::product::{Mat, gemm};

/// Output positions per tile: 64 positions of a 7^3 kernel over 17 channels are 1.5 MB of columns.
const TILE: usize = 64;
/// Chunks of tiles summed on their own (and then in order), whatever the number of threads.
const CHUNKS: usize = 8;

/// `conv3d(x, weight, bias, options)`; in training on flex with stride 1, dilation 1 and one group, one
/// operation whose gradients are the tiled products (see the module's notes). Elsewhere burn's.
pub fn conv3d(
    x: Tensor<5>,
    weight: Tensor<5>,
    bias: Option<Tensor<1>>,
    options: ConvOptions<3>,
) -> Tensor<5> {
    let plain = options.stride == [1; 3] && options.dilation == [1; 3] && options.groups == 1;
    let fused = x.is_autodiff() && x.device() == Device::flex() && crate::im2col::fused_im2col();
    if !(plain && fused) {
        return burn::tensor::module::conv3d(x, weight, bias, options);
    }
    let y = Tensor::from_dispatch(<Dispatch as TiledWeightGradBackend>::conv3d_tiled_wgrad(
        x.into_dispatch(),
        weight.into_dispatch(),
        options,
    ));
    with_bias(y, bias)
}

/// `y [B, Co, ...]` plus the bias `[Co]` of each output channel, when there is one.
pub(crate) fn with_bias(y: Tensor<5>, bias: Option<Tensor<1>>) -> Tensor<5> {
    match bias {
        Some(b) => {
            let co = b.dims()[0];
            y + b.reshape([1, co, 1, 1, 1])
        }
        None => y,
    }
}

/// The backend side of [`conv3d`]; autodiff adds the backward.
#[backend_extension(Flex, Autodiff)]
pub trait TiledWeightGradBackend: Backend {
    fn conv3d_tiled_wgrad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        options: ConvOptions<3>,
    ) -> FloatTensor<Self> {
        Self::conv3d(x, weight, None, options)
    }
}

impl TiledWeightGradBackend for Flex {}

impl<B: Backend + TiledWeightGradBackend, C: CheckpointStrategy> TiledWeightGradBackend
    for Autodiff<B, C>
{
    fn conv3d_tiled_wgrad(
        x: FloatTensor<Self>,
        weight: FloatTensor<Self>,
        options: ConvOptions<3>,
    ) -> FloatTensor<Self> {
        let guards = [x.node(), weight.node()];
        let (x, weight) = (x.into_primitive(), weight.into_primitive());
        let y = B::conv3d(x.clone(), weight.clone(), None, options.clone());
        match WeightGradBackward
            .prepare::<C>(guards)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(Saved { x, weight, options }, y),
            OpsKind::UnTracked(prep) => prep.finish(y),
        }
    }
}

#[derive(Debug, Clone)]
struct Saved<B: Backend> {
    x: FloatTensor<B>,
    weight: FloatTensor<B>,
    options: ConvOptions<3>,
}

#[derive(Debug)]
struct WeightGradBackward;

impl<B: Backend> Backward<B, 2> for WeightGradBackward {
    type State = Saved<B>;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dy = grads.consume::<B>(&ops.node);
        let [node_x, node_w] = ops.parents;
        let Saved { x, weight, options } = ops.state;
        let device = dy.device();
        let w_dims: [usize; 5] = dims(&weight);
        if let Some(node) = node_w {
            let geometry = Geometry {
                x: dims(&x),
                y: dims(&dy),
                kernel: [w_dims[2], w_dims[3], w_dims[4]],
                pad: options.padding.map(|(begin, _)| begin),
            };
            let dw = weight_gradient(
                &HostF32::read::<B>(x.clone()),
                &HostF32::read::<B>(dy.clone()),
                &geometry,
            );
            let dw = B::float_from_data(TensorData::new(dw, w_dims), &device);
            grads.register::<B>(node.id, dw);
        }
        if let Some(node) = node_x {
            let geometry = Geometry {
                x: dims(&x),
                y: dims(&dy),
                kernel: [w_dims[2], w_dims[3], w_dims[4]],
                pad: options.padding.map(|(begin, _)| begin),
            };
            let dx = match geometry.transposed() {
                Some(flipped) => {
                    let dx = input_gradient(
                        &HostF32::read::<B>(dy),
                        &HostF32::read::<B>(weight),
                        &flipped,
                    );
                    B::float_from_data(TensorData::new(dx, geometry.x), &device)
                }
                None => B::conv3d_x_backward(x, weight, dy, options),
            };
            grads.register::<B>(node.id, dx);
        }
    }
}

/// Shapes of a stride-1 convolution: input `[B, Ci, D, H, W]`, output `[B, Co, Do, Ho, Wo]`, kernel and
/// the padding before each axis.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Geometry {
    pub x: [usize; 5],
    pub y: [usize; 5],
    pub kernel: [usize; 3],
    pub pad: [usize; 3],
}

impl Geometry {
    /// The convolution that gives the input's gradient: the output gradient, padded by `k - 1 - pad`
    /// before each axis, convolved with the kernel flipped and its channel axes swapped, gives back the
    /// input's shape. `None` where a padding is wider than `k - 1` (the gradient would be a crop).
    fn transposed(&self) -> Option<Geometry> {
        let [a, b, c] = [0, 1, 2].map(|a| (self.kernel[a] - 1).checked_sub(self.pad[a]));
        let pad = [a?, b?, c?];
        Some(Geometry {
            x: self.y,
            y: self.x,
            kernel: self.kernel,
            pad,
        })
    }
}

/// `dx` of a stride-1 convolution `[B, Ci, D, H, W]` from the output gradient `dy [B, Co, ...]`, the
/// kernel `w [Co, Ci, kd, kh, kw]` and the transposed geometry ([`Geometry::transposed`]: `g.x` is
/// `dy`'s shape, `g.y` the input's): over the same tiles as the weight gradient, each tile's columns of
/// `dy` times the flipped kernel `[Ci, Co * taps]`. Every tile writes its own output positions, so the
/// tiles run in parallel and each value is one product, whatever the number of threads.
pub(crate) fn input_gradient(dy: &[f32], w: &[f32], g: &Geometry) -> Vec<f32> {
    let [b, co, ..] = g.x;
    let [_, ci, d, h, wd] = g.y;
    let taps: usize = g.kernel.iter().product();
    let kc = co * taps;
    let mut flipped = vec![0f32; ci * kc];
    for o in 0..co {
        for c in 0..ci {
            let src = &w[(o * ci + c) * taps..][..taps];
            let dst = &mut flipped[(c * co + o) * taps..][..taps];
            for (t, v) in src.iter().enumerate() {
                dst[taps - 1 - t] = *v;
            }
        }
    }
    let p = d * h * wd;
    let mut dx = par_zeroed(b * ci * p);
    if dx.is_empty() {
        return dx;
    }
    let rows = (TILE / wd.max(1)).max(1);
    let tiles: Vec<(usize, usize, usize)> = (0..b)
        .flat_map(|bi| {
            (0..d * h)
                .step_by(rows)
                .map(move |r| (bi, r, rows.min(d * h - r)))
        })
        .collect();
    let out = SendPtr(dx.as_mut_ptr());
    tiles.par_iter().for_each_init(
        || vec![0f32; kc * rows * wd],
        |cols, &(bi, r0, nr)| {
            let t = nr * wd;
            tile_columns(dy, g, bi, r0, nr, &mut cols[..kc * t]);
            // SAFETY: the tile's positions `r0 * wd..r0 * wd + t` of each of batch item `bi`'s `ci`
            // planes (`p` apart) lie inside `dx`, and no other tile writes them.
            unsafe {
                write_product(
                    out.get().add(bi * ci * p + r0 * wd),
                    p,
                    &flipped,
                    &cols[..kc * t],
                    ci,
                    kc,
                    t,
                )
            };
        },
    );
    dx
}

/// `dst [m, t] = lhs [m, kc] . cols [kc, t]`, `dst` rows `p` apart.
///
/// # Safety
/// `dst` must be valid for writes of `m` rows of `t` values `p` apart that nothing else accesses.
unsafe fn write_product(
    dst: *mut f32,
    p: usize,
    lhs: &[f32],
    cols: &[f32],
    m: usize,
    kc: usize,
    t: usize,
) {
    assert!(lhs.len() == m * kc && cols.len() == kc * t);
    let lhs = Mat::at(lhs, kc, 1);
    let cols = Mat::at(cols, t, 1);
    // SAFETY: the assert bounds what the product reads; the caller vouches for `dst`.
    unsafe { gemm(dst, p, false, lhs, cols, m, kc, t) };
}

/// `dW [Co, Ci, kd, kh, kw]` of a stride-1 convolution from its input and output gradient (host
/// float32, contiguous).
pub(crate) fn weight_gradient(x: &[f32], dy: &[f32], g: &Geometry) -> Vec<f32> {
    let [b, ci, ..] = g.x;
    let [_, co, od, oh, ow] = g.y;
    let kc = ci * g.kernel.iter().product::<usize>();
    let rows = (TILE / ow.max(1)).max(1);
    // Tiles: (batch item, first output row, rows), never across batch items.
    let tiles: Vec<(usize, usize, usize)> = (0..b)
        .flat_map(|bi| {
            (0..od * oh)
                .step_by(rows)
                .map(move |r| (bi, r, rows.min(od * oh - r)))
        })
        .collect();
    let per_chunk = tiles.len().div_ceil(CHUNKS).max(1);
    let partials: Vec<Vec<f32>> = tiles
        .par_chunks(per_chunk)
        .map(|chunk| {
            let mut dw = vec![0f32; co * kc];
            let mut cols = vec![0f32; kc * rows * ow];
            for &(bi, r0, nr) in chunk {
                let t = nr * ow;
                tile_columns(x, g, bi, r0, nr, &mut cols[..kc * t]);
                let p = od * oh * ow;
                let lhs = &dy[(bi * co) * p + r0 * ow..];
                accumulate_product(&mut dw, lhs, p, &cols[..kc * t], co, kc, t);
            }
            dw
        })
        .collect();
    let mut dw = vec![0f32; co * kc];
    for part in &partials {
        for (d, s) in dw.iter_mut().zip(part) {
            *d += s;
        }
    }
    dw
}

/// The transposed columns `[kc][t]` of output rows `r0..r0 + nr` (flat over depth and height) of batch
/// item `bi`: row `(c, dz, dy, dx)` holds the input value each position reads at that tap, 0 in the
/// padding.
fn tile_columns(x: &[f32], g: &Geometry, bi: usize, r0: usize, nr: usize, cols: &mut [f32]) {
    let [_, ci, d, h, w] = g.x;
    let [_, _, _, oh, ow] = g.y;
    let [kd, kh, kw] = g.kernel;
    let [pd, ph, pw] = g.pad;
    let t = nr * ow;
    for c in 0..ci {
        let plane = &x[(bi * ci + c) * d * h * w..][..d * h * w];
        for dz in 0..kd {
            for dy in 0..kh {
                for dx in 0..kw {
                    let row = (((c * kd + dz) * kh + dy) * kw + dx) * t;
                    let out = &mut cols[row..row + t];
                    // Output positions whose input column lies inside: w + dx - pw in 0..w.
                    let lo = pw.saturating_sub(dx).min(ow);
                    let hi = (w + pw).saturating_sub(dx).min(ow).max(lo);
                    for (q, r) in (r0..r0 + nr).enumerate() {
                        let (z, y) = (r / oh, r % oh);
                        let dst = &mut out[q * ow..(q + 1) * ow];
                        let (iz, iy) = ((z + dz).wrapping_sub(pd), (y + dy).wrapping_sub(ph));
                        if iz >= d || iy >= h || hi == lo {
                            dst.fill(0.0);
                            continue;
                        }
                        let src = &plane[(iz * h + iy) * w..][..w];
                        dst[..lo].fill(0.0);
                        dst[hi..].fill(0.0);
                        // lo >= pw - dx whenever the run is not empty, so this does not underflow.
                        let first = lo + dx - pw;
                        dst[lo..hi].copy_from_slice(&src[first..first + (hi - lo)]);
                    }
                }
            }
        }
    }
}

/// `dw [co, kc] += lhs [co, t] . cols [kc, t]^T`, `lhs` rows `p` apart.
fn accumulate_product(
    dw: &mut [f32],
    lhs: &[f32],
    p: usize,
    cols: &[f32],
    co: usize,
    kc: usize,
    t: usize,
) {
    assert!(dw.len() == co * kc && cols.len() == kc * t);
    assert!(co == 0 || lhs.len() >= (co - 1) * p + t);
    let lhs = Mat::at(lhs, p, 1);
    let cols_t = Mat::at(cols, 1, t);
    // SAFETY: the asserts bound every element the product reads or writes: `dw` is `co x kc` row-major,
    // `lhs` holds `co` rows of `t` values `p` apart, `cols` is `kc x t` row-major.
    unsafe { gemm(dw.as_mut_ptr(), kc, true, lhs, cols_t, co, t, kc) };
}
