//! The stand-in body model: layout, invariants, determinism, plausibility.
mod common;
use std::collections::HashMap;

use burn::tensor::{Device, Tensor, TensorData};
use common::standin;
use mvmp_smplx::names::{NUM_JOINTS, joint_index};
use mvmp_smplx::{BodyModel, SmplxLayer, Translation, standin_model};

#[test]
fn sizes_match_smplx() {
    let m = standin();
    assert_eq!(m.num_vertices(), 10475);
    assert_eq!(m.num_faces(), 20878);
    assert_eq!(m.num_shape_components, 20);
    assert!(m.has_smplx_tree());
    assert!(m.landmarks.is_some());
}

#[test]
fn mesh_is_closed_and_consistently_oriented() {
    let m = standin();
    let mut directed: HashMap<(u32, u32), usize> = HashMap::new();
    for f in &m.faces {
        assert!(
            f[0] != f[1] && f[1] != f[2] && f[0] != f[2],
            "degenerate face {f:?}"
        );
        for k in 0..3 {
            *directed.entry((f[k], f[(k + 1) % 3])).or_default() += 1;
        }
    }
    // Closed and oriented: every directed edge appears once and its reverse appears once.
    for (&(a, b), &n) in &directed {
        assert_eq!(n, 1, "edge {a}->{b} used {n} times");
        assert_eq!(directed.get(&(b, a)), Some(&1), "edge {a}->{b} has no twin");
    }
    let used: std::collections::HashSet<u32> = m.faces.iter().flatten().copied().collect();
    assert_eq!(used.len(), m.num_vertices());
}

#[test]
fn weights_and_regressor_are_convex() {
    let m = standin();
    let v = m.num_vertices();
    for i in 0..v {
        let row = &m.weights[i * NUM_JOINTS..(i + 1) * NUM_JOINTS];
        assert!(
            row.iter().all(|&w| w >= -1e-7),
            "vertex {i} has a negative weight"
        );
        let s: f32 = row.iter().sum();
        assert!((s - 1.0).abs() < 1e-5, "vertex {i} weights sum to {s}");
    }
    for j in 0..NUM_JOINTS {
        let row = &m.j_regressor[j * v..(j + 1) * v];
        assert!(row.iter().all(|&w| w >= 0.0));
        let s: f32 = row.iter().sum();
        assert!((s - 1.0).abs() < 1e-5, "regressor row {j} sums to {s}");
    }
}

#[test]
fn deterministic_by_seed() {
    let a = standin_model(7);
    let b = standin_model(7);
    assert_eq!(a, b);
    let c = standin_model(8);
    assert_ne!(a.v_template, c.v_template);
    assert_eq!(a.faces.len(), c.faces.len());
}

fn joints(betas: &[f32]) -> (Vec<f32>, Vec<f32>) {
    let d = Device::flex();
    let layer = SmplxLayer::new(standin(), &d);
    let out = layer.forward_axis_angle(
        Tensor::zeros([1, 55, 3], &d),
        Tensor::from_data(TensorData::new(betas.to_vec(), [1, 10]), &d),
        Tensor::zeros([1, 10], &d),
        Tensor::zeros([1, 3], &d),
        Translation::Standard,
    );
    (
        out.vertices.into_data().try_into_vec().unwrap(),
        out.joints.into_data().try_into_vec().unwrap(),
    )
}

fn height(v: &[f32]) -> f32 {
    let ys = v.iter().skip(1).step_by(3);
    ys.clone().cloned().fold(f32::MIN, f32::max) - ys.cloned().fold(f32::MAX, f32::min)
}

#[test]
fn proportions_look_human() {
    let (v, j) = joints(&[0.0; 10]);
    let h = height(&v);
    assert!((1.55..1.95).contains(&h), "height {h} m");
    let p = |name: &str| {
        let i = joint_index(name).unwrap();
        [j[i * 3], j[i * 3 + 1], j[i * 3 + 2]]
    };
    // Vertical order of the body and its left/right sides (left is +x, face is +z).
    assert!(
        p("head")[1] > p("neck")[1]
            && p("neck")[1] > p("spine3")[1]
            && p("spine1")[1] > p("pelvis")[1]
    );
    assert!(p("pelvis")[1] > p("left_knee")[1] && p("left_knee")[1] > p("left_ankle")[1]);
    assert!(
        p("left_ankle")[1] > p("left_heel")[1] - 0.1
            && p("left_big_toe")[2] > p("left_heel")[2] + 0.15
    );
    assert!(p("left_wrist")[0] > 0.5 && p("right_wrist")[0] < -0.5);
    assert!(p("left_middle")[0] > p("left_wrist")[0] + 0.1);
    assert!(p("nose")[2] > p("head")[2] + 0.05 && p("nose")[1] > p("neck")[1]);
    assert!(p("left_eye")[0] > 0.0 && p("right_eye")[0] < 0.0 && p("left_ear")[0] > 0.06);
    assert!(
        p("left_big_toe")[0] < p("left_small_toe")[0],
        "big toe is medial"
    );
    assert!(
        (p("mouth_top")[1] - p("nose")[1]) < 0.0 && p("right_eye_brow1")[1] > p("right_eye1")[1]
    );
    // The first shape direction is stature; the second is girth.
    let (tall, _) = joints(&[2.0, 0., 0., 0., 0., 0., 0., 0., 0., 0.]);
    assert!(height(&tall) > h * 1.08, "{} vs {h}", height(&tall));
    let width = |v: &[f32]| {
        let i = 5000; // a torso or limb vertex moves outward with girth
        let _ = i;
        let zs = v.iter().skip(2).step_by(3);
        zs.clone().cloned().fold(f32::MIN, f32::max) - zs.cloned().fold(f32::MAX, f32::min)
    };
    let (heavy, _) = joints(&[0., 2., 0., 0., 0., 0., 0., 0., 0., 0.]);
    assert!(width(&heavy) > width(&v) * 1.02);
}

#[test]
fn npz_round_trip_keeps_everything() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("SMPLX_STANDIN.npz");
    standin().write_npz(&p).unwrap();
    let back = BodyModel::load(&p).unwrap();
    assert_eq!(&back, standin());
    let keys = BodyModel::list_keys(&p).unwrap();
    for k in [
        "v_template",
        "f",
        "shapedirs",
        "posedirs",
        "J_regressor",
        "weights",
        "kintree_table",
    ] {
        assert!(
            keys.iter().any(|(n, _)| n == k),
            "{k} missing from {keys:?}"
        );
    }
}

#[test]
fn the_joint_count_of_a_model_is_what_its_layer_outputs() {
    let d = Device::flex();
    let full = standin().clone();
    let mut bare = full.clone();
    bare.landmarks = None;
    for (m, want) in [(full, 127), (bare, 76)] {
        assert_eq!(m.num_output_joints(), want);
        assert_eq!(SmplxLayer::new(&m, &d).num_joints(), want);
    }
}
