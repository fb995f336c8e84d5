//! The training loop: stage 1 (detection: HRNet, the RootNet and the heads trained with them), then
//! stage 2 (the whole model), with checkpoints every epoch and on interruption, validation every epoch,
//! exact resume and a stop on non-finite losses.
use std::borrow::Cow;
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use burn::data::dataloader::batcher::Batcher;
use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::{GradientsParams, ModuleOptimizer};
use burn::tensor::Gradients;
use burn::tensor::{Device, Tensor};
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde_json::json;

use mvmp_data::loader::{FrameBatch, FrameBatcher, FrameSample, ViewChoice};
use mvmp_data::sequence::covered_slots;
use mvmp_data::sources::{SourceFormat, SourceSpec, TrainingSet};
use mvmp_losses::LossWeights;
use mvmp_model::{ModelConfig, MvmpHmr, Upstream};
use mvmp_smplx::{BodyModel, SmplxLayer};

use crate::TrainError;
use crate::average::WeightAverage;
use crate::config::{Stage, StageConfig, TrainConfig};
use crate::pose_fit::{PoseFit, ReadWeights, fit_pose_read, set_read};
use crate::run::{RunDir, RunState, STATE_FORMAT, file_hash};
use crate::step::{Stage2, StepLoss, batch_grids, stage1_loss, stage2_loss_with};
use crate::validation::{check_validation_source, source_cameras, validate};
use mvmp_eval::drivers::PseudoGt;
use mvmp_infer::load_weights;

/// One optimizer step, as logged: its line in `metrics.jsonl` is the record serialized (`"kind": "step"`,
/// every weighted term under its own name, `phase_seconds` and `grad_norm` as objects).
#[derive(Debug, Clone, serde::Serialize)]
#[serde(tag = "kind", rename = "step")]
pub struct StepRecord {
    pub stage: Stage,
    /// 1-based epoch of the stage and step within it.
    pub epoch: usize,
    pub step: usize,
    #[serde(skip)]
    pub steps_per_epoch: usize,
    pub global_step: u64,
    pub lr: f64,
    /// The decoder's rate when it has its own (`decoder_lr` in the stage).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub decoder_lr: Option<f64>,
    /// HRNet's, the RootNet's and the facing head's rate when they have their own (`detection_lr`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub detection_lr: Option<f64>,
    pub seconds: f64,
    /// Where those seconds went: `load` (images and batch), `forward` (the loss), `backward`, `grad_norm`
    /// (the per-module norms) and `optimizer`, in that order.
    #[serde(rename = "phase_seconds", serialize_with = "as_object")]
    pub phases: Vec<(&'static str, f64)>,
    /// Weighted terms and their total.
    #[serde(flatten, serialize_with = "as_object")]
    pub terms: Vec<(String, f32)>,
    pub total: f32,
    /// People decoded (stage 2) and the detection diagnostics of [`StepLoss`].
    pub queries: usize,
    pub root_peak: f32,
    pub root_at_gt: f32,
    pub root_background: f32,
    /// The gradient norm of each top-level module.
    #[serde(serialize_with = "as_object")]
    pub grad_norm: Vec<(String, f32)>,
}

/// Named values as one JSON object.
fn as_object<S, K, V>(pairs: &[(K, V)], s: S) -> Result<S::Ok, S::Error>
where
    S: serde::Serializer,
    K: serde::Serialize,
    V: serde::Serialize,
{
    s.collect_map(pairs.iter().map(|(k, v)| (k, v)))
}

/// A validation pass at the end of an epoch.
#[derive(Debug, Clone)]
pub struct ValRecord {
    pub stage: Stage,
    pub epoch: usize,
    /// `root_mm`/`root_recall` in stage 1; `mpjpe_mm`, `pve_mm`, `pa_pve_mm`, `recall_500` in stage 2, and
    /// on MVMP-HMR data `heading_spread_deg`, `body_pose_spread_deg` (see [`mvmp_eval::spread`]).
    pub metrics: Vec<(String, f64)>,
}

/// What training reports as it goes (the CLI draws a progress bar from it).
pub trait Monitor {
    /// A stage starts (or resumes with `done` of its `epochs * steps_per_epoch` steps behind it).
    fn stage(&mut self, _stage: Stage, _epochs: usize, _steps_per_epoch: usize, _done: usize) {}
    fn step(&mut self, _s: &StepRecord) {}
    fn validation(&mut self, _v: &ValRecord) {}
    fn checkpoint(&mut self, _path: &Path) {}
    /// The decoder's pose read was fitted before the final weights (`stage2.pose_fit_frames`).
    fn pose_fit(&mut self, _fit: &PoseFit) {}
}

/// A monitor that reports nothing.
pub struct Quiet;
impl Monitor for Quiet {}

/// Run-time options (not part of the config).
#[derive(Clone)]
pub struct TrainOptions {
    /// The plain device; training adds autodiff to it.
    pub device: Device,
    /// Set (by Ctrl-C) to stop after the current step with a checkpoint.
    pub stop: Arc<AtomicBool>,
    /// Stop as if interrupted once the run has made this many optimizer steps.
    pub stop_after_steps: Option<u64>,
    /// Stop as if interrupted once this call has trained this long (wall time from the call; the step in
    /// flight finishes first). Comparisons of configurations at equal wall time use it.
    pub stop_after_time: Option<std::time::Duration>,
}

/// How training ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Outcome {
    Finished,
    Interrupted {
        checkpoint: PathBuf,
        global_step: u64,
    },
}

/// The frames of an epoch of `count` frames starting `start` frames into a sequence of shuffled passes
/// over the `n` training frames (`epoch_frames`): every frame once per pass, each pass in its own order
/// (depends on the seed and the pass only).
pub fn pass_frames(seed: u64, start: usize, count: usize, n: usize) -> Vec<usize> {
    let mut out = Vec::with_capacity(count);
    let mut p = start;
    while out.len() < count && n > 0 {
        let pass = p / n;
        let mut rng = ChaCha8Rng::seed_from_u64(
            seed ^ ((3u64 << 32) | pass as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15),
        );
        let mut order: Vec<usize> = (0..n).collect();
        order.shuffle(&mut rng);
        let take = (count - out.len()).min(n - p % n);
        out.extend_from_slice(&order[p % n..p % n + take]);
        p += take;
    }
    out
}

