use std::path::PathBuf;

/// Errors of prediction, evaluation and output writing. Each names the file or key involved.
#[derive(Debug, thiserror::Error)]
pub enum InferError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {what}")]
    File { path: PathBuf, what: String },
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
    /// Reading weights (burnpack).
    #[error(transparent)]
    Weights(#[from] mvmp_backbone::import::ImportError),
}

impl InferError {
    pub fn file(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        InferError::File {
            path: path.into(),
            what: what.into(),
        }
    }

    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        InferError::Io {
            path: path.into(),
            source,
        }
    }
}
