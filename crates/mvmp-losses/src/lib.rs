//! The five MVMP-HMR losses (paper Sec. 4.4; docs/architecture.md, Training):
//! `L = L_D + w_P L_P + L_mesh + w_O L_O + w_den L_denj3d`, `L_mesh = w_3D L_3D + mean_v L_2D`, paper
//! weights `w_P = 10`, `w_O = 5`, `w_den = 1`, `w_3D = 100`.
//!
//! People are compared pairwise: predictions are already matched to ground truth and padded to `[B, K]`,
//! with a mask that is 1 where a pair exists. Every L1/MSE term is the mean over the elements of the valid
//! pairs (a person with many vertices does not outweigh one with few joints). Units: metres for 3D terms,
//! network pixels for 2D terms, voxel units for the root offset.
use burn::tensor::activation::log_softmax;
use burn::tensor::{Device, Int, Tensor, TensorData};

use mvmp_geom::{Camera, CameraTensors, Letterbox};

pub mod mesh_2d;

pub use mesh_2d::{fused_mesh_2d, set_fused_mesh_2d};

/// Elements per row when [`sum_all`] splits a long reduction.
const SUM_ROW: usize = 1024;

/// The sum of every element, as `[1]`. A long tensor is summed in two stages (rows of 1024, then the row
/// sums): burn 0.22's one-pass full reduction on wgpu launches at most 65535 workgroups along one axis of
/// 4 elements each, so on adapters with that Vulkan minimum limit (lavapipe; measured by
/// `tests/backends.rs`) a 1-D sum of more than 2^18 elements silently drops the rest (2^22 ones summed
/// to 262132).
pub fn sum_all<const D: usize>(x: Tensor<D>) -> Tensor<1> {
    let n = x.shape().num_elements();
    if n <= SUM_ROW * 64 {
        return x.sum();
    }
    let rows = n.div_ceil(SUM_ROW);
    let flat = x.reshape([n]);
    let flat = if rows * SUM_ROW == n {
        flat
    } else {
        let device = flat.device();
        Tensor::cat(vec![flat, Tensor::zeros([rows * SUM_ROW - n], &device)], 0)
    };
    flat.reshape([rows, SUM_ROW]).sum_dim(1).sum()
}

/// The maximum of each row of `x` `[B, N]`, as `[B, 1]`; long rows are reduced in two stages for the reason
/// given at [`sum_all`] (the same limit breaks `max_dim` over more than 2^18 elements).
pub fn max_rows(x: Tensor<2>) -> Tensor<2> {
    let [b, n] = x.dims();
    if n <= SUM_ROW * 64 {
        return x.max_dim(1);
    }
    let rows = n.div_ceil(SUM_ROW);
    let x = if rows * SUM_ROW == n {
        x
    } else {
        let device = x.device();
        Tensor::cat(
            vec![
                x,
                Tensor::full([b, rows * SUM_ROW - n], f32::NEG_INFINITY, &device),
            ],
            1,
        )
    };
    x.reshape([b, rows, SUM_ROW])
        .max_dim(2)
        .reshape([b, rows])
        .max_dim(1)
}

/// The mean of every element, as `[1]` (see [`sum_all`]).
pub fn mean_all<const D: usize>(x: Tensor<D>) -> Tensor<1> {
    let n = x.shape().num_elements();
    sum_all(x) / n.max(1) as f32
}

/// Mean of `err` `[B, K, ...]` over the elements of pairs where `mask` `[B, K]` is 1.
fn masked_mean<const D: usize>(err: Tensor<D>, mask: Tensor<2>) -> Tensor<1> {
    let dims = err.dims();
    let (b, k) = (dims[0], dims[1]);
    let per: usize = dims[2..].iter().product();
    let e = err.reshape([b, k, per]).sum_dim(2).reshape([b, k]);
    let n = sum_all(mask.clone()).clamp_min(1.0) * per as f32;
    sum_all(e * mask) / n
}