/// Steps of an epoch over `total` training frames: `epoch_frames` of them, or all.
fn epoch_steps(cfg: &TrainConfig, total: usize) -> usize {
    let frames = match cfg.epoch_frames {
        0 => total,
        e => e,
    };
    frames.div_ceil(cfg.batch_size)
}

/// Stage-and-epoch key of the data order and view draws.
/// The samples of one batch, loaded in parallel.
fn load_batch(data: &TrainingSet, chunk: &[usize]) -> Result<Vec<FrameSample>, TrainError> {
    let items = chunk
        .par_iter()
        .map(|&i| data.load(i))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(items)
}

fn epoch_key(stage: Stage, epoch: usize) -> u64 {
    ((stage.number() as u64) << 32) | epoch as u64
}

/// The order of the training frames in an epoch (depends on the seed, stage and epoch only).
pub fn epoch_order(seed: u64, stage: Stage, epoch: usize, n: usize) -> Vec<usize> {
    let mut rng = ChaCha8Rng::seed_from_u64(
        seed ^ epoch_key(stage, epoch).wrapping_mul(0x9E37_79B9_7F4A_7C15),
    );
    let mut order: Vec<usize> = (0..n).collect();
    order.shuffle(&mut rng);
    order
}

/// The training samples of every source of `cfg` (`config` names the config in errors). Checks that each
/// joint-annotated source annotates the model's primary joint (the root the detection branch learns) and
/// that there is at least one frame.
pub fn open_training_set(
    cfg: &TrainConfig,
    model_cfg: &ModelConfig,
    config: &Path,
) -> Result<TrainingSet, TrainError> {
    let specs = cfg.training_sources();
    if specs.is_empty() {
        return Err(TrainError::Config {
            path: config.into(),
            key: "data".into(),
            what: "missing: set `data` (an MVMP-HMR dataset) or add [[sources]]".into(),
        });
    }
    // `data`, when set, is the first spec; errors name a source by its index in `[[sources]]`.
    let key = |i: usize, field: &str| match (i + cfg.sources.len()).checked_sub(specs.len()) {
        Some(k) => format!("sources[{k}].{field}"),
        None => "data".to_string(),
    };
    let mut parts = Vec::with_capacity(specs.len());
    for (i, spec) in specs.iter().enumerate() {
        let bad = |key: String, what: String| TrainError::Config {
            path: config.into(),
            key,
            what,
        };
        check_primary_joint(model_cfg, spec).map_err(|w| bad(key(i, "format"), w))?;
        let cameras = source_cameras(spec)?;
        if cfg.train_views > cameras {
            return Err(bad(
                "train_views".into(),
                format!(
                    "{}: the frames of {} ({}) have {cameras} cameras",
                    cfg.train_views,
                    key(i, "root"),
                    spec.root
                ),
            ));
        }
        let part = spec.open_training(
            ViewChoice::Random {
                count: cfg.train_views,
                seed: cfg.seed,
            },
            model_cfg.image_size,
        )?;
        parts.push(match (&spec.pseudo_gt, part) {
            (Some(dir), d) if spec.format != SourceFormat::Mvmp => {
                let dir = PathBuf::from(dir);
                if !dir.is_dir() {
                    return Err(bad(
                        key(i, "pseudo_gt"),
                        format!("{}: not a directory", dir.display()),
                    ));
                }
                let meshes = pseudo_gt_meshes(cfg, model_cfg, config, dir)?;
                d.with_meshes(meshes)
            }
            (_, part) => part,
        });
    }
    let set = TrainingSet::with_repeats(parts, specs.iter().map(SourceSpec::repeat).collect())
        .with_augment(cfg.augment, cfg.seed);
    if set.total() == 0 {
        return Err(TrainError::file(
            config,
            "the training sources have no frames in their train splits",
        ));
    }
    Ok(set)
}

/// A training source's joints must include the model's primary joint (the root the detection branch
/// learns): why not, if they do not.
fn check_primary_joint(model_cfg: &ModelConfig, spec: &SourceSpec) -> Result<(), String> {
    let set = spec.format.joint_set();
    if covered_slots(set)[model_cfg.primary_joint.joint()] {
        return Ok(());
    }
    Err(format!(
        "{}: its joints ({}) do not include the model's primary joint {:?}",
        spec.format.name(),
        set.name(),
        model_cfg.primary_joint
    ))
}

/// The pseudo-ground-truth meshes of a joint-annotated source: SMPL-X fits in `dir`, posed with the
/// model's body model.
fn pseudo_gt_meshes(
    cfg: &TrainConfig,
    model_cfg: &ModelConfig,
    config: &Path,
    dir: PathBuf,
) -> Result<Arc<crate::pseudo::PseudoGtMeshes>, TrainError> {
    // A path is absolute by now (`ModelConfig::read` resolves it beside its config).
    let base = config.parent().unwrap_or(Path::new("."));
    let body = mvmp_data::layout::load_body_model(&model_cfg.body_model, base)?;
    let layer = SmplxLayer::new(&body, &Device::flex());
    Ok(Arc::new(crate::pseudo::PseudoGtMeshes(PseudoGt {
        dir,
        layer,
        gate: cfg.match_gate,
    })))
}

/// A model initialised from `seed`. Seeding and drawing the initial weights happen under one process-wide
/// lock: the backend's generator is shared, and another thread drawing in between would change the weights.
/// Other code that draws random tensors concurrently (a model init elsewhere) should use this too.
pub fn seeded_init(cfg: &ModelConfig, device: &Device, seed: u64) -> MvmpHmr {
    static LOCK: std::sync::Mutex<()> = std::sync::Mutex::new(());
    let _guard = LOCK.lock().unwrap_or_else(|e| e.into_inner());
    device.seed(seed);
    let model = cfg.init(device);
    // Parameters are initialised lazily, on first use: draw them now, while the lock is held.
    struct Touch;
    impl burn::module::ModuleVisitor for Touch {
        fn visit_float<const D: usize>(
            &mut self,
            p: &burn::module::Param<burn::tensor::Tensor<D>>,
        ) {
            let _ = p.val();
        }
    }
    model.visit(&mut Touch);
    model
}

