//! Memory-efficient attention: `softmax(q k^T * scale) v` computed over tiles of queries and keys, so
//! that the `[N, N]` score matrix never exists whole.
//!
//! The forward keeps a running maximum and sum per query row while it walks the key tiles (the online
//! softmax) and stores only the output and each row's log-sum-exp. The backward recomputes each tile's
//! scores from `q`, `k` and that log-sum-exp (the probabilities are `exp(s - lse)`), so what autodiff
//! keeps grows linearly in the tokens: `q`, `k`, `v`, the output and one number per query row.
//! burn's own attention keeps the probabilities of every head, `[B, H, N, N]`, for its backward.
//!
//! Backward of one tile (`p` the probabilities, `do` the output gradient, `delta = rowsum(do * o)`):
//! `dv += p^T do`, `dp = do v^T`, `ds = p * (dp - delta) * scale`, `dq += ds k`, `dk += ds^T q`.

// burn-ndarray is deprecated but still a `--device` the CLI offers: the operation is registered for it.
#![allow(deprecated)]

#[cfg(feature = "wgpu")]
use burn::backend::Cube;
use burn::backend::NdArray;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Device, Slice, Tensor, TensorData};
use std::any::TypeId;
use std::sync::atomic::{AtomicBool, Ordering};

use crate::attention_host::{self, Layout, Operand};
use crate::cpu::SendPtr;
use crate::host::{HostF32, dims, par_zeroed};
use std::ops::Range;

/// Rows and columns of one score tile. 512 x 512 keeps a tile of 16 heads at 16 MiB, small beside the
/// activations around it and large enough that each matmul stays efficient.
pub const DEFAULT_BLOCK: usize = 512;

/// Attention with the tiled forward and, under autodiff, the recomputing backward.
///
/// `q [B, H, Nq, D]`, `k [B, H, Nk, D]`, `v [B, H, Nk, Dv]` -> `[B, H, Nq, Dv]`; `block` is the side of
/// a score tile (queries and keys). Panics when there are no keys (the softmax of nothing).
pub fn attention(q: Tensor<4>, k: Tensor<4>, v: Tensor<4>, scale: f64, block: usize) -> Tensor<4> {
    assert!(k.dims()[2] > 0, "attention over zero keys");
    assert!(block > 0, "attention tiles need a positive side");
    if q.dims()[2] == 0 {
        return plain_attention(q, k, v, scale);
    }
    let out = <Dispatch as AttentionBackend>::tiled_attention(
        q.into_dispatch(),
        k.into_dispatch(),
        v.into_dispatch(),
        scale,
        block,
    );
    Tensor::from_dispatch(out)
}

/// Multi-head self-attention straight from the tokens' packed projection `qkv [B, N, 3 C]` (each
/// row `[q; k; v]`, each of those ordered by head): `[B, N, C]`, the heads joined again. On flex with
/// tiles (`block` > 0) one operation that reads and writes every head where it lies, so that neither
/// splitting the heads nor joining them copies anything, forward or backward; elsewhere the heads are
/// split out, attended by [`attention`] (burn's ops when `block` is 0) and joined.
pub fn packed_self_attention(qkv: Tensor<3>, heads: usize, scale: f64, block: usize) -> Tensor<3> {
    let [b, n, c3] = qkv.dims();
    assert!(
        heads > 0 && c3 % (3 * heads) == 0,
        "packed attention: {c3} projected channels for {heads} heads"
    );
    let (c, d) = (c3 / 3, c3 / 3 / heads);
    let host = qkv.device() == Device::flex() && HOST_ATTENTION.load(Ordering::Relaxed);
    if host && block > 0 && n * d > 0 {
        let out = <Dispatch as PackedAttentionBackend>::packed_attention(
            qkv.into_dispatch(),
            heads,
            scale,
            block,
        );
        return Tensor::from_dispatch(out);
    }
    let qkv = qkv.reshape([b, n, 3, heads, d]).permute([2, 0, 3, 1, 4]); // [3, B, h, N, d]
    let part = |i| qkv.clone().narrow(0, i, 1).reshape([b, heads, n, d]);
    let (q, k, v) = (part(0), part(1), part(2));
    let out = match block {
        0 => plain_attention(q, k, v, scale),
        t => attention(q, k, v, scale, t),
    };
    out.swap_dims(1, 2).reshape([b, n, c])
}

