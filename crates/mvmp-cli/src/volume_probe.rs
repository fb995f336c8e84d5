//! `mvmp model probe`: a linear probe of a run's volumes for each person's body pose
//! (`mvmp_train::probe`), beside the same model at the initial weights its training drew.
use std::path::Path;

use anyhow::{Context, Result, bail};
use burn::tensor::Device;

use mvmp_data::loader::Split;
use mvmp_data::sequence::FramePeople;
use mvmp_eval::drivers::EvalFrame;
use mvmp_eval::truth_parts::nearest_within;
use mvmp_infer::PersonPrediction;
use mvmp_infer::Predictor;
use mvmp_model::MvmpHmr;
use mvmp_train::RunDir;
use mvmp_train::keypoints::{KeypointSummary, summarise};
use mvmp_train::probe::{
    ProbeOptions, ProbeScore, ProbedPerson, collect, mean_pose_mm, scene_count, score,
};
use mvmp_train::probe::{body_frame_offsets, pose_mm};
use mvmp_train::step::joint_heading;

use crate::progress::LazyBar;

pub struct ProbeArgs<'a> {
    pub run: &'a Path,
    pub data: &'a Path,
    pub lattice: [usize; 3],
    pub span: [f64; 3],
    pub views: Option<usize>,
    pub frames: usize,
    pub out: Option<&'a Path>,
}

pub fn probe(args: &ProbeArgs, device: &Device) -> Result<()> {
    crate::paths::out_dir_exists(args.out)?;
    let (_, tcfg, mcfg) = RunDir::open(args.run)?;
    let (pred, weights) = Predictor::from_run(args.run, device)?;
    let opts = ProbeOptions {
        lattice: args.lattice,
        span: args.span,
        views: args.views.unwrap_or(tcfg.test_views),
        max_frames: args.frames,
        sigma: tcfg.loss.heatmap_sigma,
    };
    let initial = mvmp_train::train::seeded_init(&mcfg, device, tcfg.seed);
    let models = [("trained", &pred.model), ("initial", &initial)];
    let mut scores = Vec::new();
    let mut keypoints = serde_json::Map::new();
    let mut mean_mm = None;
    for (label, model) in models {
        let train = read(model, args.data, Split::Train, &opts, device, label)?;
        let test = read(model, args.data, Split::Test, &opts, device, label)?;
        if mean_mm.is_none() {
            let mm = mean_pose_mm(&train, &test);
            println!(
                "{} training and {} held-out people; the training mean pose on the held-out people: {mm:.1} mm",
                train.len(),
                test.len()
            );
            mean_mm = Some((train.len(), test.len(), mm));
        }
        let k = keypoint_summary(&test, mcfg.heatmap_stride() as f32);
        println!(
            "2D keypoints ({label} HRNet, held out): median {:.1} px from the true joint, {:.1}% within one \
             map pixel, {:.1}% within two ({} keypoints)",
            k.median_px,
            100.0 * k.within_one_map_pixel,
            100.0 * k.within_two_map_pixels,
            k.keypoints
        );
        keypoints.insert(label.to_string(), serde_json::to_value(&k)?);
        for s in rows(label, &train, &test)? {
            println!(
                "{:<40} {:>6} features  R2 {:>7.3}  {:>6.1} mm  (ridge {})",
                s.features, s.dims, s.r2, s.joint_mm, s.ridge
            );
            scores.push(s);
        }
    }
    let own = decoder_read(&pred, args.data, opts.views, device)?;
    let mm = |x: Option<f64>| x.map_or("-".into(), |mm| format!("{mm:.1}"));
    println!(
        "the model's own prediction (held out, its own roots; {} of {} people matched within {} m): {} mm, \
         {} mm turned with its own heading",
        own.matched,
        own.people,
        OWN_GATE,
        mm(own.mm),
        mm(own.mm_own_heading)
    );
    let (train_people, test_people, mean_pose_mm) = mean_mm.unwrap_or_default();
    if let Some(out) = args.out {
        let report = serde_json::json!({
            "run": args.run, "weights": weights, "data": args.data,
            "lattice": args.lattice, "span_m": args.span, "views": opts.views,
            "train_people": train_people, "test_people": test_people,
            "mean_pose_mm": mean_pose_mm, "scores": scores,
            "keypoints_held_out": keypoints,
            "model_prediction": own,
        });
        mvmp_io::write_atomic_with(out, |w| {
            serde_json::to_writer_pretty(&mut *w, &report).map_err(std::io::Error::other)
        })?;
    }
    Ok(())
}

/// Every held-out person's keypoint errors together.
fn keypoint_summary(people: &[ProbedPerson], stride: f32) -> KeypointSummary {
    let all: Vec<f32> = people.iter().flat_map(|p| p.keypoint_px.clone()).collect();
    summarise(&all, stride)
}

fn read(
    model: &MvmpHmr,
    data: &Path,
    split: Split,
    opts: &ProbeOptions,
    device: &Device,
    label: &str,
) -> Result<Vec<ProbedPerson>> {
    let mut pb = LazyBar::new("probe", false);
    let people = collect(model, data, split, opts, device, |i, n| pb.done(i, n))
        .with_context(|| format!("reading the {} split ({label} weights)", split.name()))?;
    pb.finish();
    if people.is_empty() {
        bail!(
            "{}: the {} split has no person with annotated hips and shoulders to probe",
            data.display(),
            split.name()
        );
    }
    let scenes = scene_count(&people);
    if split == Split::Train && scenes < 2 {
        bail!(
            "{}: the people read from the train split come from {scenes} scene (--frames {}): the \
             probe needs at least 2, to choose its ridge on one and fit on the rest",
            data.display(),
            opts.max_frames
        );
    }
    Ok(people)
}

