//! The tiled attention's forward and recomputing backward as host passes on flex: per head, a tile of
//! query rows against every key at once, the scores in a buffer of the tile's own, each product one
//! GEMM over strided operands.
//!
//! Written in burn's ops (`attention`'s generic path), one tile of the tiny ViT's attention is a dozen
//! tensor operations each way, each a pass over a `[heads, rows, keys]` tensor with its own output
//! allocation, and transposed operands copied before their products; one block's attention forward and
//! backward took as long as its four linear layers. Here a tile's scores, probabilities and their
//! gradients stay in one buffer of `rows x keys` floats (a quarter of a megabyte for 64 rows of the
//! tiny ViT's 257 tokens, 2 MiB at the paper's 8465), so memory still grows linearly in the tokens.
//!
//! The forward runs every (head, query tile) in parallel. The backward runs heads in parallel and a
//! head's query tiles in order, so each head's key and value gradients are summed in one order whatever
//! the number of threads.
use rayon::prelude::*;

use crate::cpu::SendPtr;
use crate::product::{Mat, gemm, written};

/// Query rows per tile at most (fewer when the caller's tile is smaller).
const MAX_ROWS: usize = 64;

/// The sizes of one call: `heads` independent (batch x head) problems of `nq` queries and `nk` keys,
/// `d` wide queries and keys, `dv` wide values.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Dims {
    pub heads: usize,
    pub nq: usize,
    pub nk: usize,
    pub d: usize,
    pub dv: usize,
    pub scale: f32,
    pub rows: usize,
}

impl Dims {
    fn tiles(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        let rows = self.rows.clamp(1, MAX_ROWS);
        (0..self.nq)
            .step_by(rows)
            .map(move |s| (s, rows.min(self.nq - s)))
    }
}

/// `scores [t, nk] = q_tile . k^T` for head `h`'s query rows `s..s + t`, scaled.
fn scores(q: &[f32], k: &[f32], dm: Dims, h: usize, (s, t): (usize, usize), out: &mut [f32]) {
    let (nk, d) = (dm.nk, dm.d);
    let lhs = Mat::at(&q[(h * dm.nq + s) * d..], d, 1);
    let k_t = Mat::at(&k[h * nk * d..], 1, d);
    // SAFETY: `out` holds t x nk values; the reads lie within head h's rows of q and k.
    unsafe { gemm(out.as_mut_ptr(), nk, false, lhs, k_t, t, d, nk) };
    out.iter_mut().for_each(|x| *x *= dm.scale);
}

/// The output `[heads, nq, dv]` and each query row's log-sum-exp `[heads, nq]`.
pub(crate) fn forward(q: &[f32], k: &[f32], v: &[f32], dm: Dims) -> (Vec<f32>, Vec<f32>) {
    let Dims {
        heads,
        nq,
        nk,
        d,
        dv,
        ..
    } = dm;
    assert!(q.len() == heads * nq * d && k.len() == heads * nk * d && v.len() == heads * nk * dv);
    let tasks: Vec<(usize, (usize, usize))> = (0..heads)
        .flat_map(|h| dm.tiles().map(move |tile| (h, tile)))
        .collect();
    let mut lse = vec![0f32; heads * nq];
    let lse_ptr = SendPtr(lse.as_mut_ptr());
    let write = |out: SendPtr| {
        tasks.par_iter().for_each(|&(h, (s, t))| {
            let mut p = vec![0f32; t * nk];
            scores(q, k, dm, h, (s, t), &mut p);
            let mut sums = vec![0f32; t];
            for (i, row) in p.chunks_exact_mut(nk).enumerate() {
                let m = row.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b));
                row.iter_mut().for_each(|x| *x = (*x - m).exp());
                sums[i] = row.iter().sum();
                // SAFETY: row s + i of head h is this task's alone.
                unsafe { *lse_ptr.get().add(h * nq + s + i) = m + sums[i].ln() };
            }
            let dst = out.get().wrapping_add((h * nq + s) * dv);
            let vh = Mat::at(&v[h * nk * dv..], dv, 1);
            // SAFETY: the task writes its own t rows of the output, without reading them.
            unsafe { gemm(dst, dv, false, Mat::at(&p, nk, 1), vh, t, nk, dv) };
            for (i, l) in sums.iter().enumerate() {
                // SAFETY: as above; the rows were just written.
                let row = unsafe { std::slice::from_raw_parts_mut(dst.add(i * dv), dv) };
                row.iter_mut().for_each(|x| *x /= l);
            }
        })
    };
    // SAFETY: the tasks cover every (head, query row) and write all of its dv values.
    let out = unsafe { written(heads * nq * dv, write) };
    (out, lse)
}

