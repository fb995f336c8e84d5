//! Rotation conversions as tensor ops, against nalgebra (f64) and known identities.
use burn::tensor::{Device, Tensor, TensorData};
use mvmp_geom::rotation::*;
use nalgebra::{Matrix3, Vector3};

fn t2(v: &[f32], n: usize, k: usize) -> Tensor<2> {
    Tensor::from_data(TensorData::new(v.to_vec(), [n, k]), &Device::flex())
}

fn vals<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec().unwrap()
}

fn sample_axis_angles() -> Vec<[f64; 3]> {
    let mut out = vec![
        [0.0; 3],
        [1e-7, -2e-7, 3e-7],
        [1e-3, 0.0, 0.0],
        [0.0, 0.0, 3.1],
        [2.0, -1.0, 0.5],
    ];
    for i in 0..40 {
        let t = i as f64;
        let axis = Vector3::new((t * 1.3).sin(), (t * 0.7).cos(), (t * 2.1).sin()).normalize();
        let angle = 0.05 + 3.0 * ((t * 0.37).sin() * 0.5 + 0.5);
        out.push((axis * angle).into());
    }
    out
}

#[test]
fn axis_angle_to_matrix_matches_nalgebra() {
    let aa = sample_axis_angles();
    let flat: Vec<f32> = aa.iter().flatten().map(|&x| x as f32).collect();
    let m = vals(axis_angle_to_matrix(t2(&flat, aa.len(), 3)));
    for (i, a) in aa.iter().enumerate() {
        let want = axis_angle_to_matrix_f64(Vector3::from(*a));
        for r in 0..3 {
            for c in 0..3 {
                let got = m[i * 9 + r * 3 + c] as f64;
                assert!(
                    (got - want[(r, c)]).abs() < 2e-6,
                    "{a:?} [{r},{c}]: {got} vs {}",
                    want[(r, c)]
                );
            }
        }
    }
}

#[test]
fn matrix_to_axis_angle_round_trip() {
    let aa = sample_axis_angles();
    let mats: Vec<f32> = aa
        .iter()
        .flat_map(|a| {
            let m = axis_angle_to_matrix_f64(Vector3::from(*a));
            (0..9).map(move |k| m[(k / 3, k % 3)] as f32)
        })
        .collect();
    let m = Tensor::<3>::from_data(TensorData::new(mats, [aa.len(), 3, 3]), &Device::flex());
    let back = vals(matrix_to_axis_angle(m));
    for (i, a) in aa.iter().enumerate() {
        let a = Vector3::from(*a);
        let got = Vector3::new(
            back[i * 3] as f64,
            back[i * 3 + 1] as f64,
            back[i * 3 + 2] as f64,
        );
        // Compare rotations, not vectors: near pi, r and -r (mod 2 pi) are the same rotation.
        let d = axis_angle_to_matrix_f64(got) - axis_angle_to_matrix_f64(a);
        assert!(d.abs().max() < 1e-5, "{a} -> {got}");
        if a.norm() < 3.0 {
            assert!((got - a).norm() < 1e-4, "{a} -> {got}");
        }
    }
}

#[test]
fn rot6d_identity_and_round_trip() {
    let id = vals(rot6d_to_matrix(rot6d_identity(2, &Device::flex())));
    let eye = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0];
    for k in 0..18 {
        assert_eq!(id[k], eye[k % 9]);
    }
    let aa = sample_axis_angles();
    let mats: Vec<f32> = aa
        .iter()
        .flat_map(|a| {
            let m = axis_angle_to_matrix_f64(Vector3::from(*a));
            (0..9).map(move |k| m[(k / 3, k % 3)] as f32)
        })
        .collect();
    let m = Tensor::<3>::from_data(
        TensorData::new(mats.clone(), [aa.len(), 3, 3]),
        &Device::flex(),
    );
    let six = matrix_to_rot6d(m);
    let sixv = vals(six.clone());
    // The 6D vector is the first two columns.
    assert_eq!(sixv[0..3], [mats[0], mats[3], mats[6]]);
    assert_eq!(sixv[3..6], [mats[1], mats[4], mats[7]]);
    let back = vals(rot6d_to_matrix(six));
    for (g, w) in back.iter().zip(&mats) {
        assert!((g - w).abs() < 1e-5);
    }
    // Gram-Schmidt gives a proper rotation from any non-degenerate 6D input.
    let raw = [0.3f32, -2.0, 0.5, 1.0, 1.0, 0.1];
    let r = vals(rot6d_to_matrix(t2(&raw, 1, 6)));
    let m = Matrix3::from_row_slice(&r.iter().map(|&x| x as f64).collect::<Vec<_>>());
    assert!((m.transpose() * m - Matrix3::identity()).abs().max() < 1e-5);
    assert!((m.determinant() - 1.0).abs() < 1e-5);
}

#[test]
fn rodrigues_gradient_is_finite_and_correct_near_zero() {
    let device = Device::flex().autodiff();
    // Loss = sum(W * R(r)) for a fixed W; its gradient at r = 0 is the axial part of W: dR/dr_k = [e_k]x.
    let w: Vec<f32> = (0..9).map(|i| (i as f32 * 0.37).sin()).collect();
    for r0 in [[0.0f32, 0.0, 0.0], [1e-4, -2e-4, 5e-5], [0.3, -0.2, 0.9]] {
        let r =
            Tensor::<2>::from_data(TensorData::new(r0.to_vec(), [1, 3]), &device).require_grad();
        let wt = Tensor::<3>::from_data(TensorData::new(w.clone(), [1, 3, 3]), &device);
        let loss = (axis_angle_to_matrix(r.clone()) * wt).sum();
        let grads = loss.backward();
        let g: Vec<f32> = r.grad(&grads).unwrap().into_data().try_into_vec().unwrap();
        // Central differences in f64 with nalgebra.
        let f = |v: [f64; 3]| -> f64 {
            let m = axis_angle_to_matrix_f64(Vector3::from(v));
            (0..9).map(|k| m[(k / 3, k % 3)] * w[k] as f64).sum()
        };
        for k in 0..3 {
            let h = 1e-6;
            let mut a = r0.map(|x| x as f64);
            let mut b = a;
            a[k] += h;
            b[k] -= h;
            let fd = (f(a) - f(b)) / (2.0 * h);
            assert!(g[k].is_finite());
            assert!(
                (g[k] as f64 - fd).abs() < 1e-4,
                "r0 {r0:?} k {k}: {} vs {fd}",
                g[k]
            );
        }
    }
}

#[test]
fn y_up_to_z_up_takes_up_to_up() {
    let m = y_up_to_z_up();
    assert_eq!(m * Vector3::y(), Vector3::z());
    assert!((m.determinant() - 1.0).abs() < 1e-12);
}
