//! Rotations as batched, differentiable tensor ops, plus `f64` helpers for CPU-side code.
//!
//! - axis-angle `[N, 3]` <-> matrix `[N, 3, 3]` (Rodrigues; a series near zero angle keeps values and
//!   gradients finite);
//! - 6D `[N, 6]` <-> matrix: the 6D vector is the first two columns of the matrix, `a1 = v[0..3]`,
//!   `a2 = v[3..6]`, mapped back by Gram-Schmidt. Identity is `[1, 0, 0, 0, 1, 0]`.
use burn::tensor::{Tensor, TensorData};
use nalgebra::{Matrix3, Rotation3, Vector3};

/// Below this squared angle the Rodrigues coefficients use their Taylor series.
const SMALL_ANGLE_SQ: f32 = 1e-4;

/// Column `i` of a `[N, C]` tensor as `[N, 1]`.
fn col(t: &Tensor<2>, i: usize) -> Tensor<2> {
    t.clone().narrow(1, i, 1)
}

/// Axis-angle `[N, 3]` to rotation matrices `[N, 3, 3]`.
///
/// `R = I + A K + B K^2` with `K` the skew matrix of `r`, `A = sin(t)/t`, `B = (1 - cos(t))/t^2`,
/// `t = |r|`. `B` is evaluated as `2 sin^2(t/2)/t^2` (no cancellation in float32) and both use their series
/// below `t = 1e-2`, where the exact branch is evaluated at a safe angle so its gradient stays finite.
pub fn axis_angle_to_matrix(r: Tensor<2>) -> Tensor<3> {
    let n = r.dims()[0];
    let (x, y, z) = (col(&r, 0), col(&r, 1), col(&r, 2));
    let t2 = x.clone().powi_scalar(2) + y.clone().powi_scalar(2) + z.clone().powi_scalar(2);
    let small = t2.clone().lower_elem(SMALL_ANGLE_SQ);
    let safe_t2 = t2.clone().mask_fill(small.clone(), 1.0);
    let t = safe_t2.clone().sqrt();
    let a_exact = t.clone().sin() / t.clone();
    let half_sin = (t.clone() * 0.5).sin();
    let b_exact = half_sin.powi_scalar(2) * 2.0 / safe_t2;
    let t4 = t2.clone().powi_scalar(2);
    let a_series = t2.clone().mul_scalar(-1.0 / 6.0).add_scalar(1.0) + t4.clone() / 120.0;
    let b_series = t2.clone().mul_scalar(-1.0 / 24.0).add_scalar(0.5) + t4 / 720.0;
    let a = a_exact.mask_where(small.clone(), a_series);
    let b = b_exact.mask_where(small, b_series);
    let diag = -b.clone() * t2 + 1.0;
    let bxy = b.clone() * x.clone() * y.clone();
    let bxz = b.clone() * x.clone() * z.clone();
    let byz = b.clone() * y.clone() * z.clone();
    let entries = vec![
        diag.clone() + b.clone() * x.clone().powi_scalar(2),
        bxy.clone() - a.clone() * z.clone(),
        bxz.clone() + a.clone() * y.clone(),
        bxy + a.clone() * z,
        diag.clone() + b.clone() * y.clone().powi_scalar(2),
        byz.clone() - a.clone() * x.clone(),
        bxz - a.clone() * y.clone(),
        byz + a * x,
        diag + b * col(&r, 2).powi_scalar(2),
    ];
    Tensor::cat(entries, 1).reshape([n, 3, 3])
}

/// Rotation matrices `[N, 3, 3]` to axis-angle `[N, 3]`, angle in `[0, pi]`.
///
/// Goes through the unit quaternion with the numerically best of the four standard formulas per matrix
/// (largest denominator), then `angle = 2 atan2(|v|, w)`; near zero angle a series replaces `angle/|v|`.
pub fn matrix_to_axis_angle(m: Tensor<3>) -> Tensor<2> {
    let q = matrix_to_quaternion(m);
    let w = col(&q, 0);
    // q and -q are the same rotation: take w >= 0 so that the angle lands in [0, pi].
    let sign = w.clone().sign().mask_fill(w.clone().equal_elem(0.0), 1.0);
    let q = q * sign;
    let w = col(&q, 0);
    let v = q.narrow(1, 1, 3);
    let n2 = v.clone().powi_scalar(2).sum_dim(1);
    let small = n2.clone().lower_elem(1e-8);
    let safe_n = n2.clone().mask_fill(small.clone(), 1.0).sqrt();
    let factor_exact = safe_n.clone().atan2(w.clone()) * 2.0 / safe_n;
    // angle/|v| = 2 atan(n/w)/n = (2/w)(1 - n^2/(3 w^2) + ...) for small n (w ~ 1 there).
    let safe_w = w.clone().clamp_min(0.5);
    let factor_series = (-(n2 / (safe_w.clone().powi_scalar(2) * 3.0)) + 1.0) * 2.0 / safe_w;
    let factor = factor_exact.mask_where(small, factor_series);
    v * factor
}

