//! The facing head and its reading (docs/architecture.md, Facing).
//!
//! Mean fusion keeps no trace of which camera saw what: a person's front seen by one camera and back by
//! another fuse into the same voxels whichever way the person faces, so the volume cannot tell a heading.
//! A camera can: it sees a face or a shirt's front, or not. The facing head draws, per view and pixel,
//! the cosine and sine of the heading of the person there relative to the horizontal direction from that
//! person to the camera; read at a person's chest in every view and turned by each camera's direction,
//! the views agree on one heading in the world.
use burn::module::Module;
use burn::nn::conv::{Conv2d, Conv2dConfig};
use burn::nn::{GroupNorm, GroupNormConfig, PaddingConfig2d};
use burn::tensor::activation::softmax;
use burn::tensor::ops::{GridSampleOptions, GridSamplePaddingMode, InterpolateMode};
use burn::tensor::{Bool, Device, Int, Tensor, TensorData};
use mvmp_kernels::conv::conv2d;
use mvmp_kernels::gelu::gelu;
use mvmp_kernels::norm::group_norm;

use mvmp_decoder::trilinear_sample;
use mvmp_geom::VoxelGrid;

use crate::RigGrids;

/// Height above the root (metres) where the facing maps are read: about the chest, over the torso the
/// head is trained on.
pub const FACING_HEIGHT: f32 = 0.3;

/// Channels of the facing head's own image features and of its hidden layers.
pub(crate) const HIDDEN: usize = 32;

/// The facing head: its own two stride-2 convolutions on the image (HRNet's features, trained for
/// joints, carry too little of a person's colours), joined with HRNet's highest-resolution features,
/// two 3 x 3 convolutions and a 1 x 1: `[N, 3, S, S]` and `[N, width, S/4, S/4]` -> `[N, 2, S/4, S/4]`
/// (relative cosine and sine). Each hidden convolution is group-normalised (4 channels a group) and
/// followed by a GELU: with plain ReLUs the head trained from scratch at stage 1's rate sometimes
/// learned (median error 28-35 degrees at the true roots after 8 epochs) and sometimes stayed near chance
/// (54-69) from one initialisation to the next.
#[derive(Module, Debug)]
pub struct FacingHead {
    pub down1: Conv2d,
    pub norm1: GroupNorm,
    pub down2: Conv2d,
    pub norm2: GroupNorm,
    pub conv1: Conv2d,
    pub norm3: GroupNorm,
    pub conv2: Conv2d,
    pub norm4: GroupNorm,
    pub out: Conv2d,
}

impl FacingHead {
    /// A head on HRNet features of `width` channels whose maps hold the relative heading's cosine and
    /// sine (`bins` 0) or the logits of `bins` heading bins.
    pub fn new(width: usize, bins: usize, device: &Device) -> Self {
        let conv3 = |i, o, stride| {
            Conv2dConfig::new([i, o], [3, 3])
                .with_stride([stride, stride])
                .with_padding(PaddingConfig2d::Explicit(1, 1, 1, 1))
                .init(device)
        };
        let norm = |c: usize| GroupNormConfig::new(c / 4, c).init(device);
        FacingHead {
            down1: conv3(3, HIDDEN / 2, 2),
            norm1: norm(HIDDEN / 2),
            down2: conv3(HIDDEN / 2, HIDDEN, 2),
            norm2: norm(HIDDEN),
            conv1: conv3(HIDDEN + width, HIDDEN, 1),
            norm3: norm(HIDDEN),
            conv2: conv3(HIDDEN, HIDDEN, 1),
            norm4: norm(HIDDEN),
            out: Conv2dConfig::new([HIDDEN, if bins == 0 { 2 } else { bins }], [1, 1]).init(device),
        }
    }

    pub fn forward(&self, image: Tensor<4>, features: Tensor<4>) -> Tensor<4> {
        let x = gelu(group_norm(&self.norm1, conv2d(&self.down1, image)));
        let x = gelu(group_norm(&self.norm2, conv2d(&self.down2, x)));
        let x = Tensor::cat(vec![x, features], 1);
        let x = gelu(group_norm(&self.norm3, conv2d(&self.conv1, x)));
        let x = gelu(group_norm(&self.norm4, conv2d(&self.conv2, x)));
        conv2d(&self.out, x)
    }
}

