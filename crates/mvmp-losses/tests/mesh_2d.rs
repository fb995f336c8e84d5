//! The one-pass 2D mesh loss over the views against the same loss as tensor ops, one view at a time, and
//! against central finite differences of itself: rigs with distortion, skew and a letterbox, a batch of
//! two rigs, true points outside the image, a point behind a camera, and points of weight 0.
use std::sync::Mutex;

use burn::tensor::{Device, Tensor, TensorData};
use mvmp_geom::{Camera, CameraTensors, Letterbox};
use mvmp_losses::*;
use nalgebra::{Matrix3, Vector3};

/// The tests that switch the pass off run one at a time.
static SWITCH: Mutex<()> = Mutex::new(());

fn t<const D: usize>(v: Vec<f32>, shape: [usize; D], d: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(v, shape), d)
}

fn values<const D: usize>(x: Tensor<D>) -> Vec<f32> {
    x.into_data().convert::<f32>().try_into_vec().unwrap()
}

/// A camera `dist` metres from the origin at `azimuth` degrees, 1.2 m up, looking at (0, 0, 1), with
/// distortion and skew, its 320 x 240 image letterboxed into 128 x 128.
fn camera(azimuth: f64, dist: f64, k1: f64) -> (Camera, Letterbox) {
    let a = azimuth.to_radians();
    let pos = Vector3::new(dist * a.cos(), dist * a.sin(), 1.2);
    let z = (Vector3::new(0.0, 0.0, 1.0) - pos).normalize();
    let x = z.cross(&Vector3::z()).normalize();
    let y = z.cross(&x);
    let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
    let k = Matrix3::new(260.0, 1.5, 161.0, 0.0, 250.0, 118.0, 0.0, 0.0, 1.0);
    let dist = [k1, 0.04, 0.002, -0.001, -0.01];
    let cam = Camera::new("c", k, r, -(r * pos), dist, 320, 240).unwrap();
    (cam, Letterbox::new(320, 240, 128).unwrap())
}

/// Two rigs of three views; the second turned and further away.
fn rigs() -> Vec<(Vec<Camera>, Vec<Letterbox>)> {
    [(0.0, 4.0), (25.0, 5.5)]
        .iter()
        .map(|&(turn, dist)| {
            [0.0, 130.0, 250.0]
                .iter()
                .map(|&az| camera(az + turn, dist, -0.15))
                .unzip()
        })
        .collect()
}

/// Scattered values in [-0.5, 0.5) from a hash of the index and seed.
fn noise(seed: u64, n: usize) -> Vec<f32> {
    (0..n)
        .map(|i| {
            let mut z = (i as u64 + 1).wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ seed;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 40) as f32 / (1u64 << 24) as f32 - 0.5
        })
        .collect()
}

const SHAPE: [usize; 4] = [2, 3, 40, 3];

/// Predicted points round (0, 0, 1) and the truth 0-10 cm from them; a few true points far outside
/// every image, one predicted point behind the first camera, and some weights 0.
fn case() -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let n: usize = SHAPE.iter().product();
    let pred: Vec<f32> = noise(1, n)
        .iter()
        .enumerate()
        .map(|(i, v)| if i % 3 == 2 { 1.0 + 1.6 * v } else { 1.4 * v })
        .collect();
    let mut truth: Vec<f32> = pred
        .iter()
        .zip(noise(2, n))
        .map(|(p, e)| p + 0.2 * e)
        .collect();
    for m in (0..n / 3).step_by(17) {
        truth[3 * m] += 30.0;
    }
    let mut pred = pred;
    // Behind camera 0 of the first rig (at x = 4 looking towards -x).
    pred[3 * 5..3 * 5 + 3].copy_from_slice(&[4.5, 0.1, 1.1]);
    let weight = (0..n / 3)
        .map(|m| if m % 11 == 3 { 0.0 } else { 1.0 })
        .collect();
    (pred, truth, weight)
}

/// The loss as tensor ops: per view, the truth projected, then `mesh_2d_loss_weighted`.
fn by_views(points: Tensor<4>, truth: Tensor<4>, weight: Tensor<3>) -> Tensor<1> {
    let d = points.device();
    let [b, k, n, _] = SHAPE;
    let rigs = rigs();
    let mut sum = Tensor::<1>::zeros([1], &d);
    for v in 0..3 {
        let cams: Vec<CameraTensors> = rigs
            .iter()
            .map(|(c, l)| CameraTensors::new(&c[v..v + 1], Some(&l[v..v + 1]), &d))
            .collect();
        let uv: Vec<Tensor<3>> = (0..b)
            .map(|bi| {
                let p = truth.clone().narrow(0, bi, 1).reshape([k * n, 3]);
                cams[bi].project(p).uv.reshape([1, k * n, 2])
            })
            .collect();
        let uv = Tensor::cat(uv, 0).reshape([b, k, n, 2]);
        sum = sum + mesh_2d_loss_weighted(points.clone(), uv, &cams, 128.0, weight.clone());
    }
    sum
}

fn views(points: Tensor<4>, truth: Tensor<4>, weight: Tensor<3>) -> Tensor<1> {
    let rigs = rigs();
    let refs: Vec<_> = rigs
        .iter()
        .map(|(c, l)| (c.as_slice(), l.as_slice()))
        .collect();
    mesh_2d_loss_views(points, truth, &refs, 128.0, weight)
}

