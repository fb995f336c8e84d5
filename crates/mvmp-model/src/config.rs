//! The model configuration (`configs/model/*.toml`): plain serde structs that reject unknown keys, with
//! documented defaults and a validation that names the key path and the bad value.
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use mvmp_backbone::{HRNetConfig, HrnetVariant, ViTConfig, VitVariant};
use mvmp_decoder::DecoderOptions;
use mvmp_fusion::{FusionMode, RootRefine, VolumeNorm};
use mvmp_geom::VoxelGrid;
use mvmp_smplx::names::NUM_JOINTS_WITH_LANDMARKS;

#[derive(Debug, thiserror::Error)]
pub enum ModelConfigError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {what}")]
    Parse { path: PathBuf, what: String },
    #[error("model config: key `{key}`: {what}")]
    Invalid { key: String, what: String },
}

/// Which joint's likelihood the RootNet predicts (paper ablation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PrimaryJoint {
    Pelvis,
    Head,
    Spine,
}

impl PrimaryJoint {
    /// The SMPL-X joint index.
    pub fn joint(self) -> usize {
        match self {
            PrimaryJoint::Pelvis => 0,
            PrimaryJoint::Head => 15,
            PrimaryJoint::Spine => 6,
        }
    }
}

/// Most sample points of a query's lattice: each adds the volume's channels to every query's input.
pub const MAX_LATTICE: usize = 512;

