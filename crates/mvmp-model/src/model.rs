//! MVMP-HMR assembled (paper Fig. 2; docs/architecture.md, Pipeline):
//!
//! ```text
//! images [B, V, 3, S, S]
//!  -> ViT -> 1x1 reduction -> features [B, V, Cf, S/14, S/14] -> fusion -> volume [B, Cf, X, Y, Z]
//!  -> HRNet -> heatmaps [B, V, J, S/4, S/4] -> fusion (mean) -> heatmap volume [B, J, X, Y, Z]
//!  -> RootNet -> likelihood [B, 1, X, Y, Z], offset [B, 3, X, Y, Z] -> NMS + top-K -> roots [B, K, 3]
//!  -> decoder (queries, HTB, heads) -> 53 rotations, betas, expression, T_wld = root + offset
//!  -> SMPL-X -> vertices [B, K, V, 3], joints [B, K, J, 3] (world metres)
//! ```
use std::sync::Arc;

use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::tensor::module::avg_pool2d;
use burn::tensor::ops::AvgPoolOptions;
use burn::tensor::{Bool, Device, Tensor, TensorData};

use crate::ModelConfig;
use crate::body::BodyLayers;
use crate::facing::{FacingHead, facing_readout, mirror_headings, turn_to_heading};
use crate::ik::{corrected_offsets, swing_body};
use mvmp_backbone::vit::PATCH;
use mvmp_backbone::{HRNet, ViT};
use mvmp_decoder::{Decoder, DecoderConfig, QueryInputs};
use mvmp_fusion::{
    DeformableFusion, DeformableFusionConfig, FusionMode, Root, RootNet, RootNetConfig,
    SamplingGrid, extract_roots, fuse_views,
};
use mvmp_geom::rotation::rot6d_to_matrix;
use mvmp_geom::{Camera, Letterbox};
use mvmp_smplx::names::{NUM_BETAS, NUM_BODY, NUM_EXPRESSION, NUM_REGRESSED};
use mvmp_smplx::{BodyModel, SmplxLayer, Translation, regressed_to_full_pose};

/// The trainable network.
#[derive(Module, Debug)]
pub struct MvmpHmr {
    pub vit: ViT,
    /// 1 x 1 channel reduction of the ViT features to C_f before projection.
    pub reduce: Conv2d,
    pub hrnet: HRNet,
    pub rootnet: RootNet,
    pub decoder: Decoder,
    /// Present when the config asks for deformable-attention fusion (ablation).
    pub deformable: Option<DeformableFusion>,
    /// Present when the config asks for a facing head (`facing`).
    pub facing: Option<FacingHead>,
    /// Present when the config asks for 2D joint heatmaps from the ViT's features (`vit_heatmaps`):
    /// `C_f` -> one map per heatmap joint.
    pub vit_joints: Option<Conv2d>,
    /// The config the network was built from: the forward reads its grid, fusion mode, people cap,
    /// threshold and root placement from here (not saved with the weights).
    #[module(skip)]
    pub config: ModelConfig,
    /// The body model the forward poses its people with ([`MvmpHmr::with_body`]; not saved with the
    /// weights: `body_model` in the config names it).
    #[module(skip)]
    pub body: Option<BodyLayers>,
    /// A diagnostic for inference (false unless set): the fused image-feature volume replaced by zeros
    /// before the decoder, so that what the predictions owe to the images' features beyond detection,
    /// the heading and the root's height can be measured (`mvmp eval --zero-volume`).
    #[module(skip)]
    pub zero_volume: bool,
}

/// Sampling grids of one rig: for the ViT feature maps (stride 14) and the HRNet heatmaps (stride 4).
#[derive(Debug, Clone)]
pub struct RigGrids {
    pub features: SamplingGrid,
    pub heatmaps: SamplingGrid,
    /// The cameras' centres in the world, one per view.
    pub centres: Vec<[f64; 3]>,
}

impl RigGrids {
    pub fn new(
        cfg: &ModelConfig,
        cameras: &[Camera],
        letterboxes: &[Letterbox],
        device: &Device,
    ) -> Self {
        let s = cfg.image_size as usize;
        let f = s / PATCH;
        RigGrids {
            features: SamplingGrid::new(
                &cfg.grid,
                cameras,
                letterboxes,
                PATCH as f64,
                [f, f],
                device,
            ),
            heatmaps: {
                let h = cfg.hrnet_input() as usize / 4;
                SamplingGrid::new(
                    &cfg.grid,
                    cameras,
                    letterboxes,
                    cfg.heatmap_stride(),
                    [h, h],
                    device,
                )
            },
            centres: cameras.iter().map(|c| c.centre().into()).collect(),
        }
    }

