//! The V2V encoder-decoder (VoxelPose's `V2VNet`) and the RootNet built on it.
//!
//! Shapes: input `[B, Cin, X, Y, Z]` with X, Y, Z divisible by 4; output `[B, Cout, X, Y, Z]`.
//! Widths are the reference's (16, 32, 64, 128) times `width` (1.0 for the paper model, less for the tiny
//! CPU config).
use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv3d, Conv3dConfig, ConvTranspose3d, ConvTranspose3dConfig};
use burn::nn::{
    BatchNorm, BatchNormConfig, GroupNorm, GroupNormConfig, Initializer, PaddingConfig3d,
};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};
use std::sync::atomic::{AtomicUsize, Ordering};

use crate::pool::max_pool3d_2;

/// VoxelPose initialises convolutions with N(0, 0.001) and zero bias.
fn init() -> Initializer {
    Initializer::Normal {
        mean: 0.0,
        std: 0.001,
    }
}

fn conv(ci: usize, co: usize, k: usize, device: &Device) -> Conv3d {
    let p = (k - 1) / 2;
    Conv3dConfig::new([ci, co], [k; 3])
        .with_padding(PaddingConfig3d::Explicit(p, p, p))
        .with_initializer(init())
        .init(device)
}

/// The normalisation of the V2V blocks.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VolumeNorm {
    /// Batch normalisation, as the reference V2V.
    Batch,
    /// Group normalisation (4 channels a group): the same in training and inference. At batch 1 the
    /// batch statistics are one volume's, and the running averages inference uses lag behind weights that
    /// still move, so a batch-normalised detector can score people in training and miss them in
    /// validation.
    Group,
}

/// One normalisation site: exactly one of the pair is present. Separate optional fields (rather than an
/// enum module, whose variant would enter the parameter names) keep the names of batch-normalised
/// checkpoints (`bn.gamma`, ...) as they were.
fn norm(c: usize, kind: VolumeNorm, device: &Device) -> (Option<BatchNorm>, Option<GroupNorm>) {
    match kind {
        VolumeNorm::Batch => (Some(BatchNormConfig::new(c).init(device)), None),
        VolumeNorm::Group => {
            let groups = if c.is_multiple_of(4) { c / 4 } else { 1 };
            (None, Some(GroupNormConfig::new(groups, c).init(device)))
        }
    }
}

fn apply(bn: &Option<BatchNorm>, gn: &Option<GroupNorm>, x: Tensor<5>) -> Tensor<5> {
    match (bn, gn) {
        (Some(b), _) => mvmp_kernels::norm::batch_norm(b, x),
        (None, Some(g)) => mvmp_kernels::norm::group_norm(g, x),
        (None, None) => x,
    }
}

/// `relu(apply(bn, gn, x))`, the ReLU fused into the norm where training fuses the norm.
fn apply_relu(bn: &Option<BatchNorm>, gn: &Option<GroupNorm>, x: Tensor<5>) -> Tensor<5> {
    match (bn, gn) {
        (Some(b), _) => mvmp_kernels::norm::batch_norm_relu(b, x),
        (None, Some(g)) => mvmp_kernels::norm::group_norm_relu(g, x),
        (None, None) => relu(x),
    }
}

/// Conv3d(k) -> norm -> ReLU.
#[derive(Module, Debug)]
pub struct Basic3DBlock {
    conv: Conv3d,
    bn: Option<BatchNorm>,
    gn: Option<GroupNorm>,
}

impl Basic3DBlock {
    pub fn new(ci: usize, co: usize, k: usize, kind: VolumeNorm, device: &Device) -> Self {
        let (bn, gn) = norm(co, kind, device);
        Basic3DBlock {
            conv: conv(ci, co, k, device),
            bn,
            gn,
        }
    }