/// Rotation matrices `[N, 3, 3]` to unit quaternions `[N, 4]` as `(w, x, y, z)`.
pub fn matrix_to_quaternion(m: Tensor<3>) -> Tensor<2> {
    let n = m.dims()[0];
    let f = m.reshape([n, 9]);
    let e = |i: usize| col(&f, i);
    let (m00, m01, m02) = (e(0), e(1), e(2));
    let (m10, m11, m12) = (e(3), e(4), e(5));
    let (m20, m21, m22) = (e(6), e(7), e(8));
    // 4 q_k^2 for each component k, from the diagonal.
    let sq = [
        m00.clone() + m11.clone() + m22.clone() + 1.0,
        m00.clone() - m11.clone() - m22.clone() + 1.0,
        -m00.clone() + m11.clone() - m22.clone() + 1.0,
        -m00 - m11 + m22 + 1.0,
    ];
    let (d21, s21) = (m21.clone() - m12.clone(), m21 + m12);
    let (d02, s02) = (m02.clone() - m20.clone(), m02 + m20);
    let (d10, s10) = (m10.clone() - m01.clone(), m10 + m01);
    // Candidate k has its large component at index k; each row is scaled by 1/(4 q_k).
    let rows = [
        [sq[0].clone(), d21.clone(), d02.clone(), d10.clone()],
        [d21, sq[1].clone(), s10.clone(), s02.clone()],
        [d02, s10, sq[2].clone(), s21.clone()],
        [d10, s02, s21, sq[3].clone()],
    ];
    let sq_all = Tensor::cat(sq.to_vec(), 1); // [N, 4]
    let best = sq_all.clone().argmax(1); // [N, 1]
    let onehot: Tensor<2> = best.squeeze_dim::<1>(1).one_hot::<2>(4).float(); // [N, 4]
    // Denominator 2 sqrt(4 q_k^2) = 4 q_k, kept away from zero for the candidates that are not chosen.
    let denom = sq_all.clamp_min(0.01).sqrt() * 2.0; // [N, 4]
    let mut q = Tensor::<2>::zeros([n, 4], &f.device());
    for (k, row) in rows.into_iter().enumerate() {
        let cand = Tensor::cat(row.to_vec(), 1) / col(&denom, k);
        q = q + cand * col(&onehot, k);
    }
    q
}

/// 6D `[N, 6]` to rotation matrices `[N, 3, 3]` by Gram-Schmidt on the two columns.
pub fn rot6d_to_matrix(v: Tensor<2>) -> Tensor<3> {
    let n = v.dims()[0];
    let a1 = v.clone().narrow(1, 0, 3);
    let a2 = v.narrow(1, 3, 3);
    let b1 = normalize(a1);
    let proj = (b1.clone() * a2.clone()).sum_dim(1);
    let b2 = normalize(a2 - b1.clone() * proj);
    let b3 = b1.clone().cross(b2.clone(), 1);
    // Stack as columns: R[n, i, c] = b_c[i].
    Tensor::stack::<3>(vec![b1, b2, b3], 2).reshape([n, 3, 3])
}

/// Rotation matrices `[N, 3, 3]` to 6D `[N, 6]` (first column, then second column).
pub fn matrix_to_rot6d(m: Tensor<3>) -> Tensor<2> {
    let n = m.dims()[0];
    let c0 = m.clone().narrow(2, 0, 1).reshape([n, 3]);
    let c1 = m.narrow(2, 1, 1).reshape([n, 3]);
    Tensor::cat(vec![c0, c1], 1)
}

fn normalize(a: Tensor<2>) -> Tensor<2> {
    let norm = a.clone().powi_scalar(2).sum_dim(1).sqrt().clamp_min(1e-8);
    a / norm
}

/// The 6D identity `[1, 0, 0, 0, 1, 0]` repeated `n` times.
pub fn rot6d_identity(n: usize, device: &burn::tensor::Device) -> Tensor<2> {
    let data: Vec<f32> = (0..n)
        .flat_map(|_| [1.0, 0.0, 0.0, 0.0, 1.0, 0.0])
        .collect();
    Tensor::from_data(TensorData::new(data, [n, 6]), device)
}

/// `f64` axis-angle to matrix.
pub fn axis_angle_to_matrix_f64(r: Vector3<f64>) -> Matrix3<f64> {
    Rotation3::from_scaled_axis(r).into_inner()
}

/// `f64` matrix to axis-angle (angle in `[0, pi]`). The matrix is projected onto the nearest rotation first.
pub fn matrix_to_axis_angle_f64(m: Matrix3<f64>) -> Vector3<f64> {
    Rotation3::from_matrix(&m).scaled_axis()
}

/// The rotation that takes the body model's y-up rest frame to the z-up world: `(x, y, z) -> (x, -z, y)`,
/// a +90 degree turn about x. An upright person in the world has this as (part of) its global orientation.
pub fn y_up_to_z_up() -> Matrix3<f64> {
    Matrix3::new(1.0, 0.0, 0.0, 0.0, 0.0, -1.0, 0.0, 1.0, 0.0)
}
