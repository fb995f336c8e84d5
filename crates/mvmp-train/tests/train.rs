//! Training end to end on a small synthetic dataset and a small model: one batch is overfitted, an
//! interrupted run resumes to exactly the weights of an uninterrupted one, a diverging run stops naming the
//! term and the step, and inference outputs load back and reproject into their overlays.
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::OnceLock;
use std::sync::atomic::AtomicBool;

use burn::data::dataloader::batcher::Batcher;
use burn::module::{Module, ModuleVisitor, Param};
use burn::optim::{AdamConfig, GradientsParams};
use burn::tensor::{Device, Tensor};
use mvmp_data::dataset::FrameDataset;
use mvmp_data::loader::{FrameBatcher, Split, ViewChoice};
use mvmp_data::sources::{open_h36m, open_panoptic};
use mvmp_data::synth::{SynthConfig, generate};
use mvmp_eval::Evaluator;
use mvmp_eval::drivers::{PseudoGt, PseudoGtCount, evaluate_joint_sequences, pose_params};
use mvmp_eval::joint_sets::JointSet;
use mvmp_geom::VoxelGrid;
use mvmp_infer::output::{read_people_npz, write_frame, write_people_npz};
use mvmp_infer::{PersonPrediction, Predictor, load_weights};
use mvmp_losses::MeshFrame;
use mvmp_model::{ModelConfig, MvmpHmr};
use mvmp_smplx::SmplxLayer;
use mvmp_smplx::names::NUM_BODY;
use mvmp_train::step::{Stage2, stage1_loss, stage2_loss};
use mvmp_train::{Outcome, Quiet, RunDir, TrainConfig, TrainError, TrainOptions};

/// Panoptic sequences read in place and scored, as `mvmp eval --format panoptic` does.
#[allow(clippy::too_many_arguments)]
fn evaluate_panoptic(
    pred: &Predictor,
    root: &Path,
    sequences: &[String],
    stride: usize,
    cameras: &[&str],
    max_frames: usize,
    gate: f64,
    pseudo: Option<&PseudoGt>,
    each: impl FnMut(usize, usize),
) -> Result<(Evaluator, PseudoGtCount), TrainError> {
    let seqs = open_panoptic(root, sequences, cameras, stride)?;
    score(
        pred,
        &seqs,
        JointSet::Panoptic15,
        max_frames,
        gate,
        pseudo,
        each,
    )
}

/// Human3.6M read in place and scored, as `mvmp eval --format h36m` does.
#[allow(clippy::too_many_arguments)]
fn evaluate_h36m(
    pred: &Predictor,
    root: &Path,
    subjects: &[String],
    stride: usize,
    cameras: &[&str],
    max_frames: usize,
    gate: f64,
    pseudo: Option<&PseudoGt>,
    each: impl FnMut(usize, usize),
) -> Result<(Evaluator, PseudoGtCount), TrainError> {
    let seqs = open_h36m(root, subjects, cameras, stride)?;
    score(
        pred,
        &seqs,
        JointSet::H36m17,
        max_frames,
        gate,
        pseudo,
        each,
    )
}

/// Joint-annotated sequences scored; `each(i, n)` after every frame.
fn score(
    pred: &Predictor,
    seqs: &[Box<dyn mvmp_data::sequence::Sequence>],
    set: JointSet,
    max_frames: usize,
    gate: f64,
    pseudo: Option<&PseudoGt>,
    mut each: impl FnMut(usize, usize),
) -> Result<(Evaluator, PseudoGtCount), TrainError> {
    let done = |i, n, _| {
        each(i, n);
        Ok(())
    };
    Ok(evaluate_joint_sequences(
        pred, seqs, set, max_frames, gate, pseudo, done,
    )?)
}

fn dataset() -> &'static Path {
    static DIR: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    let (_, p) = DIR.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("ds");
        let mut c = SynthConfig {
            name: "train-test".into(),
            seed: 5,
            scenes: 3,
            frames_per_scene: 2,
            people: [2, 3],
            area: [3.0, 3.0],
            image_size: [160, 120],
            ..Default::default()
        };
        c.cameras.count = 3;
        c.cameras.rings[0].radius = 5.0;
        generate(&c, &out, Path::new("."), &|| {}).unwrap();
        (dir, out)
    });
    p
}

fn model_config() -> ModelConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/model/tiny.toml");
    let mut c = ModelConfig::read(&path).unwrap();
    c.image_size = 64;
    c.grid = VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [16, 16, 4]).unwrap();
    c.max_people = 3;
    c.decoder.dim = 32;
    c.rootnet_width = 0.25;
    // Every top-K peak counts as a person, so inference always has people to write.
    c.root_threshold = -1e9;
    c
}

/// A run config written beside its model config; `edit` adjusts the TOML text.
fn write_configs(dir: &Path, edit: &dyn Fn(String) -> String) -> PathBuf {
    std::fs::write(
        dir.join("model.toml"),
        toml::to_string(&model_config()).unwrap(),
    )
    .unwrap();
    let text = format!(
        r#"model = "model.toml"
data = "{}"
seed = 3
train_views = 2
test_views = 3
keep_checkpoints = 2
[stage1]
epochs = 1
lr = 1e-3
[stage2]
epochs = 1
lr = 1e-3
"#,
        dataset().display()
    );
    let path = dir.join("train.toml");
    std::fs::write(&path, edit(text)).unwrap();
    path
}

fn options(stop_after: Option<u64>) -> TrainOptions {
    TrainOptions {
        device: Device::flex(),
        stop: Arc::new(AtomicBool::new(false)),
        stop_after_steps: stop_after,
        stop_after_time: None,
    }
}

fn new_run(
    dir: &Path,
    name: &str,
    edit: &dyn Fn(String) -> String,
) -> (RunDir, TrainConfig, ModelConfig) {
    let (cfg, model) = TrainConfig::read(&write_configs(dir, edit)).unwrap();
    let run = RunDir::create(&dir.join(name), &cfg, &model, Some(dataset())).unwrap();
    RunDir::open(&run.root).unwrap()
}

/// Every float parameter, in visiting order.
fn weights<M: Module>(m: &M) -> Vec<f32> {
    struct All(Vec<f32>);
    impl ModuleVisitor for All {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            self.0
                .extend(p.val().into_data().convert::<f32>().iter::<f32>());
        }
    }
    let mut a = All(Vec::new());
    m.visit(&mut a);
    a.0
}

/// The weights of a module's convolution and linear kernels (parameters of two or more axes).
fn kernels<M: Module>(m: &M) -> Vec<f32> {
    struct Kernels(Vec<f32>);
    impl ModuleVisitor for Kernels {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            if D >= 2 {
                self.0
                    .extend(p.val().into_data().convert::<f32>().iter::<f32>());
            }
        }
    }
    let mut k = Kernels(Vec::new());
    m.visit(&mut k);
    k.0
}

fn load(run: &Path, cfg: &ModelConfig) -> Vec<f32> {
    let mut m = mvmp_train::seeded_init(cfg, &Device::flex(), 0);
    load_weights(&mut m, &run.join("model.bpk")).unwrap();
    weights(&m)
}

/// The largest difference between two runs' final weights (they must hold as many).
fn weight_gap(a: &RunDir, b: &RunDir, cfg: &ModelConfig) -> f32 {
    let (wa, wb) = (load(&a.root, cfg), load(&b.root, cfg));
    assert_eq!(wa.len(), wb.len());
    wa.iter()
        .zip(&wb)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max)
}

#[test]
fn a_few_steps_on_one_batch_lower_the_loss() {
    let ad = Device::flex().autodiff();
    let cfg = model_config();
    let mut model = mvmp_train::seeded_init(&cfg, &ad, 1);
    let ds =
        FrameDataset::open(dataset(), Split::Train, ViewChoice::Fixed(vec![0, 1]), 64).unwrap();
    let body = ds.layout().unwrap().body_model().unwrap();
    model = model.with_body(Arc::new(body.clone()));
    let batch = FrameBatcher::with_vertices(body).batch(vec![ds.load(0).unwrap()], &ad);
    let weights = mvmp_losses::LossWeights::default();
    let mut optim = AdamConfig::new().init();
    let mut totals = Vec::new();
    for _ in 0..8 {
        let l = stage2_loss(&model, &batch, &Stage2::at_true_roots(&weights), &ad);
        assert_eq!(l.queries, batch.counts[0]);
        totals.push(l.total.clone().into_scalar::<f32>());
        let g = GradientsParams::from_grads(l.total.backward(), &model);
        model = optim.step(1e-3, model, g);
    }
    assert!(
        totals[7] < 0.75 * totals[0],
        "stage 2 total loss did not fall clearly: {totals:?}"
    );
    // Stage 1 as the demo trains it: the offset L1 down-weighted so the volume MSE and heatmaps lead.
    let weights = mvmp_losses::LossWeights {
        detection_offset: 0.02,
        ..weights
    };
    let mut optim = AdamConfig::new().init();
    let mut totals = Vec::new();
    for _ in 0..10 {
        let l = stage1_loss(&model, &batch, &weights, &ad);
        totals.push(l.total.clone().into_scalar::<f32>());
        let g = GradientsParams::from_grads(l.total.backward(), &model);
        model = optim.step(1e-3, model, g);
    }
    assert!(
        totals[9] < 0.75 * totals[0],
        "stage 1 total loss did not fall clearly: {totals:?}"
    );
}

/// A facing head of heading bins trains through stage 1: its cross-entropy term starts near ln N (an
/// untrained head spreads its softmax evenly) and falls over a few steps on one batch.
#[test]
fn a_binned_facing_head_learns_in_stage_one() {
    let ad = Device::flex().autodiff();
    let mut cfg = model_config();
    cfg.facing_bins = 12;
    cfg.validate().unwrap();
    let mut model = mvmp_train::seeded_init(&cfg, &ad, 1);
    let ds =
        FrameDataset::open(dataset(), Split::Train, ViewChoice::Fixed(vec![0, 1]), 64).unwrap();
    let body = ds.layout().unwrap().body_model().unwrap();
    let batch = FrameBatcher::with_vertices(body).batch(vec![ds.load(0).unwrap()], &ad);
    let weights = mvmp_losses::LossWeights {
        facing: 1.0,
        ..Default::default()
    };
    let mut optim = AdamConfig::new().init();
    let mut terms = Vec::new();
    for _ in 0..10 {
        let l = stage1_loss(&model, &batch, &weights, &ad);
        let f = l.terms.iter().find(|t| t.0 == "facing").unwrap();
        terms.push(f.1.clone().into_scalar::<f32>());
        let g = GradientsParams::from_grads(l.total.backward(), &model);
        model = optim.step(1e-3, model, g);
    }
    assert!((terms[0] - 12f32.ln()).abs() < 0.5, "{terms:?}");
    assert!(terms[9] < 0.8 * terms[0], "{terms:?}");
}

/// A ViT heatmap head gives the ViT a gradient of its own: in stage 2 its term alone reaches the ViT and
/// the feature reduction (and not the decoder) and falls over a few steps on one batch; stage 1 has it
/// too, reaching the ViT and not HRNet.
#[test]
fn a_vit_heatmap_head_trains_the_vit_in_both_stages() {
    let ad = Device::flex().autodiff();
    let mut cfg = model_config();
    cfg.vit_heatmaps = true;
    let ds =
        FrameDataset::open(dataset(), Split::Train, ViewChoice::Fixed(vec![0, 1]), 64).unwrap();
    let body = ds.layout().unwrap().body_model().unwrap();
    let mut model = mvmp_train::seeded_init(&cfg, &ad, 1).with_body(Arc::new(body.clone()));
    let batch = FrameBatcher::with_vertices(body).batch(vec![ds.load(0).unwrap()], &ad);
    let weights = mvmp_losses::LossWeights {
        vit_heatmap: 100.0,
        ..Default::default()
    };
    let term = |m: &MvmpHmr| {
        let l = stage2_loss(m, &batch, &Stage2::at_true_roots(&weights), &ad);
        l.terms
            .into_iter()
            .find(|t| t.0 == "vit_heatmap")
            .unwrap()
            .1
    };
    let norms = mvmp_train::diagnostics::module_grad_norms(&model, &term(&model).backward());
    let norm = |name: &str| norms.iter().find(|n| n.0 == name).unwrap().1;
    assert!(norm("vit") > 0.0 && norm("reduce") > 0.0, "{norms:?}");
    assert_eq!(norm("decoder"), 0.0, "{norms:?}");
    let mut optim = AdamConfig::new().init();
    let mut values = Vec::new();
    for _ in 0..10 {
        let t = term(&model);
        values.push(t.clone().into_scalar::<f32>());
        model = optim.step(
            1e-3,
            model.clone(),
            GradientsParams::from_grads(t.backward(), &model),
        );
    }
    assert!(values[9] < 0.8 * values[0], "{values:?}");
    // Stage 1 trains the ViT and the head beside detection, as a pretraining.
    let l = stage1_loss(&model, &batch, &weights, &ad);
    let t = l
        .terms
        .into_iter()
        .find(|t| t.0 == "vit_heatmap")
        .unwrap()
        .1;
    let norms = mvmp_train::diagnostics::module_grad_norms(&model, &t.backward());
    let norm = |name: &str| norms.iter().find(|n| n.0 == name).unwrap().1;
    assert!(norm("vit") > 0.0 && norm("vit_joints") > 0.0, "{norms:?}");
    assert_eq!(norm("hrnet"), 0.0, "{norms:?}");
    // The head without its loss would stay untrained: refused, naming the key.
    let dir = tempfile::tempdir().unwrap();
    let path = write_configs(dir.path(), &|s| s);
    std::fs::write(
        dir.path().join("model.toml"),
        toml::to_string(&cfg).unwrap(),
    )
    .unwrap();
    let e = TrainConfig::read(&path).unwrap_err().to_string();
    assert!(
        e.contains("loss.vit_heatmap") && e.contains("vit_heatmaps = true"),
        "{e}"
    );
    let with_loss = write_configs(dir.path(), &|s| format!("{s}[loss]\nvit_heatmap = 1.0\n"));
    std::fs::write(
        dir.path().join("model.toml"),
        toml::to_string(&cfg).unwrap(),
    )
    .unwrap();
    TrainConfig::read(&with_loss).unwrap();
}