    pub fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        // In training a shallow volume's front folds its depth into the channels (the tiny config); a
        // deep one's goes in slabs, which bound the backward's memory (the paper's).
        let y = if x.is_autodiff() && self.conv.kernel_size[0] >= 5 {
            mvmp_kernels::conv::folded_conv3d(&self.conv, x.clone())
                .unwrap_or_else(|| conv_in_slabs(&self.conv, x, SLAB.load(Ordering::Relaxed)))
        } else {
            mvmp_kernels::conv::conv3d(&self.conv, x)
        };
        apply_relu(&self.bn, &self.gn, y)
    }
}

/// Most output voxels per slab of [`conv_in_slabs`]: 64k keeps the transient of the 7^3 front's backward
/// near 180 MB on flex (about 2.9 KB per voxel for 17 channels in), against 5.2 GB for the paper's
/// 300 x 300 x 20 grid in one piece.
pub const SLAB_VOXELS: usize = 1 << 16;

static SLAB: AtomicUsize = AtomicUsize::new(SLAB_VOXELS);

/// Set the slab size of the RootNet's large convolutions in training for the whole process
/// ([`SLAB_VOXELS`] unless set); returns the previous one. The training-memory estimate measures a model
/// at a reduced scale with the slabs reduced alike, so that a slab's transient scales as the volume does.
pub fn set_slab_voxels(voxels: usize) -> usize {
    SLAB.swap(voxels.max(1), Ordering::Relaxed)
}

/// A stride-1, "same"-padded 3D convolution computed in slabs along X of at most `max_voxels` output
/// voxels, each from its input slab with a halo of `k / 2` (zeros beyond the volume), then concatenated.
/// The result is the whole convolution's; in training each slab's backward runs on its own, so the
/// backward's working memory is a slab's rather than the volume's.
pub fn conv_in_slabs(conv: &Conv3d, x: Tensor<5>, max_voxels: usize) -> Tensor<5> {
    let [b, ci, nx, ny, nz] = x.dims();
    let [kx, ky, kz] = conv.kernel_size;
    let rows = (max_voxels / (ny * nz).max(1)).clamp(1, nx);
    if conv.stride != [1; 3] || conv.dilation != [1; 3] || conv.groups != 1 {
        return conv.forward(x);
    }
    let bias = conv.bias.as_ref().map(|p| p.val());
    if rows >= nx {
        let PaddingConfig3d::Explicit(px, py, pz) = conv.padding else {
            return conv.forward(x);
        };
        let options = burn::tensor::ops::ConvOptions::new([1; 3], [px, py, pz], [1; 3], 1);
        return mvmp_kernels::wgrad::conv3d(x, conv.weight.val(), bias, options);
    }
    let (h, device) = (kx / 2, x.device());
    let options = burn::tensor::ops::ConvOptions::new([1; 3], [0, ky / 2, kz / 2], [1; 3], 1);
    let zeros = |n: usize| Tensor::<5>::zeros([b, ci, n, ny, nz], &device);
    let slabs = (0..nx)
        .step_by(rows)
        .map(|s| {
            let e = (s + rows).min(nx);
            let (lo, hi) = (s.saturating_sub(h), (e + h).min(nx));
            let mut parts = vec![x.clone().narrow(2, lo, hi - lo)];
            if s < h {
                parts.insert(0, zeros(h - s));
            }
            if e + h > nx {
                parts.push(zeros(e + h - nx));
            }
            mvmp_kernels::wgrad::conv3d(
                Tensor::cat(parts, 2),
                conv.weight.val(),
                bias.clone(),
                options.clone(),
            )
        })
        .collect();
    Tensor::cat(slabs, 2)
}

/// conv3 -> norm -> ReLU -> conv3 -> norm, plus the identity (or conv1 + norm when widths differ), then
/// ReLU.
#[derive(Module, Debug)]
pub struct Res3DBlock {
    conv1: Conv3d,
    bn1: Option<BatchNorm>,
    gn1: Option<GroupNorm>,
    conv2: Conv3d,
    bn2: Option<BatchNorm>,
    gn2: Option<GroupNorm>,
    skip: Option<(Conv3d, Option<BatchNorm>, Option<GroupNorm>)>,
}

