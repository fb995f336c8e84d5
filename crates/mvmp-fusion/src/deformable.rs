//! Deformable-attention fusion (paper ablation): around each voxel's projected point the view is sampled at
//! `K` learned offsets and combined with learned weights, instead of one bilinear sample.
//!
//! Offsets (in feature-map pixels) and weight logits come from a linear layer on a sinusoidal encoding of
//! the voxel centre, so each place in the scene learns where to look around its projection; the weights
//! are a softmax over the `K` points, and views are averaged over those that see the voxel, as in mean
//! fusion. At initialisation the offsets are zero and the weights uniform, which is mean fusion.
use burn::config::Config;
use burn::module::Module;
use burn::nn::{Initializer, Linear, LinearConfig};
use burn::tensor::activation::softmax;
use burn::tensor::ops::{GridSampleOptions, GridSamplePaddingMode, InterpolateMode};
use burn::tensor::{Device, Tensor, TensorData};

use crate::SamplingGrid;
use mvmp_geom::VoxelGrid;

const FREQS: usize = 6;

#[derive(Config, Debug)]
pub struct DeformableFusionConfig {
    /// Sampling points per view and voxel.
    #[config(default = 4)]
    pub points: usize,
}

#[derive(Module, Debug)]
pub struct DeformableFusion {
    /// Voxel encoding -> K x (dx, dy, logit).
    pub proj: Linear,
    pub points: usize,
}

impl DeformableFusionConfig {
    pub fn init(&self, device: &Device) -> DeformableFusion {
        DeformableFusion {
            proj: LinearConfig::new(6 * FREQS, 3 * self.points)
                .with_initializer(Initializer::Zeros)
                .init(device),
            points: self.points,
        }
    }
}

fn encoding(grid: &VoxelGrid, device: &Device) -> Tensor<2> {
    let lo = grid.min_corner();
    let mut v = Vec::with_capacity(grid.num_voxels() * 6 * FREQS);
    for c in grid.centers() {
        for a in 0..3 {
            let x = (c[a] - lo[a]) / grid.size[a];
            for f in 0..FREQS {
                let w = std::f64::consts::PI * (1 << f) as f64 * x;
                v.push(w.sin() as f32);
                v.push(w.cos() as f32);
            }
        }
    }
    Tensor::from_data(TensorData::new(v, [grid.num_voxels(), 6 * FREQS]), device)
}

impl DeformableFusion {
    /// `maps [B, V, C, h, w]`, one grid per batch item -> `[B, C, X, Y, Z]`.
    pub fn forward(&self, maps: Tensor<5>, grids: &[SamplingGrid]) -> Tensor<5> {
        let [b, v, c, h, w] = maps.dims();
        let k = self.points;
        let device = maps.device();
        let opts = || {
            GridSampleOptions::new(InterpolateMode::Bilinear)
                .with_padding_mode(GridSamplePaddingMode::Border)
                .with_align_corners(false)
        };
        let mut out = Vec::with_capacity(b);
        for (bi, g) in grids.iter().enumerate() {
            let p = g.voxels.num_voxels();
            let [x, y, z] = g.voxels.shape;
            let raw = self
                .proj
                .forward(encoding(&g.voxels, &device))
                .reshape([p, k, 3]);
            // Offsets in map pixels -> normalised grid units (align_corners = false: 2 / size per pixel).
            let dx = raw.clone().narrow(2, 0, 1).reshape([p, k]) * (2.0 / w as f64);
            let dy = raw.clone().narrow(2, 1, 1).reshape([p, k]) * (2.0 / h as f64);
            let weight = softmax(raw.narrow(2, 2, 1).reshape([p, k]), 1); // [P, K]
            let mut sum: Option<Tensor<2>> = None;
            for vi in 0..v {
                let m = maps
                    .clone()
                    .narrow(0, bi, 1)
                    .narrow(1, vi, 1)
                    .reshape([1, c, h, w]);
                let base = g.grid.clone().narrow(0, vi, 1).reshape([p, 1, 2]);
                let off = Tensor::stack::<3>(vec![dx.clone(), dy.clone()], 2); // [P, K, 2]
                let pts = (base + off).reshape([1, p, k, 2]);
                let s = m.grid_sample_2d(pts, opts()).reshape([c, p, k]); // [C, P, K]
                let s = (s * weight.clone().unsqueeze_dim::<3>(0))
                    .sum_dim(2)
                    .reshape([c, p]);
                let vis = g.visible.clone().narrow(0, vi, 1);
                let s = s.mask_fill(vis.bool_not(), 0.0);
                sum = Some(match sum {
                    Some(a) => a + s,
                    None => s,
                });
            }
            let count = g.view_count().reshape([1, p]).clamp_min(1.0);
            out.push((sum.expect("at least one view") / count).reshape([1, c, x, y, z]));
        }
        Tensor::cat(out, 0)
    }
}