/// Detection loss: MSE between the root likelihood `[B, 1, X, Y, Z]` and its Gaussian target, plus L1 between
/// the predicted offset `[B, 3, X, Y, Z]` at each ground-truth root's voxel (`voxels` `[B, R]` flat indices)
/// and the root's sub-voxel offset `[B, R, 3]`, over valid roots (`mask` `[B, R]`).
pub fn detection_loss(
    likelihood: Tensor<5>,
    target: Tensor<5>,
    offset: Tensor<5>,
    voxels: Tensor<2, Int>,
    gt_offset: Tensor<3>,
    mask: Tensor<2>,
) -> Tensor<1> {
    detection_loss_weighted(likelihood, target, offset, voxels, gt_offset, mask, 1.0)
}

/// [`detection_loss`] with the offset term weighted by `offset_weight` (the paper: 1). The volume MSE is
/// a mean over every voxel, so its gradient is small beside the offset L1's; a smaller offset weight lets
/// the likelihood learn first in short trainings.
pub fn detection_loss_weighted(
    likelihood: Tensor<5>,
    target: Tensor<5>,
    offset: Tensor<5>,
    voxels: Tensor<2, Int>,
    gt_offset: Tensor<3>,
    mask: Tensor<2>,
    offset_weight: f32,
) -> Tensor<1> {
    let mse = mean_all((likelihood - target).powi_scalar(2));
    let [b, _, x, y, z] = offset.dims();
    let flat = offset.reshape([b, 3, x * y * z]);
    let idx = voxels.unsqueeze_dim::<3>(1).repeat_dim(1, 3); // [B, 3, R]
    let picked = flat.gather(2, idx).swap_dims(1, 2); // [B, R, 3]
    mse + masked_mean((picked - gt_offset).abs(), mask) * offset_weight
}

/// The squared error of the root likelihood `[B, 1, X, Y, Z]` weighted by its Gaussian target: the mean of
/// `t (l - t)^2` over the target's mass. The volume MSE of [`detection_loss`] averages over every voxel, so
/// the few voxels at people (about 0.1% of a scene's volume) weigh almost nothing beside the empty space and
/// the likelihood at people settles well below 1; this term gives the people's voxels a weight of their
/// own. 0 when the target is empty.
pub fn detection_positive_loss(likelihood: Tensor<5>, target: Tensor<5>) -> Tensor<1> {
    let err = (likelihood - target.clone()).powi_scalar(2) * target.clone();
    sum_all(err) / sum_all(target).clamp_min(1e-6)
}

/// Parameter loss: L1 on the rotation matrices of the 53 regressed joints `[B, K, 53, 3, 3]`, on betas and on
/// expression `[B, K, 10]`, each a mean over elements, summed.
pub fn parameter_loss(
    rot: Tensor<5>,
    gt_rot: Tensor<5>,
    betas: Tensor<3>,
    gt_betas: Tensor<3>,
    expression: Tensor<3>,
    gt_expression: Tensor<3>,
    mask: Tensor<2>,
) -> Tensor<1> {
    masked_mean((rot - gt_rot).abs(), mask.clone())
        + masked_mean((betas - gt_betas).abs(), mask.clone())
        + masked_mean((expression - gt_expression).abs(), mask)
}

/// The squared error of the 21 body rotations' matrices (slots 1 to 21 of the regressed `[B, K, 53, 3,
/// 3]`), a mean over elements of the present people. Beside [`parameter_loss`]'s L1, whose gradient is
/// the error's sign whatever its size, it pulls harder the further a rotation is off.
pub fn body_pose_l2_loss(rot: Tensor<5>, gt_rot: Tensor<5>, mask: Tensor<2>) -> Tensor<1> {
    let body = |r: Tensor<5>| r.narrow(2, 1, BODY_ROTATIONS);
    masked_mean((body(rot) - body(gt_rot)).powi_scalar(2), mask)
}

/// Body joints among the regressed rotations, after the global orientation.
const BODY_ROTATIONS: usize = 21;

/// 3D mesh loss: L1 on points `[B, K, N, 3]` (joints and vertices, world metres).
pub fn mesh_3d_loss(points: Tensor<4>, gt: Tensor<4>, mask: Tensor<2>) -> Tensor<1> {
    masked_mean((points - gt).abs(), mask)
}

/// 3D mesh loss with a weight per point `[B, K, N]` (1 where the ground-truth point is annotated, 0 for
/// padding and for joints a dataset does not annotate): the L1 mean over the supervised coordinates. With
/// every point of a valid pair weighted 1 it equals [`mesh_3d_loss`].
pub fn mesh_3d_loss_weighted(points: Tensor<4>, gt: Tensor<4>, weight: Tensor<3>) -> Tensor<1> {
    let [b, k, n, _] = points.dims();
    let w = weight.reshape([b, k, n, 1]);
    sum_all((points - gt).abs() * w.clone()) / (sum_all(w) * 3.0).clamp_min(1.0)
}

