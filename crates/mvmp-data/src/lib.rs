//! Datasets for mvmp: the MVMP-HMR on-disk layout, the synthetic scene generator and renderer,
//! dataset statistics and validation, and loading for training.
pub mod augment;
pub mod cdf_pose;
pub mod check;
pub mod dataset;
pub mod error;
pub mod fixtures;
pub mod h36m;
pub mod layout;
pub mod loader;
pub mod mean;
pub mod panoptic;
pub mod sequence;
pub mod sources;
pub mod stats;
pub mod synth;

pub use error::DataError;
pub use layout::{Annotation, DatasetLayout, Person, PersonView};
