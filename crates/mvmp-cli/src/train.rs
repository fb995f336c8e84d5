//! `mvmp train`: run or resume a training run with a progress bar; Ctrl-C checkpoints and stops.
use std::path::{Path, PathBuf};

use anyhow::{Context, Result};
use burn::tensor::Device;
use indicatif::ProgressBar;

use mvmp_train::{
    Monitor, Outcome, RunDir, Stage, StepRecord, TrainConfig, TrainOptions, ValRecord,
};

/// A progress bar per stage with ETA and the live loss terms; validations and checkpoints as lines.
pub struct BarMonitor {
    bar: Option<ProgressBar>,
    pub quiet: bool,
}

impl BarMonitor {
    pub fn new(quiet: bool) -> Self {
        BarMonitor { bar: None, quiet }
    }

    fn line(&self, s: String) {
        // A hidden bar (no terminal) drops println; print plainly then.
        match &self.bar {
            Some(b) if !b.is_hidden() => b.println(s),
            _ => eprintln!("{s}"),
        }
    }
}

impl Monitor for BarMonitor {
    fn stage(&mut self, stage: Stage, epochs: usize, steps_per_epoch: usize, done: usize) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
        let what = stage.trains();
        eprintln!("stage {stage} ({what}): {epochs} epochs of {steps_per_epoch} steps");
        let total = (epochs * steps_per_epoch) as u64;
        let bar = crate::progress::bar(total, &format!("stage {stage}"), self.quiet);
        bar.set_position(done as u64);
        self.bar = Some(bar);
    }

    fn step(&mut self, s: &StepRecord) {
        if let Some(b) = &self.bar {
            let terms: Vec<String> = s.terms.iter().map(|(k, v)| format!("{k} {v:.4}")).collect();
            b.set_message(format!(
                "epoch {} loss {:.4} ({}) {:.2} s/step",
                s.epoch,
                s.total,
                terms.join(", "),
                s.seconds
            ));
            b.inc(1);
        }
    }

    fn validation(&mut self, v: &ValRecord) {
        let m: Vec<String> = v
            .metrics
            .iter()
            .map(|(k, x)| format!("{k} {x:.3}"))
            .collect();
        self.line(format!(
            "stage {} epoch {} validation: {}",
            v.stage,
            v.epoch,
            m.join(", ")
        ));
    }

    fn checkpoint(&mut self, path: &Path) {
        if !self.quiet {
            self.line(format!("checkpoint {}", path.display()));
        }
    }

    fn pose_fit(&mut self, f: &mvmp_train::pose_fit::PoseFit) {
        let what = match f.applied {
            true => "set",
            false => "kept the trained read",
        };
        self.line(format!(
            "pose read fitted on {} frames ({} people): body rotations on the last fifth {:.2} deg as trained, {:.2} deg fitted, {:.2} deg at the mean; {what}",
            f.frames, f.people, f.held_back_deg, f.held_back_fitted_deg, f.held_back_mean_deg
        ));
    }
}

impl Drop for BarMonitor {
    fn drop(&mut self) {
        if let Some(b) = self.bar.take() {
            b.finish_and_clear();
        }
    }
}

pub struct TrainArgs<'a> {
    pub config: Option<&'a Path>,
    pub data: Option<&'a Path>,
    pub out: Option<&'a Path>,
    pub resume: Option<&'a Path>,
    /// A new run (`config`) that goes on from this run's stage-1 checkpoint (`RunDir::branch`).
    pub from_stage1: Option<&'a Path>,
    pub stop_after_steps: Option<u64>,
    /// Stop with a checkpoint once this call has trained this many minutes.
    pub stop_after_minutes: Option<f64>,
    /// Say how to continue a stopped run (the demo removes its run instead).
    pub resumable: bool,
}

/// Start or resume a run; returns its directory.
/// A new run that failed before its first checkpoint has nothing to resume: remove its directory, so that
/// a failed command leaves nothing half-done, and say so beside the error.
fn discard_unstarted(run: &RunDir, fresh: bool, err: anyhow::Error) -> anyhow::Error {
    if !fresh || !matches!(run.state(), Ok(None)) {
        return err;
    }
    match std::fs::remove_dir_all(&run.root) {
        Ok(()) => anyhow::anyhow!(
            "{} (no checkpoint was written: the run directory {} was removed)",
            crate::report::message(&err),
            run.root.display()
        ),
        Err(e) => anyhow::anyhow!(
            "{} (no checkpoint was written; removing the run directory {} failed too: {e})",
            crate::report::message(&err),
            run.root.display()
        ),
    }
}

