use std::path::PathBuf;

/// Errors of the geometry crate. Every variant names what was wrong and, where there is one, the file.
#[derive(Debug, thiserror::Error)]
pub enum GeomError {
    #[error("camera `{camera}`: {what}")]
    InvalidCamera {
        camera: String,
        /// Which of the camera's values are wrong, for readers that name them by their file's key.
        part: CameraPart,
        what: String,
    },
    #[error("voxel grid: {0}")]
    InvalidGrid(String),
    #[error("letterbox: {0}")]
    InvalidLetterbox(String),
    #[error("{path}: {what}")]
    File { path: PathBuf, what: String },
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("procrustes: {0}")]
    Procrustes(String),
    #[error(transparent)]
    Output(#[from] mvmp_io::IoError),
}

/// The values of a camera an [`GeomError::InvalidCamera`] is about.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum CameraPart {
    /// The intrinsic matrix K.
    Intrinsics,
    /// The rotation R.
    Rotation,
    /// The translation t.
    Translation,
    /// R and t together (where they put the camera).
    Placement,
    /// The lens distortion coefficients.
    Distortion,
    /// The image width and height.
    ImageSize,
}

impl GeomError {
    pub(crate) fn file(path: impl Into<PathBuf>, what: impl Into<String>) -> Self {
        GeomError::File {
            path: path.into(),
            what: what.into(),
        }
    }
}