/// A fresh model whose decoder regresses from the mean parameters of the training people (those of the
/// MVMP-HMR sources; others carry no SMPL-X parameters), as HMR-style regressors start from a mean. From
/// the default (upright T-pose, zero shape) the tiny demo's decoder did not reach even the data's mean
/// articulation in 192 steps: a head's bias moves about one learning rate per step, and the arms hang
/// 1.2 rad from the T-pose.
fn start_at_data_mean(
    mut model: MvmpHmr,
    data: &TrainingSet,
    device: &Device,
) -> Result<MvmpHmr, TrainError> {
    let mut acc = mvmp_data::mean::MeanAccumulator::default();
    for part in &data.parts {
        if let Some(layout) = part.layout() {
            acc.add_frames(layout, part.frame_refs())?;
        }
    }
    Ok(match acc.finish() {
        Some(mean) => {
            model.decoder = model
                .decoder
                .with_mean(mvmp_eval::drivers::mean_vector(&mean, device));
            model
        }
        None => model,
    })
}

/// Train (or resume) the run in `run`.
pub fn train(
    run: &RunDir,
    cfg: &TrainConfig,
    model_cfg: &ModelConfig,
    opts: &TrainOptions,
    mon: &mut dyn Monitor,
) -> Result<Outcome, TrainError> {
    let started = Instant::now();
    let state = run.state()?;
    if state.as_ref().is_some_and(|s| s.finished) {
        if !run.root.join("model.bpk").exists() {
            return Err(TrainError::file(
                run.state_path(),
                "key `finished` is true, but the run has no model.bpk",
            ));
        }
        return Ok(Outcome::Finished);
    }
    if state.is_none() {
        check_untrained(run)?;
    }
    let (mut trainer, model) = Trainer::open(run, cfg, model_cfg, opts, state, started)?;
    trainer.run(model, mon)
}

/// A run without `state.json` starts from the first step, so it must hold no weights that a start would
/// throw away (steps logged without a checkpoint are trained again, the same way).
fn check_untrained(run: &RunDir) -> Result<(), TrainError> {
    let ckpt = run.root.join("checkpoints");
    let has_checkpoint = std::fs::read_dir(&ckpt)
        .map(|d| {
            // Checkpoints are `step*.bpk`; a dot-file is a write a kill interrupted.
            d.flatten().any(|e| {
                let name = e.file_name().to_string_lossy().into_owned();
                name.starts_with("step") && name.ends_with(".bpk")
            })
        })
        .unwrap_or(false);
    if has_checkpoint || run.root.join("model.bpk").exists() {
        return Err(TrainError::file(
            run.state_path(),
            "missing, but the run has checkpoints or model.bpk: without it the run cannot continue \
             where it stopped; restore it, or start a new run",
        ));
    }
    Ok(())
}

/// A resumed state's epoch and step lie within its stage (a damaged `state.json` is refused before
/// anything trains).
fn check_cursor(
    run: &RunDir,
    cfg: &TrainConfig,
    s: &RunState,
    steps_per_epoch: usize,
) -> Result<(), TrainError> {
    let epochs = cfg.stage(s.stage).epochs;
    let bad = |key: &str, what: String| {
        Err(TrainError::file(
            run.state_path(),
            format!("key `{key}`: {what}"),
        ))
    };
    if s.epoch > epochs {
        return bad(
            "epoch",
            format!(
                "{}: stage {} has {epochs} epochs",
                s.epoch,
                s.stage.number()
            ),
        );
    }
    // An interruption after an epoch's last step records all of them (the epoch's end is still to run).
    if s.step_in_epoch > steps_per_epoch || (s.epoch == epochs && s.step_in_epoch > 0) {
        return bad(
            "step_in_epoch",
            format!(
                "{}: an epoch of this run has {steps_per_epoch} steps (epoch {} of {epochs})",
                s.step_in_epoch, s.epoch
            ),
        );
    }
    // Every epoch has the same steps, so the stage, epoch and step tell the run's step count.
    let before: usize = Stage::ALL
        .iter()
        .filter(|&&st| st < s.stage)
        .map(|&st| cfg.stage(st).epochs)
        .sum();
    let expected = ((before + s.epoch) * steps_per_epoch + s.step_in_epoch) as u64;
    if s.global_step != expected {
        return bad(
            "global_step",
            format!(
                "{}: stage {}, epoch {} and step {} make {expected} (or the training data changed since)",
                s.global_step,
                s.stage.number(),
                s.epoch,
                s.step_in_epoch
            ),
        );
    }
    Ok(())
}

/// Where training stands: every step before it is in the newest checkpoint.
#[derive(Debug, Clone, Copy)]
struct Cursor {
    stage: Stage,
    /// Epochs of the stage completed, and batches of the next one trained.
    epoch: usize,
    step_in_epoch: usize,
    /// Optimizer steps over the whole run.
    global: u64,
}

/// A training run in progress: the data, the devices, the body layers and the run directory it writes,
/// with the cursor. The model itself flows through the methods by value (the optimizer consumes it).
/// The batcher that poses the ground truth: with the body model of the (first) MVMP-HMR source, whose
/// people have meshes (joint-annotated people have none). When that is the model's own body model it
/// shares the model's layer rather than holding a second copy.
fn gt_batcher(
    data: &TrainingSet,
    body: &Arc<BodyModel>,
    layer: &SmplxLayer,
    model_cfg: &ModelConfig,
    run_root: &Path,
) -> Result<FrameBatcher, TrainError> {
    let source = data.parts.iter().find_map(|p| p.layout());
    Ok(match source {
        Some(l)
            if !mvmp_data::layout::same_body_model(
                &l.index.body_model,
                &l.root,
                &model_cfg.body_model,
                run_root,
            ) =>
        {
            FrameBatcher::with_vertices(l.body_model()?)
        }
        _ => FrameBatcher::with_layer(body.clone(), layer.clone()),
    })
}

struct Trainer<'a> {
    run: &'a RunDir,
    cfg: &'a TrainConfig,
    opts: &'a TrainOptions,
    started: Instant,
    plain: Device,
    ad: Device,
    body: Arc<BodyModel>,
    /// Shared with the thread that loads the next batch while a step runs.
    data: Arc<TrainingSet>,
    batcher: FrameBatcher,
    val_source: Option<SourceSpec>,
    cursor: Cursor,
    /// The optimizer state to resume the current stage with.
    resume_optim: Option<PathBuf>,
    /// The weight average to resume the current stage with.
    resume_average: Option<PathBuf>,
    /// The current stage's weight average, when it keeps one (`average_decay`).
    average: Option<WeightAverage>,
    /// What the model computes before the decoder, per training frame, under `cache_volumes`.
    kept: HashMap<usize, Upstream>,
    last_checkpoint: String,
}

