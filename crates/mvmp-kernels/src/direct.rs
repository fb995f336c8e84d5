//! A "same" 3D convolution of few channels (stride 1, every kernel side odd and padded by half of it)
//! computed directly, with its backward, for the RootNet's 3x3x3 blocks in training on flex.
//!
//! As a product of columns (`conv`) a 3x3x3 convolution over 16 channels copies 27 times its input
//! into the columns, the GEMM packs them again, and the backward writes and adds back as many: at the
//! tiny RootNet's sizes (8-64 channels, 32 x 32 x 8 voxels and less) that traffic, not the arithmetic,
//! was its time. Here the input is laid out once, zero-padded and channels last, and each tile of
//! output positions sums, tap by tap and input channel by input channel, the input value times a row
//! of the weight into registers of output channels. The positions of a tile are consecutive in the
//! padded volume's flat order, so every tap of the tile is one fixed offset into it: a slab of the
//! output (fixed first axis) is one run over the padded rows, whose positions in the padding of the
//! last axis are computed and dropped.
//!
//! The input's gradient is the same convolution of the output gradient with the kernel flipped and its
//! channel axes swapped. The weight's gradient sums, per tap, the input at that tap's offset times the
//! output gradient over every position, in blocks of positions, over a fixed number of chunks added in
//! order: no result depends on the number of threads.
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use crate::cpu::{Isa, SendPtr};
use crate::host::{HostF32, dims, par_filled};

/// Output channels of one block: one AVX-512 register of float32.
const LANES: usize = 16;
/// Input channels of one weight-gradient tile; the laid-out input's channels are padded to a multiple.
const CIN_TILE: usize = 8;
/// Output positions of one forward tile: 12 accumulators of [`LANES`].
const TILE: usize = 12;
/// Positions of one block of the weight gradient, so that its values stay in L1 over the taps.
const BLOCK: usize = 64;
/// Chunks of slabs whose weight gradients are summed on their own, then added in order.
const CHUNKS: usize = 8;

static DIRECT: AtomicBool = AtomicBool::new(true);

/// Whether training on flex computes the 3D convolutions this module takes directly (the default) or
/// as products of columns; process-wide, so that a benchmark can time both.
pub fn set_direct_conv3d(on: bool) {
    DIRECT.store(on, Ordering::Relaxed);
}

/// See [`set_direct_conv3d`].
pub fn direct_conv3d() -> bool {
    DIRECT.load(Ordering::Relaxed)
}

/// Whether a kernel of these sides, padded by `pad` before and after each axis, is one this module
/// computes: every side odd and padded by half of it, more than one tap.
pub fn takes(kernel: [usize; 3], pad: [usize; 3]) -> bool {
    kernel
        .iter()
        .zip(pad)
        .all(|(&k, p)| k % 2 == 1 && p == k / 2)
        && kernel != [1; 3]
}

/// Fewest output voxels per position a slab's tiles compute (the rest fall in the padding of the last
/// axis or past the run): the tiny RootNet's 3x3x3 blocks at a quarter of its resolution (8 x 8 x 2,
/// 16 of 36) took 5.0 and 8.5 ms forward and backward directly against 4.2 and 4.7 as products of
/// columns; at half of it (64 of 96) 4.2 and 4.9 against 6.1 and 6.8 (`--example rootnet_parts`).
const MIN_USEFUL: f64 = 0.5;

/// The share of a slab's computed positions that are output voxels, for a volume of sides `n` and a
/// kernel of sides `k` (padded by half of them).
pub fn useful(n: [usize; 3], k: [usize; 3]) -> f64 {
    let g = Grid { batch: 1, n, k };
    (n[1] * n[2]) as f64 / g.run().next_multiple_of(TILE).max(1) as f64
}

/// `conv3d(x, weight, bias)` with stride 1 and the padding `kernel / 2` of [`takes`], directly (see
/// the module's notes), in training on flex while [`direct_conv3d`] is on, where at least
/// [`MIN_USEFUL`] of what it computes is output ([`useful`]); `None` elsewhere.
pub fn conv3d(
    x: Tensor<5>,
    weight: Tensor<5>,
    bias: Option<Tensor<1>>,
    pad: [usize; 3],
) -> Option<Tensor<5>> {
    let ([_, _, kx, ky, kz], [_, _, nx, ny, nz]) = (weight.dims(), x.dims());
    let on = direct_conv3d() && crate::im2col::fused_im2col();
    if !(on && x.is_autodiff() && x.device() == Device::flex() && takes([kx, ky, kz], pad)) {
        return None;
    }
    if nx * ny * nz == 0 || useful([nx, ny, nz], [kx, ky, kz]) < MIN_USEFUL {
        return None;
    }
    Some(convolution(x, weight, bias))
}

