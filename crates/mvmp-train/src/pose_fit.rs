//! The decoder's linear pose read (`decoder.pose_read`) fitted in closed form: a ridge regression from
//! the joint samples each query reads to what the rest of the decoder leaves of the body's 21
//! rotations (6D), on training frames at the roots training decodes at: whether the read Adam trained is
//! the best linear one, and where it is not, that one (docs/architecture.md, The pose read in closed
//! form).
use burn::nn::Linear;
use burn::tensor::{Device, Tensor, TensorData};
use nalgebra::{DMatrix, Matrix3, RowDVector, Vector3};
use serde::Serialize;

use mvmp_data::loader::FrameBatch;
use mvmp_decoder::scaled_read;
use mvmp_geom::rotation::axis_angle_to_matrix_f64;
use mvmp_model::MvmpHmr;
use mvmp_smplx::names::REGRESSED_TO_JOINT;

use crate::config::QueryMode;
use crate::probe::host;
use crate::ridge::Ridge;
use crate::step::forward_at_queries;

/// Body rotations among the regressed ones: slots 1 to 21, after the global orientation.
const BODY: std::ops::Range<usize> = 1..22;
/// Numbers the read gives: 6 per body rotation.
const WIDTH: usize = 21 * 6;

/// What the fit measured and did.
#[derive(Debug, Clone, Serialize)]
pub struct PoseFit {
    pub frames: usize,
    pub people: usize,
    /// The ridge strength chosen on the last fifth of the frames (relative, see `ridge::RIDGE`).
    pub ridge: f64,
    /// The body rotations' mean angle from the truth on the last fifth of the frames, degrees: with the
    /// read as trained, and with the read fitted on the other frames.
    pub held_back_deg: f64,
    pub held_back_fitted_deg: f64,
    /// The same for every held-back person given the other frames' mean rotations (6D averaged): what
    /// reading nothing gives.
    pub held_back_mean_deg: f64,
    /// Whether the fitted read (on all frames) replaced the trained one: only where it lowered the
    /// held-back error.
    pub applied: bool,
}

/// What the fit reads of the people of some frames, one row each.
#[derive(Debug, Clone, Default)]
pub struct PoseRows {
    /// The joint samples the read took.
    pub inputs: Vec<Vec<f32>>,
    /// The body's 6D rotations from the rest of the decoder (the output less the read's part).
    pub rest: Vec<Vec<f64>>,
    /// The read's own part of the output.
    pub read: Vec<Vec<f64>>,
    /// The true body rotations, 6D (first column, then second).
    pub truth: Vec<Vec<f64>>,
}

impl PoseRows {
    pub fn len(&self) -> usize {
        self.inputs.len()
    }

    pub fn is_empty(&self) -> bool {
        self.inputs.is_empty()
    }

    fn extend(&mut self, other: PoseRows) {
        self.inputs.extend(other.inputs);
        self.rest.extend(other.rest);
        self.read.extend(other.read);
        self.truth.extend(other.truth);
    }
}

/// The rows of a batch's people with SMPL-X ground truth, decoded where training decodes them (`mode`,
/// `gate`). Empty for a model without a pose read.
pub fn batch_rows(
    model: &MvmpHmr,
    batch: &FrameBatch,
    (mode, gate): (QueryMode, f64),
    device: &Device,
) -> PoseRows {
    let Some(read) = &model.decoder.pose_read else {
        return PoseRows::default();
    };
    let (out, slots) = forward_at_queries(model, batch, None, (mode, gate), true, device);
    let Some(x) = out.pose_inputs else {
        return PoseRows::default();
    };
    let [b, k, w] = x.dims();
    let part = scaled_read(read, x.clone()); // [B, K, 126]
    let body = out
        .rot6d
        .narrow(2, BODY.start, BODY.len())
        .reshape([b, k, WIDTH]);
    let (xs, parts, bodies) = (host(x), host(part), host(body));
    let mut rows = PoseRows::default();
    for (bi, item) in slots.iter().enumerate() {
        for (ki, &(_, gi)) in item.iter().enumerate() {
            let person = &batch.people[bi][gi];
            if !person.smplx {
                continue;
            }
            let at = bi * k + ki;
            let read: Vec<f64> = parts[at * WIDTH..(at + 1) * WIDTH]
                .iter()
                .map(|&v| v as f64)
                .collect();
            let rest = (bodies[at * WIDTH..(at + 1) * WIDTH].iter().zip(&read))
                .map(|(&o, r)| o as f64 - r)
                .collect();
            rows.inputs.push(xs[at * w..(at + 1) * w].to_vec());
            rows.rest.push(rest);
            rows.read.push(read);
            rows.truth.push(body_rot6d(&person.pose));
        }
    }
    rows
}

