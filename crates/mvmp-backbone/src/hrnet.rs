//! HRNet for 2D joint heatmaps (Sun et al., "Deep High-Resolution Representation Learning for Human Pose
//! Estimation", CVPR 2019), in the layout of the reference `pose_hrnet.py`: a stride-4
//! stem with a bottleneck layer, four stages of parallel branches at strides 4, 8, 16, 32 with repeated
//! multi-resolution fusion, and a 1 x 1 head on the highest-resolution branch.
//!
//! Forward: `[B, 3, H, W]` (H, W multiples of 4; the lower-resolution branches are resized back to each
//! branch's exact size, so no larger multiple is needed) -> heatmaps `[B, J, H/4, W/4]`.
use burn::config::Config;
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{BatchNorm, BatchNormConfig, PaddingConfig2d};
use burn::tensor::activation::relu;
use burn::tensor::module::interpolate;
use burn::tensor::ops::{InterpolateMode, InterpolateOptions};
use burn::tensor::{Device, Tensor};
use mvmp_kernels::conv::conv2d;
use mvmp_kernels::norm::{batch_norm, batch_norm_relu};
use mvmp_kernels::residual::add_relu;

#[derive(Config, Debug, PartialEq)]
pub struct HRNetConfig {
    /// Output heatmaps (joints).
    pub joints: usize,
    /// Width C of the highest-resolution branch; branches are C, 2C, 4C, 8C (32 for W32, 48 for W48).
    pub width: usize,
    /// Stem channels (64 in the reference) and bottleneck planes of layer1 (64; output 4x).
    #[config(default = 64)]
    pub stem: usize,
    #[config(default = 64)]
    pub planes: usize,
    /// Basic blocks per branch in every module (4 in the reference).
    #[config(default = 4)]
    pub blocks: usize,
    /// Modules in stages 2, 3, 4 (1, 4, 3 in the reference).
    #[config(default = "[1, 4, 3]")]
    pub modules: [usize; 3],
}

impl HRNetConfig {
    pub fn hrnet_w32(joints: usize) -> Self {
        HRNetConfig::new(joints, 32)
    }
    pub fn hrnet_w48(joints: usize) -> Self {
        HRNetConfig::new(joints, 48)
    }
    /// A small HRNet for CPU tests and the demo: width 8, stem 16, one block and one module per stage.
    pub fn tiny(joints: usize) -> Self {
        HRNetConfig::new(joints, 8)
            .with_stem(16)
            .with_planes(16)
            .with_blocks(1)
            .with_modules([1, 1, 1])
    }
    /// Twice the tiny one's widths (branches 16 to 128 channels, stem 32), one block and one module per
    /// stage: about four times its multiply-adds, still far below W32.
    pub fn small(joints: usize) -> Self {
        HRNetConfig::new(joints, 16)
            .with_stem(32)
            .with_planes(32)
            .with_blocks(1)
            .with_modules([1, 1, 1])
    }
    /// A variant by its config name (`tiny`, `hrnet_w32`, `hrnet_w48`).
    pub fn by_name(name: &str, joints: usize) -> Option<Self> {
        name.parse::<crate::HrnetVariant>()
            .ok()
            .map(|v| v.config(joints))
    }
}

fn conv(ci: usize, co: usize, k: usize, stride: usize, bias: bool, device: &Device) -> Conv2d {
    let p = (k - 1) / 2;
    Conv2dConfig::new([ci, co], [k, k])
        .with_stride([stride, stride])
        .with_padding(PaddingConfig2d::Explicit(p, p, p, p))
        .with_bias(bias)
        .init(device)
}

fn bn(c: usize, device: &Device) -> BatchNorm {
    BatchNormConfig::new(c).with_momentum(0.1).init(device)
}

/// A conv (no bias) followed by batch norm: the reference's `Sequential(conv, BN)` pairs.
#[derive(Module, Debug)]
pub struct ConvBn {
    pub conv: Conv2d,
    pub bn: BatchNorm,
}

impl ConvBn {
    fn new(ci: usize, co: usize, k: usize, stride: usize, device: &Device) -> Self {
        ConvBn {
            conv: conv(ci, co, k, stride, false, device),
            bn: bn(co, device),
        }
    }
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        batch_norm(&self.bn, conv2d(&self.conv, x))
    }
    /// `relu(self.forward(x))`, the ReLU fused into the norm in training.
    pub fn forward_relu(&self, x: Tensor<4>) -> Tensor<4> {
        batch_norm_relu(&self.bn, conv2d(&self.conv, x))
    }
}

#[derive(Module, Debug)]
pub struct Bottleneck {
    pub conv1: Conv2d,
    pub bn1: BatchNorm,
    pub conv2: Conv2d,
    pub bn2: BatchNorm,
    pub conv3: Conv2d,
    pub bn3: BatchNorm,
    pub downsample: Option<ConvBn>,
}

