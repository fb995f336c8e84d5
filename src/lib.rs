//! mvmp: multiview multi-person whole-body human mesh recovery.
//!
//! This facade re-exports the workspace crates so that integration tests and benchmarks at the top level
//! (and users who want one dependency) can reach every layer.
pub use mvmp_backbone as backbone;
pub use mvmp_data as data;
pub use mvmp_decoder as decoder;
pub use mvmp_eval as eval;
pub use mvmp_fusion as fusion;
pub use mvmp_geom as geom;
pub use mvmp_infer as infer;
pub use mvmp_io as io;
pub use mvmp_kernels as kernels;
pub use mvmp_losses as losses;
pub use mvmp_model as model;
pub use mvmp_render as render;
pub use mvmp_smplx as smplx;
pub use mvmp_train as train;