pub fn train(args: TrainArgs, device: &Device, monitor: &mut BarMonitor) -> Result<PathBuf> {
    let (run, cfg, model) = match (args.resume, args.config) {
        (Some(dir), None) => {
            let (run, cfg, model) = RunDir::open(dir)?;
            if args.data.is_some() {
                anyhow::bail!(
                    "--data cannot change the dataset of a resumed run ({} trains on {})",
                    dir.display(),
                    cfg.data.as_deref().unwrap_or("?")
                );
            }
            eprintln!("resuming {}", dir.display());
            (run, cfg, model)
        }
        (None, Some(config)) => {
            let (mut cfg, model) = TrainConfig::read(config)?;
            if let Some(d) = args.data {
                cfg.data = Some(d.to_string_lossy().into_owned());
            }
            // A run going on from another's stage 1 trains on its dataset unless told otherwise.
            if let (Some(from), None) = (args.from_stage1, &cfg.data) {
                let (_, from_cfg, _) = RunDir::open(from)
                    .with_context(|| format!("--from-stage1 {}", from.display()))?;
                cfg.data = from_cfg.data;
            }
            if cfg.data.is_none() && cfg.sources.is_empty() {
                anyhow::bail!(
                    "training config {}: no training data: set `data` or add [[sources]], or pass --data DIR",
                    config.display()
                );
            }
            // Open every source now (their files, splits and cameras), before a run directory is made.
            let set = mvmp_train::open_training_set(&cfg, &model, config)?;
            let counts: Vec<String> = cfg
                .training_sources()
                .iter()
                .zip(&set.parts)
                .map(|(s, p)| format!("{} {} ({} frames)", s.format.name(), s.root, p.len()))
                .collect();
            eprintln!("training on {}", counts.join(", "));
            mvmp_train::check_validation_source(&cfg)?;
            for (key, file) in cfg.init.files() {
                if !Path::new(file).is_file() {
                    anyhow::bail!(
                        "training config {}: key `{key}`: {file}: no such file",
                        config.display()
                    );
                }
                eprintln!("starting from pretrained weights: {file} ({key})");
            }
            let out = match args.out {
                Some(o) => o.to_path_buf(),
                None => {
                    let stem = config.file_stem().and_then(|s| s.to_str()).unwrap_or("run");
                    PathBuf::from("out/runs").join(stem)
                }
            };
            let run = match args.from_stage1 {
                Some(from) => {
                    // Quitting while the copy is made removes the new directory (it has no state yet).
                    if !out.exists() {
                        crate::interrupt::new_run(&out);
                    }
                    let from = RunDir { root: from.into() };
                    let run = RunDir::branch(&from, &out, &cfg, &model)
                        .with_context(|| format!("--from-stage1 {}", from.root.display()))?;
                    let s = run.state()?.map_or(0, |s| s.global_step);
                    eprintln!(
                        "going on from step {s} of {} (stage 1)",
                        from.root.display()
                    );
                    run
                }
                None => RunDir::create(&out, &cfg, &model, None)?,
            };
            eprintln!("run directory {}", out.display());
            let (run2, cfg, model) =
                RunDir::open(&run.root).map_err(|e| discard_unstarted(&run, true, e.into()))?;
            crate::interrupt::new_run(&run.root);
            (run2, cfg, model)
        }
        (Some(_), Some(_)) => {
            anyhow::bail!("pass either --config (a new run) or --resume RUN_DIR, not both")
        }
        (None, None) => anyhow::bail!("pass --config FILE for a new run or --resume RUN_DIR"),
    };
    let opts = TrainOptions {
        device: device.clone(),
        stop: crate::interrupt::training_started(),
        stop_after_steps: args.stop_after_steps,
        stop_after_time: args
            .stop_after_minutes
            .map(|m| std::time::Duration::from_secs_f64(m * 60.0)),
    };
    let outcome = mvmp_train::train(&run, &cfg, &model, &opts, monitor);
    crate::interrupt::training_ended();
    let outcome = match outcome {
        Ok(o) => o,
        Err(e) => return Err(discard_unstarted(&run, args.config.is_some(), e.into())),
    };
    match outcome {
        Outcome::Finished => {
            eprintln!("finished: {}", run.root.join("model.bpk").display());
        }
        Outcome::Interrupted {
            checkpoint,
            global_step,
        } => {
            let hint = format!(
                "; continue with `mvmp train --resume {}`",
                run.root.display()
            );
            eprintln!(
                "stopped after step {global_step}; checkpoint {}{}",
                checkpoint.display(),
                if args.resumable { hint.as_str() } else { "" }
            );
        }
    }
    Ok(run.root)
}
