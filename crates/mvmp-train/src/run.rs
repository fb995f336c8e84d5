//! A run directory: the resolved configs, checkpoints, the state cursor and the metrics log.
//!
//! ```text
//! RUN/
//!   train.toml          the resolved training config (model = "model.toml", data absolute)
//!   model.toml          the resolved model config
//!   state.json          where training stands: stage, epoch, step, the checkpoint to resume from
//!   metrics.jsonl       one JSON object per step ("kind": "step") and per validation ("kind": "val")
//!   checkpoints/        model weights (burnpack) per epoch / interruption, the optimizer state beside
//!   model.bpk           the final weights, written when training finishes
//! ```
//! Every file is written to a temporary name and renamed, so a crash leaves the previous state whole.
use std::io::Write;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::TrainError;
use crate::config::{Stage, TrainConfig};
use mvmp_io::write_atomic;
use mvmp_model::ModelConfig;

pub use mvmp_infer::run_files::STATE_FORMAT;

/// The training cursor: everything before it is in the checkpoint it names.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunState {
    pub format: String,
    pub version: u32,
    /// Stage and epochs completed in it.
    pub stage: Stage,
    pub epoch: usize,
    /// Batches of the next epoch already trained (non-zero after an interruption).
    pub step_in_epoch: usize,
    /// Optimizer steps over the whole run.
    pub global_step: u64,
    /// Model weights, relative to the run directory.
    pub checkpoint: String,
    /// Optimizer state of the current stage, relative to the run directory.
    pub optimizer: Option<String>,
    pub finished: bool,
    /// SHA-256 of the run's `model.toml` when the checkpoint was written: the weights belong to that
    /// model, so a resume refuses another (empty, or absent, in runs of earlier versions).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub model_sha256: String,
    /// SHA-256 of the checkpoint and optimizer files as written: a resume refuses files damaged since
    /// (empty, or absent, in runs of earlier versions).
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub checkpoint_sha256: String,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub optimizer_sha256: String,
    /// The stage's weight average at the checkpoint (`average_decay`), relative to the run directory,
    /// and its SHA-256.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub average: Option<String>,
    #[serde(default, skip_serializing_if = "String::is_empty")]
    pub average_sha256: String,
}

/// An open run directory.
#[derive(Debug, Clone)]
pub struct RunDir {
    pub root: PathBuf,
}

impl RunDir {
    /// Make a new run directory (it must not exist or be empty) holding the resolved configs.
    pub fn create(
        root: &Path,
        cfg: &TrainConfig,
        model: &ModelConfig,
        data: Option<&Path>,
    ) -> Result<RunDir, TrainError> {
        if root.exists() {
            let empty = std::fs::read_dir(root)
                .map_err(|e| TrainError::io(root, e))?
                .next()
                .is_none();
            if !empty {
                return Err(TrainError::file(
                    root,
                    "the run directory exists and is not empty; pass --resume to continue it, or choose a new --out",
                ));
            }
        }
        std::fs::create_dir_all(root.join("checkpoints")).map_err(|e| TrainError::io(root, e))?;
        // Every dataset path absolute, so that the run resumes from any working directory.
        let absolute = |p: &str| -> Result<String, TrainError> {
            let abs = std::path::absolute(p).map_err(|e| TrainError::io(p, e))?;
            Ok(abs.to_string_lossy().into_owned())
        };
        let mut resolved = cfg.clone();
        resolved.model = "model.toml".into();
        if let Some(d) = data {
            resolved.data = Some(d.to_string_lossy().into_owned());
        }
        resolved.data = resolved.data.as_deref().map(absolute).transpose()?;
        for s in resolved
            .sources
            .iter_mut()
            .chain(resolved.validation.as_mut())
        {
            s.root = absolute(&s.root)?;
        }
        let run = RunDir { root: root.into() };
        let text = toml::to_string(&resolved)
            .map_err(|e| TrainError::file(run.root.join("train.toml"), e.to_string()))?;
        write_atomic(&run.root.join("train.toml"), text.as_bytes())?;
        let text = toml::to_string(model)
            .map_err(|e| TrainError::file(run.root.join("model.toml"), e.to_string()))?;
        write_atomic(&run.root.join("model.toml"), text.as_bytes())?;
        Ok(run)
    }

    /// A new run of `cfg` and `model` at `root` that goes on from where `from` stands in stage 1: its
    /// configs, with `from`'s state, the files that state names and the log up to it. Stage 1 of the
    /// two must train alike ([`TrainConfig::same_stage1`], the same model config), and `from` must not
    /// have begun stage 2; then resuming the new run trains as a new run of `cfg` would, without
    /// training stage 1 again (the learning benchmark's loss ablations share the full model's).
    pub fn branch(
        from: &RunDir,
        root: &Path,
        cfg: &TrainConfig,
        model: &ModelConfig,
    ) -> Result<RunDir, TrainError> {
        let (_, from_cfg, from_model) = RunDir::open(&from.root)?;
        if *model != from_model {
            return Err(TrainError::file(
                from.model_config_path(),
                "is not the model of the run to branch (a run goes on from weights of its own model)",
            ));
        }
        let state = from.state()?.filter(|s| s.stage == Stage::Detection);
        let Some(state) = state.filter(|s| !s.finished) else {
            return Err(TrainError::file(
                &from.root,
                "has no stage-1 checkpoint to go on from (it has not started, or is past stage 1)",
            ));
        };
        // A config without a dataset trains on `from`'s.
        let data = from_cfg.data.as_deref().filter(|_| cfg.data.is_none());
        let run = RunDir::create(root, cfg, model, data.map(Path::new))?;
        // Whatever fails from here leaves no directory behind.
        let made = run.take_stage1_of(from, &from_cfg, &state);
        if made.is_err() {
            let _ = std::fs::remove_dir_all(root);
        }
        made.map(|()| run)
    }