/// Each person's heading in the world `[B, K, 2]` from the facing maps `[B, V, 2, h, w]` read at
/// `FACING_HEIGHT` above the roots `[B, K, 3]`: per view the (cos, sin) there, relative to the
/// horizontal unit direction `d` from the root to the camera, becomes `cos d + sin d_perp` (`d_perp`
/// is `d` turned 90 degrees anticlockwise about the vertical), averaged over the views that see the
/// person's chest ([`chest_view_weights`], from the other present people `present [B, K]`) and scaled
/// to unit length.
pub fn facing_readout(
    facing: Tensor<5>,
    grids: &[RigGrids],
    grid: &VoxelGrid,
    roots: Tensor<3>,
    present: Tensor<2, Bool>,
) -> Tensor<3> {
    let b = facing.dims()[0];
    let items: Vec<Tensor<3>> = (0..b)
        .map(|bi| {
            readout_item(
                facing.clone().narrow(0, bi, 1),
                &grids[bi],
                grid,
                roots.clone().narrow(0, bi, 1),
                present.clone().narrow(0, bi, 1),
            )
        })
        .collect();
    Tensor::cat(items, 0)
}

/// [`facing_readout`] of one batch item: `facing [1, V, 2, h, w]`, `roots [1, K, 3]`,
/// `present [1, K]` -> `[1, K, 2]`.
fn readout_item(
    facing: Tensor<5>,
    g: &RigGrids,
    grid: &VoxelGrid,
    roots: Tensor<3>,
    present: Tensor<2, Bool>,
) -> Tensor<3> {
    let facing = heading_vectors(facing);
    let [_, v, c, h, w] = facing.dims();
    let k = roots.dims()[1];
    let device = facing.device();
    let weights = {
        let r: Vec<f32> = roots
            .clone()
            .into_data()
            .convert::<f32>()
            .try_into_vec()
            .unwrap_or_default();
        // Read as floats: backends store booleans in different element types (wgpu's read back as
        // `bool` failed), and a float is what every one of them converts to.
        let p: Vec<bool> = present
            .float()
            .into_data()
            .convert::<f32>()
            .try_into_vec::<f32>()
            .unwrap_or_default()
            .into_iter()
            .map(|x| x > 0.5)
            .collect();
        let mut w = chest_view_weights(&g.centres, &r, &p);
        // Unreadable roots or mask: every view at weight 1, as before the weighting.
        w.resize(v * k, 1.0);
        Tensor::<2>::from_data(TensorData::new(w, [v, k]), &device)
    };
    let lift = Tensor::<1>::from_data(TensorData::new(vec![0.0, 0.0, FACING_HEIGHT], [3]), &device);
    let points = roots.clone() + lift.reshape([1, 1, 3]);
    let rel = sample_views(facing.reshape([v, c, h, w]), g, grid, points); // [V, 2, K]
    let (cos, sin) = (
        rel.clone().narrow(1, 0, 1).reshape([v, k]),
        rel.narrow(1, 1, 1).reshape([v, k]),
    );
    let d = to_cameras(g, roots, &device); // [V, K, 2]
    let (dx, dy) = (
        d.clone().narrow(2, 0, 1).reshape([v, k]),
        d.narrow(2, 1, 1).reshape([v, k]),
    );
    let x = (cos.clone() * dx.clone() - sin.clone() * dy.clone()) * weights.clone();
    let y = (cos * dy + sin * dx) * weights;
    let mean = Tensor::stack::<3>(vec![x, y], 2)
        .mean_dim(0)
        .reshape([1, k, 2]);
    // A squared-error head shrinks its maps towards 0 where it is unsure, and its mean over the views
    // is shorter still; the decoder gets the direction alone, at the scale of its other inputs.
    unit(mean, 1e-6)
}

/// Radii (metres) about another person's vertical axis within which the line from a camera to a chest
/// is fully hidden (`OCCLUDER_INNER`) or starts to be hidden (`OCCLUDER_OUTER`).
pub const OCCLUDER_INNER: f64 = 0.1;
pub const OCCLUDER_OUTER: f64 = 0.3;
/// How far below and above their root another person's body reaches (metres).
const OCCLUDER_BELOW: f64 = 1.2;
const OCCLUDER_ABOVE: f64 = 0.9;

