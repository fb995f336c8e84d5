//! `mvmp eval`, `mvmp infer` and `mvmp demo`.
use std::path::{Path, PathBuf};

use crate::progress::{self, LazyBar};
use anyhow::{Context, Result, bail};
use burn::tensor::Device;
use serde_json::json;

use mvmp_data::loader::Split;
use mvmp_data::sources::SourceFormat;
use rayon::prelude::*;

use mvmp_eval::drivers::{
    EvalFrame, EvalOptions, PseudoGt, PseudoGtCount, evaluate, evaluate_joint_sequences,
    evaluate_sequences, frames_at_once, mean_pose_at, mvmp_split, pose_params, reference_mean,
};
use mvmp_eval::joint_sets::JointSet;
use mvmp_eval::truth_parts::{TruthPart, pose_with_truth};
use mvmp_eval::{AP_THRESHOLDS, Evaluator, Metrics};
use mvmp_geom::{Camera, Rig};
use mvmp_infer::Predictor;
use mvmp_infer::output::{read_people_npz, write_frame};
use mvmp_io::{StagedDir, write_atomic};
use mvmp_smplx::SmplxLayer;
use mvmp_train::RunDir;
use mvmp_train::run::file_hash;

/// `--split` of an mvmp tree, through the data crate's own parser (one list of names).
pub fn parse_split(s: &str) -> Result<Split> {
    s.parse::<Split>()
        .map_err(|e| anyhow::anyhow!("--split {e}"))
}

