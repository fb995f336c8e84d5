//! Metrics and matching on planted predictions with hand-computed values.
use mvmp_eval::*;

fn person(offset: [f64; 3], score: f64) -> PersonPose {
    let base = [
        [0.0, 0.0, 1.0],
        [0.1, 0.0, 0.9],
        [-0.1, 0.0, 0.9],
        [0.0, 0.05, 1.2],
        [0.0, 0.0, 1.6],
    ];
    let j: Vec<[f64; 3]> = base
        .iter()
        .map(|p| [p[0] + offset[0], p[1] + offset[1], p[2] + offset[2]])
        .collect();
    PersonPose {
        joints: j.clone(),
        vertices: Some(j),
        score,
        valid: None,
    }
}

#[test]
fn errors_by_hand() {
    let gt = person([1.0, 2.0, 0.0], 0.0);
    let pred = person([1.01, 2.0, 0.0], 0.0);
    assert!((mean_error_mm(&pred.joints, &gt.joints) - 10.0).abs() < 1e-9);
    // A similarity transform of the ground truth: PVE is large, PA-PVE vanishes.
    let sim: Vec<[f64; 3]> = gt
        .joints
        .iter()
        .map(|p| [1.3 * -p[1] + 0.2, 1.3 * p[0], 1.3 * p[2] - 0.5])
        .collect();
    assert!(mean_error_mm(&sim, &gt.joints) > 100.0);
    assert!(pa_error_mm(&sim, &gt.joints).unwrap() < 1e-6);
}

#[test]
fn hungarian_beats_greedy_and_the_gate_drops_far_pairs() {
    // Greedy nearest-first would pair A-G1 (0.1) and then B-G2 (0.5): total 0.6; the optimum is 0.4.
    let pred = [[0.0, 0.0, 1.0], [0.2, 0.0, 1.0]];
    let gt = [[0.1, 0.0, 1.0], [-0.3, 0.0, 1.0]];
    let mut m = match_people(&pred, &gt, 0.5);
    m.sort();
    assert_eq!(m, vec![(0, 1), (1, 0)]);
    // More predictions than people, and one far away: it stays unmatched.
    let pred = [[5.0, 5.0, 1.0], [0.12, 0.0, 1.0], [-0.31, 0.0, 1.0]];
    let mut m = match_people(&pred, &gt, 0.5);
    m.sort();
    assert_eq!(m, vec![(1, 0), (2, 1)]);
    assert!(match_people(&pred, &gt, 0.005).is_empty());
    assert!(match_people(&[], &gt, 0.5).is_empty());
}

#[test]
fn average_precision_by_hand() {
    // Two people; detections (score, MPJPE to nearest, person): a hit, a duplicate, a looser hit.
    let dets = [(0.9, 20.0, 0usize), (0.8, 30.0, 0), (0.7, 40.0, 1)];
    // At 50 mm: TP, FP, TP -> precision 1, 1/2, 2/3 at recall 1/2, 1/2, 1 -> AP = 0.5 * 1 + 0.5 * 2/3.
    assert!((average_precision(&dets, 2, 50.0) - (0.5 + 1.0 / 3.0)).abs() < 1e-12);
    // At 25 mm only the first counts: AP = 0.5.
    assert!((average_precision(&dets, 2, 25.0) - 0.5).abs() < 1e-12);
    assert_eq!(average_precision(&dets, 2, 10.0), 0.0);
}

