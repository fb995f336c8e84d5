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
//! Queries, keys, values, the output and the gradients are read and written where they lie
//! ([`Layout`]): heads first, or the tokens' packed projection `[B, N, 3 H d]` itself, so that a
//! self-attention needs no copies to split its heads and join them again.
//!
//! The forward runs every (head, query tile) in parallel. The backward runs heads in parallel and a
//! head's query tiles in order, so each head's key and value gradients are summed in one order whatever
//! the number of threads.
use rayon::prelude::*;

use crate::cpu::SendPtr;
use crate::product::{Mat, gemm, written};

/// Query rows per tile at most (fewer when the caller's tile is smaller).
const MAX_ROWS: usize = 64;

/// Where each head's rows of one operand lie: item `b`'s head `j` starts at `b * item + j * head`, its
/// rows `row` apart, each row's values next to each other.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Layout {
    pub item: usize,
    pub head: usize,
    pub row: usize,
}

impl Layout {
    /// `[B, H, n, w]`, contiguous.
    pub fn heads_first(heads: usize, n: usize, w: usize) -> Layout {
        Layout {
            item: heads * n * w,
            head: n * w,
            row: w,
        }
    }

    /// One of `parts` parts of `[B, n, parts * H * w]` (the packed projection, or with one part the
    /// heads joined again), from that part's first value on.
    pub fn tokens_first(heads: usize, n: usize, w: usize, parts: usize) -> Layout {
        Layout {
            item: n * parts * heads * w,
            head: w,
            row: parts * heads * w,
        }
    }
}

/// The sizes of one call: `items x per_item` independent heads of `nq` queries and `nk` keys, `d`
/// wide queries and keys, `dv` wide values.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Dims {
    pub items: usize,
    pub per_item: usize,
    pub nq: usize,
    pub nk: usize,
    pub d: usize,
    pub dv: usize,
    pub scale: f32,
    pub rows: usize,
}

impl Dims {
    fn heads(&self) -> usize {
        self.items * self.per_item
    }

    /// Where head `h` (item-major) starts in an operand laid out as `lay`.
    fn at(&self, lay: Layout, h: usize) -> usize {
        (h / self.per_item) * lay.item + (h % self.per_item) * lay.head
    }

    fn tiles(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        let rows = self.rows.clamp(1, MAX_ROWS);
        (0..self.nq)
            .step_by(rows)
            .map(move |s| (s, rows.min(self.nq - s)))
    }
}

/// An operand and its layout.
#[derive(Clone, Copy)]
pub(crate) struct Operand<'a> {
    pub values: &'a [f32],
    pub layout: Layout,
}

impl Operand<'_> {
    /// Head `h`'s rows from row `r` on, as a matrix of rows.
    fn rows(&self, dm: &Dims, h: usize, r: usize) -> Mat {
        Mat::at(
            &self.values[dm.at(self.layout, h) + r * self.layout.row..],
            self.layout.row,
            1,
        )
    }

    /// Head `h`'s rows as the columns of a matrix (the transpose).
    fn columns(&self, dm: &Dims, h: usize) -> Mat {
        Mat::at(&self.values[dm.at(self.layout, h)..], 1, self.layout.row)
    }

    /// Row `r` of head `h`, `w` values.
    fn row(&self, dm: &Dims, h: usize, r: usize, w: usize) -> &[f32] {
        let s = dm.at(self.layout, h) + r * self.layout.row;
        &self.values[s..s + w]
    }
}

/// The inputs: queries, keys and values.
#[derive(Clone, Copy)]
pub(crate) struct Inputs<'a> {
    pub q: Operand<'a>,
    pub k: Operand<'a>,
    pub v: Operand<'a>,
}

impl<'a> Inputs<'a> {
    /// q, k and v, each with its layout.
    pub fn new([q, k, v]: [&'a [f32]; 3], [lq, lk, lv]: [Layout; 3]) -> Self {
        let at = |values, layout| Operand { values, layout };
        Inputs {
            q: at(q, lq),
            k: at(k, lk),
            v: at(v, lv),
        }
    }
}

/// `scores [t, nk] = q_tile . k^T` for head `h`'s query rows `s..s + t`, scaled.
fn scores(x: &Inputs, dm: &Dims, h: usize, (s, t): (usize, usize), out: &mut [f32]) {
    let (nk, d) = (dm.nk, dm.d);
    // SAFETY: `out` holds t x nk values; the reads lie within head h's rows of q and k.
    unsafe {
        gemm(
            out.as_mut_ptr(),
            nk,
            false,
            x.q.rows(dm, h, s),
            x.k.columns(dm, h),
            t,
            d,
            nk,
        )
    };
    out.iter_mut().for_each(|x| *x *= dm.scale);
}

/// The output, `len` values laid out as `out` (every head's rows of it written), and each query row's
/// log-sum-exp `[heads, nq]`.
pub(crate) fn forward(x: Inputs, out: Layout, len: usize, dm: Dims) -> (Vec<f32>, Vec<f32>) {
    let Dims { nq, nk, dv, .. } = dm;
    let tasks: Vec<(usize, (usize, usize))> = (0..dm.heads())
        .flat_map(|h| dm.tiles().map(move |tile| (h, tile)))
        .collect();
    let mut lse = vec![0f32; dm.heads() * nq];
    let lse_ptr = SendPtr(lse.as_mut_ptr());
    let write = |dst: SendPtr| {
        tasks.par_iter().for_each(|&(h, (s, t))| {
            let mut p = vec![0f32; t * nk];
            scores(&x, &dm, h, (s, t), &mut p);
            let mut sums = vec![0f32; t];
            for (i, row) in p.chunks_exact_mut(nk).enumerate() {
                let m = row.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b));
                crate::vmath::exp_shifted(row, m);
                sums[i] = row.iter().sum();
                // SAFETY: row s + i of head h is this task's alone.
                unsafe { *lse_ptr.get().add(h * nq + s + i) = m + sums[i].ln() };
            }
            let first = dst.get().wrapping_add(dm.at(out, h) + s * out.row);
            let (p_m, v_m) = (Mat::at(&p, nk, 1), x.v.rows(&dm, h, 0));
            // SAFETY: the task writes its own t rows of head h's dv columns, without reading them.
            unsafe { gemm(first, out.row, false, p_m, v_m, t, nk, dv) };
            for (i, l) in sums.iter().enumerate() {
                // SAFETY: as above; the values were just written.
                let row = unsafe { std::slice::from_raw_parts_mut(first.add(i * out.row), dv) };
                row.iter_mut().for_each(|x| *x /= l);
            }
        })
    };
    // SAFETY: the caller's layout has every value belong to one (head, query row), all written above.
    let out = unsafe { written(len, write) };
    (out, lse)
}

