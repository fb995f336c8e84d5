//! A Vision Transformer in the DINOv2 layout (Oquab et al., "DINOv2: Learning Robust Visual Features
//! without Supervision", 2023), with module paths that mirror the torch-hub checkpoint
//! keys (`patch_embed.proj`, `blocks.N.{norm1, attn.qkv, attn.proj, ls1.gamma, norm2, mlp.fc1, mlp.fc2,
//! ls2.gamma}`, `norm`, `cls_token`, `pos_embed`, `mask_token`).
//!
//! Forward: `[B, 3, H, W]` (H, W multiples of 14 are used fully; a remainder is cropped by the patch
//! convolution) -> patch tokens after the final norm as a feature map `[B, C, H/14, W/14]`.
//! Position embeddings are interpolated to the input's patch grid the way the original DINOv2 code does
//! (bicubic, A = -0.75, `scale_factor = ((h0 + 0.1) / M, (w0 + 0.1) / M)` with PyTorch's
//! scale-factor coordinate mapping), written as two interpolation matrices so that it is exact and
//! differentiable in the embeddings.
use burn::config::Config;
use burn::module::{Module, Param};
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{Initializer, LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::tensor::{Device, Tensor, TensorData};
use mvmp_kernels::gelu::gelu;
use mvmp_kernels::layer_norm::layer_norm;
use mvmp_kernels::linear::{linear, linear_layer};

pub const PATCH: usize = 14;

#[derive(Config, Debug, PartialEq)]
pub struct ViTConfig {
    /// Token width C.
    pub embed_dim: usize,
    pub depth: usize,
    pub heads: usize,
    /// Side of the square training image the position embeddings were made for (518 for DINOv2).
    #[config(default = 518)]
    pub img_size: usize,
    #[config(default = 4.0)]
    pub mlp_ratio: f64,
    #[config(default = 1e-6)]
    pub norm_eps: f64,
    /// Side of the score tiles of attention (`mvmp_kernels::attention`); 0 computes the whole score
    /// matrix with burn's ops, which autodiff keeps per block for the backward.
    #[config(default = "mvmp_kernels::DEFAULT_BLOCK")]
    pub attention_tile: usize,
    /// In training, keep only each block's input and recompute the block in the backward
    /// (`mvmp_kernels::recompute`): a block's activations exist one block at a time.
    #[config(default = false)]
    pub block_recompute: bool,
}

impl ViTConfig {
    /// A small ViT for CPU tests and the demo: 192 wide, 4 deep, 3 heads, made for 224 x 224.
    pub fn tiny() -> Self {
        ViTConfig::new(192, 4, 3).with_img_size(224)
    }
    /// DINOv2 ViT-S/14: 384 wide, 12 deep, 6 heads.
    pub fn vit_small_14() -> Self {
        ViTConfig::new(384, 12, 6)
    }
    /// DINOv2 ViT-B/14: 768 wide, 12 deep, 12 heads.
    pub fn vit_base_14() -> Self {
        ViTConfig::new(768, 12, 12)
    }
    /// DINOv2 ViT-L/14: 1024 wide, 24 deep, 16 heads.
    pub fn vit_large_14() -> Self {
        ViTConfig::new(1024, 24, 16)
    }

    /// A variant by its config name (`tiny`, `vit_small_14`, `vit_base_14`, `vit_large_14`).
    pub fn by_name(name: &str) -> Option<Self> {
        name.parse::<crate::VitVariant>().ok().map(|v| v.config())
    }

    /// Patches per side of the position-embedding grid.
    pub fn pos_grid(&self) -> usize {
        self.img_size / PATCH
    }

    pub fn init(&self, device: &Device) -> ViT {
        let c = self.embed_dim;
        let m = self.pos_grid();
        let hidden = (c as f64 * self.mlp_ratio) as usize;
        // DINOv2's initialisation: class token N(0, 1e-6), position embeddings N(0, 0.02).
        let normal = |shape: [usize; 3], std: f64| -> Param<Tensor<3>> {
            Initializer::Normal { mean: 0.0, std }.init(shape, device)
        };
        ViT {
            patch_embed: PatchEmbed {
                proj: Conv2dConfig::new([3, c], [PATCH, PATCH])
                    .with_stride([PATCH, PATCH])
                    .init(device),
            },
            cls_token: normal([1, 1, c], 1e-6),
            pos_embed: normal([1, 1 + m * m, c], 0.02),
            // Used only by DINOv2's masked-image pre-training; kept (frozen) so checkpoints load as they are.
            mask_token: Param::from_tensor(Tensor::zeros([1, c], device)).set_require_grad(false),
            blocks: (0..self.depth)
                .map(|_| Block {
                    norm1: LayerNormConfig::new(c)
                        .with_epsilon(self.norm_eps)
                        .init(device),
                    attn: Attention {
                        qkv: LinearConfig::new(c, 3 * c).init(device),
                        proj: LinearConfig::new(c, c).init(device),
                        heads: self.heads,
                        tile: self.attention_tile,
                    },
                    ls1: LayerScale {
                        gamma: Param::from_tensor(Tensor::ones([c], device)),
                    },
                    norm2: LayerNormConfig::new(c)
                        .with_epsilon(self.norm_eps)
                        .init(device),
                    mlp: Mlp {
                        fc1: LinearConfig::new(c, hidden).init(device),
                        fc2: LinearConfig::new(hidden, c).init(device),
                    },
                    recompute: self.block_recompute,
                    norm_eps: self.norm_eps,
                    ls2: LayerScale {
                        gamma: Param::from_tensor(Tensor::ones([c], device)),
                    },
                })
                .collect(),
            norm: LayerNormConfig::new(c)
                .with_epsilon(self.norm_eps)
                .init(device),
            pos_grid: m,
            norm_eps: self.norm_eps,
        }
    }
}

#[derive(Module, Debug)]
pub struct PatchEmbed {
    pub proj: Conv2d,
}

impl PatchEmbed {
    /// `[B, 3, H, W]` -> patch tokens `[B, h w, C]` (row-major) and `[h, w] = [H / 14, W / 14]`: the
    /// stride-14 convolution of `proj`, written as one matmul over the cut-out patches. The rows and
    /// columns past the last whole patch are dropped, as the convolution drops them. A matmul is one
    /// GEMM on every backend, forward and backward, where a strided convolution's weight gradient goes
    /// through a backend's convolution kernels (on lavapipe an autotuned one was off by 0.6%).
    pub fn forward(&self, images: Tensor<4>) -> (Tensor<3>, [usize; 2]) {
        let [b, ch, h, w] = images.dims();
        let (h0, w0) = (h / PATCH, w / PATCH);
        let patches = images
            .narrow(2, 0, h0 * PATCH)
            .narrow(3, 0, w0 * PATCH)
            .reshape([b, ch, h0, PATCH, w0, PATCH])
            .permute([0, 2, 4, 1, 3, 5]) // [B, h, w, 3, 14, 14], the weight's (in, ky, kx) order
            .reshape([b, h0 * w0, ch * PATCH * PATCH]);
        let weight = self.proj.weight.val(); // [C, 3, 14, 14]
        let c = weight.dims()[0];
        let weight = weight.reshape([c, ch * PATCH * PATCH]).transpose();
        let tokens = linear(patches, weight, self.proj.bias.as_ref().map(|b| b.val())); // [B, N, C]
        (tokens, [h0, w0])
    }
}

#[derive(Module, Debug)]
pub struct Attention {
    pub qkv: Linear,
    pub proj: Linear,
    pub heads: usize,
    /// See [`ViTConfig::attention_tile`].
    pub tile: usize,
}

impl Attention {
    /// `[B, N, C]` -> `[B, N, C]`; the qkv rows are `[q; k; v]`, each ordered by head (DINOv2).
    pub fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        let c = x.dims()[2];
        let scale = 1.0 / ((c / self.heads) as f64).sqrt();
        let qkv = linear_layer(&self.qkv, x);
        let out = mvmp_kernels::packed_self_attention(qkv, self.heads, scale, self.tile);
        linear_layer(&self.proj, out)
    }
}