/// Points `[B, K, N, 3]` in each body's own frame: `R^T (p - pelvis)` for the body's pelvis `[B, K, 3]`
/// and global rotation `rot` `[B, K, 3, 3]` (body to world). A body's translation and heading then leave
/// its points where they were; only its pose and shape move them.
pub fn to_body_frame(points: Tensor<4>, pelvis: Tensor<3>, rot: Tensor<4>) -> Tensor<4> {
    let [b, k, n, _] = points.dims();
    let centred = points - pelvis.reshape([b, k, 1, 3]);
    // Row vectors: (R^T x)^T = x^T R.
    centred
        .reshape([b * k, n, 3])
        .matmul(rot.reshape([b * k, 3, 3]))
        .reshape([b, k, n, 3])
}

/// Translation loss: L1 between predicted and ground-truth pelvis positions `[B, K, 3]` (world metres)
/// over the pairs where `mask` `[B, K]` is 1. It supervises where a body is when the mesh terms compare
/// points in the body's own frame ([`MeshFrame::Body`]).
pub fn translation_loss(pelvis: Tensor<3>, gt_pelvis: Tensor<3>, mask: Tensor<2>) -> Tensor<1> {
    masked_mean((pelvis - gt_pelvis).abs(), mask)
}

/// 2D mesh loss of one view: predicted world points `[B, K, N, 3]` projected with each sample's camera
/// (with its letterbox, into network pixels of an `S x S` input), L1 against ground-truth pixels
/// `[B, K, N, 2]`, counting only ground-truth points inside the image (`0 <= u, v < S`) of valid pairs.
pub fn mesh_2d_loss(
    points: Tensor<4>,
    gt_uv: Tensor<4>,
    cameras: &[CameraTensors],
    size: f32,
    mask: Tensor<2>,
) -> Tensor<1> {
    let [b, k, n, _] = points.dims();
    let weight = mask.reshape([b, k, 1]).repeat_dim(2, n);
    mesh_2d_loss_weighted(points, gt_uv, cameras, size, weight)
}

/// [`mesh_2d_loss`] with a weight per point `[B, K, N]` instead of per pair (0 for points a dataset does
/// not annotate).
pub fn mesh_2d_loss_weighted(
    points: Tensor<4>,
    gt_uv: Tensor<4>,
    cameras: &[CameraTensors],
    size: f32,
    weight: Tensor<3>,
) -> Tensor<1> {
    let [b, k, n, _] = points.dims();
    let uv: Vec<Tensor<3>> = (0..b)
        .map(|bi| {
            let p = points.clone().narrow(0, bi, 1).reshape([k * n, 3]);
            cameras[bi].project(p).uv.reshape([1, k * n, 2])
        })
        .collect();
    let uv = Tensor::cat(uv, 0).reshape([b, k, n, 2]);
    let ok = gt_uv
        .clone()
        .greater_equal_elem(0.0)
        .bool_and(gt_uv.clone().lower_elem(size))
        .float(); // [B, K, N, 2]
    let inside = ok.clone().narrow(3, 0, 1) * ok.narrow(3, 1, 1); // [B, K, N, 1]
    let w = inside * weight.reshape([b, k, n, 1]);
    let err = sum_all((uv - gt_uv).abs() * w.clone());
    err / (sum_all(w) * 2.0).clamp_min(1.0)
}

