//! The training loop: stage 1 (HRNet + RootNet), then stage 2 (the whole model), with checkpoints every
//! epoch and on interruption, validation every epoch, exact resume and a stop on non-finite losses.
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use burn::data::dataloader::batcher::Batcher;
use burn::module::Module;
use burn::optim::{AdamConfig, GradientsParams, ModuleOptimizer};
use burn::tensor::Device;
use rand::SeedableRng;
use rand::seq::SliceRandom;
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde_json::json;

use mvmp_data::loader::{FrameBatcher, FrameDataset, Split, ViewChoice};
use mvmp_data::sources::{
    JointFrameDataset, SourceDataset, SourceFormat, SourceSpec, TrainingSet, covered_slots,
};
use mvmp_eval::{Evaluator, PersonPose};
use mvmp_model::{ModelConfig, MvmpHmr};
use mvmp_smplx::SmplxLayer;

use crate::TrainError;
use crate::config::TrainConfig;
use crate::run::{RunDir, RunState, STATE_FORMAT};
use crate::step::{stage1_loss, stage2_loss};
use mvmp_eval::drivers::{EvalOptions, PseudoGt, evaluate, ground_truth};
use mvmp_infer::{Predictor, load_weights};

/// One optimizer step, as logged.
#[derive(Debug, Clone)]
pub struct StepRecord {
    pub stage: u32,
    /// 1-based epoch of the stage and step within it.
    pub epoch: usize,
    pub step: usize,
    pub steps_per_epoch: usize,
    pub global_step: u64,
    pub lr: f64,
    pub seconds: f64,
    /// Weighted terms and their total.
    pub terms: Vec<(String, f32)>,
    pub total: f32,
}

/// A validation pass at the end of an epoch.
#[derive(Debug, Clone)]
pub struct ValRecord {
    pub stage: u32,
    pub epoch: usize,
    /// `root_mm`/`root_recall` in stage 1; `mpjpe_mm`, `pve_mm`, `pa_pve_mm`, `recall_500` in stage 2.
    pub metrics: Vec<(String, f64)>,
}