#[derive(Module, Debug)]
pub struct LayerScale {
    pub gamma: Param<Tensor<1>>,
}

impl LayerScale {
    pub fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        let c = x.dims()[2];
        x * self.gamma.val().reshape([1, 1, c])
    }
}

#[derive(Module, Debug)]
pub struct Mlp {
    pub fc1: Linear,
    pub fc2: Linear,
}

#[derive(Module, Debug)]
pub struct Block {
    pub norm1: LayerNorm,
    pub attn: Attention,
    pub ls1: LayerScale,
    pub norm2: LayerNorm,
    pub mlp: Mlp,
    pub ls2: LayerScale,
    /// See [`ViTConfig::block_recompute`].
    pub recompute: bool,
    /// The layer norms' epsilon (burn's `LayerNorm` keeps it private).
    pub norm_eps: f64,
}

impl Block {
    /// Pre-norm: `x += ls1 * attn(norm1 x)`, then `x += ls2 * mlp(norm2 x)`; recomputed in the backward
    /// when `recompute` is set and `x` is on an autodiff device.
    pub fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        if self.recompute
            && x.is_autodiff()
            && let Some(params) = self.kernel_params()
        {
            let shape = mvmp_kernels::recompute::BlockShape {
                heads: self.attn.heads,
                tile: self.attn.tile,
                eps: self.norm_eps,
            };
            return mvmp_kernels::recompute::block(x, params, shape);
        }
        self.forward_stored(x)
    }

    /// The parameters as the recompute kernel takes them; `None` when a bias or norm shift is absent
    /// (the kernel's block has them all, as DINOv2's does).
    fn kernel_params(
        &self,
    ) -> Option<mvmp_kernels::recompute::BlockParams<burn::backend::Dispatch>> {
        use mvmp_kernels::recompute::param;
        let val = |p: &Param<Tensor<1>>| param(p.val());
        let bias = |l: &Linear| l.bias.as_ref().map(val);
        Some(mvmp_kernels::recompute::BlockParams {
            norm1_gamma: val(&self.norm1.gamma),
            norm1_beta: self.norm1.beta.as_ref().map(val)?,
            qkv_weight: param(self.attn.qkv.weight.val()),
            qkv_bias: bias(&self.attn.qkv)?,
            proj_weight: param(self.attn.proj.weight.val()),
            proj_bias: bias(&self.attn.proj)?,
            ls1: val(&self.ls1.gamma),
            norm2_gamma: val(&self.norm2.gamma),
            norm2_beta: self.norm2.beta.as_ref().map(val)?,
            fc1_weight: param(self.mlp.fc1.weight.val()),
            fc1_bias: bias(&self.mlp.fc1)?,
            fc2_weight: param(self.mlp.fc2.weight.val()),
            fc2_bias: bias(&self.mlp.fc2)?,
            ls2: val(&self.ls2.gamma),
        })
    }

    /// The block in burn's ops, its activations kept by autodiff.
    pub fn forward_stored(&self, x: Tensor<3>) -> Tensor<3> {
        let normed = layer_norm(&self.norm1, x.clone(), self.norm_eps);
        let x = x + self.ls1.forward(self.attn.forward(normed));
        let normed = layer_norm(&self.norm2, x.clone(), self.norm_eps);
        let hidden = gelu(linear_layer(&self.mlp.fc1, normed));
        let m = linear_layer(&self.mlp.fc2, hidden);
        x + self.ls2.forward(m)
    }
}

