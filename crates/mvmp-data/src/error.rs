use std::path::PathBuf;

/// Errors of the data crate; each names the file and, where there is one, the key and the value.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {what}")]
    File { path: PathBuf, what: String },
    #[error("config {path}: key `{key}`: {what}")]
    Config {
        path: PathBuf,
        key: String,
        what: String,
    },
    #[error(transparent)]
    Geom(#[from] mvmp_geom::GeomError),
    #[error(transparent)]
    Output(#[from] mvmp_io::IoError),
    #[error(transparent)]
    Smplx(#[from] mvmp_smplx::SmplxError),
}

impl DataError {
    pub fn file(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        DataError::File {
            path: path.into(),
            what: what.into(),
        }
    }

    pub fn io(path: impl Into<PathBuf>, source: std::io::Error) -> Self {
        DataError::Io {
            path: path.into(),
            source,
        }
    }
}

/// A camera's error as a file reader words it: an invalid value is named by the key the file keeps it
/// under (`key` of the part: Human3.6M's intrinsics are `calibration_matrix`, Panoptic's distortion
/// `distCoef`), so that a user finds it in the file.
pub(crate) fn camera_error(
    err: mvmp_geom::GeomError,
    key: impl Fn(mvmp_geom::CameraPart) -> String,
) -> String {
    match &err {
        mvmp_geom::GeomError::InvalidCamera { part, .. } => format!("key `{}`: {err}", key(*part)),
        _ => err.to_string(),
    }
}
