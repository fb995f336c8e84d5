//! The panel products of the fused SMPL-X pass: `dst [N][PANEL] = panel [K][PANEL]^T . feat [K][N]`, the
//! K rows of one block of PANEL vertices against every body's K features, in AVX-512, AVX2 + FMA and
//! plain Rust.
use crate::cpu::Isa;

/// Vertices per panel (the lanes of one panel row).
pub const PANEL: usize = 32;
const BLOCK: usize = PANEL;

/// `dst [N][BLOCK] = panel [K][BLOCK]^T . feat [K][N]`.
pub fn gemm_panel(isa: Isa, panel: &[f32], feat: &[f32], k: usize, n: usize, dst: &mut [f32]) {
    assert!(panel.len() >= k * BLOCK && feat.len() >= k * n && dst.len() >= n * BLOCK);
    match isa {
        // SAFETY: the features were detected, and the asserts above bound every access.
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => unsafe { x86::gemm_avx512(panel, feat, k, n, dst) },
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => unsafe { x86::gemm_avx2(panel, feat, k, n, dst) },
        Isa::Portable => gemm_portable(panel, feat, k, n, dst),
    }
}

fn gemm_portable(panel: &[f32], feat: &[f32], k: usize, n: usize, dst: &mut [f32]) {
    for c in 0..n {
        let mut acc = [0f32; BLOCK];
        for q in 0..k {
            let f = feat[q * n + c];
            let row = &panel[q * BLOCK..(q + 1) * BLOCK];
            for (x, &p) in acc.iter_mut().zip(row) {
                *x += p * f;
            }
        }
        dst[c * BLOCK..(c + 1) * BLOCK].copy_from_slice(&acc);
    }
}

#[cfg(target_arch = "x86_64")]
mod x86 {
    use super::PANEL as BLOCK;
    use std::arch::x86_64::*;

    /// Panel rows per chunk: 64 rows of a 32-vertex panel are 8 KiB, so a chunk, its features and the
    /// output columns stay in L1 while every column tile passes over them.
    const KC: usize = 64;

    /// One column tile over one chunk of rows; `acc` adds to what `dst` holds instead of overwriting.
    #[derive(Clone, Copy)]
    struct Tile {
        q0: usize,
        q1: usize,
        n: usize,
        c0: usize,
        acc: bool,
    }

    /// The tiles of a panel product in the order they run, with their widths: chunks of KC rows, and
    /// within a chunk every column tile, so each chunk is used from L1 by all columns and the panel
    /// streams from L3 once, overlapped with the arithmetic.
    fn tiles(k: usize, n: usize, nr_max: usize) -> impl Iterator<Item = (Tile, usize)> {
        (0..k).step_by(KC).flat_map(move |q0| {
            let q1 = (q0 + KC).min(k);
            (0..n).step_by(nr_max).map(move |c0| {
                let acc = q0 > 0;
                (Tile { q0, q1, n, c0, acc }, (n - c0).min(nr_max))
            })
        })
    }

    /// Columns per tile: 2 x 12 accumulators of 16 lanes leave registers for the panel.
    const NR512: usize = 12;
    /// Columns per tile with 8-lane registers: 4 x 3 accumulators.
    const NR256: usize = 3;

    #[target_feature(enable = "avx512f")]
    pub(super) unsafe fn gemm_avx512(
        panel: &[f32],
        feat: &[f32],
        k: usize,
        n: usize,
        dst: &mut [f32],
    ) {
        for (t, nr) in tiles(k, n, NR512) {
            // SAFETY: columns c0..c0+nr < n and rows q0..q1 <= k; the caller checked the lengths.
            unsafe {
                match nr {
                    12 => tile512::<12>(panel, feat, t, dst),
                    11 => tile512::<11>(panel, feat, t, dst),
                    10 => tile512::<10>(panel, feat, t, dst),
                    9 => tile512::<9>(panel, feat, t, dst),
                    8 => tile512::<8>(panel, feat, t, dst),
                    7 => tile512::<7>(panel, feat, t, dst),
                    6 => tile512::<6>(panel, feat, t, dst),
                    5 => tile512::<5>(panel, feat, t, dst),
                    4 => tile512::<4>(panel, feat, t, dst),
                    3 => tile512::<3>(panel, feat, t, dst),
                    2 => tile512::<2>(panel, feat, t, dst),
                    _ => tile512::<1>(panel, feat, t, dst),
                }
            }
        }
    }