impl Res3DBlock {
    pub fn new(ci: usize, co: usize, kind: VolumeNorm, device: &Device) -> Self {
        let (bn1, gn1) = norm(co, kind, device);
        let (bn2, gn2) = norm(co, kind, device);
        Res3DBlock {
            conv1: conv(ci, co, 3, device),
            bn1,
            gn1,
            conv2: conv(co, co, 3, device),
            bn2,
            gn2,
            skip: (ci != co).then(|| {
                let (b, g) = norm(co, kind, device);
                (conv(ci, co, 1, device), b, g)
            }),
        }
    }

    pub fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        use mvmp_kernels::conv::conv3d;
        let r = apply_relu(&self.bn1, &self.gn1, conv3d(&self.conv1, x.clone()));
        let r = apply(&self.bn2, &self.gn2, conv3d(&self.conv2, r));
        let s = match &self.skip {
            Some((c, b, g)) => apply(b, g, conv3d(c, x)),
            None => x,
        };
        mvmp_kernels::residual::add_relu(r, s)
    }
}

/// ConvTranspose3d(k 2, s 2) -> norm -> ReLU.
#[derive(Module, Debug)]
pub struct Upsample3DBlock {
    deconv: ConvTranspose3d,
    bn: Option<BatchNorm>,
    gn: Option<GroupNorm>,
}

impl Upsample3DBlock {
    pub fn new(ci: usize, co: usize, kind: VolumeNorm, device: &Device) -> Self {
        let (bn, gn) = norm(co, kind, device);
        Upsample3DBlock {
            deconv: ConvTranspose3dConfig::new([ci, co], [2; 3])
                .with_stride([2; 3])
                .with_initializer(init())
                .init(device),
            bn,
            gn,
        }
    }

    pub fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        apply_relu(&self.bn, &self.gn, self.deconv.forward(x))
    }
}

#[derive(Config, Debug)]
pub struct V2VNetConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    /// Multiplier of the reference widths (16, 32, 64, 128).
    #[config(default = 1.0)]
    pub width: f64,
    #[config(default = "VolumeNorm::Batch")]
    pub norm: VolumeNorm,
}

#[derive(Module, Debug)]
pub struct V2VNet {
    front: Basic3DBlock,
    front_res: Res3DBlock,
    skip1: Res3DBlock,
    enc1: Res3DBlock,
    skip2: Res3DBlock,
    enc2: Res3DBlock,
    mid1: Res3DBlock,
    mid2: Res3DBlock,
    up2: Upsample3DBlock,
    dec2: Res3DBlock,
    up1: Upsample3DBlock,
    output: Conv3d,
}

impl V2VNetConfig {
    pub fn widths(&self) -> [usize; 4] {
        [16, 32, 64, 128].map(|c| ((c as f64 * self.width).round() as usize).max(2))
    }

    pub fn init(&self, device: &Device) -> V2VNet {
        let [w0, w1, w2, w3] = self.widths();
        let n = self.norm;
        V2VNet {
            front: Basic3DBlock::new(self.in_channels, w0, 7, n, device),
            front_res: Res3DBlock::new(w0, w1, n, device),
            skip1: Res3DBlock::new(w1, w1, n, device),
            enc1: Res3DBlock::new(w1, w2, n, device),
            skip2: Res3DBlock::new(w2, w2, n, device),
            enc2: Res3DBlock::new(w2, w3, n, device),
            mid1: Res3DBlock::new(w3, w3, n, device),
            mid2: Res3DBlock::new(w3, w3, n, device),
            up2: Upsample3DBlock::new(w3, w2, n, device),
            dec2: Res3DBlock::new(w2, w2, n, device),
            up1: Upsample3DBlock::new(w2, w1, n, device),
            output: Conv3dConfig::new([w1, self.out_channels], [1; 3])
                .with_initializer(init())
                .init(device),
        }
    }
}