/// The backend side of [`packed_self_attention`]; autodiff adds the backward.
#[backend_extension(Flex, Autodiff)]
pub trait PackedAttentionBackend: Backend {
    fn packed_attention(
        qkv: FloatTensor<Self>,
        heads: usize,
        scale: f64,
        block: usize,
    ) -> FloatTensor<Self> {
        packed_forward::<Self>(qkv, heads, scale, block).0
    }
}

impl PackedAttentionBackend for Flex {}

impl<B: Backend + PackedAttentionBackend, C: CheckpointStrategy> PackedAttentionBackend
    for Autodiff<B, C>
{
    fn packed_attention(
        qkv: FloatTensor<Self>,
        heads: usize,
        scale: f64,
        block: usize,
    ) -> FloatTensor<Self> {
        let guards = [qkv.node()];
        let qkv = qkv.into_primitive();
        let (out, lse) = packed_forward::<B>(qkv.clone(), heads, scale, block);
        match PackedBackward
            .prepare::<C>(guards)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let state = PackedSaved {
                    qkv,
                    out: out.clone(),
                    lse,
                    heads,
                    scale,
                    block,
                };
                prep.finish(state, out)
            }
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

/// The sizes of a packed self-attention, and the layouts of q, k, v (each from its part's first
/// value) and of the joined output.
fn packed_dims(
    [b, n, c3]: [usize; 3],
    heads: usize,
    scale: f64,
    block: usize,
) -> (attention_host::Dims, [Layout; 4]) {
    let d = c3 / 3 / heads;
    let dm = attention_host::Dims {
        items: b,
        per_item: heads,
        nq: n,
        nk: n,
        d,
        dv: d,
        scale: scale as f32,
        rows: block,
    };
    let part = Layout::tokens_first(heads, n, d, 3);
    (dm, [part, part, part, Layout::tokens_first(heads, n, d, 1)])
}

/// q, k and v of the packed projection `qkv` of `c` channels each.
fn packed_inputs<'a>(qkv: &'a [f32], c: usize, lay: &[Layout; 4]) -> attention_host::Inputs<'a> {
    let parts = [qkv, &qkv[c..], &qkv[2 * c..]];
    attention_host::Inputs::new(parts, [lay[0], lay[1], lay[2]])
}

/// The joined output `[B, N, C]` and each (item, head, query)'s log-sum-exp.
fn packed_forward<B: Backend>(
    qkv: FloatTensor<B>,
    heads: usize,
    scale: f64,
    block: usize,
) -> (FloatTensor<B>, Vec<f32>) {
    let device = qkv.device();
    let shape: [usize; 3] = dims(&qkv);
    let [b, n, c3] = shape;
    let (dm, lay) = packed_dims(shape, heads, scale, block);
    let qkv = HostF32::read::<B>(qkv);
    let x = packed_inputs(&qkv, c3 / 3, &lay);
    let (out, lse) = attention_host::forward(x, lay[3], b * n * c3 / 3, dm);
    let out = B::float_from_data(TensorData::new(out, [b, n, c3 / 3]), &device);
    (out, lse)
}

#[derive(Debug)]
struct PackedBackward;

/// What the packed backward needs: the projection, the output and the log-sum-exp.
#[derive(Debug, Clone)]
struct PackedSaved<B: Backend> {
    qkv: FloatTensor<B>,
    out: FloatTensor<B>,
    lse: Vec<f32>,
    heads: usize,
    scale: f64,
    block: usize,
}

