//! The mean SMPL-X parameters of a set of annotated frames: where the decoder's regression starts (the
//! role of the mean-parameter file of HMR-style regressors) and the "mean pose" reference of evaluation.
use nalgebra::{Matrix3, Rotation3, Vector3};

use crate::DataError;
use crate::layout::{Annotation, DatasetLayout, FrameRef};
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS};

/// Mean parameters of some people.
#[derive(Debug, Clone, PartialEq)]
pub struct MeanParams {
    /// Per joint of the full pose (55), the rotation nearest to the mean rotation matrix (row-major).
    pub rotations: Vec<[f64; 9]>,
    pub betas: [f64; NUM_BETAS],
    pub expression: [f64; NUM_EXPRESSION],
    /// How many people the mean is over.
    pub people: usize,
}

/// Running sums of rotation matrices and coefficients.
#[derive(Debug, Clone)]
pub struct MeanAccumulator {
    rotations: Vec<Matrix3<f64>>,
    betas: [f64; NUM_BETAS],
    expression: [f64; NUM_EXPRESSION],
    people: usize,
}

impl Default for MeanAccumulator {
    fn default() -> Self {
        MeanAccumulator {
            rotations: vec![Matrix3::zeros(); NUM_JOINTS],
            betas: [0.0; NUM_BETAS],
            expression: [0.0; NUM_EXPRESSION],
            people: 0,
        }
    }
}

impl MeanAccumulator {
    /// Add one person's parameters.
    pub fn add(&mut self, p: &mvmp_smplx::SmplxParams) {
        let pose = p.full_pose();
        for (j, acc) in self.rotations.iter_mut().enumerate() {
            let aa = Vector3::new(pose[j * 3], pose[j * 3 + 1], pose[j * 3 + 2]);
            *acc += Rotation3::new(aa).into_inner();
        }
        for (acc, v) in self.betas.iter_mut().zip(&p.betas) {
            *acc += v;
        }
        for (acc, v) in self.expression.iter_mut().zip(&p.expression) {
            *acc += v;
        }
        self.people += 1;
    }

    /// Add every person of some frames of a dataset.
    pub fn add_frames(
        &mut self,
        layout: &DatasetLayout,
        frames: &[FrameRef],
    ) -> Result<(), DataError> {
        for f in frames {
            let views = layout.scenes[f.scene].rig.len();
            let ann = Annotation::read(&f.dir.join("annotation.json"), views)?;
            for person in &ann.people {
                self.add(&person.smplx);
            }
        }
        Ok(())
    }

    /// The mean (`None` without people). A mean of rotations is the rotation nearest to their mean
    /// matrix (the chordal L2 mean), found by SVD.
    pub fn finish(&self) -> Option<MeanParams> {
        let n = self.people as f64;
        (self.people > 0).then(|| MeanParams {
            rotations: self
                .rotations
                .iter()
                .map(|m| nearest_rotation(m / n))
                .collect(),
            betas: self.betas.map(|v| v / n),
            expression: self.expression.map(|v| v / n),
            people: self.people,
        })
    }
}

/// The rotation nearest to `m` in the Frobenius norm (identity when `m` is zero).
fn nearest_rotation(m: Matrix3<f64>) -> [f64; 9] {
    let svd = m.svd(true, true);
    let r = match (svd.u, svd.v_t) {
        (Some(u), Some(v_t)) if m.norm() > 1e-9 => {
            let d = (u * v_t).determinant().signum();
            u * Matrix3::from_diagonal(&Vector3::new(1.0, 1.0, d)) * v_t
        }
        _ => Matrix3::identity(),
    };
    std::array::from_fn(|k| r[(k / 3, k % 3)])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn person(pose: &[(usize, [f64; 3])], betas: f64) -> mvmp_smplx::SmplxParams {
        let mut full = vec![0.0; NUM_JOINTS * 3];
        for (j, aa) in pose {
            full[j * 3..j * 3 + 3].copy_from_slice(aa);
        }
        mvmp_smplx::SmplxParams::from_full_pose(
            &full,
            &[betas; NUM_BETAS],
            &[0.0; NUM_EXPRESSION],
            [0.0; 3],
        )
    }

    /// Two turns about one axis average to the turn halfway between them; coefficients average.
    #[test]
    fn rotations_about_one_axis_average_to_the_middle() {
        let mut acc = MeanAccumulator::default();
        acc.add(&person(&[(16, [0.0, 0.0, -1.0])], 1.0));
        acc.add(&person(&[(16, [0.0, 0.0, -0.4])], 0.0));
        let m = acc.finish().expect("two people");
        let want = Rotation3::new(Vector3::new(0.0, 0.0, -0.7)).into_inner();
        for k in 0..9 {
            assert!((m.rotations[16][k] - want[(k / 3, k % 3)]).abs() < 1e-12);
            assert!((m.rotations[3][k] - Matrix3::<f64>::identity()[(k / 3, k % 3)]).abs() < 1e-12);
        }
        assert_eq!(m.betas, [0.5; 10]);
        assert_eq!(m.people, 2);
        // A mean of opposite turns is the identity, not a degenerate matrix.
        let mut acc = MeanAccumulator::default();
        acc.add(&person(
            &[(1, [0.0, 0.0, std::f64::consts::FRAC_PI_2])],
            0.0,
        ));
        acc.add(&person(
            &[(1, [0.0, 0.0, -std::f64::consts::FRAC_PI_2])],
            0.0,
        ));
        let r = acc.finish().unwrap().rotations[1];
        let m = Matrix3::from_row_slice(&r);
        assert!((m.transpose() * m - Matrix3::identity()).norm() < 1e-9);
        assert!((m.determinant() - 1.0).abs() < 1e-9);
        assert!(MeanAccumulator::default().finish().is_none());
    }
}