impl<'a> Trainer<'a> {
    /// The run's data and model, resumed from its state when it has one.
    fn open(
        run: &'a RunDir,
        cfg: &'a TrainConfig,
        model_cfg: &'a ModelConfig,
        opts: &'a TrainOptions,
        state: Option<RunState>,
        started: Instant,
    ) -> Result<(Self, MvmpHmr), TrainError> {
        let plain = opts.device.clone();
        let ad = plain.clone().autodiff();
        let mut model = seeded_init(model_cfg, &ad, cfg.seed);
        let mut cursor = Cursor {
            stage: Stage::Detection,
            epoch: 0,
            step_in_epoch: 0,
            global: 0,
        };
        let mut last_checkpoint = String::from("none (no checkpoint was written yet)");
        let mut resume_optim = None;
        let mut resume_average = None;
        if let Some(s) = &state {
            run.check_model_unchanged(s)?;
            run.check_checkpoint_files(s)?;
            load_weights(&mut model, &run.root.join(&s.checkpoint))?;
            model = model.train();
            cursor = Cursor {
                stage: s.stage,
                epoch: s.epoch,
                step_in_epoch: s.step_in_epoch,
                global: s.global_step,
            };
            last_checkpoint = run.root.join(&s.checkpoint).display().to_string();
            resume_optim = s.optimizer.as_ref().map(|o| run.root.join(o));
            resume_average = s.average.as_ref().map(|a| run.root.join(a));
        }
        let body = mvmp_data::layout::load_body_model(&model_cfg.body_model, &run.root)?;
        let mut data = open_training_set(cfg, model_cfg, &run.root.join("train.toml"))?;
        data.expect_joints(body.num_output_joints(), &model_cfg.body_model);
        check_validation_source(cfg)?;
        // Ground-truth meshes are posed with the body model of the (first) MVMP-HMR source; joint-annotated
        // people have none.
        let body = Arc::new(body);
        // The model's layer poses the ground truth too. Validation's copy of the model builds its own on
        // the plain device and drops it, so that it is not held through the training steps' peak.
        model = model.with_body(body.clone());
        let batcher = gt_batcher(&data, &body, &model.body_layer(&ad), model_cfg, &run.root)?;
        if let Some(s) = &state {
            check_cursor(run, cfg, s, epoch_steps(cfg, data.total()))?;
        }
        run.truncate_log(cursor.global)?;
        run.remove_stale_temporaries()?;
        if state.is_none() {
            crate::init::load_init(&mut model, &cfg.init)?;
            model = start_at_data_mean(model, &data, &ad)?;
        }
        let trainer = Trainer {
            run,
            cfg,
            opts,
            started,
            plain,
            ad,
            body,
            data: Arc::new(data),
            batcher,
            val_source: cfg.validation_source(),
            cursor,
            resume_optim,
            resume_average,
            average: None,
            kept: HashMap::new(),
            last_checkpoint,
        };
        Ok((trainer, model))
    }

    fn steps_per_epoch(&self) -> usize {
        epoch_steps(self.cfg, self.data.total())
    }

    /// The training frames of an epoch, in order.
    fn frame_order(&self, stage: Stage, epoch: usize) -> Vec<usize> {
        let n = self.data.total();
        let e = self.cfg.epoch_frames;
        if e == 0 {
            return epoch_order(self.cfg.seed, stage, epoch, n);
        }
        let before: usize = Stage::ALL
            .iter()
            .filter(|&&st| st < stage)
            .map(|&st| self.cfg.stage(st).epochs)
            .sum();
        pass_frames(self.cfg.seed, (before + epoch) * e, e, n)
    }

    /// Both stages from the cursor on, then the final weights.
    fn run(&mut self, mut model: MvmpHmr, mon: &mut dyn Monitor) -> Result<Outcome, TrainError> {
        for stage in Stage::ALL {
            if stage < self.cursor.stage {
                continue;
            }
            if stage > self.cursor.stage {
                self.cursor = Cursor {
                    stage,
                    epoch: 0,
                    step_in_epoch: 0,
                    ..self.cursor
                };
                self.resume_optim = None;
                self.resume_average = None;
            }
            let out;
            (model, out) = self.run_stage(model, mon)?;
            if let Some(out) = out {
                return Ok(out);
            }
        }
        let fin = self.run.root.join("model.bpk");
        let mut last = self.averaged(&model);
        if let Some(read) = self.fit_pose(last.as_ref(), mon)? {
            set_read(last.to_mut(), &read);
        }
        mvmp_io::checkpoint::save(last.as_ref(), &fin)?;
        let mut s = self
            .run
            .state()?
            .ok_or_else(|| TrainError::file(self.run.state_path(), "missing"))?;
        s.finished = true;
        self.run.write_state(&s)?;
        Ok(Outcome::Finished)
    }

    /// The decoder's pose read of `model` fitted in closed form on `stage2.pose_fit_frames` training
    /// frames spread over the set (see [`fit_pose_read`]), the fit logged to `metrics.jsonl`; the
    /// weights only where they lower the held-back error. The frames' views and jitter are drawn as for
    /// one epoch past the stage's last, so that a resumed run fits the same.
    fn fit_pose(
        &self,
        model: &MvmpHmr,
        mon: &mut dyn Monitor,
    ) -> Result<Option<ReadWeights>, TrainError> {
        let total = self.data.total();
        let n = self.cfg.stage2.pose_fit_frames.min(total);
        if n == 0 {
            return Ok(None);
        }
        let plain = model.clone().valid();
        self.data
            .set_epoch(epoch_key(Stage::Whole, self.cfg.stage2.epochs));
        let batcher = FrameBatcher::default();
        let mut failed = None;
        let batches = (0..n).map_while(|i| match self.data.load(i * total / n) {
            Ok(sample) => Some(batcher.batch(vec![sample], &self.plain)),
            Err(e) => {
                failed = Some(e);
                None
            }
        });
        let queries = (self.cfg.queries, self.cfg.match_gate);
        let t0 = Instant::now();
        let fit = fit_pose_read(&plain, batches, queries, &self.plain);
        if let Some(e) = failed {
            return Err(e.into());
        }
        let Some((fit, weights)) = fit else {
            return Ok(None);
        };
        let mut line = json!({"kind": "pose_fit", "global_step": self.cursor.global});
        line["fit"] = json!(fit);
        line["seconds"] = json!(t0.elapsed().as_secs_f64());
        self.run.log(&line)?;
        mon.pose_fit(&fit);
        Ok(weights)
    }

