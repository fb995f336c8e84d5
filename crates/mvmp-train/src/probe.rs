//! A linear probe of the model's volumes: how much of each person's body pose a ridge regression reads
//! from a volume sampled on a lattice round the person's true root, turned with their true heading
//! (docs/architecture.md, The image features go unread). The pose is the 21 body joints relative to
//! the pelvis, in the person's own frame (x ahead, y to the left, z up). A volume that carries the
//! pose lets the probe predict it on scenes it did not fit far better than the training mean does; one
//! that does not leaves the probe at the mean whatever a decoder could learn from it.
use std::path::Path;

use burn::data::dataloader::batcher::Batcher;
use burn::tensor::{Bool, Device, Tensor, TensorData};
use nalgebra::DMatrix;

use mvmp_data::dataset::FrameDataset;
use mvmp_data::loader::{FrameBatch, FrameBatcher, PersonGt, Split, ViewChoice};
use mvmp_decoder::{height_features, lattice_offsets, sample_turned};
use mvmp_fusion::Root;
use mvmp_model::facing::facing_readout;
use mvmp_model::{Detection, MvmpHmr, RigGrids};

use crate::TrainError;
use crate::keypoints::keypoint_errors;
use crate::ridge::{Ridge, sse};
use crate::step::{batch_grids, joint_heading, truth_joint_volume};

/// Body joints after the pelvis (SMPL-X order) whose offsets make up the probed pose.
const POSE_JOINTS: std::ops::Range<usize> = 1..22;
/// Gaussian bumps of the root height among the height features (the decoder's own encoding).
const HEIGHT_BUMPS: usize = 8;
/// Metres from a person's true root within which the nearest detected root is theirs.
const OWN_ROOT_GATE: f64 = 0.5;

/// Where the volumes are sampled and on what.
#[derive(Debug, Clone)]
pub struct ProbeOptions {
    /// Lattice points per axis (x ahead, y left, z up), centred on the root.
    pub lattice: [usize; 3],
    /// Metres from the lattice's first point to its last per axis.
    pub span: [f64; 3],
    /// Cameras per frame (the first ones of each rig).
    pub views: usize,
    /// Frames read per split at most, spread evenly over it (0: all).
    pub max_frames: usize,
    /// Width of the ground-truth heatmaps' Gaussians, map pixels (the training's `heatmap_sigma`).
    pub sigma: f32,
}

/// What the probe reads of one person.
#[derive(Debug, Clone, Default)]
pub struct ProbedPerson {
    pub scene: String,
    /// The image-feature volume on the lattice, `L * Cf`.
    pub volume: Vec<f32>,
    /// The joint heatmap volume on the lattice, `L * J`.
    pub heatmaps: Vec<f32>,
    /// Each heatmap joint's centroid over the lattice in the person's frame, metres, `J * 3`: the
    /// lattice offsets weighted by the squared non-negative heatmap there (zero where it has none).
    pub centroids: Vec<f32>,
    /// The heatmap volume fused, as the model fuses its own, from the heatmap loss's targets (Gaussians
    /// at the visible ground-truth joints) on the lattice, `L * J`: what perfect 2D maps would give.
    pub true_heatmaps: Vec<f32>,
    /// Each heatmap joint's centroid over the lattice in `true_heatmaps`, as `centroids`.
    pub true_centroids: Vec<f32>,
    /// `heatmaps` and `true_heatmaps` with the lattice where the decoder puts it: round the model's own
    /// root (the detection nearest the person within [`OWN_ROOT_GATE`], the true root where none is)
    /// turned with the facing head's heading there (the true heading for a model without one).
    pub own_heatmaps: Vec<f32>,
    pub own_true_heatmaps: Vec<f32>,
    /// `true_heatmaps` at the model's own root turned with the true heading, and at the true root turned
    /// with the model's heading: which of the two placements costs what.
    pub own_root_true_heatmaps: Vec<f32>,
    pub own_heading_true_heatmaps: Vec<f32>,
    /// The height features of the model's own root.
    pub own_height: Vec<f32>,
    /// The root height and its Gaussian bumps.
    pub height: Vec<f32>,
    /// The body joints' offsets from the pelvis in the person's frame, metres, `21 * 3`.
    pub pose: Vec<f64>,
    /// For each view and heatmap joint the person shows, how far (network pixels) HRNet's map puts its
    /// peak from the true 2D joint ([`keypoint_errors`]).
    pub keypoint_px: Vec<f32>,
}

