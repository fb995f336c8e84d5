//! A convolution's columns (im2col) on flex, in the channels-first layout it is given, with a backward
//! that adds every column back onto the input plane it was copied from (col2im). A 2D input is a 3D one
//! of depth 1.
//!
//! Row `(c, kd, kh, kw)` of a batch item's columns is input channel `c` shifted by the tap, over the
//! output positions: `[B, C * taps, Do * Ho * Wo]` (Caffe's layout). The weight `[Co, C, kd, kh, kw]`
//! flattened is then the left factor of one batched product whose output is already `[B, Co,
//! positions]`, so neither the input nor the output is transposed, either way (`conv`). Rows are copies
//! of contiguous runs of the input and the backward's sums adds of contiguous runs; planes run in
//! parallel, and each plane's sums are taken in one order whatever the number of threads. Columns with
//! the channels last (one row per output position) needed the input transposed, the product's output
//! and its gradient permuted, and the input gradient transposed back: the tiny HRNet's forward and
//! backward took 104-132 ms with them and 72-89 ms this way (`mvmp bench model --backward`, two runs
//! each).
//!
//! As tensor ops (`conv::product` on other backends) the columns are a pad, one strided slice per
//! kernel tap and a concatenation, and autodiff's backward of them makes a zero tensor the size of the
//! padded input for every tap, assigns the tap's gradient into it and adds them all.
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Tensor, TensorData};
use rayon::prelude::*;

use crate::host::{HostF32, dims, par_filled};

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
}

/// `x [B, C, D, H, W]` -> `[B, C * kd * kh * kw, Do * Ho * Wo]` (see the module's notes).
pub fn columns(x: Tensor<5>, geometry: Columns) -> Tensor<3> {
    Tensor::from_dispatch(<Dispatch as Im2colBackend>::im2col(
        x.into_dispatch(),
        geometry,
    ))
}

/// The backend side of [`columns`]; autodiff adds the backward.
#[backend_extension(Flex, Autodiff)]
pub trait Im2colBackend: Backend {
    fn im2col(x: FloatTensor<Self>, geometry: Columns) -> FloatTensor<Self> {
        let device = x.device();
        let dims = dims(&x);
        let cols = forward_host(&HostF32::read::<Self>(x), dims, &geometry);
        let shape = [dims[0], dims[1] * geometry.taps(), geometry.outputs()];
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
        let dx = backward_host(&HostF32::read::<B>(grad), dims, &geometry);
        grads.register::<B>(
            node.id,
            B::float_from_data(TensorData::new(dx, dims), &device),
        );
    }
}

/// One run of a tap's row: output positions `out + lo .. out + hi` read the input from `input + lo *
/// stride` on, every `stride`-th value.
struct Run {
    out: usize,
    input: usize,
    lo: usize,
    hi: usize,
}

/// The output positions `lo..hi` along one axis of `out` positions whose tap `k` (stride `s`, padding
/// `p` before) lands inside the input's `n`.
fn span(out: usize, s: usize, k: usize, p: usize, n: usize) -> (usize, usize) {
    let lo = p.saturating_sub(k).div_ceil(s);
    let hi = match (n + p).checked_sub(k + 1) {
        Some(last) => (last / s + 1).min(out),
        None => 0,
    };
    (lo, hi.max(lo))
}

/// Calls `f` with each run of tap `t` (flat over the kernel) in an input plane of `size`, one per output
/// line (fixed output depth and row) whose tap lands inside the input, in the order of the lines; the
/// padding's are left out. Plain loops over the lines that land inside, rather than a test of every
/// line: the tiny RootNet's lines are 8 voxels long, and its forward and backward took 89.6 / 101.1 ms
/// this way against 103.9 / 108.5 (`mvmp bench model --backward`, alternating, values bit for bit).
fn for_runs(g: &Columns, size: [usize; 3], t: usize, mut f: impl FnMut(Run)) {
    let [_, kh, kw] = g.kernel;
    let k = [t / (kh * kw), t / kw % kh, t % kw];
    let [(z0, z1), (y0, y1), (lo, hi)] =
        std::array::from_fn(|a| span(g.out[a], g.stride[a], k[a], g.pad[a], size[a]));
    if lo == hi {
        return;
    }
    let [_, oh, ow] = g.out;
    let [_, h, w] = size;
    let input_at = |o: usize, a: usize| o * g.stride[a] + k[a] - g.pad[a];
    for z in z0..z1 {
        for y in y0..y1 {
            f(Run {
                out: (z * oh + y) * ow,
                input: (input_at(z, 0) * h + input_at(y, 1)) * w + input_at(lo, 2),
                lo,
                hi,
            });
        }
    }
}