    /// The grids of every item of a batch (its cameras and letterboxes per item).
    pub fn for_batch(
        cfg: &ModelConfig,
        cameras: &[Vec<Camera>],
        letterboxes: &[Vec<Letterbox>],
        device: &Device,
    ) -> Vec<Self> {
        cameras
            .iter()
            .zip(letterboxes)
            .map(|(c, l)| RigGrids::new(cfg, c, l, device))
            .collect()
    }
}

/// Everything the forward produces (inputs of the losses and of inference).
#[derive(Debug, Clone)]
pub struct MvmpOutput {
    /// `[B, V, J, S/4, S/4]`
    pub heatmaps: Tensor<5>,
    /// `[B, V, 2, S/4, S/4]` with a facing head (see [`Detection::facing`]).
    pub facing: Option<Tensor<5>>,
    /// `[B, V, J, S/14, S/14]`: the heatmap joints read from the ViT's features, in training and with
    /// a `vit_heatmaps` head only.
    pub vit_heatmaps: Option<Tensor<5>>,
    /// `[B, 1, X, Y, Z]` and `[B, 3, X, Y, Z]`
    pub likelihood: Tensor<5>,
    pub offset: Tensor<5>,
    /// Detected roots per batch item, best first (also when the roots to decode at were given).
    pub detections: Vec<Vec<Root>>,
    /// `[B, K, 3]` roots the people were decoded at, `[B, K]` which slots hold a person.
    pub roots: Tensor<3>,
    pub present: Tensor<2, Bool>,
    /// `[B, K, 53, 6]`, `[B, K, 53, 3, 3]`
    pub rot6d: Tensor<4>,
    pub rotmats: Tensor<5>,
    /// `[B, K, 10]` each
    pub betas: Tensor<3>,
    pub expression: Tensor<3>,
    /// `[B, K, 3]` pelvis in the world (T_wld)
    pub transl: Tensor<3>,
    /// `[B, K, V, 3]`, `[B, K, J, 3]`
    pub vertices: Tensor<4>,
    pub joints: Tensor<4>,
    /// `[B, K, W]` what the decoder's linear pose read took, when it has one.
    pub pose_inputs: Option<Tensor<3>>,
    /// `[B, K, 21, 3]` with `decoder.joint_offsets`: the body joints' offsets from the pelvis (world
    /// axes, metres) that the posed joints have plus the decoder's correction; outside training the
    /// body's rotations are swung to them ([`crate::ik`]).
    pub joint_offsets: Option<Tensor<4>>,
}

impl ModelConfig {
    /// The decoder this model builds: its options and what the rest of the config fixes.
    pub fn decoder_config(&self) -> DecoderConfig {
        let joints = match self.decoder.query_joints {
            true => self.heatmap_joints.len(),
            false => 0,
        };
        DecoderConfig::new(self.feature_channels)
            .with_options(self.decoder.clone())
            .with_joint_channels(joints)
            .with_heading(self.facing)
            .with_attention_tile(self.attention_tile)
    }

    pub fn init(&self, device: &Device) -> MvmpHmr {
        let vit = self
            .vit()
            .with_attention_tile(self.attention_tile)
            .with_block_recompute(self.block_recompute);
        MvmpHmr {
            reduce: Conv2dConfig::new([vit.embed_dim, self.feature_channels], [1, 1]).init(device),
            vit: vit.init(device),
            hrnet: self.hrnet_config().init(device),
            rootnet: RootNetConfig::new(self.heatmap_joints.len())
                .with_width(self.rootnet_width)
                .with_norm(self.rootnet_norm)
                .init(device),
            decoder: self.decoder_config().init(device),
            deformable: (self.fusion == FusionMode::Deformable)
                .then(|| DeformableFusionConfig::new().init(device)),
            facing: self
                .facing
                .then(|| FacingHead::new(self.hrnet_config().width, self.facing_bins, device)),
            vit_joints: self.vit_heatmaps.then(|| {
                Conv2dConfig::new([self.feature_channels, self.heatmap_joints.len()], [1, 1])
                    .init(device)
            }),
            config: self.clone(),
            body: None,
            zero_volume: false,
        }
    }
}