/// The people of a split of an MVMP-HMR dataset, each as [`ProbedPerson`]. People whose heading the
/// annotation does not give (hips and shoulders not annotated) are left out.
pub fn collect(
    model: &MvmpHmr,
    data: &Path,
    split: Split,
    opts: &ProbeOptions,
    device: &Device,
    mut progress: impl FnMut(usize, usize),
) -> Result<Vec<ProbedPerson>, TrainError> {
    let cfg = &model.config;
    let ds = FrameDataset::open(
        data,
        split,
        ViewChoice::Fixed((0..opts.views).collect()),
        cfg.image_size,
    )?;
    let n = match opts.max_frames {
        0 => ds.len(),
        m => m.min(ds.len()),
    };
    let lattice = lattice_offsets(opts.lattice, opts.span);
    let batcher = FrameBatcher::default();
    let mut out = Vec::new();
    for i in 0..n {
        // Spread over the split, so that a few frames still come from several scenes.
        let batch = batcher.batch(vec![ds.load(i * ds.len() / n)?], device);
        progress(i, n);
        out.extend(probe_frame(model, &batch, &lattice, opts.sigma, device));
    }
    Ok(out)
}

/// The people of a one-frame batch whose heading the annotation gives, with that heading.
pub(crate) fn headed_people(batch: &FrameBatch) -> Vec<(&PersonGt, [f64; 2])> {
    (batch.people[0].iter())
        .filter(|p| p.joints_3d.len() >= POSE_JOINTS.end)
        .filter_map(|p| {
            let joints: Vec<[f64; 3]> = p.joints_3d.iter().map(|j| j.map(f64::from)).collect();
            Some((p, joint_heading(&joints, &batch.covers[0])?))
        })
        .collect()
}

/// What the probe reads of each person of a one-frame batch.
fn probe_frame(
    model: &MvmpHmr,
    batch: &FrameBatch,
    lattice: &[[f32; 3]],
    sigma: f32,
    device: &Device,
) -> Vec<ProbedPerson> {
    let cfg = &model.config;
    let primary = cfg.primary_joint.joint();
    let people = headed_people(batch);
    let k = people.len();
    if k == 0 {
        return vec![];
    }
    let rows = |v: Vec<f32>, w: usize| Tensor::<1>::from_data(TensorData::new(v, [k * w]), device);
    let roots = people.iter().flat_map(|(p, _)| p.joints_3d[primary]);
    let roots = rows(roots.collect(), 3).reshape([1, k, 3]);
    let heads = people.iter().flat_map(|(_, h)| h.map(|x| x as f32));
    let heads = rows(heads.collect(), 2).reshape([1, k, 2]);
    let grids = batch_grids(cfg, batch, device);
    let volume = model.feature_volume(batch.images.clone(), &grids);
    let (det, hvol) = model.detect_with_volume(batch.images.clone(), &grids);
    let stride = cfg.heatmap_stride() as f32;
    let tvol = truth_joint_volume(cfg, batch, &grids, sigma, device);
    let place = |v: Tensor<5>, roots: &Tensor<3>, heads: &Tensor<3>| {
        host(sample_turned(
            v,
            roots.clone(),
            heads.clone(),
            lattice,
            &cfg.grid,
        ))
    };
    let at = |v: Tensor<5>| place(v, &roots, &heads);
    let (own_roots, own_heads) = own_placement(model, &det, &grids, &people, device);
    let oh = place(hvol.clone(), &own_roots, &own_heads);
    let ot = place(tvol.clone(), &own_roots, &own_heads);
    let ot_root = place(tvol.clone(), &own_roots, &heads);
    let ot_heading = place(tvol.clone(), &roots, &own_heads);
    let own_height = heights(own_roots.clone());
    let (fv, fh, ft) = (at(volume), at(hvol), at(tvol));
    let height = heights(roots.clone());
    let [_, _, _, mh, mw] = det.heatmaps.dims();
    let maps = host(det.heatmaps.clone());
    let keypoints = |p: &PersonGt| keypoint_errors(&maps, [mh, mw], p, &cfg.heatmap_joints, stride);
    let (cv, ch, hw) = (fv.len() / k, fh.len() / k, HEIGHT_BUMPS + 1);
    // Person j's part of values of `w` per person.
    let part = |v: &[f32], j: usize, w: usize| v[j * w..(j + 1) * w].to_vec();
    (people.iter().enumerate())
        .map(|(j, (p, h))| ProbedPerson {
            scene: batch.names[0].0.clone(),
            volume: part(&fv, j, cv),
            centroids: centroids(&part(&fh, j, ch), lattice),
            heatmaps: part(&fh, j, ch),
            true_centroids: centroids(&part(&ft, j, ch), lattice),
            true_heatmaps: part(&ft, j, ch),
            own_heatmaps: part(&oh, j, ch),
            own_true_heatmaps: part(&ot, j, ch),
            own_root_true_heatmaps: part(&ot_root, j, ch),
            own_heading_true_heatmaps: part(&ot_heading, j, ch),
            own_height: part(&own_height, j, hw),
            height: part(&height, j, hw),
            pose: body_frame_pose(&p.joints_3d, *h),
            keypoint_px: keypoints(p),
        })
        .collect()
}