fn forward_host(x: &[f32], [b, c, d, h, w]: [usize; 5], g: &Columns) -> Vec<f32> {
    let (taps, outputs, plane) = (g.taps(), g.outputs(), d * h * w);
    let sw = g.stride[2];
    let n = b * c * taps * outputs;
    let mut cols: Vec<f32> = Vec::with_capacity(n);
    // Each row is zeroed just before its runs are copied in, while it is in cache, rather than the
    // whole buffer up front (a pass over megabytes of columns).
    cols.spare_capacity_mut()[..n]
        .par_chunks_mut(taps * outputs)
        .enumerate()
        .for_each(|(bc, dst)| {
            let src = &x[bc * plane..(bc + 1) * plane];
            for (t, row) in dst.chunks_exact_mut(outputs).enumerate() {
                row.fill(std::mem::MaybeUninit::new(0.0));
                // SAFETY: every value of the row was just written.
                let row = unsafe { &mut *(row as *mut [std::mem::MaybeUninit<f32>] as *mut [f32]) };
                for_runs(g, [d, h, w], t, |r| {
                    let out = &mut row[r.out + r.lo..r.out + r.hi];
                    if sw == 1 {
                        out.copy_from_slice(&src[r.input..r.input + out.len()]);
                    } else {
                        let strided = src[r.input..].iter().step_by(sw);
                        out.iter_mut().zip(strided).for_each(|(o, s)| *o = *s);
                    }
                });
            }
        });
    // SAFETY: the chunks above cover all `n` values and zeroed each row before anything else.
    unsafe { cols.set_len(n) };
    cols
}

fn backward_host(grad: &[f32], [b, c, d, h, w]: [usize; 5], g: &Columns) -> Vec<f32> {
    let (taps, outputs, plane) = (g.taps(), g.outputs(), d * h * w);
    let sw = g.stride[2];
    par_filled(b * c * plane, plane, |bc, dst| {
        let src = &grad[bc * taps * outputs..(bc + 1) * taps * outputs];
        for (t, row) in src.chunks_exact(outputs).enumerate() {
            for_runs(g, [d, h, w], t, |r| {
                let from = &row[r.out + r.lo..r.out + r.hi];
                if sw == 1 {
                    let to = &mut dst[r.input..r.input + from.len()];
                    to.iter_mut().zip(from).for_each(|(a, v)| *a += v);
                } else {
                    let to = dst[r.input..].iter_mut().step_by(sw);
                    to.zip(from).for_each(|(a, v)| *a += v);
                }
            });
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The columns and their backward against a direct loop over every output position and tap, for
    /// strides 1 and 2, uneven padding, and kernels of one and three taps per axis: the forward bit for
    /// bit, and the backward as the scatter of the columns onto the inputs they were read from.
    #[test]
    fn columns_are_the_taps_and_their_backward_the_scatter() {
        let cases = [
            ([2, 3, 4, 5, 6], [3, 3, 3], [1, 1, 1], [1, 1, 1]),
            ([1, 4, 5, 7, 6], [3, 3, 3], [2, 2, 2], [1, 1, 1]),
            ([3, 2, 1, 9, 8], [1, 3, 3], [1, 2, 2], [0, 1, 1]),
            ([1, 5, 2, 4, 4], [1, 1, 1], [1, 1, 1], [0, 0, 0]),
            ([2, 2, 1, 6, 7], [1, 3, 3], [1, 2, 2], [0, 0, 2]),
        ];
        for (dims, kernel, stride, pad) in cases {
            let [b, c, d, h, w] = dims;
            let size = [d, h, w];
            let out: [usize; 3] =
                std::array::from_fn(|a| (size[a] + 2 * pad[a] - kernel[a]) / stride[a] + 1);
            let g = Columns {
                kernel,
                stride,
                pad,
                out,
            };
            let (taps, outputs, plane) = (g.taps(), g.outputs(), d * h * w);
            let x: Vec<f32> = (0..b * c * plane).map(|i| i as f32 + 1.0).collect();
            let grad: Vec<f32> = (0..b * c * taps * outputs)
                .map(|i| ((i * 7919 % 1013) as f32 - 506.0) * 0.01)
                .collect();
            let (mut want, mut dx) = (vec![0f32; grad.len()], vec![0f32; x.len()]);
            for bc in 0..b * c {
                for t in 0..taps {
                    for o in 0..outputs {
                        let at = (bc * taps + t) * outputs + o;
                        let oz = [o / (out[1] * out[2]), o / out[2] % out[1], o % out[2]];
                        let k = [
                            t / (kernel[1] * kernel[2]),
                            t / kernel[2] % kernel[1],
                            t % kernel[2],
                        ];
                        let i: Option<Vec<usize>> = (0..3)
                            .map(|a| {
                                (oz[a] * stride[a] + k[a])
                                    .checked_sub(pad[a])
                                    .filter(|&i| i < size[a])
                            })
                            .collect();
                        if let Some(i) = i {
                            let p = bc * plane + (i[0] * h + i[1]) * w + i[2];
                            want[at] = x[p];
                            dx[p] += grad[at];
                        }
                    }
                }
            }
            assert_eq!(forward_host(&x, dims, &g), want, "{dims:?} {g:?}");
            let got = backward_host(&grad, dims, &g);
            for (i, (a, e)) in got.iter().zip(&dx).enumerate() {
                assert!(
                    (a - e).abs() <= 1e-5 * e.abs().max(1.0),
                    "{dims:?} {g:?} [{i}]: {a} vs {e}"
                );
            }
        }
    }
}