    /// The current stage's remaining epochs, each validated and checkpointed. `Some` when training stops
    /// before the stage ends.
    fn run_stage(
        &mut self,
        mut model: MvmpHmr,
        mon: &mut dyn Monitor,
    ) -> Result<(MvmpHmr, Option<Outcome>), TrainError> {
        let stage = self.cursor.stage;
        let sc = self.cfg.stage(stage).clone();
        // Before the check below: a run stopped between its last checkpoint and its final weights ends
        // on the saved average.
        self.average = self.start_average(&model, &sc)?;
        if self.cursor.epoch >= sc.epochs {
            return Ok((model, None));
        }
        let mut optim = self.optimizer()?;
        if stage == Stage::Whole && sc.freeze_backbone {
            model.vit = model.vit.clone().no_grad();
        }
        if stage == Stage::Whole && sc.freeze_detection {
            // Frozen rather than only without gradients: HRNet's batch norms then keep the running
            // statistics stage 1 left instead of updating them in every forward.
            model.hrnet = model.hrnet.clone().freeze();
            if !sc.train_rootnet {
                model.rootnet = model.rootnet.clone().freeze();
            }
            model.facing = model.facing.clone().map(|f| f.freeze());
        }
        self.kept.clear();
        if stage == Stage::Whole && sc.cache_volumes {
            // The rest of what the kept volumes come from.
            model.reduce = model.reduce.clone().no_grad();
            model.deformable = model.deformable.clone().map(|d| d.no_grad());
            model.vit_joints = model.vit_joints.clone().map(|c| c.no_grad());
        }
        let spe = self.steps_per_epoch();
        let done = self.cursor.epoch * spe + self.cursor.step_in_epoch;
        mon.stage(stage, sc.epochs, spe, done);
        while self.cursor.epoch < sc.epochs {
            let out;
            (model, out) = self.run_epoch(model, &sc, &mut optim, mon)?;
            if out.is_some() {
                return Ok((model, out));
            }
            let out = self.end_epoch(&model, &optim, mon)?;
            if out.is_some() {
                return Ok((model, out));
            }
        }
        Ok((model, None))
    }

    /// Adam for a stage, with, on resume, the saved state.
    fn optimizer(&mut self) -> Result<ModuleOptimizer, TrainError> {
        // Clipping is the trainer's own (`scale_gradients`): burn's clips each parameter's gradient
        // apart, not the norm of all of them.
        let optim = crate::adam::adam();
        match self.resume_optim.take() {
            Some(p) => optim
                .load(&p)
                .map_err(|e| TrainError::file(&p, format!("optimizer state: {e}"))),
            None => Ok(optim),
        }
    }

    /// The stage's weight average: resumed from its checkpoint, or started at the current weights.
    fn start_average(
        &mut self,
        model: &MvmpHmr,
        sc: &StageConfig,
    ) -> Result<Option<WeightAverage>, TrainError> {
        let saved = self.resume_average.take();
        if sc.average_decay == 0.0 {
            return Ok(None);
        }
        let done = self.cursor.epoch * self.steps_per_epoch() + self.cursor.step_in_epoch;
        // A stage resumed without a saved average (a config that did not keep one) starts it here.
        let Some(p) = saved else {
            return Ok(Some(WeightAverage::start(model, sc.average_decay, done)));
        };
        let mut weights = model.valid();
        load_weights(&mut weights, &p)?;
        Ok(Some(WeightAverage::start(&weights, sc.average_decay, done)))
    }

