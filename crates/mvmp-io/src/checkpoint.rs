//! Model checkpoints: a module saved whole in burn-store's burnpack format (mvmp's key names), atomically,
//! and loaded back with a report of what matched; and the check that weights are ones a trained network
//! can hold.
use std::path::Path;

use burn::store::{BurnpackStore, ModuleSnapshot};

use crate::IoError;

/// What loading weights into a module did (a checkpoint, or an import of another format's).
#[derive(Debug, Clone, Default)]
pub struct LoadReport {
    /// mvmp parameters that received a value.
    pub loaded: Vec<String>,
    /// mvmp parameters the file did not provide.
    pub missing: Vec<String>,
    /// File tensors that went nowhere.
    pub unused: Vec<String>,
    /// Tensors that matched a key but could not be applied (shape or dtype), with the reason.
    pub errors: Vec<String>,
}

impl From<burn::store::ApplyResult> for LoadReport {
    fn from(r: burn::store::ApplyResult) -> Self {
        LoadReport {
            loaded: r.applied,
            missing: r.missing.into_iter().map(|(k, _)| k).collect(),
            unused: r.unused,
            errors: r.errors.iter().map(|e| e.to_string()).collect(),
        }
    }
}

/// The first parameter of `module` (its module path) that no trained network holds, and what is wrong
/// with it: a NaN or infinite value (every prediction made with it is NaN), or a batch norm's negative
/// running variance (its square root is NaN).
pub fn first_invalid_weight<M: burn::module::Module>(module: &M) -> Option<(String, &'static str)> {
    #[derive(Default)]
    struct Finder {
        path: Vec<String>,
        found: Option<(String, &'static str)>,
    }
    impl burn::module::ModuleVisitor for Finder {
        fn enter_module(&mut self, name: &str, _container: &str) {
            self.path.push(name.to_string());
        }
        fn exit_module(&mut self, _name: &str, _container: &str) {
            self.path.pop();
        }
        fn visit_float<const D: usize>(
            &mut self,
            p: &burn::module::Param<burn::tensor::Tensor<D>>,
        ) {
            if self.found.is_some() {
                return;
            }
            // Read on the host: one pass over the weights, whatever the backend's own checks do.
            let data = p.val().into_data();
            let variance = self.path.last().is_some_and(|n| n == "running_var");
            let problem = data.iter::<f32>().find_map(|x| {
                if !x.is_finite() {
                    Some("hold a NaN or infinite value")
                } else if variance && x < 0.0 {
                    Some("hold a negative variance")
                } else {
                    None
                }
            });
            if let Some(what) = problem {
                self.found = Some((self.path.join("."), what));
            }
        }
    }
    let mut f = Finder::default();
    module.visit(&mut f);
    f.found
}

/// Refuse weights read from `path` that no trained network holds ([`first_invalid_weight`]).
pub fn check_finite<M: burn::module::Module>(module: &M, path: &Path) -> Result<(), IoError> {
    match first_invalid_weight(module) {
        None => Ok(()),
        Some((at, what)) => Err(IoError::File {
            path: path.into(),
            what: format!("the weights of `{at}` {what}"),
        }),
    }
}

/// Save a module in burn-store's native burnpack format (mvmp key names), atomically.
pub fn save<M: burn::module::Module>(module: &M, path: &Path) -> Result<(), IoError> {
    crate::write_atomic_via(path, |tmp| {
        let mut store = BurnpackStore::from_file(tmp)
            .auto_extension(false)
            .overwrite(true);
        module.save_into(&mut store).map_err(|e| IoError::File {
            path: path.into(),
            what: e.to_string(),
        })
    })
}

/// Load weights written by [`save`].
pub fn load<M: burn::module::Module>(module: &mut M, path: &Path) -> Result<LoadReport, IoError> {
    if !path.exists() {
        return Err(IoError::Io {
            path: path.into(),
            source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        });
    }
    // Partial: the caller decides which missing tensors it can do without (the report lists them).
    let mut store = BurnpackStore::from_file(path)
        .auto_extension(false)
        .allow_partial(true);
    let r = module.load_from(&mut store).map_err(|e| IoError::File {
        path: path.into(),
        what: e.to_string(),
    })?;
    Ok(r.into())
}
