//! Similarity Procrustes (Umeyama): the scale `s`, proper rotation `R` and translation `t` minimising
//! `sum_i |s R x_i + t - y_i|^2`. The rotation never is a reflection: when the best orthogonal map has
//! determinant -1, the singular direction of least weight is flipped (the standard correction).
use nalgebra::{Matrix3, Vector3};

use crate::GeomError;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Similarity {
    pub scale: f64,
    pub rotation: Matrix3<f64>,
    pub translation: Vector3<f64>,
}

impl Similarity {
    pub fn apply(&self, p: &Vector3<f64>) -> Vector3<f64> {
        self.scale * (self.rotation * p) + self.translation
    }
}

/// Fit the similarity that maps `src` onto `dst` (equal lengths, at least 3 points, not all coincident).
pub fn similarity_procrustes(
    src: &[Vector3<f64>],
    dst: &[Vector3<f64>],
) -> Result<Similarity, GeomError> {
    if src.len() != dst.len() {
        return Err(GeomError::Procrustes(format!(
            "point counts differ: {} vs {}",
            src.len(),
            dst.len()
        )));
    }
    if src.len() < 3 {
        return Err(GeomError::Procrustes(format!(
            "need at least 3 points, got {}",
            src.len()
        )));
    }
    let n = src.len() as f64;
    let mu_x = src.iter().sum::<Vector3<f64>>() / n;
    let mu_y = dst.iter().sum::<Vector3<f64>>() / n;
    let mut cov = Matrix3::zeros();
    let mut var_x = 0.0;
    for (x, y) in src.iter().zip(dst) {
        let (dx, dy) = (x - mu_x, y - mu_y);
        cov += dy * dx.transpose();
        var_x += dx.norm_squared();
    }
    cov /= n;
    var_x /= n;
    if !(var_x > 0.0 && var_x.is_finite()) {
        return Err(GeomError::Procrustes(format!(
            "source points have no spread (variance {var_x})"
        )));
    }
    let svd = cov.svd(true, true);
    let (u, v_t) = (svd.u.unwrap(), svd.v_t.unwrap());
    let mut d = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        // Flip the direction of the least singular value; no order of the values is assumed.
        let s = &svd.singular_values;
        let least = (0..3).min_by(|&a, &b| s[a].total_cmp(&s[b])).unwrap_or(2);
        d[(least, least)] = -1.0;
    }
    let rotation = u * d * v_t;
    let trace_ds: f64 = (0..3).map(|i| d[(i, i)] * svd.singular_values[i]).sum();
    let scale = trace_ds / var_x;
    let translation = mu_y - scale * rotation * mu_x;
    Ok(Similarity {
        scale,
        rotation,
        translation,
    })
}