#[test]
fn an_interrupted_run_resumes_to_the_same_weights_and_log() {
    let dir = tempfile::tempdir().unwrap();
    let keep = |s: String| s;
    // Straight through: 4 training frames, 1 epoch per stage = 8 steps.
    let (run_a, cfg, model) = new_run(dir.path(), "a", &keep);
    let out = mvmp_train::train(&run_a, &cfg, &model, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    // Stopped mid stage 1 and again mid stage 2, resumed each time.
    let (run_b, cfg_b, model_b) = new_run(dir.path(), "b", &keep);
    for (stop, step) in [(Some(3), 3), (Some(6), 6)] {
        match mvmp_train::train(&run_b, &cfg_b, &model_b, &options(stop), &mut Quiet).unwrap() {
            Outcome::Interrupted {
                global_step,
                checkpoint,
            } => {
                assert_eq!(global_step, step);
                assert!(checkpoint.exists());
            }
            o => panic!("expected an interruption, got {o:?}"),
        }
        let s = run_b.state().unwrap().unwrap();
        assert_eq!((s.global_step, s.finished), (step, false));
    }
    let (run_b, cfg_b, model_b) = RunDir::open(&run_b.root).unwrap();
    let out = mvmp_train::train(&run_b, &cfg_b, &model_b, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    // The logs agree step for step (losses of the same batches with the same weights).
    trained_alike(&run_a, &run_b, &model);
    // Validation ran every epoch of both stages.
    let log = std::fs::read_to_string(run_a.metrics_path()).unwrap();
    // Gradient norms per module: stage 1's graph holds HRNet and the RootNet only; stage 2's everything.
    for v in log
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|v| v["kind"] == "step")
    {
        let g = |m: &str| v["grad_norm"][m].as_f64().unwrap();
        assert!(g("hrnet") > 0.0 && g("rootnet") > 0.0, "{v}");
        if v["stage"] == 1 {
            assert_eq!((g("vit"), g("decoder")), (0.0, 0.0), "{v}");
        } else {
            assert!(g("vit") > 0.0 && g("decoder") > 0.0, "{v}");
        }
        // The step's time split into its phases, within the step's own time.
        let phases = v["phase_seconds"].as_object().unwrap();
        let mut names: Vec<&str> = phases.keys().map(String::as_str).collect();
        names.sort_unstable();
        assert_eq!(
            names,
            ["backward", "forward", "grad_norm", "load", "optimizer"],
            "{v}"
        );
        let split: f64 = phases.values().map(|x| x.as_f64().unwrap()).sum();
        assert!(phases.values().all(|x| x.as_f64().unwrap() >= 0.0), "{v}");
        assert!(split <= v["seconds"].as_f64().unwrap() + 1e-6, "{v}");
    }
    assert!(log.contains("\"root_recall\""), "stage 1 validation");
    assert!(log.contains("\"recall_500\""), "stage 2 validation");
    // Only the newest checkpoints are kept; the final weights and resolved configs are there.
    let ckpts: Vec<_> = std::fs::read_dir(run_a.root.join("checkpoints"))
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    assert_eq!(
        ckpts.iter().filter(|f| f.starts_with("step")).count(),
        2,
        "{ckpts:?}"
    );
    assert_eq!(
        ckpts.iter().filter(|f| f.starts_with("optim-")).count(),
        1,
        "{ckpts:?}"
    );
    assert!(run_a.state().unwrap().unwrap().finished);
    // A finished run resumes to "finished" without training.
    let n = log.lines().count();
    assert_eq!(
        mvmp_train::train(&run_a, &cfg, &model, &options(None), &mut Quiet).unwrap(),
        Outcome::Finished
    );
    assert_eq!(
        std::fs::read_to_string(run_a.metrics_path())
            .unwrap()
            .lines()
            .count(),
        n
    );
}

/// The step lines' totals of a run's log, by global step.
fn step_totals(r: &RunDir) -> Vec<(u64, f64)> {
    std::fs::read_to_string(r.metrics_path())
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|v| v["kind"] == "step")
        .map(|v| {
            (
                v["global_step"].as_u64().unwrap(),
                v["total"].as_f64().unwrap(),
            )
        })
        .collect()
}

