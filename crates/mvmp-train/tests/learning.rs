//! The whole gradient path learns: a small model trained through `mvmp_train::train` on two synthetic
//! frames must find every person on them and drive their joint error far below where it starts. A
//! regression anywhere between the images and the losses (a detached tensor, a wrong target, a loss that
//! no longer reaches a module, a detector that scores people only in training mode) breaks it.
use std::path::Path;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;

use burn::tensor::Device;
use mvmp_data::loader::Split;
use mvmp_data::synth::{SynthConfig, generate};
use mvmp_eval::drivers::{EvalOptions, evaluate};
use mvmp_eval::joint_sets::JointSet;
use mvmp_fusion::VolumeNorm;
use mvmp_geom::VoxelGrid;
use mvmp_infer::{Predictor, load_weights};
use mvmp_model::ModelConfig;
use mvmp_train::{Outcome, Quiet, RunDir, TrainConfig, TrainOptions};

/// Two scenes of one frame, three people each, four views: both scenes fall in the train split.
fn dataset(dir: &Path) -> std::path::PathBuf {
    let out = dir.join("ds");
    let mut c = SynthConfig {
        name: "overfit".into(),
        seed: 11,
        scenes: 2,
        frames_per_scene: 1,
        people: [3, 3],
        area: [3.0, 3.0],
        image_size: [160, 160],
        ..Default::default()
    };
    c.cameras.count = 4;
    c.cameras.rings[0].radius = 5.0;
    generate(&c, &out, Path::new("."), &|| {}).unwrap();
    out
}

fn model_config() -> ModelConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/model/tiny.toml");
    let mut c = ModelConfig::read(&path).unwrap();
    c.image_size = 112;
    c.grid = VoxelGrid::new([0.0, 0.0, 1.0], [5.0, 5.0, 2.0], [20, 20, 8]).unwrap();
    c.max_people = 4;
    c.decoder.dim = 64;
    c.decoder.pool = 2;
    c.rootnet_width = 0.25;
    c.rootnet_norm = VolumeNorm::Group;
    // The flip test reads mirrored views, which a facing head that has learned two frames by appearance
    // reads wrong: with it the training-frame MPJPE was 60.4 mm (PA-MPJPE 8.5), without it 6.6.
    c.facing_flip = false;
    c
}

const TRAIN: &str = r#"model = "model.toml"
seed = 0
train_views = 4
test_views = 4
queries = "mixed"
keep_checkpoints = 1

[[sources]]
format = "mvmp"
root = "DATA"
repeat = 10

[validation]
format = "mvmp"
root = "DATA"
split = "train"

[stage1]
epochs = 3
lr = 3e-3
warmup_steps = 5
schedule = "cosine"

[stage2]
epochs = 16
lr = 2e-3
warmup_steps = 10
schedule = "cosine"

[loss]
detection_offset = 0.02
detection_positive = 1.0
"#;

/// Bound on the training-frame MPJPE. Measured with `mvmp train` (release, 2 cores) on a set synthesised
/// with these settings and with these configs, the last validation (stage-2 step 320): 6.0 mm with seed 0
/// (over the 16 epochs: 341, 255, 220, 177, 188, 160, 116, 124, 121, 115, 111, 15, 10, 8.1, 6.4, 6.0 mm),
/// every person found. Before the synthetic people had hair and the decoder started from the data's mean
/// parameters, seeds 0, 1 and 2 ended at 10.4, 10.7 and 10.4 mm. The curve falls slowly, then drops
/// sharply, at an epoch that differs between seeds (7 to 11); with 8 epochs the cosine decay ended before
/// the drop (95.8 mm). 40 mm leaves the drop several epochs of slack and fails when the stage-2 gradient
/// path stops learning.
const MPJPE_BOUND_MM: f64 = 40.0;

#[test]
fn two_frames_are_overfitted_and_every_person_is_found() {
    let dir = tempfile::tempdir().unwrap();
    let data = dataset(dir.path());
    std::fs::write(
        dir.path().join("model.toml"),
        toml::to_string(&model_config()).unwrap(),
    )
    .unwrap();
    let text = TRAIN.replace("DATA", &data.display().to_string());
    let cfg_path = dir.path().join("train.toml");
    std::fs::write(&cfg_path, text).unwrap();
    let (cfg, model_cfg) = TrainConfig::read(&cfg_path).unwrap();
    let run = RunDir::create(&dir.path().join("run"), &cfg, &model_cfg, None).unwrap();
    let opts = TrainOptions {
        device: Device::flex(),
        stop: Arc::new(AtomicBool::new(false)),
        stop_after_steps: None,
        stop_after_time: None,
    };
    let out = mvmp_train::train(&run, &cfg, &model_cfg, &opts, &mut Quiet).unwrap();
    assert_eq!(out, Outcome::Finished);
    assert!(run.root.join("curves.png").is_file());

    let device = Device::flex();
    let mut model = mvmp_train::seeded_init(&model_cfg, &device, 0);
    load_weights(&mut model, &run.root.join("model.bpk")).unwrap();
    let body = mvmp_data::layout::load_body_model(&model_cfg.body_model, &run.root).unwrap();
    let pred = Predictor::new(model, body, &device);
    let eval = EvalOptions {
        split: Split::Train,
        views: 4,
        max_frames: 0,
        gate: mvmp_eval::DEFAULT_GATE,
        joints: JointSet::Smplx127,
        truth: Vec::new(),
    };
    let m = evaluate(&pred, &data, &eval, |_, _, _| Ok(()))
        .unwrap()
        .overall();
    assert_eq!(
        (m.matched, m.ground_truth),
        (6, 6),
        "every person on the training frames is found: {m:?}"
    );
    let mpjpe = m.mpjpe_mm.unwrap();
    eprintln!("training-frame MPJPE {mpjpe:.1} mm (bound {MPJPE_BOUND_MM} mm): {m:?}");
    assert!(
        mpjpe < MPJPE_BOUND_MM,
        "training-frame MPJPE {mpjpe:.1} mm, bound {MPJPE_BOUND_MM} mm"
    );
}