    /// This new run's resolved config trains stage 1 as `from_cfg` does: take `from`'s `state`.
    fn take_stage1_of(
        &self,
        from: &RunDir,
        from_cfg: &TrainConfig,
        state: &RunState,
    ) -> Result<(), TrainError> {
        let (_, resolved, _) = RunDir::open(&self.root)?;
        if !resolved.same_stage1(from_cfg) {
            return Err(TrainError::file(
                &self.root,
                format!(
                    "its stage 1 would not train as that of {} (configs differ beyond stage 2)",
                    from.root.display()
                ),
            ));
        }
        self.copy_state_of(from, state)
    }

    /// `state` of `from` and what it names, with `from`'s model config as written (the same config,
    /// so that the state's hash of it holds).
    fn copy_state_of(&self, from: &RunDir, state: &RunState) -> Result<(), TrainError> {
        let src = from.model_config_path();
        std::fs::copy(&src, self.model_config_path()).map_err(|e| TrainError::io(&src, e))?;
        let named = [Some(&state.checkpoint), state.optimizer.as_ref()];
        for file in named.into_iter().chain([state.average.as_ref()]).flatten() {
            let (src, dst) = (from.root.join(file), self.root.join(file));
            if let Some(dir) = dst.parent() {
                std::fs::create_dir_all(dir).map_err(|e| TrainError::io(dir, e))?;
            }
            std::fs::copy(&src, &dst).map_err(|e| TrainError::io(&src, e))?;
        }
        let log = from.metrics_path();
        if log.exists() {
            std::fs::copy(&log, self.metrics_path()).map_err(|e| TrainError::io(&log, e))?;
            self.truncate_log(state.global_step)?;
        }
        self.check_model_unchanged(state)?;
        self.write_state(state)
    }

    /// Open an existing run: its resolved configs.
    pub fn open(root: &Path) -> Result<(RunDir, TrainConfig, ModelConfig), TrainError> {
        mvmp_infer::run_files::check_run_dir(root)?;
        let path = root.join(mvmp_infer::run_files::TRAIN_CONFIG);
        let (cfg, model) = TrainConfig::read(&path)?;
        Ok((RunDir { root: root.into() }, cfg, model))
    }

    pub fn state_path(&self) -> PathBuf {
        self.root.join("state.json")
    }

    pub fn state(&self) -> Result<Option<RunState>, TrainError> {
        let path = self.state_path();
        if !path.exists() {
            return Ok(None);
        }
        let text = std::fs::read_to_string(&path).map_err(|e| TrainError::io(&path, e))?;
        let s: RunState = mvmp_io::parse_json(&text).map_err(|e| TrainError::file(&path, e))?;
        if s.format != STATE_FORMAT || s.version != 1 {
            return Err(TrainError::file(
                &path,
                format!(
                    "format {:?} version {}: expected {STATE_FORMAT:?} version 1",
                    s.format, s.version
                ),
            ));
        }
        for (key, file) in [
            ("checkpoint", Some(&s.checkpoint)),
            ("optimizer", s.optimizer.as_ref()),
            ("average", s.average.as_ref()),
        ] {
            let inside = file.is_some_and(|f| {
                let f = Path::new(f);
                f.components()
                    .all(|c| matches!(c, std::path::Component::Normal(_)))
                    && f.components().next().is_some()
            });
            if file.is_some() && !inside {
                return Err(TrainError::file(
                    &path,
                    format!("key `{key}`: {file:?} is not a file inside the run directory"),
                ));
            }
        }
        Ok(Some(s))
    }

    /// The run's resolved model config.
    pub fn model_config_path(&self) -> PathBuf {
        self.root.join(mvmp_infer::run_files::MODEL_CONFIG)
    }

    /// A resumed state's model is the run's model now.
    pub fn check_model_unchanged(&self, s: &RunState) -> Result<(), TrainError> {
        if s.model_sha256.is_empty() {
            return Ok(());
        }
        let path = self.model_config_path();
        if file_hash(&path)? != s.model_sha256 {
            return Err(TrainError::file(
                &path,
                "changed since the checkpoint state.json names was written (its model_sha256 \
                 differs): the checkpoint's weights belong to the model it had; undo the change, or \
                 start a new run",
            ));
        }
        Ok(())
    }