/// Two runs of 8 steps trained alike: the same steps logged with the same losses (to 1e-5), and final
/// weights within 1e-6.
/// Train `run` to its end; the model it started from (its seed's initialisation) and the one it ended
/// with.
fn trained_from_start(
    run: &RunDir,
    cfg: &TrainConfig,
    model_cfg: &ModelConfig,
) -> (MvmpHmr, MvmpHmr) {
    let out = mvmp_train::train(run, cfg, model_cfg, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    let start = mvmp_train::seeded_init(model_cfg, &Device::flex(), cfg.seed);
    let mut end = mvmp_train::seeded_init(model_cfg, &Device::flex(), 0);
    load_weights(&mut end, &run.root.join("model.bpk")).unwrap();
    (start, end)
}

fn trained_alike(a: &RunDir, b: &RunDir, model: &ModelConfig) {
    let (la, lb) = (step_totals(a), step_totals(b));
    assert_eq!(la.len(), 8);
    assert_eq!(
        la.iter().map(|x| x.0).collect::<Vec<_>>(),
        lb.iter().map(|x| x.0).collect::<Vec<_>>()
    );
    for (x, y) in la.iter().zip(&lb) {
        assert!(
            (x.1 - y.1).abs() <= 1e-5 * x.1.abs().max(1.0),
            "{x:?} vs {y:?}"
        );
    }
    let gap = weight_gap(a, b, model);
    assert!(gap <= 1e-6, "final weights differ by up to {gap}");
}

/// A run branched from another's stage 1 trains as a run of its own config does, and only a config
/// whose stage 1 trains alike may branch.
#[test]
fn a_branched_run_goes_on_from_another_runs_stage_one() {
    let dir = tempfile::tempdir().unwrap();
    // Loss terms stage 1 does not read.
    let ablated = |s: String| s + "[loss]\norientation = 0.0\ndensity = 0.0\n";
    let (own, cfg, model) = new_run(dir.path(), "own", &ablated);
    let out = mvmp_train::train(&own, &cfg, &model, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    let (donor, donor_cfg, _) = new_run(dir.path(), "donor", &|s| s);
    assert!(cfg.same_stage1(&donor_cfg) && donor_cfg.same_stage1(&cfg));
    assert_ne!(cfg, donor_cfg);
    // Stopped at the end of stage 1 (4 frames, one epoch).
    let out = mvmp_train::train(&donor, &donor_cfg, &model, &options(Some(4)), &mut Quiet);
    assert!(
        matches!(out, Ok(Outcome::Interrupted { global_step: 4, .. })),
        "{out:?}"
    );
    let root = dir.path().join("branched");
    let branched = RunDir::branch(&donor, &root, &cfg, &model).unwrap();
    let (branched, bcfg, bmodel) = RunDir::open(&branched.root).unwrap();
    assert_eq!((bcfg.loss.orientation, bcfg.loss.density), (0.0, 0.0));
    let out = mvmp_train::train(&branched, &bcfg, &bmodel, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    trained_alike(&own, &branched, &model);

    // Refused, leaving nothing: a stage 1 of its own, a run past stage 1, another model.
    let mut other = cfg.clone();
    other.stage1.lr *= 2.0;
    assert!(!other.same_stage1(&donor_cfg));
    let mut other_model = model.clone();
    other_model.decoder.dim = 64;
    for (from, cfg, model, what) in [
        (&donor, &other, &model, "its stage 1 would not train as"),
        (&own, &cfg, &model, "has no stage-1 checkpoint"),
        (&donor, &cfg, &other_model, "is not the model of the run"),
    ] {
        let to = dir.path().join("refused");
        let e = RunDir::branch(from, &to, cfg, model)
            .unwrap_err()
            .to_string();
        assert!(e.contains(what), "{e}");
        assert!(!to.exists(), "{e}");
    }
}

/// `epoch_frames` shorter than the set: every epoch has that many steps, each validated, and a run
/// stopped inside one resumes to the same losses and weights.
#[test]
fn short_epochs_train_and_resume_like_whole_ones() {
    let dir = tempfile::tempdir().unwrap();
    let edit = |s: String| {
        s.replace(
            "keep_checkpoints = 2\n",
            "keep_checkpoints = 2\nepoch_frames = 3\n",
        )
        .replacen("epochs = 1", "epochs = 2", 1)
    };
    let (run_a, cfg, model) = new_run(dir.path(), "a", &edit);
    assert_eq!(cfg.epoch_frames, 3);
    let out = mvmp_train::train(&run_a, &cfg, &model, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    let (run_b, cfg_b, model_b) = new_run(dir.path(), "b", &edit);
    let stopped = mvmp_train::train(&run_b, &cfg_b, &model_b, &options(Some(4)), &mut Quiet);
    assert!(
        matches!(stopped, Ok(Outcome::Interrupted { global_step: 4, .. })),
        "{stopped:?}"
    );
    let (run_b, cfg_b, model_b) = RunDir::open(&run_b.root).unwrap();
    let out = mvmp_train::train(&run_b, &cfg_b, &model_b, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    let lines = |r: &RunDir, kind: &str| -> Vec<serde_json::Value> {
        std::fs::read_to_string(r.metrics_path())
            .unwrap()
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .filter(|v| v["kind"] == kind)
            .collect()
    };
    let (la, lb) = (lines(&run_a, "step"), lines(&run_b, "step"));
    // 2 + 1 epochs of 3 frames (the set has 4).
    assert_eq!(la.len(), 9);
    assert_eq!(la.len(), lb.len());
    for (a, b) in la.iter().zip(&lb) {
        let (x, y) = (a["total"].as_f64().unwrap(), b["total"].as_f64().unwrap());
        assert!((x - y).abs() <= 1e-5 * x.abs().max(1.0), "{a} vs {b}");
    }
    assert_eq!(lines(&run_a, "val").len(), 3);
    let max = weight_gap(&run_a, &run_b, &model);
    assert!(max <= 1e-6, "resumed weights differ by up to {max}");
}

/// With `average_decay`, stage 2 ends on the average of its weights, not on the last step's, and a run
/// interrupted in the middle of the stage resumes to the same average.
#[test]
fn a_weight_average_ends_the_run_and_survives_a_resume() {
    let dir = tempfile::tempdir().unwrap();
    let avg = |s: String| s.replace("[stage2]\n", "[stage2]\naverage_decay = 0.5\n");
    let (run_a, cfg, model) = new_run(dir.path(), "a", &avg);
    assert_eq!(cfg.stage2.average_decay, 0.5);
    let out = mvmp_train::train(&run_a, &cfg, &model, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    // Stopped after two of stage 2's four steps, then resumed.
    let (run_b, cfg_b, model_b) = new_run(dir.path(), "b", &avg);
    let out = mvmp_train::train(&run_b, &cfg_b, &model_b, &options(Some(6)), &mut Quiet).unwrap();
    assert!(matches!(out, Outcome::Interrupted { .. }), "{out:?}");
    let s = run_b.state().unwrap().unwrap();
    let saved = run_b
        .root
        .join(s.average.as_deref().expect("an average in the state"));
    assert!(saved.exists(), "{}", saved.display());
    // An unfinished run is evaluated and used with the average, as its validation was.
    assert_eq!(run_b.weights().unwrap(), saved);
    let (run_b, cfg_b, model_b) = RunDir::open(&run_b.root).unwrap();
    let out = mvmp_train::train(&run_b, &cfg_b, &model_b, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    let max = weight_gap(&run_a, &run_b, &model);
    assert!(max <= 1e-6, "resumed averages differ by up to {max}");
    // The final weights are not the last step's.
    let ckpts = run_a.root.join("checkpoints");
    let last = ckpts.join("step0000008-stage2-epoch001.bpk");
    let mut raw = mvmp_train::seeded_init(&model, &Device::flex(), 0);
    load_weights(&mut raw, &last).unwrap();
    let wa = load(&run_a.root, &model);
    let gap = weights(&raw)
        .iter()
        .zip(&wa)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(gap > 1e-6, "the final weights are the last step's");
    // One average beside the newest weights; the step's time names its share.
    let names: Vec<String> = std::fs::read_dir(&ckpts)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    let averages: Vec<&String> = names.iter().filter(|n| n.starts_with("average-")).collect();
    assert_eq!(
        averages,
        ["average-step0000008-stage2-epoch001.bpk"],
        "{names:?}"
    );
    let log = std::fs::read_to_string(run_a.metrics_path()).unwrap();
    let last_step = log
        .lines()
        .rev()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .find(|v| v["kind"] == "step")
        .unwrap();
    assert!(
        last_step["phase_seconds"]["average"].as_f64().is_some(),
        "{last_step}"
    );
}

/// `stage2.pose_fit_frames` fits the decoder's linear pose read in closed form before the final weights:
/// the fit is logged, and it changes the read alone (every other weight is the weight of the same run
/// without it), setting it only where it lowered the held-back error.
#[test]
fn the_pose_read_is_fitted_before_the_final_weights() {
    let dir = tempfile::tempdir().unwrap();
    let mut finals = Vec::new();
    for (name, frames) in [("plain", 0), ("fit", 6)] {
        let d = dir.path().join(name);
        std::fs::create_dir(&d).unwrap();
        let stage2 = format!("[stage2]\npose_fit_frames = {frames}\n");
        let path = write_configs(&d, &|s| s.replace("[stage2]\n", &stage2));
        let model_path = d.join("model.toml");
        let text = std::fs::read_to_string(&model_path).unwrap();
        assert!(text.contains("pose_read = false"), "{text}");
        std::fs::write(
            &model_path,
            text.replace("pose_read = false", "pose_read = true"),
        )
        .unwrap();
        let (cfg, model) = TrainConfig::read(&path).unwrap();
        let run = RunDir::create(&d.join("run"), &cfg, &model, Some(dataset())).unwrap();
        let out = mvmp_train::train(&run, &cfg, &model, &options(None), &mut Quiet).unwrap();
        assert_eq!(out, Outcome::Finished);
        let mut m = mvmp_train::seeded_init(&model, &Device::flex(), 0);
        load_weights(&mut m, &run.root.join("model.bpk")).unwrap();
        let log = std::fs::read_to_string(run.metrics_path()).unwrap();
        let fits: Vec<serde_json::Value> = (log.lines())
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .filter(|v| v["kind"] == "pose_fit")
            .collect();
        finals.push((m, fits));
    }
    let (plain, none) = &finals[0];
    let (fitted, fits) = &finals[1];
    assert!(none.is_empty(), "{none:?}");
    assert_eq!(fits.len(), 1, "{fits:?}");
    let fit = &fits[0]["fit"];
    let (frames, people) = (
        fit["frames"].as_u64().unwrap(),
        fit["people"].as_u64().unwrap(),
    );
    // The dataset's training frames, 2 to 3 people each.
    assert!((2..=6).contains(&frames), "{fit}");
    assert!(people >= 2 * frames, "{fit}");
    let before = fit["held_back_deg"].as_f64().unwrap();
    let after = fit["held_back_fitted_deg"].as_f64().unwrap();
    assert!(before.is_finite() && after.is_finite(), "{fit}");
    let applied = fit["applied"].as_bool().unwrap();
    assert_eq!(applied, after < before, "{fit}");
    let read = |m: &MvmpHmr| weights(m.decoder.pose_read.as_ref().unwrap());
    assert_eq!(read(fitted) != read(plain), applied, "{fit}");
    let rest = |m: &MvmpHmr| {
        let mut m = m.clone();
        m.decoder.pose_read = None;
        weights(&m)
    };
    let (a, b) = (rest(plain), rest(fitted));
    assert_eq!(a.len(), b.len());
    let gap = a
        .iter()
        .zip(&b)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max);
    assert!(gap <= 1e-6, "the fit moved other weights by {gap}");
}

/// With `term_gradients`, each epoch's first step logs every term's module gradient norms: the 2D heatmap
/// loss reaches HRNet but not the RootNet, the parameter loss the decoder but not the RootNet (roots are
/// detached), the detection loss the RootNet but not the decoder.
#[test]
fn term_gradients_show_which_modules_each_loss_reaches() {
    let dir = tempfile::tempdir().unwrap();
    let edit = |s: String| s.replacen("seed = 3", "seed = 3\nterm_gradients = true", 1);
    let (run, cfg, model) = new_run(dir.path(), "terms", &edit);
    let out = mvmp_train::train(&run, &cfg, &model, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    let lines: Vec<serde_json::Value> = std::fs::read_to_string(run.metrics_path())
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .filter(|v: &serde_json::Value| v["kind"] == "grad_terms")
        .collect();
    assert_eq!(lines.len(), 2, "one per epoch, 1 + 1 epochs");
    let g = |v: &serde_json::Value, term: &str, module: &str| {
        v["terms"][term][module]
            .as_f64()
            .unwrap_or_else(|| panic!("{term}.{module} in {v}"))
    };
    let (s1, s2) = (&lines[0], &lines[1]);
    assert!(
        g(s1, "heatmap_2d", "hrnet") > 0.0 && g(s1, "heatmap_2d", "rootnet") == 0.0,
        "{s1}"
    );
    assert!(g(s1, "detection", "rootnet") > 0.0, "{s1}");
    assert!(
        g(s2, "parameters", "decoder") > 0.0 && g(s2, "parameters", "rootnet") == 0.0,
        "{s2}"
    );
    assert!(
        g(s2, "detection", "rootnet") > 0.0 && g(s2, "detection", "decoder") == 0.0,
        "{s2}"
    );
}

#[test]
fn a_wall_time_limit_stops_after_the_step_in_flight_with_a_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let (run, cfg, model) = new_run(dir.path(), "timed", &|s| s);
    let opts = TrainOptions {
        stop_after_time: Some(std::time::Duration::ZERO),
        ..options(None)
    };
    match mvmp_train::train(&run, &cfg, &model, &opts, &mut Quiet).unwrap() {
        Outcome::Interrupted {
            global_step,
            checkpoint,
        } => {
            assert_eq!(global_step, 1);
            assert!(checkpoint.exists());
        }
        o => panic!("expected an interruption, got {o:?}"),
    }
}

/// A fresh run's decoder regresses from the mean parameters of its training people (kept in the
/// checkpoint), not from the default upright T-pose.
#[test]
fn a_fresh_run_starts_its_decoder_at_the_training_mean() {
    let dir = tempfile::tempdir().unwrap();
    let (run, cfg, model) = new_run(dir.path(), "mean", &|s| s);
    let Outcome::Interrupted { checkpoint, .. } =
        mvmp_train::train(&run, &cfg, &model, &options(Some(1)), &mut Quiet).unwrap()
    else {
        panic!("expected a stop after one step");
    };
    let mut m = mvmp_train::seeded_init(&model, &Device::flex(), 0);
    load_weights(&mut m, &checkpoint).unwrap();
    let vals = |t: Tensor<1>| t.into_data().convert::<f32>().try_to_vec::<f32>().unwrap();
    let stored = vals(m.decoder.mean.val());
    let mean = mvmp_eval::drivers::training_mean(dataset())
        .unwrap()
        .unwrap();
    let want = vals(mvmp_eval::drivers::mean_vector(&mean, &Device::flex()));
    let default = vals(mvmp_decoder::mean_params(&Device::flex()));
    assert_eq!(stored, want);
    // The global orientation stays the default; the synthetic people's arms hang, so the shoulders do not.
    assert_eq!(stored[..6], default[..6]);
    let shoulder = 16 * 6;
    let moved: f32 = (0..6)
        .map(|k| (stored[shoulder + k] - default[shoulder + k]).abs())
        .sum();
    assert!(moved > 0.5, "left shoulder 6D moved by {moved}");
}

/// `[init]`: a new run's HRNet and ViT start from the files it names (relative to its config), which
/// must hold those modules whole and with the model's shapes.
#[test]
fn a_new_run_starts_from_pretrained_backbones() {
    let dir = tempfile::tempdir().unwrap();
    let model = model_config();
    let donor = mvmp_train::seeded_init(&model, &Device::flex(), 42);
    let save = |m: &dyn Fn(&std::path::Path) -> Result<(), mvmp_io::IoError>, name: &str| {
        m(&dir.path().join(name)).unwrap();
    };
    save(&|p| mvmp_io::checkpoint::save(&donor.hrnet, p), "hrnet.bpk");
    save(&|p| mvmp_io::checkpoint::save(&donor.vit, p), "vit.bpk");
    let mut fewer = model.clone();
    fewer.heatmap_joints.truncate(5);
    let other = fewer.init(&Device::flex());
    save(
        &|p| mvmp_io::checkpoint::save(&other.hrnet, p),
        "hrnet5.bpk",
    );
    let with_init = |hrnet: &str| {
        let hrnet = hrnet.to_string();
        move |s: String| format!("{s}[init]\nhrnet = \"{hrnet}\"\nvit = \"vit.bpk\"\n")
    };
    let (run, cfg, m) = new_run(dir.path(), "init", &with_init("hrnet.bpk"));
    assert_eq!(
        cfg.init.hrnet.as_deref().map(Path::new),
        Some(
            std::path::absolute(dir.path().join("hrnet.bpk"))
                .unwrap()
                .as_path()
        )
    );
    let Outcome::Interrupted { checkpoint, .. } =
        mvmp_train::train(&run, &cfg, &m, &options(Some(1)), &mut Quiet).unwrap()
    else {
        panic!("expected a stop after one step");
    };
    let mut trained = mvmp_train::seeded_init(&model, &Device::flex(), 0);
    load_weights(&mut trained, &checkpoint).unwrap();
    let gap = |a: Vec<f32>, b: Vec<f32>| {
        assert_eq!(a.len(), b.len());
        a.iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max)
    };
    // Stage 1 leaves the ViT alone; one Adam step at 1e-3 moves each HRNet weight by about 1e-3.
    assert_eq!(gap(weights(&trained.vit), weights(&donor.vit)), 0.0);
    let moved = gap(kernels(&trained.hrnet), kernels(&donor.hrnet));
    assert!(moved <= 1.5e-3, "HRNet kernels {moved} from the donor's");
    let fresh = mvmp_train::seeded_init(&model, &Device::flex(), cfg.seed);
    assert!(gap(kernels(&fresh.hrnet), kernels(&donor.hrnet)) > 0.05);

    // Files that do not fit are refused naming the key and the file, before any step.
    std::fs::write(dir.path().join("text.bpk"), "not weights").unwrap();
    for (name, file, want) in [
        (
            "garbage",
            "text.bpk",
            "cannot be loaded into the model's HRNet",
        ),
        (
            "joints",
            "hrnet5.bpk",
            "cannot be loaded into the model's HRNet `tiny` with 17 heatmap joints",
        ),
        ("module", "vit.bpk", "are not in the file"),
        ("absent", "none.bpk", "no such file"),
    ] {
        let (run, cfg, m) = new_run(dir.path(), name, &with_init(file));
        let err = mvmp_train::train(&run, &cfg, &m, &options(Some(1)), &mut Quiet)
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(file) && err.contains("`init.hrnet`") && err.contains(want),
            "{err}"
        );
        assert!(
            run.state().unwrap().is_none(),
            "{name}: a checkpoint was written"
        );
    }
}

#[test]
fn a_diverging_run_stops_naming_the_term_and_the_step() {
    let dir = tempfile::tempdir().unwrap();
    let (run, cfg, model) = new_run(dir.path(), "nan", &|s| {
        s.replacen("lr = 1e-3", "lr = 1e30", 1)
    });
    let err = mvmp_train::train(&run, &cfg, &model, &options(None), &mut Quiet).unwrap_err();
    match &err {
        TrainError::NonFinite {
            stage, step, term, ..
        } => {
            assert_eq!(*stage, mvmp_train::Stage::Detection);
            assert!(*step >= 2, "the first step's loss is finite: {err}");
            assert!(
                ["detection", "heatmap_2d"].contains(&term.as_str()),
                "{err}"
            );
        }
        e => panic!("expected a non-finite loss error, got {e}"),
    }
    let msg = err.to_string();
    assert!(msg.contains("step") && msg.contains("checkpoint"), "{msg}");
}

#[test]
fn bad_configs_name_the_key() {
    let dir = tempfile::tempdir().unwrap();
    for (edit, key) in [
        (("lr = 1e-3", "lr = -1.0"), "stage1.lr"),
        (("seed = 3", "seed = 3\nbatch_size = 0"), "batch_size"),
        (("seed = 3", "seed = 3\nlearning_rate = 1"), "learning_rate"),
        (
            ("[stage1]", "[loss]\nmesh_3d = -2.0\n[stage1]"),
            "loss.mesh_3d",
        ),
        (
            ("[stage1]", "[loss]\ndetection_sigma = 0.0\n[stage1]"),
            "loss.detection_sigma",
        ),
        (
            ("[stage1]", "[loss]\ndetection_positive = nan\n[stage1]"),
            "loss.detection_positive",
        ),
        (
            ("[stage1]", "[loss]\nheatmap_2d_positive = -1.0\n[stage1]"),
            "loss.heatmap_2d_positive",
        ),
        (
            ("[stage1]", "[loss]\nparameters_body_l2 = inf\n[stage1]"),
            "loss.parameters_body_l2",
        ),
        (
            ("lr = 1e-3", "lr = 1e-3\nfinal_lr_factor = 2.0"),
            "stage1.final_lr_factor",
        ),
        (
            ("lr = 1e-3", "lr = 1e-3\nschedule = \"linear\""),
            "schedule",
        ),
        // The model (tiny.toml's) has a facing head, which nothing else trains.
        (
            ("[stage1]", "[loss]\nfacing = 0.0\n[stage1]"),
            "loss.facing",
        ),
        (
            ("lr = 1e-3", "lr = 1e-3\nfreeze_detection = true"),
            "stage1.freeze_detection",
        ),
        // The model has no joint offsets' head for the term to train.
        (
            ("[stage1]", "[loss]\njoint_offsets = 100.0\n[stage1]"),
            "loss.joint_offsets",
        ),
        // The model has no linear pose read (`decoder.pose_read`) to fit.
        (
            ("[stage2]", "[stage2]\npose_fit_frames = 4"),
            "stage2.pose_fit_frames",
        ),
        (
            ("lr = 1e-3", "lr = 1e-3\npose_fit_frames = 4"),
            "stage1.pose_fit_frames",
        ),
        (
            ("lr = 1e-3", "lr = 1e-3\ndetection_lr = 1e-4"),
            "stage1.detection_lr",
        ),
        (
            ("[stage2]\n", "[stage2]\ndetection_lr = -1.0\n"),
            "stage2.detection_lr",
        ),
        (
            ("[stage2]\n", "[stage2]\naverage_decay = 1.0\n"),
            "stage2.average_decay",
        ),
        (
            ("[stage2]\n", "[stage2]\naverage_decay = nan\n"),
            "stage2.average_decay",
        ),
        (
            (
                "[stage2]\n",
                "[stage2]\ndetection_lr = 1e-4\nfreeze_detection = true\n",
            ),
            "stage2.detection_lr",
        ),
        (
            ("lr = 1e-3", "lr = 1e-3\ncache_volumes = true"),
            "stage1.cache_volumes",
        ),
        (
            ("lr = 1e-3", "lr = 1e-3\ntrain_rootnet = true"),
            "stage1.train_rootnet",
        ),
        // Without freeze_detection the RootNet trains anyway.
        (
            ("[stage2]\n", "[stage2]\ntrain_rootnet = true\n"),
            "stage2.train_rootnet",
        ),
        // The volumes would go stale while the ViT trains.
        (
            (
                "[stage2]\n",
                "[stage2]\ncache_volumes = true\nfreeze_detection = true\n",
            ),
            "stage2.cache_volumes",
        ),
        // One frame a step.
        (
            (
                "keep_checkpoints = 2\n[stage1]\nepochs = 1\nlr = 1e-3\n[stage2]\n",
                "keep_checkpoints = 2\nbatch_size = 2\n[stage1]\nepochs = 1\nlr = 1e-3\n[stage2]\n\
                 cache_volumes = true\nfreeze_detection = true\nfreeze_backbone = true\n",
            ),
            "stage2.cache_volumes",
        ),
        // The model (tiny.toml's) has no ViT heatmap head for this loss to train.
        (
            ("[stage1]", "[loss]\nvit_heatmap = 10.0\n[stage1]"),
            "loss.vit_heatmap",
        ),
        (
            ("[stage1]", "[loss]\nvit_heatmap_sigma = 0.0\n[stage1]"),
            "loss.vit_heatmap_sigma",
        ),
        (("test_views = 3", "test_views = 1000000"), "test_views"),
        (("train_views = 2", "train_views = 0"), "train_views"),
    ] {
        let path = write_configs(dir.path(), &|s| s.replacen(edit.0, edit.1, 1));
        let e = TrainConfig::read(&path).unwrap_err().to_string();
        assert!(e.contains(key) && e.contains("train.toml"), "{key}: {e}");
    }
    // More test views than the validation scenes have cameras: named when the source is checked.
    let path = write_configs(dir.path(), &|s| {
        s.replacen("test_views = 3", "test_views = 9", 1)
    });
    let (cfg, _) = TrainConfig::read(&path).unwrap();
    let e = mvmp_train::check_validation_source(&cfg)
        .unwrap_err()
        .to_string();
    assert!(e.contains("test_views = 9"), "{e}");
    // A validation split the config names that has no frames validates nothing: refused, naming the
    // dataset and the split (a one-scene set holds no held-out scene).
    let one = dir.path().join("one-scene");
    let c = SynthConfig {
        name: "one".into(),
        seed: 2,
        scenes: 1,
        frames_per_scene: 1,
        people: [1, 1],
        area: [3.0, 3.0],
        image_size: [64, 48],
        ..Default::default()
    };
    generate(&c, &one, Path::new("."), &|| {}).unwrap();
    let path = write_configs(dir.path(), &|s| {
        format!(
            "{s}[validation]\nformat = \"mvmp\"\nroot = \"{}\"\nsplit = \"test\"\n",
            one.display()
        )
    });
    let (cfg, _) = TrainConfig::read(&path).unwrap();
    let e = mvmp_train::check_validation_source(&cfg)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("one-scene") && e.contains("test split has no frames"),
        "{e}"
    );
    // More training views than the scenes have cameras: named with the source.
    let path = write_configs(dir.path(), &|s| {
        s.replacen("train_views = 2", "train_views = 9", 1)
    });
    let (cfg, model) = TrainConfig::read(&path).unwrap();
    let e = mvmp_train::open_training_set(&cfg, &model, &path)
        .err()
        .expect("9 views of 3 cameras")
        .to_string();
    assert!(
        e.contains("train_views") && e.contains("9: the frames of data") && e.contains("3 cameras"),
        "{e}"
    );
    // A run directory that holds files is not overwritten.
    let (cfg, model) = TrainConfig::read(&write_configs(dir.path(), &|s| s)).unwrap();
    let e = RunDir::create(dir.path(), &cfg, &model, Some(dataset()))
        .unwrap_err()
        .to_string();
    assert!(e.contains("not empty"), "{e}");
}

#[test]
fn inference_outputs_load_back_and_reproject_into_the_overlays() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = model_config();
    let d = Device::flex();
    let body = mvmp_smplx::standin_model(0);
    let pred = Predictor::new(mvmp_train::seeded_init(&cfg, &d, 2), body, &d);
    let ds =
        FrameDataset::open(dataset(), Split::Test, ViewChoice::Fixed(vec![0, 1, 2]), 64).unwrap();
    let batch = FrameBatcher::default().batch(vec![ds.load(0).unwrap()], &d);
    let people = pred
        .predict(batch.images.clone(), &batch.cameras, &batch.letterboxes)
        .remove(0);
    assert_eq!(people.len(), 3, "threshold -inf keeps the top-K roots");
    let frame = &ds.frame_refs()[0];
    let rig = &ds.layout().unwrap().scenes[frame.scene].rig;
    let ann = mvmp_data::Annotation::read(&frame.dir.join("annotation.json"), rig.len()).unwrap();
    let images: Vec<image::RgbImage> = ann
        .images
        .iter()
        .map(|f| image::open(frame.dir.join(f)).unwrap().to_rgb8())
        .collect();
    let out = dir.path().join("frame");
    write_frame(
        &out,
        &people,
        pred.layer.faces(),
        &rig.cameras,
        Some(&images),
        &cfg.grid,
    )
    .unwrap();

    // people.npz: the standard smplx keys, and posing them again gives the same meshes.
    let mut npz = npyz::npz::NpzArchive::open(out.join("people.npz")).unwrap();
    for (key, width) in [
        ("global_orient", 3),
        ("body_pose", 63),
        ("jaw_pose", 3),
        ("leye_pose", 3),
        ("reye_pose", 3),
        ("left_hand_pose", 45),
        ("right_hand_pose", 45),
        ("betas", 10),
        ("expression", 10),
        ("transl", 3),
        ("pelvis", 3),
    ] {
        let a = npz
            .by_name(key)
            .unwrap()
            .unwrap_or_else(|| panic!("key {key}"));
        assert_eq!(a.shape(), &[3, width], "{key}");
    }
    let stored = read_people_npz(&out.join("people.npz")).unwrap();
    // A NaN score and a shape coefficient of 1e30 are refused, naming the file, key and index.
    let bad = dir.path().join("bad.npz");
    let mut nan = people.clone();
    nan[1].score = f32::NAN;
    write_people_npz(&bad, &nan).unwrap();
    let e = read_people_npz(&bad).unwrap_err().to_string();
    assert!(
        e.contains("bad.npz") && e.contains("`scores`[1] = NaN"),
        "{e}"
    );
    let mut huge = people.clone();
    huge[2].betas[4] = 1e30;
    write_people_npz(&bad, &huge).unwrap();
    let e = read_people_npz(&bad).unwrap_err().to_string();
    assert!(e.contains("person 2") && e.contains("`betas`[4]"), "{e}");
    let posed = pose_params(
        &pred.layer,
        &stored
            .iter()
            .map(|p| (p.params.clone(), p.score))
            .collect::<Vec<_>>(),
    );
    for (p, q) in people.iter().zip(&posed) {
        let v = q.vertices.as_ref().unwrap();
        let max = p
            .vertices
            .iter()
            .zip(v)
            .map(|(a, b)| {
                (0..3)
                    .map(|k| (a[k] as f64 - b[k]).abs())
                    .fold(0.0, f64::max)
            })
            .fold(0.0, f64::max);
        assert!(max < 2e-3, "re-posed stored parameters differ by {max} m");
    }

    // OBJ and PLY parse; the OBJ vertices are the predicted mesh.
    for (i, p) in people.iter().enumerate() {
        let (models, _) = tobj::load_obj(
            out.join(format!("person_{i:02}.obj")),
            &tobj::LoadOptions::default(),
        )
        .unwrap();
        let m = &models[0].mesh;
        assert_eq!(m.positions.len(), p.vertices.len() * 3);
        assert_eq!(m.indices.len(), pred.layer.faces().len() * 3);
        assert!(out.join(format!("person_{i:02}.ply")).exists());
    }

    // Overlays: same size as the inputs; where a mesh vertex projects inside the image, the overlay
    // differs from the input (a mesh was drawn there).
    let (mut inside, mut changed) = (0, 0);
    for (v, cam) in rig.cameras.iter().enumerate() {
        let ov = image::open(out.join(format!("overlay_{v:02}.png")))
            .unwrap()
            .to_rgb8();
        assert_eq!(ov.dimensions(), (cam.width, cam.height));
        for p in &people {
            for x in p.vertices.iter().step_by(7) {
                let (uv, z) = cam.project(&nalgebra::Vector3::new(
                    x[0] as f64,
                    x[1] as f64,
                    x[2] as f64,
                ));
                let (u, w) = (uv.x.round(), uv.y.round());
                if z > 0.1
                    && u >= 1.0
                    && w >= 1.0
                    && u < cam.width as f64 - 1.0
                    && w < cam.height as f64 - 1.0
                {
                    inside += 1;
                    let differs = (-1..=1).any(|dy: i64| {
                        (-1..=1).any(|dx: i64| {
                            let (a, b) = ((u as i64 + dx) as u32, (w as i64 + dy) as u32);
                            ov.get_pixel(a, b) != images[v].get_pixel(a, b)
                        })
                    });
                    changed += differs as usize;
                }
            }
        }
    }
    assert!(inside > 100, "{inside} projected vertices inside the views");
    assert!(
        changed as f64 >= 0.98 * inside as f64,
        "{changed} of {inside} projected vertices fall on drawn pixels"
    );
    let top = image::open(out.join("topdown.png")).unwrap();
    assert_eq!(top.width(), 640);
}

#[test]
fn every_shipped_training_config_reads() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/train");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).unwrap() {
        let p = e.unwrap().path();
        if p.extension().is_some_and(|x| x == "toml") {
            TrainConfig::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
            n += 1;
        }
    }
    assert!(n >= 2, "{n} configs");
}

