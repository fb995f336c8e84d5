//! Inference with a trained MVMP-HMR model: the [`Predictor`] (images and cameras in, people in the world
//! out), reading a run directory's model, and what inference writes for a frame (`people.npz`, meshes,
//! overlays, a top-down view).
pub mod error;
pub mod output;
pub mod predictor;
pub mod run_files;

pub use error::InferError;
pub use predictor::{PersonPrediction, Predictor, load_weights};