impl<B: Backend> Backward<B, 1> for PackedBackward {
    type State = PackedSaved<B>;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node] = ops.parents;
        let dout = grads.consume::<B>(&ops.node);
        let Some(node) = node else { return };
        let s = ops.state;
        let device = dout.device();
        let shape: [usize; 3] = dims(&s.qkv);
        let c = shape[2] / 3;
        let (dm, lay) = packed_dims(shape, s.heads, s.scale, s.block);
        let (qkv, out) = (HostF32::read::<B>(s.qkv), HostF32::read::<B>(s.out));
        let saved = attention_host::Saved {
            x: packed_inputs(&qkv, c, &lay),
            out: Operand {
                values: &out,
                layout: lay[3],
            },
            lse: &s.lse,
        };
        let mut dqkv = par_zeroed(qkv.len());
        let base = dqkv.as_mut_ptr();
        let g = attention_host::Grads {
            dst: std::array::from_fn(|i| SendPtr(base.wrapping_add(i * c))),
            layouts: [lay[0], lay[1], lay[2]],
        };
        // SAFETY: `dqkv` is zeroed, shaped as the projection whose parts these layouts address, and
        // read only once the call returns.
        unsafe { attention_host::backward(&saved, &HostF32::read::<B>(dout), dm, &g) };
        let dqkv = B::float_from_data(TensorData::new(dqkv, shape), &device);
        grads.register::<B>(node.id, dqkv);
    }
}

/// burn's attention as plain tensor ops, `softmax(q k^T * scale) v`: the reference the tiled operation
/// is tested against, and what training uses when tiling is off.
pub fn plain_attention(q: Tensor<4>, k: Tensor<4>, v: Tensor<4>, scale: f64) -> Tensor<4> {
    let scores = q.matmul(k.swap_dims(2, 3)) * scale;
    burn::tensor::activation::softmax(scores, 3).matmul(v)
}

/// The backend side of [`attention`]. Flex runs the host passes; the other backends the same tiled
/// forward, written in their own float ops; autodiff adds the recomputing backward.
#[backend_extension(Flex, NdArray, Cube: cfg(feature = "wgpu"), Autodiff)]
pub trait AttentionBackend: Backend {
    fn tiled_attention(
        q: FloatTensor<Self>,
        k: FloatTensor<Self>,
        v: FloatTensor<Self>,
        scale: f64,
        block: usize,
    ) -> FloatTensor<Self> {
        forward_any::<Self>(q, k, v, scale, block).0
    }
}

impl AttentionBackend for Flex {}
impl AttentionBackend for NdArray {}
#[cfg(feature = "wgpu")]
impl AttentionBackend for Cube {}

impl<B: Backend + AttentionBackend, C: CheckpointStrategy> AttentionBackend for Autodiff<B, C> {
    fn tiled_attention(
        q: FloatTensor<Self>,
        k: FloatTensor<Self>,
        v: FloatTensor<Self>,
        scale: f64,
        block: usize,
    ) -> FloatTensor<Self> {
        let guards = [q.node(), k.node(), v.node()];
        let (q, k, v) = (q.into_primitive(), k.into_primitive(), v.into_primitive());
        let (out, lse) = forward_any::<B>(q.clone(), k.clone(), v.clone(), scale, block);
        // Compute-bound: a checkpointing strategy keeps this state rather than rerunning the tiles.
        match TiledBackward
            .prepare::<C>(guards)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let state = Saved {
                    q,
                    k,
                    v,
                    out: out.clone(),
                    lse,
                    scale,
                    block,
                };
                prep.finish(state, out)
            }
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

#[derive(Debug)]
struct TiledBackward;

/// What the backward needs: the inputs, the output and each query row's log-sum-exp `[B, H, Nq, 1]`.
#[derive(Debug, Clone)]
struct Saved<B: Backend> {
    q: FloatTensor<B>,
    k: FloatTensor<B>,
    v: FloatTensor<B>,
    out: FloatTensor<B>,
    lse: FloatTensor<B>,
    scale: f64,
    block: usize,
}

impl<B: Backend> Backward<B, 3> for TiledBackward {
    type State = Saved<B>;