/// A Panoptic sequence in the real layout: five HD cameras at 160 x 120, `frames` pose files with two
/// people (the second without an annotated body centre in frame 1), a JPEG per camera and frame.
fn panoptic_fixture(root: &Path, name: &str, frames: usize) {
    mvmp_data::fixtures::panoptic_sequence(root, name, frames).unwrap();
}

#[test]
fn a_run_scores_on_panoptic_read_in_place() {
    let root = tempfile::tempdir().unwrap();
    panoptic_fixture(root.path(), "160906_pizza1", 3);
    let cfg = model_config();
    let d = Device::flex();
    let pred = Predictor::new(
        mvmp_train::seeded_init(&cfg, &d, 4),
        mvmp_smplx::standin_model(0),
        &d,
    );
    let cams = &mvmp_data::panoptic::VOXELPOSE_CAMERAS[..3];
    let seqs = vec!["160906_pizza1".to_string()];
    let mut seen = 0;
    let ev = evaluate_panoptic(&pred, root.path(), &seqs, 1, cams, 0, 0.5, None, |_, n| {
        seen = n
    })
    .unwrap()
    .0;
    assert_eq!(seen, 3);
    let m = ev.overall();
    // 2 + 1 + 2 people with an annotated body centre; 3 kept roots per frame.
    assert_eq!(m.ground_truth, 5);
    assert_eq!(m.predictions, 9);
    assert!(
        m.pve_mm.is_none() && m.pa_pve_mm.is_none(),
        "Panoptic has no meshes"
    );
    assert!(ev.per_scene().contains_key("160906_pizza1"));
    // Stride 2 keeps frames 0 and 2.
    let ev = evaluate_panoptic(&pred, root.path(), &seqs, 2, cams, 0, 0.5, None, |_, _| {})
        .unwrap()
        .0;
    assert_eq!(ev.overall().ground_truth, 4);
    // A sequence of the split that is not there, and an image of the wrong size, are named.
    let e = evaluate_panoptic(
        &pred,
        root.path(),
        &["160906_band4".to_string()],
        1,
        cams,
        0,
        0.5,
        None,
        |_, _| {},
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("160906_band4"), "{e}");
    let bad = root
        .path()
        .join("160906_pizza1/hdImgs/00_06/00_06_00000001.jpg");
    image::RgbImage::new(80, 60).save(&bad).unwrap();
    let e = evaluate_panoptic(&pred, root.path(), &seqs, 1, cams, 0, 0.5, None, |_, _| {})
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("00_06_00000001.jpg") && e.contains("80x60"),
        "{e}"
    );
}

/// A Human3.6M tree (mvmp_data::h36m's layout) with the data crate's fixtures: S9 "Walking" (5 frames),
/// the images of the first two cameras at the dataset's sizes, and S11 "Directions" (left out).
fn h36m_fixture(root: &Path) {
    let files = Path::new(env!("CARGO_MANIFEST_DIR")).join("../mvmp-data/tests/fixtures/h36m");
    let sequences = [("S9", "Walking"), ("S11", "Directions")];
    mvmp_data::fixtures::h36m_tree(root, &files, &sequences, 2).unwrap();
}

#[test]
fn a_run_scores_on_h36m_read_in_place() {
    use mvmp_data::h36m::{CAMERAS, image_file};
    let root = tempfile::tempdir().unwrap();
    h36m_fixture(root.path());
    let cfg = model_config();
    let d = Device::flex();
    let pred = Predictor::new(
        mvmp_train::seeded_init(&cfg, &d, 4),
        mvmp_smplx::standin_model(0),
        &d,
    );
    let subjects = ["S9".to_string(), "S11".to_string()];
    let mut seen = 0;
    let ev = evaluate_h36m(
        &pred,
        root.path(),
        &subjects,
        2,
        &CAMERAS[..2],
        0,
        0.5,
        None,
        |_, n| seen = n,
    )
    .unwrap()
    .0;
    // Rows 0, 2 and 4 of S9 "Walking"; S11's "Directions" is left out.
    assert_eq!(seen, 3);
    let m = ev.overall();
    assert_eq!(m.ground_truth, 3);
    assert_eq!(m.predictions, 9);
    assert!(m.pve_mm.is_none() && m.pa_pve_mm.is_none());
    assert_eq!(
        ev.per_scene().keys().cloned().collect::<Vec<_>>(),
        ["S9/Walking"]
    );
    // An image of the wrong size, and a missing one, are named.
    let bad = image_file(root.path(), "S9", "Walking", CAMERAS[1], 2);
    image::RgbImage::new(500, 500).save(&bad).unwrap();
    let run = |cams: &[&str]| {
        evaluate_h36m(
            &pred,
            root.path(),
            &subjects,
            2,
            cams,
            0,
            0.5,
            None,
            |_, _| {},
        )
        .unwrap_err()
        .to_string()
    };
    let e = run(&CAMERAS[..2]);
    assert!(e.contains("000003.jpg") && e.contains("500x500"), "{e}");
    let e = run(&CAMERAS[..3]);
    assert!(e.contains("Walking.58860488/000001.jpg"), "{e}");
}

