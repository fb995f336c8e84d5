//! The V2V encoder-decoder (VoxelPose's `V2VNet`, REFERENCE.md 3) and the RootNet built on it.
//!
//! Shapes: input `[B, Cin, X, Y, Z]` with X, Y, Z divisible by 4; output `[B, Cout, X, Y, Z]`.
//! Widths are the reference's (16, 32, 64, 128) times `width` (1.0 for the paper model, less for the tiny
//! CPU config).
use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv3d, Conv3dConfig, ConvTranspose3d, ConvTranspose3dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, Initializer, PaddingConfig3d};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor};

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

/// Conv3d(k) -> BN -> ReLU.
#[derive(Module, Debug)]
pub struct Basic3DBlock {
    conv: Conv3d,
    bn: BatchNorm,
}

impl Basic3DBlock {
    pub fn new(ci: usize, co: usize, k: usize, device: &Device) -> Self {
        Basic3DBlock {
            conv: conv(ci, co, k, device),
            bn: BatchNormConfig::new(co).init(device),
        }
    }

    pub fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        relu(self.bn.forward(self.conv.forward(x)))
    }
}

/// conv3 -> BN -> ReLU -> conv3 -> BN, plus the identity (or conv1 + BN when widths differ), then ReLU.
#[derive(Module, Debug)]
pub struct Res3DBlock {
    conv1: Conv3d,
    bn1: BatchNorm,
    conv2: Conv3d,
    bn2: BatchNorm,
    skip: Option<(Conv3d, BatchNorm)>,
}

impl Res3DBlock {
    pub fn new(ci: usize, co: usize, device: &Device) -> Self {
        Res3DBlock {
            conv1: conv(ci, co, 3, device),
            bn1: BatchNormConfig::new(co).init(device),
            conv2: conv(co, co, 3, device),
            bn2: BatchNormConfig::new(co).init(device),
            skip: (ci != co).then(|| {
                (
                    conv(ci, co, 1, device),
                    BatchNormConfig::new(co).init(device),
                )
            }),
        }
    }

    pub fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        let r = relu(self.bn1.forward(self.conv1.forward(x.clone())));
        let r = self.bn2.forward(self.conv2.forward(r));
        let s = match &self.skip {
            Some((c, b)) => b.forward(c.forward(x)),
            None => x,
        };
        relu(r + s)
    }
}

/// ConvTranspose3d(k 2, s 2) -> BN -> ReLU.
#[derive(Module, Debug)]
pub struct Upsample3DBlock {
    deconv: ConvTranspose3d,
    bn: BatchNorm,
}

impl Upsample3DBlock {
    pub fn new(ci: usize, co: usize, device: &Device) -> Self {
        Upsample3DBlock {
            deconv: ConvTranspose3dConfig::new([ci, co], [2; 3])
                .with_stride([2; 3])
                .with_initializer(init())
                .init(device),
            bn: BatchNormConfig::new(co).init(device),
        }
    }

    pub fn forward(&self, x: Tensor<5>) -> Tensor<5> {
        relu(self.bn.forward(self.deconv.forward(x)))
    }
}

#[derive(Config, Debug)]
pub struct V2VNetConfig {
    pub in_channels: usize,
    pub out_channels: usize,
    /// Multiplier of the reference widths (16, 32, 64, 128).
    #[config(default = 1.0)]
    pub width: f64,
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
        V2VNet {
            front: Basic3DBlock::new(self.in_channels, w0, 7, device),
            front_res: Res3DBlock::new(w0, w1, device),
            skip1: Res3DBlock::new(w1, w1, device),
            enc1: Res3DBlock::new(w1, w2, device),
            skip2: Res3DBlock::new(w2, w2, device),
            enc2: Res3DBlock::new(w2, w3, device),
            mid1: Res3DBlock::new(w3, w3, device),
            mid2: Res3DBlock::new(w3, w3, device),
            up2: Upsample3DBlock::new(w3, w2, device),
            dec2: Res3DBlock::new(w2, w2, device),
            up1: Upsample3DBlock::new(w2, w1, device),
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