/// Where the decoder would read each person: the model's detected root nearest their true one (within
/// [`OWN_ROOT_GATE`]; else the true root) `[1, K, 3]`, and the facing head's heading there `[1, K, 2]`
/// (the true heading without a facing head).
fn own_placement(
    model: &MvmpHmr,
    det: &Detection,
    grids: &[RigGrids],
    people: &[(&PersonGt, [f64; 2])],
    device: &Device,
) -> (Tensor<3>, Tensor<3>) {
    let cfg = &model.config;
    let primary = cfg.primary_joint.joint();
    let found = model.detect_roots(det.likelihood.clone(), det.offset.clone());
    let k = people.len();
    let own: Vec<f32> = (people.iter())
        .flat_map(|(p, _)| {
            let truth = p.joints_3d[primary].map(f64::from);
            let dist = |r: &Root| {
                (0..3)
                    .map(|a| (r.position[a] - truth[a]).powi(2))
                    .sum::<f64>()
            };
            let nearest = found[0].iter().min_by(|a, b| dist(a).total_cmp(&dist(b)));
            match nearest.filter(|r| dist(r).sqrt() <= OWN_ROOT_GATE) {
                Some(r) => r.position,
                None => truth,
            }
            .map(|x| x as f32)
        })
        .collect();
    let roots = Tensor::<3>::from_data(TensorData::new(own, [1, k, 3]), device);
    let heads = match &det.facing {
        Some(f) => {
            let present =
                Tensor::<2, Bool>::from_data(TensorData::new(vec![true; k], [1, k]), device);
            facing_readout(f.clone(), grids, &cfg.grid, roots.clone(), present)
        }
        None => {
            let h = people
                .iter()
                .flat_map(|(_, h)| h.map(|x| x as f32))
                .collect();
            Tensor::from_data(TensorData::new(h, [1, k, 2]), device)
        }
    };
    (roots, heads)
}

/// Each root's height and its Gaussian bumps, `K * (1 + HEIGHT_BUMPS)`.
fn heights(roots: Tensor<3>) -> Vec<f32> {
    let z = host(roots.clone().narrow(2, 2, 1));
    let bumps = host(height_features(roots, HEIGHT_BUMPS));
    (z.iter().enumerate())
        .flat_map(|(j, &h)| {
            std::iter::once(h).chain(
                bumps[j * HEIGHT_BUMPS..(j + 1) * HEIGHT_BUMPS]
                    .iter()
                    .copied(),
            )
        })
        .collect()
}

/// A float tensor's values on the host.
pub(crate) fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data_as::<f32>()
        .try_into_vec::<f32>()
        .unwrap_or_default()
}

/// Each channel's centroid over the lattice from samples `[L][J]` (lattice point slowest).
fn centroids(samples: &[f32], lattice: &[[f32; 3]]) -> Vec<f32> {
    let j = samples.len() / lattice.len().max(1);
    (0..j)
        .flat_map(|c| {
            let (mut sum, mut w) = ([0.0f32; 3], 0.0f32);
            for (l, o) in lattice.iter().enumerate() {
                let x = samples[l * j + c].max(0.0).powi(2);
                w += x;
                (0..3).for_each(|a| sum[a] += x * o[a]);
            }
            sum.map(|v| if w > 0.0 { v / w } else { 0.0 })
        })
        .collect()
}

/// The body joints' offsets from the pelvis, turned into the frame whose x axis is the heading.
fn body_frame_pose(joints: &[[f32; 3]], heading: [f64; 2]) -> Vec<f64> {
    let joints: Vec<[f64; 3]> = joints.iter().map(|j| j.map(f64::from)).collect();
    body_frame_offsets(&joints, heading)
}