/// A fit in `people.npz`: the rest pose of the stand-in body with its pelvis at `at`.
fn fit_at(layer: &SmplxLayer, at: [f64; 3]) -> PersonPrediction {
    let rest = pose_params(layer, &[(mvmp_smplx::SmplxParams::default(), 1.0)]);
    let p0 = rest[0].joints[0];
    PersonPrediction {
        score: 1.0,
        pose: vec![0.0; 165],
        betas: [0.0; 10],
        expression: [0.0; 10],
        pelvis: at.map(|x| x as f32),
        transl: [0, 1, 2].map(|a| (at[a] - p0[a]) as f32),
        joints: Vec::new(),
        vertices: Vec::new(),
    }
}

#[test]
fn pseudo_ground_truth_meshes_give_pve_on_joint_datasets() {
    use mvmp_data::h36m::CAMERAS;
    let root = tempfile::tempdir().unwrap();
    h36m_fixture(root.path());
    let cfg = model_config();
    let d = Device::flex();
    let body = mvmp_smplx::standin_model(0);
    let layer = SmplxLayer::new(&body, &d);
    let pred = Predictor::new(mvmp_train::seeded_init(&cfg, &d, 4), body, &d);
    let subjects = ["S9".to_string()];
    // Fits at the annotated pelvis of rows 0, 2, 4 (fixture joint 0: x = 1000 + 5 f, y = -400,
    // z = 900 + f mm), and a second, far one that must not be taken.
    let fits = root.path().join("fits");
    for row in [0usize, 2, 4] {
        let f = row as f64;
        let dir = fits.join(format!("S9/Walking/{:06}", row + 1));
        std::fs::create_dir_all(&dir).unwrap();
        write_people_npz(
            &dir.join("people.npz"),
            &[
                fit_at(&layer, [3.0, 3.0, 0.9]),
                fit_at(
                    &layer,
                    [(1000.0 + 5.0 * f) / 1000.0, -0.4, (900.0 + f) / 1000.0],
                ),
            ],
        )
        .unwrap();
    }
    // The fits are matched within the evaluation's gate, as `mvmp eval --pseudo-gt` matches them.
    let score = |with_fits: bool, gate: f64| {
        let pseudo = PseudoGt {
            dir: fits.clone(),
            layer: layer.clone(),
            gate,
        };
        evaluate_h36m(
            &pred,
            root.path(),
            &subjects,
            2,
            &CAMERAS[..2],
            0,
            gate,
            with_fits.then_some(&pseudo),
            |_, _| {},
        )
    };
    let (_, count) = score(true, 0.5).unwrap();
    assert_eq!((count.with_mesh, count.people), (3, 3));
    // A wide gate matches every person to a prediction, so every person's mesh is compared.
    let (ev, _) = score(true, 100.0).unwrap();
    let m = ev.overall();
    assert_eq!(m.matched, 3);
    assert!(m.pve_mm.is_some_and(|v| v.is_finite() && v > 0.0) && m.pa_pve_mm.is_some());
    // Without fits there are no meshes to compare.
    let (ev, count) = score(false, 100.0).unwrap();
    assert_eq!(count.people, 0);
    assert!(ev.overall().pve_mm.is_none());
    // The near fit is the one taken: with only the far fit left, nobody has a mesh.
    for row in [0usize, 2, 4] {
        let p = fits.join(format!("S9/Walking/{:06}/people.npz", row + 1));
        write_people_npz(&p, &[fit_at(&layer, [3.0, 3.0, 0.9])]).unwrap();
    }
    let (ev, count) = score(true, 0.5).unwrap();
    assert_eq!((count.with_mesh, count.people), (0, 3));
    assert!(ev.overall().pve_mm.is_none());
    // A scored frame without a fit is named.
    std::fs::remove_file(fits.join("S9/Walking/000003/people.npz")).unwrap();
    let e = score(true, 0.5).unwrap_err().to_string();
    assert!(e.contains("S9/Walking/000003/people.npz"), "{e}");
}

/// A Panoptic source over the fixture sequence `160906_pizza1` with the first `views` cameras.
fn panoptic_source(root: &Path, views: usize) -> mvmp_data::sources::SourceSpec {
    mvmp_data::sources::SourceSpec {
        format: mvmp_data::sources::SourceFormat::Panoptic,
        root: root.to_string_lossy().into_owned(),
        split: Some("160906_pizza1".into()),
        stride: Some(1),
        cameras: Some(
            mvmp_data::panoptic::VOXELPOSE_CAMERAS[..views]
                .iter()
                .map(|s| s.to_string())
                .collect(),
        ),
        repeat: None,
        pseudo_gt: None,
    }
}

#[test]
fn panoptic_frames_become_samples_with_their_joints_in_smplx_slots() {
    use mvmp_data::sequence::covered_slots;
    use mvmp_smplx::joint_sets::JointSet;
    let root = tempfile::tempdir().unwrap();
    panoptic_fixture(root.path(), "160906_pizza1", 3);
    // Frame 0, person 0: the left elbow (joints19 index 4) below the confidence threshold.
    let f0 = root
        .path()
        .join("160906_pizza1/hdPose3d_stage1_coco19/body3DScene_00000000.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&f0).unwrap()).unwrap();
    v["bodies"][0]["joints19"][4 * 4 + 3] = serde_json::json!(0.05);
    std::fs::write(&f0, v.to_string()).unwrap();

    let spec = panoptic_source(root.path(), 3);
    let ds = spec
        .open_training(ViewChoice::Fixed(vec![0, 2]), 64)
        .unwrap();
    assert!(
        ds.layout().is_none(),
        "a Panoptic source is not an MVMP-HMR layout"
    );
    assert_eq!(ds.len(), 3);
    let s = ds.load(0).unwrap();
    assert_eq!(
        (s.scene.as_str(), s.frame.as_str()),
        ("160906_pizza1", "00000000")
    );
    assert_eq!(s.cameras.len(), 2);
    assert_eq!(s.cameras[1].name, "00_12");
    assert_eq!(s.people.len(), 2);
    let slots = JointSet::Panoptic15.smplx_indices();
    assert_eq!(s.cover, covered_slots(JointSet::Panoptic15));
    assert_eq!(s.cover.iter().filter(|&&c| c).count(), 15);
    let raw = mvmp_data::panoptic::read_bodies(&f0).unwrap();
    for (p, b) in s.people.iter().zip(&raw) {
        assert!(!p.smplx, "joint-annotated people have no SMPL-X");
        assert_eq!(p.joints_3d.len(), 127);
        for (k, &slot) in slots.iter().enumerate() {
            let want = b.valid(k);
            assert_eq!(p.joint_valid[slot] == 1.0, want, "joint {k} slot {slot}");
            if want {
                for a in 0..3 {
                    assert!((p.joints_3d[slot][a] as f64 - b.joints[k][a]).abs() < 1e-5);
                }
            }
        }
        // Slots outside the set carry nothing.
        let total: f32 = p.joint_valid.iter().sum();
        assert_eq!(total as usize, (0..15).filter(|&k| b.valid(k)).count());
        // The root is the body centre (in the pelvis slot, the model's primary joint).
        assert_eq!(p.pelvis, b.joints[2].map(|x| x as f32));
        // 2D joints: the projection of each annotated joint into each view's network pixels.
        for (vi, (cam, lb)) in s.cameras.iter().zip(&s.letterboxes).enumerate() {
            for (k, &slot) in slots.iter().enumerate() {
                let [u, vv, vis] = p.joints_2d[vi][slot];
                let q = mvmp_data::loader::project_to_network(cam, lb, b.joints[k]);
                let (uv, _) = cam.project(&nalgebra::Vector3::from(b.joints[k]));
                let inside = uv.x >= 0.0
                    && uv.y >= 0.0
                    && uv.x < cam.width as f64
                    && uv.y < cam.height as f64;
                match q {
                    Some(q) if b.valid(k) && inside => {
                        assert_eq!(vis, 1.0);
                        assert!((u as f64 - q.x).abs() < 1e-3 && (vv as f64 - q.y).abs() < 1e-3);
                    }
                    _ => assert_eq!(vis, 0.0, "joint {k} view {vi}"),
                }
            }
        }
    }
    assert_eq!(
        s.people[0].joint_valid[slots[4]], 0.0,
        "the low-confidence elbow"
    );
    // Frame 1: the second person has no annotated body centre and is left out.
    assert_eq!(ds.load(1).unwrap().people.len(), 1);
    // Errors name what is wrong: a sequence of the split that is not there, too many views.
    let e = mvmp_data::sources::SourceSpec {
        split: Some("160906_band4".into()),
        ..spec.clone()
    }
    .open_training(ViewChoice::Fixed(vec![0]), 64)
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("160906_band4"), "{e}");
    let e = spec
        .open_training(ViewChoice::Random { count: 4, seed: 0 }, 64)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("4 views") && e.contains("3 cameras"), "{e}");
}

/// Stage 2 on a batch of joint-annotated people: the SMPL-X terms (parameters, density; orientation needs
/// spine1, which Panoptic lacks) are exactly zero and the joint terms are finite and positive; in a batch
/// with an MVMP-HMR frame beside it every term is active and gradients are finite.
/// Each weighted term of a step's loss by name.
fn term_values(l: &mvmp_train::step::StepLoss) -> std::collections::BTreeMap<&'static str, f32> {
    l.terms
        .iter()
        .map(|(n, t)| (*n, t.clone().into_scalar::<f32>()))
        .collect()
}

/// A model and the two kinds of people to train it on: the synthetic set's (SMPL-X ground truth) and a
/// one-frame Panoptic fixture's (joints only), two views each.
struct TwoKinds {
    _root: tempfile::TempDir,
    ad: Device,
    model: MvmpHmr,
    batcher: FrameBatcher,
    smplx: FrameDataset,
    joints: FrameDataset,
}

fn two_kinds() -> TwoKinds {
    let root = tempfile::tempdir().unwrap();
    panoptic_fixture(root.path(), "160906_pizza1", 1);
    let ad = Device::flex().autodiff();
    let cfg = model_config();
    let model = mvmp_train::seeded_init(&cfg, &ad, 2);
    let joints = panoptic_source(root.path(), 2)
        .open_training(ViewChoice::Fixed(vec![0, 1]), 64)
        .unwrap();
    let smplx =
        FrameDataset::open(dataset(), Split::Train, ViewChoice::Fixed(vec![0, 1]), 64).unwrap();
    let body = smplx.layout().unwrap().body_model().unwrap();
    TwoKinds {
        _root: root,
        model: model.with_body(Arc::new(body.clone())),
        batcher: FrameBatcher::with_vertices(body),
        ad,
        smplx,
        joints,
    }
}

/// A decoder with `joint_offsets` gets the offsets' term at its weight (linear in it, absent at 0) on
/// SMPL-X and joint-annotated people alike, and the term's gradient reaches the offsets' head and read.
#[test]
fn the_joint_offsets_term_trains_the_offsets_head() {
    let k = two_kinds();
    let mut cfg = model_config();
    cfg.decoder.joint_offsets = true;
    let body = k.smplx.layout().unwrap().body_model().unwrap();
    let model = mvmp_train::seeded_init(&cfg, &k.ad, 2).with_body(Arc::new(body));
    let batch = k.batcher.batch(
        vec![k.smplx.load(0).unwrap(), k.joints.load(0).unwrap()],
        &k.ad,
    );
    let loss = |w: f32| {
        let weights = mvmp_losses::LossWeights {
            joint_offsets: w,
            ..Default::default()
        };
        stage2_loss(&model, &batch, &Stage2::at_true_roots(&weights), &k.ad)
    };
    assert!(!term_values(&loss(0.0)).contains_key("joint_offsets"));
    let (one, three) = (loss(1.0), loss(3.0));
    let (a, b) = (
        term_values(&one)["joint_offsets"],
        term_values(&three)["joint_offsets"],
    );
    assert!(a > 0.0 && a.is_finite(), "{a}");
    assert!((b - 3.0 * a).abs() < 1e-5 * b, "{a} {b}");
    let term = one
        .terms
        .iter()
        .find(|(n, _)| *n == "joint_offsets")
        .unwrap()
        .1
        .clone();
    let grads = term.backward();
    let head = &model.decoder.offsets_head.as_ref().unwrap().fc2.weight;
    let read = &model.decoder.offsets_read.as_ref().unwrap().weight;
    for (name, g) in [("head", head.grad(&grads)), ("read", read.grad(&grads))] {
        let g: Vec<f32> = g.expect(name).into_data().try_to_vec().unwrap();
        assert!(
            g.iter().all(|x| x.is_finite()) && g.iter().any(|&x| x != 0.0),
            "{name}"
        );
    }
}

