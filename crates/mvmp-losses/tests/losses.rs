//! Each loss on hand-computed cases and against central finite differences of itself.
use burn::tensor::{Device, Int, Tensor, TensorData};
use mvmp_geom::{Camera, CameraTensors, Letterbox};
use mvmp_losses::*;
use nalgebra::{Matrix3, Vector3};

fn t<const D: usize>(v: Vec<f32>, shape: [usize; D], d: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(v, shape), d)
}

fn scalar(x: Tensor<1>) -> f32 {
    x.into_scalar::<f32>()
}

fn mask(v: Vec<f32>, b: usize, k: usize, d: &Device) -> Tensor<2> {
    t(v, [b, k], d)
}

#[test]
fn parameter_loss_by_hand() {
    let d = Device::flex();
    let eye: Vec<f32> = (0..2 * 53)
        .flat_map(|_| [1., 0., 0., 0., 1., 0., 0., 0., 1.])
        .collect();
    let mut other = eye.clone();
    other[4] += 0.9; // person 0, joint 0, R[1][1]
    other[53 * 9] += 5.0; // person 1 is masked out
    let betas = vec![0.0f32; 20];
    let mut gb = betas.clone();
    gb[3] = 2.0;
    let l = parameter_loss(
        t(other, [1, 2, 53, 3, 3], &d),
        t(eye, [1, 2, 53, 3, 3], &d),
        t(betas.clone(), [1, 2, 10], &d),
        t(gb, [1, 2, 10], &d),
        t(betas.clone(), [1, 2, 10], &d),
        t(betas, [1, 2, 10], &d),
        mask(vec![1.0, 0.0], 1, 2, &d),
    );
    let want = 0.9 / 477.0 + 2.0 / 10.0;
    assert!((scalar(l) - want).abs() < 1e-6, "{} vs {want}", 0);
}

/// Only the 21 body slots count (1 to 21 of the 53), squared, over the present people's 21 x 9 elements.
#[test]
fn body_pose_l2_by_hand() {
    let d = Device::flex();
    let eye: Vec<f32> = (0..2 * 53)
        .flat_map(|_| [1., 0., 0., 0., 1., 0., 0., 0., 1.])
        .collect();
    let mut other = eye.clone();
    other[0] += 3.0; // the global orientation: not a body slot
    other[9 + 1] += 0.5; // body slot 1 (the left hip)
    other[21 * 9 + 8] -= 0.2; // body slot 21 (the right wrist)
    other[22 * 9] += 4.0; // the first hand slot
    other[53 * 9 + 9] += 5.0; // person 1 is masked out
    let l = scalar(body_pose_l2_loss(
        t(other, [1, 2, 53, 3, 3], &d),
        t(eye, [1, 2, 53, 3, 3], &d),
        mask(vec![1.0, 0.0], 1, 2, &d),
    ));
    let want = (0.25 + 0.04) / 189.0;
    assert!((l - want).abs() < 1e-7, "{l} vs {want}");
}

#[test]
fn orientation_by_hand() {
    let d = Device::flex();
    // GT: left hip +x, right hip -x, spine1 +y: O = (2, 0, 0) x (0, 1, 0) = (0, 0, 2).
    let gt = vec![0., 0., 0., 1., 0., 0., -1., 0., 0., 0., 1., 0.];
    let o: Vec<f32> = orientation(t(gt.clone(), [1, 1, 4, 3], &d))
        .into_data()
        .try_into_vec()
        .unwrap();
    assert_eq!(o, vec![0.0, 0.0, 2.0]);
    // The person turned around (hips swapped): O = (0, 0, -2), L1 mean = 4 / 3.
    let pred = vec![0., 0., 0., -1., 0., 0., 1., 0., 0., 0., 1., 0.];
    let l = orientation_loss(
        t(pred, [1, 1, 4, 3], &d),
        t(gt, [1, 1, 4, 3], &d),
        mask(vec![1.0], 1, 1, &d),
    );
    assert!((scalar(l) - 4.0 / 3.0).abs() < 1e-6);
}