/// The detection branch's outputs (stage 1 trains only this branch).
#[derive(Debug, Clone)]
pub struct Detection {
    /// `[B, V, J, S/4, S/4]`
    pub heatmaps: Tensor<5>,
    /// `[B, 1, X, Y, Z]` and `[B, 3, X, Y, Z]`
    pub likelihood: Tensor<5>,
    pub offset: Tensor<5>,
    /// `[B, V, 2, S/4, S/4]` with a facing head: each pixel's person's heading relative to the camera.
    pub facing: Option<Tensor<5>>,
}

/// What the network computes before the decoder ([`MvmpHmr::upstream`]). With the backbones and the
/// detection branch frozen it depends on the frame alone, so a stage that trains the decoder alone can
/// keep it per frame instead of computing it again.
#[derive(Debug, Clone)]
pub struct Upstream {
    /// `[B, Cf, X, Y, Z]` the fused image features.
    pub volume: Tensor<5>,
    pub detection: Detection,
    /// `[B, J, X, Y, Z]` the fused heatmaps the RootNet read.
    pub joints: Tensor<5>,
    /// See [`MvmpOutput::vit_heatmaps`].
    pub vit_heatmaps: Option<Tensor<5>>,
}

impl Upstream {
    /// The same values, out of any autodiff graph.
    pub fn detach(self) -> Self {
        let d = self.detection;
        Upstream {
            volume: self.volume.detach(),
            detection: Detection {
                heatmaps: d.heatmaps.detach(),
                likelihood: d.likelihood.detach(),
                offset: d.offset.detach(),
                facing: d.facing.map(Tensor::detach),
            },
            joints: self.joints.detach(),
            vit_heatmaps: self.vit_heatmaps.map(Tensor::detach),
        }
    }
}

impl MvmpHmr {
    /// The network with the body model its forward poses people with.
    pub fn with_body(mut self, body: Arc<BodyModel>) -> Self {
        self.body = Some(BodyLayers::new(body));
        self
    }

    /// The body layer on `device`. A network without a body model ([`MvmpHmr::with_body`]) cannot pose
    /// people: only its detection branch runs.
    pub fn body_layer(&self, device: &Device) -> Arc<SmplxLayer> {
        self.body
            .as_ref()
            .expect("a body model to pose people with (MvmpHmr::with_body)")
            .on(device)
    }

    /// Per-view features for the volume: the ViT's patch tokens reduced to `feature_channels` by the 1x1
    /// `reduce` layer, `[B*V, 3, S, S]` -> `[B*V, Cf, h, w]`.
    ///
    /// The 1x1 convolution is computed as the matrix product it is, on the tokens, with the layer's own
    /// weight and bias (so checkpoints are unchanged). As a convolution its input would be the tokens
    /// without the class token, a view whose batch stride is `(N + 1) C`; burn-cubecl 0.22.1's
    /// `conv_im2col_1x1` kernel checks only the spatial strides before folding batch and positions into
    /// one axis, so when autotune picks it (it did on a fresh kernel cache) every batch item after the
    /// first reads shifted tokens.
    pub fn view_features(&self, x: Tensor<4>) -> Tensor<4> {
        let (tokens, [h, w]) = self.vit.forward_tokens(x);
        let [n, _, c] = tokens.dims();
        let cf = self.reduce.weight.dims()[0];
        let weight = self.reduce.weight.val().reshape([cf, c]).transpose();
        let mut out = tokens.matmul(weight.unsqueeze::<3>()); // [B*V, h*w, Cf]
        if let Some(bias) = &self.reduce.bias {
            out = out + bias.val().reshape([1, 1, cf]);
        }
        out.swap_dims(1, 2).reshape([n, cf, h, w])
    }

    /// The `vit_heatmaps` head's maps `[B, V, J, h, w]` of per-view features `[B*V, Cf, h, w]` (`None`
    /// without the head).
    fn joint_maps(&self, feats: Tensor<4>, [b, v]: [usize; 2]) -> Option<Tensor<5>> {
        let head = self.vit_joints.as_ref()?;
        let maps = mvmp_kernels::conv::conv2d(head, feats);
        let [_, j, h, w] = maps.dims();
        Some(maps.reshape([b, v, j, h, w]))
    }