/// The 2D mesh loss of predicted world points `[B, K, N, 3]` summed over the views: in each view, the
/// predictions and the true points `[B, K, N, 3]` projected with `rigs[b]`'s camera and letterbox, and
/// [`mesh_2d_loss_weighted`] between them (the truth's projection a constant). `rigs[b]` holds batch
/// item `b`'s cameras and letterboxes, as many views for each.
///
/// On flex one pass over the points ([`mesh_2d`]); otherwise, and under autodiff with
/// [`set_fused_mesh_2d`] off, one view at a time as tensor ops. Both give the same values and gradients
/// (tested to 1e-5).
pub fn mesh_2d_loss_views(
    points: Tensor<4>,
    truth: Tensor<4>,
    rigs: &[(&[Camera], &[Letterbox])],
    size: f32,
    weight: Tensor<3>,
) -> Tensor<1> {
    if mesh_2d::applies(&points.device()) {
        let host = |t: TensorData| {
            t.convert::<f32>()
                .try_into_vec::<f32>()
                .expect("float32 after convert")
        };
        let cameras = rigs
            .iter()
            .map(|(cams, lbs)| {
                cams.iter()
                    .zip(lbs.iter())
                    .map(|(c, l)| mesh_2d::HostCamera::new(c, Some(l)))
                    .collect()
            })
            .collect();
        let plan = mesh_2d::Mesh2dPlan::new(
            cameras,
            &host(truth.into_data()),
            &host(weight.into_data()),
            size,
        );
        return mesh_2d::loss(points, plan);
    }
    let [b, k, n, _] = truth.dims();
    let device = points.device();
    let views = rigs.first().map_or(0, |r| r.0.len());
    let mut sum: Option<Tensor<1>> = None;
    for v in 0..views {
        let cams: Vec<CameraTensors> = rigs
            .iter()
            .map(|(c, l)| CameraTensors::new(&c[v..v + 1], Some(&l[v..v + 1]), &device))
            .collect();
        let uv: Vec<Tensor<3>> = (0..b)
            .map(|bi| {
                let pts = truth.clone().narrow(0, bi, 1).reshape([k * n, 3]);
                cams[bi].project(pts).uv.reshape([1, k * n, 2])
            })
            .collect();
        let truth_uv = Tensor::cat(uv, 0).reshape([b, k, n, 2]).detach();
        let l = mesh_2d_loss_weighted(points.clone(), truth_uv, &cams, size, weight.clone());
        sum = Some(sum.take().map_or(l.clone(), |s| s + l));
    }
    sum.unwrap_or_else(|| Tensor::zeros([1], &device))
}

/// The orientation vector `O = (J_lhip - J_rhip) x (J_spine1 - J_pelvis)` of joints `[B, K, J, 3]` in SMPL-X
/// order (pelvis 0, left hip 1, right hip 2, spine1 3): `[B, K, 3]`.
pub fn orientation(joints: Tensor<4>) -> Tensor<3> {
    let [b, k, _, _] = joints.dims();
    let j = |i: usize| joints.clone().narrow(2, i, 1).reshape([b, k, 3]);
    let (a, c) = (j(1) - j(2), j(3) - j(0));
    let e = |t: &Tensor<3>, i: usize| t.clone().narrow(2, i, 1);
    Tensor::cat(
        vec![
            e(&a, 1) * e(&c, 2) - e(&a, 2) * e(&c, 1),
            e(&a, 2) * e(&c, 0) - e(&a, 0) * e(&c, 2),
            e(&a, 0) * e(&c, 1) - e(&a, 1) * e(&c, 0),
        ],
        2,
    )
}

/// Orientation loss: L1 between predicted and ground-truth orientation vectors.
pub fn orientation_loss(joints: Tensor<4>, gt_joints: Tensor<4>, mask: Tensor<2>) -> Tensor<1> {
    masked_mean((orientation(joints) - orientation(gt_joints)).abs(), mask)
}

/// The local grid of the density loss: `side^3` points spanning `extent` metres, centred on the origin,
/// voxel-centre convention, `[side^3, 3]`.
pub fn density_grid(side: usize, extent: f64, device: &Device) -> Tensor<2> {
    let step = extent / side as f64;
    let mut v = Vec::with_capacity(side * side * side * 3);
    for i in 0..side {
        for j in 0..side {
            for k in 0..side {
                for idx in [i, j, k] {
                    v.push((-extent / 2.0 + (idx as f64 + 0.5) * step) as f32);
                }
            }
        }
    }
    Tensor::from_data(TensorData::new(v, [side * side * side, 3]), device)
}

/// The coordinates of the density cube along each axis: `side` points spanning `extent` metres, centred
/// on the origin, voxel-centre convention, `[side]`. The cube's points ([`density_grid`]) are their
/// product.
pub fn density_axis(side: usize, extent: f64, device: &Device) -> Tensor<1> {
    let step = extent / side as f64;
    let v: Vec<f32> = (0..side)
        .map(|i| (-extent / 2.0 + (i as f64 + 0.5) * step) as f32)
        .collect();
    Tensor::from_data(TensorData::new(v, [side]), device)
}

