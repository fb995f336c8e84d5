//! Projection of per-view 2D maps into the voxel grid (docs/architecture.md, Cameras and projection).
//!
//! Every voxel centre is projected into every view with distortion and the letterbox (mvmp-geom), giving
//! network pixels `u'`; a feature map of stride `k` samples at `f = (u' + 0.5) / k - 0.5`. A voxel is seen
//! by a view when it is in front of the camera and its distorted projection lies in the original image.
//! Seen voxels are sampled bilinearly with border padding; fusion averages (or takes the maximum) over the
//! views that see the voxel, and is 0 where none does. The sampling grids ([`SamplingGrid`]) depend only on
//! the rig and the voxel grid, so a caller can build them once per rig and reuse them for every frame.
use std::sync::Arc;

use burn::tensor::ops::{GridSampleOptions, GridSamplePaddingMode, InterpolateMode};
use burn::tensor::{Bool, Device, Tensor, TensorData};

use mvmp_geom::{Camera, CameraTensors, Letterbox, VoxelGrid};

use crate::cpu::HostGrid;
use crate::fused::FusePlan;

/// How views are combined.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum FusionMode {
    /// Mean over the views that see the voxel (the paper's choice).
    Mean,
    /// Maximum over the views that see the voxel (ablation).
    Max,
    /// Learned offsets and weights around each projected point (ablation; [`crate::DeformableFusion`]).
    Deformable,
}

/// Cached sampling positions of every voxel in every view of one rig.
#[derive(Debug, Clone)]
pub struct SamplingGrid {
    /// `[V, 1, P, 2]` grid_sample coordinates (align_corners = false) for maps of size `map_hw`.
    pub grid: Tensor<4>,
    /// `[V, P]` true where the view sees the voxel.
    pub visible: Tensor<2, Bool>,
    /// The voxel grid.
    pub voxels: VoxelGrid,
    /// Size `[h, w]` of the maps the grid samples and their stride in network pixels.
    pub map_hw: [usize; 2],
    pub stride: f64,
    /// The positions on the host for the fused CPU pass (made on the CPU backend without autodiff).
    host: Option<Arc<HostGrid>>,
}

impl SamplingGrid {
    /// Grids for maps of `map_hw` at `stride` network pixels per map pixel.
    pub fn new(
        voxels: &VoxelGrid,
        cameras: &[Camera],
        letterboxes: &[Letterbox],
        stride: f64,
        map_hw: [usize; 2],
        device: &Device,
    ) -> Self {
        let centers: Vec<f32> = voxels
            .centers()
            .iter()
            .flatten()
            .map(|&x| x as f32)
            .collect();
        let p = voxels.num_voxels();
        let v = cameras.len();
        let ct = CameraTensors::new(cameras, Some(letterboxes), device);
        let proj = ct.project(Tensor::from_data(TensorData::new(centers, [p, 3]), device));
        // On flex, with or without autodiff: the fused pass (and under autodiff its backward) reads them.
        let host = if *device == Device::flex() {
            let f32s = |t: Tensor<3>| t.into_data_as::<f32>().try_into_vec::<f32>().ok();
            let uv = f32s(proj.uv.clone());
            let seen = f32s(proj.visible.clone().float().reshape([v, p, 1]));
            uv.zip(seen)
                .map(|(uv, seen)| Arc::new(HostGrid::new(&uv, &seen, v, p, stride, map_hw)))
        } else {
            None
        };
        let [h, w] = map_hw;
        // Normalised coordinates with align_corners = false: g = (2 f + 1) / W - 1, f = (u' + 0.5) / k - 0.5.
        let u = proj.uv.clone().narrow(2, 0, 1);
        let vv = proj.uv.narrow(2, 1, 1);
        let gx = (u + 0.5) * (2.0 / (stride * w as f64)) - 1.0;
        let gy = (vv + 0.5) * (2.0 / (stride * h as f64)) - 1.0;
        let grid = Tensor::cat(vec![gx, gy], 2).reshape([v, 1, p, 2]);
        SamplingGrid {
            grid,
            visible: proj.visible,
            voxels: *voxels,
            map_hw,
            stride,
            host,
        }
    }

    /// Whether [`fuse_views`] can take the fused CPU pass with this grid (on flex).
    pub fn is_fused(&self) -> bool {
        self.host.is_some()
    }

    pub fn num_views(&self) -> usize {
        self.grid.dims()[0]
    }

