//! An error budget for SMPL-X predictions: `mvmp eval --truth PARTS` replaces parameter groups of each
//! prediction with those of the annotated person nearest its pelvis, keeping the predicted pelvis, so the
//! figures say how much of the error each group carries.

use std::str::FromStr;

use burn::tensor::{Tensor, TensorData};
use mvmp_data::layout::Person;
use mvmp_smplx::params::ParamTensors;
use mvmp_smplx::{SmplxLayer, SmplxParams};

use crate::PersonPose;
use crate::drivers::pose_params;

/// A group of SMPL-X parameters that can be taken from the annotation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum TruthPart {
    /// The global orientation.
    Orient,
    /// The 21 body joints' rotations.
    Body,
    /// Both hands' 15 joints each.
    Hands,
    /// The jaw, the eyes and the expression.
    Face,
    /// The betas.
    Shape,
}

impl TruthPart {
    pub const ALL: [TruthPart; 5] = [
        TruthPart::Orient,
        TruthPart::Body,
        TruthPart::Hands,
        TruthPart::Face,
        TruthPart::Shape,
    ];

    pub fn name(self) -> &'static str {
        match self {
            TruthPart::Orient => "orient",
            TruthPart::Body => "body",
            TruthPart::Hands => "hands",
            TruthPart::Face => "face",
            TruthPart::Shape => "shape",
        }
    }

    /// Copy this group's values from `truth` into `p`.
    fn copy(self, truth: &SmplxParams, p: &mut SmplxParams) {
        match self {
            TruthPart::Orient => p.global_orient = truth.global_orient.clone(),
            TruthPart::Body => p.body_pose = truth.body_pose.clone(),
            TruthPart::Hands => {
                p.left_hand_pose = truth.left_hand_pose.clone();
                p.right_hand_pose = truth.right_hand_pose.clone();
            }
            TruthPart::Face => {
                p.jaw_pose = truth.jaw_pose.clone();
                p.leye_pose = truth.leye_pose.clone();
                p.reye_pose = truth.reye_pose.clone();
                p.expression = truth.expression.clone();
            }
            TruthPart::Shape => p.betas = truth.betas.clone(),
        }
    }
}

impl FromStr for TruthPart {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        TruthPart::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| format!("{s:?}: expected orient, body, hands, face or shape"))
    }
}

/// A set of parts, as `--truth` names it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TruthParts(pub Vec<TruthPart>);

/// Parse a comma-separated list of parts (`body,shape`); each at most once, sorted.
pub fn parse_truth_parts(s: &str) -> Result<TruthParts, String> {
    let mut parts = s
        .split(',')
        .map(|p| p.trim().parse())
        .collect::<Result<Vec<TruthPart>, String>>()?;
    parts.sort();
    if parts.windows(2).any(|w| w[0] == w[1]) {
        return Err(format!("{s:?}: a part is named twice"));
    }
    Ok(TruthParts(parts))
}

/// `people` posed with `parts` taken from the annotated person nearest each one's pelvis within `gate`
/// metres; each body is posed with its pelvis where its own parameters put it (new betas move the
/// pelvis of smplx's `transl` otherwise). People with no annotated person within the gate keep their own
/// parameters.
pub fn pose_with_truth(
    layer: &SmplxLayer,
    people: &[(SmplxParams, f64)],
    truth: &[Person],
    parts: &[TruthPart],
    gate: f64,
) -> Vec<PersonPose> {
    let own = pose_params(layer, people);
    if parts.is_empty() || own.is_empty() {
        return own;
    }
    let pelvis: Vec<[f64; 3]> = own.iter().map(|p| p.joints[0]).collect();
    let bodies: Vec<SmplxParams> = people
        .iter()
        .zip(&pelvis)
        .map(|((params, _), at)| {
            let mut p = params.clone();
            if let Some(t) = nearest(truth, at, gate) {
                parts.iter().for_each(|part| part.copy(&t.smplx, &mut p));
            }
            p
        })
        .collect();
    let device = layer.device();
    let t = ParamTensors::from_params(&bodies, device);
    let flat: Vec<f32> = pelvis.iter().flatten().map(|&x| x as f32).collect();
    let out = layer.forward_axis_angle(
        t.pose,
        t.betas,
        t.expression,
        Tensor::from_data(TensorData::new(flat, [bodies.len(), 3]), device),
        mvmp_smplx::Translation::Pelvis,
    );
    crate::drivers::to_poses(out.joints, out.vertices, people.iter().map(|p| p.1))
}

