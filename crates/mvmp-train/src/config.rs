//! The training config (`configs/train/*.toml`): what to train on, the two stages and the loss weights.
//! Unknown keys are rejected; every error names the key and the bad value.
use std::path::{Path, PathBuf};

use mvmp_data::augment::Photometric;
use mvmp_data::sources::{SourceFormat, SourceSpec};
use mvmp_losses::LossWeights;
use mvmp_model::ModelConfig;
use serde::{Deserialize, Serialize};

use crate::TrainError;

/// Where stage 2 decodes people during training.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum QueryMode {
    /// At detected roots matched to a ground-truth person within the gate (unmatched ones get no loss).
    Detected,
    /// At the ground-truth roots.
    Gt,
    /// Detected roots matched within the gate, plus the ground-truth root of every person no detection
    /// reached (early in training the RootNet finds few people; this keeps every person supervised).
    Mixed,
}

/// The two training stages. Logs, checkpoint names and `state.json` write them as 1 and 2.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize)]
#[serde(try_from = "u32", into = "u32")]
pub enum Stage {
    /// HRNet and the RootNet learn to find people (the 2D heatmap and detection losses).
    Detection = 1,
    /// The whole model, the decoder's losses added.
    Whole = 2,
}

impl Stage {
    pub const ALL: [Stage; 2] = [Stage::Detection, Stage::Whole];

    pub fn number(self) -> u32 {
        self as u32
    }

    /// What the stage trains, for progress lines.
    pub fn trains(self) -> &'static str {
        match self {
            Stage::Detection => "detection",
            Stage::Whole => "whole model",
        }
    }
}

impl From<Stage> for u32 {
    fn from(s: Stage) -> u32 {
        s.number()
    }
}

impl TryFrom<u32> for Stage {
    type Error = String;
    fn try_from(n: u32) -> Result<Stage, String> {
        match n {
            1 => Ok(Stage::Detection),
            2 => Ok(Stage::Whole),
            n => Err(format!("stage {n}: expected 1 or 2")),
        }
    }
}

impl std::fmt::Display for Stage {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.number())
    }
}

/// The learning-rate curve of a stage after its warm-up.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum LrSchedule {
    #[default]
    Constant,
    Cosine,
}

fn final_lr_factor() -> f64 {
    0.01
}