/// A lattice of points per axis (key `key`) spanning metres per axis (key `span_key`).
fn check_lattice(
    (key, span_key): (&'static str, &'static str),
    lattice: [usize; 3],
    span: [f64; 3],
) -> Result<(), (&'static str, String)> {
    let points = lattice.iter().try_fold(1usize, |n, &a| n.checked_mul(a));
    if !points.is_some_and(|n| (1..=MAX_LATTICE).contains(&n)) {
        return Err((
            key,
            format!(
                "{lattice:?}: every axis needs at least one point and at most {MAX_LATTICE} in all"
            ),
        ));
    }
    if let Some(s) = span.iter().find(|s| !(s.is_finite() && **s >= 0.0)) {
        return Err((
            span_key,
            format!("{s}: a span must be finite and non-negative (metres)"),
        ));
    }
    Ok(())
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelConfig {
    /// Network input size S (images are letterboxed to S x S).
    pub image_size: u32,
    /// ViT variant: tiny, vit_small_14, vit_base_14, vit_large_14.
    pub backbone: VitVariant,
    /// Feature channels after the 1 x 1 reduction (C_f).
    pub feature_channels: usize,
    /// HRNet variant: tiny, hrnet_w32, hrnet_w48.
    pub hrnet: HrnetVariant,
    /// HRNet and the facing head see the input average-pooled by this factor, so the heatmaps are
    /// S / (4 x this) on a side. 1 (the default) gives them the ViT's input; VoxelPose's pose network
    /// reads cameras at half their resolution, and at 1288 x 1288 HRNet-W32's training activations over
    /// five views are most of a step's memory (README, Training at paper scale).
    pub hrnet_downsample: u32,
    /// SMPL-X joints whose 2D heatmaps HRNet predicts and the heatmap volume holds.
    pub heatmap_joints: Vec<usize>,
    /// The voxel grid (world metres).
    pub grid: VoxelGrid,
    /// View fusion: mean (paper) or max (ablation).
    pub fusion: FusionMode,
    /// RootNet width multiplier (1.0 = the reference V2V).
    pub rootnet_width: f64,
    /// RootNet normalisation: `batch` (the reference V2V) or `group` (the same in training and inference;
    /// what batch-1 training on a CPU needs, see `VolumeNorm`).
    pub rootnet_norm: VolumeNorm,
    pub primary_joint: PrimaryJoint,
    /// Most people per scene (top-K of root extraction).
    pub max_people: usize,
    /// Root likelihood threshold.
    pub root_threshold: f32,
    /// Where a root sits within its peak voxel: `offset` (the offset head, paper) or `peak` (the vertex
    /// of the likelihood's Gaussian peak).
    pub root_refine: RootRefine,
    pub decoder: DecoderOptions,
    /// A facing head on HRNet (two maps: the cosine and sine of each person's heading relative to the
    /// direction to the camera, trained where the person's torso shows) whose reading at each person,
    /// turned into the world by the cameras' directions, the decoder adds to its query. false (the paper)
    /// has none; a backbone trained from scratch needs it (docs/architecture.md, Facing).
    pub facing: bool,
    /// What the facing head's maps hold: 0, the cosine and sine of the relative heading (regressed by
    /// squared error); N (4 to 64), the logits of N heading bins (trained by cross-entropy to a von Mises
    /// label one bin wide), read as the mean of the bins' directions under their softmax.
    #[serde(skip_serializing_if = "is_zero")]
    pub facing_bins: usize,
    /// A flip test for the facing head outside training: it also reads every view mirrored left to
    /// right, and its maps, mirrored back with each heading's angle to the camera negated, are averaged
    /// with the plain ones. It costs one more pass of HRNet and the head per view at inference; training
    /// is unchanged. false (the default) reads each view once.
    #[serde(skip_serializing_if = "is_false")]
    pub facing_flip: bool,
    /// A 1 x 1 head on the reduced ViT features (`C_f` channels, before fusion) that predicts the 2D
    /// heatmaps of `heatmap_joints`, trained by the loss's `vit_heatmap` term in both stages. It gives the
    /// ViT a signal of its own, as the paper's ViTPose backbone has from its 2D pose pretraining
    /// (docs/architecture.md, The image features go unread). Inference does not run it.
    #[serde(skip_serializing_if = "is_false")]
    pub vit_heatmaps: bool,
    /// Body model: `standin:SEED` or a path to an SMPLX_*.npz.
    pub body_model: String,
    /// Side of the score tiles of the ViT's and the decoder's attention: autodiff keeps each row's
    /// softmax statistics instead of the `[heads, N, N]` probabilities, and the backward recomputes the
    /// scores tile by tile (`mvmp_kernels::attention`). 0 computes the whole score matrix with burn's ops.
    pub attention_tile: usize,
    /// In training, keep only each ViT block's input and recompute the block in its backward
    /// (`mvmp_kernels::recompute`): the ViT's activations exist one block at a time, for one more forward
    /// of the ViT per step. Inference is unchanged.
    pub block_recompute: bool,
}

fn is_zero(n: &usize) -> bool {
    *n == 0
}

fn is_false(b: &bool) -> bool {
    !*b
}

/// Most heading bins of a facing head (`facing_bins`).
pub const MAX_FACING_BINS: usize = 64;

/// Largest network input side (the paper's is 1288).
pub const MAX_IMAGE_SIZE: u32 = 4096;
/// Most channels of the feature volume and of the decoder's width.
pub const MAX_WIDTH: usize = 4096;
/// Most Human Transformer Blocks (the paper has 2).
pub const MAX_DEPTH: usize = 64;
/// Most height features a decoder reads (`[decoder] height_features`).
pub const MAX_HEIGHT_FEATURES: usize = 64;

/// The widest FFN a decoder block may have, in multiples of its width (the paper's has 4).
pub const MAX_FFN_RATIO: usize = 16;

/// The most people a config may decode per scene: 1000 slots of 10475 vertices are 126 MB of meshes per
/// batch item, which every stage after the decoder holds several times.
pub const MAX_PEOPLE: usize = 1000;

impl Default for ModelConfig {
    fn default() -> Self {
        ModelConfig {
            image_size: 224,
            backbone: VitVariant::Tiny,
            feature_channels: 32,
            hrnet: HrnetVariant::Tiny,
            hrnet_downsample: 1,
            heatmap_joints: (0..22).collect(),
            grid: VoxelGrid {
                center: [0.0, 0.0, 1.0],
                size: [8.0, 8.0, 2.0],
                shape: [32, 32, 8],
            },
            fusion: FusionMode::Mean,
            rootnet_width: 0.5,
            rootnet_norm: VolumeNorm::Batch,
            primary_joint: PrimaryJoint::Pelvis,
            max_people: 10,
            root_threshold: 0.3,
            root_refine: RootRefine::Offset,
            decoder: DecoderOptions {
                dim: 128,
                heads: 4,
                pool: 2,
                ..Default::default()
            },
            facing: false,
            facing_bins: 0,
            facing_flip: false,
            vit_heatmaps: false,
            body_model: "standin:0".into(),
            attention_tile: mvmp_kernels::DEFAULT_BLOCK,
            block_recompute: false,
        }
    }
}

impl ModelConfig {
    pub fn read(path: &Path) -> Result<Self, ModelConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ModelConfigError::Io {
            path: path.into(),
            source,
        })?;
        let cfg: ModelConfig = toml::from_str(&text).map_err(|e| ModelConfigError::Parse {
            path: path.into(),
            what: e.to_string(),
        })?;
        // The key alone does not say which file: the run's, the demo's, or one a training config names.
        cfg.validate().map_err(|e| ModelConfigError::Parse {
            path: path.into(),
            what: e.to_string(),
        })?;
        Ok(cfg.with_body_model_beside(path))
    }

    /// A relative body-model path is relative to the config file that names it: made absolute here, so
    /// that a run's copy of the config (another directory) and every command find the same file.
    fn with_body_model_beside(mut self, path: &Path) -> Self {
        let named = Path::new(&self.body_model);
        if !self.body_model.starts_with("standin:") && named.is_relative() {
            let joined = path.parent().unwrap_or(Path::new(".")).join(named);
            let absolute = std::path::absolute(&joined).unwrap_or(joined);
            self.body_model = absolute.to_string_lossy().into_owned();
        }
        self
    }

    pub fn vit(&self) -> ViTConfig {
        self.backbone.config()
    }

    /// Side of HRNet's input, `image_size / hrnet_downsample`.
    pub fn hrnet_input(&self) -> u32 {
        self.image_size / self.hrnet_downsample.max(1)
    }

    /// Network pixels per heatmap pixel: 4 x `hrnet_downsample`.
    pub fn heatmap_stride(&self) -> f64 {
        4.0 * self.hrnet_downsample.max(1) as f64
    }

    pub fn hrnet_config(&self) -> HRNetConfig {
        self.hrnet.config(self.heatmap_joints.len())
    }

    pub fn validate(&self) -> Result<(), ModelConfigError> {
        self.check_inputs()
            .and_then(|()| self.check_volume())
            .map_err(|(key, what)| ModelConfigError::Invalid {
                key: key.into(),
                what,
            })
    }

    /// The input size, HRNet's downsampling, the feature channels and the heatmap joints: the offending
    /// key and why.
    fn check_inputs(&self) -> Result<(), (&'static str, String)> {
        // Heatmaps are exactly S/4; a multiple of 14 also uses every pixel in the ViT (the paper: 1288).
        if self.image_size < 28
            || self.image_size > MAX_IMAGE_SIZE
            || !self.image_size.is_multiple_of(4)
        {
            return Err((
                "image_size",
                format!(
                    "{}: must be a multiple of 4 from 28 to {MAX_IMAGE_SIZE}",
                    self.image_size
                ),
            ));
        }
        let k = self.hrnet_downsample;
        if k == 0 || !self.image_size.is_multiple_of(4 * k) || self.image_size / k < 28 {
            return Err((
                "hrnet_downsample",
                format!(
                    "{k}: must be at least 1, divide image_size ({}) into a multiple of 4 and leave \
                     HRNet at least 28 pixels",
                    self.image_size
                ),
            ));
        }
        if self.feature_channels == 0 || self.feature_channels > MAX_WIDTH {
            return Err((
                "feature_channels",
                format!("{}: expected 1 to {MAX_WIDTH}", self.feature_channels),
            ));
        }
        if self.heatmap_joints.is_empty()
            || self
                .heatmap_joints
                .iter()
                .any(|&j| j >= NUM_JOINTS_WITH_LANDMARKS)
        {
            return Err((
                "heatmap_joints",
                format!(
                    "{:?}: a non-empty list of SMPL-X joint indices below {NUM_JOINTS_WITH_LANDMARKS}",
                    self.heatmap_joints
                ),
            ));
        }
        let mut seen = [false; NUM_JOINTS_WITH_LANDMARKS];
        if let Some(j) = self
            .heatmap_joints
            .iter()
            .find(|&&j| std::mem::replace(&mut seen[j], true))
        {
            return Err((
                "heatmap_joints",
                format!("{:?}: joint {j} is listed twice", self.heatmap_joints),
            ));
        }
        if let Err(what) = mvmp_smplx::check_reference(&self.body_model) {
            return Err(("body_model", what));
        }
        if self.facing_bins != 0 && !(4..=MAX_FACING_BINS).contains(&self.facing_bins) {
            return Err((
                "facing_bins",
                format!(
                    "{}: expected 0 (cosine and sine) or 4 to {MAX_FACING_BINS} bins",
                    self.facing_bins
                ),
            ));
        }
        if self.facing_bins != 0 && !self.facing {
            return Err((
                "facing_bins",
                format!(
                    "{}: set without a facing head (facing = false)",
                    self.facing_bins
                ),
            ));
        }
        if self.facing_flip && !self.facing {
            return Err((
                "facing_flip",
                "true: set without a facing head (facing = false)".into(),
            ));
        }
        if !self.heatmap_joints.contains(&self.primary_joint.joint()) {
            return Err((
                "primary_joint",
                format!(
                    "{:?} (joint {}) is not in heatmap_joints",
                    self.primary_joint,
                    self.primary_joint.joint()
                ),
            ));
        }
        Ok(())
    }

    /// The grid, the RootNet, detection and the decoder: the offending key and why.
    fn check_volume(&self) -> Result<(), (&'static str, String)> {
        self.grid.validate().map_err(|e| ("grid", e.to_string()))?;
        if self.grid.shape.iter().any(|s| !s.is_multiple_of(4)) {
            return Err((
                "grid.shape",
                format!(
                    "{:?}: every side must be divisible by 4 (the V2V encoder pools twice)",
                    self.grid.shape
                ),
            ));
        }
        if !(self.rootnet_width > 0.0 && self.rootnet_width <= 4.0) {
            return Err((
                "rootnet_width",
                format!("{}: expected (0, 4]", self.rootnet_width),
            ));
        }
        if self.max_people == 0 || self.max_people > MAX_PEOPLE {
            return Err((
                "max_people",
                format!(
                    "{}: expected 1 to {MAX_PEOPLE} (each slot is a decoded SMPL-X mesh)",
                    self.max_people
                ),
            ));
        }
        // The likelihood is a sigmoid: at 1 or above no voxel ever passes (below 0 every peak does).
        if !(self.root_threshold.is_finite() && self.root_threshold < 1.0) {
            return Err((
                "root_threshold",
                format!(
                    "{}: must be a finite likelihood below 1 (a negative one keeps every peak)",
                    self.root_threshold
                ),
            ));
        }
        let d = &self.decoder;
        if d.dim == 0 || d.dim > MAX_WIDTH || d.heads == 0 || !d.dim.is_multiple_of(d.heads) {
            return Err((
                "decoder.dim",
                format!(
                    "{} must be a multiple of decoder.heads = {} from 1 to {MAX_WIDTH}",
                    d.dim, d.heads
                ),
            ));
        }
        if d.depth > MAX_DEPTH {
            return Err((
                "decoder.depth",
                format!("{}: expected 0 to {MAX_DEPTH} blocks", d.depth),
            ));
        }
        if d.pool == 0 {
            return Err(("decoder.pool", "must be at least 1".into()));
        }
        // An axis the factor does not divide stays unpooled; one that divides none pools nothing.
        if d.pool > 1 && !self.grid.shape.iter().any(|s| s.is_multiple_of(d.pool)) {
            return Err((
                "decoder.pool",
                format!(
                    "{}: divides none of the grid's sides {:?}, so nothing would be pooled",
                    d.pool, self.grid.shape
                ),
            ));
        }
        if !(1..=MAX_FFN_RATIO).contains(&d.ffn_ratio) {
            return Err((
                "decoder.ffn_ratio",
                format!(
                    "{}: expected 1 to {MAX_FFN_RATIO} (the FFN's width in multiples of decoder.dim)",
                    d.ffn_ratio
                ),
            ));
        }
        check_lattice(
            ("decoder.query_lattice", "decoder.query_span"),
            d.query_lattice,
            d.query_span,
        )?;
        check_lattice(
            ("decoder.joint_lattice", "decoder.joint_span"),
            d.joint_lattice,
            d.joint_span,
        )?;
        let turns = d.query_lattice.iter().product::<usize>() > 1 || d.query_joints;
        if d.heading_lattice && !(self.facing && turns) {
            return Err((
                "decoder.heading_lattice",
                "true: the lattice turns with the facing head's heading, so it needs `facing = true` and a query_lattice of more than one point (or query_joints)".into(),
            ));
        }
        if d.joint_samples && !d.query_joints {
            return Err((
                "decoder.joint_samples",
                "true: it sets how the joint heatmap volume is read, so it needs `query_joints = true`".into(),
            ));
        }
        if d.pose_read && !d.joint_samples {
            return Err((
                "decoder.pose_read",
                "true: it reads the joint heatmap samples, so it needs `joint_samples = true`"
                    .into(),
            ));
        }
        if d.joint_offsets && !(d.joint_samples && self.facing) {
            return Err((
                "decoder.joint_offsets",
                "true: its read takes the joint heatmap samples and its offsets are in the facing head's heading frame, so it needs `joint_samples = true` and `facing = true`".into(),
            ));
        }
        // Each feature is one input of `height_proj`: a count past this only sizes an allocation.
        if d.height_features > MAX_HEIGHT_FEATURES {
            return Err((
                "decoder.height_features",
                format!("{}: expected 0 to {MAX_HEIGHT_FEATURES}", d.height_features),
            ));
        }
        Ok(())
    }
}
