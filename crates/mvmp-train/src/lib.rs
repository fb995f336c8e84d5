//! Training, prediction and evaluation runs of MVMP-HMR, and the files inference writes.
pub mod config;
pub mod curves;
pub mod diagnostics;
pub mod error;
pub mod output;
pub mod predict;
pub mod pseudo;
pub mod run;
pub mod step;
pub mod train;

pub use config::{LrSchedule, QueryMode, StageConfig, TrainConfig};
pub use error::TrainError;
pub use predict::{EvalOptions, PersonPrediction, Predictor, evaluate};
pub use run::{RunDir, RunState};
pub use train::{
    Monitor, Outcome, Quiet, StepRecord, TrainOptions, ValRecord, check_validation_source,
    open_training_set, seeded_init, train,
};