#[derive(Module, Debug)]
pub struct ViT {
    pub patch_embed: PatchEmbed,
    pub cls_token: Param<Tensor<3>>,
    pub pos_embed: Param<Tensor<3>>,
    pub mask_token: Param<Tensor<2>>,
    pub blocks: Vec<Block>,
    pub norm: LayerNorm,
    pub pos_grid: usize,
    /// The final layer norm's epsilon (burn's `LayerNorm` keeps it private).
    pub norm_eps: f64,
}

/// PyTorch's bicubic kernel (A = -0.75) weights for a fractional position `t` at offsets -1, 0, 1, 2.
fn cubic_weights(t: f64) -> [f64; 4] {
    let a = -0.75;
    let w_far = |x: f64| ((a * x - 5.0 * a) * x + 8.0 * a) * x - 4.0 * a; // 1 < |x| < 2
    let w_near = |x: f64| ((a + 2.0) * x - (a + 3.0)) * x * x + 1.0; // |x| <= 1
    [w_far(t + 1.0), w_near(t), w_near(1.0 - t), w_far(2.0 - t)]
}

/// The `[out, inp]` matrix of 1D bicubic interpolation with PyTorch's `scale_factor` mapping
/// (`src = (dst + 0.5) / scale - 0.5`, align_corners = false, indices clamped at the borders).
pub fn bicubic_matrix(inp: usize, out: usize, scale: f64) -> Vec<f64> {
    let mut m = vec![0.0; out * inp];
    for o in 0..out {
        let src = (o as f64 + 0.5) / scale - 0.5;
        let f = src.floor();
        let w = cubic_weights(src - f);
        for (k, wk) in w.iter().enumerate() {
            let i = (f as i64 - 1 + k as i64).clamp(0, inp as i64 - 1) as usize;
            m[o * inp + i] += wk;
        }
    }
    m
}