/// What the backward reads besides the output gradient: the inputs, the output and the log-sum-exp.
pub(crate) struct Saved<'a> {
    pub q: &'a [f32],
    pub k: &'a [f32],
    pub v: &'a [f32],
    pub out: &'a [f32],
    pub lse: &'a [f32],
}

/// The gradients of q, k and v from the output gradient `dout [heads, nq, dv]`.
pub(crate) fn backward(s: Saved, dout: &[f32], dm: Dims) -> [Vec<f32>; 3] {
    let Dims {
        heads,
        nq,
        nk,
        d,
        dv,
        ..
    } = dm;
    assert!(
        dout.len() == heads * nq * dv && s.out.len() == dout.len() && s.lse.len() == heads * nq
    );
    let mut dq = vec![0f32; heads * nq * d];
    let mut dk = vec![0f32; heads * nk * d];
    let mut dv_all = vec![0f32; heads * nk * dv];
    dq.par_chunks_mut(nq * d)
        .zip(dk.par_chunks_mut(nk * d))
        .zip(dv_all.par_chunks_mut(nk * dv))
        .enumerate()
        .for_each(|(h, ((dq, dk), dvh))| head_backward(&s, dout, dm, h, [dq, dk, dvh]));
    [dq, dk, dv_all]
}

/// One head's gradients, its query tiles in order.
fn head_backward(s: &Saved, dout: &[f32], dm: Dims, h: usize, [dq, dk, dvh]: [&mut [f32]; 3]) {
    let Dims { nq, nk, d, dv, .. } = dm;
    let (do_h, o_h) = (&dout[h * nq * dv..], &s.out[h * nq * dv..]);
    let (q_h, k_h, v_h) = (&s.q[h * nq * d..], &s.k[h * nk * d..], &s.v[h * nk * dv..]);
    for (st, t) in dm.tiles() {
        let mut p = vec![0f32; t * nk];
        scores(s.q, s.k, dm, h, (st, t), &mut p);
        for (i, row) in p.chunks_exact_mut(nk).enumerate() {
            let l = s.lse[h * nq + st + i];
            row.iter_mut().for_each(|x| *x = (*x - l).exp());
        }
        let do_t = Mat::at(&do_h[st * dv..], dv, 1);
        // dv += p^T . do
        // SAFETY: every destination below is this head's own buffer or `dp`, sized as written.
        unsafe {
            gemm(
                dvh.as_mut_ptr(),
                dv,
                true,
                Mat::at(&p, 1, nk),
                do_t,
                nk,
                t,
                dv,
            )
        };
        // dp = do . v^T, then ds = p * (dp - delta) * scale in place.
        let mut ds = vec![0f32; t * nk];
        unsafe {
            gemm(
                ds.as_mut_ptr(),
                nk,
                false,
                do_t,
                Mat::at(v_h, 1, dv),
                t,
                dv,
                nk,
            )
        };
        for (i, (dsr, pr)) in ds.chunks_exact_mut(nk).zip(p.chunks_exact(nk)).enumerate() {
            let r = (st + i) * dv;
            let delta: f32 = do_h[r..r + dv]
                .iter()
                .zip(&o_h[r..r + dv])
                .map(|(a, b)| a * b)
                .sum();
            dsr.iter_mut()
                .zip(pr)
                .for_each(|(x, &pv)| *x = pv * (*x - delta) * dm.scale);
        }
        let ds_m = Mat::at(&ds, nk, 1);
        // dq = ds . k (this tile's rows), dk += ds^T . q
        unsafe {
            gemm(
                dq.as_mut_ptr().add(st * d),
                d,
                false,
                ds_m,
                Mat::at(k_h, d, 1),
                t,
                nk,
                d,
            )
        };
        let q_t = Mat::at(&q_h[st * d..], d, 1);
        unsafe { gemm(dk.as_mut_ptr(), d, true, Mat::at(&ds, 1, nk), q_t, nk, t, d) };
    }
}
