//! The tensor SMPL-X layer against the independent f64 reference, identities and finite differences.
mod common;
use burn::tensor::{Device, Tensor, TensorData};
use common::{reference_forward, standin, test_pose};
use mvmp_smplx::names::NUM_JOINTS_WITH_LANDMARKS;
use mvmp_smplx::{SmplxLayer, Translation};

fn t<const D: usize>(v: &[f64], shape: [usize; D], d: &Device) -> Tensor<D> {
    let v: Vec<f32> = v.iter().map(|&x| x as f32).collect();
    Tensor::from_data(TensorData::new(v, shape), d)
}

fn vals<const D: usize>(x: Tensor<D>) -> Vec<f32> {
    x.into_data().try_into_vec().unwrap()
}

#[test]
fn zero_pose_and_shape_give_the_template() {
    let d = Device::flex();
    let m = standin();
    let layer = SmplxLayer::new(m, &d);
    let out = layer.forward_axis_angle(
        Tensor::zeros([2, 55, 3], &d),
        Tensor::zeros([2, 10], &d),
        Tensor::zeros([2, 10], &d),
        Tensor::zeros([2, 3], &d),
        Translation::Standard,
    );
    let v = vals(out.vertices);
    for (k, &x) in v.iter().enumerate() {
        assert!(
            (x - m.v_template[k % m.v_template.len()]).abs() < 1e-6,
            "vertex coord {k}"
        );
    }
    assert_eq!(out.joints.dims(), [2, NUM_JOINTS_WITH_LANDMARKS, 3]);
}

#[test]
fn batched_forward_matches_reference() {
    let d = Device::flex();
    let m = standin();
    let layer = SmplxLayer::new(m, &d);
    let n = 3;
    let poses: Vec<Vec<f64>> = (0..n).map(|i| test_pose(i as f64)).collect();
    let betas: Vec<Vec<f64>> = (0..n)
        .map(|i| {
            (0..10)
                .map(|k| ((k + i) as f64 * 0.9).cos() * 1.5)
                .collect()
        })
        .collect();
    let exprs: Vec<Vec<f64>> = (0..n)
        .map(|i| (0..10).map(|k| ((k * i) as f64 * 0.4).sin()).collect())
        .collect();
    let transl = [[0.5, -1.0, 2.0], [0.0, 0.0, 0.0], [-3.0, 4.0, 0.1]];
    let out = layer.forward_axis_angle(
        t(&poses.concat(), [n, 55, 3], &d),
        t(&betas.concat(), [n, 10], &d),
        t(&exprs.concat(), [n, 10], &d),
        t(&transl.concat(), [n, 3], &d),
        Translation::Standard,
    );
    let v = vals(out.vertices);
    let j = vals(out.joints);
    let nv = m.num_vertices();
    for i in 0..n {
        let r = reference_forward(m, &poses[i], &betas[i], &exprs[i], transl[i]);
        let mut worst = 0f64;
        for (k, p) in r.vertices.iter().enumerate() {
            for a in 0..3 {
                worst = worst.max((v[(i * nv + k) * 3 + a] as f64 - p[a]).abs());
            }
        }
        for (k, p) in r.joints.iter().enumerate() {
            for a in 0..3 {
                worst = worst.max((j[(i * r.joints.len() + k) * 3 + a] as f64 - p[a]).abs());
            }
        }
        // float32 through a chain of up to 12 rotations: micrometres.
        assert!(worst < 2e-5, "body {i}: max error {worst} m");
    }
}

#[test]
fn pelvis_translation_puts_the_pelvis_there() {
    let d = Device::flex();
    let layer = SmplxLayer::new(standin(), &d);
    let transl = [3.0, -2.0, 1.0];
    let betas: Vec<f64> = (0..10).map(|k| (k as f64).sin() * 2.0).collect();
    let out = layer.forward_axis_angle(
        t(&test_pose(0.3), [1, 55, 3], &d),
        t(&betas, [1, 10], &d),
        Tensor::zeros([1, 10], &d),
        t(&transl, [1, 3], &d),
        Translation::Pelvis,
    );
    let j = vals(out.joints);
    for a in 0..3 {
        assert!((j[a] as f64 - transl[a]).abs() < 1e-5);
    }
}