/// [`conv3d`] taken directly whatever its shares (the caller checked the kernel and device).
pub(crate) fn convolution(x: Tensor<5>, weight: Tensor<5>, bias: Option<Tensor<1>>) -> Tensor<5> {
    let y = Tensor::from_dispatch(<Dispatch as DirectConvBackend>::conv3d_direct(
        x.into_dispatch(),
        weight.into_dispatch(),
    ));
    crate::wgrad::with_bias(y, bias)
}

/// The backend side of [`conv3d`]; autodiff adds the backward.
#[backend_extension(Flex, Autodiff)]
pub trait DirectConvBackend: Backend {
    fn conv3d_direct(x: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self> {
        let device = x.device();
        let (xd, wd) = (dims::<5>(&x), dims::<5>(&weight));
        let g = Grid::new(xd, wd);
        let (x, w) = (HostF32::read::<Self>(x), HostF32::read::<Self>(weight));
        let y = forward_host(&x, &w, [wd[0], wd[1]], &g);
        Self::float_from_data(
            TensorData::new(y, [xd[0], wd[0], xd[2], xd[3], xd[4]]),
            &device,
        )
    }
}

impl DirectConvBackend for Flex {}

impl<B: Backend + DirectConvBackend, C: CheckpointStrategy> DirectConvBackend for Autodiff<B, C> {
    fn conv3d_direct(x: FloatTensor<Self>, weight: FloatTensor<Self>) -> FloatTensor<Self> {
        let guards = [x.node(), weight.node()];
        let (x, weight) = (x.into_primitive(), weight.into_primitive());
        let y = B::conv3d_direct(x.clone(), weight.clone());
        match DirectBackward
            .prepare::<C>(guards)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish((x, weight), y),
            OpsKind::UnTracked(prep) => prep.finish(y),
        }
    }
}

#[derive(Debug)]
struct DirectBackward;

impl<B: Backend> Backward<B, 2> for DirectBackward {
    type State = (FloatTensor<B>, FloatTensor<B>);

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let dy = grads.consume::<B>(&ops.node);
        let [node_x, node_w] = ops.parents;
        let (x, weight) = ops.state;
        let device = dy.device();
        let (xd, wd) = (dims::<5>(&x), dims::<5>(&weight));
        let g = Grid::new(xd, wd);
        let [co, ci] = [wd[0], wd[1]];
        let (cip, cop) = (ci.next_multiple_of(CIN_TILE), co.next_multiple_of(LANES));
        // The output gradient laid out once, read by both gradients.
        let dyp = padded_last(&HostF32::read::<B>(dy), co, cop, &g);
        let w = HostF32::read::<B>(weight);
        if let Some(node) = node_w {
            let xp = padded_last(&HostF32::read::<B>(x), ci, cip, &g);
            let dw = weight_gradient(&xp, cip, &dyp, cop, &g, Isa::detect());
            let dw = unpack_weight(&dw, co, ci, g.taps(), cip, cop);
            grads.register::<B>(
                node.id,
                B::float_from_data(TensorData::new(dw, wd), &device),
            );
        }
        if let Some(node) = node_x {
            let flipped = pack_weight(&w, [co, ci], g.taps(), cop, true);
            let dx = convolve(&dyp, cop, &flipped, ci, &g, Isa::detect());
            grads.register::<B>(
                node.id,
                B::float_from_data(TensorData::new(dx, xd), &device),
            );
        }
    }
}

/// The shapes of one convolution: batch, the volume's sides, the kernel's, and the padding (half the
/// kernel) that keeps the volume's sides.
#[derive(Debug, Clone, Copy)]
struct Grid {
    batch: usize,
    n: [usize; 3],
    k: [usize; 3],
}

impl Grid {
    fn new(x: [usize; 5], w: [usize; 5]) -> Grid {
        Grid {
            batch: x[0],
            n: [x[2], x[3], x[4]],
            k: [w[2], w[3], w[4]],
        }
    }

    fn pad(&self) -> [usize; 3] {
        self.k.map(|k| k / 2)
    }