#[test]
fn density_by_hand() {
    let d = Device::flex();
    let axis = density_axis(1, 1.0, &d); // one point, at the centre
    let (sigma, off) = (0.1f32, 0.05f32);
    let l = density_loss(
        t(vec![off, 0.0, 0.0], [1, 1, 1, 3], &d),
        t(vec![0.0, 0.0, 0.0], [1, 1, 1, 3], &d),
        t(vec![0.0, 0.0, 0.0], [1, 1, 3], &d),
        axis,
        sigma,
        mask(vec![1.0], 1, 1, &d),
    );
    let want = (1.0 - (-(off * off) / (2.0 * sigma * sigma)).exp()).powi(2);
    assert!((scalar(l) - want).abs() < 1e-6);
    let g: Vec<f32> = density_grid(2, 1.0, &d).into_data().try_into_vec().unwrap();
    assert_eq!(g[..6], [-0.25, -0.25, -0.25, -0.25, -0.25, 0.25]);
}

/// The loss's separable density on a cube equals every point's sum over joints on the same cube's
/// points (5 a side, off-centre people, joints inside and outside it): float rounding apart, 1e-6.
#[test]
fn density_on_the_cube_is_the_pointwise_density() {
    let d = Device::flex();
    let (side, extent, sigma) = (5, 1.3, 0.2f32);
    let people = joints(3, 7);
    let centre = t(vec![0.1, -0.2, 0.05, -0.3, 0.0, 0.2], [1, 2, 3], &d);
    let p = t(people, [1, 2, 7, 3], &d);
    let v = |x: Tensor<3>| -> Vec<f32> { x.into_data().try_into_vec().unwrap() };
    let cube = v(joint_density_cube(
        p.clone(),
        centre.clone(),
        density_axis(side, extent, &d),
        sigma,
    ));
    let points = v(joint_density(
        p,
        centre,
        density_grid(side, extent, &d),
        sigma,
    ));
    assert_eq!(cube.len(), 2 * side * side * side);
    let peak = points.iter().cloned().fold(0.0f32, f32::max);
    assert!(peak > 0.5, "some joints lie near the cube's points: {peak}");
    for (i, (a, b)) in cube.iter().zip(&points).enumerate() {
        assert!((a - b).abs() < 1e-6, "point {i}: {a} against {b}");
    }
}

#[test]
fn detection_by_hand() {
    let d = Device::flex();
    // A 2 x 2 x 1 volume: likelihood 0.5 everywhere, target 1 at voxel 3: MSE = (3 * 0.25 + 0.25) / 4.
    let lik = t(vec![0.5; 4], [1, 1, 2, 2, 1], &d);
    let target = t(vec![0.0, 0.0, 0.0, 1.0], [1, 1, 2, 2, 1], &d);
    // Offsets: channel-major; at voxel 3 the prediction is (0.1, -0.2, 0.3), the truth (0.2, 0.2, 0.0).
    let mut off = vec![0.0f32; 12];
    off[3] = 0.1;
    off[7] = -0.2;
    off[11] = 0.3;
    let l = detection_loss(
        lik,
        target,
        t(off, [1, 3, 2, 2, 1], &d),
        Tensor::<2, Int>::from_data(TensorData::new(vec![3i64, 0], [1, 2]), &d),
        t(vec![0.2, 0.2, 0.0, 9.0, 9.0, 9.0], [1, 2, 3], &d),
        mask(vec![1.0, 0.0], 1, 2, &d),
    );
    let want = 0.25 + (0.1 + 0.4 + 0.3) / 3.0;
    assert!((scalar(l) - want).abs() < 1e-6, "{}", want);
}

fn camera() -> (Camera, Letterbox) {
    let k = Matrix3::new(100.0, 0.0, 31.5, 0.0, 100.0, 31.5, 0.0, 0.0, 1.0);
    let cam = Camera::new(
        "c",
        k,
        Matrix3::identity(),
        Vector3::zeros(),
        [0.0; 5],
        64,
        64,
    )
    .unwrap();
    (cam, Letterbox::new(64, 64, 64).unwrap())
}

