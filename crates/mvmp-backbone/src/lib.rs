//! Per-view backbones of MVMP-HMR: the DINOv2-style ViT (patch 14) whose feature maps are fused into the
//! voxel volume, and the HRNet whose 2D joint heatmaps feed the RootNet.
pub mod hrnet;
pub mod import;
pub mod variant;
pub mod vit;

pub use hrnet::{HRNet, HRNetConfig};
pub use variant::{HrnetVariant, VitVariant};
pub use vit::{ViT, ViTConfig};