/// Joint density `[B, K, G]`: at each local grid point `grid` `[G, 3]` around `centre` `[B, K, 3]`, the sum over
/// joints `[B, K, J, 3]` of `exp(-|c - j|^2 / (2 sigma^2))`. Every point against every joint at once
/// (`[B, K, G, J]`); the loss takes [`joint_density_cube`], which gives the same on a cube.
pub fn joint_density(
    joints: Tensor<4>,
    centre: Tensor<3>,
    grid: Tensor<2>,
    sigma: f32,
) -> Tensor<3> {
    let [b, k, nj, _] = joints.dims();
    let g = grid.dims()[0];
    let pts = grid.reshape([1, 1, g, 1, 3]) + centre.reshape([b, k, 1, 1, 3]);
    let d2 = (pts - joints.reshape([b, k, 1, nj, 3]))
        .powi_scalar(2)
        .sum_dim(4); // [B, K, G, J, 1]
    (d2 / (-2.0 * sigma * sigma))
        .exp()
        .sum_dim(3)
        .reshape([b, k, g])
}

/// [`joint_density`] on the cube whose axis coordinates are `axis` `[S]` (see [`density_axis`]), in
/// [`density_grid`]'s order (x slowest) `[B, K, S^3]`. A Gaussian is the product of one per axis, so the
/// density is a sum over joints of outer products of three `[S]` vectors: one batched matrix product,
/// where every point against every joint is `S^3 x J` values per person (3 M for 127 joints and 16
/// points a side).
pub fn joint_density_cube(
    joints: Tensor<4>,
    centre: Tensor<3>,
    axis: Tensor<1>,
    sigma: f32,
) -> Tensor<3> {
    let [b, k, nj, _] = joints.dims();
    let s = axis.dims()[0];
    let rel = joints - centre.reshape([b, k, 1, 3]);
    // Each joint's Gaussian along each axis `[B, K, J, 3, S]`.
    let g = (axis.reshape([1, 1, 1, 1, s]) - rel.reshape([b, k, nj, 3, 1]))
        .powi_scalar(2)
        .div_scalar(-2.0 * sigma * sigma)
        .exp();
    let along = |a: usize| g.clone().narrow(3, a, 1).reshape([b * k, nj, s]);
    let xy = (along(0).reshape([b * k, nj, s, 1]) * along(1).reshape([b * k, nj, 1, s])).reshape([
        b * k,
        nj,
        s * s,
    ]);
    xy.swap_dims(1, 2)
        .matmul(along(2))
        .reshape([b, k, s * s * s])
}

/// 3D joint density loss: MSE between the densities of predicted and ground-truth joints on the cube
/// `axis^3` (see [`density_axis`]) around the ground-truth pelvis.
pub fn density_loss(
    joints: Tensor<4>,
    gt_joints: Tensor<4>,
    gt_pelvis: Tensor<3>,
    axis: Tensor<1>,
    sigma: f32,
    mask: Tensor<2>,
) -> Tensor<1> {
    let p = joint_density_cube(joints, gt_pelvis.clone(), axis.clone(), sigma);
    let t = joint_density_cube(gt_joints, gt_pelvis, axis, sigma);
    masked_mean((p - t).powi_scalar(2), mask)
}

/// 2D heatmap loss of the pose network (stage 1 pre-training, as HRNet's and VoxelPose's joint MSE):
/// the MSE between heatmaps `[B, V, J, H, W]` and their Gaussian targets per joint, weighted by
/// `weight` `[B, V, J]` (1 for a visible joint, 0 otherwise), averaged over `B x V x J`.
pub fn heatmap_loss(pred: Tensor<5>, target: Tensor<5>, weight: Tensor<3>) -> Tensor<1> {
    let [b, v, j, h, w] = pred.dims();
    let per_joint = (pred - target)
        .powi_scalar(2)
        .reshape([b, v, j, h * w])
        .mean_dim(3)
        .reshape([b, v, j]);
    mean_all(per_joint * weight)
}