    #[inline]
    #[target_feature(enable = "avx512f")]
    unsafe fn tile512<const NR: usize>(panel: &[f32], feat: &[f32], t: Tile, dst: &mut [f32]) {
        let d = dst.as_mut_ptr();
        let mut acc = [[_mm512_setzero_ps(); 2]; NR];
        if t.acc {
            for (c, acc) in acc.iter_mut().enumerate() {
                // SAFETY: column c0 + c < n and dst holds n rows of BLOCK floats.
                unsafe {
                    let d = d.add((t.c0 + c) * BLOCK);
                    *acc = [_mm512_loadu_ps(d), _mm512_loadu_ps(d.add(16))];
                }
            }
        }
        let p = panel.as_ptr();
        let f = feat.as_ptr();
        for q in t.q0..t.q1 {
            // SAFETY: q < k and the panel holds k rows of BLOCK floats; feat holds k rows of n.
            unsafe {
                if t.c0 == 0 {
                    // The first tile pulls the next chunk towards L1 while it computes: the hardware
                    // prefetcher alone leaves the stream from L3 exposed.
                    let ahead = p.wrapping_add((q + KC) * BLOCK) as *const i8;
                    _mm_prefetch::<_MM_HINT_T0>(ahead);
                    _mm_prefetch::<_MM_HINT_T0>(ahead.wrapping_add(64));
                }
                let a0 = _mm512_loadu_ps(p.add(q * BLOCK));
                let a1 = _mm512_loadu_ps(p.add(q * BLOCK + 16));
                let fr = f.add(q * t.n + t.c0);
                for (c, acc) in acc.iter_mut().enumerate() {
                    let w = _mm512_set1_ps(*fr.add(c));
                    acc[0] = _mm512_fmadd_ps(a0, w, acc[0]);
                    acc[1] = _mm512_fmadd_ps(a1, w, acc[1]);
                }
            }
        }
        for (c, acc) in acc.iter().enumerate() {
            // SAFETY: as above.
            unsafe {
                let d = d.add((t.c0 + c) * BLOCK);
                _mm512_storeu_ps(d, acc[0]);
                _mm512_storeu_ps(d.add(16), acc[1]);
            }
        }
    }

    #[target_feature(enable = "avx2,fma")]
    pub(super) unsafe fn gemm_avx2(
        panel: &[f32],
        feat: &[f32],
        k: usize,
        n: usize,
        dst: &mut [f32],
    ) {
        for (t, nr) in tiles(k, n, NR256) {
            // SAFETY: as for AVX-512.
            unsafe {
                match nr {
                    3 => tile256::<3>(panel, feat, t, dst),
                    2 => tile256::<2>(panel, feat, t, dst),
                    _ => tile256::<1>(panel, feat, t, dst),
                }
            }
        }
    }

    #[inline]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn tile256<const NR: usize>(panel: &[f32], feat: &[f32], t: Tile, dst: &mut [f32]) {
        let d = dst.as_mut_ptr();
        let mut acc = [[_mm256_setzero_ps(); 4]; NR];
        if t.acc {
            for (c, acc) in acc.iter_mut().enumerate() {
                // SAFETY: as in `tile512`.
                unsafe {
                    let d = d.add((t.c0 + c) * BLOCK);
                    for (r, v) in acc.iter_mut().enumerate() {
                        *v = _mm256_loadu_ps(d.add(r * 8));
                    }
                }
            }
        }
        let p = panel.as_ptr();
        let f = feat.as_ptr();
        for q in t.q0..t.q1 {
            // SAFETY: as in `tile512`.
            unsafe {
                let a = [
                    _mm256_loadu_ps(p.add(q * BLOCK)),
                    _mm256_loadu_ps(p.add(q * BLOCK + 8)),
                    _mm256_loadu_ps(p.add(q * BLOCK + 16)),
                    _mm256_loadu_ps(p.add(q * BLOCK + 24)),
                ];
                let fr = f.add(q * t.n + t.c0);
                for (c, acc) in acc.iter_mut().enumerate() {
                    let w = _mm256_set1_ps(*fr.add(c));
                    for r in 0..4 {
                        acc[r] = _mm256_fmadd_ps(a[r], w, acc[r]);
                    }
                }
            }
        }
        for (c, acc) in acc.iter().enumerate() {
            // SAFETY: as in `tile512`.
            unsafe {
                let d = d.add((t.c0 + c) * BLOCK);
                for (r, v) in acc.iter().enumerate() {
                    _mm256_storeu_ps(d.add(r * 8), *v);
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cpu::Isa;

    /// Every kernel the machine can run equals a plain f64 product (random panel and features, column
    /// counts that exercise every tile width and tail).
    #[test]
    fn gemm_kernels_match_a_plain_product() {
        #[allow(unused_mut)] // only x86-64 adds kernels
        let mut isas = vec![Isa::Portable];
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
            {
                isas.push(Isa::Avx2);
            }
            if std::arch::is_x86_feature_detected!("avx512f") {
                isas.push(Isa::Avx512);
            }
        }
        // k = 150 spans two full row chunks and a partial one; k = 37 fits in one.
        for (k, n) in [37usize, 150]
            .into_iter()
            .flat_map(|k| [1usize, 2, 3, 5, 12, 13, 30, 31].map(|n| (k, n)))
        {
            let panel: Vec<f32> = (0..k * BLOCK).map(|i| ((i as f32) * 0.731).sin()).collect();
            let feat: Vec<f32> = (0..k * n).map(|i| ((i as f32) * 0.417).cos()).collect();
            for &isa in &isas {
                let mut dst = vec![f32::NAN; n * BLOCK];
                gemm_panel(isa, &panel, &feat, k, n, &mut dst);
                for c in 0..n {
                    for i in 0..BLOCK {
                        let want: f64 = (0..k)
                            .map(|q| panel[q * BLOCK + i] as f64 * feat[q * n + c] as f64)
                            .sum();
                        let got = dst[c * BLOCK + i] as f64;
                        assert!(
                            (got - want).abs() < 1e-4,
                            "{isa:?} k={k} n={n} column {c} lane {i}: {got} vs {want}"
                        );
                    }
                }
            }
        }
    }
}