#[test]
fn mesh_2d_by_hand_counts_only_points_inside() {
    let d = Device::flex();
    let (cam, lb) = camera();
    let ct = CameraTensors::new(&[cam], Some(&[lb]), &d);
    // Points at depth 2: (0.1, 0, 2) -> u = 36.5, v = 31.5; (0, -0.2, 2) -> (31.5, 21.5).
    let pts = t(
        vec![0.1, 0.0, 2.0, 0.0, -0.2, 2.0, 0.0, 0.0, 2.0],
        [1, 1, 3, 3],
        &d,
    );
    // GT: off by (1, -2) and (0, 3); the third GT point is outside the image and must not count.
    let gt = t(vec![37.5, 29.5, 31.5, 24.5, -5.0, 10.0], [1, 1, 3, 2], &d);
    let l = mesh_2d_loss(pts, gt, &[ct], 64.0, mask(vec![1.0], 1, 1, &d));
    let want = (1.0 + 2.0 + 0.0 + 3.0) / 4.0;
    assert!((scalar(l) - want).abs() < 1e-4, "{}", want);
}

/// Central differences of `f` at `x` against the autodiff gradient.
fn check_gradient(name: &str, x: Vec<f32>, shape: [usize; 4], f: &dyn Fn(Tensor<4>) -> Tensor<1>) {
    let ad = Device::flex().autodiff();
    let xt = t(x.clone(), shape, &ad).require_grad();
    let grads = f(xt.clone()).backward();
    let g: Vec<f32> = xt.grad(&grads).unwrap().into_data().try_into_vec().unwrap();
    let plain = Device::flex();
    let eval = |v: Vec<f32>| scalar(f(t(v, shape, &plain)));
    let eps = 1e-3f32;
    for i in (0..x.len()).step_by((x.len() / 12).max(1)) {
        let (mut a, mut b) = (x.clone(), x.clone());
        a[i] += eps;
        b[i] -= eps;
        let fd = (eval(a) - eval(b)) / (2.0 * eps);
        assert!(
            (g[i] - fd).abs() < 2e-2 * fd.abs().max(1.0),
            "{name}[{i}]: autodiff {} vs fd {fd}",
            g[i]
        );
    }
}

/// Scattered test joints from a hash (an arithmetic pattern in the index, like a sinusoid or a modular
/// progression, puts the points on a curve where orientation vectors vanish or coincide).
fn joints(seed: u64, n: usize) -> Vec<f32> {
    (0..2 * n * 3)
        .map(|i| {
            let mut z = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                ^ seed.wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            ((z >> 40) as f32 / (1u64 << 24) as f32 - 0.5) * 0.8
        })
        .collect()
}

#[test]
fn gradients_match_finite_differences() {
    let plain = Device::flex();
    let gt = joints(1, 6);
    let gtm = |d: &Device| t(gt.clone(), [1, 2, 6, 3], d);
    let m = |d: &Device| mask(vec![1.0, 1.0], 1, 2, d);
    check_gradient("orientation", joints(0, 6), [1, 2, 6, 3], &|x| {
        let d = x.device();
        orientation_loss(x, gtm(&d), m(&d))
    });
    check_gradient("density", joints(0, 6), [1, 2, 6, 3], &|x| {
        let d = x.device();
        let pelvis = t(vec![0.0, 0.0, 0.0, 0.1, 0.0, 0.0], [1, 2, 3], &d);
        density_loss(x, gtm(&d), pelvis, density_axis(4, 1.2, &d), 0.15, m(&d))
    });
    check_gradient("mesh_3d", joints(0, 6), [1, 2, 6, 3], &|x| {
        let d = x.device();
        mesh_3d_loss(x, gtm(&d), m(&d))
    });
    let (cam, lb) = camera();
    check_gradient(
        "mesh_2d",
        joints(0, 6)
            .iter()
            .enumerate()
            .map(|(i, v)| if i % 3 == 2 { v + 2.0 } else { *v })
            .collect(),
        [1, 2, 6, 3],
        &|x| {
            let d = x.device();
            let ct = CameraTensors::new(std::slice::from_ref(&cam), Some(&[lb]), &d);
            let gt2: Vec<f32> = (0..2 * 6 * 2)
                .map(|i| 20.0 + (i as f32 * 1.3) % 25.0)
                .collect();
            mesh_2d_loss(x, t(gt2, [1, 2, 6, 2], &d), &[ct], 64.0, m(&d))
        },
    );
    let _ = plain;
}