/// The probed pose of joints `[J >= 22][3]` (world, z up) seen with the heading `[hx, hy]`: the 21 body
/// joints' offsets from the pelvis in the frame whose x axis is the heading, metres, `21 * 3`.
pub fn body_frame_offsets(joints: &[[f64; 3]], [hx, hy]: [f64; 2]) -> Vec<f64> {
    let pelvis = joints[0];
    POSE_JOINTS
        .flat_map(|j| {
            let d: [f64; 3] = std::array::from_fn(|a| joints[j][a] - pelvis[a]);
            // Ahead (hx, hy), left (-hy, hx).
            [d[0] * hx + d[1] * hy, -d[0] * hy + d[1] * hx, d[2]]
        })
        .collect()
}

/// How well one set of features predicts the pose on the held-out people.
#[derive(Debug, Clone, serde::Serialize)]
pub struct ProbeScore {
    pub features: String,
    pub dims: usize,
    /// The ridge strength chosen on the last fifth of the training scenes (at least one; relative, see
    /// `RIDGE`).
    pub ridge: f64,
    /// 1 - SSE / SST of the held-out pose, SST about the training mean.
    pub r2: f64,
    /// Mean distance between predicted and true joint offsets, mm.
    pub joint_mm: f64,
}

/// Fit a ridge regression from `features` of the `train` people to their pose, choosing its strength on
/// the last fifth of the training scenes (at least one), and score it on `test`.
pub fn score(
    name: &str,
    train: &[ProbedPerson],
    test: &[ProbedPerson],
    features: impl Fn(&ProbedPerson) -> Vec<f32>,
) -> Result<ProbeScore, String> {
    let scenes = scene_count(train);
    if scenes < 2 || test.is_empty() {
        return Err(format!(
            "{scenes} training scenes and {} held-out people: the probe needs at least 2 scenes (it \
             chooses its ridge on the last fifth of them) and 1 person",
            test.len()
        ));
    }
    let (x, y) = (matrix(train, &features), targets(train));
    let (xt, yt) = (matrix(test, &features), targets(test));
    let cut = fold_cut(train);
    let (fit_x, fit_y) = (x.rows(0, cut).into_owned(), y.rows(0, cut).into_owned());
    let (val_x, val_y) = (
        x.rows(cut, x.nrows() - cut).into_owned(),
        y.rows(cut, y.nrows() - cut).into_owned(),
    );
    let best = Ridge::fit(&fit_x, &fit_y).choose(&val_x, &val_y);
    let pred = Ridge::fit(&x, &y).predict(&xt, best);
    let mean = y.row_mean();
    let sst: f64 = (0..yt.nrows())
        .map(|i| (yt.row(i) - &mean).norm_squared())
        .sum();
    Ok(ProbeScore {
        features: name.to_string(),
        dims: x.ncols(),
        ridge: best,
        r2: 1.0 - sse(&pred, &yt) / sst.max(f64::MIN_POSITIVE),
        joint_mm: joint_mm(&pred, &yt),
    })
}

/// The error of predicting every held-out person's pose as the training mean, mm.
pub fn mean_pose_mm(train: &[ProbedPerson], test: &[ProbedPerson]) -> f64 {
    let mean = targets(train).row_mean();
    let yt = targets(test);
    let pred = DMatrix::from_fn(yt.nrows(), yt.ncols(), |_, c| mean[c]);
    joint_mm(&pred, &yt)
}

fn scene_names(people: &[ProbedPerson]) -> Vec<&str> {
    let mut scenes: Vec<&str> = people.iter().map(|p| p.scene.as_str()).collect();
    scenes.dedup();
    scenes
}

/// How many scenes the people come from.
pub fn scene_count(people: &[ProbedPerson]) -> usize {
    scene_names(people).len()
}

/// The index of the first person of the last fifth of the scenes (people are in scene order).
fn fold_cut(people: &[ProbedPerson]) -> usize {
    let scenes = scene_names(people);
    let keep = (scenes.len() * 4 / 5).max(1);
    let first_out = scenes.get(keep).copied();
    (people.iter())
        .position(|p| Some(p.scene.as_str()) == first_out)
        .unwrap_or(people.len() * 4 / 5)
        .clamp(1, people.len() - 1)
}