    fn padded(&self) -> [usize; 3] {
        std::array::from_fn(|a| self.n[a] + 2 * self.pad()[a])
    }

    fn taps(&self) -> usize {
        self.k.iter().product()
    }

    /// Positions of one slab's run: from its first row's first voxel to its last row's last, through
    /// the padding of the last axis between rows.
    fn run(&self) -> usize {
        let [_, ny, nz] = self.n;
        (ny - 1) * self.padded()[2] + nz
    }

    /// The flat padded position of output slab `i`'s first voxel in batch item `b`, less the padding
    /// before it: tap `t` of the run's position `r` reads `slab(b, i) + r + offsets()[t]`.
    fn slab(&self, b: usize, i: usize) -> usize {
        let [xp, yp, zp] = self.padded();
        (b * xp + i) * yp * zp
    }

    /// Each tap's offset into the padded volume, in the weight's order of taps.
    fn offsets(&self) -> Vec<usize> {
        let [_, yp, zp] = self.padded();
        let [kx, ky, kz] = self.k;
        (0..kx * ky * kz)
            .map(|t| ((t / (ky * kz)) * yp + t / kz % ky) * zp + t % kz)
            .collect()
    }

    /// The offset of the kernel's centre: where a run's position lies itself in the padded volume.
    fn centre(&self) -> usize {
        let [_, yp, zp] = self.padded();
        let [px, py, pz] = self.pad();
        (px * yp + py) * zp + pz
    }

    /// Positions of the padded volume, with [`TILE`] more at the end for the last tile's overrun.
    fn positions(&self) -> usize {
        self.batch * self.padded().iter().product::<usize>() + TILE
    }
}

/// `src [B, C, X, Y, Z]` -> the zero-padded volume channels last, `cp >= C` channels a position (zeros
/// past `C`), with [`Grid::positions`] positions.
fn padded_last(src: &[f32], c: usize, cp: usize, g: &Grid) -> Vec<f32> {
    let [xp, yp, zp] = g.padded();
    let [nx, ny, nz] = g.n;
    let [px, py, pz] = g.pad();
    let slab = yp * zp * cp;
    assert!(src.len() == g.batch * c * nx * ny * nz);
    par_filled(g.positions() * cp, slab, |s, out| {
        let (b, ip) = (s / xp, s % xp);
        if b >= g.batch || ip < px || ip >= px + nx {
            return;
        }
        let i = ip - px;
        for ch in 0..c {
            let plane = &src[((b * c + ch) * nx + i) * ny * nz..][..ny * nz];
            for (j, row) in plane.chunks_exact(nz).enumerate() {
                let first = ((j + py) * zp + pz) * cp + ch;
                for (l, v) in row.iter().enumerate() {
                    out[first + l * cp] = *v;
                }
            }
        }
    })
}

/// `w [Co, Ci, taps]` -> `[taps][rp][Co']` (`rp >= Ci` rows, the input's channels as laid out, and
/// the output channels padded with zeros to a multiple of [`LANES`]), the rows a forward tile reads;
/// `flipped`: the input gradient's kernel `[taps][rp][Ci']` (`rp >= Co`), taps reversed (every axis
/// flipped) and the channel axes swapped.
fn pack_weight(w: &[f32], [co, ci]: [usize; 2], taps: usize, rp: usize, flipped: bool) -> Vec<f32> {
    let cols = if flipped { ci } else { co };
    let cp = cols.next_multiple_of(LANES);
    let mut out = vec![0f32; taps * rp * cp];
    for o in 0..co {
        for c in 0..ci {
            for t in 0..taps {
                let v = w[(o * ci + c) * taps + t];
                let at = match flipped {
                    false => (t * rp + c) * cp + o,
                    true => ((taps - 1 - t) * rp + o) * cp + c,
                };
                out[at] = v;
            }
        }
    }
    out
}

/// The weight gradient `[taps][Ci'][Co']` -> `[Co, Ci, taps]`.
fn unpack_weight(
    dw: &[f32],
    co: usize,
    ci: usize,
    taps: usize,
    cip: usize,
    cop: usize,
) -> Vec<f32> {
    let mut out = vec![0f32; co * ci * taps];
    for o in 0..co {
        for c in 0..ci {
            for t in 0..taps {
                out[(o * ci + c) * taps + t] = dw[(t * cip + c) * cop + o];
            }
        }
    }
    out
}

