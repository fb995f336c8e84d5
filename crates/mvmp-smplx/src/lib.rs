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

/// Whether `reference` can name a body model: `standin:SEED` with a whole-number seed, or a non-empty
/// path (whether the file exists is for the loader to say). The error says what is wrong with it.
pub fn check_reference(reference: &str) -> Result<(), String> {
    match reference.strip_prefix("standin:") {
        Some(seed) if seed.parse::<u64>().is_err() => Err(format!(
            "{reference:?}: expected `standin:SEED` with a whole-number seed, or a path"
        )),
        None if reference.trim().is_empty() => {
            Err("\"\": expected `standin:SEED` or the path of an SMPL-X .npz".into())
        }
        _ => Ok(()),
    }
}
