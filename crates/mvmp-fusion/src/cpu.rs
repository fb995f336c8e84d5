//! Sampling and fusion as one pass on the CPU backend, and its gradient with respect to the maps.
//!
//! The tensor path of [`crate::fuse_views`] samples one view at a time into a `[C, P]` plane, masks it
//! and adds it to the running sum, so at paper scale (1.8 M voxels, 32 channels) every view writes and
//! reads several full volumes. Here the maps are turned channels-last once, and each block of voxels
//! gathers all its views' bilinear samples while its `[voxels][C]` accumulator is in L1, then writes the
//! finished values once, channels-first, into the output. Same arithmetic as the tensor path: border
//! padding, align_corners = false, views that do not see a voxel left out, 0 where none does.
use mvmp_kernels::cpu::{Isa, SendPtr};
use rayon::prelude::*;

use mvmp_kernels::host::transpose_planes;

use crate::FusionMode;

/// Voxels per block: the accumulator of 16 voxels x 32 channels is 2 KiB.
const BLOCK: usize = 16;

/// Host copy of a rig's sampling positions: `[V][P]` map-pixel coordinates `(x, y)`, already clamped to
/// the map (border padding); NaN where the view does not see the voxel.
#[derive(Debug)]
pub(crate) struct HostGrid {
    xy: Vec<[f32; 2]>,
    /// `[P]`: one over the number of views that see the voxel, 0 where none does (the mean's weight).
    inv_count: Vec<f32>,
    pub(crate) views: usize,
    pub(crate) voxels: usize,
    pub(crate) map_hw: [usize; 2],
}

impl HostGrid {
    /// From the projected network pixels `uv [V, P, 2]` and visibility `[V, P]` (1 seen, 0 not) of maps
    /// of `map_hw` at `stride` network pixels per map pixel.
    pub(crate) fn new(
        uv: &[f32],
        visible: &[f32],
        views: usize,
        voxels: usize,
        stride: f64,
        map_hw: [usize; 2],
    ) -> Self {
        let [h, w] = map_hw;
        let (xmax, ymax) = (w.saturating_sub(1) as f32, h.saturating_sub(1) as f32);
        let s = stride as f32;
        let xy = uv
            .chunks_exact(2)
            .zip(visible)
            .map(|(u, &seen)| {
                if seen > 0.5 {
                    // f = (u' + 0.5) / k - 0.5, then border padding clamps it into the map.
                    let x = ((u[0] + 0.5) / s - 0.5).clamp(0.0, xmax);
                    let y = ((u[1] + 0.5) / s - 0.5).clamp(0.0, ymax);
                    if x.is_finite() && y.is_finite() {
                        return [x, y];
                    }
                }
                [f32::NAN, f32::NAN]
            })
            .collect::<Vec<_>>();
        let inv_count = (0..voxels)
            .map(|p| {
                let seen = (0..views)
                    .filter(|&v| !xy[v * voxels + p][0].is_nan())
                    .count();
                if seen == 0 { 0.0 } else { 1.0 / seen as f32 }
            })
            .collect();
        HostGrid {
            xy,
            inv_count,
            views,
            voxels,
            map_hw,
        }
    }
}

/// Fuse one batch item: `maps [V][C][h][w]` into `out [C][P]` (every element is written).
pub(crate) fn fuse(
    grid: &HostGrid,
    maps: &[f32],
    channels: usize,
    mode: FusionMode,
    out: &mut [std::mem::MaybeUninit<f32>],
) {
    let (v, p, c) = (grid.views, grid.voxels, channels);
    let [h, w] = grid.map_hw;
    assert_eq!(maps.len(), v * c * h * w, "maps vs grid");
    assert_eq!(out.len(), c * p, "output vs grid");
    if h * w == 0 {
        // Empty maps: no view sees anything, so every voxel is unseen.
        out.iter_mut().for_each(|o| {
            o.write(0.0);
        });
        return;
    }
    if out.is_empty() {
        return;
    }
    // Channels last, so a bilinear tap is C contiguous floats.
    let last = transpose_planes(maps, v, c, h * w);
    let out = SendPtr(out.as_mut_ptr().cast::<f32>());
    let isa = Isa::detect();
    let max = mode == FusionMode::Max;
    (0..p.div_ceil(BLOCK))
        .into_par_iter()
        .with_min_len(64)
        .for_each_init(
            || (vec![0f32; BLOCK * c], [0u32; BLOCK]),
            |(acc, count), blk| {
                let p0 = blk * BLOCK;
                let n = BLOCK.min(p - p0);
                acc.fill(if max { f32::NEG_INFINITY } else { 0.0 });
                count.fill(0);
                for vi in 0..v {
                    let xy = &grid.xy[vi * p + p0..vi * p + p0 + n];
                    let map = &last[vi * h * w * c..(vi + 1) * h * w * c];
                    sample_block(isa, xy, map, [h, w], c, max, acc, count);
                }
                for ch in 0..c {
                    // SAFETY: `out` holds c * p floats; block `blk` writes only voxels p0..p0+n of each
                    // channel row, which no other block touches.
                    let row =
                        unsafe { std::slice::from_raw_parts_mut(out.get().add(ch * p + p0), n) };
                    for (i, o) in row.iter_mut().enumerate() {
                        let a = acc[i * c + ch];
                        *o = match (max, count[i]) {
                            (_, 0) => 0.0,
                            (true, _) => a,
                            (false, k) => a / k as f32,
                        };
                    }
                }
            },
        );
}

