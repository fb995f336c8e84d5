//! Geometry for mvmp: cameras and projection, the letterbox transform, rotations as tensor ops,
//! similarity Procrustes, the voxel grid and the camera-rig file.
//!
//! Conventions (docs/architecture.md, Conventions): world right-handed, z up, metres. Cameras follow OpenCV:
//! `x_cam = R x_world + t`, the camera looks along +z, u right, v down, integer pixel coordinates are pixel
//! centres, distortion is Brown-Conrady `[k1, k2, p1, p2, k3]` with OpenCV's tangential form.

pub mod camera;
pub mod error;
pub mod letterbox;
pub mod procrustes;
pub mod project;
pub mod rig;
pub mod rotation;
pub mod voxel;

pub use camera::Camera;
pub use error::{CameraPart, GeomError};
pub use letterbox::Letterbox;
pub use procrustes::{Similarity, similarity_procrustes};
pub use project::CameraTensors;
pub use rig::Rig;
pub use voxel::VoxelGrid;