    /// The `vit_heatmaps` head's maps `[B, V, J, S/14, S/14]` of images `[B, V, 3, S, S]`: the ViT and
    /// the head alone (stage 1 trains them so beside detection; `None` without the head).
    pub fn vit_joint_maps(&self, images: Tensor<5>) -> Option<Tensor<5>> {
        self.vit_joints.as_ref()?;
        let [b, v, _, s, _] = images.dims();
        let feats = self.view_features(images.reshape([b * v, 3, s, s]));
        self.joint_maps(feats, [b, v])
    }

    /// The fused image-feature volume `[B, Cf, X, Y, Z]` of images `[B, V, 3, S, S]`: what the decoder
    /// is handed (with `volume_norm` it standardises each channel before reading it).
    pub fn feature_volume(&self, images: Tensor<5>, grids: &[RigGrids]) -> Tensor<5> {
        let [b, v, _, s, _] = images.dims();
        let feats = self.view_features(images.reshape([b * v, 3, s, s]));
        self.fuse_features(feats, grids, [b, v])
    }

    /// Per-view features `[B*V, Cf, h, w]` fused into the volume (a volume of zeros with `zero_volume`).
    fn fuse_features(&self, feats: Tensor<4>, grids: &[RigGrids], [b, v]: [usize; 2]) -> Tensor<5> {
        let [_, cf, h, w] = feats.dims();
        let feats = feats.reshape([b, v, cf, h, w]);
        let fgrids: Vec<SamplingGrid> = grids.iter().map(|g| g.features.clone()).collect();
        let volume = match &self.deformable {
            Some(d) => d.forward(feats, &fgrids),
            None => fuse_views(feats, &fgrids, self.config.fusion),
        };
        match self.zero_volume {
            true => volume.zeros_like(),
            false => volume,
        }
    }

    /// The detection branch alone: HRNet heatmaps, their mean fusion and the RootNet.
    pub fn detect(&self, images: Tensor<5>, grids: &[RigGrids]) -> Detection {
        self.detect_with_volume(images, grids).0
    }

    /// [`MvmpHmr::detect`] and the heatmap volume `[B, J, X, Y, Z]` the RootNet read.
    pub fn detect_with_volume(
        &self,
        images: Tensor<5>,
        grids: &[RigGrids],
    ) -> (Detection, Tensor<5>) {
        let [b, v, _, s, _] = images.dims();
        let mut images = images.reshape([b * v, 3, s, s]);
        // The grids say what size the heatmaps must be (`hrnet_downsample` in the config).
        let k = s / (4 * grids[0].heatmaps.map_hw[0]);
        if k > 1 {
            images = avg_pool2d(images, AvgPoolOptions::new([k, k]));
        }
        let x = self.hrnet.features(images.clone());
        let hm = mvmp_kernels::conv::conv2d(&self.hrnet.final_layer, x.clone()); // [B*V, J, S/4, S/4]
        let [_, j, hh, hw] = hm.dims();
        let heatmaps = hm.reshape([b, v, j, hh, hw]);
        let facing = self.facing.as_ref().map(|f| {
            let mut maps = f.forward(images.clone(), x);
            if self.config.facing_flip && !images.is_autodiff() {
                maps = (maps + self.mirrored_facing(f, images)) / 2.0;
            }
            let c = maps.dims()[1];
            maps.reshape([b, v, c, hh, hw])
        });
        let hgrids: Vec<SamplingGrid> = grids.iter().map(|g| g.heatmaps.clone()).collect();
        let hvol = fuse_views(heatmaps.clone(), &hgrids, FusionMode::Mean);
        let (likelihood, offset) = self.rootnet.forward(hvol.clone());
        let det = Detection {
            heatmaps,
            likelihood,
            offset,
            facing,
        };
        (det, hvol)
    }

    /// The facing head's maps `[N, C, h, w]` of `images` `[N, 3, S, S]` mirrored left to right, mirrored
    /// back and read as maps of the images themselves ([`mirror_headings`]).
    fn mirrored_facing(&self, head: &FacingHead, images: Tensor<4>) -> Tensor<4> {
        let mirrored = images.flip([3]);
        let x = self.hrnet.features(mirrored.clone());
        mirror_headings(head.forward(mirrored, x).flip([3]))
    }