    fn backward(self, ops: Ops<Self::State, 3>, grads: &mut Gradients, _: &mut Checkpointer) {
        let [node_q, node_k, node_v] = ops.parents;
        let grad = grads.consume::<B>(&ops.node);
        let [dq, dk, dv] = match host_dims::<B>(&ops.state.q, &ops.state.v, ops.state.k.shape()[2])
        {
            Some((dm, device)) => host_backward::<B>(ops.state, grad, dm, &device),
            None => backward::<B>(ops.state, grad),
        };
        for (node, g) in [(node_q, dq), (node_k, dk), (node_v, dv)] {
            if let Some(node) = node {
                grads.register::<B>(node.id, g);
            }
        }
    }
}

/// Rows `range` of dimension `dim` of a 4D tensor.
fn rows<B: Backend>(t: &FloatTensor<B>, dim: usize, range: Range<usize>) -> FloatTensor<B> {
    let mut slices = [
        Slice::from(..),
        Slice::from(..),
        Slice::from(..),
        Slice::from(..),
    ];
    slices[dim] = Slice::from(range);
    B::float_slice(t.clone(), &slices)
}

/// The tile ranges of `n` rows.
fn tiles(n: usize, block: usize) -> impl Iterator<Item = Range<usize>> {
    (0..n).step_by(block).map(move |s| s..(s + block).min(n))
}

fn add_into<B: Backend>(acc: &mut Option<FloatTensor<B>>, x: FloatTensor<B>) {
    *acc = Some(match acc.take() {
        Some(a) => B::float_add(a, x),
        None => x,
    });
}

static HOST_ATTENTION: AtomicBool = AtomicBool::new(true);

/// Whether flex takes the host passes (the default) or the tiled forward and backward in burn's ops;
/// process-wide, so that a benchmark can time both.
pub fn set_host_attention(on: bool) {
    HOST_ATTENTION.store(on, Ordering::Relaxed);
}

/// The problem's sizes when it runs as host passes (on flex, with queries, keys and values of some
/// width), and the device for the results.
fn host_dims<B: Backend>(
    q: &FloatTensor<B>,
    v: &FloatTensor<B>,
    nk: usize,
) -> Option<(attention_host::Dims, B::Device)> {
    let on_flex =
        TypeId::of::<B>() == TypeId::of::<Flex>() && HOST_ATTENTION.load(Ordering::Relaxed);
    let [b, h, nq, d]: [usize; 4] = dims(q);
    let dv = v.shape()[3];
    let dm = attention_host::Dims {
        items: b,
        per_item: h,
        nq,
        nk,
        d,
        dv,
        scale: 0.0,
        rows: 0,
    };
    (on_flex && nq * nk * d * dv > 0).then(|| (dm, q.device()))
}

/// Heads-first layouts of q, k, v and the output for `dm`.
fn heads_first(dm: &attention_host::Dims) -> [Layout; 4] {
    let h = dm.per_item;
    [
        Layout::heads_first(h, dm.nq, dm.d),
        Layout::heads_first(h, dm.nk, dm.d),
        Layout::heads_first(h, dm.nk, dm.dv),
        Layout::heads_first(h, dm.nq, dm.dv),
    ]
}

/// The forward on the host where [`host_dims`] allows, in burn's ops elsewhere.
fn forward_any<B: Backend>(
    q: FloatTensor<B>,
    k: FloatTensor<B>,
    v: FloatTensor<B>,
    scale: f64,
    block: usize,
) -> (FloatTensor<B>, FloatTensor<B>) {
    let Some((dm, device)) = host_dims::<B>(&q, &v, k.shape()[2]) else {
        return forward::<B>(q, k, v, scale, block);
    };
    let dm = attention_host::Dims {
        scale: scale as f32,
        rows: block,
        ..dm
    };
    let [lq, lk, lv, lo] = heads_first(&dm);
    let (q, k, v) = (
        HostF32::read::<B>(q),
        HostF32::read::<B>(k),
        HostF32::read::<B>(v),
    );
    let x = attention_host::Inputs::new([&q, &k, &v], [lq, lk, lv]);
    let [b, h, nq, dv] = [dm.items, dm.per_item, dm.nq, dm.dv];
    let (out, lse) = attention_host::forward(x, lo, b * h * nq * dv, dm);
    (
        B::float_from_data(TensorData::new(out, [b, h, nq, dv]), &device),
        B::float_from_data(TensorData::new(lse, [b, h, nq, 1]), &device),
    )
}

/// The backward on the host (see [`host_dims`]).
fn host_backward<B: Backend>(
    s: Saved<B>,
    dout: FloatTensor<B>,
    dm: attention_host::Dims,
    device: &B::Device,
) -> [FloatTensor<B>; 3] {
    let dm = attention_host::Dims {
        scale: s.scale as f32,
        rows: s.block,
        ..dm
    };
    let shapes = [s.q.shape(), s.k.shape(), s.v.shape()];
    let read = |t: &FloatTensor<B>| HostF32::read::<B>(t.clone());
    let (q, k, v, out, lse) = (
        read(&s.q),
        read(&s.k),
        read(&s.v),
        read(&s.out),
        read(&s.lse),
    );
    let [lq, lk, lv, lo] = heads_first(&dm);
    let saved = attention_host::Saved {
        x: attention_host::Inputs::new([&q, &k, &v], [lq, lk, lv]),
        out: Operand {
            values: &out,
            layout: lo,
        },
        lse: &lse,
    };
    let mut grads = [q.len(), k.len(), v.len()].map(par_zeroed);
    let g = attention_host::Grads {
        dst: std::array::from_fn(|i| SendPtr(grads[i].as_mut_ptr())),
        layouts: [lq, lk, lv],
    };
    // SAFETY: the buffers are zeroed, sized as q, k and v whose layouts these are, and only read
    // back once the call returns.
    unsafe { attention_host::backward(&saved, &HostF32::read::<B>(dout), dm, &g) };
    let mut shapes = shapes.into_iter();
    grads.map(|g| {
        let shape = shapes.next().expect("one shape per gradient");
        B::float_from_data(TensorData::new(g, shape), device)
    })
}

/// The tiled forward: the output `[B, H, Nq, Dv]` and each query row's log-sum-exp `[B, H, Nq, 1]`.
fn forward<B: Backend>(
    q: FloatTensor<B>,
    k: FloatTensor<B>,
    v: FloatTensor<B>,
    scale: f64,
    block: usize,
) -> (FloatTensor<B>, FloatTensor<B>) {
    let (nq, nk) = (q.shape()[2], k.shape()[2]);
    let kt = B::float_swap_dims(k, 2, 3); // [B, H, D, Nk]
    let (mut outs, mut lses) = (Vec::new(), Vec::new());
    for qr in tiles(nq, block) {
        let qb = B::float_mul_scalar(rows::<B>(&q, 2, qr), scale.into());
        // Running row maximum `m`, sum `l` of exp(s - m), and output sum `acc` scaled by exp(-m).
        let mut run: Option<(FloatTensor<B>, FloatTensor<B>, FloatTensor<B>)> = None;
        for kr in tiles(nk, block) {
            let s = B::float_matmul(qb.clone(), rows::<B>(&kt, 3, kr.clone()));
            let vb = rows::<B>(&v, 2, kr);
            let tile_max = B::float_max_dim(s.clone(), 3);
            run = Some(match run {
                None => {
                    let p = B::float_exp(B::float_sub(s, tile_max.clone()));
                    (
                        tile_max,
                        B::float_sum_dim(p.clone(), 3),
                        B::float_matmul(p, vb),
                    )
                }
                Some((m, l, acc)) => {
                    let m_new = B::float_max_dim(B::float_cat(vec![m.clone(), tile_max], 3), 3);
                    let alpha = B::float_exp(B::float_sub(m, m_new.clone()));
                    let p = B::float_exp(B::float_sub(s, m_new.clone()));
                    let l = B::float_add(
                        B::float_mul(l, alpha.clone()),
                        B::float_sum_dim(p.clone(), 3),
                    );
                    let acc = B::float_add(B::float_mul(acc, alpha), B::float_matmul(p, vb));
                    (m_new, l, acc)
                }
            });
        }
        let (m, l, acc) = run.expect("at least one key tile");
        outs.push(B::float_div(acc, l.clone()));
        lses.push(B::float_add(m, B::float_log(l)));
    }
    (B::float_cat(outs, 2), B::float_cat(lses, 2))
}

/// The recomputing backward: gradients of `q`, `k`, `v` from the output gradient `dout`.
fn backward<B: Backend>(s: Saved<B>, dout: FloatTensor<B>) -> [FloatTensor<B>; 3] {
    let (nq, nk) = (s.q.shape()[2], s.k.shape()[2]);
    let delta = B::float_sum_dim(B::float_mul(dout.clone(), s.out), 3); // [B, H, Nq, 1]
    let kt = B::float_swap_dims(s.k.clone(), 2, 3);
    let vt = B::float_swap_dims(s.v.clone(), 2, 3);
    let key_tiles: Vec<_> = tiles(nk, s.block).collect();
    let mut dk: Vec<Option<FloatTensor<B>>> = vec![None; key_tiles.len()];
    let mut dv: Vec<Option<FloatTensor<B>>> = vec![None; key_tiles.len()];
    let mut dq = Vec::new();
    for qr in tiles(nq, s.block) {
        let qb = rows::<B>(&s.q, 2, qr.clone());
        let qs = B::float_mul_scalar(qb.clone(), s.scale.into());
        let (dob, lse, dl) = (
            rows::<B>(&dout, 2, qr.clone()),
            rows::<B>(&s.lse, 2, qr.clone()),
            rows::<B>(&delta, 2, qr),
        );
        let mut dqb = None;
        for (j, kr) in key_tiles.iter().enumerate() {
            let scores = B::float_matmul(qs.clone(), rows::<B>(&kt, 3, kr.clone()));
            let p = B::float_exp(B::float_sub(scores, lse.clone())); // [B, H, bq, bk]
            let pt = B::float_swap_dims(p.clone(), 2, 3);
            add_into::<B>(&mut dv[j], B::float_matmul(pt, dob.clone()));
            let dp = B::float_matmul(dob.clone(), rows::<B>(&vt, 3, kr.clone()));
            let ds = B::float_mul_scalar(
                B::float_mul(p, B::float_sub(dp, dl.clone())),
                s.scale.into(),
            );
            add_into::<B>(
                &mut dqb,
                B::float_matmul(ds.clone(), rows::<B>(&s.k, 2, kr.clone())),
            );
            add_into::<B>(
                &mut dk[j],
                B::float_matmul(B::float_swap_dims(ds, 2, 3), qb.clone()),
            );
        }
        dq.push(dqb.expect("at least one key tile"));
    }
    let cat = |parts: Vec<Option<FloatTensor<B>>>| {
        B::float_cat(
            parts
                .into_iter()
                .map(|p| p.expect("every key tile met a query tile"))
                .collect(),
            2,
        )
    };
    [B::float_cat(dq, 2), cat(dk), cat(dv)]
}
