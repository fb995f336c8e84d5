//! Block recompute: a pre-norm transformer block (the DINOv2 ViT's, with layer scales) whose backward
//! recomputes it from its input instead of reading activations kept by the forward.
//!
//! Under autodiff the forward runs on the inner backend, so the graph keeps only the block's input and
//! its parameters. The backward rebuilds the block on a fresh autodiff graph from those, runs that
//! graph's backward with the incoming gradient, and hands the gradients of the input and of every
//! parameter to the outer graph. A ViT-L/14 block at 8465 tokens keeps one `[N, C]` input instead of
//! its norms, projections, GELU input and the attention's tensors.
//!
//! The block: `x += ls1 * proj(attn(norm1 x))`, then `x += ls2 * fc2(gelu(fc1(norm2 x)))`, with the
//! attention of [`crate::attention`] over `heads` heads (qkv rows ordered `[q; k; v]`, each by head).

// burn-ndarray is deprecated but still a `--device` the CLI offers: the operation is registered for it.
#![allow(deprecated)]

#[cfg(feature = "wgpu")]
use burn::backend::Cube;
use burn::backend::NdArray;
use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::ops::FloatTensorOps;
use burn::backend::tensor::FloatTensor;
use burn::backend::{
    Autodiff, AutodiffBackend, Backend, Dispatch, ExtensionType, Flex, TensorMetadata,
    backend_extension,
};
use burn::tensor::{Slice, Tensor};

use crate::attention::AttentionBackend;

/// The parameters of one block, in burn's layouts (`Linear` weights `[in, out]`).
#[derive(ExtensionType)]
pub struct BlockParams<B: Backend> {
    pub norm1_gamma: FloatTensor<B>,
    pub norm1_beta: FloatTensor<B>,
    pub qkv_weight: FloatTensor<B>,
    pub qkv_bias: FloatTensor<B>,
    pub proj_weight: FloatTensor<B>,
    pub proj_bias: FloatTensor<B>,
    pub ls1: FloatTensor<B>,
    pub norm2_gamma: FloatTensor<B>,
    pub norm2_beta: FloatTensor<B>,
    pub fc1_weight: FloatTensor<B>,
    pub fc1_bias: FloatTensor<B>,
    pub fc2_weight: FloatTensor<B>,
    pub fc2_bias: FloatTensor<B>,
    pub ls2: FloatTensor<B>,
}

const PARAMS: usize = 14;

impl<B: Backend> BlockParams<B> {
    fn into_array(self) -> [FloatTensor<B>; PARAMS] {
        [
            self.norm1_gamma,
            self.norm1_beta,
            self.qkv_weight,
            self.qkv_bias,
            self.proj_weight,
            self.proj_bias,
            self.ls1,
            self.norm2_gamma,
            self.norm2_beta,
            self.fc1_weight,
            self.fc1_bias,
            self.fc2_weight,
            self.fc2_bias,
            self.ls2,
        ]
    }
}

/// What the block needs besides tensors.
#[derive(Debug, Clone, Copy)]
pub struct BlockShape {
    pub heads: usize,
    /// Side of the attention's score tiles.
    pub tile: usize,
    /// The layer norms' epsilon.
    pub eps: f64,
}

/// One block on `x [B, N, C]`; under autodiff, recomputed in the backward.
pub fn block(x: Tensor<3>, params: BlockParams<Dispatch>, shape: BlockShape) -> Tensor<3> {
    let out = <Dispatch as BlockBackend>::recomputed_block(
        x.into_dispatch(),
        params,
        shape.heads,
        shape.tile,
        shape.eps,
    );
    Tensor::from_dispatch(out)
}

/// A tensor's backend value, for [`BlockParams`].
pub fn param<const D: usize>(t: Tensor<D>) -> FloatTensor<Dispatch> {
    t.into_dispatch()
}

#[backend_extension(Flex, NdArray, Cube: cfg(feature = "wgpu"), Autodiff)]
pub trait BlockBackend: AttentionBackend {
    fn recomputed_block(
        x: FloatTensor<Self>,
        #[extension_type] params: BlockParams<Self>,
        heads: usize,
        tile: usize,
        eps: f64,
    ) -> FloatTensor<Self> {
        forward::<Self>(x, params.into_array(), heads, tile, eps)
    }
}

impl BlockBackend for Flex {}
impl BlockBackend for NdArray {}
#[cfg(feature = "wgpu")]
impl BlockBackend for Cube {}