    /// The checkpoint and optimizer files a state names are the ones it was written with.
    pub fn check_checkpoint_files(&self, s: &RunState) -> Result<(), TrainError> {
        let files = [
            (Some(&s.checkpoint), &s.checkpoint_sha256),
            (s.optimizer.as_ref(), &s.optimizer_sha256),
            (s.average.as_ref(), &s.average_sha256),
        ];
        for (file, sha) in files {
            let Some(file) = file.filter(|_| !sha.is_empty()) else {
                continue;
            };
            let path = self.root.join(file);
            if &file_hash(&path)? != sha {
                return Err(TrainError::file(
                    &path,
                    "differs from the file state.json names (its SHA-256 has changed since it was \
                     written): the checkpoint is damaged; resume from a copy, or start a new run",
                ));
            }
        }
        Ok(())
    }

    pub fn write_state(&self, s: &RunState) -> Result<(), TrainError> {
        let text = serde_json::to_string_pretty(s).expect("state serialises");
        write_atomic(&self.state_path(), text.as_bytes())?;
        Ok(())
    }

    /// The weights to predict with: the final weights, else the newest checkpoint.
    pub fn weights(&self) -> Result<PathBuf, TrainError> {
        Ok(mvmp_infer::run_files::weights(&self.root)?)
    }

    pub fn metrics_path(&self) -> PathBuf {
        self.root.join("metrics.jsonl")
    }

    /// Append one line to the metrics log.
    pub fn log(&self, value: &serde_json::Value) -> Result<(), TrainError> {
        let path = self.metrics_path();
        let mut f = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&path)
            .map_err(|e| TrainError::io(&path, e))?;
        // One write per line: a kill mid-step then leaves whole lines, or at worst one torn last line that
        // `truncate_log` drops.
        let line = format!("{value}\n");
        f.write_all(line.as_bytes())
            .map_err(|e| TrainError::io(&path, e))
    }

    /// Remove temporary files a kill left in `checkpoints/` (a checkpoint or optimizer state being written);
    /// the checkpoint the state names was complete before it was named.
    pub fn remove_stale_temporaries(&self) -> Result<(), TrainError> {
        // Checkpoints hold no dot-files of their own; the run's root holds the temporaries of the
        // state, the log's rewrite, the curves and the model file, beside files a person may keep.
        let ours = |name: &str| name.starts_with(".tmp") || name.starts_with(".mvmp-partial-");
        self.remove_dot_files(&self.root.join("checkpoints"), |_| true)?;
        self.remove_dot_files(&self.root, ours)
    }

    fn remove_dot_files(&self, dir: &Path, stale: impl Fn(&str) -> bool) -> Result<(), TrainError> {
        let Ok(entries) = std::fs::read_dir(dir) else {
            return Ok(());
        };
        for e in entries {
            let p = e.map_err(|e| TrainError::io(dir, e))?.path();
            let name = p.file_name().and_then(|f| f.to_str()).unwrap_or("");
            if name.starts_with('.') && stale(name) && p.is_file() {
                tracing::warn!("removing {} (left by an interrupted write)", p.display());
                std::fs::remove_file(&p).map_err(|e| TrainError::io(&p, e))?;
            }
        }
        Ok(())
    }

    /// Drop log lines written after `global_step` (steps a crash lost, trained again on resume).
    pub fn truncate_log(&self, global_step: u64) -> Result<(), TrainError> {
        let path = self.metrics_path();
        if !path.exists() {
            return Ok(());
        }
        let text = std::fs::read_to_string(&path).map_err(|e| TrainError::io(&path, e))?;
        let mut kept = String::new();
        let lines: Vec<&str> = text.lines().collect();
        for (i, line) in lines.iter().enumerate() {
            let v: serde_json::Value = match serde_json::from_str(line) {
                Ok(v) => v,
                // A kill while the last line was written: that step is trained again.
                Err(e) if i + 1 == lines.len() && !text.ends_with('\n') => {
                    tracing::warn!("{}: dropping a torn last line ({e})", path.display());
                    continue;
                }
                Err(e) => {
                    return Err(TrainError::file(&path, format!("line {}: {e}", i + 1)));
                }
            };
            if v.get("global_step").and_then(|s| s.as_u64()).unwrap_or(0) <= global_step {
                kept.push_str(line);
                kept.push('\n');
            }
        }
        write_atomic(&path, kept.as_bytes())?;
        Ok(())
    }

    /// SHA-256 of the resolved configs (train.toml then model.toml).
    pub fn config_hash(&self) -> Result<String, TrainError> {
        let mut h = Sha256::new();
        for f in ["train.toml", "model.toml"] {
            let p = self.root.join(f);
            h.update(std::fs::read(&p).map_err(|e| TrainError::io(&p, e))?);
        }
        Ok(hex(&h.finalize()))
    }
}

/// SHA-256 of a file, hex.
pub fn file_hash(path: &Path) -> Result<String, TrainError> {
    let bytes = std::fs::read(path).map_err(|e| TrainError::io(path, e))?;
    Ok(hex(&Sha256::digest(&bytes)))
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}