/// Loss of a facing head (not one of the paper's five): the squared error of the maps `[B, V, 2, H, W]`
/// to their targets, weighted per pixel by `weight` `[B, V, H, W]` (where a person's torso shows) and
/// divided by the weights' sum, so that it is a mean over the supervised pixels whatever their number.
pub fn facing_loss(pred: Tensor<5>, target: Tensor<5>, weight: Tensor<4>) -> Tensor<1> {
    let [b, v, _, h, w] = pred.dims();
    let err = (pred - target)
        .powi_scalar(2)
        .sum_dim(2)
        .reshape([b, v, h, w]);
    sum_all(err * weight.clone()) / sum_all(weight).clamp_min(1e-6)
}

/// Loss of a facing head whose maps are the logits of heading bins `[B, V, N, H, W]`: the cross-entropy
/// to the label distributions `labels` (same shape, summing to 1 over the bins), weighted per pixel by
/// `weight` `[B, V, H, W]` and divided by the weights' sum, as [`facing_loss`].
pub fn facing_bin_loss(logits: Tensor<5>, labels: Tensor<5>, weight: Tensor<4>) -> Tensor<1> {
    let [b, v, _, h, w] = logits.dims();
    let ce = (labels * log_softmax(logits, 2))
        .sum_dim(2)
        .neg()
        .reshape([b, v, h, w]);
    sum_all(ce * weight.clone()) / sum_all(weight).clamp_min(1e-6)
}

/// Gaussian heatmap targets `[J, H, W]` (flat) of one view for joints at network pixels `(u, v)`, on maps of
/// `stride` network pixels per map pixel (map coordinate `(u + 0.5) / stride - 0.5`, as the fusion samples),
/// `exp(-d^2 / (2 sigma^2))` with `sigma` in map pixels, cut at 3 sigma. Joints with `None` stay zero.
pub fn heatmap_target(
    joints: &[Option<[f32; 2]>],
    hw: [usize; 2],
    stride: f32,
    sigma: f32,
) -> Vec<f32> {
    let [h, w] = hw;
    let mut out = vec![0f32; joints.len() * h * w];
    for (ji, p) in joints.iter().enumerate() {
        let Some([u, v]) = *p else { continue };
        let (x, y) = ((u + 0.5) / stride - 0.5, (v + 0.5) / stride - 0.5);
        let r = 3.0 * sigma;
        let (x0, x1) = ((x - r).floor().max(0.0), (x + r).ceil().min(w as f32 - 1.0));
        let (y0, y1) = ((y - r).floor().max(0.0), (y + r).ceil().min(h as f32 - 1.0));
        if x0 > x1 || y0 > y1 {
            continue;
        }
        for iy in y0 as usize..=y1 as usize {
            for ix in x0 as usize..=x1 as usize {
                let d2 = (ix as f32 - x).powi(2) + (iy as f32 - y).powi(2);
                out[(ji * h + iy) * w + ix] = (-d2 / (2.0 * sigma * sigma)).exp();
            }
        }
    }
    out
}

/// Where the 3D mesh term and the joint-density term compare predicted and ground-truth points.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MeshFrame {
    /// In the world, as the paper: a body's translation and heading errors enter every one of its points,
    /// so that early in training they outweigh, and steer, what the terms say about its pose.
    #[default]
    World,
    /// Centred on each body's pelvis (the prediction on its own, the ground truth on its own): the
    /// translation error is taken out, the heading error stays; the pelvis is supervised by the
    /// `translation` term.
    Pelvis,
    /// In each body's own frame ([`to_body_frame`]: the prediction in its own pelvis and global rotation,
    /// the ground truth in its own), so that these terms see pose and shape alone; the pelvis is
    /// supervised by the `translation` term, the global rotation by the parameter and orientation terms.
    Body,
}