/// Add one view's samples of a block of voxels to their accumulators `[voxel][C]`.
///
/// The loop is compiled once per instruction set: the default x86-64 target has only SSE2.
#[allow(clippy::too_many_arguments)]
fn sample_block(
    isa: Isa,
    xy: &[[f32; 2]],
    map: &[f32],
    hw: [usize; 2],
    c: usize,
    max: bool,
    acc: &mut [f32],
    count: &mut [u32; BLOCK],
) {
    #[cfg(target_arch = "x86_64")]
    {
        type Args<'a> = (
            &'a [[f32; 2]],
            &'a [f32],
            [usize; 2],
            usize,
            bool,
            &'a mut [f32],
            &'a mut [u32; BLOCK],
        );
        #[target_feature(enable = "avx512f")]
        fn avx512(a: Args) {
            sample_block_body(a.0, a.1, a.2, a.3, a.4, a.5, a.6)
        }
        #[target_feature(enable = "avx2,fma")]
        fn avx2(a: Args) {
            sample_block_body(a.0, a.1, a.2, a.3, a.4, a.5, a.6)
        }
        let args = (xy, map, hw, c, max, acc, count);
        match isa {
            // SAFETY: the features were detected at run time.
            Isa::Avx512 => unsafe { avx512(args) },
            // SAFETY: as above.
            Isa::Avx2 => unsafe { avx2(args) },
            Isa::Portable => {
                let (xy, map, hw, c, max, acc, count) = args;
                sample_block_body(xy, map, hw, c, max, acc, count)
            }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = isa;
        sample_block_body(xy, map, hw, c, max, acc, count)
    }
}

#[inline(always)]
fn sample_block_body(
    xy: &[[f32; 2]],
    map: &[f32],
    [h, w]: [usize; 2],
    c: usize,
    max: bool,
    acc: &mut [f32],
    count: &mut [u32; BLOCK],
) {
    for (i, &[x, y]) in xy.iter().enumerate() {
        if x.is_nan() {
            continue;
        }
        let (x0, y0) = (x.floor(), y.floor());
        let (fx, fy) = (x - x0, y - y0);
        let (x0, y0) = (x0 as usize, y0 as usize);
        let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
        let tap = |yy: usize, xx: usize| &map[(yy * w + xx) * c..(yy * w + xx + 1) * c];
        let (m00, m01, m10, m11) = (tap(y0, x0), tap(y0, x1), tap(y1, x0), tap(y1, x1));
        let (w00, w01) = ((1.0 - fx) * (1.0 - fy), fx * (1.0 - fy));
        let (w10, w11) = ((1.0 - fx) * fy, fx * fy);
        let a = &mut acc[i * c..(i + 1) * c];
        let taps = m00.iter().zip(m01).zip(m10).zip(m11);
        if max {
            for (a, (((&p00, &p01), &p10), &p11)) in a.iter_mut().zip(taps) {
                *a = a.max(w00 * p00 + w01 * p01 + w10 * p10 + w11 * p11);
            }
        } else {
            for (a, (((&p00, &p01), &p10), &p11)) in a.iter_mut().zip(taps) {
                *a += w00 * p00 + w01 * p01 + w10 * p10 + w11 * p11;
            }
        }
        count[i] += 1;
    }
}

