//! `[init]`: pretrained backbone weights loaded into a new run's network before its first step.
use std::path::Path;

use mvmp_io::checkpoint;
use mvmp_model::MvmpHmr;

use crate::TrainError;
use crate::config::InitWeights;

/// One file of `[init]` that was loaded.
#[derive(Debug, Clone, PartialEq)]
pub struct Loaded {
    /// `init.hrnet` or `init.vit`.
    pub key: &'static str,
    pub file: String,
    /// Tensors it gave the module.
    pub tensors: usize,
}

/// Load `[init]`'s files into `model`'s HRNet and ViT. Every tensor of the module must come from the
/// file, with the module's shapes: a file of another variant, joint count or module is refused, naming
/// the key, the file and the first tensor that did not fit.
pub fn load_init(model: &mut MvmpHmr, init: &InitWeights) -> Result<Vec<Loaded>, TrainError> {
    let cfg = &model.config;
    let hrnet = format!(
        "HRNet `{}` with {} heatmap joints",
        cfg.hrnet,
        cfg.heatmap_joints.len()
    );
    let vit = format!("ViT `{}`", cfg.backbone);
    let mut loaded = Vec::new();
    if let Some(file) = &init.hrnet {
        let tensors = load_module(&mut model.hrnet, Path::new(file), "init.hrnet", &hrnet)?;
        loaded.push(Loaded {
            key: "init.hrnet",
            file: file.clone(),
            tensors,
        });
    }
    if let Some(file) = &init.vit {
        let tensors = load_module(&mut model.vit, Path::new(file), "init.vit", &vit)?;
        loaded.push(Loaded {
            key: "init.vit",
            file: file.clone(),
            tensors,
        });
    }
    Ok(loaded)
}

/// Load `path` into `module` (the model's `what`) whole; the number of tensors loaded.
fn load_module<M: burn::module::Module>(
    module: &mut M,
    path: &Path,
    key: &str,
    what: &str,
) -> Result<usize, TrainError> {
    let bad = |w: String| TrainError::file(path, format!("`{key}`: {w}"));
    if !path.is_file() {
        return Err(bad("no such file".into()));
    }
    // burn refuses tensors of other shapes (and files that are not burnpacks) outright; the report holds
    // what else did not fit.
    let r = checkpoint::load(module, path).map_err(|e| match e {
        mvmp_io::IoError::File { what: why, .. } => {
            bad(format!("cannot be loaded into the model's {what} ({why})"))
        }
        e => bad(e.to_string()),
    })?;
    if let Some(e) = r.errors.first() {
        return Err(bad(format!(
            "{} of its tensors do not fit the model's {what} (first: {e})",
            r.errors.len()
        )));
    }
    if let Some(m) = r.missing.first() {
        return Err(bad(format!(
            "{} of the model's {what} tensors are not in the file (first: `{m}`); {} of its tensors went nowhere: are these weights of that module alone?",
            r.missing.len(),
            r.unused.len()
        )));
    }
    checkpoint::check_finite(module, path)?;
    Ok(r.loaded.len())
}