/// How well each view sees each person's chest, `[V, K]` row-major in 0..=1, from the cameras' centres,
/// the roots (`K x 3`, flat) and which of them are people. Another person stands in the way of a view
/// when the line from its camera to the chest (`FACING_HEIGHT` above the root) passes, between them,
/// within `OCCLUDER_OUTER` of their vertical axis and within their height; the view's weight is the
/// product over people in the way of a ramp from 1 at `OCCLUDER_OUTER` to 0 at `OCCLUDER_INNER`. A view
/// that shows someone else shows their heading: unweighted, such views turned the demo's readings of
/// people hidden in one view to a median error of 40 degrees against 19 for people seen in all four. A
/// person hidden in every view gets every view at weight 1.
pub fn chest_view_weights(centres: &[[f64; 3]], roots: &[f32], present: &[bool]) -> Vec<f32> {
    let k = present.len().min(roots.len() / 3);
    let root = |i: usize| [0, 1, 2].map(|a| roots[i * 3 + a] as f64);
    let mut out = vec![1.0f32; centres.len() * present.len()];
    for p in (0..k).filter(|&p| present[p]) {
        let r = root(p);
        let chest = [r[0], r[1], r[2] + FACING_HEIGHT as f64];
        let seen: Vec<f64> = centres
            .iter()
            .map(|o| {
                (0..k)
                    .filter(|&q| q != p && present[q])
                    .map(|q| 1.0 - cover(*o, chest, root(q)))
                    .product()
            })
            .collect();
        if seen.iter().sum::<f64>() > 1e-3 {
            for (v, w) in seen.into_iter().enumerate() {
                out[v * present.len() + p] = w as f32;
            }
        }
    }
    out
}

/// How much of the line from `camera` to `chest` the body standing at root `q` hides, 0..=1.
fn cover(camera: [f64; 3], chest: [f64; 3], q: [f64; 3]) -> f64 {
    let d = [0, 1, 2].map(|a| chest[a] - camera[a]);
    let hh = d[0] * d[0] + d[1] * d[1];
    if hh < 1e-12 {
        return 0.0;
    }
    // The point of the line horizontally nearest the other person's axis; it must lie between the two.
    let s = ((q[0] - camera[0]) * d[0] + (q[1] - camera[1]) * d[1]) / hh;
    if s <= 0.0 || s >= 1.0 {
        return 0.0;
    }
    let at = [0, 1, 2].map(|a| camera[a] + s * d[a]);
    if at[2] < q[2] - OCCLUDER_BELOW || at[2] > q[2] + OCCLUDER_ABOVE {
        return 0.0;
    }
    let dist = (at[0] - q[0]).hypot(at[1] - q[1]);
    ((OCCLUDER_OUTER - dist) / (OCCLUDER_OUTER - OCCLUDER_INNER)).clamp(0.0, 1.0)
}

/// The centre of heading bin `k` of `n` (radians, anticlockwise from the direction to the camera).
pub fn bin_angle(k: usize, n: usize) -> f64 {
    std::f64::consts::TAU * k as f64 / n as f64
}

/// The bins' unit directions `[N, 2]` (cosine, sine).
fn bin_directions(n: usize, device: &Device) -> Tensor<2> {
    let d: Vec<f32> = (0..n)
        .flat_map(|k| {
            let a = bin_angle(k, n);
            [a.cos() as f32, a.sin() as f32]
        })
        .collect();
    Tensor::from_data(TensorData::new(d, [n, 2]), device)
}

/// Facing maps `[B, V, C, h, w]` as relative heading vectors `[B, V, 2, h, w]`: two channels already
/// are (cosine, sine); more are the logits of that many heading bins, read as the mean of the bins'
/// directions under their softmax (short where the head is torn between bins, as a regressed vector is).
pub fn heading_vectors(maps: Tensor<5>) -> Tensor<5> {
    let [b, v, c, h, w] = maps.dims();
    if c == 2 {
        return maps;
    }
    let dirs = bin_directions(c, &maps.device());
    let p = softmax(maps, 2).swap_dims(2, 4).reshape([b * v * w * h, c]);
    p.matmul(dirs).reshape([b, v, w, h, 2]).swap_dims(2, 4)
}

/// Facing maps `[N, C, h, w]` of a view mirrored left to right as maps of the view itself: a mirror
/// negates each heading's angle to the camera (exactly when the camera has no roll, so that its mirror
/// plane is vertical), so the sine changes sign (`C` = 2) or bin `k` becomes bin `(C - k) mod C`.
pub fn mirror_headings(maps: Tensor<4>) -> Tensor<4> {
    let c = maps.dims()[1];
    let device = maps.device();
    if c == 2 {
        let sign = Tensor::<1>::from_data(TensorData::new(vec![1.0f32, -1.0], [2]), &device);
        return maps * sign.reshape([1, 2, 1, 1]);
    }
    let order: Vec<i64> = (0..c).map(|k| ((c - k) % c) as i64).collect();
    maps.select(
        1,
        Tensor::<1, Int>::from_data(TensorData::new(order, [c]), &device),
    )
}

/// The von Mises label over `n` heading bins of relative heading vectors `[B, V, 2, h, w]` (unit):
/// `softmax_k(kappa cos(theta - theta_k))` with `kappa = (n / 2 pi)^2`, one bin's width of spread.
pub fn bin_labels(target: Tensor<5>, n: usize) -> Tensor<5> {
    let [b, v, _, h, w] = target.dims();
    let kappa = (n as f64 / std::f64::consts::TAU).powi(2) as f32;
    let dirs = bin_directions(n, &target.device()); // [N, 2]
    let cosines = target
        .swap_dims(2, 4)
        .reshape([b * v * w * h, 2])
        .matmul(dirs.transpose()); // cos(theta - theta_k)
    softmax(cosines.mul_scalar(kappa), 1)
        .reshape([b, v, w, h, n])
        .swap_dims(2, 4)
}