impl Bottleneck {
    fn new(ci: usize, planes: usize, device: &Device) -> Self {
        Bottleneck {
            conv1: conv(ci, planes, 1, 1, false, device),
            bn1: bn(planes, device),
            conv2: conv(planes, planes, 3, 1, false, device),
            bn2: bn(planes, device),
            conv3: conv(planes, planes * 4, 1, 1, false, device),
            bn3: bn(planes * 4, device),
            downsample: (ci != planes * 4).then(|| ConvBn::new(ci, planes * 4, 1, 1, device)),
        }
    }
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let r = batch_norm_relu(&self.bn1, conv2d(&self.conv1, x.clone()));
        let r = batch_norm_relu(&self.bn2, conv2d(&self.conv2, r));
        let r = batch_norm(&self.bn3, conv2d(&self.conv3, r));
        let s = match &self.downsample {
            Some(d) => d.forward(x),
            None => x,
        };
        add_relu(r, s)
    }
}

#[derive(Module, Debug)]
pub struct BasicBlock {
    pub conv1: Conv2d,
    pub bn1: BatchNorm,
    pub conv2: Conv2d,
    pub bn2: BatchNorm,
}

impl BasicBlock {
    fn new(c: usize, device: &Device) -> Self {
        BasicBlock {
            conv1: conv(c, c, 3, 1, false, device),
            bn1: bn(c, device),
            conv2: conv(c, c, 3, 1, false, device),
            bn2: bn(c, device),
        }
    }
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        let r = batch_norm_relu(&self.bn1, conv2d(&self.conv1, x.clone()));
        add_relu(batch_norm(&self.bn2, conv2d(&self.conv2, r)), x)
    }
}

/// One step of a downsampling chain: conv3x3 s2 + BN (+ ReLU except for the last step).
#[derive(Module, Debug)]
pub struct Down {
    pub cb: ConvBn,
    pub relu: bool,
}

/// How branch j reaches resolution i inside a fuse layer: for j > i a conv1x1 + BN and nearest
/// upsampling by 2^(j - i) (`up`); for j < i a chain of i - j stride-2 convolutions (`down`).
#[derive(Module, Debug)]
pub struct Fuse {
    pub up: Option<ConvBn>,
    pub down: Vec<Down>,
}

#[derive(Module, Debug)]
pub struct HrModule {
    pub branches: Vec<Vec<BasicBlock>>,
    /// `fuse_layers[i][j]`, None on the diagonal.
    pub fuse_layers: Vec<Vec<Option<Fuse>>>,
}

impl HrModule {
    fn new(widths: &[usize], blocks: usize, outputs: usize, device: &Device) -> Self {
        let nb = widths.len();
        HrModule {
            branches: widths
                .iter()
                .map(|&c| (0..blocks).map(|_| BasicBlock::new(c, device)).collect())
                .collect(),
            fuse_layers: (0..outputs)
                .map(|i| {
                    (0..nb)
                        .map(|j| {
                            if j > i {
                                Some(Fuse {
                                    up: Some(ConvBn::new(widths[j], widths[i], 1, 1, device)),
                                    down: Vec::new(),
                                })
                            } else if j < i {
                                Some(Fuse {
                                    up: None,
                                    down: (0..i - j)
                                        .map(|k| {
                                            let last = k == i - j - 1;
                                            let co = if last { widths[i] } else { widths[j] };
                                            Down {
                                                cb: ConvBn::new(widths[j], co, 3, 2, device),
                                                relu: !last,
                                            }
                                        })
                                        .collect(),
                                })
                            } else {
                                None
                            }
                        })
                        .collect()
                })
                .collect(),
        }
    }

    /// Branch inputs `[B, C_b, H_b, W_b]` -> fused outputs (one per output resolution).
    pub fn forward(&self, xs: Vec<Tensor<4>>) -> Vec<Tensor<4>> {
        let xs: Vec<Tensor<4>> = xs
            .into_iter()
            .zip(&self.branches)
            .map(|(x, blocks)| blocks.iter().fold(x, |x, b| b.forward(x)))
            .collect();
        self.fuse_layers
            .iter()
            .enumerate()
            .map(|(i, row)| {
                let [_, _, h, w] = xs[i].dims();
                let mut ys = Vec::with_capacity(row.len());
                for (j, f) in row.iter().enumerate() {
                    let y = match f {
                        None => xs[j].clone(),
                        Some(Fuse { up: Some(cb), .. }) => interpolate(
                            cb.forward(xs[j].clone()),
                            InterpolateOptions::new(InterpolateMode::Nearest)
                                .with_output_size([h, w]),
                        ),
                        Some(Fuse { up: None, down }) => down.iter().fold(xs[j].clone(), |x, d| {
                            if d.relu {
                                d.cb.forward_relu(x)
                            } else {
                                d.cb.forward(x)
                            }
                        }),
                    };
                    ys.push(y);
                }
                // The last addition and the ReLU are one pass each way in training.
                let last = ys.pop().expect("at least one branch");
                match ys.into_iter().reduce(|a, b| a + b) {
                    Some(rest) => add_relu(rest, last),
                    None => relu(last),
                }
            })
            .collect()
    }
}