    /// The weights to validate and finish with: the average when the stage keeps one (a plain-device
    /// copy, so that the training model's running statistics are left alone), else the model's own.
    fn averaged<'m>(&self, model: &'m MvmpHmr) -> Cow<'m, MvmpHmr> {
        match &self.average {
            Some(a) => Cow::Owned(a.apply(model.valid())),
            None => Cow::Borrowed(model),
        }
    }

    /// The rest of the current epoch. `Some` when a stop was asked for (after a checkpoint).
    fn run_epoch(
        &mut self,
        mut model: MvmpHmr,
        sc: &StageConfig,
        optim: &mut ModuleOptimizer,
        mon: &mut dyn Monitor,
    ) -> Result<(MvmpHmr, Option<Outcome>), TrainError> {
        let Cursor { stage, epoch, .. } = self.cursor;
        // Kept volumes are those of the stage's first draws, so every epoch draws as the first does.
        let draws = if sc.cache_volumes { 0 } else { epoch };
        self.data.set_epoch(epoch_key(stage, draws));
        let order = self.frame_order(stage, epoch);
        let skip = self.cursor.step_in_epoch;
        let chunks: Vec<&[usize]> = order.chunks(self.cfg.batch_size).skip(skip).collect();
        let data = Arc::clone(&self.data);
        // The next batch loads on a thread of its own while a step runs: a sample depends only on the
        // epoch and its index, so the batches are those of loading in turn, and the load (decoding,
        // letterboxing, augmentation) takes a core that the step leaves idle in its serial parts.
        std::thread::scope(|scope| {
            let prefetch = |chunk: &[usize]| {
                let (data, chunk) = (&data, chunk.to_vec());
                scope.spawn(move || load_batch(data, &chunk))
            };
            let mut next = chunks.first().map(|c| prefetch(c));
            for k in 0..chunks.len() {
                let loading = next.take().expect("a batch is loading for every chunk");
                let items = loading.join().expect("the loading thread does not panic")?;
                next = chunks.get(k + 1).map(|c| prefetch(c));
                let rec;
                (model, rec) = self.step(model, sc, optim, (skip + k, chunks[k]), items)?;
                mon.step(&rec);
                if self.stop_requested() {
                    let global = self.cursor.global;
                    let name = format!("step{global:07}-stage{stage}-epoch{:03}-part", epoch + 1);
                    let path = self.save(&model, optim, &name)?;
                    mon.checkpoint(&path);
                    let out = Outcome::Interrupted {
                        checkpoint: path,
                        global_step: global,
                    };
                    return Ok((model, Some(out)));
                }
            }
            Ok((model, None))
        })
    }

    fn stop_requested(&self) -> bool {
        let o = self.opts;
        o.stop.load(Ordering::SeqCst)
            || o.stop_after_steps.is_some_and(|s| self.cursor.global >= s)
            || o.stop_after_time
                .is_some_and(|d| self.started.elapsed() >= d)
    }

    /// What the model computes before the decoder for training frame `frame` of `batch`: kept from the
    /// first time the stage decoded it (`cache_volumes`). The first one kept must leave room for all of
    /// them ([`check_room`]).
    fn kept_upstream(
        &mut self,
        model: &MvmpHmr,
        frame: usize,
        batch: &FrameBatch,
    ) -> Result<Upstream, TrainError> {
        if let Some(up) = self.kept.get(&frame) {
            return Ok(up.clone());
        }
        let grids = batch_grids(&model.config, batch, &self.ad);
        let up = model.upstream(batch.images.clone(), &grids).detach();
        if self.kept.is_empty() {
            check_room(kept_bytes(&up), self.data.total(), &self.plain).map_err(
                |(key, what)| TrainError::Config {
                    path: self.run.root.join("train.toml"),
                    key,
                    what,
                },
            )?;
        }
        self.kept.insert(frame, up.clone());
        Ok(up)
    }

    /// One optimizer step on the loaded frames `items` (batch `bi` of the epoch, the training frames
    /// `frames`), logged to `metrics.jsonl`.
    fn step(
        &mut self,
        model: MvmpHmr,
        sc: &StageConfig,
        optim: &mut ModuleOptimizer,
        (bi, frames): (usize, &[usize]),
        items: Vec<FrameSample>,
    ) -> Result<(MvmpHmr, StepRecord), TrainError> {
        let t0 = Instant::now();
        let mut clock = PhaseClock::new();
        let Cursor { stage, epoch, .. } = self.cursor;
        let batch = self.batcher.batch(items, &self.ad);
        clock.lap("load");
        let kept = match stage == Stage::Whole && sc.cache_volumes {
            true => {
                let up = self.kept_upstream(&model, frames[0], &batch)?;
                clock.lap("volumes");
                Some(up)
            }
            false => None,
        };
        let (cfg, ad) = (self.cfg, &self.ad);
        let stage2_weights = stage2_weights(&cfg.loss, sc);
        let loss_of = |model: &MvmpHmr| match stage {
            Stage::Detection => stage1_loss(model, &batch, &cfg.loss, ad),
            Stage::Whole => {
                let setup = Stage2 {
                    weights: &stage2_weights,
                    queries: cfg.queries,
                    gate: cfg.match_gate,
                };
                let kept = match sc.train_rootnet {
                    true => kept.clone().map(|up| model.rerun_rootnet(up)),
                    false => kept.clone(),
                };
                stage2_loss_with(model, &batch, kept, &setup, ad)
            }
        };
        if cfg.term_gradients && bi == 0 {
            let terms = crate::diagnostics::term_grad_norms(&model, loss_of);
            self.run.log(&json!({
                "kind": "grad_terms", "stage": stage, "epoch": epoch + 1,
                "global_step": self.cursor.global, "terms": terms,
            }))?;
        }
        clock.restart(); // the optional per-term diagnostics are not part of a step's phases
        let loss = loss_of(&model);
        // The terms are read back here, so the forward has run when the clock reads.
        let terms = self.finite_terms(&loss)?;
        clock.lap("forward");
        let grads = loss.total.backward();
        clock.lap("backward");
        let grad_norm = crate::diagnostics::module_grad_norms(&model, &grads);
        clock.lap("grad_norm");
        let spe = self.steps_per_epoch();
        let (at, total) = (epoch * spe + bi, sc.epochs * spe);
        let rates = Rates {
            lr: sc.lr_at(at, total),
            decoder: sc.decoder_lr_at(at, total),
            detection: sc.detection_lr_at(at, total),
        };
        let clip = clip_factor(&grad_norm, sc.grad_clip);
        let model = apply_gradients(model, optim, grads, &rates, clip);
        clock.lap("optimizer");
        if let Some(a) = &mut self.average {
            a.update(&model);
            clock.lap("average");
        }
        self.cursor.global += 1;
        self.cursor.step_in_epoch = bi + 1;
        let rec = StepRecord {
            stage,
            epoch: epoch + 1,
            step: bi + 1,
            steps_per_epoch: spe,
            global_step: self.cursor.global,
            lr: rates.lr,
            decoder_lr: rates.decoder,
            detection_lr: rates.detection,
            seconds: t0.elapsed().as_secs_f64(),
            phases: clock.laps,
            total: terms.iter().map(|t| t.1).sum(),
            terms,
            queries: loss.queries,
            root_peak: loss.root_peak,
            root_at_gt: loss.root_at_gt,
            root_background: loss.root_background,
            grad_norm: grad_norm.iter().map(|(k, v)| (k.to_string(), *v)).collect(),
        };
        self.run.log(&json!(rec))?;
        Ok((model, rec))
    }

    /// Every term's value; a non-finite one stops training, naming the step and the last checkpoint.
    fn finite_terms(&self, loss: &StepLoss) -> Result<Vec<(String, f32)>, TrainError> {
        let mut terms = Vec::new();
        for (name, t) in &loss.terms {
            let v: f32 = t.clone().into_scalar();
            if !v.is_finite() {
                return Err(TrainError::NonFinite {
                    stage: self.cursor.stage,
                    epoch: self.cursor.epoch + 1,
                    step: self.cursor.global + 1,
                    term: name.to_string(),
                    value: v,
                    checkpoint: self.last_checkpoint.clone(),
                });
            }
            terms.push((name.to_string(), v));
        }
        Ok(terms)
    }

    /// Validate, log, redraw the curves and checkpoint at the end of an epoch. `Some` when a stop was
    /// asked for.
    fn end_epoch(
        &mut self,
        model: &MvmpHmr,
        optim: &ModuleOptimizer,
        mon: &mut dyn Monitor,
    ) -> Result<Option<Outcome>, TrainError> {
        self.cursor.epoch += 1;
        self.cursor.step_in_epoch = 0;
        let Cursor {
            stage,
            epoch,
            global,
            ..
        } = self.cursor;
        let metrics = match &self.val_source {
            Some(src) => validate(
                self.averaged(model).as_ref(),
                self.cfg,
                &self.body,
                src,
                stage,
                &self.plain,
            )?,
            None => Vec::new(),
        };
        let val = ValRecord {
            stage,
            epoch,
            metrics,
        };
        let mut line =
            json!({"kind": "val", "stage": stage, "epoch": epoch, "global_step": global});
        for (k, v) in &val.metrics {
            line[k] = json!(v);
        }
        self.run.log(&line)?;
        crate::curves::write_curves(&self.run.metrics_path(), &self.run.root.join("curves.png"))?;
        mon.validation(&val);
        let name = format!("step{global:07}-stage{stage}-epoch{epoch:03}");
        let path = self.save(model, optim, &name)?;
        self.last_checkpoint = path.display().to_string();
        mon.checkpoint(&path);
        if self.opts.stop.load(Ordering::SeqCst) {
            return Ok(Some(Outcome::Interrupted {
                checkpoint: path,
                global_step: global,
            }));
        }
        Ok(None)
    }

    /// Write a checkpoint (weights and optimizer) at the cursor and move the state to it; prune old ones.
    fn save(
        &self,
        model: &MvmpHmr,
        optim: &ModuleOptimizer,
        name: &str,
    ) -> Result<PathBuf, TrainError> {
        let dir = self.run.root.join("checkpoints");
        let weights = dir.join(format!("{name}.bpk"));
        // BatchNorm keeps its newest running statistics in a per-thread slot until the next update or a
        // `valid()`/`train()` call folds them in; saving sees only the folded value. Fold them now so the
        // checkpoint holds the statistics the next step would read (resuming is then exact).
        let _ = model.valid();
        mvmp_io::checkpoint::save(model, &weights)?;
        let opt = dir.join(format!("optim-{name}.bpk"));
        mvmp_io::write_atomic_via(&opt, |tmp| {
            optim
                .save(tmp)
                .map_err(|e| TrainError::file(&opt, e.to_string()))
        })?;
        let average = match self.average {
            Some(_) => {
                let p = dir.join(format!("average-{name}.bpk"));
                mvmp_io::checkpoint::save(self.averaged(model).as_ref(), &p)?;
                Some(p)
            }
            None => None,
        };
        let c = self.cursor;
        self.run.write_state(&RunState {
            format: STATE_FORMAT.into(),
            version: 1,
            stage: c.stage,
            epoch: c.epoch,
            step_in_epoch: c.step_in_epoch,
            global_step: c.global,
            checkpoint: format!("checkpoints/{name}.bpk"),
            optimizer: Some(format!("checkpoints/optim-{name}.bpk")),
            finished: false,
            model_sha256: file_hash(&self.run.model_config_path())?,
            checkpoint_sha256: file_hash(&weights)?,
            optimizer_sha256: file_hash(&opt)?,
            average: average
                .as_ref()
                .map(|_| format!("checkpoints/average-{name}.bpk")),
            average_sha256: match &average {
                Some(p) => file_hash(p)?,
                None => String::new(),
            },
        })?;
        let newest = [opt.as_path(), average.as_deref().unwrap_or(&opt)];
        prune_checkpoints(&dir, &weights, &newest, self.cfg.keep_checkpoints)?;
        Ok(weights)
    }
}

