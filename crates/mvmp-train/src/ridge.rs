//! Ridge regression on standardised features, with its strength chosen on held-back rows: the linear
//! probe's read of the volumes and the closed-form fit of the decoder's pose read.
use nalgebra::{DMatrix, RowDVector, SymmetricEigen};

/// Ridge strengths tried, as multiples of the mean squared norm of a standardised feature row.
pub const RIDGE: [f64; 7] = [1e-3, 1e-2, 3e-2, 0.1, 0.3, 1.0, 3.0];

/// Ridge regression on standardised features, in whichever form has the smaller matrix to decompose:
/// the primal `Z^T Z` (features x features) when the people outnumber the features, else the dual
/// `Z Z^T` (people x people). Either is decomposed once, `Q Lambda Q^T`, so each strength costs one
/// product: the weights are `B (Lambda + lambda I)^-1 Q^T Z'^T (Y - mean)` with `B = Q`, `Z' = Z`
/// (primal) or `B = Z^T Q`, `Z' = I` (dual).
pub struct Ridge {
    mean: RowDVector<f64>,
    scale: RowDVector<f64>,
    eigenvalues: nalgebra::DVector<f64>,
    /// `B` above: features x rank.
    basis: DMatrix<f64>,
    /// `Q^T Z'^T (Y - mean)`: rank x targets.
    projected: DMatrix<f64>,
    y_mean: RowDVector<f64>,
    /// The mean squared norm of a standardised row, the unit of the strengths.
    unit: f64,
}

impl Ridge {
    pub fn fit(x: &DMatrix<f64>, y: &DMatrix<f64>) -> Ridge {
        let n = x.nrows() as f64;
        let mean = x.row_mean();
        let var = RowDVector::from_fn(x.ncols(), |_, j| {
            x.column(j)
                .iter()
                .map(|v| (v - mean[j]).powi(2))
                .sum::<f64>()
                / n
        });
        // A constant feature carries nothing; dividing it by 1 keeps it at zero once centred. The bar is
        // relative, so that features that are all small (an untrained head's) are still read.
        let floor = 1e-12 * var.max().max(f64::MIN_POSITIVE);
        let scale = var.map(|v| if v > floor { v.sqrt().recip() } else { 1.0 });
        let z = standardise(x, &mean, &scale);
        let y_mean = y.row_mean();
        let yc = DMatrix::from_fn(y.nrows(), y.ncols(), |i, j| y[(i, j)] - y_mean[j]);
        let (eigen, basis, projected) = if z.ncols() <= z.nrows() {
            let eigen = SymmetricEigen::new(z.transpose() * &z);
            let projected = eigen.eigenvectors.transpose() * (z.transpose() * yc);
            let basis = eigen.eigenvectors.clone();
            (eigen, basis, projected)
        } else {
            let eigen = SymmetricEigen::new(&z * z.transpose());
            let projected = eigen.eigenvectors.transpose() * yc;
            let basis = z.transpose() * &eigen.eigenvectors;
            (eigen, basis, projected)
        };
        Ridge {
            unit: eigen.eigenvalues.sum() / n,
            mean,
            scale,
            eigenvalues: eigen.eigenvalues,
            basis,
            projected,
            y_mean,
        }
    }

    /// The weights on standardised features at strength `r` (times [`Ridge::unit`]).
    fn standard_weights(&self, r: f64) -> DMatrix<f64> {
        let lambda = r * self.unit.max(f64::MIN_POSITIVE);
        let mut a = self.projected.clone();
        for (i, mut row) in a.row_iter_mut().enumerate() {
            row /= self.eigenvalues[i].max(0.0) + lambda;
        }
        &self.basis * a
    }

    /// Predictions for the rows of `x` at strength `r` (times [`Ridge::unit`]).
    pub fn predict(&self, x: &DMatrix<f64>, r: f64) -> DMatrix<f64> {
        let mut pred = standardise(x, &self.mean, &self.scale) * self.standard_weights(r);
        for mut row in pred.row_iter_mut() {
            row += &self.y_mean;
        }
        pred
    }

    /// The fit at strength `r` as a map of the raw features: `x W + b` equals [`Ridge::predict`]'s row
    /// (`W` features x targets, `b` a row of targets).
    pub fn weights(&self, r: f64) -> (DMatrix<f64>, RowDVector<f64>) {
        let mut w = self.standard_weights(r);
        for (j, mut row) in w.row_iter_mut().enumerate() {
            row *= self.scale[j];
        }
        let bias = &self.y_mean - &self.mean * &w;
        (w, bias)
    }

    /// The strength of [`RIDGE`] whose predictions of `val_x` are nearest `val_y` (summed squares).
    pub fn choose(&self, val_x: &DMatrix<f64>, val_y: &DMatrix<f64>) -> f64 {
        (RIDGE.iter())
            .map(|&r| (r, sse(&self.predict(val_x, r), val_y)))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map_or(1.0, |(r, _)| r)
    }
}

fn standardise(x: &DMatrix<f64>, mean: &RowDVector<f64>, scale: &RowDVector<f64>) -> DMatrix<f64> {
    DMatrix::from_fn(x.nrows(), x.ncols(), |i, j| {
        (x[(i, j)] - mean[j]) * scale[j]
    })
}

/// The summed squared difference of two matrices.
pub fn sse(a: &DMatrix<f64>, b: &DMatrix<f64>) -> f64 {
    (a - b).norm_squared()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Targets an exact linear map of the features: at the weakest strength the fit recovers the map
    /// and its bias, `weights` reproduces `predict` on other rows, and the strength chosen on exact rows
    /// is the weakest.
    #[test]
    fn the_raw_weights_reproduce_the_predictions_and_an_exact_map() {
        let x = DMatrix::from_fn(40, 3, |i, j| {
            ((i * 7 + j * 13) % 11) as f64 * (j + 1) as f64
        });
        let w = DMatrix::from_row_slice(3, 2, &[0.5, -1.0, 2.0, 0.25, -0.75, 1.5]);
        let b = RowDVector::from_row_slice(&[3.0, -2.0]);
        let rows = |x: &DMatrix<f64>| {
            let mut y = x * &w;
            y.row_iter_mut().for_each(|mut r| r += &b);
            y
        };
        let ridge = Ridge::fit(&x, &rows(&x));
        let (fw, fb) = ridge.weights(1e-3);
        // Strength 1e-3 of a row's squared norm shrinks an exact fit by about that fraction.
        assert!((&fw - &w).abs().max() < 0.02, "{fw}");
        assert!((&fb - &b).abs().max() < 0.1, "{fb}");
        let other = DMatrix::from_fn(5, 3, |i, j| (i + 2 * j) as f64 - 3.0);
        let mut by_weights = &other * &fw;
        by_weights.row_iter_mut().for_each(|mut r| r += &fb);
        assert!((by_weights - ridge.predict(&other, 1e-3)).abs().max() < 1e-9);
        assert_eq!(ridge.choose(&other, &rows(&other)), RIDGE[0]);
    }
}