#[test]
fn weights_default_to_the_paper_and_terms_add_up() {
    let w = LossWeights::default();
    assert_eq!(
        (
            w.detection,
            w.parameters,
            w.mesh_3d,
            w.orientation,
            w.density
        ),
        (1.0, 10.0, 100.0, 5.0, 1.0)
    );
    assert!(w.validate().is_ok());
    let bad = LossWeights {
        orientation: -1.0,
        ..Default::default()
    };
    assert!(
        bad.validate()
            .unwrap_err()
            .contains("loss.orientation = -1")
    );
    // Values far past any use are refused too, naming the key: a weight that overflows the loss, a
    // Gaussian wider than the scene.
    let refused = [
        (
            "loss.density = 10000000",
            LossWeights {
                density: 1e7,
                ..Default::default()
            },
        ),
        (
            "loss.detection_sigma = 1000",
            LossWeights {
                detection_sigma: 1e3,
                ..Default::default()
            },
        ),
        (
            "loss.density_extent = 1000",
            LossWeights {
                density_extent: 1e3,
                ..Default::default()
            },
        ),
        (
            "loss.heatmap_sigma = 1000",
            LossWeights {
                heatmap_sigma: 1e3,
                ..Default::default()
            },
        ),
        (
            "loss.density_sigma = 0",
            LossWeights {
                density_sigma: 0.0,
                ..Default::default()
            },
        ),
        (
            "loss.facing = NaN",
            LossWeights {
                facing: f32::NAN,
                ..Default::default()
            },
        ),
    ];
    for (key, w) in refused {
        let e = w.validate().unwrap_err();
        assert!(e.starts_with(key), "{e}");
    }
    let edge = LossWeights {
        parameters: 1e6,
        density_sigma: 10.0,
        ..Default::default()
    };
    assert!(edge.validate().is_ok());
    let d = Device::flex();
    let one = |v: f32| Some(t(vec![v], [1], &d));
    let terms = LossTerms {
        detection: one(1.0),
        parameters: None,
        mesh: one(2.5),
        orientation: one(0.5),
        density: None,
        heatmap_2d: None,
        facing: one(0.25),
        vit_heatmap: None,
        joint_offsets: None,
    };
    assert_eq!(scalar(terms.total().unwrap()), 4.25);
    assert_eq!(
        terms.named().iter().map(|(n, _)| *n).collect::<Vec<_>>(),
        ["detection", "mesh", "orientation", "facing"]
    );
    assert!(LossTerms::default().total().is_none());
}

#[test]
fn heatmap_loss_by_hand_weights_joints() {
    let d = Device::flex();
    // B=1, V=1, J=2, 1x2 maps. Joint 0 errors (1, 3): MSE 5; joint 1 errors (2, 0): MSE 2, weight 0.
    let pred = t(vec![1.0, 3.0, 2.0, 0.0], [1, 1, 2, 1, 2], &d);
    let target = t(vec![0.0; 4], [1, 1, 2, 1, 2], &d);
    let w = t(vec![1.0, 0.0], [1, 1, 2], &d);
    assert!((scalar(heatmap_loss(pred, target, w)) - 2.5).abs() < 1e-6);
}