/// Loss weights and density-loss settings (the `[loss]` table of a training config). A weight of 0 switches
/// its term off (ablations). Defaults are the paper's.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LossWeights {
    pub detection: f32,
    pub parameters: f32,
    /// Weight of the 3D part of the mesh loss (joints and vertices).
    pub mesh_3d: f32,
    /// Weight of the 2D part (mean over views).
    pub mesh_2d: f32,
    pub orientation: f32,
    pub density: f32,
    /// Gaussian width of the joint densities (metres).
    pub density_sigma: f32,
    /// Points per side of the local density grid and its extent (metres) around the GT pelvis.
    pub density_grid: usize,
    pub density_extent: f64,
    /// Weight of the offset L1 inside the detection loss (the paper: 1).
    pub detection_offset: f32,
    /// Weight of [`detection_positive_loss`] inside the detection loss (the paper: 0, a plain volume MSE).
    pub detection_positive: f32,
    /// Width (metres) of the Gaussian root target (0.2, the reference's). On a coarse grid it covers
    /// about one voxel per person (0.25 m voxels: the neighbours get 0.46); a wider target gives the
    /// detector more voxels to learn from, and the sub-voxel offsets still place the root.
    pub detection_sigma: f64,
    /// Weight of [`body_pose_l2_loss`], added to the parameter term (the paper: 0, the L1 alone).
    pub parameters_body_l2: f32,
    /// Weight of the L1 between the body joints' offsets from the pelvis a decoder with
    /// `joint_offsets` gives and the true ones (not in the paper, which regresses rotations alone).
    pub joint_offsets: f32,
    /// Weight of the 2D heatmap loss of stage 1 (the pose network's pre-training; not one of the five).
    pub heatmap_2d: f32,
    /// Weight of the 2D heatmap loss in stage 2 (the paper: 0, stage 1 only). Without it HRNet, whose
    /// features the facing head shares, is trained in stage 2 by the detection term alone.
    pub heatmap_2d_stage2: f32,
    /// Width of the 2D heatmap targets in heatmap pixels (HRNet: 2).
    pub heatmap_sigma: f32,
    /// Weight, inside the 2D heatmap term, of the joint maps' squared error weighted by their Gaussian
    /// targets ([`detection_positive_loss`] on the maps; HRNet: 0, a plain MSE). The plain MSE averages
    /// over every pixel, where the few pixels at joints weigh little beside the empty image.
    pub heatmap_2d_positive: f32,
    /// Weight of the 2D joint heatmap term on the ViT's reduced features, read by a model's
    /// `vit_heatmaps` head in both stages (the paper: 0; its ViT comes pretrained on 2D pose).
    pub vit_heatmap: f32,
    /// Width of those targets in feature-map pixels (one pixel is a ViT patch).
    pub vit_heatmap_sigma: f32,
    /// Weight of [`facing_loss`] in both stages, for a model with a facing head (not one of the five).
    pub facing: f32,
    /// The frame of the 3D mesh and density terms (the paper: the world).
    pub mesh_frame: MeshFrame,
    /// Weight of [`translation_loss`], added to the mesh term (the paper: 0; the world-frame mesh term
    /// carries the translation there).
    pub translation: f32,
    /// The mesh, 2D mesh and density terms train the body-pose rotations too (the paper). false leaves
    /// those rotations to the parameter term (the terms see them detached).
    pub mesh_pose: bool,
}

impl Default for LossWeights {
    fn default() -> Self {
        LossWeights {
            detection: 1.0,
            parameters: 10.0,
            mesh_3d: 100.0,
            mesh_2d: 1.0,
            orientation: 5.0,
            density: 1.0,
            density_sigma: 0.1,
            density_grid: 16,
            density_extent: 2.2,
            detection_offset: 1.0,
            detection_positive: 0.0,
            detection_sigma: 0.2,
            parameters_body_l2: 0.0,
            joint_offsets: 0.0,
            heatmap_2d: 1.0,
            heatmap_2d_stage2: 0.0,
            heatmap_sigma: 2.0,
            heatmap_2d_positive: 0.0,
            vit_heatmap: 0.0,
            vit_heatmap_sigma: 1.0,
            facing: 0.1,
            mesh_frame: MeshFrame::World,
            translation: 0.0,
            mesh_pose: true,
        }
    }
}

/// Most points per side of the density loss's cube (the default is 16): each person's density holds
/// side^3 values, and side^2 per joint on the way.
pub const MAX_DENSITY_GRID: usize = 64;
/// Largest loss weight: the paper's are 1 to 100; far larger ones only overflow the loss.
pub const MAX_WEIGHT: f32 = 1e6;
/// Largest width of a Gaussian target in metres (a person is about 2 m tall), and of the density
/// loss's cube.
pub const MAX_WIDTH_M: f64 = 10.0;
pub const MAX_EXTENT_M: f64 = 100.0;
/// Largest width of a 2D heatmap target, in map pixels.
pub const MAX_WIDTH_PX: f64 = 256.0;