/// The convolution of `x [B, Ci, ...]` with `w [Co, Ci, taps]`, channels first.
fn forward_host(x: &[f32], w: &[f32], [co, ci]: [usize; 2], g: &Grid) -> Vec<f32> {
    let cip = ci.next_multiple_of(CIN_TILE);
    let xp = padded_last(x, ci, cip, g);
    let w = pack_weight(w, [co, ci], g.taps(), cip, false);
    convolve(&xp, cip, &w, co, g, Isa::detect())
}

/// `out [B, Co, X, Y, Z]` (channels first): the padded, channels-last `inp` (`cin` channels a position,
/// a multiple of [`CIN_TILE`]) convolved with the packed `w [taps][cin][Co']`.
fn convolve(inp: &[f32], cin: usize, w: &[f32], co: usize, g: &Grid, isa: Isa) -> Vec<f32> {
    let [nx, ny, nz] = g.n;
    let zp = g.padded()[2];
    let (run, offs, cop) = (g.run(), g.offsets(), co.next_multiple_of(LANES));
    assert!(inp.len() == g.positions() * cin && w.len() == offs.len() * cin * cop);
    let plane = nx * ny * nz;
    let mut out = vec![0f32; g.batch * co * plane];
    let items: Vec<(usize, usize, usize)> = (0..g.batch)
        .flat_map(|b| (0..nx).flat_map(move |i| (0..cop / LANES).map(move |cb| (b, i, cb))))
        .collect();
    let dst = SendPtr(out.as_mut_ptr());
    items.par_iter().for_each(|&(b, i, cb)| {
        let lanes = LANES.min(co - cb * LANES);
        for r0 in (0..run).step_by(TILE) {
            let p = g.slab(b, i) + r0;
            // SAFETY: the tile reads positions p + off .. p + off + TILE, within the slack of
            // `Grid::positions` past the last run, and the weight's block `cb` of every row (asserted).
            let acc = unsafe { tile(isa, inp, cin, &offs, w, cop, cb, p) };
            for (t, acc) in acc.iter().enumerate().take(run - r0) {
                let (j, l) = ((r0 + t) / zp, (r0 + t) % zp);
                if l >= nz {
                    continue;
                }
                for (lane, v) in acc.iter().enumerate().take(lanes) {
                    let o = cb * LANES + lane;
                    // SAFETY: (b, o, i, j, l) lies inside `out`, and only item (b, i, cb) writes it.
                    unsafe { *dst.get().add((b * co + o) * plane + (i * ny + j) * nz + l) = *v };
                }
            }
        }
    });
    out
}

/// One forward tile: the [`TILE`] positions from `p` against output-channel block `cb`.
///
/// # Safety
/// `inp` must hold `(p + off + TILE) * cin` values for every offset, and `w` `taps * cin * cop`.
#[allow(clippy::too_many_arguments)]
unsafe fn tile(
    isa: Isa,
    inp: &[f32],
    cin: usize,
    offs: &[usize],
    w: &[f32],
    cop: usize,
    cb: usize,
    p: usize,
) -> [[f32; LANES]; TILE] {
    debug_assert!(offs.iter().all(|o| (p + o + TILE) * cin <= inp.len()));
    let (x, w) = (inp.as_ptr(), w.as_ptr().wrapping_add(cb * LANES));
    match isa {
        // SAFETY: the feature was detected; the caller vouches for the reads.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => unsafe { x86::tile_avx512(x, cin, offs, w, cop, p) },
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => unsafe { x86::tile_avx2(x, cin, offs, w, cop, p) },
        // SAFETY: as above.
        Isa::Portable => unsafe { tile_generic(x, cin, offs, w, cop, p) },
    }
}

/// [`tile`] in plain Rust: `w` points at the block's first lane of row 0.
#[inline(always)]
unsafe fn tile_generic(
    x: *const f32,
    cin: usize,
    offs: &[usize],
    w: *const f32,
    cop: usize,
    p: usize,
) -> [[f32; LANES]; TILE] {
    let mut acc = [[0f32; LANES]; TILE];
    for (tap, &off) in offs.iter().enumerate() {
        // SAFETY: the caller vouches for every read below.
        unsafe {
            let xs = x.add((p + off) * cin);
            for c in 0..cin {
                let wr = &*(w.add((tap * cin + c) * cop) as *const [f32; LANES]);
                for (t, acc) in acc.iter_mut().enumerate() {
                    let v = *xs.add(t * cin + c);
                    for (a, wl) in acc.iter_mut().zip(wr) {
                        *a += v * wl;
                    }
                }
            }
        }
    }
    acc
}

