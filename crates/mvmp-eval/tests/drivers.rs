//! The scoring loop on a small synthetic dataset: frames scored several at a time give the figures of
//! frames scored one by one, and what each frame keeps reaches `each` in frame order.
use std::path::Path;

use burn::tensor::Device;
use mvmp_data::loader::Split;
use mvmp_data::synth::{SynthConfig, generate};
use mvmp_eval::drivers::{
    EvalFrame, EvalOptions, evaluate_sequences, mean_pose_at, mvmp_split, reference_mean,
};
use mvmp_eval::joint_sets::JointSet;
use mvmp_smplx::SmplxLayer;

#[test]
fn frames_scored_at_once_score_as_frames_in_turn() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("ds");
    let mut c = SynthConfig {
        name: "drivers".into(),
        seed: 5,
        scenes: 5,
        frames_per_scene: 1,
        people: [1, 3],
        area: [3.0, 3.0],
        image_size: [64, 64],
        ..Default::default()
    };
    c.cameras.count = 2;
    generate(&c, &data, Path::new("."), &|| {}).unwrap();
    let device = Device::flex();
    let (seqs, truth) = mvmp_split(&data, Split::All, &device).unwrap();
    let layout = mvmp_data::DatasetLayout::open(&data).unwrap();
    let layer = SmplxLayer::new(&layout.body_model().unwrap(), &device);
    let (mean, _) = reference_mean(&data, &device).unwrap();
    let opts = EvalOptions {
        split: Split::All,
        views: 2,
        max_frames: 0,
        gate: mvmp_eval::DEFAULT_GATE,
        joints: JointSet::Smplx127,
        truth: Vec::new(),
    };
    // The mean pose at each frame's own pelvises: a frame's poses landing on another frame would
    // score a root error, so the figures also check that each frame keeps its own.
    let predict = |at: &EvalFrame| Ok((mean_pose_at(&layer, &mean, &at.roots()), at.names()));
    let run = |at_once: usize| {
        let mut seen = Vec::new();
        let (ev, count) =
            evaluate_sequences(&seqs, &truth, &opts, at_once, predict, |i, n, names| {
                seen.push((i, n, names));
                Ok(())
            })
            .unwrap();
        (ev.overall(), count, seen)
    };
    let (one, count, seen) = run(1);
    assert_eq!(seen.len(), 5);
    for (k, (i, n, _)) in seen.iter().enumerate() {
        assert_eq!((*i, *n), (k, 5));
    }
    assert!(one.ground_truth > 0 && one.matched == one.ground_truth);
    for at_once in [2, 3, 8] {
        assert_eq!(
            run(at_once),
            (one.clone(), count, seen.clone()),
            "{at_once} at once"
        );
    }
}