impl ViT {
    pub fn embed_dim(&self) -> usize {
        self.norm.gamma.val().dims()[0]
    }

    /// Position embeddings for an `h0 x w0` patch grid, `[1, 1 + h0 w0, C]` (class token first).
    pub fn interpolate_pos_embed(&self, h0: usize, w0: usize) -> Tensor<3> {
        let pe = self.pos_embed.val();
        let m = self.pos_grid;
        let c = pe.dims()[2];
        if h0 == m && w0 == m {
            return pe;
        }
        let device = pe.device();
        let cls = pe.clone().narrow(1, 0, 1);
        let grid = pe.narrow(1, 1, m * m).reshape([m, m, c]).permute([2, 0, 1]); // [C, M, M]
        let mat = |out: usize| {
            let s = (out as f64 + 0.1) / m as f64;
            let v: Vec<f32> = bicubic_matrix(m, out, s)
                .into_iter()
                .map(|x| x as f32)
                .collect();
            Tensor::<2>::from_data(TensorData::new(v, [out, m]), &device)
        };
        let mh = mat(h0).unsqueeze_dim::<3>(0); // [1, h0, M]
        let mw = mat(w0).transpose().unsqueeze_dim::<3>(0); // [1, M, w0]
        let out = mh.matmul(grid).matmul(mw); // [C, h0, w0]
        let out = out.permute([1, 2, 0]).reshape([1, h0 * w0, c]);
        Tensor::cat(vec![cls, out], 1)
    }

    /// `[B, 3, H, W]` -> `[B, C, H/14, W/14]`.
    pub fn forward(&self, images: Tensor<4>) -> Tensor<4> {
        let (x, [h0, w0]) = self.forward_tokens(images);
        let [b, _, c] = x.dims();
        x.swap_dims(1, 2).reshape([b, c, h0, w0])
    }

    /// `[B, 3, H, W]` -> the patch tokens `[B, (H/14) (W/14), C]` (row-major) and the patch grid `[h, w]`.
    pub fn forward_tokens(&self, images: Tensor<4>) -> (Tensor<3>, [usize; 2]) {
        let (tokens, [h0, w0]) = self.patch_embed.forward(images); // [B, N, C]
        let b = tokens.dims()[0];
        let cls = self.cls_token.val().repeat_dim(0, b);
        let mut x = Tensor::cat(vec![cls, tokens], 1) + self.interpolate_pos_embed(h0, w0);
        for blk in &self.blocks {
            x = blk.forward(x);
        }
        let x = layer_norm(&self.norm, x, self.norm_eps).narrow(1, 1, h0 * w0); // drop the class token
        (x, [h0, w0])
    }
}