/// The 21 body rotations of a 55 x 3 axis-angle pose as 6D (first column, then second) -> 126 numbers.
pub fn body_rot6d(pose: &[f32]) -> Vec<f64> {
    BODY.flat_map(|s| {
        let j = REGRESSED_TO_JOINT[s];
        let aa = Vector3::from_fn(|a, _| pose[3 * j + a] as f64);
        six(&axis_angle_to_matrix_f64(aa))
    })
    .collect()
}

/// A rotation's 6D numbers: its first column, then its second.
fn six(m: &Matrix3<f64>) -> [f64; 6] {
    [
        m[(0, 0)],
        m[(1, 0)],
        m[(2, 0)],
        m[(0, 1)],
        m[(1, 1)],
        m[(2, 1)],
    ]
}

/// The rotation 6D numbers stand for (Gram-Schmidt on the two columns, as the model turns its own).
fn rot6d_matrix(v: &[f64]) -> Matrix3<f64> {
    let a1 = Vector3::new(v[0], v[1], v[2]);
    let a2 = Vector3::new(v[3], v[4], v[5]);
    let b1 = a1 / a1.norm().max(1e-8);
    let u = a2 - b1 * b1.dot(&a2);
    let b2 = u / u.norm().max(1e-8);
    Matrix3::from_columns(&[b1, b2, b1.cross(&b2)])
}

/// The mean angle (degrees) between the 6D rotations of `pred` and `truth` rows of 21 each.
pub fn mean_angle_deg(pred: &[Vec<f64>], truth: &[Vec<f64>]) -> f64 {
    let mut sum = 0.0;
    let mut n = 0usize;
    for (p, t) in pred.iter().zip(truth) {
        for (a, b) in p.chunks(6).zip(t.chunks(6)) {
            let r = rot6d_matrix(a).transpose() * rot6d_matrix(b);
            let cos = ((r.trace() - 1.0) / 2.0).clamp(-1.0, 1.0);
            sum += cos.acos().to_degrees();
            n += 1;
        }
    }
    sum / n.max(1) as f64
}

/// Rows of `v` as a matrix.
fn matrix<T: Copy + Into<f64>>(v: &[Vec<T>]) -> DMatrix<f64> {
    let d = v.first().map_or(0, Vec::len);
    DMatrix::from_fn(v.len(), d, |i, j| v[i][j].into())
}

/// `rest` plus a read's prediction, row by row.
fn plus(rest: &[Vec<f64>], read: &DMatrix<f64>) -> Vec<Vec<f64>> {
    (rest.iter().enumerate())
        .map(|(i, r)| {
            r.iter()
                .enumerate()
                .map(|(j, v)| v + read[(i, j)])
                .collect()
        })
        .collect()
}

/// The read fitted on `rows`, its strength chosen on the rows from `cut` on (the last frames), and
/// what it measured. `None` for the weights where it does not lower the held-back error.
pub fn fit_rows(rows: &PoseRows, cut: usize) -> (PoseFit, Option<ReadWeights>) {
    let x = matrix(&rows.inputs);
    // What the read must add to the rest of the decoder's output.
    let target = DMatrix::from_fn(rows.len(), WIDTH, |i, j| rows.truth[i][j] - rows.rest[i][j]);
    let n = rows.len();
    let head = |m: &DMatrix<f64>| m.rows(0, cut).into_owned();
    let tail = |m: &DMatrix<f64>| m.rows(cut, n - cut).into_owned();
    let fold = Ridge::fit(&head(&x), &head(&target));
    let ridge = fold.choose(&tail(&x), &tail(&target));
    let held_truth = &rows.truth[cut..];
    let trained: Vec<Vec<f64>> = (rows.rest[cut..].iter().zip(&rows.read[cut..]))
        .map(|(r, p)| r.iter().zip(p).map(|(a, b)| a + b).collect())
        .collect();
    let held_back_deg = mean_angle_deg(&trained, held_truth);
    let fitted = plus(&rows.rest[cut..], &fold.predict(&tail(&x), ridge));
    let held_back_fitted_deg = mean_angle_deg(&fitted, held_truth);
    let mean = matrix(&rows.truth[..cut]).row_mean();
    let mean_rows = vec![mean.iter().copied().collect::<Vec<f64>>(); n - cut];
    let held_back_mean_deg = mean_angle_deg(&mean_rows, held_truth);
    let applied = held_back_fitted_deg < held_back_deg;
    let weights = applied.then(|| Ridge::fit(&x, &target).weights(ridge));
    let fit = PoseFit {
        frames: 0,
        people: n,
        ridge,
        held_back_deg,
        held_back_fitted_deg,
        held_back_mean_deg,
        applied,
    };
    (fit, weights)
}