/// A transition: existing branches whose width changes get conv3x3 + BN + ReLU; a new branch is made from
/// the last branch by a stride-2 conv3x3 + BN + ReLU.
#[derive(Module, Debug)]
pub struct Transition {
    pub layers: Vec<Option<ConvBn>>,
}

impl Transition {
    fn new(prev: &[usize], next: &[usize], device: &Device) -> Self {
        Transition {
            layers: next
                .iter()
                .enumerate()
                .map(|(i, &c)| {
                    if i < prev.len() {
                        (prev[i] != c).then(|| ConvBn::new(prev[i], c, 3, 1, device))
                    } else {
                        Some(ConvBn::new(
                            *prev.last().expect("a branch"),
                            c,
                            3,
                            2,
                            device,
                        ))
                    }
                })
                .collect(),
        }
    }

    pub fn forward(&self, xs: &[Tensor<4>]) -> Vec<Tensor<4>> {
        self.layers
            .iter()
            .enumerate()
            .map(|(i, l)| {
                let src = if i < xs.len() {
                    xs[i].clone()
                } else {
                    xs[xs.len() - 1].clone()
                };
                match l {
                    Some(cb) => cb.forward_relu(src),
                    None => src,
                }
            })
            .collect()
    }
}

#[derive(Module, Debug)]
pub struct HRNet {
    pub conv1: Conv2d,
    pub bn1: BatchNorm,
    pub conv2: Conv2d,
    pub bn2: BatchNorm,
    pub layer1: Vec<Bottleneck>,
    pub transition1: Transition,
    pub stage2: Vec<HrModule>,
    pub transition2: Transition,
    pub stage3: Vec<HrModule>,
    pub transition3: Transition,
    pub stage4: Vec<HrModule>,
    pub final_layer: Conv2d,
}

impl HRNetConfig {
    pub fn init(&self, device: &Device) -> HRNet {
        let c = self.width;
        let w = [c, 2 * c, 4 * c, 8 * c];
        let l1_out = self.planes * 4;
        let stage = |nb: usize, modules: usize, last_single: bool| -> Vec<HrModule> {
            (0..modules)
                .map(|m| {
                    let outputs = if last_single && m == modules - 1 {
                        1
                    } else {
                        nb
                    };
                    HrModule::new(&w[..nb], self.blocks, outputs, device)
                })
                .collect()
        };
        HRNet {
            conv1: conv(3, self.stem, 3, 2, false, device),
            bn1: bn(self.stem, device),
            conv2: conv(self.stem, self.stem, 3, 2, false, device),
            bn2: bn(self.stem, device),
            layer1: (0..4)
                .map(|i| {
                    Bottleneck::new(if i == 0 { self.stem } else { l1_out }, self.planes, device)
                })
                .collect(),
            transition1: Transition::new(&[l1_out], &w[..2], device),
            stage2: stage(2, self.modules[0], false),
            transition2: Transition::new(&w[..2], &w[..3], device),
            stage3: stage(3, self.modules[1], false),
            transition3: Transition::new(&w[..3], &w[..4], device),
            stage4: stage(4, self.modules[2], true),
            // The reference initialises convolutions with N(0, 0.001): heatmaps start near zero, not at the
            // unit scale of a default init that the MSE would first have to undo.
            final_layer: Conv2dConfig::new([c, self.joints], [1, 1])
                .with_initializer(burn::nn::Initializer::Normal {
                    mean: 0.0,
                    std: 0.001,
                })
                .init(device),
        }
    }
}

impl HRNet {
    /// `[B, 3, H, W]` -> `[B, J, H/4, W/4]`.
    pub fn forward(&self, x: Tensor<4>) -> Tensor<4> {
        conv2d(&self.final_layer, self.features(x))
    }

    /// The highest-resolution branch's output, what the final layer reads: `[B, 3, H, W]` ->
    /// `[B, width, H/4, W/4]`.
    pub fn features(&self, x: Tensor<4>) -> Tensor<4> {
        let x = batch_norm_relu(&self.bn1, conv2d(&self.conv1, x));
        let x = batch_norm_relu(&self.bn2, conv2d(&self.conv2, x));
        let x = self.layer1.iter().fold(x, |x, b| b.forward(x));
        let mut xs = self.transition1.forward(&[x]);
        for m in &self.stage2 {
            xs = m.forward(xs);
        }
        xs = self.transition2.forward(&xs);
        for m in &self.stage3 {
            xs = m.forward(xs);
        }
        xs = self.transition3.forward(&xs);
        for m in &self.stage4 {
            xs = m.forward(xs);
        }
        xs.swap_remove(0)
    }
}