fn matrix(people: &[ProbedPerson], f: &impl Fn(&ProbedPerson) -> Vec<f32>) -> DMatrix<f64> {
    let rows: Vec<Vec<f32>> = people.iter().map(f).collect();
    let d = rows.first().map_or(0, Vec::len);
    DMatrix::from_fn(rows.len(), d, |i, j| rows[i][j] as f64)
}

fn targets(people: &[ProbedPerson]) -> DMatrix<f64> {
    let d = people.first().map_or(0, |p| p.pose.len());
    DMatrix::from_fn(people.len(), d, |i, j| people[i].pose[j])
}

/// The mean distance (mm) between predicted and true probed poses (rows of `21 * 3` metres), the
/// probe's own error.
pub fn pose_mm(pred: &[Vec<f64>], truth: &[Vec<f64>]) -> f64 {
    let rows = |v: &[Vec<f64>]| {
        let d = v.first().map_or(0, Vec::len);
        DMatrix::from_fn(v.len(), d, |i, j| v[i][j])
    };
    joint_mm(&rows(pred), &rows(truth))
}

fn joint_mm(pred: &DMatrix<f64>, truth: &DMatrix<f64>) -> f64 {
    let joints = truth.ncols() / 3;
    let mut sum = 0.0;
    for i in 0..truth.nrows() {
        for j in 0..joints {
            let d = pred.fixed_view::<1, 3>(i, 3 * j) - truth.fixed_view::<1, 3>(i, 3 * j);
            sum += d.norm();
        }
    }
    1000.0 * sum / (truth.nrows() * joints).max(1) as f64
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two lattice points, two channels: weights are the squared non-negative samples (1 and 9, then
    /// 0 and 4 with the negative clipped), and a channel with no weight sits at the root.
    #[test]
    fn centroids_weight_the_lattice_by_the_squared_samples() {
        let lattice = [[0.0, 0.0, -0.5], [1.0, 2.0, 0.5]];
        let c = centroids(&[1.0, -5.0, 3.0, 2.0], &lattice);
        let want = [0.9, 1.8, 0.4, 1.0, 2.0, 0.5];
        for (a, b) in c.iter().zip(want) {
            assert!((a - b).abs() < 1e-6, "{c:?}");
        }
        assert_eq!(centroids(&[0.0, -1.0], &lattice[..1]), vec![0.0; 6]);
    }

    /// A person at (1, 1, 0) facing +y: a joint 1 m to their +y is 1 m ahead, one at +x is 1 m to their
    /// right (-y in their frame); the error is the mean joint distance in mm.
    #[test]
    fn body_frame_offsets_turn_with_the_heading_and_pose_mm_averages_joints() {
        let mut joints = vec![[1.0, 1.0, 0.0]; 22];
        joints[1] = [1.0, 2.0, 0.0];
        joints[2] = [2.0, 1.0, 0.5];
        let o = body_frame_offsets(&joints, [0.0, 1.0]);
        assert_eq!(o.len(), 63);
        let want = [1.0, 0.0, 0.0, 0.0, -1.0, 0.5];
        for (a, b) in o[..6].iter().zip(want) {
            assert!((a - b).abs() < 1e-12, "{o:?}");
        }
        assert!(o[6..].iter().all(|&x| x == 0.0));
        // One joint 5 cm off (3 and 4 cm along two axes), the other 20 exact.
        let mut other = o.clone();
        other[0] += 0.03;
        other[1] += 0.04;
        let mm = pose_mm(&[other], &[o]);
        assert!((mm - 50.0 / 21.0).abs() < 1e-9, "{mm}");
    }

    /// The held-back part starts at the first person of the last fifth of the scenes (at least one),
    /// however many people each scene has.
    #[test]
    fn the_ridge_is_chosen_on_the_last_scenes() {
        let people = |sizes: &[usize]| -> Vec<ProbedPerson> {
            (sizes.iter().enumerate())
                .flat_map(|(s, &n)| {
                    (0..n).map(move |_| ProbedPerson {
                        scene: format!("scene_{s:03}"),
                        ..Default::default()
                    })
                })
                .collect()
        };
        // 10 scenes: the last 2 are held back.
        assert_eq!(fold_cut(&people(&[1, 2, 3, 4, 5, 6, 7, 8, 9, 10])), 36);
        // 2 scenes: the second.
        assert_eq!(fold_cut(&people(&[7, 1])), 7);
        assert_eq!(scene_count(&people(&[3, 1, 4])), 3);
    }
}