impl<B: Backend + BlockBackend, C: CheckpointStrategy> BlockBackend for Autodiff<B, C> {
    fn recomputed_block(
        x: FloatTensor<Self>,
        params: BlockParams<Self>,
        heads: usize,
        tile: usize,
        eps: f64,
    ) -> FloatTensor<Self> {
        let inputs: Vec<FloatTensor<Self>> =
            std::iter::once(x).chain(params.into_array()).collect();
        let guards: [_; PARAMS + 1] = std::array::from_fn(|i| inputs[i].node());
        let prims: Vec<FloatTensor<B>> = inputs.into_iter().map(|t| t.into_primitive()).collect();
        let (x, p) = split::<B>(prims.clone());
        let out = forward::<B>(x, p, heads, tile, eps);
        match Recompute.prepare::<C>(guards).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish(
                Saved {
                    inputs: prims,
                    heads,
                    tile,
                    eps,
                },
                out,
            ),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

fn split<B: Backend>(mut all: Vec<FloatTensor<B>>) -> (FloatTensor<B>, [FloatTensor<B>; PARAMS]) {
    let params: Vec<_> = all.drain(1..).collect();
    let x = all.pop().expect("the block's input");
    (
        x,
        params
            .try_into()
            .unwrap_or_else(|_| unreachable!("{PARAMS} parameters")),
    )
}

#[derive(Debug)]
struct Recompute;

/// The block's input and parameters: all the backward needs to rebuild it.
#[derive(Debug, Clone)]
struct Saved<B: Backend> {
    inputs: Vec<FloatTensor<B>>,
    heads: usize,
    tile: usize,
    eps: f64,
}

impl<B: Backend + BlockBackend> Backward<B, { PARAMS + 1 }> for Recompute {
    type State = Saved<B>;

    fn backward(
        self,
        ops: Ops<Self::State, { PARAMS + 1 }>,
        grads: &mut Gradients,
        _: &mut Checkpointer,
    ) {
        let grad = grads.consume::<B>(&ops.node);
        let s = ops.state;
        // A fresh graph over leaves holding the saved values; its backward, seeded with the incoming
        // gradient (as the weights of a sum), gives every input's gradient.
        type Ad<B> = Autodiff<B>;
        let leaves: Vec<FloatTensor<Ad<B>>> = s
            .inputs
            .into_iter()
            .map(|t| Ad::<B>::float_set_require_grad(Ad::<B>::from_inner(t), true))
            .collect();
        let (x, p) = split::<Autodiff<B>>(leaves.clone());
        let out = forward::<Autodiff<B>>(x, p, s.heads, s.tile, s.eps);
        let seeded = Ad::<B>::float_mul(out, Ad::<B>::from_inner(grad));
        let inner = Ad::<B>::backward(Ad::<B>::float_sum(seeded));
        for (node, leaf) in ops.parents.into_iter().zip(&leaves) {
            if let (Some(node), Some(g)) = (node, Ad::<B>::grad(leaf, &inner)) {
                grads.register::<B>(node.id, g);
            }
        }
    }
}

/// `x [B, N, C] @ w [C, O] + b [O]`.
fn linear<B: Backend>(x: FloatTensor<B>, w: &FloatTensor<B>, b: &FloatTensor<B>) -> FloatTensor<B> {
    let [bs, n, c] = dims3::<B>(&x);
    let o = w.shape()[1];
    let y = B::float_matmul(B::float_reshape(x, [bs * n, c].into()), w.clone());
    let y = B::float_add(y, B::float_reshape(b.clone(), [1, o].into()));
    B::float_reshape(y, [bs, n, o].into())
}

fn dims3<B: Backend>(x: &FloatTensor<B>) -> [usize; 3] {
    let s = x.shape();
    [s[0], s[1], s[2]]
}

/// `x * g` with `g [C]` over the last axis.
fn scale_channels<B: Backend>(x: FloatTensor<B>, g: &FloatTensor<B>) -> FloatTensor<B> {
    let c = g.shape()[0];
    B::float_mul(x, B::float_reshape(g.clone(), [1, 1, c].into()))
}

/// The block on any backend's float ops: plain on the inner backend, differentiable on `Autodiff<B>`.
fn forward<B: AttentionBackend>(
    x: FloatTensor<B>,
    p: [FloatTensor<B>; PARAMS],
    heads: usize,
    tile: usize,
    eps: f64,
) -> FloatTensor<B> {
    let [
        n1g,
        n1b,
        qkv_w,
        qkv_b,
        proj_w,
        proj_b,
        ls1,
        n2g,
        n2b,
        fc1_w,
        fc1_b,
        fc2_w,
        fc2_b,
        ls2,
    ] = p;
    let [bs, n, c] = dims3::<B>(&x);
    let d = c / heads;
    let h = B::layer_norm(x.clone(), n1g, Some(n1b), eps);
    let qkv = linear::<B>(h, &qkv_w, &qkv_b);
    let qkv = B::float_permute(
        B::float_reshape(qkv, [bs, n, 3, heads, d].into()),
        &[2, 0, 3, 1, 4],
    );
    let part = |i: usize| {
        let all = Slice::from(..);
        let one = B::float_slice(qkv.clone(), &[Slice::from(i..i + 1), all, all, all, all]);
        B::float_reshape(one, [bs, heads, n, d].into())
    };
    let tile = if tile == 0 { n.max(1) } else { tile };
    let att = B::tiled_attention(part(0), part(1), part(2), 1.0 / (d as f64).sqrt(), tile);
    let att = B::float_reshape(B::float_swap_dims(att, 1, 2), [bs, n, c].into());
    let x = B::float_add(
        x,
        scale_channels::<B>(linear::<B>(att, &proj_w, &proj_b), &ls1),
    );
    let h = B::layer_norm(x.clone(), n2g, Some(n2b), eps);
    let m = linear::<B>(B::gelu(linear::<B>(h, &fc1_w, &fc1_b)), &fc2_w, &fc2_b);
    B::float_add(x, scale_channels::<B>(m, &ls2))
}