/// One training stage.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StageConfig {
    /// Passes over the training split (0 skips the stage).
    pub epochs: usize,
    /// Adam's peak learning rate.
    pub lr: f64,
    /// The decoder's peak learning rate, on the same schedule (default: `lr`). A transformer decoder
    /// trained from scratch at a rate made for the convolutional stages collapses: every person gets the
    /// same body pose, whatever the queries hold (docs/architecture.md, Training).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub decoder_lr: Option<f64>,
    /// The peak rate of what stage 1 trained (HRNet, the RootNet and the facing head) in stage 2, on the
    /// same schedule (default: `lr`; stage 2 only). Stage 2 starts its own warm-up at its own peak, and at
    /// the whole model's rate those modules unlearn part of what stage 1 taught them (on the demo the
    /// facing head's error at the true roots went from 17.5 degrees after stage 1 to 25-27 in stage 2).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub detection_lr: Option<f64>,
    /// Steps of linear warm-up from 0 to `lr` at the start of the stage (0 = none).
    #[serde(default)]
    pub warmup_steps: usize,
    /// The learning rate after the warm-up: constant, or a cosine decay to `lr * final_lr_factor` at the
    /// stage's last step.
    #[serde(default)]
    pub schedule: LrSchedule,
    #[serde(default = "final_lr_factor")]
    pub final_lr_factor: f64,
    /// Clip the global gradient norm to this value (0 = off).
    #[serde(default)]
    pub grad_clip: f32,
    /// Keep the ViT backbone fixed (stage 2 only; stage 1 never touches it).
    #[serde(default)]
    pub freeze_backbone: bool,
    /// Keep what stage 1 trained fixed in stage 2: HRNet, the RootNet and the facing head; stage 2 then
    /// drops the detection and facing terms, which would train nothing (stage 2 only). Without the 2D
    /// heatmap loss of stage 1 their shared features drift under stage 2's other terms: on the demo the
    /// facing head's error at the true roots went from 34.9 degrees after stage 1 to 45.6-66.9 in stage 2 (seed 0)
    /// (docs/architecture.md, Training).
    #[serde(default)]
    pub freeze_detection: bool,
    /// With `freeze_detection`, the RootNet goes on training (stage 2 only): HRNet and the facing head
    /// stay fixed, the detection term stays in the loss and `detection_lr` is the RootNet's rate; with
    /// `cache_volumes` the RootNet reads each frame's kept heatmap volume. Without it the kept
    /// volumes' detections are stage 1's: on the learning benchmark's kept volumes (seed 1) the held-out
    /// root was 50.9 mm off without it and 43.2 with it, MPJPE 104.3 and 99.2, at twice the cost of a
    /// step that trains the decoder alone (docs/learning.md).
    #[serde(default)]
    pub train_rootnet: bool,
    /// Validate with, and end the run on, an exponential moving average of the weights over the stage's
    /// steps, with this decay per step (0 = off, the paper). Training itself goes on from the raw weights;
    /// the average is checkpointed beside them (docs/architecture.md, Weight averaging).
    #[serde(default)]
    pub average_decay: f64,
    /// At the stage's end, fit the decoder's linear pose read (`decoder.pose_read`) in closed form on this
    /// many training frames spread over the set (0 = off; stage 2 only): a ridge regression from the joint
    /// samples it reads to what the rest of the decoder leaves of the body's rotations, kept where it
    /// lowers their error on the last fifth of the frames (docs/architecture.md, The pose read in closed
    /// form).
    #[serde(default)]
    pub pose_fit_frames: usize,
    /// Keep each training frame's image-feature volume, detection and heatmap volume from the first time
    /// the stage decodes it, and decode from them after (stage 2 only; needs `freeze_backbone`,
    /// `freeze_detection` and `batch_size = 1`). Everything before the decoder is then fixed: the ViT's
    /// channel reduction and a learned fusion too. So that what is kept is what a fresh forward would
    /// give, every epoch of the stage draws each frame's views and colour jitter as its first does.
    /// A step then runs the decoder, the body layer and the losses alone; the kept tensors take about
    /// 2.7 MB a frame in the tiny config (docs/architecture.md, Training).
    #[serde(default)]
    pub cache_volumes: bool,
}

impl StageConfig {
    /// The learning rate of the stage's step `step` (0-based) of `total`. A pure function of the step, so
    /// that a resumed run follows the same curve.
    pub fn lr_at(&self, step: usize, total: usize) -> f64 {
        if step < self.warmup_steps {
            return self.lr * (step + 1) as f64 / (self.warmup_steps + 1) as f64;
        }
        match self.schedule {
            LrSchedule::Constant => self.lr,
            LrSchedule::Cosine => {
                let span = total.saturating_sub(self.warmup_steps).max(2) - 1;
                let t = ((step - self.warmup_steps) as f64 / span as f64).min(1.0);
                let floor = self.lr * self.final_lr_factor;
                floor + (self.lr - floor) * 0.5 * (1.0 + (std::f64::consts::PI * t).cos())
            }
        }
    }

    /// The decoder's rate at that step, when it has its own ([`StageConfig::decoder_lr`]): the same
    /// curve scaled to its peak.
    pub fn decoder_lr_at(&self, step: usize, total: usize) -> Option<f64> {
        self.rescaled(self.decoder_lr, step, total)
    }

    /// The detection modules' rate at that step, when they have their own
    /// ([`StageConfig::detection_lr`]).
    pub fn detection_lr_at(&self, step: usize, total: usize) -> Option<f64> {
        self.rescaled(self.detection_lr, step, total)
    }