type Loss = fn(Tensor<4>, Tensor<4>, Tensor<3>) -> Tensor<1>;

/// The loss and its gradient in the points on `d`.
fn value_and_grad(f: Loss, d: &Device) -> (f32, Vec<f32>) {
    let (pred, truth, weight) = case();
    let x = t(pred, SHAPE, d).require_grad();
    let l = f(
        x.clone(),
        t(truth, SHAPE, d),
        t(weight, [SHAPE[0], SHAPE[1], SHAPE[2]], d),
    );
    let value = values(l.clone())[0];
    let g = values(x.grad(&l.backward()).unwrap());
    (value, g)
}

/// Asserts `a` and `b` agree within `tol` of the larger magnitude in `b`.
fn assert_close(what: &str, a: &[f32], b: &[f32], tol: f32) {
    let scale = b.iter().fold(0f32, |m, x| m.max(x.abs()));
    for (i, (x, y)) in a.iter().zip(b).enumerate() {
        assert!((x - y).abs() <= tol * scale, "{what}[{i}]: {x} against {y}");
    }
}

#[test]
fn the_pass_gives_the_tensor_ops_values_and_gradients() {
    let _one = SWITCH.lock().unwrap_or_else(|e| e.into_inner());
    let ad = Device::flex().autodiff();
    let (want, want_g) = value_and_grad(by_views, &ad);
    assert!(want > 0.5, "a case with a loss to compare: {want}");
    assert!(want_g.iter().any(|&g| g != 0.0));
    let (got, got_g) = value_and_grad(views, &ad);
    assert_close("loss", &[got], &[want], 1e-5);
    assert_close("gradient", &got_g, &want_g, 1e-5);
    // Points of weight 0 and the point behind a camera whose truth is outside every view get nothing.
    let (_, _, weight) = case();
    for (m, w) in weight.iter().enumerate() {
        if *w == 0.0 {
            assert_eq!(&got_g[3 * m..3 * m + 3], &[0.0; 3], "point {m} weighs 0");
        }
    }
    // Without autodiff the same value.
    let plain = Device::flex();
    let (pred, truth, weight) = case();
    let l = views(
        t(pred, SHAPE, &plain),
        t(truth, SHAPE, &plain),
        t(weight, [2, 3, 40], &plain),
    );
    assert_close("loss without autodiff", &values(l), &[want], 1e-5);
}

#[test]
fn switched_off_the_loss_is_the_tensor_ops() {
    let _one = SWITCH.lock().unwrap_or_else(|e| e.into_inner());
    let ad = Device::flex().autodiff();
    set_fused_mesh_2d(false);
    let off = value_and_grad(views, &ad);
    set_fused_mesh_2d(true);
    let want = value_and_grad(by_views, &ad);
    assert_eq!(off.0, want.0);
    assert_eq!(off.1, want.1);
}

/// Central differences, one point weighted at a time (so that the loss, read in float32, is a few
/// pixels and its differences resolve the gradient), every coordinate of eight points.
#[test]
fn the_pass_gradient_matches_finite_differences() {
    let (pred, truth, _) = case();
    let plain = Device::flex();
    let ad = Device::flex().autodiff();
    let n = SHAPE[0] * SHAPE[1] * SHAPE[2];
    for m in [1, 38, 77, 110, 131, 160, 199, 236] {
        let mut weight = vec![0f32; n];
        weight[m] = 1.0;
        let loss = |x: Tensor<4>| {
            let d = x.device();
            views(
                x,
                t(truth.clone(), SHAPE, &d),
                t(weight.clone(), [2, 3, 40], &d),
            )
        };
        let x = t(pred.clone(), SHAPE, &ad).require_grad();
        let g = values(x.grad(&loss(x.clone()).backward()).unwrap());
        let eps = 1e-3f32;
        for j in 0..3 {
            let i = 3 * m + j;
            let (mut a, mut b) = (pred.clone(), pred.clone());
            a[i] += eps;
            b[i] -= eps;
            let at = |p: Vec<f32>| values(loss(t(p, SHAPE, &plain)))[0];
            let fd = (at(a) - at(b)) / (2.0 * eps);
            assert!(
                (g[i] - fd).abs() <= 1e-2 * fd.abs().max(1.0),
                "point {m}, axis {j}: pass {} vs fd {fd}",
                g[i]
            );
        }
        assert!(
            g[3 * m..3 * m + 3].iter().any(|&v| v.abs() > 1.0),
            "point {m} moves the loss"
        );
    }
}

/// Every view of both rigs sees most of the predicted points: the case compares projections.
#[test]
fn the_rigs_see_the_points() {
    let (pred, _, _) = case();
    for (cams, _) in rigs() {
        for cam in &cams {
            let seen = pred
                .chunks_exact(3)
                .filter(|p| {
                    let x = Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64);
                    let (uv, depth) = cam.project(&x);
                    depth > 0.0 && cam.contains(uv)
                })
                .count();
            assert!(seen > 200, "{seen} of 240 points seen");
        }
    }
}
