//! The assembled MVMP-HMR model and its configuration.
pub mod body;
pub mod config;
pub mod facing;
pub mod ik;
pub mod model;
pub mod summary;

pub use body::BodyLayers;
pub use config::{ModelConfig, ModelConfigError};
pub use model::{Detection, MvmpHmr, MvmpOutput, RigGrids, Upstream, roots_tensor};