/// Wall time per phase of a step.
struct PhaseClock {
    at: Instant,
    laps: Vec<(&'static str, f64)>,
}

impl PhaseClock {
    fn new() -> Self {
        PhaseClock {
            at: Instant::now(),
            laps: Vec::new(),
        }
    }

    /// Record the time since the last lap (or restart) as `name`.
    fn lap(&mut self, name: &'static str) {
        self.laps.push((name, self.at.elapsed().as_secs_f64()));
        self.at = Instant::now();
    }

    fn restart(&mut self) {
        self.at = Instant::now();
    }
}

/// The factor that brings the global gradient norm (over the modules' norms) down to `clip`; `None`
/// when it is within it or clipping is off (0).
fn clip_factor(norms: &[(&'static str, f32)], clip: f32) -> Option<f32> {
    let global = norms.iter().map(|(_, n)| n * n).sum::<f32>().sqrt();
    (clip > 0.0 && global > clip).then(|| clip / global)
}

/// A step's learning rates: the stage's, and the decoder's and detection's when they have their own.
struct Rates {
    lr: f64,
    decoder: Option<f64>,
    detection: Option<f64>,
}

/// One optimizer step: every gradient scaled by the clipping factor, the modules with rates of their own
/// stepped apart (Adam's state is per parameter).
fn apply_gradients(
    model: MvmpHmr,
    optim: &mut ModuleOptimizer,
    mut grads: Gradients,
    rates: &Rates,
    clip: Option<f32>,
) -> MvmpHmr {
    let mut groups = Vec::new();
    if let Some(r) = rates.decoder {
        groups.push((r, GradientsParams::from_module(&mut grads, &model.decoder)));
    }
    if let Some(r) = rates.detection {
        let detection = detection_grads(&mut grads, &model);
        groups.extend(detection.into_iter().map(|g| (r, g)));
    }
    let mut grads = GradientsParams::from_grads(grads, &model);
    if let Some(factor) = clip {
        scale_gradients(&model, &mut grads, factor);
        for (_, g) in groups.iter_mut() {
            scale_gradients(&model, g, factor);
        }
    }
    let mut model = optim.step(rates.lr, model, grads);
    for (r, g) in groups {
        model = optim.step(r, model, g);
    }
    model
}

/// The gradients of what stage 1 trains (HRNet, the RootNet, the facing head), taken out of `grads`.
fn detection_grads(grads: &mut Gradients, model: &MvmpHmr) -> Vec<GradientsParams> {
    let mut out = vec![
        GradientsParams::from_module(grads, &model.hrnet),
        GradientsParams::from_module(grads, &model.rootnet),
    ];
    if let Some(f) = &model.facing {
        out.push(GradientsParams::from_module(grads, f));
    }
    out
}

/// Multiplies every gradient of `module`'s parameters in `grads` by `factor`.
fn scale_gradients<M: Module>(module: &M, grads: &mut GradientsParams, factor: f32) {
    struct Scale<'a> {
        grads: &'a mut GradientsParams,
        factor: f32,
    }
    impl ModuleVisitor for Scale<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            if let Some(g) = self.grads.remove::<D>(p.id) {
                self.grads.register(p.id, g * self.factor);
            }
        }
    }
    module.visit(&mut Scale { grads, factor });
}