    /// The stage's curve at that step scaled from its peak `lr` to `peak`.
    fn rescaled(&self, peak: Option<f64>, step: usize, total: usize) -> Option<f64> {
        peak.map(|p| self.lr_at(step, total) * p / self.lr)
    }
}

/// The most views per frame a config may ask for (every index is allocated per frame; CMU Panoptic, the
/// largest rig read here, has 31 HD and 480 VGA cameras).
pub const MAX_VIEWS: usize = 1000;
/// Most frames per training step.
pub const MAX_BATCH: usize = 1024;
/// Most epochs (and warm-up steps) per stage: step counts stay far from overflowing.
pub const MAX_EPOCHS: usize = 1_000_000;
/// Most times one source's frames are drawn per epoch (`[[sources]] repeat`): an epoch's order holds
/// every draw.
pub const MAX_REPEAT: usize = 1_000;

/// A training run's configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TrainConfig {
    /// Model config, relative to this file's directory (or absolute).
    pub model: String,
    /// Dataset root in the mvmp layout, relative to the working directory; `--data` overrides it. Trains on
    /// its train split, together with any `[[sources]]`.
    #[serde(default)]
    pub data: Option<String>,
    /// Seed of initialisation, data order and view choice.
    #[serde(default)]
    pub seed: u64,
    #[serde(default = "one")]
    pub batch_size: usize,
    /// Views drawn at random per training sample (paper: 5).
    #[serde(default = "five")]
    pub train_views: usize,
    /// Views used for validation and evaluation: the first N cameras of each rig.
    #[serde(default = "five")]
    pub test_views: usize,
    /// Gate (metres) of the matching of predicted to ground-truth roots in training and evaluation.
    #[serde(default = "gate")]
    pub match_gate: f64,
    #[serde(default = "mixed")]
    pub queries: QueryMode,
    /// Model checkpoints kept (the newest ones; the final weights are always kept).
    #[serde(default = "three")]
    pub keep_checkpoints: usize,
    /// Validation frames per epoch (the first N of the test split; 0 = all).
    #[serde(default)]
    pub val_frames: usize,
    /// Training frames per epoch (0, the default: the whole training set). Fewer: the epochs of both
    /// stages take successive frames of one shuffled pass over the set after another, so a set larger
    /// than the schedule is seen frame by frame before any frame repeats, and each epoch still ends in a
    /// validation and a checkpoint.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub epoch_frames: usize,
    /// Diagnostics: at the first step of every epoch, the gradient norm of each top-level module under
    /// each loss term alone (a `grad_terms` line in metrics.jsonl). Each term costs one more forward and
    /// backward of that step.
    #[serde(default)]
    pub term_gradients: bool,
    pub stage1: StageConfig,
    pub stage2: StageConfig,
    #[serde(default)]
    pub loss: LossWeights,
    /// Photometric jitter of training images (off by default; the paper states none).
    #[serde(default)]
    pub augment: Photometric,
    /// More training data: MVMP-HMR trees, CMU Panoptic or Human3.6M read in place (see
    /// [`SourceSpec`]); their frames are shuffled together with `data`'s.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub sources: Vec<SourceSpec>,
    /// The dataset validated on after every epoch (its `test` split unless it names one). Default: the
    /// first MVMP-HMR source, else the first source.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub validation: Option<SourceSpec>,
    /// Pretrained weights a new run starts from (not read when a run resumes).
    #[serde(default, skip_serializing_if = "InitWeights::is_empty")]
    pub init: InitWeights,
}

/// `[init]`: backbone weights loaded into a new run's network before its first step, as the paper starts
/// from backbones pretrained on 2D pose. Paths are relative to the training config's directory (or
/// absolute); the run's own copy of the config holds them absolute.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InitWeights {
    /// HRNet weights of the model's `hrnet` variant and heatmap joints, as `mvmp import hrnet` or
    /// `mvmp model extract --module hrnet` write them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub hrnet: Option<String>,
    /// ViT weights of the model's `backbone` variant, as `mvmp import dinov2` or `mvmp model extract
    /// --module vit` write them.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub vit: Option<String>,
}