#[test]
fn joint_annotated_people_get_joint_losses_only() {
    let TwoKinds {
        _root,
        ad,
        model,
        batcher,
        smplx: ds,
        joints: pan,
    } = two_kinds();
    let weights = mvmp_losses::LossWeights::default();
    let terms = |batch: &mvmp_data::loader::FrameBatch| {
        let l = stage2_loss(&model, batch, &Stage2::at_true_roots(&weights), &ad);
        let t = term_values(&l);
        (l, t)
    };
    let joints_only = batcher.batch(vec![pan.load(0).unwrap()], &ad);
    assert!(
        joints_only.vertices.is_none(),
        "no SMPL-X person, no vertices"
    );
    let (_, t) = terms(&joints_only);
    assert_eq!(t["parameters"], 0.0, "{t:?}");
    assert_eq!(t["density"], 0.0, "{t:?}");
    assert_eq!(t["orientation"], 0.0, "{t:?}");
    assert!(t["mesh"].is_finite() && t["mesh"] > 0.0, "{t:?}");
    assert!(t["detection"].is_finite(), "{t:?}");
    let s1 = stage1_loss(&model, &joints_only, &weights, &ad);
    for (n, v) in &s1.terms {
        let v: f32 = v.clone().into_scalar();
        assert!(v.is_finite() && v > 0.0, "stage 1 {n} = {v}");
    }

    let mixed = batcher.batch(vec![ds.load(0).unwrap(), pan.load(0).unwrap()], &ad);
    assert!(mixed.vertices.is_some());
    let (l, t) = terms(&mixed);
    for name in ["parameters", "density", "orientation", "mesh", "detection"] {
        assert!(t[name].is_finite() && t[name] > 0.0, "{name}: {t:?}");
    }
    let grads = l.total.backward();
    struct Finite<'a>(&'a burn::tensor::Gradients, usize);
    impl ModuleVisitor for Finite<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            if let Some(g) = p.val().grad(self.0) {
                assert!(
                    g.into_data()
                        .convert::<f32>()
                        .iter::<f32>()
                        .all(f32::is_finite),
                    "a non-finite gradient"
                );
                self.1 += 1;
            }
        }
    }
    let mut f = Finite(&grads, 0);
    model.visit(&mut f);
    assert!(f.1 > 10, "{} parameter tensors got gradients", f.1);
}

/// `mvmp train` on MVMP-HMR plus a Panoptic source, validated on Panoptic: both stages run over the
/// frames of both, and the validation lines carry Panoptic's metrics.
#[test]
fn a_run_trains_on_mvmp_and_panoptic_and_validates_on_panoptic() {
    let root = tempfile::tempdir().unwrap();
    panoptic_fixture(root.path(), "160906_pizza1", 2);
    let dir = tempfile::tempdir().unwrap();
    let pan = root.path().display().to_string();
    let (run, cfg, model) = new_run(dir.path(), "run", &|t| {
        let table = format!(
            "format = \"panoptic\"\nroot = \"{pan}\"\nsplit = \"160906_pizza1\"\nstride = 1\n"
        );
        format!("{t}\n[[sources]]\n{table}repeat = 2\n\n[validation]\n{table}").replacen(
            "keep_checkpoints = 2\n",
            "keep_checkpoints = 2\nval_frames = 2\n",
            1,
        )
    });
    assert_eq!(cfg.sources.len(), 1);
    assert_eq!(cfg.training_sources().len(), 2);
    let set = mvmp_train::open_training_set(&cfg, &model, &run.root.join("train.toml")).unwrap();
    let mvmp_frames = set.parts[0].len();
    assert_eq!(set.parts[1].len(), 2);
    // `repeat = 2`: each Panoptic frame twice per epoch.
    assert_eq!(set.samples_of(1), 4);
    assert_eq!(set.total(), mvmp_frames + 4);
    let (a, b) = (
        set.load(mvmp_frames).unwrap(),
        set.load(mvmp_frames + 2).unwrap(),
    );
    assert_eq!(
        (a.scene.as_str(), a.frame.as_str()),
        (b.scene.as_str(), b.frame.as_str())
    );
    let out = mvmp_train::train(&run, &cfg, &model, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    let log = std::fs::read_to_string(run.root.join("metrics.jsonl")).unwrap();
    let lines: Vec<serde_json::Value> = log
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    let steps = lines.iter().filter(|l| l["kind"] == "step").count();
    assert_eq!(
        steps,
        2 * (mvmp_frames + 4),
        "both stages over both sources"
    );
    let vals: Vec<&serde_json::Value> = lines.iter().filter(|l| l["kind"] == "val").collect();
    assert_eq!(vals.len(), 2);
    assert!(vals[0]["root_recall"].is_number(), "{}", vals[0]);
    assert!(vals[1]["recall_500"].is_number(), "{}", vals[1]);
    assert!(vals[1].get("pve_mm").is_none(), "Panoptic has no meshes");
}

#[test]
fn source_configs_are_checked() {
    let root = tempfile::tempdir().unwrap();
    panoptic_fixture(root.path(), "160906_pizza1", 1);
    let pan = root.path().display().to_string();
    let dir = tempfile::tempdir().unwrap();
    let read = |extra: &str, edit: &dyn Fn(String) -> String| {
        let p = write_configs(dir.path(), &|t| edit(format!("{t}{extra}")));
        TrainConfig::read(&p).map(|(c, m)| (c, m, p))
    };
    let e = read(
        &format!("[[sources]]\nformat = \"mvmp\"\nroot = \"{pan}\"\nstride = 2\n"),
        &|t| t,
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("sources[0]") && e.contains("stride"), "{e}");
    let e = read(
        &format!("[[sources]]\nformat = \"kinect\"\nroot = \"{pan}\"\n"),
        &|t| t,
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("kinect"), "{e}");
    let e = read(
        &format!("[[sources]]\nformat = \"panoptic\"\nroot = \"{pan}\"\nrepeat = 0\n"),
        &|t| t,
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("sources[0].repeat"), "{e}");
    // Pseudo-ground-truth fits belong to joint-annotated training sources.
    let e = read(
        &format!("[[sources]]\nformat = \"mvmp\"\nroot = \"{pan}\"\npseudo_gt = \"fits\"\n"),
        &|t| t,
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("sources[0].pseudo_gt"), "{e}");
    let e = read(
        &format!("[validation]\nformat = \"panoptic\"\nroot = \"{pan}\"\npseudo_gt = \"fits\"\n"),
        &|t| t,
    )
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("validation.pseudo_gt"), "{e}");
    // More views than a Panoptic source reads cameras (two listed), for training and for validation: the
    // key is named before anything is loaded.
    let cams = "cameras = [\"00_03\", \"00_06\"]\n";
    let (cfg, model, path) = read(
        &format!("[[sources]]\nformat = \"panoptic\"\nroot = \"{pan}\"\nsplit = \"160906_pizza1\"\n{cams}"),
        &|t| t.replacen("train_views = 2", "train_views = 3", 1),
    )
    .unwrap();
    let e = mvmp_train::open_training_set(&cfg, &model, &path)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("train_views")
            && e.contains("3: the frames of sources[0].root")
            && e.contains("2 cameras"),
        "{e}"
    );
    let (cfg, _, _) = read(
        &format!("[validation]\nformat = \"panoptic\"\nroot = \"{pan}\"\nsplit = \"160906_pizza1\"\n{cams}"),
        &|t| t,
    )
    .unwrap();
    let e = mvmp_train::check_validation_source(&cfg)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("test_views = 3") && e.contains("2 cameras"),
        "{e}"
    );
    // A primary joint the source does not annotate (Panoptic has no spine joint).
    std::fs::write(dir.path().join("m.toml"), {
        let mut m = model_config();
        m.primary_joint = mvmp_model::config::PrimaryJoint::Spine;
        let spine = mvmp_model::config::PrimaryJoint::Spine.joint();
        if !m.heatmap_joints.contains(&spine) {
            m.heatmap_joints.push(spine);
        }
        toml::to_string(&m).unwrap()
    })
    .unwrap();
    let (cfg, model, path) = read(
        &format!(
            "[[sources]]\nformat = \"panoptic\"\nroot = \"{pan}\"\nsplit = \"160906_pizza1\"\n"
        ),
        &|t| t.replace("model = \"model.toml\"", "model = \"m.toml\""),
    )
    .unwrap();
    let e = mvmp_train::open_training_set(&cfg, &model, &path)
        .err()
        .unwrap()
        .to_string();
    assert!(
        e.contains("sources[0].format") && e.contains("Spine"),
        "{e}"
    );
    // No data at all.
    let (cfg, model, path) = read("", &|t| {
        t.lines()
            .filter(|l| !l.starts_with("data"))
            .collect::<Vec<_>>()
            .join("\n")
    })
    .unwrap();
    let e = mvmp_train::open_training_set(&cfg, &model, &path)
        .err()
        .unwrap()
        .to_string();
    assert!(e.contains("data") && e.contains("[[sources]]"), "{e}");
}

#[test]
fn h36m_frames_become_samples_with_all_17_joints() {
    use mvmp_data::sources::{SourceFormat, SourceSpec};
    use mvmp_smplx::joint_sets::JointSet;
    let root = tempfile::tempdir().unwrap();
    h36m_fixture(root.path());
    let spec = SourceSpec {
        format: SourceFormat::H36m,
        root: root.path().to_string_lossy().into_owned(),
        split: Some("S9".into()),
        stride: Some(2),
        cameras: Some(
            mvmp_data::h36m::CAMERAS[..2]
                .iter()
                .map(|s| s.to_string())
                .collect(),
        ),
        repeat: None,
        pseudo_gt: None,
    };
    let ds = spec
        .open_training(ViewChoice::Random { count: 2, seed: 1 }, 64)
        .unwrap();
    // 5 pose rows, every 2nd: rows 0, 2, 4.
    assert_eq!(ds.len(), 3);
    let s = ds.load(1).unwrap();
    assert_eq!(
        (s.scene.as_str(), s.frame.as_str()),
        ("S9/Walking", "000003")
    );
    assert_eq!(s.people.len(), 1);
    let p = &s.people[0];
    let seq = mvmp_data::h36m::H36mSequence::open(root.path(), "S9", "Walking", &["54138969"], 1)
        .unwrap();
    let slots = JointSet::H36m17.smplx_indices();
    for (k, &slot) in slots.iter().enumerate() {
        assert_eq!(p.joint_valid[slot], 1.0);
        for a in 0..3 {
            assert!((p.joints_3d[slot][a] as f64 - seq.joints[2][k][a]).abs() < 1e-5);
        }
    }
    assert_eq!(p.joint_valid.iter().sum::<f32>(), 17.0);
    assert_eq!(p.pelvis, seq.joints[2][0].map(|x| x as f32));
    // The camera without images is named when a sample needs it.
    let e = SourceSpec {
        cameras: Some(vec!["54138969".into(), "58860488".into()]),
        ..spec
    }
    .open_training(ViewChoice::Fixed(vec![0, 1]), 64)
    .and_then(|d| d.load(0))
    .err()
    .unwrap()
    .to_string();
    assert!(e.contains("58860488"), "{e}");
}

/// `pseudo_gt` on a joint-annotated source: the annotated person nearest a fit (within the match gate)
/// becomes an SMPL-X person with the fit's parameters and pelvis; the others, and every joint target, stay
/// as the dataset gives them; a missing fits directory or frame is named.
#[test]
fn pseudo_ground_truth_fits_become_smplx_targets() {
    use burn::tensor::TensorData;
    use write_people_npz;
    let root = tempfile::tempdir().unwrap();
    panoptic_fixture(root.path(), "160906_pizza1", 2);
    let pan = root.path().display().to_string();
    let fits = root.path().join("fits");
    let dir = tempfile::tempdir().unwrap();
    let (run, cfg, model) = new_run(dir.path(), "run", &|t| {
        format!(
            "{t}\n[[sources]]\nformat = \"panoptic\"\nroot = \"{pan}\"\nsplit = \"160906_pizza1\"\n\
             stride = 1\npseudo_gt = \"{}\"\n",
            fits.display()
        )
    });
    let open = || mvmp_train::open_training_set(&cfg, &model, &run.root.join("train.toml"));
    let e = open().err().unwrap().to_string();
    assert!(
        e.contains("sources[0].pseudo_gt") && e.contains("not a directory"),
        "{e}"
    );

    // The same frames without fits give the dataset's roots.
    let plain = panoptic_source(root.path(), 5)
        .open_training(ViewChoice::Fixed(vec![0, 1]), 64)
        .unwrap();
    let d = Device::flex();
    let layer = SmplxLayer::new(&mvmp_smplx::standin_model(0), &d);
    let betas = [0.8, -0.5, 0.3, 0.0, 0.2, 0.0, -0.1, 0.0, 0.0, 0.4];
    let mut written = Vec::new();
    for f in 0..2 {
        let r = plain.load(f).unwrap().people[0].pelvis;
        // 5 cm from person 0's root; the other fit is far from everyone.
        let mut near = fit_at(&layer, [r[0] as f64 + 0.05, r[1] as f64, r[2] as f64]);
        near.betas = betas;
        near.pose[3 * 18 + 2] = 0.4; // left elbow
        let fd = fits.join(format!("160906_pizza1/{f:08}"));
        std::fs::create_dir_all(&fd).unwrap();
        write_people_npz(
            &fd.join("people.npz"),
            &[fit_at(&layer, [9.0, 9.0, 0.9]), near.clone()],
        )
        .unwrap();
        written.push(near);
    }
    // Independent expectation of the fit's pelvis: the shaped rest pelvis plus smplx's transl.
    let rest: Vec<f32> = layer
        .rest_joints(
            Tensor::from_data(TensorData::new(betas.to_vec(), [1, 10]), &d),
            Tensor::zeros([1, 10], &d),
        )
        .into_data()
        .try_into_vec()
        .unwrap();
    let set = open().unwrap();
    let part = &set.parts[1];
    for (f, near) in written.iter().enumerate() {
        let (s, p) = (part.load(f).unwrap(), plain.load(f).unwrap());
        assert_eq!(s.people.len(), p.people.len());
        let (a, b) = (&s.people[0], &p.people[0]);
        assert!(a.smplx && !b.smplx, "frame {f}");
        assert_eq!(a.betas, betas);
        assert!((a.pose[3 * 18 + 2] - 0.4).abs() < 1e-6);
        for (k, (&r, &t)) in rest.iter().zip(&near.transl).enumerate() {
            let want = r + t;
            assert!(
                (a.pelvis[k] - want).abs() < 1e-4,
                "frame {f} axis {k}: {} vs {want}",
                a.pelvis[k]
            );
        }
        assert_eq!(a.joints_3d, b.joints_3d);
        assert_eq!(a.joint_valid, b.joint_valid);
        for (x, y) in s.people.iter().zip(&p.people).skip(1) {
            assert!(!x.smplx);
            assert_eq!(x.pelvis, y.pelvis);
        }
    }
    // A batch of such a frame has vertices and every SMPL-X term of stage 2.
    let ad = Device::flex().autodiff();
    let mcfg = model_config();
    let net =
        mvmp_train::seeded_init(&mcfg, &ad, 2).with_body(Arc::new(mvmp_smplx::standin_model(0)));
    let batch = FrameBatcher::with_vertices(mvmp_smplx::standin_model(0))
        .batch(vec![part.load(0).unwrap()], &ad);
    assert!(batch.vertices.is_some());
    let l = stage2_loss(
        &net,
        &batch,
        &Stage2::at_true_roots(&mvmp_losses::LossWeights::default()),
        &ad,
    );
    for (name, t) in &l.terms {
        let v: f32 = t.clone().into_scalar();
        assert!(v.is_finite(), "{name} = {v}");
        if ["parameters", "density", "mesh"].contains(name) {
            assert!(v > 0.0, "{name} = {v}");
        }
    }
    // A malformed fits file and a frame without fits stop the load, naming the file.
    let bad = fits.join("160906_pizza1/00000001/people.npz");
    std::fs::write(&bad, b"not an npz archive").unwrap();
    let e = part.load(1).unwrap_err().to_string();
    assert!(e.contains("00000001/people.npz"), "{e}");
    std::fs::remove_file(&bad).unwrap();
    let e = part.load(1).unwrap_err().to_string();
    assert!(
        e.contains("00000001/people.npz") && e.contains("no pseudo-ground-truth"),
        "{e}"
    );
}

