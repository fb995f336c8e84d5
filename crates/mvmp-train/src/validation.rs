//! Validation after every epoch: the source it reads (checked before training starts), the root
//! error, recall and heading error of the detector in stage 1, the mesh metrics and the spreads of the
//! predicted headings and body poses in stage 2.
use std::path::Path;

use burn::data::dataloader::batcher::Batcher;
use burn::module::Module;
use burn::tensor::Device;

use mvmp_data::dataset::FrameDataset;
use mvmp_data::loader::{FrameBatcher, Split, ViewChoice};
use mvmp_data::sources::{SourceFormat, SourceSpec};
use mvmp_eval::drivers::{EvalOptions, evaluate};
use mvmp_eval::spread;
use mvmp_eval::{Evaluator, PersonPose};
use mvmp_infer::Predictor;
use mvmp_model::MvmpHmr;

use crate::TrainError;
use crate::config::{Stage, TrainConfig};

/// Open the validation source the way validation will (its split, the first `test_views` cameras), so
/// that a wrong path or split stops the run before training rather than after the first epoch.
pub fn check_validation_source(cfg: &TrainConfig) -> Result<(), TrainError> {
    let Some(src) = cfg.validation_source() else {
        return Ok(());
    };
    let cameras = source_cameras(&src)?;
    if cfg.test_views > cameras {
        return Err(TrainError::file(
            &src.root,
            format!(
                "test_views = {}: the validation {} source has {cameras} cameras",
                cfg.test_views,
                src.format.name()
            ),
        ));
    }
    if src.format == SourceFormat::Mvmp {
        let split: Split = src
            .split
            .as_deref()
            .unwrap_or("test")
            .parse()
            .map_err(|e: String| TrainError::file(&src.root, e))?;
        // The cameras were counted above; the split must be readable, and one that has no frames
        // validates nothing: an error where the config names it, a warning where it is the training
        // data's own held-out split (a set of one or two scenes has none).
        let layout = mvmp_data::DatasetLayout::open(Path::new(&src.root))?;
        if mvmp_data::loader::split_frames(&layout, split)?.is_empty() {
            let what = format!(
                "the {} split has no frames ({} scenes): nothing will be validated",
                split.name(),
                layout.scenes.len()
            );
            if cfg.validation.is_some() {
                return Err(TrainError::file(&src.root, what));
            }
            tracing::warn!("{}: {what}", src.root);
        }
        return Ok(());
    }
    let seqs = validation_sequences(cfg, &src)?;
    if seqs.iter().all(|s| s.is_empty()) {
        return Err(TrainError::file(
            &src.root,
            "the validation split has no frames",
        ));
    }
    Ok(())
}

/// The cameras every frame of a source has: the fewest of any scene of an MVMP-HMR tree, the cameras a
/// Panoptic or Human3.6M source reads.
pub(crate) fn source_cameras(spec: &SourceSpec) -> Result<usize, TrainError> {
    Ok(match spec.format {
        SourceFormat::Mvmp => {
            let layout = mvmp_data::DatasetLayout::open(Path::new(&spec.root))?;
            layout.scenes.iter().map(|s| s.rig.len()).min().unwrap_or(0)
        }
        _ => spec.camera_names().len(),
    })
}

/// The sequences of a joint-annotated validation source, with the first `test_views` cameras.
fn validation_sequences(
    cfg: &TrainConfig,
    source: &SourceSpec,
) -> Result<Vec<Box<dyn mvmp_data::sequence::Sequence>>, TrainError> {
    let cams = source.camera_names();
    if cfg.test_views == 0 || cfg.test_views > cams.len() {
        return Err(TrainError::file(
            &source.root,
            format!(
                "test_views = {} but the validation source has {} cameras",
                cfg.test_views,
                cams.len()
            ),
        ));
    }
    let spec = SourceSpec {
        cameras: Some(cams[..cfg.test_views].to_vec()),
        ..source.clone()
    };
    Ok(spec.open_sequences("test")?)
}

/// Validation on the test split: root error and recall in stage 1, the mesh metrics in stage 2.
pub(crate) fn validate(
    model: &MvmpHmr,
    cfg: &TrainConfig,
    body: &mvmp_smplx::BodyModel,
    source: &SourceSpec,
    stage: Stage,
    device: &Device,
) -> Result<Vec<(String, f64)>, TrainError> {
    let pred = Predictor::new(model.valid(), body.clone(), device);
    if source.format != SourceFormat::Mvmp {
        return validate_joints(&pred, cfg, source, stage);
    }
    let data = Path::new(&source.root);
    let split: Split = source
        .split
        .as_deref()
        .unwrap_or("test")
        .parse()
        .map_err(|e: String| TrainError::file(data, e))?;
    let opts = EvalOptions {
        split,
        views: cfg.test_views,
        max_frames: cfg.val_frames,
        gate: cfg.match_gate,
        joints: mvmp_eval::joint_sets::JointSet::Smplx127,
        truth: Vec::new(),
    };
    let metrics = if stage == Stage::Detection {
        root_metrics(&pred, data, &opts)?
    } else {
        // Every predicted person's pose: their spread across people tells a decoder that reads its
        // input from one that predicts the same body for everyone (docs/architecture.md, Training).
        let mut poses: Vec<Vec<f64>> = Vec::new();
        let m = evaluate(&pred, data, &opts, |_, _, frame| {
            poses.extend(
                frame
                    .people
                    .iter()
                    .map(|p| p.pose.iter().map(|&x| x as f64).collect()),
            );
            Ok(())
        })?
        .overall();
        let headings: Vec<f64> = poses
            .iter()
            .map(|p| spread::heading_deg([p[0], p[1], p[2]]))
            .collect();
        let body: Vec<Vec<f64>> = poses.iter().map(|p| p[3..66].to_vec()).collect();
        measured(&[
            ("mpjpe_mm", m.mpjpe_mm),
            ("pve_mm", m.pve_mm),
            ("pa_pve_mm", m.pa_pve_mm),
            ("root_mm", m.root_mm),
            ("rr_mpjpe_mm", m.rr_mpjpe_mm),
            ("pa_mpjpe_mm", m.pa_mpjpe_mm),
            ("recall_500", m.recall_500),
            ("heading_spread_deg", spread::heading_spread_deg(&headings)),
            ("body_pose_spread_deg", spread::pose_spread_deg(&body)),
        ])
        .into_iter()
        // The detector's own recall and the facing head's error at the true roots, as in stage 1:
        // whether stage 2 keeps what stage 1 taught them.
        .chain(
            root_metrics(&pred, data, &opts)?
                .into_iter()
                .filter(|(k, _)| k == "root_recall" || k == "facing_deg"),
        )
        .collect()
    };
    Ok(metrics)
}