impl InitWeights {
    pub fn is_empty(&self) -> bool {
        self.hrnet.is_none() && self.vit.is_none()
    }

    /// The files with their keys (`init.hrnet`, `init.vit`).
    pub fn files(&self) -> impl Iterator<Item = (&'static str, &str)> {
        [("init.hrnet", &self.hrnet), ("init.vit", &self.vit)]
            .into_iter()
            .filter_map(|(k, p)| p.as_deref().map(|p| (k, p)))
    }
}

fn one() -> usize {
    1
}
fn is_zero(n: &usize) -> bool {
    *n == 0
}
fn three() -> usize {
    3
}
fn five() -> usize {
    5
}
fn gate() -> f64 {
    0.5
}
fn mixed() -> QueryMode {
    QueryMode::Mixed
}

impl TrainConfig {
    /// Whether stage 1 of a run of `self` trains as one of `other` does, step for step: the two differ
    /// at most in `[stage2]`, in `keep_checkpoints` and in the loss settings stage 1 does not read
    /// (`step::stage1_loss` reads the detection, 2D heatmap, ViT heatmap and facing terms). A run of
    /// `self` may then go on from `other`'s stage-1 weights ([`crate::RunDir::branch`]).
    pub fn same_stage1(&self, other: &TrainConfig) -> bool {
        let mut a = self.clone();
        a.stage2 = other.stage2.clone();
        a.keep_checkpoints = other.keep_checkpoints;
        let (l, o) = (&mut a.loss, &other.loss);
        l.parameters = o.parameters;
        l.mesh_3d = o.mesh_3d;
        l.mesh_2d = o.mesh_2d;
        l.orientation = o.orientation;
        l.density = o.density;
        l.density_sigma = o.density_sigma;
        l.density_grid = o.density_grid;
        l.density_extent = o.density_extent;
        l.parameters_body_l2 = o.parameters_body_l2;
        l.joint_offsets = o.joint_offsets;
        l.heatmap_2d_stage2 = o.heatmap_2d_stage2;
        l.mesh_frame = o.mesh_frame;
        l.translation = o.translation;
        l.mesh_pose = o.mesh_pose;
        a == *other
    }

    /// Read and validate a config; returns it with the model config it names.
    pub fn read(path: &Path) -> Result<(TrainConfig, ModelConfig), TrainError> {
        let text = std::fs::read_to_string(path).map_err(|e| TrainError::io(path, e))?;
        let mut cfg: TrainConfig = toml::from_str(&text).map_err(|e| TrainError::Parse {
            path: path.into(),
            what: e.to_string(),
        })?;
        cfg.validate(path)?;
        cfg.resolve_init(path)?;
        let model_path = cfg.model_path(path);
        let model = ModelConfig::read(&model_path)?;
        if model.facing && cfg.loss.facing == 0.0 {
            return Err(TrainError::Config {
                path: path.into(),
                key: "loss.facing".into(),
                what: format!(
                    "0, but the model ({}) has a facing head (`facing = true`), which only this loss trains: the decoder would read an untrained head",
                    model_path.display()
                ),
            });
        }
        check_vit_heatmaps(path, &model_path, &model, &cfg.loss)?;
        if model.decoder.joint_offsets != (cfg.loss.joint_offsets > 0.0) {
            return Err(TrainError::Config {
                path: path.into(),
                key: "loss.joint_offsets".into(),
                what: format!(
                    "{}, but the model ({}) has `decoder.joint_offsets = {}`: the offsets' head and their loss go together (only this loss trains the head)",
                    cfg.loss.joint_offsets,
                    model_path.display(),
                    model.decoder.joint_offsets
                ),
            });
        }
        let read = model.decoder.pose_read && model.decoder.joint_samples;
        if cfg.stage2.pose_fit_frames > 0 && !read {
            return Err(TrainError::Config {
                path: path.into(),
                key: "stage2.pose_fit_frames".into(),
                what: format!(
                    "{}, but the model ({}) has no linear pose read to fit (`decoder.pose_read` and `decoder.joint_samples`)",
                    cfg.stage2.pose_fit_frames,
                    model_path.display()
                ),
            });
        }
        Ok((cfg, model))
    }

