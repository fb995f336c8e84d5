//! Multiview fusion for MVMP-HMR: projection of per-view 2D maps into the voxel grid and their fusion,
//! 3D pooling and non-maximum suppression, the RootNet (V2V) and root extraction, and the Gaussian 3D
//! targets of the detection loss.
mod cpu;
pub mod deformable;
mod fused;
pub mod pool;
pub mod project;
pub mod roots;
pub mod v2v;

pub use deformable::{DeformableFusion, DeformableFusionConfig};
pub use fused::{FuseBackend, FusePlan, fused_backward, set_fused_backward};
pub use project::{FusionMode, SamplingGrid, fuse_views, fuse_views_tensor_ops};
pub use roots::{Root, RootRefine, Subvoxel, extract_roots, gaussian_target};
pub use v2v::{RootNet, RootNetConfig, V2VNet, V2VNetConfig, VolumeNorm};