impl V2VNet {
    /// `[B, Cin, X, Y, Z]` -> `[B, Cout, X, Y, Z]`.
    pub fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        let x = self.front_res.forward(self.front.forward(x)); // [B, w1, X, Y, Z]
        let s1 = self.skip1.forward(x.clone());
        let x = self.enc1.forward(max_pool3d_2(x)); // [B, w2, X/2, ..]
        let s2 = self.skip2.forward(x.clone());
        let x = self.enc2.forward(max_pool3d_2(x)); // [B, w3, X/4, ..]
        let x = self.mid2.forward(self.mid1.forward(x));
        let x = self.dec2.forward(self.up2.forward(x) + s2); // [B, w2, X/2, ..]
        let x = self.up1.forward(x) + s1; // [B, w1, X, Y, Z]
        self.output.forward(x)
    }
}

/// RootNet: V2V on the heatmap volume `[B, J, X, Y, Z]`, giving the primary-joint likelihood
/// `[B, 1, X, Y, Z]` and the sub-voxel offset of a root in each voxel `[B, 3, X, Y, Z]` (voxel units).
#[derive(Config, Debug)]
pub struct RootNetConfig {
    /// Heatmap channels (joints).
    pub joints: usize,
    #[config(default = 1.0)]
    pub width: f64,
    #[config(default = "VolumeNorm::Batch")]
    pub norm: VolumeNorm,
}

#[derive(Module, Debug)]
pub struct RootNet {
    v2v: V2VNet,
}

impl RootNetConfig {
    pub fn init(&self, device: &Device) -> RootNet {
        RootNet {
            v2v: V2VNetConfig::new(self.joints, 4)
                .with_width(self.width)
                .with_norm(self.norm)
                .init(device),
        }
    }
}

impl RootNet {
    /// Returns (likelihood `[B, 1, X, Y, Z]`, offset `[B, 3, X, Y, Z]`).
    pub fn forward(&self, heatmaps: Tensor<5>) -> (Tensor<5>, Tensor<5>) {
        let out = self.v2v.forward(heatmaps);
        (out.clone().narrow(1, 0, 1), out.narrow(1, 1, 3))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Distribution;

    /// The convolution in slabs is the whole convolution: values and the gradients of input, weight and
    /// bias, with slabs that do not divide X and a first and last slab that need zero halos.
    #[test]
    fn a_convolution_in_slabs_is_the_whole_convolution() {
        let d = Device::flex().autodiff();
        d.seed(5);
        let conv = conv(3, 4, 7, &d);
        let x = Tensor::<5>::random([2, 3, 11, 6, 5], Distribution::Normal(0.0, 1.0), &d)
            .require_grad();
        let w = Tensor::<5>::random([2, 4, 11, 6, 5], Distribution::Normal(0.0, 1.0), &d);
        let run = |slabs: bool| {
            let y = if slabs {
                conv_in_slabs(&conv, x.clone(), 4 * 30)
            } else {
                conv.forward(x.clone())
            };
            let grads = (y.clone() * w.clone()).sum().backward();
            let flat = |t: Tensor<5>| t.flatten::<1>(0, 4);
            [
                flat(y.detach()),
                flat(x.grad(&grads).unwrap()),
                flat(conv.weight.val().grad(&grads).unwrap()),
                conv.bias.as_ref().unwrap().val().grad(&grads).unwrap(),
            ]
        };
        for (i, (a, b)) in run(true).into_iter().zip(run(false)).enumerate() {
            let scale = b.clone().abs().max().into_scalar::<f32>().max(1e-6);
            let diff = (a - b).abs().max().into_scalar::<f32>() / scale;
            assert!(
                diff < 1e-5,
                "output/d input/d weight/d bias [{i}] differs by {diff}"
            );
        }
    }
}