/// The weight gradient `[taps][cin][cop]` from the laid-out input (`cin` channels a position) and
/// output gradient (`cop`): per slab, blocks of [`BLOCK`] positions, every tap and tile of channels.
fn weight_gradient(
    xp: &[f32],
    cin: usize,
    dyp: &[f32],
    cop: usize,
    g: &Grid,
    isa: Isa,
) -> Vec<f32> {
    let (run, offs, centre) = (g.run(), g.offsets(), g.centre());
    assert!(xp.len() == g.positions() * cin && dyp.len() == g.positions() * cop);
    let size = offs.len() * cin * cop;
    let slabs: Vec<(usize, usize)> = (0..g.batch)
        .flat_map(|b| (0..g.n[0]).map(move |i| (b, i)))
        .collect();
    let per_chunk = slabs.len().div_ceil(CHUNKS).max(1);
    let partials: Vec<Vec<f32>> = slabs
        .par_chunks(per_chunk)
        .map(|chunk| {
            let mut dw = vec![0f32; size];
            for &(b, i) in chunk {
                for r0 in (0..run).step_by(BLOCK) {
                    let (p, n) = (g.slab(b, i) + r0, BLOCK.min(run - r0));
                    for (tap, &off) in offs.iter().enumerate() {
                        for ct in (0..cin).step_by(CIN_TILE) {
                            for cb in 0..cop / LANES {
                                let at = (tap * cin + ct) * cop + cb * LANES;
                                // SAFETY: positions p + off + n and p + centre + n lie within the
                                // runs (asserted sizes); the tile's rows of `dw` are inside it.
                                unsafe {
                                    let x = xp.as_ptr().add((p + off) * cin + ct);
                                    let d = dyp.as_ptr().add((p + centre) * cop + cb * LANES);
                                    wtile(isa, dw.as_mut_ptr().add(at), cop, x, cin, d, n)
                                }
                            }
                        }
                    }
                }
            }
            dw
        })
        .collect();
    let mut dw = vec![0f32; size];
    for part in &partials {
        for (d, s) in dw.iter_mut().zip(part) {
            *d += s;
        }
    }
    dw
}

/// `dw [k][lane] += x [p][k] * d [p][lane]` over `n` positions, for [`CIN_TILE`] rows `k` of `dw`
/// (`cop` apart), `x`'s positions `cin` apart and `d`'s `cop` apart.
///
/// # Safety
/// Every one of those reads and writes must be in bounds.
unsafe fn wtile(
    isa: Isa,
    dw: *mut f32,
    cop: usize,
    x: *const f32,
    cin: usize,
    d: *const f32,
    n: usize,
) {
    match isa {
        // SAFETY: the feature was detected; the caller vouches for the accesses.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => unsafe { x86::wtile_avx512(dw, cop, x, cin, d, n) },
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => unsafe { x86::wtile_avx2(dw, cop, x, cin, d, n) },
        // SAFETY: as above.
        Isa::Portable => unsafe { wtile_generic(dw, cop, x, cin, d, n) },
    }
}

