use std::path::PathBuf;

/// Errors of training. Each names the file, key or step involved.
#[derive(Debug, thiserror::Error)]
pub enum TrainError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {what}")]
    File { path: PathBuf, what: String },
    /// A config that does not parse (TOML syntax, an unknown key, a value of the wrong type): the
    /// parser's message names the line, the column and the key.
    #[error("training config {path}: {what}")]
    Parse { path: PathBuf, what: String },
    #[error("training config {path}: key `{key}`: {what}")]
    Config {
        path: PathBuf,
        key: String,
        what: String,
    },
    #[error(
        "stage {stage}, epoch {epoch}, step {step}: loss term `{term}` is {value}; training stopped, the last good checkpoint is {checkpoint}"
    )]
    NonFinite {
        stage: crate::Stage,
        epoch: usize,
        step: u64,
        term: String,
        value: f32,
        checkpoint: String,
    },
    /// A decoder fit (`decoder_fit::fit`) whose weights left the finite numbers.
    #[error("decoder fit, step {step}: {what}; the learning rate ({lr}) is too high for it")]
    Diverged { step: usize, what: String, lr: f64 },
    #[error(transparent)]
    Data(#[from] mvmp_data::DataError),
    #[error(transparent)]
    Model(#[from] mvmp_model::ModelConfigError),
    #[error(transparent)]
    Smplx(#[from] mvmp_smplx::SmplxError),
    #[error(transparent)]
    Geom(#[from] mvmp_geom::GeomError),
    #[error(transparent)]
    Output(#[from] mvmp_io::IoError),
    #[error(transparent)]
    Infer(#[from] mvmp_infer::InferError),
    /// Reading or writing weights (burnpack).
    #[error(transparent)]
    Weights(#[from] mvmp_backbone::import::ImportError),
}

impl TrainError {
    pub fn file(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        TrainError::File {
            path: path.into(),
            what: what.into(),
        }
    }

    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        TrainError::Io {
            path: path.into(),
            source,
        }
    }
}