/// Loss used by the gradient checks: a fixed weighting of every vertex and joint coordinate.
fn loss_weights(n: usize) -> Vec<f64> {
    (0..n).map(|k| ((k as f64) * 0.618).sin()).collect()
}

fn ref_loss(pose: &[f64], betas: &[f64], expr: &[f64], transl: [f64; 3]) -> f64 {
    let r = reference_forward(standin(), pose, betas, expr, transl);
    let wv = loss_weights(r.vertices.len() * 3);
    let wj = loss_weights(r.joints.len() * 3);
    let sv: f64 = r
        .vertices
        .iter()
        .flat_map(|p| [p.x, p.y, p.z])
        .zip(&wv)
        .map(|(a, b)| a * b)
        .sum();
    let sj: f64 = r
        .joints
        .iter()
        .flat_map(|p| [p.x, p.y, p.z])
        .zip(&wj)
        .map(|(a, b)| a * b)
        .sum();
    sv * 1e-3 + sj
}

/// Both training paths: the fused operation (`forward` under autodiff on flex) and the tensor ops.
#[derive(Debug, Clone, Copy)]
enum Path {
    Fused,
    TensorOps,
}

fn pose_with(
    layer: &SmplxLayer,
    path: Path,
    pose: Tensor<3>,
    b: Tensor<2>,
    e: Tensor<2>,
    tr: Tensor<2>,
    mode: Translation,
) -> mvmp_smplx::SmplxOutput {
    let n = pose.dims()[0];
    let rot =
        mvmp_geom::rotation::axis_angle_to_matrix(pose.reshape([n * 55, 3])).reshape([n, 55, 3, 3]);
    match path {
        Path::Fused => layer.forward(rot, b, e, tr, mode),
        Path::TensorOps => layer.forward_tensor_ops(rot, b, e, tr, mode),
    }
}

#[test]
fn gradients_match_finite_differences() {
    for path in [Path::Fused, Path::TensorOps] {
        gradients_match_finite_differences_on(path);
    }
}

fn gradients_match_finite_differences_on(path: Path) {
    let d = Device::flex().autodiff();
    let m = standin();
    let layer = SmplxLayer::new(m, &d);
    let pose = test_pose(1.0);
    let betas: Vec<f64> = (0..10).map(|k| (k as f64 * 0.3).cos()).collect();
    let expr: Vec<f64> = (0..10).map(|k| (k as f64 * 0.5).sin() * 0.5).collect();
    let transl = [0.2, 0.3, -0.1];
    let pt = t(&pose, [1, 55, 3], &d).require_grad();
    let bt = t(&betas, [1, 10], &d).require_grad();
    let et = t(&expr, [1, 10], &d).require_grad();
    let tt = t(&transl, [1, 3], &d).require_grad();
    let out = pose_with(
        &layer,
        path,
        pt.clone(),
        bt.clone(),
        et.clone(),
        tt.clone(),
        Translation::Standard,
    );
    let [_, nv, _] = out.vertices.dims();
    let [_, nj, _] = out.joints.dims();
    let wv = t(&loss_weights(nv * 3), [1, nv, 3], &d);
    let wj = t(&loss_weights(nj * 3), [1, nj, 3], &d);
    let loss = (out.vertices * wv).sum() * 1e-3 + (out.joints * wj).sum();
    let grads = loss.backward();
    let g_pose = vals(pt.grad(&grads).unwrap());
    let g_betas = vals(bt.grad(&grads).unwrap());
    let g_expr = vals(et.grad(&grads).unwrap());
    let g_transl = vals(tt.grad(&grads).unwrap());

    let h = 1e-5;
    let check = |name: &str, k: usize, got: f32, f: &dyn Fn(f64) -> f64| {
        let fd = (f(h) - f(-h)) / (2.0 * h);
        let tol = 2e-3 * fd.abs().max(1.0);
        assert!(
            (got as f64 - fd).abs() < tol,
            "{path:?}: d loss / d {name}[{k}]: autodiff {got} vs finite differences {fd}"
        );
    };
    // Global orientation, a knee, an elbow, the jaw, a finger joint.
    for joint in [0usize, 4, 18, 22, 27] {
        for a in 0..3 {
            let k = joint * 3 + a;
            check("pose", k, g_pose[k], &|e| {
                let mut p = pose.clone();
                p[k] += e;
                ref_loss(&p, &betas, &expr, transl)
            });
        }
    }
    for k in 0..10 {
        check("betas", k, g_betas[k], &|e| {
            let mut b = betas.clone();
            b[k] += e;
            ref_loss(&pose, &b, &expr, transl)
        });
        check("expression", k, g_expr[k], &|e| {
            let mut x = expr.clone();
            x[k] += e;
            ref_loss(&pose, &betas, &x, transl)
        });
    }
    for k in 0..3 {
        check("transl", k, g_transl[k], &|e| {
            let mut tr = transl;
            tr[k] += e;
            ref_loss(&pose, &betas, &expr, tr)
        });
    }
}