    /// `[init]`'s files made absolute (relative ones are the config's directory's). Whether they exist
    /// is asked when a new run loads them: a run resumed or scored does not read them.
    fn resolve_init(&mut self, path: &Path) -> Result<(), TrainError> {
        let dir = path.parent().unwrap_or(Path::new("."));
        for (key, slot) in [
            ("init.hrnet", &mut self.init.hrnet),
            ("init.vit", &mut self.init.vit),
        ] {
            if let Some(file) = slot.as_deref() {
                let abs = std::path::absolute(dir.join(file)).map_err(|e| TrainError::Config {
                    path: path.into(),
                    key: key.into(),
                    what: format!("{file}: {e}"),
                })?;
                *slot = Some(abs.to_string_lossy().into_owned());
            }
        }
        Ok(())
    }

    /// The model config's path for a config read from `path`.
    pub fn model_path(&self, path: &Path) -> PathBuf {
        let m = Path::new(&self.model);
        if m.is_absolute() {
            m.into()
        } else {
            path.parent().unwrap_or(Path::new(".")).join(m)
        }
    }

    pub fn validate(&self, path: &Path) -> Result<(), TrainError> {
        self.check_run()
            .and_then(|()| self.check_stages())
            .and_then(|()| self.check_sources())
            .and_then(|()| self.loss.validate().map_err(|what| ("loss".into(), what)))
            .map_err(|(key, what)| TrainError::Config {
                path: path.into(),
                key,
                what,
            })
    }

    /// Batch, views, matching gate, checkpoints and augmentation: the offending key and why.
    fn check_run(&self) -> Result<(), (String, String)> {
        let bad = |key: &str, what: String| Err((key.to_string(), what));
        if !(1..=MAX_BATCH).contains(&self.batch_size) {
            return bad(
                "batch_size",
                format!("{}: expected 1 to {MAX_BATCH}", self.batch_size),
            );
        }
        for (key, n) in [
            ("train_views", self.train_views),
            ("test_views", self.test_views),
        ] {
            if !(1..=MAX_VIEWS).contains(&n) {
                return bad(key, format!("{n}: expected 1 to {MAX_VIEWS} views"));
            }
        }
        if !(self.match_gate.is_finite() && self.match_gate > 0.0) {
            return bad(
                "match_gate",
                format!("{}: must be positive", self.match_gate),
            );
        }
        if self.keep_checkpoints == 0 {
            return bad("keep_checkpoints", "0: must be at least 1".into());
        }
        if let Some((key, x)) = self.augment.invalid() {
            return bad(
                &format!("augment.{key}"),
                format!("{x}: expected a strength within [0, 1)"),
            );
        }
        Ok(())
    }