/// The evaluation protocol, as stated in every report.
pub fn protocol(gate: f64, joints: JointSet) -> serde_json::Value {
    let joints_text = match joints {
        JointSet::Smplx127 => {
            "smplx127: the 127 SMPL-X joints (55 LBS joints, 21 vertex joints, 51 face landmarks)"
                .to_string()
        }
        JointSet::Panoptic15 => format!(
            "panoptic15: CMU Panoptic joints19[0..15], each taken from the SMPL-X joint at the same place ({})",
            mvmp_eval::joint_sets::PANOPTIC15
                .iter()
                .map(|(a, b)| format!("{a}={b}"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
        JointSet::H36m17 => format!(
            "h36m17: Human3.6M's 17 joints, each taken from the SMPL-X joint at the same place ({})",
            mvmp_eval::joint_sets::H36M17
                .iter()
                .map(|(a, b)| format!("{a}={b}"))
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    json!({
        "matching": "Hungarian assignment of predictions to ground truth on root (pelvis) distance",
        "gate_m": gate,
        "joints": joints_text,
        "joint_set": joints.name(),
        "root_joint": joints.root(),
        "mpjpe": "mean joint L2 on matched pairs, world frame, mm, no alignment",
        "pve": "mean vertex L2 on matched pairs, world frame, mm, no alignment",
        "pa_pve": "mean vertex L2 after a similarity Procrustes alignment (scale, rotation, translation) per person, mm",
        "root": "root (pelvis) L2 on matched pairs, mm: where people are",
        "rr_mpjpe": "mean joint L2 with each person's root at the origin (root-relative MPJPE), mm: orientation and pose",
        "pa_mpjpe": "mean joint L2 after a similarity Procrustes alignment per person (PA-MPJPE), mm: pose alone",
        "ap_thresholds_mm": AP_THRESHOLDS,
        "ap": "VOC-style AP: predictions by descending score, each to its nearest ground truth by MPJPE",
        "recall_500": "fraction of ground-truth people with a prediction within 500 mm MPJPE",
    })
}

/// Where the predictions came from.
pub enum Source<'a> {
    Run(&'a Path),
    Predictions(&'a Path),
    MeanPose,
}

pub struct EvalArgs<'a> {
    pub source: Source<'a>,
    pub data: &'a Path,
    pub split: Split,
    pub views: Option<usize>,
    pub frames: usize,
    pub gate: f64,
    pub out: Option<&'a Path>,
    pub save_predictions: Option<&'a Path>,
    pub body_model: Option<&'a str>,
    pub joints: JointSet,
    /// Dataset layout.
    pub format: SourceFormat,
    /// The split's name as given (Panoptic: a named split or comma-separated sequences; Human3.6M: a named
    /// split or comma-separated subjects).
    pub split_name: &'a str,
    /// Every N-th frame (Panoptic and Human3.6M).
    pub stride: Option<usize>,
    /// SMPL-X pseudo-ground-truth meshes for Panoptic and Human3.6M (`DIR/<sequence>/<frame>/people.npz`).
    pub pseudo_gt: Option<&'a Path>,
    /// The fused image-feature volume zeroed before the decoder (a diagnostic; runs only).
    pub zero_volume: bool,
    /// Parameter groups taken from the matched annotation before scoring (an error budget; runs and
    /// predictions on an mvmp dataset).
    pub truth: Vec<TruthPart>,
}

impl<'a> EvalArgs<'a> {
    /// The held-out scenes of an mvmp tree under the default protocol (every test frame, the run's test
    /// views, the default gate, SMPL-X joints), the report written to `out`.
    pub fn held_out(source: Source<'a>, data: &'a Path, out: &'a Path) -> Self {
        EvalArgs {
            source,
            data,
            split: Split::Test,
            views: None,
            frames: 0,
            gate: mvmp_eval::DEFAULT_GATE,
            out: Some(out),
            save_predictions: None,
            body_model: None,
            joints: JointSet::Smplx127,
            format: SourceFormat::Mvmp,
            split_name: "test",
            stride: None,
            pseudo_gt: None,
            zero_volume: false,
            truth: Vec::new(),
        }
    }

    /// The evaluation protocol these arguments ask for, over `views` views.
    fn options(&self, views: usize) -> EvalOptions {
        EvalOptions {
            split: self.split,
            views,
            max_frames: self.frames,
            gate: self.gate,
            joints: self.joints,
            truth: self.truth.clone(),
        }
    }
}

fn fmt(x: Option<f64>) -> String {
    x.map_or("-".into(), |v| format!("{v:.1}"))
}

/// A table of figures, one row per named set.
pub fn table(rows: &[(String, Metrics)]) -> String {
    let mut s = format!(
        "{:<28} {:>9} {:>9} {:>9} {:>8} {:>7} {:>7} {:>7}\n",
        "", "MPJPE", "PVE", "PA-PVE", "recall", "AP25", "AP100", "AP150"
    );
    for (name, m) in rows {
        s += &format!(
            "{:<28} {:>9} {:>9} {:>9} {:>8} {:>7.3} {:>7.3} {:>7.3}\n",
            name,
            fmt(m.mpjpe_mm),
            fmt(m.pve_mm),
            fmt(m.pa_pve_mm),
            m.recall_500.map_or("-".into(), |r| format!("{r:.3}")),
            m.ap.get("25").copied().unwrap_or(0.0),
            m.ap.get("100").copied().unwrap_or(0.0),
            m.ap.get("150").copied().unwrap_or(0.0),
        );
    }
    s
}

/// The parts of the joint error, a line (`None` without matched people): where people are, how they
/// are turned and stand, how they stand.
pub fn error_parts(m: &Metrics) -> Option<String> {
    Some(format!(
        "joint error in parts: root {:.1} mm, root-relative MPJPE {:.1} mm, PA-MPJPE {:.1} mm",
        m.root_mm?, m.rr_mpjpe_mm?, m.pa_mpjpe_mm?
    ))
}

/// Run an evaluation; returns the overall figures and the report.
pub fn eval(args: &EvalArgs, device: &Device, quiet: bool) -> Result<(Metrics, serde_json::Value)> {
    if args.zero_volume && !matches!(args.source, Source::Run(_)) {
        bail!("--zero-volume applies to a run's weights (--run), not to predictions or a baseline");
    }
    if !args.truth.is_empty()
        && (matches!(args.source, Source::MeanPose) || args.format != SourceFormat::Mvmp)
    {
        bail!(
            "--truth replaces parameters of predictions with those of SMPL-X annotations: it needs \
             --run or --predictions on an mvmp dataset, not a baseline or a joint-annotated dataset"
        );
    }
    check_save_predictions(args)?;
    check_outputs(args)?;
    check_meshes(args)?;
    match args.format {
        SourceFormat::Mvmp => {
            if args.stride.is_some() {
                bail!(
                    "--stride applies to --format panoptic and h36m; an mvmp split scores every frame"
                );
            }
        }
        SourceFormat::Panoptic => {
            let ds = JointDataset::panoptic(args.split_name);
            return eval_joint_dataset(args, ds, device, quiet);
        }
        SourceFormat::H36m => {
            let ds = JointDataset::h36m(args.split_name);
            return eval_joint_dataset(args, ds, device, quiet);
        }
    }
    let split_name = args.split.name();
    let layout = mvmp_data::DatasetLayout::open(args.data)?;
    if mvmp_data::loader::split_frames(&layout, args.split)?.is_empty() {
        bail!(
            "{}: the {split_name} split has no frames ({} scenes in dataset.json)",
            args.data.display(),
            layout.scenes.len()
        );
    }
    let min_views = layout.scenes.iter().map(|s| s.rig.len()).min().unwrap_or(0);
    if let Some(v) = args.views.filter(|&v| v > min_views) {
        anyhow::bail!(
            "--views {v}: {} has scenes with only {min_views} cameras",
            args.data.display()
        );
    }
    let ((ev, source, views), staged) = match args.source {
        Source::Run(run_dir) => eval_run(args, run_dir, min_views, device, quiet)?,
        Source::Predictions(dir) => (
            eval_predictions(args, dir, &layout, min_views, device)?,
            None,
        ),
        Source::MeanPose => (eval_mean_pose(args, &layout, device)?, None),
    };
    let header = json!({
        "source": source,
        "data": absolute(args.data),
        "split": split_name,
        "views": views,
        "protocol": protocol(args.gate, args.joints),
    });
    let header = with_truth_note(header, &args.truth);
    finish_with_predictions(&ev, header, "ground_truth", args.out, staged)
}

/// The report's note of the parameter groups taken from the annotations, if any.
fn with_truth_note(mut header: serde_json::Value, truth: &[TruthPart]) -> serde_json::Value {
    if !truth.is_empty() {
        let names: Vec<&str> = truth.iter().map(|p| p.name()).collect();
        header["truth_parts"] = json!({
            "parts": names,
            "note": "these parameter groups of each prediction were replaced by those of the annotated \
                     person nearest its pelvis within the gate, the predicted pelvis kept: an error budget, \
                     not the model's own figures",
        });
    }
    header
}

/// [`finish_report`], then the saved predictions put in place: a report that cannot be written leaves
/// no predictions behind, and predictions that cannot be put in place take the report away again.
fn finish_with_predictions(
    ev: &Evaluator,
    header: serde_json::Value,
    gt_key: &str,
    out: Option<&Path>,
    staged: Option<StagedDir>,
) -> Result<(Metrics, serde_json::Value)> {
    let report = finish_report(ev, header, gt_key, out)?;
    if let Some(s) = staged
        && let Err(e) = s.finish()
    {
        if let Some(out) = out {
            let _ = std::fs::remove_file(out);
        }
        return Err(e.into());
    }
    Ok(report)
}

/// `--save-predictions` is refused rather than ignored where there is nothing to save: only a model's
/// predictions are written.
fn check_save_predictions(args: &EvalArgs) -> Result<()> {
    if let Some(dir) = args.save_predictions
        && !matches!(args.source, Source::Run(_))
    {
        bail!(
            "--save-predictions {}: needs --run (stored predictions and the mean pose have nothing new to save)",
            dir.display()
        );
    }
    Ok(())
}

/// The report and the saved predictions go beside the inputs, never over them: `--out` replaces only a
/// file that is itself an evaluation report (a rerun's), never a dataset's, a run's or any other file;
/// `--save-predictions` never goes over a run's own files.
fn check_outputs(args: &EvalArgs) -> Result<()> {
    if let Some(out) = args.out.filter(|o| o.is_file()) {
        // A report is a few kilobytes per scene; anything far larger is not one and is not read.
        let small = std::fs::metadata(out).is_ok_and(|m| m.len() <= 64 << 20);
        let report = small
            .then(|| std::fs::read_to_string(out).ok())
            .flatten()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
            .is_some_and(|v| v["format"] == "mvmp-eval-report");
        if !report {
            bail!(
                "--out {}: the file exists and is not an evaluation report; refusing to overwrite it",
                out.display()
            );
        }
    }
    if let (Some(dir), Source::Run(run)) = (args.save_predictions, &args.source) {
        for f in [
            "train.toml",
            "model.toml",
            "state.json",
            "model.bpk",
            "metrics.jsonl",
            "checkpoints",
        ] {
            crate::paths::not_over_input("--save-predictions", dir, &run.join(f))?;
        }
    }
    Ok(())
}

/// With `--save-predictions`, the staging directory every frame's files go to, moved into place once all
/// frames are scored.
fn stage_predictions(args: &EvalArgs) -> Result<Option<StagedDir>> {
    Ok(args
        .save_predictions
        .map(|d| StagedDir::new(d).map(|s| s.owning(mvmp_infer::output::is_frame_output)))
        .transpose()?)
}

/// What one scoring gave: the evaluator, where the predictions came from, the views used.
type Scored = (Evaluator, serde_json::Value, usize);

/// A run's model on the split; with `--save-predictions`, every frame's files, staged for the caller to
/// put in place once the report is written.
fn eval_run(
    args: &EvalArgs,
    run_dir: &Path,
    min_views: usize,
    device: &Device,
    quiet: bool,
) -> Result<(Scored, Option<StagedDir>)> {
    let (run, cfg, _) = RunDir::open(run_dir)?;
    let (mut pred, weights) = Predictor::from_run(run_dir, device)?;
    pred.model.zero_volume = args.zero_volume;
    let views = args.views.unwrap_or(cfg.test_views.min(min_views));
    let opts = args.options(views);
    let mut pb = LazyBar::new("eval", quiet);
    let faces = pred.layer.faces().to_vec();
    let staged = stage_predictions(args)?;
    let ev = evaluate(&pred, args.data, &opts, |i, n, fp| {
        if let Some(dir) = &staged {
            let d = dir.path().join(&fp.scene).join(&fp.frame);
            write_frame(&d, &fp.people, &faces, &fp.cameras, None, &pred.cfg().grid)?;
        }
        pb.done(i, n);
        Ok(())
    })?;
    pb.finish();
    Ok((
        (ev, run_source(&run, &weights, args.zero_volume)?, views),
        staged,
    ))
}

/// Stored predictions (infer's layout) posed with the body model given or the dataset's.
fn eval_predictions(
    args: &EvalArgs,
    dir: &Path,
    layout: &mvmp_data::DatasetLayout,
    min_views: usize,
    device: &Device,
) -> Result<Scored> {
    let body = match args.body_model {
        Some(r) => mvmp_data::layout::load_body_model(r, Path::new("."))?,
        None => layout.body_model()?,
    };
    let layer = SmplxLayer::new(&body, device);
    let views = args.views.unwrap_or(1).min(min_views.max(1));
    let opts = args.options(views);
    let (seqs, truth) = mvmp_split(args.data, opts.split, device)?;
    let predict = |at: &EvalFrame| {
        let (scene, frame) = at.names();
        let path = dir.join(scene).join(frame).join("people.npz");
        if !path.exists() {
            return Err(mvmp_infer::InferError::file(
                &path,
                "no predictions for this frame (expected PRED_DIR/<scene>/<frame>/people.npz)",
            ));
        }
        let people: Vec<_> = read_people_npz(&path)?
            .into_iter()
            .map(|p| (p.params, p.score))
            .collect();
        if args.truth.is_empty() {
            return Ok(pose_params(&layer, &people));
        }
        let truth = at.smplx_people()?;
        Ok(pose_with_truth(
            &layer,
            &people,
            truth,
            &args.truth,
            args.gate,
        ))
    };
    let scored = |at: &EvalFrame| Ok((predict(at)?, ()));
    let (ev, _) = evaluate_sequences(&seqs, &truth, &opts, 1, scored, |_, _, ()| Ok(()))?;
    Ok((ev, json!({"predictions": dir.display().to_string()}), views))
}

/// The mean-pose reference at each ground-truth pelvis.
fn eval_mean_pose(
    args: &EvalArgs,
    layout: &mvmp_data::DatasetLayout,
    device: &Device,
) -> Result<Scored> {
    let layer = SmplxLayer::new(&layout.body_model()?, device);
    // The mean of the training split (what a trained decoder starts from); without people there,
    // the untrained decoder's parameters.
    let (mean, people) = reference_mean(args.data, device)?;
    let opts = args.options(1);
    let (seqs, truth) = mvmp_split(args.data, opts.split, device)?;
    let posed = |at: &EvalFrame| Ok((mean_pose_at(&layer, &mean, &at.roots()), ()));
    let (ev, _) = evaluate_sequences(&seqs, &truth, &opts, 1, posed, |_, _, ()| Ok(()))?;
    Ok((
        ev,
        json!({
            "baseline": "mean pose at the ground-truth pelvis",
            "mean_of_training_people": people,
        }),
        1,
    ))
}

/// Where a run's figures came from: the run, its weights and the hashes of both, and the diagnostic
/// that changed the model's inputs, if any.
fn run_source(run: &RunDir, weights: &Path, zero_volume: bool) -> Result<serde_json::Value> {
    let mut source = json!({
        "run": run.root.display().to_string(),
        "checkpoint": weights.display().to_string(),
        "checkpoint_sha256": file_hash(weights)?,
        "config_sha256": run.config_hash()?,
    });
    if zero_volume {
        source["ablation"] = json!("the fused image-feature volume zeroed before the decoder");
    }
    Ok(source)
}

fn absolute(p: &Path) -> String {
    std::path::absolute(p)
        .unwrap_or(p.into())
        .display()
        .to_string()
}

/// The report: `header` (source, data, protocol, ...) plus the overall figures (the ground-truth count
/// under `gt_key`) and per-scene figures; written atomically to `out` when given.
fn finish_report(
    ev: &Evaluator,
    header: serde_json::Value,
    gt_key: &str,
    out: Option<&Path>,
) -> Result<(Metrics, serde_json::Value)> {
    let overall = ev.overall();
    let mut report = json!({"format": "mvmp-eval-report", "version": 1});
    for (k, v) in header.as_object().expect("a JSON object") {
        report[k] = v.clone();
    }
    report["mpjpe_mm"] = json!(overall.mpjpe_mm);
    report["pve_mm"] = json!(overall.pve_mm);
    report["pa_pve_mm"] = json!(overall.pa_pve_mm);
    report["root_mm"] = json!(overall.root_mm);
    report["rr_mpjpe_mm"] = json!(overall.rr_mpjpe_mm);
    report["pa_mpjpe_mm"] = json!(overall.pa_mpjpe_mm);
    report["recall_500"] = json!(overall.recall_500);
    report["ap"] = json!(overall.ap);
    report["matched"] = json!(overall.matched);
    report[gt_key] = json!(overall.ground_truth);
    report["predictions"] = json!(overall.predictions);
    report["per_scene"] = json!(ev.per_scene());
    if let Some(out) = out {
        if let Some(d) = out.parent().filter(|d| !d.as_os_str().is_empty()) {
            std::fs::create_dir_all(d).with_context(|| format!("creating {}", d.display()))?;
        }
        write_atomic(out, serde_json::to_string_pretty(&report)?.as_bytes())?;
    }
    Ok((overall, report))
}

/// The images of one frame directory: the annotation's list when there is one, else the image files in
/// name order (depth_* and mask_* skipped).
pub fn frame_images(dir: &Path, views: usize) -> Result<Vec<PathBuf>> {
    let ann = dir.join("annotation.json");
    if ann.exists() {
        let a = mvmp_data::Annotation::read(&ann, views)?;
        return Ok(a.images.iter().map(|i| dir.join(i)).collect());
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("reading {}", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| {
            let name = p.file_name().and_then(|f| f.to_str()).unwrap_or("");
            let ext = p
                .extension()
                .and_then(|e| e.to_str())
                .unwrap_or("")
                .to_ascii_lowercase();
            matches!(ext.as_str(), "png" | "jpg" | "jpeg")
                && !name.starts_with("depth_")
                && !name.starts_with("mask_")
        })
        .collect();
    files.sort();
    if files.len() != views {
        bail!(
            "{}: {} images, but the rig has {views} cameras (one image per camera, in rig order)",
            dir.display(),
            files.len()
        );
    }
    Ok(files)
}

fn load_images(paths: &[PathBuf], cams: &[Camera]) -> Result<Vec<image::RgbImage>> {
    if paths.len() != cams.len() {
        bail!(
            "{} images for a rig of {} cameras: pass one image per camera, in rig order",
            paths.len(),
            cams.len()
        );
    }
    // One file for two cameras is a typing slip that would score a view as another's.
    let files: Vec<PathBuf> = paths
        .iter()
        .map(|p| std::fs::canonicalize(p).unwrap_or_else(|_| p.clone()))
        .collect();
    for (i, f) in files.iter().enumerate() {
        if let Some(j) = files[..i].iter().position(|g| g == f) {
            bail!(
                "{}: the image of camera {i} ({}) is also camera {j}'s: pass one image per camera",
                paths[i].display(),
                cams[i].name
            );
        }
    }
    Ok(mvmp_data::dataset::read_frame_images(paths, cams)?)
}

/// Infer one frame; returns the number of people.
fn infer_frame(pred: &Predictor, rig: &Rig, paths: &[PathBuf], out: &Path) -> Result<usize> {
    let imgs = load_images(paths, &rig.cameras)?;
    let people = pred.predict_images(&imgs, &rig.cameras)?;
    write_frame(
        out,
        &people,
        pred.layer.faces(),
        &rig.cameras,
        Some(&imgs),
        &pred.cfg().grid,
    )?;
    Ok(people.len())
}

pub struct InferArgs<'a> {
    pub run: &'a Path,
    pub rig: &'a Path,
    pub images: &'a [PathBuf],
    pub frames: Option<&'a Path>,
    pub out: &'a Path,
}

pub fn infer(args: &InferArgs, device: &Device, quiet: bool) -> Result<()> {
    let rig = Rig::read(args.rig)?;
    let (pred, weights) = Predictor::from_run(args.run, device)?;
    match (args.frames, args.images.is_empty()) {
        (Some(dir), true) => {
            let mut frames: Vec<PathBuf> = std::fs::read_dir(dir)
                .with_context(|| format!("reading {}", dir.display()))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.is_dir())
                .collect();
            frames.sort();
            if frames.is_empty() {
                bail!(
                    "{}: no frame directories (expected one sub-directory per frame holding one image per camera)",
                    dir.display()
                );
            }
            let b = progress::bar(frames.len() as u64, "infer", quiet);
            // All frames are written to a staging directory and moved into place together.
            let staged = StagedDir::new(args.out)?.owning(mvmp_infer::output::is_frame_output);
            // Frames are independent: on flex one per thread at a time, as evaluation scores them.
            let mut total = 0;
            for window in frames.chunks(frames_at_once(device)) {
                let people: Vec<Result<usize>> = window
                    .par_iter()
                    .map(|f| {
                        let paths = frame_images(f, rig.len())?;
                        let name = f.file_name().expect("a directory name");
                        let n = infer_frame(&pred, &rig, &paths, &staged.path().join(name))?;
                        b.inc(1);
                        Ok(n)
                    })
                    .collect();
                for n in people {
                    total += n?;
                }
            }
            staged.finish()?;
            b.finish_and_clear();
            eprintln!(
                "{} frames, {total} people in all, weights {}; outputs in {}",
                frames.len(),
                weights.display(),
                args.out.display()
            );
        }
        (None, false) => {
            let staged = StagedDir::new(args.out)?.owning(mvmp_infer::output::is_frame_output);
            let n = infer_frame(&pred, &rig, args.images, staged.path())?;
            staged.finish()?;
            eprintln!(
                "{n} people (weights {}); outputs in {}",
                weights.display(),
                args.out.display()
            );
        }
        (Some(_), false) => bail!("pass either --images or --frames, not both"),
        (None, true) => bail!("pass --images (one per camera, in rig order) or --frames DIR"),
    }
    Ok(())
}

/// The demo's embedded configs (the repository's tiny configs), so `mvmp demo` runs from anywhere.
pub const DEMO_SYNTH: &str = include_str!("../../../configs/synth/tiny.toml");
pub const DEMO_MODEL: &str = include_str!("../../../configs/model/tiny.toml");
pub const DEMO_TRAIN: &str = include_str!("../../../configs/train/tiny.toml");

/// The demo's synthesis (with `scenes` one-frame scenes), model and training configs written into `dir`
/// as `synth.toml`, `model.toml` and `train.toml` (the training config pointing at the model beside it).
pub fn write_demo_configs(dir: &Path, scenes: usize) -> Result<()> {
    let is_count = |l: &str| l.starts_with("scenes = ");
    anyhow::ensure!(
        DEMO_SYNTH.lines().filter(|l| is_count(l)).count() == 1,
        "the embedded synthesis config has no single `scenes = N` line"
    );
    let synth: String = DEMO_SYNTH
        .lines()
        .map(|l| match is_count(l) {
            true => format!("scenes = {scenes}\n"),
            false => format!("{l}\n"),
        })
        .collect();
    write_atomic(&dir.join("synth.toml"), synth.as_bytes())?;
    write_atomic(&dir.join("model.toml"), DEMO_MODEL.as_bytes())?;
    let train = DEMO_TRAIN.replace("\"../model/tiny.toml\"", "\"model.toml\"");
    write_atomic(&dir.join("train.toml"), train.as_bytes())?;
    Ok(())
}

/// `mvmp demo`: synthesise, train both stages, evaluate on held-out scenes beside two references, infer.
/// `out` must be new or empty, and a demo that fails or is interrupted leaves it so.
pub fn demo(out: &Path, seed: u64, device: &Device) -> Result<()> {
    check_new_or_empty(out)?;
    let existed = out.exists();
    crate::interrupt::unfinished_output(out, existed);
    let result = demo_configs(out, seed).and_then(|cfg_dir| demo_steps(out, &cfg_dir, device));
    crate::interrupt::finished(out);
    let Err(e) = result else {
        return Ok(());
    };
    Err(match crate::interrupt::clear(out, existed) {
        Ok(()) => e.context(format!(
            "the demo's outputs in {} were removed",
            out.display()
        )),
        Err(c) => e.context(format!(
            "removing the demo's unfinished outputs in {} failed too: {c}",
            out.display()
        )),
    })
}

fn demo_steps(out: &Path, cfg_dir: &Path, device: &Device) -> Result<()> {
    let t0 = std::time::Instant::now();
    let mut phases = Phases::new();
    let data = out.join("data");
    let run_dir = out.join("run");
    eprintln!("[1/5] synthetic dataset -> {}", data.display());
    crate::data::synth(&cfg_dir.join("synth.toml"), &data)?;
    phases.lap("synthesis");

    eprintln!(
        "[2/5] references on the held-out scenes: the untrained model, the mean pose at the GT pelvis"
    );
    let (m_untrained, m_mean) = demo_references(cfg_dir, &data, out, device)?;
    phases.lap("references");

    eprintln!("[3/5] training -> {}", run_dir.display());
    crate::train::train(
        crate::train::TrainArgs {
            config: Some(&cfg_dir.join("train.toml")),
            data: Some(&data),
            out: Some(&run_dir),
            resume: None,
            from_stage1: None,
            stop_after_steps: None,
            stop_after_minutes: None,
            resumable: false,
        },
        device,
        &mut crate::train::BarMonitor::new(false),
    )?;
    if !run_dir.join("model.bpk").exists() {
        bail!("training was interrupted");
    }
    phases.lap("training");

    eprintln!("[4/5] evaluation on the held-out scenes");
    let eval_path = out.join("eval.json");
    let pred_dir = out.join("predictions");
    let args = EvalArgs {
        save_predictions: Some(&pred_dir),
        ..EvalArgs::held_out(Source::Run(&run_dir), &data, &eval_path)
    };
    let (m_trained, _) = eval(&args, device, false)?;
    phases.lap("evaluation");

    eprintln!("[5/5] inference on a held-out frame");
    let infer_dir = out.join("infer");
    demo_infer(&data, &run_dir, &infer_dir, device)?;
    phases.lap("inference");

    println!(
        "\nheld-out scenes ({} people matched of {}), errors in mm:",
        m_trained.matched, m_trained.ground_truth
    );
    print!(
        "{}",
        table(&[
            ("untrained model".into(), m_untrained),
            ("mean pose at GT pelvis".into(), m_mean.clone()),
            ("trained (this demo)".into(), m_trained.clone()),
        ])
    );
    for (name, m) in [("mean pose at GT pelvis", &m_mean), ("trained", &m_trained)] {
        if let Some(parts) = error_parts(m) {
            println!("{name:<23} {parts}");
        }
    }
    println!("\ndataset      {}", data.display());
    println!(
        "run          {}  (metrics.jsonl, checkpoints/, model.bpk)",
        run_dir.display()
    );
    println!(
        "evaluation   {}  (predictions in {})",
        eval_path.display(),
        pred_dir.display()
    );
    println!(
        "inference    {}  (people.npz, person_XX.obj/.ply, overlay_XX.png, topdown.png)",
        infer_dir.display()
    );
    println!(
        "total time   {:.1} min ({})",
        t0.elapsed().as_secs_f64() / 60.0,
        phases
    );
    Ok(())
}

/// The minutes each of the demo's phases took, in order.
struct Phases {
    last: std::time::Instant,
    done: Vec<(&'static str, f64)>,
}

impl Phases {
    fn new() -> Self {
        Phases {
            last: std::time::Instant::now(),
            done: Vec::new(),
        }
    }

    /// Ends the phase `name` now.
    fn lap(&mut self, name: &'static str) {
        let now = std::time::Instant::now();
        let minutes = (now - self.last).as_secs_f64() / 60.0;
        self.done.push((name, minutes));
        self.last = now;
    }
}

impl std::fmt::Display for Phases {
    fn fmt(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        for (i, (name, minutes)) in self.done.iter().enumerate() {
            let sep = if i == 0 { "" } else { ", " };
            write!(f, "{sep}{name} {minutes:.1}")?;
        }
        Ok(())
    }
}

fn check_new_or_empty(out: &Path) -> Result<()> {
    if out.exists()
        && std::fs::read_dir(out)
            .with_context(|| format!("reading {}", out.display()))?
            .next()
            .is_some()
    {
        bail!(
            "{} exists and is not empty: remove it or pass --out to a new directory",
            out.display()
        );
    }
    Ok(())
}

/// The demo's configs (the embedded ones, the training seed set to `seed`) written to `out/configs`,
/// which it returns.
fn demo_configs(out: &Path, seed: u64) -> Result<PathBuf> {
    let cfg_dir = out.join("configs");
    std::fs::create_dir_all(&cfg_dir).with_context(|| format!("creating {}", cfg_dir.display()))?;
    let train_text = DEMO_TRAIN
        .replace("\"../model/tiny.toml\"", "\"model.toml\"")
        .replace("\nseed = 0\n", &format!("\nseed = {seed}\n"));
    anyhow::ensure!(
        train_text.contains(&format!("\nseed = {seed}\n")),
        "the embedded training config has no `seed = 0` line to set the seed in"
    );
    for (name, text) in [
        ("synth.toml", DEMO_SYNTH),
        ("model.toml", DEMO_MODEL),
        ("train.toml", train_text.as_str()),
    ] {
        write_atomic(&cfg_dir.join(name), text.as_bytes())?;
    }
    Ok(cfg_dir)
}

/// The references on the held-out scenes: the untrained model (the initial weights the run starts
/// from) and the mean pose at each ground-truth pelvis (its report written to `out`).
fn demo_references(
    cfg_dir: &Path,
    data: &Path,
    out: &Path,
    device: &Device,
) -> Result<(Metrics, Metrics)> {
    let (train_cfg, model_cfg) = mvmp_train::TrainConfig::read(&cfg_dir.join("train.toml"))?;
    let body = mvmp_data::layout::load_body_model(&model_cfg.body_model, cfg_dir)?;
    let init = mvmp_train::seeded_init(&model_cfg, device, train_cfg.seed);
    let untrained = Predictor::new(init, body, device);
    let opts = EvalOptions {
        split: Split::Test,
        views: train_cfg.test_views,
        max_frames: 0,
        gate: mvmp_eval::DEFAULT_GATE,
        joints: JointSet::Smplx127,
        truth: Vec::new(),
    };
    let m_untrained = evaluate(&untrained, data, &opts, |_, _, _| Ok(()))?.overall();
    drop(untrained);
    let mean_path = out.join("eval-mean-pose.json");
    let base = EvalArgs::held_out(Source::MeanPose, data, &mean_path);
    let (m_mean, _) = eval(&base, device, true)?;
    Ok((m_untrained, m_mean))
}

/// Inference on the first held-out frame into `infer_dir`.
fn demo_infer(data: &Path, run_dir: &Path, infer_dir: &Path, device: &Device) -> Result<()> {
    let layout = mvmp_data::DatasetLayout::open(data)?;
    let test = mvmp_data::loader::split_scenes(&layout, Split::Test)?;
    let scene = &layout.scenes[*test.first().context("the dataset has no test scene")?];
    let frame = scene
        .index
        .frames
        .first()
        .context("the first test scene has no frames")?;
    let images = frame_images(&scene.dir.join(frame), scene.rig.len())?;
    infer(
        &InferArgs {
            run: run_dir,
            rig: &scene.dir.join("cameras.json"),
            images: &images,
            frames: None,
            out: infer_dir,
        },
        device,
        true,
    )
}

/// Refuses the mesh options where nothing would read them: `--pseudo-gt` on an mvmp dataset (its
/// annotations are SMPL-X already), `--body-model` where neither stored predictions nor fits are posed
/// (a run poses its predictions with its own body model, the mean pose with the dataset's).
fn check_meshes(args: &EvalArgs) -> Result<()> {
    if let (Some(dir), SourceFormat::Mvmp) = (args.pseudo_gt, args.format) {
        bail!(
            "--pseudo-gt {}: fits apply to --format panoptic and h36m; an mvmp dataset's annotations \
             are SMPL-X already",
            dir.display()
        );
    }
    let posed = args.pseudo_gt.is_some() || matches!(args.source, Source::Predictions(_));
    if let (Some(model), false) = (args.body_model, posed) {
        bail!(
            "--body-model {model}: it poses stored predictions (--predictions) or the fits of \
             --pseudo-gt; a run poses its predictions with its own body model, the mean pose with the \
             dataset's"
        );
    }
    Ok(())
}

/// The pseudo-ground-truth meshes of a joint-annotated evaluation, posed with `--body-model` (default: the
/// run's body model), and the report's line on what PVE used.
fn pseudo_gt(args: &EvalArgs, pred: &Predictor, device: &Device) -> Result<Option<PseudoGt>> {
    let Some(dir) = args.pseudo_gt else {
        return Ok(None);
    };
    if !dir.is_dir() {
        bail!("--pseudo-gt {}: not a directory", dir.display());
    }
    let layer = match args.body_model {
        Some(r) => SmplxLayer::new(
            &mvmp_data::layout::load_body_model(r, Path::new("."))?,
            device,
        ),
        None => (*pred.layer).clone(),
    };
    Ok(Some(PseudoGt {
        dir: dir.to_path_buf(),
        layer,
        gate: args.gate,
    }))
}

fn meshes_note(args: &EvalArgs, count: PseudoGtCount) -> serde_json::Value {
    match args.pseudo_gt {
        None => {
            json!("none: PVE and PA-PVE are not computed (pass --pseudo-gt DIR with SMPL-X fits)")
        }
        Some(d) => json!(format!(
            "SMPL-X pseudo-ground-truth from {} (body model {}): PVE and PA-PVE over the {} of {} annotated people that have a fit",
            absolute(d),
            args.body_model.unwrap_or("of the run"),
            count.with_mesh,
            count.people
        )),
    }
}

/// Opens a dataset's sequences in place: root, sequence (or subject) names, cameras, stride.
type OpenSequences =
    fn(
        &Path,
        &[String],
        &[&str],
        usize,
    ) -> Result<Vec<Box<dyn mvmp_data::sequence::Sequence>>, mvmp_data::DataError>;

/// A joint-annotated dataset as `mvmp eval` reads it in place: which sequences, cameras and joints, and
/// how the report names them.
struct JointDataset {
    /// The report's `dataset` and the name in messages.
    name: &'static str,
    label: &'static str,
    set: JointSet,
    cameras: &'static [&'static str],
    /// The report key of `parts` ("subjects" or "sequences") and the split's label.
    parts_key: &'static str,
    parts: Vec<String>,
    split_label: String,
    default_stride: usize,
    ground_truth: &'static str,
    open: OpenSequences,
}

impl JointDataset {
    fn h36m(split: &str) -> Self {
        JointDataset {
            name: "human3.6m",
            label: "Human3.6M",
            set: JointSet::H36m17,
            cameras: &mvmp_data::h36m::CAMERAS,
            parts_key: "subjects",
            parts: mvmp_data::h36m::split_subjects(split),
            split_label: split.to_string(),
            default_stride: 5,
            ground_truth: "Human3.6M D3_Positions, 17 of the 32 joints (0,1,2,3,6,7,8,12,13,14,15,17,18,19,25,26,27), world, one person per frame, S11 Directions left out",
            open: mvmp_data::sources::open_h36m,
        }
    }

    fn panoptic(split: &str) -> Self {
        let (parts, stride, label) = mvmp_data::sources::panoptic_split(split);
        JointDataset {
            name: "cmu-panoptic",
            label: "Panoptic",
            set: JointSet::Panoptic15,
            cameras: &mvmp_data::panoptic::VOXELPOSE_CAMERAS,
            parts_key: "sequences",
            parts,
            split_label: label,
            default_stride: stride,
            ground_truth: "Panoptic joints19, first 15 joints, a joint counts where its confidence > 0.1; bodies without an annotated body centre are dropped",
            open: mvmp_data::sources::open_panoptic,
        }
    }
}

/// `mvmp eval --format panoptic|h36m`: a run scored on the dataset read in place.
fn eval_joint_dataset(
    args: &EvalArgs,
    ds: JointDataset,
    device: &Device,
    quiet: bool,
) -> Result<(Metrics, serde_json::Value)> {
    let Source::Run(run_dir) = args.source else {
        bail!("--format {} scores a run (--run RUN_DIR)", args.format);
    };
    let stride = args.stride.unwrap_or(ds.default_stride);
    if stride == 0 {
        bail!("--stride 0: keep every N-th frame with N >= 1");
    }
    let views = args.views.unwrap_or(ds.cameras.len());
    if views == 0 || views > ds.cameras.len() {
        bail!(
            "--views {views}: {} evaluation uses 1 to {} of the cameras {:?}",
            ds.label,
            ds.cameras.len(),
            ds.cameras
        );
    }
    let cameras = &ds.cameras[..views];
    let (run, _, _) = RunDir::open(run_dir)?;
    let (mut pred, weights) = Predictor::from_run(&run.root, device)?;
    pred.model.zero_volume = args.zero_volume;
    let pseudo = pseudo_gt(args, &pred, device)?;
    let seqs = (ds.open)(args.data, &ds.parts, cameras, stride)?;
    if seqs.iter().all(|s| s.is_empty()) {
        bail!(
            "{}: the {} split ({}) has no frames with poses",
            args.data.display(),
            ds.split_label,
            ds.parts.join(", ")
        );
    }
    let mut pb = LazyBar::new("eval", quiet);
    let faces = pred.layer.faces().to_vec();
    let staged = stage_predictions(args)?;
    let (ev, count) = evaluate_joint_sequences(
        &pred,
        &seqs,
        ds.set,
        args.frames,
        args.gate,
        pseudo.as_ref(),
        |i, n, fp| {
            if let Some(dir) = &staged {
                let d = dir.path().join(&fp.scene).join(&fp.frame);
                write_frame(&d, &fp.people, &faces, &fp.cameras, None, &pred.cfg().grid)?;
            }
            pb.done(i, n);
            Ok(())
        },
    )?;
    pb.finish();
    let mut header = json!({
        "source": run_source(&run, &weights, args.zero_volume)?,
        "data": absolute(args.data),
        "dataset": ds.name,
        "split": ds.split_label,
        "stride": stride,
        "cameras": cameras,
        "views": views,
        "ground_truth": ds.ground_truth,
        "meshes": meshes_note(args, count),
        "protocol": protocol(args.gate, ds.set),
    });
    header[ds.parts_key] = json!(ds.parts);
    finish_with_predictions(&ev, header, "ground_truth_people", args.out, staged)
}
