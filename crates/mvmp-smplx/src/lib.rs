//! SMPL-X for mvmp: body-model files, the batched differentiable layer, the stand-in model and mesh export.
pub mod error;
pub mod export;
mod fused;
pub mod joint_sets;
pub mod layer;
pub mod model;
pub mod names;
mod op;
pub mod params;
pub mod people;
pub mod standin;

pub use error::SmplxError;
pub use layer::{SmplxLayer, SmplxOutput, Translation, regressed_to_full_pose};
pub use model::BodyModel;
pub use op::{LbsBackend, LbsPlan, fused_backward, set_fused_backward};
pub use params::{ParamTensors, SmplxParams};
pub use standin::standin_model;