/// `x` `[.., .., 2]` divided by its length along the last axis (at least `eps`).
fn unit(x: Tensor<3>, eps: f32) -> Tensor<3> {
    let len = x.clone().powi_scalar(2).sum_dim(2).sqrt().clamp_min(eps);
    x / len
}

/// The regressed rotations `[N, 53, 3, 3]` with the global orientation (the first) turned about the
/// vertical so that an upright default person (facing -y: the y-up to z-up turn of the canonical +z)
/// faces `heading` `[N, 2]` (unit): the decoder's global orientation is relative to the facing
/// head's reading, so that a decoder that has not yet learned the heading already gets it.
pub fn turn_to_heading(rotmats: Tensor<4>, heading: Tensor<2>) -> Tensor<4> {
    let [n, j, _, _] = rotmats.dims();
    let hx = heading.clone().narrow(1, 0, 1);
    let hy = heading.narrow(1, 1, 1);
    // The turn about z taking (0, -1) to (hx, hy): cosine -hy, sine hx.
    let (c, s) = (hy.neg(), hx);
    let zero = c.zeros_like();
    let one = zero.clone().add_scalar(1.0);
    let turn = Tensor::cat(
        vec![
            c.clone(),
            s.clone().neg(),
            zero.clone(),
            s,
            c,
            zero.clone(),
            zero.clone(),
            zero,
            one,
        ],
        1,
    )
    .reshape([n, 1, 3, 3]);
    let global = turn.matmul(rotmats.clone().narrow(1, 0, 1));
    Tensor::cat(vec![global, rotmats.narrow(1, 1, j - 1)], 1)
}

/// Maps `[V, C, h, w]` at world `points [1, K, 3]` in each view -> `[V, C, K]`. The map positions of the
/// voxel centres are smooth in space: a point's is their trilinear interpolation.
fn sample_views(maps: Tensor<4>, g: &RigGrids, grid: &VoxelGrid, points: Tensor<3>) -> Tensor<3> {
    let [v, c, _, _] = maps.dims();
    let k = points.dims()[1];
    let [nx, ny, nz] = grid.shape;
    let p = g.heatmaps.grid.dims()[2];
    let coords = g
        .heatmaps
        .grid
        .clone()
        .reshape([v, p, 2])
        .swap_dims(1, 2)
        .reshape([1, v * 2, nx, ny, nz]);
    let uv = trilinear_sample(coords, points, grid) // [1, K, V * 2]
        .reshape([k, v, 2])
        .swap_dims(0, 1)
        .reshape([v, 1, k, 2]);
    let opts = GridSampleOptions::new(InterpolateMode::Bilinear)
        .with_padding_mode(GridSamplePaddingMode::Border)
        .with_align_corners(false);
    maps.grid_sample_2d(uv, opts).reshape([v, c, k])
}

/// Horizontal unit directions from the roots `[1, K, 3]` to each view's camera -> `[V, K, 2]`.
fn to_cameras(g: &RigGrids, roots: Tensor<3>, device: &Device) -> Tensor<3> {
    let v = g.centres.len();
    let k = roots.dims()[1];
    let centres: Vec<f32> = g
        .centres
        .iter()
        .flat_map(|c| [c[0] as f32, c[1] as f32])
        .collect();
    let centres = Tensor::<2>::from_data(TensorData::new(centres, [v, 2]), device);
    let to_cam = centres.reshape([v, 1, 2]) - roots.narrow(2, 0, 2).reshape([1, k, 2]);
    unit(to_cam, 1e-3)
}

/// The target of the facing maps for one person and camera: (cos, sin) of the heading `[hx, hy]` (unit,
/// horizontal) relative to the horizontal unit direction from the person at `at` to the camera at
/// `camera`. `None` when the camera stands right above the person.
pub fn relative_heading(heading: [f64; 2], at: [f64; 3], camera: [f64; 3]) -> Option<[f32; 2]> {
    let (dx, dy) = (camera[0] - at[0], camera[1] - at[1]);
    let n = (dx * dx + dy * dy).sqrt();
    if n < 1e-6 {
        return None;
    }
    let (dx, dy) = (dx / n, dy / n);
    let cos = heading[0] * dx + heading[1] * dy;
    let sin = heading[1] * dx - heading[0] * dy;
    Some([cos as f32, sin as f32])
}
