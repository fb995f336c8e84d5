//! Training MVMP-HMR: configs, run directories, the two-stage training loop, its logs and curves.
//! Inference lives in `mvmp_infer`, the evaluation drivers in `mvmp_eval::drivers`.
pub mod adam;
pub mod average;
pub mod config;
pub mod curves;
pub mod decoder_fit;
pub mod diagnostics;
pub mod error;
pub mod init;
pub mod keypoints;
pub mod pose_fit;
pub mod probe;
pub mod pseudo;
pub mod ridge;
pub mod run;
pub mod step;
pub mod train;
pub mod validation;

pub use config::{LrSchedule, QueryMode, Stage, StageConfig, TrainConfig};
pub use error::TrainError;
pub use run::{RunDir, RunState};
pub use train::{
    Monitor, Outcome, Quiet, StepRecord, TrainOptions, ValRecord, open_training_set, seeded_init,
    train,
};
pub use validation::check_validation_source;