    /// Forward. `grids`: one [`RigGrids`] per batch item. `roots`: decode at these roots `[B, K, 3]` with
    /// presence `[B, K]` (training with ground-truth roots); `None` decodes at the detected roots.
    pub fn forward(
        &self,
        images: Tensor<5>,
        grids: &[RigGrids],
        roots: Option<(Tensor<3>, Tensor<2, Bool>)>,
    ) -> MvmpOutput {
        match roots {
            Some(r) => self.forward_select(images, grids, |_| r),
            None => {
                let (k, device) = (self.config.max_people, images.device());
                self.forward_select(images, grids, |det| roots_tensor(det, k, &device))
            }
        }
    }

    /// Forward that lets `select` choose where to decode people from the detected roots (best first, at
    /// most `max_people` per batch item): it returns roots `[B, K, 3]` and presence `[B, K]`. Training
    /// uses it to match detections to the ground truth.
    pub fn forward_select(
        &self,
        images: Tensor<5>,
        grids: &[RigGrids],
        select: impl FnOnce(&[Vec<Root>]) -> (Tensor<3>, Tensor<2, Bool>),
    ) -> MvmpOutput {
        self.forward_posed(images, grids, select, true)
    }

    /// [`MvmpHmr::forward_select`] whose vertices and joints are posed from body-pose rotations
    /// detached when `pose_grad` is false: the same values, but what reads them trains the global
    /// rotation, shape and placement and not the body pose (training's `mesh_pose = false`).
    pub fn forward_posed(
        &self,
        images: Tensor<5>,
        grids: &[RigGrids],
        select: impl FnOnce(&[Vec<Root>]) -> (Tensor<3>, Tensor<2, Bool>),
        pose_grad: bool,
    ) -> MvmpOutput {
        let up = self.upstream(images, grids);
        self.decode_posed(up, grids, select, pose_grad)
    }

    /// Everything the forward computes before the decoder: the image-feature volume, the detection
    /// branch and the heatmap volume its RootNet read.
    pub fn upstream(&self, images: Tensor<5>, grids: &[RigGrids]) -> Upstream {
        let [b, v, _, s, _] = images.dims();
        let x = images.clone().reshape([b * v, 3, s, s]);
        let feats = self.view_features(x); // [B*V, Cf, h, w]
        let vit_heatmaps = match feats.is_autodiff() {
            true => self.joint_maps(feats.clone(), [b, v]),
            false => None,
        };
        let volume = self.fuse_features(feats, grids, [b, v]);
        let (detection, joints) = self.detect_with_volume(images, grids);
        Upstream {
            volume,
            detection,
            joints,
            vit_heatmaps,
        }
    }

    /// `up` with the RootNet run again on its heatmap volume: what training decodes from when it keeps
    /// the volumes of a fixed HRNet but goes on training the RootNet.
    pub fn rerun_rootnet(&self, mut up: Upstream) -> Upstream {
        let (likelihood, offset) = self.rootnet.forward(up.joints.clone());
        up.detection.likelihood = likelihood;
        up.detection.offset = offset;
        up
    }