#[test]
fn a_torn_log_line_and_stale_temporaries_do_not_stop_a_resume() {
    let dir = tempfile::tempdir().unwrap();
    let (run, _, _) = new_run(dir.path(), "run", &|s| s);
    let log = run.metrics_path();
    // A kill while the fourth line was written leaves it without its end.
    std::fs::write(
        &log,
        "{\"kind\":\"step\",\"global_step\":1}\n{\"kind\":\"step\",\"global_step\":2}\n\
         {\"kind\":\"step\",\"global_step\":3}\n{\"kind\":\"step\",\"glo",
    )
    .unwrap();
    run.truncate_log(2).unwrap();
    assert_eq!(
        std::fs::read_to_string(&log).unwrap(),
        "{\"kind\":\"step\",\"global_step\":1}\n{\"kind\":\"step\",\"global_step\":2}\n"
    );
    // A malformed line that is not the torn last one is an error naming the line.
    std::fs::write(&log, "{\"global_step\":1}\nnot json\n{\"global_step\":2}\n").unwrap();
    let e = run.truncate_log(2).unwrap_err().to_string();
    assert!(e.contains("metrics.jsonl") && e.contains("line 2"), "{e}");

    let ck = run.root.join("checkpoints");
    std::fs::create_dir_all(&ck).unwrap();
    for f in [
        ".tmpAbC123",
        ".optim-step0000004-part.tmp",
        "step0000004.bpk",
    ] {
        std::fs::write(ck.join(f), b"x").unwrap();
    }
    // In the run's root: the temporaries of the state, the log, the curves and the model file go; a
    // person's own dot-file stays.
    for f in [".tmpXyZ789", ".mvmp-partial-q1w2.bpk", ".notes"] {
        std::fs::write(run.root.join(f), b"x").unwrap();
    }
    run.remove_stale_temporaries().unwrap();
    for (f, kept) in [
        (".tmpXyZ789", false),
        (".mvmp-partial-q1w2.bpk", false),
        (".notes", true),
    ] {
        assert_eq!(run.root.join(f).exists(), kept, "{f}");
    }
    let mut left: Vec<String> = std::fs::read_dir(&ck)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    left.sort();
    assert_eq!(left, vec!["step0000004.bpk".to_string()]);
}

/// Stage 2's loss options on a batch of an SMPL-X person set and a joints-only one: the 2D heatmap term
/// joins when asked; with the mesh and density terms in each body's own frame every term is finite, the
/// frame changes those two terms alone, and the translation term joins the mesh term; the gradients stay
/// finite.
#[test]
fn body_frame_mesh_terms_run_on_smplx_and_joint_people() {
    let k = two_kinds();
    let (ad, model) = (&k.ad, &k.model);
    let batch = k.batcher.batch(
        vec![k.smplx.load(0).unwrap(), k.joints.load(0).unwrap()],
        ad,
    );
    let terms = |weights: &mvmp_losses::LossWeights| {
        let l = stage2_loss(model, &batch, &Stage2::at_true_roots(weights), ad);
        let t = term_values(&l);
        (l, t)
    };
    let world = mvmp_losses::LossWeights::default();
    let (_, w) = terms(&world);
    // Stage 1's 2D heatmap term joins stage 2 only when asked.
    assert!(!w.contains_key("heatmap_2d"), "{w:?}");
    let (_, h) = terms(&mvmp_losses::LossWeights {
        heatmap_2d_stage2: 1.0,
        ..world.clone()
    });
    assert!(
        h["heatmap_2d"].is_finite() && h["heatmap_2d"] > 0.0,
        "{h:?}"
    );
    // The target-weighted part adds its weight times a positive error to the plain MSE (the maps are
    // the same in every call, so the addition is linear in the weight).
    let positive = |p: f32| {
        terms(&mvmp_losses::LossWeights {
            heatmap_2d_stage2: 1.0,
            heatmap_2d_positive: p,
            ..world.clone()
        })
        .1["heatmap_2d"]
    };
    let (half, one) = (
        positive(0.5) - h["heatmap_2d"],
        positive(1.0) - h["heatmap_2d"],
    );
    assert!(half > 0.0 && half.is_finite(), "{half}");
    assert!((one - 2.0 * half).abs() < 1e-4 * one, "{half} {one}");
    // The body rotations' squared error joins the parameter term at its own weight, also linearly.
    let w_params = w["parameters"];
    let l2 = |w: f32| {
        terms(&mvmp_losses::LossWeights {
            parameters_body_l2: w,
            ..world.clone()
        })
        .1["parameters"]
            - w_params
    };
    let (a, b) = (l2(1.0), l2(3.0));
    assert!(a > 0.0 && (b - 3.0 * a).abs() < 1e-4 * b, "{a} {b}");
    for frame in [MeshFrame::Pelvis, MeshFrame::Body] {
        let local = mvmp_losses::LossWeights {
            mesh_frame: frame,
            ..world.clone()
        };
        let (_, t) = terms(&local);
        for name in ["parameters", "orientation", "detection"] {
            assert_eq!(t[name], w[name], "{frame:?} {name}");
        }
        for name in ["mesh", "density"] {
            assert!(t[name].is_finite() && t[name] > 0.0, "{frame:?}: {t:?}");
            assert_ne!(t[name], w[name], "{frame:?} {name}");
        }
        let with_t = mvmp_losses::LossWeights {
            translation: 100.0,
            ..local
        };
        let (l, t2) = terms(&with_t);
        assert!(t2["mesh"] > t["mesh"], "{t2:?} against {t:?}");
        let grads = l.total.backward();
        let g = model
            .decoder
            .offset_head
            .fc2
            .weight
            .val()
            .grad(&grads)
            .expect("the translation reaches the offset head");
        let g: Vec<f32> = g.into_data().convert::<f32>().try_into_vec().unwrap();
        assert!(g.iter().all(|x| x.is_finite()) && g.iter().any(|x| *x != 0.0));
    }
}

/// A stage 2 that keeps detection fixed leaves HRNet, the RootNet and the facing head as they were and
/// trains the rest; its log has no detection or facing term.
#[test]
fn stage_two_can_keep_detection_fixed() {
    let dir = tempfile::tempdir().unwrap();
    let (run, cfg, model_cfg) = new_run(dir.path(), "run", &|t| {
        t.replace("[stage1]\nepochs = 1", "[stage1]\nepochs = 0")
            .replace("[stage2]\n", "[stage2]\nfreeze_detection = true\n")
    });
    assert!(cfg.stage2.freeze_detection && cfg.stage1.epochs == 0);
    let (start, end) = trained_from_start(&run, &cfg, &model_cfg);
    assert_eq!(weights(&end.hrnet), weights(&start.hrnet));
    assert_eq!(weights(&end.rootnet), weights(&start.rootnet));
    assert_eq!(weights(&end.facing), weights(&start.facing));
    assert_ne!(weights(&end.decoder), weights(&start.decoder));
    let log = std::fs::read_to_string(run.metrics_path()).unwrap();
    let steps: Vec<serde_json::Value> = log
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .filter(|v: &serde_json::Value| v["kind"] == "step")
        .collect();
    assert!(!steps.is_empty());
    for s in &steps {
        assert!(s.get("detection").is_none(), "{s}");
        assert!(s.get("facing").is_none(), "{s}");
        assert!(s.get("mesh").is_some(), "{s}");
    }
}

