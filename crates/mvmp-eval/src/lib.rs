//! Matching and metrics for multi-person mesh recovery, and the drivers that score a predictor on a
//! dataset with them ([`drivers`]).
//!
//! Protocol: predictions are matched one-to-one to ground-truth people by the Hungarian algorithm on
//! pelvis distance, and a pair counts only within the gate (0.5 m by default). On matched pairs: MPJPE
//! (mean joint L2, world, millimetres, no alignment), PVE (mean vertex L2, world, mm) and PA-PVE (after a
//! similarity Procrustes alignment of the vertices). Detection: AP at MPJPE thresholds 25..150 mm
//! (VoxelPose's protocol: predictions by descending score, each to its nearest-by-MPJPE ground truth, a true
//! positive when below the threshold and that person is not yet claimed; interpolated precision) and the
//! recall at 500 mm (distinct people reached within 500 mm).
/// The joint sets of joint-annotated datasets (defined with the SMPL-X joint names).
pub use mvmp_smplx::joint_sets;

pub mod drivers;
pub mod spread;
pub mod truth_parts;

use std::collections::BTreeMap;

use nalgebra::Vector3;
use pathfinding::prelude::{Matrix, kuhn_munkres_min};
use serde::{Deserialize, Serialize};

use mvmp_geom::similarity_procrustes;

/// Default pelvis-distance gate of the matching (metres).
pub const DEFAULT_GATE: f64 = 0.5;
/// AP thresholds (mm).
pub const AP_THRESHOLDS: [f64; 6] = [25.0, 50.0, 75.0, 100.0, 125.0, 150.0];

/// One person: world joints (metres; index 0 is the pelvis) and optionally vertices.
#[derive(Debug, Clone, Default)]
pub struct PersonPose {
    pub joints: Vec<[f64; 3]>,
    pub vertices: Option<Vec<[f64; 3]>>,
    /// Detection score (predictions only).
    pub score: f64,
    /// Which joints are annotated (ground truth of datasets with per-joint validity); `None` = all.
    pub valid: Option<Vec<bool>>,
}

/// Mean joint error (mm) of a prediction against a ground-truth person over its annotated joints.
pub fn joint_error_mm(pred: &PersonPose, gt: &PersonPose) -> f64 {
    let (a, b) = annotated_joints(pred, gt);
    mean_error_mm(&a, &b)
}

/// The (predicted, ground-truth) joints of the joints the ground truth annotates.
fn annotated_joints(pred: &PersonPose, gt: &PersonPose) -> (Vec<[f64; 3]>, Vec<[f64; 3]>) {
    pred.joints
        .iter()
        .zip(&gt.joints)
        .enumerate()
        .filter(|(j, _)| gt.valid.as_ref().is_none_or(|v| v[*j]))
        .map(|(_, (p, g))| (*p, *g))
        .unzip()
}