/// The metrics that were computed (a metric is absent when nothing was matched).
fn measured(metrics: &[(&str, Option<f64>)]) -> Vec<(String, f64)> {
    metrics
        .iter()
        .filter_map(|&(k, v)| v.map(|v| (k.to_string(), v)))
        .collect()
}

/// Validation on a joint-annotated dataset: root metrics in stage 1; MPJPE on the dataset's joint set and
/// the recall in stage 2 (no meshes).
fn validate_joints(
    pred: &Predictor,
    cfg: &TrainConfig,
    source: &SourceSpec,
    stage: Stage,
) -> Result<Vec<(String, f64)>, TrainError> {
    let seqs = validation_sequences(cfg, source)?;
    let metrics = if stage == Stage::Detection {
        let ds = FrameDataset::new(
            &source.root,
            seqs,
            ViewChoice::Fixed((0..cfg.test_views).collect()),
            pred.cfg().image_size,
        )?;
        root_metrics_of(
            pred,
            ds.len(),
            |i| ds.load(i),
            cfg.val_frames,
            cfg.match_gate,
        )?
    } else {
        let (ev, _) = mvmp_eval::drivers::evaluate_joint_sequences(
            pred,
            &seqs,
            source.format.joint_set(),
            cfg.val_frames,
            cfg.match_gate,
            None,
            |_, _, _| Ok(()),
        )?;
        let m = ev.overall();
        measured(&[("mpjpe_mm", m.mpjpe_mm), ("recall_500", m.recall_500)])
    };
    Ok(metrics)
}

/// Root localisation on a split: mean error of matched roots (mm) and the fraction of people found.
pub fn root_metrics(
    pred: &Predictor,
    data: &Path,
    opts: &EvalOptions,
) -> Result<Vec<(String, f64)>, TrainError> {
    let ds = FrameDataset::open(
        data,
        opts.split,
        ViewChoice::Fixed((0..opts.views).collect()),
        pred.cfg().image_size,
    )?;
    root_metrics_of(pred, ds.len(), |i| ds.load(i), opts.max_frames, opts.gate)
}

/// Root metrics over `len` samples given by `load` (at most `max_frames`; 0 = all).
fn root_metrics_of(
    pred: &Predictor,
    len: usize,
    load: impl Fn(usize) -> Result<mvmp_data::loader::FrameSample, mvmp_data::DataError>,
    max_frames: usize,
    gate: f64,
) -> Result<Vec<(String, f64)>, TrainError> {
    let batcher = FrameBatcher::default();
    let n = match max_frames {
        0 => len,
        m => m.min(len),
    };
    let primary = pred.cfg().primary_joint.joint();
    let mut ev = Evaluator::new(gate);
    let mut facing = Vec::new();
    for i in 0..n {
        let sample = load(i)?;
        let gt: Vec<PersonPose> = sample
            .people
            .iter()
            .map(|p| PersonPose {
                joints: vec![p.joints_3d[primary].map(|x| x as f64)],
                vertices: None,
                score: 1.0,
                valid: None,
            })
            .collect();
        let batch = batcher.batch(vec![sample], &pred.device);
        let (mut roots, det, grids) =
            pred.detect_with_maps(batch.images.clone(), &batch.cameras, &batch.letterboxes);
        let roots = roots.remove(0);
        facing.extend(crate::step::facing_errors_deg(
            &det,
            &grids,
            &crate::step::HostGt::new(&batch),
            pred.cfg(),
            &pred.device,
        ));
        let det: Vec<PersonPose> = roots
            .iter()
            .map(|r| PersonPose {
                joints: vec![r.position],
                vertices: None,
                score: r.score as f64,
                valid: None,
            })
            .collect();
        ev.add_frame(&batch.names[0].0, &det, &gt);
    }
    let m = ev.overall();
    let found = m.matched as f64 / m.ground_truth.max(1) as f64;
    let mut out = vec![("root_recall".to_string(), found)];
    if let Some(e) = m.mpjpe_mm {
        out.push(("root_mm".into(), e));
    }
    if !facing.is_empty() {
        // The median: a head that has learned leaves a few people (hidden in most views) far off.
        facing.sort_by(f64::total_cmp);
        out.push(("facing_deg".into(), facing[facing.len() / 2]));
    }
    Ok(out)
}
