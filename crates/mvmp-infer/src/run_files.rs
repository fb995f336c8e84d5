//! The files of a run directory that inference reads (training writes them; see `mvmp_train::run`):
//! `train.toml` marks the directory as a run, `model.toml` is the resolved model config, and the weights
//! are `model.bpk` once training finished, else those of the checkpoint `state.json` names (its weight
//! average when the stage keeps one: what validation scored).
use std::path::{Path, PathBuf};

use mvmp_model::ModelConfig;

use crate::InferError;

pub const TRAIN_CONFIG: &str = "train.toml";
pub const MODEL_CONFIG: &str = "model.toml";
pub const FINAL_WEIGHTS: &str = "model.bpk";
pub const STATE: &str = "state.json";
/// The `format` field of `state.json`.
pub const STATE_FORMAT: &str = "mvmp-run-state";

/// An error unless `root` holds a run (its `train.toml`).
pub fn check_run_dir(root: &Path) -> Result<(), InferError> {
    if root.join(TRAIN_CONFIG).exists() {
        Ok(())
    } else {
        Err(InferError::file(
            root,
            "not a run directory (no train.toml); runs are made by `mvmp train`",
        ))
    }
}

/// The run's resolved model config.
pub fn model_config(root: &Path) -> Result<ModelConfig, InferError> {
    check_run_dir(root)?;
    Ok(ModelConfig::read(&root.join(MODEL_CONFIG))?)
}

/// The weights of the checkpoint `state.json` names (relative to the run): its weight average when it has
/// one, else the checkpoint itself; `None` if the run has no state yet.
pub fn state_checkpoint(root: &Path) -> Result<Option<String>, InferError> {
    let path = root.join(STATE);
    if !path.exists() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&path).map_err(|e| InferError::io(&path, e))?;
    let v: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| InferError::file(&path, e.to_string()))?;
    let format = v.get("format").and_then(|f| f.as_str());
    let version = v.get("version").and_then(|f| f.as_u64());
    if format != Some(STATE_FORMAT) || version != Some(1) {
        return Err(InferError::file(
            &path,
            format!("format {format:?} version {version:?}: expected {STATE_FORMAT:?} version 1"),
        ));
    }
    let present = |key: &str| v.get(key).filter(|f| !f.is_null());
    let (key, file) = match (present("average"), present("checkpoint")) {
        (Some(a), _) => ("average", a),
        (None, Some(c)) => ("checkpoint", c),
        (None, None) => return Err(InferError::file(&path, "key `checkpoint` is missing")),
    };
    match file.as_str() {
        Some(f) if inside_run(f) => Ok(Some(f.to_string())),
        _ => Err(InferError::file(
            &path,
            format!("key `{key}`: {file} is not a file inside the run directory"),
        )),
    }
}

/// Whether `file` names a file inside the run: a relative path of plain names (no `..`, no root).
fn inside_run(file: &str) -> bool {
    let f = Path::new(file);
    f.components().next().is_some()
        && f.components()
            .all(|c| matches!(c, std::path::Component::Normal(_)))
}

/// The weights to predict with: the final weights, else the newest checkpoint's ([`state_checkpoint`]).
pub fn weights(root: &Path) -> Result<PathBuf, InferError> {
    let fin = root.join(FINAL_WEIGHTS);
    if fin.exists() {
        return Ok(fin);
    }
    match state_checkpoint(root)? {
        Some(c) => Ok(root.join(c)),
        None => Err(InferError::file(
            root,
            "the run has no checkpoint yet (no model.bpk, no state.json)",
        )),
    }
}