/// A fitted read: `x W + b` with `W` inputs x 126 and `b` a row of 126.
pub type ReadWeights = (DMatrix<f64>, RowDVector<f64>);

/// Fit the read of `model` (a model on a plain device) on `frames` one-frame batches, decoded where
/// training decodes (`queries`), and measure it on the last fifth of the frames. The weights come back
/// only where they lower that error. `None` when the model has no pose read or the frames do not give
/// people to fit and to hold back.
pub fn fit_pose_read(
    model: &MvmpHmr,
    frames: impl IntoIterator<Item = FrameBatch>,
    queries: (QueryMode, f64),
    device: &Device,
) -> Option<(PoseFit, Option<ReadWeights>)> {
    model.decoder.pose_read.as_ref()?;
    let mut rows = PoseRows::default();
    let mut starts = Vec::new();
    for batch in frames {
        starts.push(rows.len());
        rows.extend(batch_rows(model, &batch, queries, device));
    }
    let count = starts.len();
    // The last fifth of the frames (at least one) is held back.
    let cut = starts.get((count * 4 / 5).max(1)).copied()?;
    if cut == 0 || cut >= rows.len() {
        return None;
    }
    let (mut fit, weights) = fit_rows(&rows, cut);
    fit.frames = count;
    Some((fit, weights))
}

/// The decoder's read set to give `x W + b` (see [`fitted_linear`]).
pub fn set_read(model: &mut MvmpHmr, read: &ReadWeights) {
    if let Some(layer) = model.decoder.pose_read.take() {
        model.decoder.pose_read = Some(fitted_linear(layer, read));
    }
}