    /// Number of views that see each voxel, `[P]`.
    pub fn view_count(&self) -> Tensor<1> {
        self.visible
            .clone()
            .float()
            .sum_dim(0)
            .reshape([self.voxels.num_voxels()])
    }
}

/// Fuse per-view maps into volumes.
///
/// `maps`: `[B, V, C, h, w]`; `grids`: one [`SamplingGrid`] per batch item (its rig). Returns
/// `[B, C, X, Y, Z]`.
///
/// On flex this is one fused pass (`cpu.rs`) that writes the volume once, and under autodiff its
/// backward scatters straight to the maps (`fused.rs`); otherwise, and with the fused backward off,
/// [`fuse_views_tensor_ops`]. Both compute the same values and gradients (tested to 1e-5).
pub fn fuse_views(maps: Tensor<5>, grids: &[SamplingGrid], mode: FusionMode) -> Tensor<5> {
    let [b, v, _, h, w] = maps.dims();
    assert_eq!(grids.len(), b, "one sampling grid per batch item");
    let shape = grids[0].voxels.shape;
    for g in grids {
        assert_eq!(g.num_views(), v, "grid views vs map views");
        assert_eq!(g.map_hw, [h, w], "grid map size vs map size");
        // One output tensor: every batch item's grid must have the same shape (the tensor path's
        // `cat` requires the same).
        assert_eq!(
            g.voxels.shape, shape,
            "voxel grid shapes differ within the batch"
        );
    }
    let hosts = grids.iter().map(|g| g.host.clone()).collect();
    match FusePlan::new(&maps.device(), hosts, shape, mode) {
        Some(plan) => crate::fused::fuse(maps, plan),
        None => fuse_views_tensor_ops(maps, grids, mode),
    }
}

/// [`fuse_views`] as tensor ops on any backend, differentiable in the maps. Views are accumulated one at
/// a time, so memory holds one fused volume, one view's samples and the per-voxel view count, never
/// every view's volume at once.
pub fn fuse_views_tensor_ops(
    maps: Tensor<5>,
    grids: &[SamplingGrid],
    mode: FusionMode,
) -> Tensor<5> {
    let [b, v, c, h, w] = maps.dims();
    assert_eq!(grids.len(), b, "one sampling grid per batch item");
    let opts = || {
        GridSampleOptions::new(InterpolateMode::Bilinear)
            .with_padding_mode(GridSamplePaddingMode::Border)
            .with_align_corners(false)
    };
    let mut out = Vec::with_capacity(b);
    for (bi, g) in grids.iter().enumerate() {
        assert_eq!(g.num_views(), v, "grid views vs map views");
        assert_eq!(g.map_hw, [h, w], "grid map size vs map size");
        let p = g.voxels.num_voxels();
        let [x, y, z] = g.voxels.shape;
        let sample_view = |vi: usize| -> (Tensor<2>, Tensor<2, Bool>) {
            let m = maps
                .clone()
                .narrow(0, bi, 1)
                .narrow(1, vi, 1)
                .reshape([1, c, h, w]);
            let s = m.grid_sample_2d(g.grid.clone().narrow(0, vi, 1), opts()); // [1, C, 1, P]
            let vis = g.visible.clone().narrow(0, vi, 1); // [1, P]
            (s.reshape([c, p]), vis)
        };
        let fused = match mode {
            FusionMode::Mean => {
                let mut sum: Option<Tensor<2>> = None;
                for vi in 0..v {
                    let (s, vis) = sample_view(vi);
                    let s = s.mask_fill(vis.bool_not(), 0.0);
                    sum = Some(match sum {
                        Some(acc) => acc + s,
                        None => s,
                    });
                }
                let count = g.view_count().reshape([1, p]).clamp_min(1.0);
                sum.expect("at least one view") / count
            }
            FusionMode::Deformable => {
                panic!("deformable fusion has parameters: use DeformableFusion::forward")
            }
            FusionMode::Max => {
                let mut acc: Option<Tensor<2>> = None;
                for vi in 0..v {
                    let (s, vis) = sample_view(vi);
                    let s = s.mask_fill(vis.bool_not(), f32::NEG_INFINITY);
                    acc = Some(match acc {
                        Some(a) => a.max_pair(s),
                        None => s,
                    });
                }
                let unseen = g.view_count().reshape([1, p]).equal_elem(0.0);
                acc.expect("at least one view").mask_fill(unseen, 0.0)
            }
        };
        out.push(fused.reshape([1, c, x, y, z]));
    }
    Tensor::cat(out, 0)
}