#[inline(always)]
unsafe fn wtile_generic(
    dw: *mut f32,
    cop: usize,
    x: *const f32,
    cin: usize,
    d: *const f32,
    n: usize,
) {
    let mut acc = [[0f32; LANES]; CIN_TILE];
    // SAFETY: the caller vouches for every access.
    unsafe {
        for (k, acc) in acc.iter_mut().enumerate() {
            *acc = *(dw.add(k * cop) as *const [f32; LANES]);
        }
        for q in 0..n {
            let dr = &*(d.add(q * cop) as *const [f32; LANES]);
            for (k, acc) in acc.iter_mut().enumerate() {
                let v = *x.add(q * cin + k);
                for (a, dl) in acc.iter_mut().zip(dr) {
                    *a += v * dl;
                }
            }
        }
        for (k, acc) in acc.iter().enumerate() {
            *(dw.add(k * cop) as *mut [f32; LANES]) = *acc;
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::{CIN_TILE, LANES, TILE};
    use std::arch::x86_64::*;

    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn tile_avx512(
        x: *const f32,
        cin: usize,
        offs: &[usize],
        w: *const f32,
        cop: usize,
        p: usize,
    ) -> [[f32; LANES]; TILE] {
        let mut acc = [_mm512_setzero_ps(); TILE];
        for (tap, &off) in offs.iter().enumerate() {
            // SAFETY: the caller vouches for every read.
            unsafe {
                let xs = x.add((p + off) * cin);
                let wt = w.add(tap * cin * cop);
                for c in 0..cin {
                    let wv = _mm512_loadu_ps(wt.add(c * cop));
                    for (t, a) in acc.iter_mut().enumerate() {
                        *a = _mm512_fmadd_ps(_mm512_set1_ps(*xs.add(t * cin + c)), wv, *a);
                    }
                }
            }
        }
        let mut out = [[0f32; LANES]; TILE];
        for (o, a) in out.iter_mut().zip(acc) {
            // SAFETY: `o` holds LANES floats.
            unsafe { _mm512_storeu_ps(o.as_mut_ptr(), a) };
        }
        out
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn tile_avx2(
        x: *const f32,
        cin: usize,
        offs: &[usize],
        w: *const f32,
        cop: usize,
        p: usize,
    ) -> [[f32; LANES]; TILE] {
        // SAFETY: the caller's promise, passed on.
        unsafe { super::tile_generic(x, cin, offs, w, cop, p) }
    }

    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn wtile_avx512(
        dw: *mut f32,
        cop: usize,
        x: *const f32,
        cin: usize,
        d: *const f32,
        n: usize,
    ) {
        // SAFETY: the caller vouches for every access.
        unsafe {
            let mut acc: [__m512; CIN_TILE] =
                std::array::from_fn(|k| _mm512_loadu_ps(dw.add(k * cop)));
            for q in 0..n {
                let dv = _mm512_loadu_ps(d.add(q * cop));
                let xs = x.add(q * cin);
                for (k, a) in acc.iter_mut().enumerate() {
                    *a = _mm512_fmadd_ps(_mm512_set1_ps(*xs.add(k)), dv, *a);
                }
            }
            for (k, a) in acc.into_iter().enumerate() {
                _mm512_storeu_ps(dw.add(k * cop), a);
            }
        }
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn wtile_avx2(
        dw: *mut f32,
        cop: usize,
        x: *const f32,
        cin: usize,
        d: *const f32,
        n: usize,
    ) {
        // SAFETY: the caller's promise, passed on.
        unsafe { super::wtile_generic(dw, cop, x, cin, d, n) }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values from a fixed sequence in [-1, 1).
    fn values(n: usize, seed: u64) -> Vec<f32> {
        let mut z = seed;
        (0..n)
            .map(|_| {
                z = z
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((z >> 40) as f32 / (1u64 << 23) as f32) - 1.0
            })
            .collect()
    }

    fn relative(a: &[f32], b: &[f32]) -> f32 {
        let scale = b.iter().fold(1e-6f32, |m, v| m.max(v.abs()));
        a.iter().zip(b).fold(0f32, |m, (x, y)| m.max((x - y).abs())) / scale
    }

    /// Every instruction set this machine has gives the plain Rust kernels' forward and weight
    /// gradient to 1e-5 (the AVX-512 kernel fuses its multiply-adds, the others do not), for channels
    /// that fill neither a register nor a tile.
    #[test]
    fn every_instruction_set_gives_the_plain_kernels() {
        let g = Grid {
            batch: 2,
            n: [4, 5, 6],
            k: [3, 3, 3],
        };
        let (ci, co): (usize, usize) = (11, 21);
        let (cip, cop) = (ci.next_multiple_of(CIN_TILE), co.next_multiple_of(LANES));
        let x = values(2 * ci * 120, 1);
        let dy = values(2 * co * 120, 2);
        let w = pack_weight(&values(co * ci * 27, 3), [co, ci], 27, cip, false);
        let xp = padded_last(&x, ci, cip, &g);
        let dyp = padded_last(&dy, co, cop, &g);
        let plain = (
            convolve(&xp, cip, &w, co, &g, Isa::Portable),
            weight_gradient(&xp, cip, &dyp, cop, &g, Isa::Portable),
        );
        let mut isas = vec![Isa::detect()];
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
        {
            isas.push(Isa::Avx2);
        }
        for isa in isas {
            let y = convolve(&xp, cip, &w, co, &g, isa);
            let dw = weight_gradient(&xp, cip, &dyp, cop, &g, isa);
            assert!(relative(&y, &plain.0) < 1e-5, "{isa:?}: forward");
            assert!(relative(&dw, &plain.1) < 1e-5, "{isa:?}: weight gradient");
        }
    }
}