#[test]
fn heatmap_target_peaks_where_the_fusion_samples() {
    // Network pixel u = 9.5 at stride 4 is map coordinate (9.5 + 0.5) / 4 - 0.5 = 2.0 exactly.
    let h = heatmap_target(&[Some([9.5, 5.5]), None], [4, 6], 4.0, 1.0);
    assert_eq!(h.len(), 2 * 4 * 6);
    // (u, v) -> map (2.0, 1.0): the peak is 1 at row 1, column 2; a neighbour is exp(-1/2).
    assert!((h[6 + 2] - 1.0).abs() < 1e-6);
    assert!((h[6 + 3] - (-0.5f32).exp()).abs() < 1e-6);
    assert!((h[2 * 6 + 3] - (-1.0f32).exp()).abs() < 1e-6);
    assert!(
        h[24..].iter().all(|&x| x == 0.0),
        "a missing joint stays zero"
    );
    // Beyond 3 sigma nothing is written: sigma 0.5 reaches columns 0..=4 of row 1, not column 5.
    let h = heatmap_target(&[Some([9.5, 5.5])], [4, 6], 4.0, 0.5);
    assert!(h[6 + 4] > 0.0);
    assert_eq!(h[6 + 5], 0.0);
}

/// Per-point weights: an unannotated point (weight 0) does not count however wrong it is; the mean runs
/// over the annotated coordinates only: (|1|+|1|+|1| + |2|) / (2 points x 3) = 5/6. With every point of a
/// valid pair weighted 1 it is the per-pair loss.
#[test]
fn weighted_mesh_3d_loss_by_hand() {
    let d = Device::default();
    let pts = t(
        vec![1.0, 1.0, 1.0, 100.0, -100.0, 100.0, 2.0, 0.0, 0.0],
        [1, 1, 3, 3],
        &d,
    );
    let gt = Tensor::<4>::zeros([1, 1, 3, 3], &d);
    let w = t(vec![1.0, 0.0, 1.0], [1, 1, 3], &d);
    let l = scalar(mesh_3d_loss_weighted(pts.clone(), gt.clone(), w));
    assert!((l - 5.0 / 6.0).abs() < 1e-6, "{l}");
    let all = scalar(mesh_3d_loss_weighted(
        pts.clone(),
        gt.clone(),
        Tensor::ones([1, 1, 3], &d),
    ));
    let pair = scalar(mesh_3d_loss(pts, gt, mask(vec![1.0], 1, 1, &d)));
    assert!(
        (all - pair).abs() < 1e-5 && (pair - 305.0 / 9.0).abs() < 1e-4,
        "{all} {pair}"
    );
}

#[test]
fn detection_positive_loss_by_hand() {
    let d = Device::flex();
    // Four voxels; target mass 1 + 0.5 = 1.5 at the first two.
    let target = t(vec![1.0, 0.5, 0.0, 0.0], [1, 1, 1, 1, 4], &d);
    let lik = t(vec![0.4, 0.5, 0.9, 0.0], [1, 1, 1, 1, 4], &d);
    // (1 * 0.6^2 + 0.5 * 0^2) / 1.5; the empty voxel at 0.9 does not count.
    let want = 0.36 / 1.5;
    assert!((scalar(detection_positive_loss(lik.clone(), target)) - want).abs() < 1e-6);
    // An empty target gives 0, not a division by zero.
    let empty = t(vec![0.0; 4], [1, 1, 1, 1, 4], &d);
    assert_eq!(scalar(detection_positive_loss(lik, empty)), 0.0);
}

#[test]
fn facing_loss_by_hand() {
    let d = Device::flex();
    // One view of 1 x 2 pixels, channels (c0, c1): predicted (1, 0) and (0.5, 0), targets (0, 0.5) and
    // (0, -1); squared errors 1 + 0.25 and 0.25 + 1; weights 1 and 3.
    let pred = t(vec![1.0, 0.5, 0.0, 0.0], [1, 1, 2, 1, 2], &d);
    let target = t(vec![0.0, 0.0, 0.5, -1.0], [1, 1, 2, 1, 2], &d);
    let weight = t(vec![1.0, 3.0], [1, 1, 1, 2], &d);
    let e0 = 1.0 + 0.25;
    let e1 = 0.25 + 1.0;
    let want = (e0 + 3.0 * e1) / 4.0;
    assert!((scalar(facing_loss(pred.clone(), target.clone(), weight)) - want).abs() < 1e-6);
    // Weight only on pixel 0 with a different error at pixel 1: pixel 1 does not count.
    let weight = t(vec![2.0, 0.0], [1, 1, 1, 2], &d);
    let pred = t(vec![1.0, 9.0, 0.0, 9.0], [1, 1, 2, 1, 2], &d);
    assert!((scalar(facing_loss(pred, target, weight)) - e0).abs() < 1e-6);
}