/// The bilinear taps of map pixel `(x, y)` (already clamped into the map): the four pixels' indices
/// and weights, as [`sample_block_body`] computes them.
#[inline(always)]
fn taps(x: f32, y: f32, [h, w]: [usize; 2]) -> [(usize, f32); 4] {
    let (x0, y0) = (x.floor(), y.floor());
    let (fx, fy) = (x - x0, y - y0);
    let (x0, y0) = (x0 as usize, y0 as usize);
    let (x1, y1) = ((x0 + 1).min(w - 1), (y0 + 1).min(h - 1));
    [
        (y0 * w + x0, (1.0 - fx) * (1.0 - fy)),
        (y0 * w + x1, fx * (1.0 - fy)),
        (y1 * w + x0, (1.0 - fx) * fy),
        (y1 * w + x1, fx * fy),
    ]
}

/// The gradient of [`fuse`] with respect to its maps: `grad [C][P]`, the fused volume's gradient, to
/// `[V][C][h][w]`. The mean hands each seeing view `1 / count` of a voxel's gradient, spread over its
/// four bilinear taps; the maximum hands all of it to the view that won (the first among equals), which
/// needs the maps (`max_maps`) to find again. Views are scattered in parallel, each into its own map, so
/// the sums run in one order whatever the number of threads.
pub(crate) fn fuse_backward(
    grid: &HostGrid,
    grad: &[f32],
    max_maps: Option<&[f32]>,
    channels: usize,
) -> Vec<f32> {
    let (v, p, c) = (grid.views, grid.voxels, channels);
    let [h, w] = grid.map_hw;
    assert_eq!(grad.len(), c * p, "gradient vs grid");
    if h * w == 0 || c * p == 0 {
        return vec![0.0; v * c * h * w];
    }
    let grad = transpose_planes(grad, 1, c, p); // [P][C]
    let winners = max_maps.map(|maps| max_winners(grid, maps, c));
    let mut last = vec![0f32; v * h * w * c];
    last.par_chunks_mut(h * w * c)
        .enumerate()
        .for_each(|(vi, acc)| {
            for (pi, &[x, y]) in grid.xy[vi * p..(vi + 1) * p].iter().enumerate() {
                if x.is_nan() {
                    continue;
                }
                let g = &grad[pi * c..(pi + 1) * c];
                for (tap, wt) in taps(x, y, grid.map_hw) {
                    let a = &mut acc[tap * c..(tap + 1) * c];
                    match &winners {
                        None => {
                            let wt = wt * grid.inv_count[pi];
                            a.iter_mut().zip(g).for_each(|(a, g)| *a += wt * g);
                        }
                        Some(win) => {
                            let win = &win[pi * c..(pi + 1) * c];
                            for ((a, g), &k) in a.iter_mut().zip(g).zip(win) {
                                if k as usize == vi {
                                    *a += wt * g;
                                }
                            }
                        }
                    }
                }
            }
        });
    transpose_planes(&last, v, h * w, c)
}

/// `[P][C]`: the view whose sample is the maximum at each voxel and channel (the first among equals),
/// `u8::MAX` where no view sees the voxel. Callers keep the views under 255.
fn max_winners(grid: &HostGrid, maps: &[f32], c: usize) -> Vec<u8> {
    let (v, p) = (grid.views, grid.voxels);
    let [h, w] = grid.map_hw;
    assert!(v < u8::MAX as usize, "max fusion's gradient over {v} views");
    let last = transpose_planes(maps, v, c, h * w);
    let mut win = vec![u8::MAX; p * c];
    win.par_chunks_mut(BLOCK * c).enumerate().for_each_init(
        || (vec![0f32; c], vec![0f32; c]),
        |(best, s), (blk, win)| {
            for (i, win) in win.chunks_exact_mut(c).enumerate() {
                let pi = blk * BLOCK + i;
                best.fill(f32::NEG_INFINITY);
                for vi in 0..v {
                    let [x, y] = grid.xy[vi * p + pi];
                    if x.is_nan() {
                        continue;
                    }
                    let map = &last[vi * h * w * c..(vi + 1) * h * w * c];
                    s.fill(0.0);
                    for (tap, wt) in taps(x, y, grid.map_hw) {
                        let m = &map[tap * c..(tap + 1) * c];
                        s.iter_mut().zip(m).for_each(|(s, m)| *s += wt * m);
                    }
                    for ((b, k), &s) in best.iter_mut().zip(win.iter_mut()).zip(s.iter()) {
                        if s > *b {
                            (*b, *k) = (s, vi as u8);
                        }
                    }
                }
            }
        },
    );
    win
}
