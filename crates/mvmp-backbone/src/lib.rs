//! Per-view backbones of MVMP-HMR: the DINOv2-style ViT (patch 14) that gives the feature maps fused into
//! the voxel volume.
pub mod vit;

pub use vit::{ViT, ViTConfig};