/// What the backward reads besides the output gradient (laid out as the output): the inputs, the
/// output and the log-sum-exp.
pub(crate) struct Saved<'a> {
    pub x: Inputs<'a>,
    pub out: Operand<'a>,
    pub lse: &'a [f32],
}

/// Where the gradients of q, k and v go: zeroed buffers, each head's part of them written by it alone.
pub(crate) struct Grads {
    pub dst: [SendPtr; 3],
    pub layouts: [Layout; 3],
}

// SAFETY: the pointers are written only as `backward` describes, each head its own values.
unsafe impl Sync for Grads {}

/// The gradients of q, k and v from the output gradient, into `g`.
///
/// # Safety
/// `g`'s buffers must be zeroed, hold every value their layouts address for these sizes, and not be
/// accessed otherwise until this returns.
pub(crate) unsafe fn backward(s: &Saved, dout: &[f32], dm: Dims, g: &Grads) {
    assert_eq!(s.lse.len(), dm.heads() * dm.nq);
    (0..dm.heads()).into_par_iter().for_each(|h| {
        // SAFETY: head h writes only its own rows and columns (the caller vouches for the buffers).
        unsafe { head_backward(s, dout, &dm, h, g) }
    });
}

/// One head's gradients, its query tiles in order.
///
/// # Safety
/// As [`backward`]; no other call writes head `h`'s values meanwhile.
unsafe fn head_backward(s: &Saved, dout: &[f32], dm: &Dims, h: usize, g: &Grads) {
    let Dims { nk, d, dv, .. } = *dm;
    let dout = Operand {
        values: dout,
        layout: s.out.layout,
    };
    let [dq, dk, dvh] =
        std::array::from_fn(|i| g.dst[i].get().wrapping_add(dm.at(g.layouts[i], h)));
    let [lq, lk, lv] = g.layouts;
    let mut p = Vec::new();
    let mut ds = Vec::new();
    for (st, t) in dm.tiles() {
        p.resize(t * nk, 0.0);
        ds.resize(t * nk, 0.0);
        scores(&s.x, dm, h, (st, t), &mut p);
        for (i, row) in p.chunks_exact_mut(nk).enumerate() {
            let l = s.lse[h * dm.nq + st + i];
            crate::vmath::exp_shifted(row, l);
        }
        let do_t = dout.rows(dm, h, st);
        // SAFETY (all four products): each destination is head h's own (the caller's buffers) or a
        // buffer of this call's, sized as written; every read lies within head h's rows.
        unsafe {
            // dv += p^T . do
            gemm(dvh, lv.row, true, Mat::at(&p, 1, nk), do_t, nk, t, dv);
            // dp = do . v^T, then ds = p * (dp - delta) * scale in place.
            gemm(
                ds.as_mut_ptr(),
                nk,
                false,
                do_t,
                s.x.v.columns(dm, h),
                t,
                dv,
                nk,
            );
        }
        for (i, (dsr, pr)) in ds.chunks_exact_mut(nk).zip(p.chunks_exact(nk)).enumerate() {
            let (dor, or) = (dout.row(dm, h, st + i, dv), s.out.row(dm, h, st + i, dv));
            let delta: f32 = dor.iter().zip(or).map(|(a, b)| a * b).sum();
            dsr.iter_mut()
                .zip(pr)
                .for_each(|(x, &pv)| *x = pv * (*x - delta) * dm.scale);
        }
        let (ds_rows, ds_cols) = (Mat::at(&ds, nk, 1), Mat::at(&ds, 1, nk));
        // SAFETY: as above.
        unsafe {
            // dq = ds . k for this tile's rows, dk += ds^T . q
            let dq_t = dq.add(st * lq.row);
            gemm(dq_t, lq.row, false, ds_rows, s.x.k.rows(dm, h, 0), t, nk, d);
            gemm(dk, lk.row, true, ds_cols, s.x.q.rows(dm, h, st), nk, t, d);
        }
    }
}