/// What training reports as it goes (the CLI draws a progress bar from it).
pub trait Monitor {
    /// A stage starts (or resumes with `done` of its `epochs * steps_per_epoch` steps behind it).
    fn stage(&mut self, _stage: u32, _epochs: usize, _steps_per_epoch: usize, _done: usize) {}
    fn step(&mut self, _s: &StepRecord) {}
    fn validation(&mut self, _v: &ValRecord) {}
    fn checkpoint(&mut self, _path: &Path) {}
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

/// Stage-and-epoch key of the data order and view draws.
fn epoch_key(stage: u32, epoch: usize) -> u64 {
    ((stage as u64) << 32) | epoch as u64
}

/// The order of the training frames in an epoch (depends on the seed, stage and epoch only).
pub fn epoch_order(seed: u64, stage: u32, epoch: usize, n: usize) -> Vec<usize> {
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
    let primary = model_cfg.primary_joint.joint();
    // `data`, when set, is the first spec; errors name a source by its index in `[[sources]]`.
    let key = |i: usize, field: &str| match (i + cfg.sources.len()).checked_sub(specs.len()) {
        Some(k) => format!("sources[{k}].{field}"),
        None => "data".to_string(),
    };
    let mut parts = Vec::with_capacity(specs.len());
    for (i, spec) in specs.iter().enumerate() {
        let set = spec.format.joint_set();
        if !covered_slots(set)[primary] {
            return Err(TrainError::Config {
                path: config.into(),
                key: key(i, "format"),
                what: format!(
                    "{}: its joints ({}) do not include the model's primary joint {:?}",
                    spec.format.name(),
                    set.name(),
                    model_cfg.primary_joint
                ),
            });
        }
        if spec.format == SourceFormat::Mvmp {
            let layout = mvmp_data::DatasetLayout::open(Path::new(&spec.root))?;
            let cameras = layout.scenes.iter().map(|s| s.rig.len()).min().unwrap_or(0);
            if cfg.train_views > cameras {
                return Err(TrainError::Config {
                    path: config.into(),
                    key: "train_views".into(),
                    what: format!(
                        "{}: the scenes of {} ({}) have {cameras} cameras",
                        cfg.train_views,
                        key(i, "root"),
                        spec.root
                    ),
                });
            }
        }
        let part = spec.open_training(
            ViewChoice::Random {
                count: cfg.train_views,
                seed: cfg.seed,
            },
            model_cfg.image_size,
        )?;
        parts.push(match (&spec.pseudo_gt, part) {
            (Some(dir), SourceDataset::Joints(d)) => {
                let dir = PathBuf::from(dir);
                if !dir.is_dir() {
                    return Err(TrainError::Config {
                        path: config.into(),
                        key: key(i, "pseudo_gt"),
                        what: format!("{}: not a directory", dir.display()),
                    });
                }
                // The body model resolves as the run resolves it (relative to the run directory).
                let base = config.parent().unwrap_or(Path::new("."));
                let body = mvmp_data::layout::load_body_model(&model_cfg.body_model, base)?;
                let layer = SmplxLayer::new(&body, &Device::flex());
                SourceDataset::Joints(d.with_meshes(Arc::new(crate::pseudo::PseudoGtMeshes(
                    PseudoGt {
                        dir,
                        layer,
                        gate: cfg.match_gate,
                    },
                ))))
            }
            (_, part) => part,
        });
    }
    let set = TrainingSet::with_repeats(parts, specs.iter().map(SourceSpec::repeat).collect());
    if set.total() == 0 {
        return Err(TrainError::file(
            config,
            "the training sources have no frames in their train splits",
        ));
    }
    Ok(set)
}

/// Open the validation source the way validation will (its split, the first `test_views` cameras), so
/// that a wrong path or split stops the run before training rather than after the first epoch.
pub fn check_validation_source(cfg: &TrainConfig) -> Result<(), TrainError> {
    let Some(src) = cfg.validation_source() else {
        return Ok(());
    };
    if src.format == SourceFormat::Mvmp {
        let split: Split = src
            .split
            .as_deref()
            .unwrap_or("test")
            .parse()
            .map_err(|e: String| TrainError::file(&src.root, e))?;
        let layout = mvmp_data::DatasetLayout::open(Path::new(&src.root))?;
        let cameras = layout.scenes.iter().map(|s| s.rig.len()).min().unwrap_or(0);
        if cfg.test_views > cameras {
            return Err(TrainError::file(
                &src.root,
                format!(
                    "test_views = {}: the validation scenes have {cameras} cameras",
                    cfg.test_views
                ),
            ));
        }
        FrameDataset::open(
            Path::new(&src.root),
            split,
            ViewChoice::Fixed((0..cfg.test_views).collect()),
            14,
        )?;
        return Ok(());
    }
    let seqs = validation_sequences(cfg, &src)?;
    if seqs.iter().all(|s| s.is_empty()) {
        return Err(TrainError::file(
            &src.root,
            "the validation split has no frames",
        ));
    }
    Ok(())
}

/// The sequences of a joint-annotated validation source, with the first `test_views` cameras.
fn validation_sequences(
    cfg: &TrainConfig,
    source: &SourceSpec,
) -> Result<Vec<Box<dyn mvmp_data::sources::JointAnnotated>>, TrainError> {
    let cams = source.camera_names();
    if cfg.test_views == 0 || cfg.test_views > cams.len() {
        return Err(TrainError::file(
            &source.root,
            format!(
                "test_views = {} but the validation source has {} cameras",
                cfg.test_views,
                cams.len()
            ),
        ));
    }
    let spec = SourceSpec {
        cameras: Some(cams[..cfg.test_views].to_vec()),
        ..source.clone()
    };
    Ok(spec.open_sequences("test")?)
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

/// Train (or resume) the run in `run`.
pub fn train(
    run: &RunDir,
    cfg: &TrainConfig,
    model_cfg: &ModelConfig,
    opts: &TrainOptions,
    mon: &mut dyn Monitor,
) -> Result<Outcome, TrainError> {
    let started = Instant::now();
    let plain = opts.device.clone();
    let ad = plain.clone().autodiff();
    let config_path = run.root.join("train.toml");
    let val_source = cfg.validation_source();
    let state = run.state()?;
    if state.as_ref().is_some_and(|s| s.finished) {
        return Ok(Outcome::Finished);
    }
    let mut model = seeded_init(model_cfg, &ad, cfg.seed);
    let (mut stage, mut epoch, mut step_in_epoch, mut global) = (1u32, 0usize, 0usize, 0u64);
    let mut last_checkpoint = String::from("none (no checkpoint was written yet)");
    let mut resume_optim: Option<PathBuf> = None;
    if let Some(s) = &state {
        load_weights(&mut model, &run.root.join(&s.checkpoint))?;
        model = model.train();
        (stage, epoch, step_in_epoch, global) = (s.stage, s.epoch, s.step_in_epoch, s.global_step);
        last_checkpoint = run.root.join(&s.checkpoint).display().to_string();
        resume_optim = s.optimizer.as_ref().map(|o| run.root.join(o));
    }
    run.truncate_log(global)?;
    run.remove_stale_temporaries()?;

    let body = mvmp_data::layout::load_body_model(&model_cfg.body_model, &run.root)?;
    let layer = SmplxLayer::new(&body, &ad);
    let val_layer = SmplxLayer::new(&body, &plain);
    let ds = open_training_set(cfg, model_cfg, &config_path)?;
    check_validation_source(cfg)?;
    // Ground-truth meshes are posed with the body model of the (first) MVMP-HMR source; joint-annotated
    // people have none.
    let gt_body = match ds.parts.iter().find_map(|p| match p {
        SourceDataset::Mvmp(d) => Some(d),
        SourceDataset::Joints(_) => None,
    }) {
        Some(d) => d.layout().body_model()?,
        None => body.clone(),
    };
    let batcher = FrameBatcher::with_vertices(gt_body);
    let n = ds.total();
    let steps_per_epoch = n.div_ceil(cfg.batch_size);

    while stage <= 2 {
        let sc = cfg.stage(stage).clone();
        if epoch >= sc.epochs {
            stage += 1;
            (epoch, step_in_epoch) = (0, 0);
            resume_optim = None;
            continue;
        }
        let mut adam = AdamConfig::new();
        if sc.grad_clip > 0.0 {
            adam = adam.with_grad_clipping(Some(
                burn::grad_clipping::GradientClippingConfig::Norm(sc.grad_clip),
            ));
        }
        let mut optim: ModuleOptimizer = adam.init();
        if let Some(p) = resume_optim.take() {
            optim = optim
                .load(&p)
                .map_err(|e| TrainError::file(&p, format!("optimizer state: {e}")))?;
        }
        if stage == 2 && sc.freeze_backbone {
            model.vit = model.vit.clone().no_grad();
        }
        mon.stage(
            stage,
            sc.epochs,
            steps_per_epoch,
            epoch * steps_per_epoch + step_in_epoch,
        );
        while epoch < sc.epochs {
            ds.set_epoch(epoch_key(stage, epoch));
            let order = epoch_order(cfg.seed, stage, epoch, n);
            for (bi, chunk) in order.chunks(cfg.batch_size).enumerate().skip(step_in_epoch) {
                let t0 = Instant::now();
                let items = chunk
                    .par_iter()
                    .map(|&i| ds.load(i))
                    .collect::<Result<Vec<_>, _>>()?;
                let batch = batcher.batch(items, &ad);
                let loss_of = |model: &MvmpHmr| {
                    if stage == 1 {
                        stage1_loss(model, &batch, model_cfg, &cfg.loss, &ad)
                    } else {
                        stage2_loss(
                            model,
                            &batch,
                            model_cfg,
                            &layer,
                            &cfg.loss,
                            cfg.queries,
                            cfg.match_gate,
                            &ad,
                        )
                    }
                };
                if cfg.term_gradients && bi == 0 {
                    let terms = crate::diagnostics::term_grad_norms(&model, loss_of);
                    run.log(&json!({
                        "kind": "grad_terms", "stage": stage, "epoch": epoch + 1,
                        "global_step": global, "terms": terms,
                    }))?;
                }
                let loss = loss_of(&model);
                let mut terms = Vec::new();
                for (name, t) in &loss.terms {
                    let v: f32 = t.clone().into_scalar();
                    if !v.is_finite() {
                        return Err(TrainError::NonFinite {
                            stage,
                            epoch: epoch + 1,
                            step: global + 1,
                            term: name.to_string(),
                            value: v,
                            checkpoint: last_checkpoint,
                        });
                    }
                    terms.push((name.to_string(), v));
                }
                let total: f32 = terms.iter().map(|t| t.1).sum();
                let grads = loss.total.backward();
                let grad_norms = crate::diagnostics::module_grad_norms(&model, &grads);
                let grads = GradientsParams::from_grads(grads, &model);
                let lr = sc.lr_at(epoch * steps_per_epoch + bi, sc.epochs * steps_per_epoch);
                model = optim.step(lr, model, grads);
                global += 1;
                step_in_epoch = bi + 1;
                let rec = StepRecord {
                    stage,
                    epoch: epoch + 1,
                    step: bi + 1,
                    steps_per_epoch,
                    global_step: global,
                    lr,
                    seconds: t0.elapsed().as_secs_f64(),
                    terms,
                    total,
                };
                let mut line = json!({
                    "kind": "step", "stage": stage, "epoch": rec.epoch, "step": rec.step,
                    "global_step": global, "lr": lr, "seconds": rec.seconds, "total": total,
                    "queries": loss.queries, "root_peak": loss.root_peak, "root_at_gt": loss.root_at_gt,
                    "root_background": loss.root_background,
                });
                for (k, v) in &rec.terms {
                    line[k] = json!(v);
                }
                line["grad_norm"] = grad_norms
                    .iter()
                    .map(|(k, v)| (k.to_string(), json!(v)))
                    .collect();
                run.log(&line)?;
                mon.step(&rec);
                let stop = opts.stop.load(Ordering::SeqCst)
                    || opts.stop_after_steps.is_some_and(|s| global >= s)
                    || opts.stop_after_time.is_some_and(|d| started.elapsed() >= d);
                if stop {
                    let name = format!("step{global:07}-stage{stage}-epoch{:03}-part", epoch + 1);
                    let path = save(
                        run,
                        cfg,
                        &model,
                        &optim,
                        &name,
                        stage,
                        epoch,
                        step_in_epoch,
                        global,
                    )?;
                    mon.checkpoint(&path);
                    return Ok(Outcome::Interrupted {
                        checkpoint: path,
                        global_step: global,
                    });
                }
            }
            epoch += 1;
            step_in_epoch = 0;
            let val = match &val_source {
                Some(src) => validate(
                    &model, model_cfg, cfg, &body, &val_layer, src, stage, &plain,
                )?,
                None => ValRecord {
                    stage,
                    epoch: 0,
                    metrics: Vec::new(),
                },
            };
            let mut line =
                json!({"kind": "val", "stage": stage, "epoch": epoch, "global_step": global});
            for (k, v) in &val.metrics {
                line[k] = json!(v);
            }
            let val = ValRecord { epoch, ..val };
            run.log(&line)?;
            crate::curves::write_curves(&run.metrics_path(), &run.root.join("curves.png"))?;
            mon.validation(&val);
            let name = format!("step{global:07}-stage{stage}-epoch{epoch:03}");
            let path = save(run, cfg, &model, &optim, &name, stage, epoch, 0, global)?;
            last_checkpoint = path.display().to_string();
            mon.checkpoint(&path);
            if opts.stop.load(Ordering::SeqCst) {
                return Ok(Outcome::Interrupted {
                    checkpoint: path,
                    global_step: global,
                });
            }
        }
    }
    let fin = run.root.join("model.bpk");
    mvmp_backbone::import::save_native(&model, &fin)?;
    let mut s = run
        .state()?
        .ok_or_else(|| TrainError::file(run.state_path(), "missing"))?;
    s.finished = true;
    run.write_state(&s)?;
    Ok(Outcome::Finished)
}

/// Write a checkpoint (weights and optimizer) and move the state cursor to it; prune old ones.
#[allow(clippy::too_many_arguments)]
fn save(
    run: &RunDir,
    cfg: &TrainConfig,
    model: &MvmpHmr,
    optim: &ModuleOptimizer,
    name: &str,
    stage: u32,
    epoch: usize,
    step_in_epoch: usize,
    global: u64,
) -> Result<PathBuf, TrainError> {
    let dir = run.root.join("checkpoints");
    let weights = dir.join(format!("{name}.bpk"));
    // BatchNorm keeps its newest running statistics in a per-thread slot until the next update or a
    // `valid()`/`train()` call folds them in; saving sees only the folded value. Fold them now so the
    // checkpoint holds the statistics the next step would read (resuming is then exact).
    let _ = model.valid();
    mvmp_backbone::import::save_native(model, &weights)?;
    let opt = dir.join(format!("optim-{name}.bpk"));
    let tmp = dir.join(format!(".optim-{name}.tmp"));
    optim
        .save(&tmp)
        .map_err(|e| TrainError::file(&opt, e.to_string()))?;
    std::fs::rename(&tmp, &opt).map_err(|e| TrainError::io(&opt, e))?;
    run.write_state(&RunState {
        format: STATE_FORMAT.into(),
        version: 1,
        stage,
        epoch,
        step_in_epoch,
        global_step: global,
        checkpoint: format!("checkpoints/{name}.bpk"),
        optimizer: Some(format!("checkpoints/optim-{name}.bpk")),
        finished: false,
    })?;
    // Only the newest optimizer state is needed; model weights: the newest `keep_checkpoints`.
    let mut models = Vec::new();
    for e in std::fs::read_dir(&dir).map_err(|e| TrainError::io(&dir, e))? {
        let p = e.map_err(|e| TrainError::io(&dir, e))?.path();
        let f = p
            .file_name()
            .and_then(|f| f.to_str())
            .unwrap_or("")
            .to_string();
        if f.starts_with("optim-") && p != opt {
            std::fs::remove_file(&p).map_err(|e| TrainError::io(&p, e))?;
        } else if f.starts_with("step") && f.ends_with(".bpk") {
            models.push(p);
        }
    }
    models.sort();
    let drop = models.len().saturating_sub(cfg.keep_checkpoints);
    for p in &models[..drop] {
        if *p != weights {
            std::fs::remove_file(p).map_err(|e| TrainError::io(p, e))?;
        }
    }
    Ok(weights)
}

/// Validation on the test split: root error and recall in stage 1, the mesh metrics in stage 2.
#[allow(clippy::too_many_arguments)]
fn validate(
    model: &MvmpHmr,
    model_cfg: &ModelConfig,
    cfg: &TrainConfig,
    body: &mvmp_smplx::BodyModel,
    layer: &SmplxLayer,
    source: &SourceSpec,
    stage: u32,
    device: &Device,
) -> Result<ValRecord, TrainError> {
    let pred = Predictor::with_layer(
        model.valid(),
        model_cfg.clone(),
        body.clone(),
        layer.clone(),
        device,
    );
    if source.format != SourceFormat::Mvmp {
        return validate_joints(&pred, cfg, source, stage);
    }
    let data = Path::new(&source.root);
    let split: Split = source
        .split
        .as_deref()
        .unwrap_or("test")
        .parse()
        .map_err(|e: String| TrainError::file(data, e))?;
    let opts = EvalOptions {
        split,
        views: cfg.test_views,
        max_frames: cfg.val_frames,
        gate: cfg.match_gate,
        joints: mvmp_eval::joint_sets::JointSet::Smplx127,
    };
    let metrics = if stage == 1 {
        root_metrics(&pred, data, &opts)?
    } else {
        let m = evaluate(&pred, data, &opts, |_, _, _| Ok(()))?.overall();
        measured(&[
            ("mpjpe_mm", m.mpjpe_mm),
            ("pve_mm", m.pve_mm),
            ("pa_pve_mm", m.pa_pve_mm),
            ("recall_500", m.recall_500),
        ])
    };
    Ok(ValRecord {
        stage,
        epoch: 0,
        metrics,
    })
}

/// The metrics that were computed (a metric is absent when nothing was matched).
fn measured(metrics: &[(&str, Option<f64>)]) -> Vec<(String, f64)> {
    metrics
        .iter()
        .filter_map(|&(k, v)| v.map(|v| (k.to_string(), v)))
        .collect()
}

/// Validation on a joint-annotated dataset: root metrics in stage 1; MPJPE on the dataset's joint set and
/// the recall in stage 2 (no meshes).
fn validate_joints(
    pred: &Predictor,
    cfg: &TrainConfig,
    source: &SourceSpec,
    stage: u32,
) -> Result<ValRecord, TrainError> {
    let seqs = validation_sequences(cfg, source)?;
    let metrics = if stage == 1 {
        let ds = JointFrameDataset::new(
            &source.root,
            seqs,
            ViewChoice::Fixed((0..cfg.test_views).collect()),
            pred.cfg.image_size,
        )?;
        root_metrics_of(
            pred,
            ds.len(),
            |i| ds.load(i),
            cfg.val_frames,
            cfg.match_gate,
        )?
    } else {
        let (ev, _) = mvmp_eval::drivers::evaluate_joint_sequences(
            pred,
            &seqs,
            source.format.joint_set(),
            cfg.val_frames,
            cfg.match_gate,
            None,
            |_, _| {},
        )?;
        let m = ev.overall();
        measured(&[("mpjpe_mm", m.mpjpe_mm), ("recall_500", m.recall_500)])
    };
    Ok(ValRecord {
        stage,
        epoch: 0,
        metrics,
    })
}

/// Root localisation on a split: mean error of matched roots (mm) and the fraction of people found.
pub fn root_metrics(
    pred: &Predictor,
    data: &Path,
    opts: &EvalOptions,
) -> Result<Vec<(String, f64)>, TrainError> {
    let ds = FrameDataset::open(
        data,
        opts.split,
        ViewChoice::Fixed((0..opts.views).collect()),
        pred.cfg.image_size,
    )?;
    root_metrics_of(
        pred,
        ds.frames().len(),
        |i| ds.load(i),
        opts.max_frames,
        opts.gate,
    )
}

/// Root metrics over `len` samples given by `load` (at most `max_frames`; 0 = all).
fn root_metrics_of(
    pred: &Predictor,
    len: usize,
    load: impl Fn(usize) -> Result<mvmp_data::loader::FrameSample, mvmp_data::DataError>,
    max_frames: usize,
    gate: f64,
) -> Result<Vec<(String, f64)>, TrainError> {
    let batcher = FrameBatcher::default();
    let n = match max_frames {
        0 => len,
        m => m.min(len),
    };
    let primary = pred.cfg.primary_joint.joint();
    let mut ev = Evaluator::new(gate);
    for i in 0..n {
        let batch = batcher.batch(vec![load(i)?], &pred.device);
        let roots = pred
            .detect(batch.images.clone(), &batch.cameras, &batch.letterboxes)
            .remove(0);
        let gt: Vec<PersonPose> = ground_truth(&batch)
            .remove(0)
            .into_iter()
            .map(|p| PersonPose {
                joints: vec![p.joints[primary]],
                vertices: None,
                score: 1.0,
                valid: None,
            })
            .collect();
        let det: Vec<PersonPose> = roots
            .iter()
            .map(|r| PersonPose {
                joints: vec![r.position],
                vertices: None,
                score: r.score as f64,
                valid: None,
            })
            .collect();
        ev.add_frame(&batch.names[0].0, &det, &gt);
    }
    let m = ev.overall();
    let found = m.matched as f64 / m.ground_truth.max(1) as f64;
    let mut out = vec![("root_recall".to_string(), found)];
    if let Some(e) = m.mpjpe_mm {
        out.push(("root_mm".into(), e));
    }
    Ok(out)
}