    /// The rest of [`MvmpHmr::forward_posed`]: the roots `select` chooses, the decoder and the body
    /// layer on what [`MvmpHmr::upstream`] gave.
    pub fn decode_posed(
        &self,
        up: Upstream,
        grids: &[RigGrids],
        select: impl FnOnce(&[Vec<Root>]) -> (Tensor<3>, Tensor<2, Bool>),
        pose_grad: bool,
    ) -> MvmpOutput {
        let cfg = &self.config;
        let Upstream {
            volume,
            detection:
                Detection {
                    heatmaps,
                    likelihood,
                    offset,
                    facing,
                },
            joints: hvol,
            vit_heatmaps,
        } = up;
        let layer = self.body_layer(&volume.device());
        let b = volume.dims()[0];
        let detections = self.detect_roots(likelihood.clone().detach(), offset.clone().detach());
        let (roots, present) = select(&detections);
        let kk = roots.dims()[1];
        // The decoder reads the facing head's estimate; the facing loss alone trains the head.
        let heading = facing
            .clone()
            .map(|f| facing_readout(f.detach(), grids, &cfg.grid, roots.clone(), present.clone()));
        // The joint heatmap volume, where the decoder reads it, is trained by the detection's terms alone.
        let inputs = QueryInputs {
            heading: heading.clone(),
            joints: cfg.decoder.query_joints.then(|| hvol.detach()),
        };
        let dec =
            self.decoder
                .forward_with(volume, inputs, &cfg.grid, roots.clone(), present.clone());
        let n = b * kk;
        let rotmats = rot6d_to_matrix(dec.rot6d.clone().reshape([n * NUM_REGRESSED, 6])).reshape([
            n,
            NUM_REGRESSED,
            3,
            3,
        ]);
        let rotmats = match &heading {
            Some(h) => turn_to_heading(rotmats, h.clone().reshape([n, 2])),
            None => rotmats,
        };
        let posed = if pose_grad {
            rotmats.clone()
        } else {
            detach_body_pose(rotmats.clone())
        };
        let (betas, expression) = (
            dec.betas.clone().reshape([n, NUM_BETAS]),
            dec.expression.clone().reshape([n, NUM_EXPRESSION]),
        );
        let pose = |r: Tensor<4>| {
            layer.forward(
                regressed_to_full_pose(r),
                betas.clone(),
                expression.clone(),
                dec.transl.clone().reshape([n, 3]),
                Translation::Pelvis,
            )
        };
        let mut body = pose(posed);
        let joint_offsets = dec.joint_offsets.map(|c| {
            corrected_offsets(
                body.joints.clone(),
                c.reshape([n, NUM_BODY * 3]),
                rotmats.clone().narrow(1, 0, 1).reshape([n, 3, 3]),
            )
        });
        // Outside training the body's bones are swung onto the corrected joints.
        let mut rotmats = rotmats;
        if let Some(o) = joint_offsets.as_ref().filter(|o| !o.is_autodiff()) {
            let rest = layer.rest_joints(betas.clone(), expression.clone());
            rotmats = swing_body(rotmats, rest, o.clone());
            body = pose(rotmats.clone());
        }
        let nv = layer.num_vertices();
        let nj = layer.num_joints();
        MvmpOutput {
            heatmaps,
            facing,
            vit_heatmaps,
            likelihood,
            offset,
            detections,
            roots,
            present,
            rot6d: dec.rot6d,
            rotmats: rotmats.reshape([b, kk, NUM_REGRESSED, 3, 3]),
            betas: dec.betas,
            expression: dec.expression,
            transl: dec.transl,
            vertices: body.vertices.reshape([b, kk, nv, 3]),
            joints: body.joints.reshape([b, kk, nj, 3]),
            pose_inputs: dec.pose_inputs,
            joint_offsets: joint_offsets.map(|o| o.reshape([b, kk, NUM_BODY, 3])),
        }
    }
}

/// Rotations `[N, 53, 3, 3]` with the 21 body-pose ones (after the global rotation) detached.
fn detach_body_pose(rot: Tensor<4>) -> Tensor<4> {
    let r = rot.dims()[1];
    Tensor::cat(
        vec![
            rot.clone().narrow(1, 0, 1),
            rot.clone().narrow(1, 1, NUM_BODY).detach(),
            rot.narrow(1, 1 + NUM_BODY, r - 1 - NUM_BODY),
        ],
        1,
    )
}

impl MvmpHmr {
    /// The roots a detection gives, per batch item, best first: the likelihood's peaks above the
    /// threshold (at most `max_people`), placed within their voxels as `root_refine` says.
    pub fn detect_roots(&self, likelihood: Tensor<5>, offset: Tensor<5>) -> Vec<Vec<Root>> {
        let cfg = &self.config;
        extract_roots(
            likelihood,
            cfg.root_refine.with_offset(offset),
            &cfg.grid,
            cfg.max_people,
            cfg.root_threshold,
        )
    }
}

/// Roots `[B, K, 3]` and presence `[B, K]` from per-item root lists (at most `k` each, in order).
pub fn roots_tensor(
    roots: &[Vec<Root>],
    k: usize,
    device: &Device,
) -> (Tensor<3>, Tensor<2, Bool>) {
    let b = roots.len();
    let k = k.max(1);
    let mut r = vec![0f32; b * k * 3];
    let mut p = vec![false; b * k];
    for (bi, d) in roots.iter().enumerate() {
        for (ki, root) in d.iter().enumerate().take(k) {
            p[bi * k + ki] = true;
            for a in 0..3 {
                r[(bi * k + ki) * 3 + a] = root.position[a] as f32;
            }
        }
    }
    (
        Tensor::from_data(TensorData::new(r, [b, k, 3]), device),
        Tensor::from_data(TensorData::new(p, [b, k]), device),
    )
}