    /// Each stage's rates, clipping and schedule: the offending key and why.
    fn check_stages(&self) -> Result<(), (String, String)> {
        let bad = |key: String, what: String| Err((key, what));
        for (name, s) in [("stage1", &self.stage1), ("stage2", &self.stage2)] {
            for (key, n) in [("epochs", s.epochs), ("warmup_steps", s.warmup_steps)] {
                if n > MAX_EPOCHS {
                    return bad(
                        format!("{name}.{key}"),
                        format!("{n}: expected at most {MAX_EPOCHS}"),
                    );
                }
            }
            if !(s.lr.is_finite() && s.lr > 0.0) {
                return bad(format!("{name}.lr"), format!("{}: must be positive", s.lr));
            }
            for (key, rate) in [
                ("decoder_lr", s.decoder_lr),
                ("detection_lr", s.detection_lr),
            ] {
                if let Some(d) = rate
                    && !(d.is_finite() && d > 0.0)
                {
                    return bad(format!("{name}.{key}"), format!("{d}: must be positive"));
                }
            }
            if !(s.final_lr_factor.is_finite() && (0.0..=1.0).contains(&s.final_lr_factor)) {
                return bad(
                    format!("{name}.final_lr_factor"),
                    format!("{}: must be within [0, 1]", s.final_lr_factor),
                );
            }
            if !(s.average_decay.is_finite() && (0.0..1.0).contains(&s.average_decay)) {
                return Err((
                    format!("{name}.average_decay"),
                    format!("{}: must be 0 (off) or in (0, 1)", s.average_decay),
                ));
            }
            if !(s.grad_clip.is_finite() && s.grad_clip >= 0.0) {
                return bad(
                    format!("{name}.grad_clip"),
                    format!("{}: must be 0 (off) or positive", s.grad_clip),
                );
            }
        }
        if self.stage1.freeze_backbone {
            return bad(
                "stage1.freeze_backbone".into(),
                "true: stage 1 trains HRNet and the RootNet only; set it in stage2".into(),
            );
        }
        if self.stage1.freeze_detection {
            return bad(
                "stage1.freeze_detection".into(),
                "true: stage 1 is what trains detection; set it in stage2".into(),
            );
        }
        if let Some(d) = self.stage1.detection_lr {
            return bad(
                "stage1.detection_lr".into(),
                format!("{d}: stage 1 trains detection alone, at its lr; set it in stage2"),
            );
        }
        if self.stage1.pose_fit_frames > 0 {
            return bad(
                "stage1.pose_fit_frames".into(),
                format!(
                    "{}: stage 1 does not train the decoder; set it in stage2",
                    self.stage1.pose_fit_frames
                ),
            );
        }
        if self.stage2.pose_fit_frames > MAX_EPOCHS {
            return bad(
                "stage2.pose_fit_frames".into(),
                format!(
                    "{}: expected at most {MAX_EPOCHS}",
                    self.stage2.pose_fit_frames
                ),
            );
        }
        if self.stage1.cache_volumes {
            return bad(
                "stage1.cache_volumes".into(),
                "true: stage 1 trains what the volumes come from; set it in stage2".into(),
            );
        }
        if self.stage2.cache_volumes
            && !(self.stage2.freeze_backbone && self.stage2.freeze_detection)
        {
            return bad(
                "stage2.cache_volumes".into(),
                "true without freeze_backbone = true and freeze_detection = true: the volumes it keeps \
                 would go stale as those modules train"
                    .into(),
            );
        }
        if self.stage2.cache_volumes && self.batch_size != 1 {
            return bad(
                "stage2.cache_volumes".into(),
                format!(
                    "true with batch_size = {}: it keeps one frame per step (batch_size = 1)",
                    self.batch_size
                ),
            );
        }
        if self.stage1.train_rootnet {
            return bad(
                "stage1.train_rootnet".into(),
                "true: stage 1 trains the RootNet anyway; set it in stage2 with freeze_detection"
                    .into(),
            );
        }
        if self.stage2.train_rootnet && !self.stage2.freeze_detection {
            return bad(
                "stage2.train_rootnet".into(),
                "true without freeze_detection = true: the RootNet trains with the rest of detection \
                 anyway"
                    .into(),
            );
        }
        if self.stage2.freeze_detection
            && !self.stage2.train_rootnet
            && self.stage2.detection_lr.is_some()
        {
            return bad(
                "stage2.detection_lr".into(),
                "set with freeze_detection = true (and no train_rootnet), which trains detection at no \
                 rate"
                    .into(),
            );
        }
        if self.epoch_frames > MAX_EPOCHS {
            return bad(
                "epoch_frames".into(),
                format!("{}: expected at most {MAX_EPOCHS}", self.epoch_frames),
            );
        }
        if self.stage1.epochs + self.stage2.epochs == 0 {
            return bad(
                "stage1.epochs, stage2.epochs".into(),
                "both 0: nothing to train".into(),
            );
        }
        Ok(())
    }