/// `layer` with its parameters set so that its output divided by the square root of its inputs (as the
/// decoder scales the read) is `x W + b`. They keep their ids, so that an optimizer's state goes on with
/// them.
pub fn fitted_linear(layer: Linear, (w, b): &ReadWeights) -> Linear {
    let scale = (w.nrows() as f64).sqrt();
    let (rows, cols) = (w.nrows(), w.ncols());
    // nalgebra is column-major; the layer's weight is `[inputs, outputs]`, row-major.
    let wv: Vec<f32> = (0..rows)
        .flat_map(|i| (0..cols).map(move |j| (w[(i, j)] * scale) as f32))
        .collect();
    let bv: Vec<f32> = b.iter().map(|&v| (v * scale) as f32).collect();
    let weight = layer.weight.map(|old| {
        let t = Tensor::<2>::from_data(TensorData::new(wv, [rows, cols]), &old.device());
        t.set_require_grad(old.is_require_grad())
    });
    let bias = layer.bias.map(|p| {
        p.map(|old| {
            let t = Tensor::<1>::from_data(TensorData::new(bv, [cols]), &old.device());
            t.set_require_grad(old.is_require_grad())
        })
    });
    Linear { weight, bias }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mvmp_geom::rotation::matrix_to_axis_angle_f64;

    /// A rotation's own 6D gives it back, and rotations a known angle apart measure that angle.
    #[test]
    fn angles_between_6d_rotations() {
        let r = axis_angle_to_matrix_f64(Vector3::new(0.3, -0.2, 0.5));
        let six = |m: Matrix3<f64>| super::six(&m).to_vec();
        assert!((rot6d_matrix(&six(r)) - r).abs().max() < 1e-12);
        let turn = axis_angle_to_matrix_f64(Vector3::new(0.0, 0.0, 30f64.to_radians()));
        let a: Vec<f64> = (0..21).flat_map(|_| six(r)).collect();
        let b: Vec<f64> = (0..21).flat_map(|_| six(r * turn)).collect();
        assert!((mean_angle_deg(std::slice::from_ref(&a), &[b]) - 30.0).abs() < 1e-9);
        assert!(mean_angle_deg(std::slice::from_ref(&a), std::slice::from_ref(&a)).abs() < 1e-6);
    }

    /// Rows whose truth is the rest (no bend) plus bends linear in the inputs: the fit is applied and
    /// its held-back error is a small part of the read as trained (zero) and of the mean bend's.
    #[test]
    fn an_exact_linear_read_is_found_and_applied() {
        let n = 60;
        let inputs: Vec<Vec<f32>> = (0..n)
            .map(|i| {
                (0..4)
                    .map(|j| (((i * 5 + j * 11) % 13) as f32 - 6.0) / 6.0)
                    .collect()
            })
            .collect();
        let rest: Vec<Vec<f64>> = (0..n).map(|_| body_rot6d(&[0.0; 165])).collect();
        let truth: Vec<Vec<f64>> = (inputs.iter())
            .map(|x| {
                let mut pose = vec![0.0f32; 165];
                // Every body joint bends about one axis with one input, and a little to start with.
                for j in 1..22 {
                    pose[3 * j + j % 3] = 0.2 * x[j % 4] + 0.05;
                }
                body_rot6d(&pose)
            })
            .collect();
        let rows = PoseRows {
            inputs,
            read: vec![vec![0.0; WIDTH]; n],
            rest,
            truth,
        };
        let (fit, weights) = fit_rows(&rows, 48);
        assert!(fit.applied && weights.is_some(), "{fit:?}");
        assert_eq!(fit.people, n);
        assert!(fit.held_back_deg > 3.0, "{fit:?}");
        assert!(fit.held_back_mean_deg > 3.0, "{fit:?}");
        // 6D entries are cosines and sines, not linear in the inputs: nearly exact, not exact.
        assert!(
            fit.held_back_fitted_deg < 0.1 * fit.held_back_mean_deg,
            "{fit:?}"
        );
    }

    /// The fitted layer, scaled as the decoder scales its read, gives `x W + b`, and keeps its ids.
    #[test]
    fn a_fitted_layer_gives_the_read_it_was_fitted_to() {
        let d = Device::flex();
        let layer = burn::nn::LinearConfig::new(3, 2).init(&d);
        let id = layer.weight.id;
        let w = DMatrix::from_row_slice(3, 2, &[0.5, -1.0, 2.0, 0.25, -0.75, 1.5]);
        let b = RowDVector::from_row_slice(&[3.0, -2.0]);
        let fitted = fitted_linear(layer, &(w.clone(), b.clone()));
        assert_eq!(fitted.weight.id, id);
        let x = [0.2f32, -1.0, 0.7, 1.5, 0.0, -0.4];
        let xt = Tensor::<2>::from_data(TensorData::new(x.to_vec(), [2, 3]), &d);
        let got = host(fitted.forward(xt) / 3f64.sqrt());
        let xm = DMatrix::from_row_slice(2, 3, &x.map(f64::from));
        let mut want = xm * w;
        want.row_iter_mut().for_each(|mut r| r += &b);
        for (i, g) in got.iter().enumerate() {
            assert!(
                (*g as f64 - want[(i / 2, i % 2)]).abs() < 1e-5,
                "{got:?} {want}"
            );
        }
    }

    /// The body slots are joints 1 to 21 in order, each read from its own three numbers.
    #[test]
    fn body_rot6d_reads_joints_one_to_twenty_one() {
        let mut pose = vec![0.0f32; 55 * 3];
        pose[3 * 4..3 * 4 + 3].copy_from_slice(&[0.4, 0.1, -0.2]);
        let six = body_rot6d(&pose);
        assert_eq!(six.len(), WIDTH);
        let m = rot6d_matrix(&six[3 * 6..4 * 6]);
        let aa = matrix_to_axis_angle_f64(m);
        assert!((aa - Vector3::new(0.4, 0.1, -0.2)).norm() < 1e-6, "{aa}");
        let identity = [1.0, 0.0, 0.0, 0.0, 1.0, 0.0];
        assert!(
            six[..6]
                .iter()
                .zip(identity)
                .all(|(a, b)| (a - b).abs() < 1e-12)
        );
    }
}