#[test]
fn evaluator_overall_and_per_scene() {
    let mut ev = Evaluator::new(DEFAULT_GATE);
    let gt = vec![person([0.0, 0.0, 0.0], 0.0), person([2.0, 0.0, 0.0], 0.0)];
    // Scene a: both found, 10 mm and 30 mm off; a false positive far away.
    let pred = vec![
        person([0.01, 0.0, 0.0], 0.9),
        person([2.0, 0.03, 0.0], 0.8),
        person([9.0, 9.0, 0.0], 0.5),
    ];
    ev.add_frame("a", &pred, &gt);
    // Scene b: one of two found, 20 mm off.
    ev.add_frame("b", &[person([0.0, 0.0, 0.02], 0.7)], &gt);
    let all = ev.overall();
    assert_eq!((all.matched, all.ground_truth, all.predictions), (3, 4, 4));
    assert!((all.mpjpe_mm.unwrap() - 20.0).abs() < 1e-9);
    assert!((all.pve_mm.unwrap() - 20.0).abs() < 1e-9);
    assert!(
        all.pa_pve_mm.unwrap() < 1e-6,
        "rigid shifts vanish after alignment"
    );
    assert!((all.recall_500.unwrap() - 0.75).abs() < 1e-12);
    let scenes = ev.per_scene();
    assert!((scenes["a"].mpjpe_mm.unwrap() - 20.0).abs() < 1e-9);
    assert!((scenes["b"].recall_500.unwrap() - 0.5).abs() < 1e-12);
    // At 25 mm: detections by score 0.9 (10 mm, TP), 0.8 (30 mm, FP), 0.7 (20 mm, TP, other frame), 0.5 (FP).
    let ap25 = all.ap["25"];
    let want = 0.25 * 1.0 + 0.25 * (2.0 / 3.0);
    assert!((ap25 - want).abs() < 1e-12, "{ap25} vs {want}");
}

#[test]
fn unannotated_ground_truth_joints_do_not_count() {
    // Two joints: the first is 30 mm off, the second 1 m off but not annotated in the ground truth.
    let gt = PersonPose {
        joints: vec![[0.0; 3], [0.0, 0.0, 1.0]],
        vertices: None,
        score: 1.0,
        valid: Some(vec![true, false]),
    };
    let pred = PersonPose {
        joints: vec![[0.03, 0.0, 0.0], [0.0, 0.0, 2.0]],
        vertices: None,
        score: 0.9,
        valid: None,
    };
    assert!((mvmp_eval::joint_error_mm(&pred, &gt) - 30.0).abs() < 1e-9);
    let mut ev = Evaluator::new(0.5);
    ev.add_frame("s", &[pred], &[gt]);
    assert!((ev.overall().mpjpe_mm.unwrap() - 30.0).abs() < 1e-9);
}

#[test]
fn error_parts_by_hand() {
    let gt = person([0.0, 0.0, 0.0], 0.0);
    // The ground truth turned a half turn about the vertical through its root (joint 0, at the origin's
    // column) and moved 0.3 m, 0.4 m: root 500 mm; root-relative, each joint is off by twice its
    // horizontal distance from the root's column; after alignment nothing is left.
    let turned: Vec<[f64; 3]> = gt
        .joints
        .iter()
        .map(|p| [-p[0] + 0.3, -p[1] + 0.4, p[2]])
        .collect();
    let pred = PersonPose {
        joints: turned,
        ..gt.clone()
    };
    let [root, rel, pa] = error_parts_mm(&pred, &gt, 0).unwrap();
    let want_rel = (0.0 + 0.2 + 0.2 + 0.1 + 0.0) / 5.0 * 1000.0;
    assert!((root - 500.0).abs() < 1e-9, "{root}");
    assert!((rel - want_rel).abs() < 1e-9, "{rel} against {want_rel}");
    assert!(pa < 1e-6, "{pa}");
    // Without an annotated root there are no parts.
    let unrooted = PersonPose {
        valid: Some(vec![false, true, true, true, true]),
        ..gt.clone()
    };
    assert!(error_parts_mm(&pred, &unrooted, 0).is_none());
    let mut ev = Evaluator::new(DEFAULT_GATE);
    ev.add_frame("s", &[pred], &[gt]);
    let m = ev.overall();
    assert!((m.root_mm.unwrap() - 500.0).abs() < 1e-9);
    assert!((m.rr_mpjpe_mm.unwrap() - want_rel).abs() < 1e-9);
}