#[test]
fn regressed_order_maps_to_the_full_pose() {
    use mvmp_geom::rotation::axis_angle_to_matrix;
    use mvmp_smplx::names::REGRESSED_TO_JOINT;
    use mvmp_smplx::regressed_to_full_pose;
    let d = Device::flex();
    // Distinct rotation per regressed slot: angle 0.01 * (slot + 1) about x.
    let aa: Vec<f64> = (0..53)
        .flat_map(|i| [0.01 * (i + 1) as f64, 0.0, 0.0])
        .collect();
    let rot = axis_angle_to_matrix(t(&aa, [53, 3], &d)).reshape([1, 53, 3, 3]);
    let full = vals(regressed_to_full_pose(rot));
    let angle = |j: usize| (full[j * 9 + 7] as f64).asin(); // R[2][1] = sin(angle)
    for (slot, &joint) in REGRESSED_TO_JOINT.iter().enumerate() {
        assert!(
            (angle(joint) - 0.01 * (slot + 1) as f64).abs() < 1e-6,
            "slot {slot} -> joint {joint}"
        );
    }
    for eye in [23, 24] {
        assert_eq!(angle(eye), 0.0);
    }
}

/// The fused CPU pass (`forward` on plain flex) and the tensor-op path compute the same function, for
/// batch sizes that fill the kernels' column tiles exactly and ones that leave a remainder.
#[test]
fn fused_pass_matches_the_tensor_ops() {
    let d = Device::flex();
    let layer = SmplxLayer::new(standin(), &d);
    assert!(layer.is_fused(), "plain flex must take the fused pass");
    for n in [1usize, 3, 13, 37] {
        let pose: Vec<f64> = (0..n).flat_map(|i| test_pose(0.37 * i as f64)).collect();
        let betas: Vec<f64> = (0..n * 10).map(|k| (k as f64 * 0.71).sin() * 2.0).collect();
        let expr: Vec<f64> = (0..n * 10).map(|k| (k as f64 * 1.3).cos()).collect();
        let transl: Vec<f64> = (0..n * 3).map(|k| (k as f64 * 0.5).sin() * 10.0).collect();
        for mode in [Translation::Standard, Translation::Pelvis] {
            let rot = mvmp_geom::rotation::axis_angle_to_matrix(t(&pose, [n * 55, 3], &d))
                .reshape([n, 55, 3, 3]);
            let inputs = || {
                (
                    rot.clone(),
                    t(&betas, [n, 10], &d),
                    t(&expr, [n, 10], &d),
                    t(&transl, [n, 3], &d),
                )
            };
            let (r, b, e, tr) = inputs();
            let fused = layer.forward(r, b, e, tr, mode);
            let (r, b, e, tr) = inputs();
            let plain = layer.forward_tensor_ops(r, b, e, tr, mode);
            assert_eq!(fused.vertices.dims(), plain.vertices.dims());
            assert_eq!(fused.joints.dims(), plain.joints.dims());
            for (what, a, b) in [
                ("vertices", vals(fused.vertices), vals(plain.vertices)),
                ("joints", vals(fused.joints), vals(plain.joints)),
            ] {
                let worst = a
                    .iter()
                    .zip(&b)
                    .map(|(x, y)| (x - y).abs())
                    .fold(0f32, f32::max);
                // Both f32; translations up to 10 m leave ~1 µm of rounding.
                assert!(
                    worst < 1e-5,
                    "batch {n}, {mode:?}, {what}: max diff {worst} m"
                );
            }
        }
    }
}