/// The index of the point of `points` nearest `at`, if it lies within `gate` metres.
pub fn nearest_within(
    points: impl IntoIterator<Item = [f64; 3]>,
    at: [f64; 3],
    gate: f64,
) -> Option<usize> {
    let dist = |p: [f64; 3]| (0..3).map(|a| (p[a] - at[a]).powi(2)).sum::<f64>().sqrt();
    (points.into_iter().map(dist).enumerate())
        .filter(|(_, d)| *d <= gate)
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

fn nearest<'a>(truth: &'a [Person], at: &[f64; 3], gate: f64) -> Option<&'a Person> {
    nearest_within(truth.iter().map(|p| p.pelvis), *at, gate).map(|i| &truth[i])
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::tensor::Device;
    use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS};

    fn wave(n: usize, scale: f64, phase: f64) -> Vec<f64> {
        (0..n)
            .map(|i| scale * (1.3 * i as f64 + phase).sin())
            .collect()
    }

    fn params(phase: f64, transl: [f64; 3]) -> SmplxParams {
        SmplxParams::from_full_pose(
            &wave(NUM_JOINTS * 3, 0.3, phase),
            &wave(NUM_BETAS, 1.0, phase),
            &wave(NUM_EXPRESSION, 0.5, phase),
            transl,
        )
    }

    fn person(smplx: SmplxParams, pelvis: [f64; 3]) -> Person {
        Person {
            id: 0,
            smplx,
            pelvis,
            joints_3d: Vec::new(),
            views: Vec::new(),
        }
    }

    fn centred(p: &PersonPose) -> Vec<[f64; 3]> {
        let o = p.joints[0];
        let v = p.vertices.as_ref().unwrap();
        v.iter()
            .map(|q| std::array::from_fn(|a| q[a] - o[a]))
            .collect()
    }

    fn max_diff(a: &[[f64; 3]], b: &[[f64; 3]]) -> f64 {
        a.iter()
            .zip(b)
            .flat_map(|(x, y)| (0..3).map(move |k| (x[k] - y[k]).abs()))
            .fold(0.0, f64::max)
    }

    #[test]
    fn taken_parts_follow_the_truth_and_keep_the_predicted_pelvis() {
        let layer = SmplxLayer::new(&mvmp_smplx::standin::standin_model(0), &Device::default());
        let truth_params = params(0.7, [5.0, -3.0, 0.2]);
        let predicted = params(2.1, [1.0, 2.0, 0.9]);
        let far = params(4.0, [-6.0, 0.0, 0.9]);
        let own = pose_params(&layer, &[(predicted.clone(), 0.9), (far.clone(), 0.8)]);
        // The annotation's pelvis 0.2 m from the prediction's: within the 0.5 m gate.
        let at = own[0].joints[0];
        let truth = [person(truth_params.clone(), [at[0] + 0.2, at[1], at[2]])];
        let people = [(predicted.clone(), 0.9), (far, 0.8)];

        let all = pose_with_truth(&layer, &people, &truth, &TruthPart::ALL, 0.5);
        // Every group from the truth: the truth's own mesh (posed by smplx's `transl`, another code path),
        // moved to the predicted pelvis.
        let want = pose_params(&layer, &[(truth_params.clone(), 1.0)]);
        assert!(max_diff(&centred(&all[0]), &centred(&want[0])) < 1e-5);
        assert!(max_diff(&[all[0].joints[0]], &[at]) < 1e-5);
        assert_eq!(all[0].score, 0.9);
        // The person outside the gate keeps its own parameters.
        assert!(
            max_diff(
                all[1].vertices.as_ref().unwrap(),
                own[1].vertices.as_ref().unwrap()
            ) < 1e-5
        );

        // The shape alone: the predicted pose with the truth's betas, at the predicted pelvis.
        let shape = pose_with_truth(&layer, &people, &truth, &[TruthPart::Shape], 0.5);
        let mut reshaped = predicted.clone();
        reshaped.betas = truth_params.betas.clone();
        let want = pose_params(&layer, &[(reshaped, 1.0)]);
        assert!(max_diff(&centred(&shape[0]), &centred(&want[0])) < 1e-5);
        assert!(max_diff(&[shape[0].joints[0]], &[at]) < 1e-5);

        // No parts: the model's own figures.
        let none = pose_with_truth(&layer, &people, &truth, &[], 0.5);
        assert_eq!(none[0].vertices, own[0].vertices);
    }

    #[test]
    fn parts_parse_from_a_comma_list() {
        let p = parse_truth_parts("shape, body").unwrap();
        assert_eq!(p.0, vec![TruthPart::Body, TruthPart::Shape]);
        assert!(
            parse_truth_parts("body,body")
                .unwrap_err()
                .contains("twice")
        );
        assert!(parse_truth_parts("legs").unwrap_err().contains("\"legs\""));
    }
}