impl LossWeights {
    /// Check values; errors name the key and the value.
    pub fn validate(&self) -> Result<(), String> {
        for (k, v) in [
            ("detection", self.detection),
            ("parameters", self.parameters),
            ("parameters_body_l2", self.parameters_body_l2),
            ("joint_offsets", self.joint_offsets),
            ("mesh_3d", self.mesh_3d),
            ("mesh_2d", self.mesh_2d),
            ("orientation", self.orientation),
            ("density", self.density),
            ("heatmap_2d", self.heatmap_2d),
            ("heatmap_2d_stage2", self.heatmap_2d_stage2),
            ("heatmap_2d_positive", self.heatmap_2d_positive),
            ("vit_heatmap", self.vit_heatmap),
            ("detection_offset", self.detection_offset),
            ("detection_positive", self.detection_positive),
            ("facing", self.facing),
            ("translation", self.translation),
        ] {
            if !(0.0..=MAX_WEIGHT).contains(&v) {
                return Err(format!(
                    "loss.{k} = {v}: a weight must be from 0 to {MAX_WEIGHT}"
                ));
            }
        }
        for (k, v, most, unit) in [
            ("density_sigma", self.density_sigma as f64, MAX_WIDTH_M, "m"),
            ("detection_sigma", self.detection_sigma, MAX_WIDTH_M, "m"),
            ("density_extent", self.density_extent, MAX_EXTENT_M, "m"),
            (
                "heatmap_sigma",
                self.heatmap_sigma as f64,
                MAX_WIDTH_PX,
                "pixels",
            ),
            (
                "vit_heatmap_sigma",
                self.vit_heatmap_sigma as f64,
                MAX_WIDTH_PX,
                "pixels",
            ),
        ] {
            if !(v > 0.0 && v <= most) {
                return Err(format!(
                    "loss.{k} = {v}: must be positive and at most {most} {unit}"
                ));
            }
        }
        if self.density_grid == 0 || self.density_grid > MAX_DENSITY_GRID {
            return Err(format!(
                "loss.density_grid = {}: expected 1 to {MAX_DENSITY_GRID} points a side",
                self.density_grid
            ));
        }
        Ok(())
    }
}

/// The weighted terms of one step, each already multiplied by its weight (0-weight terms are skipped and
/// reported as `None`), and their sum.
#[derive(Debug, Clone, Default)]
pub struct LossTerms {
    pub detection: Option<Tensor<1>>,
    pub parameters: Option<Tensor<1>>,
    pub mesh: Option<Tensor<1>>,
    pub orientation: Option<Tensor<1>>,
    pub density: Option<Tensor<1>>,
    /// Stage 1's 2D heatmap term (in stage 2 where `heatmap_2d_stage2` asks for it).
    pub heatmap_2d: Option<Tensor<1>>,
    /// The facing head's term, for a model with one.
    pub facing: Option<Tensor<1>>,
    /// The 2D joint heatmap term on the ViT's features, for a model with a `vit_heatmaps` head.
    pub vit_heatmap: Option<Tensor<1>>,
    /// The body joints' offsets from the pelvis, for a decoder that gives them (`joint_offsets`).
    pub joint_offsets: Option<Tensor<1>>,
}

impl LossTerms {
    /// The total `L_D + w_P L_P + L_mesh + w_O L_O + w_den L_denj3d` and the two auxiliary terms, summed
    /// in the order of [`LossTerms::named`].
    pub fn total(&self) -> Option<Tensor<1>> {
        (self.named().into_iter().map(|(_, t)| t)).reduce(|a, b| a + b)
    }

    /// (name, value) of every active term, for logs.
    pub fn named(&self) -> Vec<(&'static str, Tensor<1>)> {
        [
            ("detection", &self.detection),
            ("parameters", &self.parameters),
            ("mesh", &self.mesh),
            ("orientation", &self.orientation),
            ("density", &self.density),
            ("heatmap_2d", &self.heatmap_2d),
            ("facing", &self.facing),
            ("vit_heatmap", &self.vit_heatmap),
            ("joint_offsets", &self.joint_offsets),
        ]
        .into_iter()
        .filter_map(|(n, t)| t.clone().map(|t| (n, t)))
        .collect()
    }
}