/// How a matched pair's joint error divides (mm): the root's distance (where the person is), the mean
/// joint error with each person's root moved to the origin (root-relative MPJPE: orientation and pose),
/// and after a similarity Procrustes alignment of the joints (PA-MPJPE: pose alone). A model that has
/// learned where people are but not how they stand has a small first figure and a PA-MPJPE near the
/// mean pose's. `None` when the ground truth does not annotate the root.
pub fn error_parts_mm(pred: &PersonPose, gt: &PersonPose, root: usize) -> Option<[f64; 3]> {
    if gt.valid.as_ref().is_some_and(|v| !v[root]) {
        return None;
    }
    let (pr, gr) = (pred.joints[root], gt.joints[root]);
    let (a, b) = annotated_joints(pred, gt);
    let centre = |x: &[[f64; 3]], r: [f64; 3]| -> Vec<[f64; 3]> {
        x.iter()
            .map(|p| [p[0] - r[0], p[1] - r[1], p[2] - r[2]])
            .collect()
    };
    let relative = mean_error_mm(&centre(&a, pr), &centre(&b, gr));
    let pa = pa_error_mm(&a, &b)?;
    Some([dist(pr, gr) * 1000.0, relative, pa])
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

/// Mean L2 distance between corresponding points, in millimetres.
pub fn mean_error_mm(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
    let n = a.len().min(b.len()).max(1);
    a.iter().zip(b).map(|(p, q)| dist(*p, *q)).sum::<f64>() / n as f64 * 1000.0
}

/// Mean L2 after aligning `pred` to `gt` with the best similarity (scale, rotation, translation), mm.
pub fn pa_error_mm(pred: &[[f64; 3]], gt: &[[f64; 3]]) -> Option<f64> {
    let p: Vec<Vector3<f64>> = pred.iter().map(|x| Vector3::from(*x)).collect();
    let g: Vec<Vector3<f64>> = gt.iter().map(|x| Vector3::from(*x)).collect();
    let s = similarity_procrustes(&p, &g).ok()?;
    let aligned: Vec<[f64; 3]> = p.iter().map(|x| s.apply(x).into()).collect();
    Some(mean_error_mm(&aligned, gt))
}

/// Hungarian matching on pelvis distance; pairs farther than `gate` metres are dropped.
/// Returns `(prediction, ground truth)` index pairs.
pub fn match_people(pred: &[[f64; 3]], gt: &[[f64; 3]], gate: f64) -> Vec<(usize, usize)> {
    if pred.is_empty() || gt.is_empty() {
        return Vec::new();
    }
    // Integer costs (micrometres) for the assignment; rows must not outnumber columns.
    let transpose = pred.len() > gt.len();
    let (rows, cols) = if transpose { (gt, pred) } else { (pred, gt) };
    let cost: Vec<i64> = rows
        .iter()
        .flat_map(|r| {
            cols.iter()
                .map(move |c| (dist(*r, *c) * 1e6).round() as i64)
        })
        .collect();
    let m = Matrix::from_vec(rows.len(), cols.len(), cost).expect("sizes agree");
    let (_, assign) = kuhn_munkres_min(&m);
    assign
        .into_iter()
        .enumerate()
        .map(|(r, c)| if transpose { (c, r) } else { (r, c) })
        .filter(|&(p, g)| dist(pred[p], gt[g]) <= gate)
        .collect()
}

/// Figures of a set of frames.
#[derive(Debug, Clone, Serialize, Deserialize, PartialEq)]
pub struct Metrics {
    pub mpjpe_mm: Option<f64>,
    pub pve_mm: Option<f64>,
    pub pa_pve_mm: Option<f64>,
    /// The parts of the joint error ([`error_parts_mm`]): root distance, root-relative MPJPE, PA-MPJPE.
    pub root_mm: Option<f64>,
    pub rr_mpjpe_mm: Option<f64>,
    pub pa_mpjpe_mm: Option<f64>,
    pub recall_500: Option<f64>,
    /// AP per threshold, keyed by the threshold in mm ("25", "50", ...).
    pub ap: BTreeMap<String, f64>,
    pub matched: usize,
    pub ground_truth: usize,
    pub predictions: usize,
}

#[derive(Debug, Default, Clone)]
struct Acc {
    joint_err: Vec<f64>,
    vert_err: Vec<f64>,
    pa_err: Vec<f64>,
    /// [`error_parts_mm`] of each matched pair.
    parts: Vec<[f64; 3]>,
    gt: usize,
    reached_500: usize,
    /// (score, mpjpe to nearest GT, frame-unique GT id) per prediction.
    dets: Vec<(f64, f64, usize)>,
    predictions: usize,
}

/// Accumulates frames, overall and per scene.
#[derive(Debug, Default, Clone)]
pub struct Evaluator {
    pub gate: f64,
    /// Index of the root joint (matched on) within the joint set.
    pub root: usize,
    overall: Acc,
    scenes: BTreeMap<String, Acc>,
    next_gt: usize,
}

impl Evaluator {
    pub fn new(gate: f64) -> Self {
        Evaluator {
            gate,
            ..Default::default()
        }
    }

    /// Add one frame's predictions and ground truth (joints in the same joint set).
    pub fn add_frame(&mut self, scene: &str, pred: &[PersonPose], gt: &[PersonPose]) {
        let base = self.next_gt;
        self.next_gt += gt.len();
        let pp: Vec<[f64; 3]> = pred.iter().map(|p| p.joints[self.root]).collect();
        let gp: Vec<[f64; 3]> = gt.iter().map(|p| p.joints[self.root]).collect();
        let pairs = match_people(&pp, &gp, self.gate);
        let mut frame = Acc {
            gt: gt.len(),
            predictions: pred.len(),
            ..Default::default()
        };
        for &(pi, gi) in &pairs {
            frame.joint_err.push(joint_error_mm(&pred[pi], &gt[gi]));
            frame
                .parts
                .extend(error_parts_mm(&pred[pi], &gt[gi], self.root));
            if let (Some(pv), Some(gv)) = (&pred[pi].vertices, &gt[gi].vertices) {
                frame.vert_err.push(mean_error_mm(pv, gv));
                if let Some(e) = pa_error_mm(pv, gv) {
                    frame.pa_err.push(e);
                }
            }
        }
        // Detection: each prediction against its nearest ground truth by MPJPE.
        let mut reached = vec![false; gt.len()];
        for p in pred {
            let best = gt
                .iter()
                .enumerate()
                .map(|(gi, g)| (joint_error_mm(p, g), gi))
                .min_by(|a, b| a.0.total_cmp(&b.0));
            if let Some((e, gi)) = best {
                frame.dets.push((p.score, e, base + gi));
                if e < 500.0 {
                    reached[gi] = true;
                }
            } else {
                frame.dets.push((p.score, f64::INFINITY, usize::MAX));
            }
        }
        frame.reached_500 = reached.iter().filter(|r| **r).count();
        for acc in [
            &mut self.overall,
            self.scenes.entry(scene.to_string()).or_default(),
        ] {
            acc.joint_err.extend(&frame.joint_err);
            acc.vert_err.extend(&frame.vert_err);
            acc.pa_err.extend(&frame.pa_err);
            acc.parts.extend(&frame.parts);
            acc.gt += frame.gt;
            acc.reached_500 += frame.reached_500;
            acc.dets.extend(&frame.dets);
            acc.predictions += frame.predictions;
        }
    }

    pub fn overall(&self) -> Metrics {
        metrics(&self.overall)
    }

    pub fn per_scene(&self) -> BTreeMap<String, Metrics> {
        self.scenes
            .iter()
            .map(|(k, v)| (k.clone(), metrics(v)))
            .collect()
    }
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// VOC-style AP (interpolated precision, all points) at an MPJPE threshold.
pub fn average_precision(dets: &[(f64, f64, usize)], total_gt: usize, threshold_mm: f64) -> f64 {
    if total_gt == 0 {
        return 0.0;
    }
    let mut order: Vec<usize> = (0..dets.len()).collect();
    order.sort_by(|&a, &b| dets[b].0.total_cmp(&dets[a].0));
    let mut claimed = std::collections::HashSet::new();
    let (mut tp, mut fp) = (0.0, 0.0);
    let mut prec = Vec::new();
    let mut rec = Vec::new();
    for i in order {
        let (_, e, g) = dets[i];
        if e < threshold_mm && claimed.insert(g) {
            tp += 1.0;
        } else {
            fp += 1.0;
        }
        prec.push(tp / (tp + fp));
        rec.push(tp / total_gt as f64);
    }
    // Precision envelope, then the area under the recall steps.
    for i in (0..prec.len().saturating_sub(1)).rev() {
        prec[i] = prec[i].max(prec[i + 1]);
    }
    let mut ap = 0.0;
    let mut last_r = 0.0;
    for (p, r) in prec.iter().zip(&rec) {
        if *r > last_r {
            ap += (r - last_r) * p;
            last_r = *r;
        }
    }
    ap
}

fn metrics(a: &Acc) -> Metrics {
    let part = |i: usize| mean(&a.parts.iter().map(|p| p[i]).collect::<Vec<_>>());
    Metrics {
        mpjpe_mm: mean(&a.joint_err),
        pve_mm: mean(&a.vert_err),
        pa_pve_mm: mean(&a.pa_err),
        root_mm: part(0),
        rr_mpjpe_mm: part(1),
        pa_mpjpe_mm: part(2),
        recall_500: (a.gt > 0).then(|| a.reached_500 as f64 / a.gt as f64),
        ap: AP_THRESHOLDS
            .iter()
            .map(|&t| (format!("{}", t as u32), average_precision(&a.dets, a.gt, t)))
            .collect(),
        matched: a.joint_err.len(),
        ground_truth: a.gt,
        predictions: a.predictions,
    }
}