#[test]
fn facing_bin_loss_by_hand() {
    let d = Device::flex();
    // One view of 1 x 2 pixels, 4 bins (channel-major). Pixel 0: equal logits, so log-softmax is
    // -ln 4 in every bin and the cross-entropy is ln 4 whatever the label. Pixel 1: logits (ln 2, 0, 0,
    // 0) give probabilities (2/5, 1/5, 1/5, 1/5); its label (1/2, 1/2, 0, 0) costs
    // -(ln(2/5) + ln(1/5)) / 2. Weights 1 and 3.
    let logits = t(
        vec![0.0, 2f32.ln(), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        [1, 1, 4, 1, 2],
        &d,
    );
    let labels = t(
        vec![0.1, 0.5, 0.2, 0.5, 0.3, 0.0, 0.4, 0.0],
        [1, 1, 4, 1, 2],
        &d,
    );
    let weight = t(vec![1.0, 3.0], [1, 1, 1, 2], &d);
    let e0 = 4f32.ln();
    let e1 = -((0.4f32).ln() + (0.2f32).ln()) / 2.0;
    let want = (e0 + 3.0 * e1) / 4.0;
    let got = scalar(facing_bin_loss(logits, labels, weight));
    assert!((got - want).abs() < 1e-5, "{got} {want}");
}

#[test]
fn body_frame_by_hand() {
    let d = Device::flex();
    // A quarter turn about z (body x -> world y) at pelvis (2, 3, 4): the body point (1, 0, 0) is the
    // world point (2, 4, 4) and the body point (0, 0, 1) is (2, 3, 5).
    let rot = t(vec![0., -1., 0., 1., 0., 0., 0., 0., 1.], [1, 1, 3, 3], &d);
    let pelvis = t(vec![2., 3., 4.], [1, 1, 3], &d);
    let world = t(vec![2., 4., 4., 2., 3., 5.], [1, 1, 2, 3], &d);
    let body: Vec<f32> = to_body_frame(world, pelvis, rot)
        .into_data()
        .try_into_vec()
        .unwrap();
    let want = [1., 0., 0., 0., 0., 1.];
    for (a, w) in body.iter().zip(want) {
        assert!((a - w).abs() < 1e-6, "{body:?} against {want:?}");
    }
}

#[test]
fn body_frame_takes_out_any_rigid_motion() {
    let d = Device::flex();
    let pts = joints(7, 3); // 6 points
    let local = t(pts.clone(), [1, 1, 6, 3], &d);
    let r = nalgebra::Rotation3::from_euler_angles(0.3, -1.1, 2.4);
    let m: Vec<f32> = r.matrix().iter().map(|&x| x as f32).collect(); // column-major
    let rot = t(m, [1, 1, 3, 3], &d).swap_dims(2, 3); // row-major R
    let shift = [0.7f32, -2.5, 1.2];
    let moved: Vec<f32> = pts
        .chunks(3)
        .flat_map(|p| {
            let q = r * Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
            (0..3).map(move |i| q[i] as f32 + shift[i])
        })
        .collect();
    let back = to_body_frame(
        t(moved, [1, 1, 6, 3], &d),
        t(shift.to_vec(), [1, 1, 3], &d),
        rot,
    );
    let err = scalar((back - local).abs().max());
    assert!(err < 1e-5, "body frame off by {err}");
}

#[test]
fn translation_loss_by_hand_skips_masked_pairs() {
    let d = Device::flex();
    let pred = t(vec![0.1, 0.0, -0.2, 9.0, 9.0, 9.0], [1, 2, 3], &d);
    let gt = t(vec![0.0; 6], [1, 2, 3], &d);
    let l = scalar(translation_loss(pred, gt, mask(vec![1.0, 0.0], 1, 2, &d)));
    assert!((l - 0.1).abs() < 1e-6, "{l}");
}