/// What one row of the probe reads of a person.
type Features = dyn Fn(&ProbedPerson) -> Vec<f32>;

/// The feature sets probed for one model: the root height alone, each volume, and each with the height.
/// The height and the ground-truth maps do not depend on the weights, and where the initial weights put
/// the roots says nothing: those rows are read once, with the trained model.
fn rows(label: &str, train: &[ProbedPerson], test: &[ProbedPerson]) -> Result<Vec<ProbeScore>> {
    let with_height = |a: &[f32], p: &ProbedPerson| [a, &p.height].concat();
    let own = |a: &[f32], p: &ProbedPerson| [a, &p.own_height].concat();
    // (name, read for every model, what it reads)
    let sets: [(&str, bool, Box<Features>); 15] = [
        ("root height", false, Box::new(|p| p.height.clone())),
        ("image-feature volume", true, Box::new(|p| p.volume.clone())),
        (
            "image-feature volume + height",
            true,
            Box::new(move |p| with_height(&p.volume, p)),
        ),
        ("heatmap volume", true, Box::new(|p| p.heatmaps.clone())),
        (
            "heatmap volume + height",
            true,
            Box::new(move |p| with_height(&p.heatmaps, p)),
        ),
        ("heatmap centroids", true, Box::new(|p| p.centroids.clone())),
        (
            "heatmap centroids + height",
            true,
            Box::new(move |p| with_height(&p.centroids, p)),
        ),
        (
            "ground-truth heatmap volume",
            false,
            Box::new(|p| p.true_heatmaps.clone()),
        ),
        (
            "ground-truth heatmap volume + height",
            false,
            Box::new(move |p| with_height(&p.true_heatmaps, p)),
        ),
        (
            "ground-truth heatmap centroids + height",
            false,
            Box::new(move |p| with_height(&p.true_centroids, p)),
        ),
        (
            "the model's root height",
            false,
            Box::new(|p| p.own_height.clone()),
        ),
        (
            "heatmap volume + height at the model's roots",
            false,
            Box::new(move |p| own(&p.own_heatmaps, p)),
        ),
        (
            "ground-truth heatmap volume + height at the model's roots",
            false,
            Box::new(move |p| own(&p.own_true_heatmaps, p)),
        ),
        (
            "ground-truth heatmap volume + height at the model's roots, true heading",
            false,
            Box::new(move |p| own(&p.own_root_true_heatmaps, p)),
        ),
        (
            "ground-truth heatmap volume + height at the true roots, model's heading",
            false,
            Box::new(move |p| with_height(&p.own_heading_true_heatmaps, p)),
        ),
    ];
    (sets.iter())
        .filter(|(_, each, _)| *each || label == "trained")
        .map(|(name, each, f)| {
            let name = match each {
                true => format!("{name}, {label}"),
                false => name.to_string(),
            };
            score(&name, train, test, f).map_err(|e| anyhow::anyhow!("{}: {e}", name))
        })
        .collect()
}

/// Metres within which a prediction's pelvis is a held-out person's.
const OWN_GATE: f64 = 0.5;

/// The model's own body pose in the probe's terms: its predicted joints for each held-out person
/// (the prediction whose pelvis is nearest theirs, within [`OWN_GATE`]) as offsets from its pelvis in the
/// person's true frame, against the true ones. What the decoder reads, beside what a linear read could.
#[derive(Debug, Clone, Default, serde::Serialize)]
struct DecoderRead {
    people: usize,
    matched: usize,
    /// `None` when no prediction matched.
    mm: Option<f64>,
    /// The same with the predicted joints turned with the heading of their own hips and shoulders: the
    /// pose without the body's error of heading.
    mm_own_heading: Option<f64>,
}

fn decoder_read(
    pred: &Predictor,
    data: &Path,
    views: usize,
    device: &Device,
) -> Result<DecoderRead> {
    let (seqs, _) = mvmp_eval::drivers::mvmp_split(data, Split::Test, device)?;
    let (mut guess, mut turned, mut truth, mut people) = (Vec::new(), Vec::new(), Vec::new(), 0);
    let mut pb = LazyBar::new("predict", false);
    let pairs = mvmp_data::sequence::frame_pairs(&seqs);
    for (i, &(si, fi)) in pairs.iter().enumerate() {
        pb.done(i, pairs.len());
        let frame = seqs[si].frame(fi)?;
        let FramePeople::Smplx(annotated) = &frame.people else {
            continue;
        };
        let at = EvalFrame {
            sequence: seqs[si].as_ref(),
            index: fi,
            frame: &frame,
        };
        let found = mvmp_eval::drivers::predict_frame(pred, views, &at)?;
        for person in annotated {
            let cover = vec![true; person.joints_3d.len()];
            let Some(heading) = joint_heading(&person.joints_3d, &cover) else {
                continue;
            };
            people += 1;
            let joints = |p: &PersonPrediction| -> Vec<[f64; 3]> {
                p.joints.iter().map(|j| j.map(f64::from)).collect()
            };
            let pelvises = found.iter().map(|p| p.pelvis.map(f64::from));
            if let Some(p) = nearest_within(pelvises, person.pelvis, OWN_GATE).map(|i| &found[i]) {
                let j = joints(p);
                let own = joint_heading(&j, &vec![true; j.len()]).unwrap_or(heading);
                guess.push(body_frame_offsets(&j, heading));
                turned.push(body_frame_offsets(&j, own));
                truth.push(body_frame_offsets(&person.joints_3d, heading));
            }
        }
    }
    pb.finish();
    Ok(DecoderRead {
        people,
        matched: guess.len(),
        mm: (!guess.is_empty()).then(|| pose_mm(&guess, &truth)),
        mm_own_heading: (!turned.is_empty()).then(|| pose_mm(&turned, &truth)),
    })
}