    /// The extra training sources and the validation source: the offending key and why.
    fn check_sources(&self) -> Result<(), (String, String)> {
        let bad = |key: String, what: &str| Err((key, what.to_string()));
        for (i, src) in self.sources.iter().enumerate() {
            if src.stride == Some(0) {
                return bad(
                    format!("sources[{i}].stride"),
                    "0: keep every N-th frame with N >= 1",
                );
            }
            if src.repeat == Some(0) {
                return bad(
                    format!("sources[{i}].repeat"),
                    "0: each frame is drawn at least once per epoch",
                );
            }
            if let Some(r) = src.repeat.filter(|&r| r > MAX_REPEAT) {
                return Err((
                    format!("sources[{i}].repeat"),
                    format!("{r}: at most {MAX_REPEAT} draws of each frame per epoch"),
                ));
            }
            if src.format == SourceFormat::Mvmp && (src.stride.is_some() || src.cameras.is_some()) {
                return bad(
                    format!("sources[{i}]"),
                    "stride and cameras apply to panoptic and h36m sources; an mvmp source uses every frame",
                );
            }
            let cams = src.cameras.as_deref().unwrap_or_default();
            if let Some(c) = (1..cams.len()).find(|&k| cams[..k].contains(&cams[k])) {
                return Err((
                    format!("sources[{i}].cameras"),
                    format!(
                        "{:?} is listed twice: a rig's cameras are distinct",
                        cams[c]
                    ),
                ));
            }
            if src.format == SourceFormat::Mvmp && src.pseudo_gt.is_some() {
                return bad(
                    format!("sources[{i}].pseudo_gt"),
                    "applies to panoptic and h36m sources; an mvmp source has SMPL-X ground truth",
                );
            }
        }
        let validation = self.validation.as_ref();
        if validation.is_some_and(|v| v.pseudo_gt.is_some()) {
            return bad(
                "validation.pseudo_gt".into(),
                "applies to training sources; validation scores the dataset's joints (use `mvmp eval --pseudo-gt` for meshes)",
            );
        }
        if validation.is_some_and(|v| v.repeat.is_some()) {
            return bad(
                "validation.repeat".into(),
                "repeat applies to training sources; validation uses each frame once",
            );
        }
        Ok(())
    }

    /// The training sources: `data` (an MVMP-HMR tree, its train split) first, then `sources`.
    pub fn training_sources(&self) -> Vec<SourceSpec> {
        let mut out: Vec<SourceSpec> = self
            .data
            .iter()
            .map(|d| SourceSpec {
                format: SourceFormat::Mvmp,
                root: d.clone(),
                split: None,
                stride: None,
                cameras: None,
                repeat: None,
                pseudo_gt: None,
            })
            .collect();
        out.extend(self.sources.iter().cloned());
        out
    }

    /// The validation source: `validation`, else the first MVMP-HMR training source, else the first
    /// training source (each on its test split unless `validation` names another).
    pub fn validation_source(&self) -> Option<SourceSpec> {
        if let Some(v) = &self.validation {
            return Some(v.clone());
        }
        let all = self.training_sources();
        all.iter()
            .find(|s| s.format == SourceFormat::Mvmp)
            .or(all.first())
            .map(|s| SourceSpec {
                split: None,
                ..s.clone()
            })
    }

    pub fn stage(&self, stage: Stage) -> &StageConfig {
        match stage {
            Stage::Detection => &self.stage1,
            Stage::Whole => &self.stage2,
        }
    }
}