/// A stage 2 that keeps each frame's volumes (`cache_volumes`) trains the decoder alone, and a run
/// stopped in its second epoch resumes to the same weights: the volumes kept again after the resume are
/// the first epoch's, because every epoch draws each frame's views and colours as the first did.
#[test]
fn stage_two_can_keep_each_frames_volumes() {
    let dir = tempfile::tempdir().unwrap();
    let edit = |t: String| {
        t.replace("seed = 3\n", "seed = 3\nterm_gradients = true\n")
            .replace("[stage1]\nepochs = 1", "[stage1]\nepochs = 0")
            .replace(
                "[stage2]\nepochs = 1\n",
                "[stage2]\nepochs = 2\nfreeze_backbone = true\nfreeze_detection = true\ncache_volumes = true\n",
            )
            + "[augment]\nbrightness = 0.5\ncolor = 0.2\n"
    };
    let (run_a, cfg, model_cfg) = new_run(dir.path(), "a", &edit);
    assert!(cfg.stage2.cache_volumes && cfg.stage2.epochs == 2);
    let (start, end) = trained_from_start(&run_a, &cfg, &model_cfg);
    assert_eq!(weights(&end.vit), weights(&start.vit));
    assert_eq!(weights(&end.reduce), weights(&start.reduce));
    assert_eq!(weights(&end.hrnet), weights(&start.hrnet));
    assert_eq!(weights(&end.rootnet), weights(&start.rootnet));
    assert_eq!(weights(&end.facing), weights(&start.facing));
    assert_ne!(weights(&end.decoder), weights(&start.decoder));
    // The kept volumes' time is a phase of its own.
    let log = std::fs::read_to_string(run_a.metrics_path()).unwrap();
    let mut steps = log.lines().filter(|l| l.contains("\"kind\":\"step\""));
    assert!(steps.clone().count() == 8 && steps.all(|l| l.contains("\"volumes\":")));
    // Each term's gradients reach the decoder alone.
    let terms = log
        .lines()
        .find(|l| l.contains("\"kind\":\"grad_terms\""))
        .unwrap();
    let terms: serde_json::Value = serde_json::from_str(terms).unwrap();
    let mut decoder = 0.0;
    for (name, norms) in terms["terms"].as_object().unwrap() {
        for (module, n) in norms.as_object().unwrap() {
            let n = n.as_f64().unwrap();
            assert!(module == "decoder" || n == 0.0, "{name}: {module} {n}");
            decoder += n;
        }
    }
    assert!(decoder > 0.0, "{terms}");
    // 4 training frames an epoch: stopped two steps into the second.
    let (run_b, cfg_b, model_b) = new_run(dir.path(), "b", &edit);
    let stopped = mvmp_train::train(&run_b, &cfg_b, &model_b, &options(Some(6)), &mut Quiet);
    assert!(matches!(
        stopped,
        Ok(Outcome::Interrupted { global_step: 6, .. })
    ));
    let (run_b, cfg_b, model_b) = RunDir::open(&run_b.root).unwrap();
    let out = mvmp_train::train(&run_b, &cfg_b, &model_b, &options(None), &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    trained_alike(&run_a, &run_b, &model_cfg);
}

/// With `train_rootnet` beside kept volumes, stage 2 trains the RootNet on each frame's kept heatmap
/// volume and the decoder: HRNet, the facing head and the ViT stay where they were, the detection term
/// stays in the loss and its gradient reaches the RootNet.
#[test]
fn stage_two_can_train_the_rootnet_on_kept_volumes() {
    let dir = tempfile::tempdir().unwrap();
    let edit = |t: String| {
        t.replace("seed = 3\n", "seed = 3\nterm_gradients = true\n")
            .replace("[stage1]\nepochs = 1", "[stage1]\nepochs = 0")
            .replace(
                "[stage2]\nepochs = 1\n",
                "[stage2]\nepochs = 2\nfreeze_backbone = true\nfreeze_detection = true\n\
                 cache_volumes = true\ntrain_rootnet = true\ndetection_lr = 2e-3\n",
            )
    };
    let (run, cfg, model_cfg) = new_run(dir.path(), "r", &edit);
    assert!(cfg.stage2.train_rootnet && cfg.stage2.epochs == 2);
    let (start, end) = trained_from_start(&run, &cfg, &model_cfg);
    assert_eq!(weights(&end.vit), weights(&start.vit));
    assert_eq!(weights(&end.hrnet), weights(&start.hrnet));
    assert_eq!(weights(&end.facing), weights(&start.facing));
    assert_ne!(kernels(&end.rootnet), kernels(&start.rootnet));
    assert_ne!(weights(&end.decoder), weights(&start.decoder));
    let log = std::fs::read_to_string(run.metrics_path()).unwrap();
    let steps: Vec<serde_json::Value> = log
        .lines()
        .filter(|l| l.contains("\"kind\":\"step\""))
        .map(|l| serde_json::from_str(l).unwrap())
        .collect();
    assert_eq!(steps.len(), 8);
    for s in &steps {
        assert!(s.get("detection").is_some(), "{s}");
        assert!(s.get("facing").is_none(), "{s}");
        assert!(s["detection_lr"].as_f64().is_some(), "{s}");
    }
    let terms = log
        .lines()
        .find(|l| l.contains("\"kind\":\"grad_terms\""))
        .unwrap();
    let terms: serde_json::Value = serde_json::from_str(terms).unwrap();
    let rootnet = terms["terms"]["detection"]["rootnet"].as_f64().unwrap();
    assert!(rootnet > 0.0, "{terms}");
    for (name, norms) in terms["terms"].as_object().unwrap() {
        for (module, n) in norms.as_object().unwrap() {
            let n = n.as_f64().unwrap();
            let trained = module == "decoder" || module == "rootnet";
            assert!(trained || n == 0.0, "{name}: {module} {n}");
        }
    }
}

/// A stage 2 with a rate of its own for detection steps HRNet, the RootNet and the facing head at that
/// rate and the rest at the stage's: at a vanishing rate they stay where they were, while the same
/// stage without it moves them; the log carries the rate.
#[test]
fn stage_two_can_train_detection_at_its_own_rate() {
    let dir = tempfile::tempdir().unwrap();
    let run_with = |name: &str, stage2: &str| {
        let stage2 = stage2.to_string();
        let (run, cfg, model_cfg) = new_run(dir.path(), name, &move |t| {
            t.replace("[stage1]\nepochs = 1", "[stage1]\nepochs = 0")
                .replace("[stage2]\n", &format!("[stage2]\n{stage2}"))
        });
        let out = mvmp_train::train(&run, &cfg, &model_cfg, &options(None), &mut Quiet).unwrap();
        assert_eq!(out, Outcome::Finished);
        let mut end = mvmp_train::seeded_init(&model_cfg, &Device::flex(), 0);
        load_weights(&mut end, &run.root.join("model.bpk")).unwrap();
        let start = mvmp_train::seeded_init(&model_cfg, &Device::flex(), cfg.seed);
        (
            start,
            end,
            std::fs::read_to_string(run.metrics_path()).unwrap(),
        )
    };
    let moved = |a: Vec<f32>, b: Vec<f32>| {
        a.iter()
            .zip(&b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0f32, f32::max)
    };
    let (start, slow, log) = run_with("slow", "detection_lr = 1e-12\n");
    let (_, plain, _) = run_with("plain", "");
    // Kernels only: HRNet's batch norms update their running statistics in every forward.
    for (name, s, a, b) in [
        (
            "hrnet",
            kernels(&start.hrnet),
            kernels(&slow.hrnet),
            kernels(&plain.hrnet),
        ),
        (
            "rootnet",
            kernels(&start.rootnet),
            kernels(&slow.rootnet),
            kernels(&plain.rootnet),
        ),
        (
            "facing",
            kernels(&start.facing),
            kernels(&slow.facing),
            kernels(&plain.facing),
        ),
    ] {
        let (kept, trained) = (moved(s.clone(), a), moved(s, b));
        assert!(kept < 1e-7 && trained > 1e-5, "{name}: {kept} {trained}");
    }
    assert!(moved(weights(&start.decoder), weights(&slow.decoder)) > 1e-5);
    let step = log
        .lines()
        .find(|l| l.contains("\"kind\":\"step\""))
        .unwrap();
    let v: serde_json::Value = serde_json::from_str(step).unwrap();
    assert!(v["detection_lr"].as_f64().unwrap() < 1e-11, "{step}");
}

/// With `mesh_pose = false` the mesh and density terms train the global rotation (and the rest) but
/// not the body-pose rotations, whose head columns get no gradient from them; by default they do.
#[test]
fn mesh_terms_can_leave_the_body_pose_to_the_parameter_term() {
    let k = two_kinds();
    let (ad, model) = (&k.ad, &k.model);
    let batch = k.batcher.batch(vec![k.smplx.load(0).unwrap()], ad);
    // The rotation head's output columns: 6 for the global rotation, then 6 per body joint.
    let columns = |mesh_pose: bool| {
        let weights = mvmp_losses::LossWeights {
            parameters: 0.0,
            orientation: 0.0,
            mesh_pose,
            ..Default::default()
        };
        let l = stage2_loss(model, &batch, &Stage2::at_true_roots(&weights), ad);
        let g = model
            .decoder
            .rot_head
            .fc2
            .weight
            .val()
            .grad(&l.total.backward());
        let g = g.expect("the mesh terms reach the rotation head");
        let norm = |from: usize, n: usize| -> f32 {
            g.clone().narrow(1, from, n).abs().sum().into_scalar()
        };
        (norm(0, 6), norm(6, NUM_BODY * 6))
    };
    let (global, body) = columns(true);
    assert!(global > 0.0 && body > 0.0, "{global} {body}");
    let (global, body) = columns(false);
    assert!(global > 0.0, "{global}");
    assert_eq!(body, 0.0);
}

/// People for the probe's regression tests: `scenes` scenes of 5, features from `feature`, the pose
/// from `pose` (63 values).
fn probe_people(
    scenes: usize,
    feature: impl Fn(usize) -> Vec<f32>,
    pose: impl Fn(usize, &[f32]) -> Vec<f64>,
) -> Vec<mvmp_train::probe::ProbedPerson> {
    (0..scenes * 5)
        .map(|i| {
            let f = feature(i);
            mvmp_train::probe::ProbedPerson {
                scene: format!("scene_{:03}", i / 5),
                pose: pose(i, &f),
                volume: f,
                ..Default::default()
            }
        })
        .collect()
}

/// A deterministic value in [-1, 1) per (i, k).
fn hashed(i: usize, k: usize) -> f32 {
    let h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (k as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
    let h = h ^ (h >> 29);
    (h.wrapping_mul(0x94D0_49BB_1331_11EB) >> 40) as f32 / (1u64 << 23) as f32 - 1.0
}

/// A probe score recomputed from the primal ridge, `(Z^T Z + lambda I)^-1 Z^T (Y - mean)` on the
/// standardised features, at the strength the score reports (times the mean squared norm of a
/// standardised row, which is the number of features): the same R^2 and joint error within 1e-6.
fn check_against_primal_ridge(
    train: &[mvmp_train::probe::ProbedPerson],
    test: &[mvmp_train::probe::ProbedPerson],
    s: &mvmp_train::probe::ProbeScore,
) {
    use nalgebra::DMatrix;
    let d = train[0].volume.len();
    let x = DMatrix::from_fn(train.len(), d, |i, j| train[i].volume[j] as f64);
    let y = DMatrix::from_fn(train.len(), 63, |i, j| train[i].pose[j]);
    let n = train.len() as f64;
    let (xm, ym) = (x.row_mean(), y.row_mean());
    let sd: Vec<f64> = (0..d)
        .map(|j| (x.column(j).iter().map(|v| (v - xm[j]).powi(2)).sum::<f64>() / n).sqrt())
        .collect();
    let z = DMatrix::from_fn(x.nrows(), d, |i, j| (x[(i, j)] - xm[j]) / sd[j]);
    let yc = DMatrix::from_fn(y.nrows(), 63, |i, j| y[(i, j)] - ym[j]);
    let lambda = s.ridge * d as f64;
    let w = (z.transpose() * &z + DMatrix::identity(d, d) * lambda)
        .lu()
        .solve(&(z.transpose() * yc))
        .unwrap();
    let (mut sse, mut sst, mut dist) = (0.0, 0.0, 0.0);
    for p in test {
        let zt = DMatrix::from_fn(1, d, |_, j| (p.volume[j] as f64 - xm[j]) / sd[j]);
        let pred = zt * &w;
        for j in 0..21 {
            let mut e2 = 0.0;
            for a in 0..3 {
                let k = 3 * j + a;
                let e = p.pose[k] - (pred[k] + ym[k]);
                e2 += e * e;
                sst += (p.pose[k] - ym[k]).powi(2);
            }
            sse += e2;
            dist += e2.sqrt();
        }
    }
    let (r2, mm) = (1.0 - sse / sst, 1000.0 * dist / (test.len() * 21) as f64);
    assert!(
        (s.r2 - r2).abs() < 1e-6,
        "{}: {} against {r2}",
        s.features,
        s.r2
    );
    assert!(
        (s.joint_mm - mm).abs() < 1e-6,
        "{}: {} against {mm}",
        s.features,
        s.joint_mm
    );
}

/// The probe's ridge regression, checked against the primal solution computed here at the strength it
/// reports: the same R^2 and joint error (1e-6), a pose that is linear in the features read almost
/// exactly, and features unrelated to the pose reading nothing.
#[test]
fn the_volume_probe_reads_a_linear_pose_and_not_noise() {
    use mvmp_train::probe::{mean_pose_mm, score};
    let d = 6;
    let feature = |i: usize| (0..d).map(|k| hashed(i, k)).collect::<Vec<f32>>();
    // Linear in the features plus noise of a tenth of the signal.
    let noisy = |i: usize, f: &[f32]| -> Vec<f64> {
        (0..63)
            .map(|k| {
                let lin: f64 = (0..d)
                    .map(|j| f[j] as f64 * (((j + k) % 5) as f64 - 2.0))
                    .sum();
                0.01 * lin + 0.003 * hashed(i, 100 + k) as f64
            })
            .collect()
    };
    let train = probe_people(20, feature, noisy);
    let test = probe_people(6, |i| feature(1000 + i), |i, f| noisy(1000 + i, f));
    let s = score("noisy", &train, &test, |p| p.volume.clone()).unwrap();

    check_against_primal_ridge(&train, &test, &s);
    assert_eq!(s.dims, d);
    assert!(s.r2 > 0.9, "{s:?}");
    assert!(s.joint_mm < 0.3 * mean_pose_mm(&train, &test), "{s:?}");

    // 40 features that have nothing to do with the pose: the chosen ridge keeps the probe at the mean.
    let unrelated = |i: usize| (0..40).map(|k| hashed(i, 500 + k)).collect::<Vec<f32>>();
    let train = probe_people(20, unrelated, |i, _| noisy(i, &feature(i)));
    let test = probe_people(
        6,
        |i| unrelated(1000 + i),
        |i, _| noisy(1000 + i, &feature(1000 + i)),
    );
    let s = score("unrelated", &train, &test, |p| p.volume.clone()).unwrap();
    assert!(s.r2 < 0.1 && s.r2 > -0.2, "{s:?}");
    check_against_primal_ridge(&train, &test, &s);

    // More features than people (the dual form): still the primal solution, and still readable.
    let wide = |i: usize| {
        let mut f = feature(i);
        f.extend((0..40).map(|k| hashed(i, 900 + k)));
        f
    };
    let train = probe_people(4, wide, |i, _| noisy(i, &feature(i)));
    let test = probe_people(
        3,
        |i| wide(1000 + i),
        |i, _| noisy(1000 + i, &feature(1000 + i)),
    );
    let s = score("wide", &train, &test, |p| p.volume.clone()).unwrap();
    assert_eq!(s.dims, d + 40);
    check_against_primal_ridge(&train, &test, &s);
    assert!(s.r2 > 0.3, "{s:?}");

    // One training scene leaves nothing to choose the ridge on.
    let e = score("one", &train[..5], &test, |p| p.volume.clone()).unwrap_err();
    assert!(
        e.contains("1 training scenes") && e.contains("at least 2"),
        "{e}"
    );
}

/// What the probe reads of each person of a split: the volumes on the lattice (its points times the
/// channels), the root height and its bumps, and the pose in the person's own frame, whose left hip
/// lies to their left and whose heights are the world's.
#[test]
fn the_volume_probe_reads_each_person_in_their_own_frame() {
    use mvmp_train::probe::{ProbeOptions, collect};
    let cfg = model_config();
    let device = Device::flex();
    let model = mvmp_train::train::seeded_init(&cfg, &device, 0);
    let opts = ProbeOptions {
        lattice: [2, 2, 3],
        span: [0.5, 0.5, 1.0],
        views: 2,
        max_frames: 0,
        sigma: 2.0,
    };
    let people = collect(&model, dataset(), Split::Train, &opts, &device, |_, _| {}).unwrap();
    let ds =
        FrameDataset::open(dataset(), Split::Train, ViewChoice::Fixed(vec![0, 1]), 64).unwrap();
    let truth: Vec<_> = (0..ds.len())
        .flat_map(|i| ds.load(i).unwrap().people)
        .collect();
    assert_eq!(people.len(), truth.len());
    // The lattice round each root lies on the person's own joints' Gaussians.
    let truth_mass: f32 = people.iter().flat_map(|p| &p.true_heatmaps).sum();
    assert!(truth_mass > 0.0);
    for (p, t) in people.iter().zip(&truth) {
        assert_eq!(p.volume.len(), 12 * cfg.feature_channels);
        assert_eq!(p.heatmaps.len(), 12 * cfg.heatmap_joints.len());
        assert_eq!(p.centroids.len(), 3 * cfg.heatmap_joints.len());
        assert_eq!(p.true_heatmaps.len(), p.heatmaps.len());
        // Read where the model puts the person: its root nearest theirs, within the gate.
        assert_eq!(p.own_heatmaps.len(), p.heatmaps.len());
        assert_eq!(p.own_true_heatmaps.len(), p.heatmaps.len());
        assert_eq!(p.own_root_true_heatmaps.len(), p.heatmaps.len());
        assert_eq!(p.own_heading_true_heatmaps.len(), p.heatmaps.len());
        assert_eq!(p.own_height.len(), 9);
        assert!((p.own_height[0] - t.joints_3d[0][2]).abs() <= 0.5);
        // Fused from Gaussians of peak 1: a mean over views of values in [0, 1].
        assert!(p.true_heatmaps.iter().all(|&x| (0.0..=1.0).contains(&x)));
        // A centroid is a weighted mean of the lattice's offsets: inside its box.
        for c in p.centroids.chunks(3) {
            assert!(
                c[0].abs() <= 0.25 + 1e-6 && c[1].abs() <= 0.25 + 1e-6 && c[2].abs() <= 0.5 + 1e-6
            );
        }
        assert_eq!(p.height.len(), 9);
        assert_eq!(p.height[0], t.joints_3d[0][2]);
        assert_eq!(p.pose.len(), 63);
        // Joint 1 is the left hip, joint 2 the right (SMPL-X order).
        assert!(p.pose[1] > 0.03 && p.pose[4] < -0.03, "{:?}", &p.pose[..6]);
        for j in 1..22 {
            let dz = (t.joints_3d[j][2] - t.joints_3d[0][2]) as f64;
            assert!((p.pose[3 * (j - 1) + 2] - dz).abs() < 1e-6);
        }
    }
}