/// Only the newest optimizer state and weight average (`newest`) are kept, as a resume reads no other;
/// model weights: the newest `keep` (never `weights`).
fn prune_checkpoints(
    dir: &Path,
    weights: &Path,
    newest: &[&Path],
    keep: usize,
) -> Result<(), TrainError> {
    let mut models = Vec::new();
    for e in std::fs::read_dir(dir).map_err(|e| TrainError::io(dir, e))? {
        let p = e.map_err(|e| TrainError::io(dir, e))?.path();
        let f = p
            .file_name()
            .and_then(|f| f.to_str())
            .unwrap_or("")
            .to_string();
        let state = f.starts_with("optim-") || f.starts_with("average-");
        if state && !newest.contains(&p.as_path()) {
            std::fs::remove_file(&p).map_err(|e| TrainError::io(&p, e))?;
        } else if f.starts_with("step") && f.ends_with(".bpk") {
            models.push(p);
        }
    }
    models.sort();
    let drop = models.len().saturating_sub(keep);
    for p in &models[..drop] {
        if p != weights {
            std::fs::remove_file(p).map_err(|e| TrainError::io(p, e))?;
        }
    }
    Ok(())
}

/// Stage 2's loss weights: without the detection (unless the RootNet trains), heatmap and facing terms
/// when the stage keeps detection fixed, and without the ViT heatmap term when it keeps the volumes (the head is fixed then and its maps
/// kept: the term would train nothing).
fn stage2_weights(w: &LossWeights, sc: &StageConfig) -> LossWeights {
    let mut out = w.clone();
    if sc.freeze_detection {
        if !sc.train_rootnet {
            out.detection = 0.0;
        }
        out.facing = 0.0;
        out.heatmap_2d_stage2 = 0.0;
    }
    if sc.cache_volumes {
        out.vit_heatmap = 0.0;
    }
    out
}

/// Bytes a kept [`Upstream`] holds.
fn kept_bytes(up: &Upstream) -> u64 {
    let d = &up.detection;
    let tensors = [
        &up.volume,
        &up.joints,
        &d.heatmaps,
        &d.likelihood,
        &d.offset,
    ];
    let optional = [d.facing.as_ref(), up.vit_heatmaps.as_ref()];
    (tensors.into_iter().chain(optional.into_iter().flatten()))
        .map(|t| (t.shape().num_elements() * t.dtype().size()) as u64)
        .sum()
}

/// Whether `frames` kept upstreams of `per_frame` bytes fit in the host's available memory, with half
/// of it left for the steps; devices with memory of their own are not checked. The offending key and
/// why, when they do not.
fn check_room(per_frame: u64, frames: usize, device: &Device) -> Result<(), (String, String)> {
    // burn-ndarray is deprecated, but `--device ndarray` still runs on the host.
    #[allow(deprecated)]
    let host = *device == Device::flex() || *device == Device::ndarray();
    if !host {
        return Ok(());
    }
    let mut sys = sysinfo::System::new();
    sys.refresh_memory();
    let (need, free) = (per_frame * frames as u64, sys.available_memory());
    if free == 0 || need <= free / 2 {
        return Ok(());
    }
    let gib = |b: u64| b as f64 / f64::from(1u32 << 30);
    Err((
        "stage2.cache_volumes".into(),
        format!(
            "true, but keeping {frames} frames at {:.1} MB each takes {:.1} GiB, more than half of the \
             {:.1} GiB of memory available",
            per_frame as f64 / 1e6,
            gib(need),
            gib(free)
        ),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::LinearConfig;

    /// Epochs smaller than the set take successive frames of shuffled passes: every frame once per pass
    /// before any repeats, passes in different orders, an epoch straddling two passes included.
    #[test]
    fn kept_volumes_must_leave_half_the_memory() {
        let d = Device::flex();
        assert!(check_room(0, 1000, &d).is_ok());
        let (key, what) = check_room(1 << 40, 1000, &d).unwrap_err();
        assert_eq!(key, "stage2.cache_volumes");
        assert!(
            what.contains("1000 frames") && what.contains("1099511.6 MB"),
            "{what}"
        );
    }

    #[test]
    fn short_epochs_see_every_frame_once_a_pass() {
        let (n, e) = (10, 4);
        let frames: Vec<usize> = (0..5).flat_map(|g| pass_frames(7, g * e, e, n)).collect();
        assert_eq!(frames.len(), 20);
        for pass in frames.chunks(n) {
            let mut sorted = pass.to_vec();
            sorted.sort();
            assert_eq!(sorted, (0..n).collect::<Vec<_>>());
        }
        assert_ne!(frames[..n], frames[n..]);
        assert_eq!(pass_frames(7, 8, 4, n), frames[8..12]);
        // An epoch longer than the set runs on into the next pass.
        assert_eq!(pass_frames(7, 0, 20, n), frames);
        assert!(pass_frames(7, 0, 3, 0).is_empty());
    }

    /// Clipping scales every gradient by one factor, so that their joint norm is the bound: the ratio
    /// between two layers' gradients stays what it was (burn's own clipping bounds each apart).
    #[test]
    fn clipping_scales_all_gradients_by_one_factor() {
        let d = Device::flex().autodiff();
        let (a, b) = (
            LinearConfig::new(3, 2).init(&d),
            LinearConfig::new(2, 1).init(&d),
        );
        let x = Tensor::<2>::from_data([[1.0, -2.0, 0.5], [0.3, 0.1, -1.0]], &d);
        let loss = b.forward(a.forward(x)).powi_scalar(2).sum() * 100.0;
        let g = loss.backward();
        let norm = |w: &Param<Tensor<2>>, gp: &GradientsParams| -> f32 {
            let t: Tensor<2> = gp.get(w.id).expect("a gradient");
            t.powi_scalar(2).sum().into_scalar::<f32>().sqrt()
        };
        let mut gp = GradientsParams::new();
        for (p, grad) in [
            (&a.weight, a.weight.grad(&g)),
            (&b.weight, b.weight.grad(&g)),
        ] {
            gp.register(p.id, grad.expect("a gradient"));
        }
        let (na, nb) = (norm(&a.weight, &gp), norm(&b.weight, &gp));
        let norms = [("a", na), ("b", nb)];
        let global = (na * na + nb * nb).sqrt();
        assert_eq!(clip_factor(&norms, 0.0), None);
        assert_eq!(clip_factor(&norms, global * 2.0), None);
        let f = clip_factor(&norms, 1.0).expect("above the bound");
        assert!(
            (f - 1.0 / global).abs() < 1e-6 * f,
            "{f} vs {}",
            1.0 / global
        );
        scale_gradients(&a, &mut gp, f);
        scale_gradients(&b, &mut gp, f);
        let (ca, cb) = (norm(&a.weight, &gp), norm(&b.weight, &gp));
        assert!(((ca * ca + cb * cb).sqrt() - 1.0).abs() < 1e-5);
        assert!((ca / cb - na / nb).abs() < 1e-4 * (na / nb));
    }
}