/// A `vit_heatmaps` head and the `vit_heatmap` loss go together: the head without its loss is an
/// untrained layer, the loss without the head has nothing to read.
fn check_vit_heatmaps(
    path: &Path,
    model_path: &Path,
    model: &ModelConfig,
    loss: &LossWeights,
) -> Result<(), TrainError> {
    let what = match (model.vit_heatmaps, loss.vit_heatmap > 0.0) {
        (true, false) => format!(
            "0, but the model ({}) has a ViT heatmap head (`vit_heatmaps = true`), which only this loss trains",
            model_path.display()
        ),
        (false, true) => format!(
            "{}, but the model ({}) has no ViT heatmap head (`vit_heatmaps = false`) for it to train",
            loss.vit_heatmap,
            model_path.display()
        ),
        _ => return Ok(()),
    };
    Err(TrainError::Config {
        path: path.into(),
        key: "loss.vit_heatmap".into(),
        what,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stages_are_numbered_one_and_two() {
        assert_eq!(Stage::Detection.number(), 1);
        assert_eq!(Stage::Whole.number(), 2);
        assert_eq!(serde_json::to_string(&Stage::Whole).unwrap(), "2");
        assert_eq!(
            serde_json::from_str::<Stage>("1").unwrap(),
            Stage::Detection
        );
        let e = serde_json::from_str::<Stage>("3").unwrap_err().to_string();
        assert!(e.contains("stage 3"), "{e}");
        assert_eq!(format!("stage{}", Stage::Whole), "stage2");
    }

    fn stage(warmup_steps: usize, schedule: LrSchedule) -> StageConfig {
        StageConfig {
            epochs: 1,
            lr: 1e-3,
            decoder_lr: None,
            detection_lr: None,
            warmup_steps,
            schedule,
            final_lr_factor: 0.1,
            grad_clip: 0.0,
            freeze_backbone: false,
            freeze_detection: false,
            train_rootnet: false,
            average_decay: 0.0,
            pose_fit_frames: 0,
            cache_volumes: false,
        }
    }

    #[test]
    fn learning_rate_curves() {
        let close = |a: f64, b: f64| (a - b).abs() < 1e-12;
        let c = stage(0, LrSchedule::Constant);
        assert!((0..10).all(|s| close(c.lr_at(s, 10), 1e-3)));
        // Warm-up of 3 steps: 1/4, 2/4, 3/4 of the peak, then the peak.
        let w = stage(3, LrSchedule::Constant);
        let got: Vec<f64> = (0..5).map(|s| w.lr_at(s, 10)).collect();
        for (g, want) in got.iter().zip([0.25e-3, 0.5e-3, 0.75e-3, 1e-3, 1e-3]) {
            assert!(close(*g, want), "{got:?}");
        }
        // Cosine after a warm-up of 2 over 12 steps: the peak at step 2, the floor (0.1 lr) at step 11,
        // halfway between at the middle step (2 + 9/2 = 6.5: the mean of steps 6 and 7 by symmetry).
        let k = stage(2, LrSchedule::Cosine);
        assert!(close(k.lr_at(2, 12), 1e-3));
        assert!(close(k.lr_at(11, 12), 1e-4));
        assert!(close(k.lr_at(6, 12) + k.lr_at(7, 12), 1e-3 + 1e-4));
        assert!((2..11).all(|s| k.lr_at(s + 1, 12) < k.lr_at(s, 12)));
        // The decoder's own rate follows the same curve at its own peak; without one it has none.
        assert_eq!(k.decoder_lr_at(5, 12), None);
        let dk = StageConfig {
            decoder_lr: Some(2e-4),
            ..k
        };
        assert!((0..12).all(|s| close(dk.decoder_lr_at(s, 12).unwrap(), 0.2 * dk.lr_at(s, 12))));
        // So do the detection modules'.
        assert_eq!(dk.detection_lr_at(5, 12), None);
        let tk = StageConfig {
            detection_lr: Some(5e-4),
            ..dk
        };
        assert!((0..12).all(|s| close(tk.detection_lr_at(s, 12).unwrap(), 0.5 * tk.lr_at(s, 12))));
    }
}
