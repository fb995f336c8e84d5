use std::path::PathBuf;

/// Errors of the SMPL-X crate; each names the file and, where there is one, the key.
#[derive(Debug, thiserror::Error)]
pub enum SmplxError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error(
        "{path}: this is a pickled SMPL-X model; mvmp reads the npz layout. Convert it once with Python:\n  \
         python scripts/pkl_to_npz.py {path}\n(or: import pickle, numpy as np; d = pickle.load(open(PATH, 'rb'), \
         encoding='latin1'); np.savez(OUT, **{{k: np.asarray(v) for k, v in d.items() if not callable(v)}}))"
    )]
    Pickle { path: PathBuf },
    #[error("{path}: not a readable npz archive: {what}")]
    NotNpz { path: PathBuf, what: String },
    #[error("{path}: key `{key}` is missing")]
    MissingKey { path: PathBuf, key: String },
    #[error("{path}: key `{key}` has shape {actual:?}, expected {expected}")]
    Shape {
        path: PathBuf,
        key: String,
        expected: String,
        actual: Vec<usize>,
    },
    #[error("{path}: key `{key}` has dtype {dtype}, expected {expected}")]
    Dtype {
        path: PathBuf,
        key: String,
        dtype: String,
        expected: &'static str,
    },
    #[error("{path}: key `{key}`: {what}")]
    Value {
        path: PathBuf,
        key: String,
        what: String,
    },
    #[error("{path}: {what}")]
    File { path: PathBuf, what: String },
    #[error("parameters: {0}")]
    Params(String),
    #[error(transparent)]
    Geom(#[from] mvmp_geom::GeomError),
    #[error(transparent)]
    Output(#[from] mvmp_io::IoError),
}