/// The fused operation's backward gives the tensor ops' gradients in every input (rotation matrices,
/// betas, expression, translation), for both translation modes and batch sizes that fill the kernels'
/// tiles exactly and ones that leave a remainder.
#[test]
fn fused_backward_matches_the_tensor_ops() {
    let d = Device::flex().autodiff();
    let layer = SmplxLayer::new(standin(), &d);
    assert!(
        layer.is_fused(),
        "autodiff flex must take the fused operation"
    );
    for n in [1usize, 3, 13] {
        let pose: Vec<f64> = (0..n)
            .flat_map(|i| test_pose(0.41 * i as f64 + 0.2))
            .collect();
        let betas: Vec<f64> = (0..n * 10).map(|k| (k as f64 * 0.71).sin() * 2.0).collect();
        let expr: Vec<f64> = (0..n * 10).map(|k| (k as f64 * 1.3).cos()).collect();
        let transl: Vec<f64> = (0..n * 3).map(|k| (k as f64 * 0.5).sin() * 3.0).collect();
        for mode in [Translation::Standard, Translation::Pelvis] {
            let run = |path: Path| {
                let rot = mvmp_geom::rotation::axis_angle_to_matrix(t(&pose, [n * 55, 3], &d))
                    .reshape([n, 55, 3, 3])
                    .detach()
                    .require_grad();
                let b = t(&betas, [n, 10], &d).require_grad();
                let e = t(&expr, [n, 10], &d).require_grad();
                let tr = t(&transl, [n, 3], &d).require_grad();
                let out = match path {
                    Path::Fused => {
                        layer.forward(rot.clone(), b.clone(), e.clone(), tr.clone(), mode)
                    }
                    Path::TensorOps => layer.forward_tensor_ops(
                        rot.clone(),
                        b.clone(),
                        e.clone(),
                        tr.clone(),
                        mode,
                    ),
                };
                let [_, nv, _] = out.vertices.dims();
                let [_, nj, _] = out.joints.dims();
                let wv = t(&loss_weights(n * nv * 3), [n, nv, 3], &d);
                let wj = t(&loss_weights(n * nj * 3), [n, nj, 3], &d);
                let grads = ((out.vertices * wv).sum() + (out.joints * wj).sum()).backward();
                [
                    vals(rot.grad(&grads).unwrap()),
                    vals(b.grad(&grads).unwrap()),
                    vals(e.grad(&grads).unwrap()),
                    vals(tr.grad(&grads).unwrap()),
                ]
            };
            let (fused, plain) = (run(Path::Fused), run(Path::TensorOps));
            for (what, a, b) in ["rotations", "betas", "expression", "translation"]
                .iter()
                .zip(&fused)
                .zip(&plain)
                .map(|((w, a), b)| (w, a, b))
            {
                let scale = b.iter().fold(1f32, |m, x| m.max(x.abs()));
                let worst = a
                    .iter()
                    .zip(b)
                    .map(|(x, y)| (x - y).abs())
                    .fold(0f32, f32::max);
                // Both float32 sums over ~10^4 vertices in different orders.
                assert!(
                    worst <= 1e-5 * scale,
                    "batch {n}, {mode:?}, {what}: max diff {worst} (largest gradient {scale})"
                );
            }
        }
    }
}

/// Axis-angle inputs under autodiff get their gradients through the fused operation.
#[test]
fn autodiff_inputs_get_gradients() {
    let d = Device::flex().autodiff();
    let layer = SmplxLayer::new(standin(), &d);
    assert!(layer.is_fused());
    let betas = t(&[0.5; 10], [1, 10], &d).require_grad();
    let out = layer.forward_axis_angle(
        t(&test_pose(0.2), [1, 55, 3], &d),
        betas.clone(),
        Tensor::zeros([1, 10], &d),
        Tensor::zeros([1, 3], &d),
        Translation::Standard,
    );
    let grads = out.vertices.sum().backward();
    let g = vals(betas.grad(&grads).expect("betas gradient"));
    assert!(g.iter().any(|x| x.abs() > 1e-3), "gradient {g:?}");
}
