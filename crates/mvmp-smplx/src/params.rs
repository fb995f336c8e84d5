//! SMPL-X parameters with the standard smplx keys (axis-angle), as read from and written to files.
use std::path::Path;

use burn::tensor::{Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use crate::SmplxError;
use crate::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS, POSE_KEYS};

/// The largest magnitude a shape or expression coefficient may have (in standard deviations; fitted
/// bodies stay within a few).
pub const MAX_COEFFICIENT: f64 = 100.0;
/// Largest axis-angle component accepted (radians, 16 turns): beyond it the f32 forward loses the angle.
pub const MAX_ANGLE: f64 = 100.0;
/// Largest translation component accepted (metres).
pub const MAX_TRANSLATION: f64 = 1.0e5;

/// One body's parameters. Missing keys are zero. Lengths: `global_orient`, `jaw_pose`, `leye_pose`,
/// `reye_pose`, `transl` 3; `body_pose` 63; hand poses 45 each; `betas` and `expression` up to 10.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SmplxParams {
    #[serde(default)]
    pub global_orient: Vec<f64>,
    #[serde(default)]
    pub body_pose: Vec<f64>,
    #[serde(default)]
    pub jaw_pose: Vec<f64>,
    #[serde(default)]
    pub leye_pose: Vec<f64>,
    #[serde(default)]
    pub reye_pose: Vec<f64>,
    #[serde(default)]
    pub left_hand_pose: Vec<f64>,
    #[serde(default)]
    pub right_hand_pose: Vec<f64>,
    #[serde(default)]
    pub betas: Vec<f64>,
    #[serde(default)]
    pub expression: Vec<f64>,
    #[serde(default)]
    pub transl: Vec<f64>,
}

/// How the translation places the body.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Translation {
    /// smplx's `transl`: added to the model's own origin (the pelvis then sits at `J_0(betas) + transl`).
    #[default]
    Standard,
    /// The paper's `T_wld` (docs/architecture.md, SMPL-X): the translation is the pelvis position in the
    /// world.
    Pelvis,
}

/// Most bodies one parameter file may hold: they are posed in one batch.
pub const MAX_BODIES: usize = 4096;

impl SmplxParams {
    fn field(&self, key: &str) -> &Vec<f64> {
        match key {
            "global_orient" => &self.global_orient,
            "body_pose" => &self.body_pose,
            "jaw_pose" => &self.jaw_pose,
            "leye_pose" => &self.leye_pose,
            "reye_pose" => &self.reye_pose,
            "left_hand_pose" => &self.left_hand_pose,
            "right_hand_pose" => &self.right_hand_pose,
            "betas" => &self.betas,
            "expression" => &self.expression,
            "transl" => &self.transl,
            _ => unreachable!("unknown key {key}"),
        }
    }

    fn field_mut(&mut self, key: &str) -> &mut Vec<f64> {
        match key {
            "global_orient" => &mut self.global_orient,
            "body_pose" => &mut self.body_pose,
            "jaw_pose" => &mut self.jaw_pose,
            "leye_pose" => &mut self.leye_pose,
            "reye_pose" => &mut self.reye_pose,
            "left_hand_pose" => &mut self.left_hand_pose,
            "right_hand_pose" => &mut self.right_hand_pose,
            "betas" => &mut self.betas,
            "expression" => &mut self.expression,
            "transl" => &mut self.transl,
            _ => unreachable!("unknown key {key}"),
        }
    }

    /// Check lengths (pose keys exact or absent, betas and expression at most their count), finite values
    /// and coefficient magnitudes; `which` names the body in messages (for example "bodies[2]").
    pub fn validate(&self, which: &str) -> Result<(), SmplxError> {
        let mut keys: Vec<(&str, usize, bool)> = POSE_KEYS
            .iter()
            .map(|(k, _, n)| (*k, n * 3, true))
            .collect();
        keys.extend([
            ("betas", NUM_BETAS, false),
            ("expression", NUM_EXPRESSION, false),
            ("transl", 3, true),
        ]);
        for (key, len, exact) in keys {
            let v = self.field(key);
            let ok = if exact {
                v.is_empty() || v.len() == len
            } else {
                v.len() <= len
            };
            if !ok {
                let want = if exact {
                    format!("{len}")
                } else {
                    format!("at most {len}")
                };
                return Err(SmplxError::Params(format!(
                    "{which}: key `{key}` has {} values, expected {want}",
                    v.len()
                )));
            }
            if let Some(i) = v.iter().position(|x| !x.is_finite()) {
                return Err(SmplxError::Params(format!(
                    "{which}: key `{key}`[{i}] = {} is not finite",
                    v[i]
                )));
            }
            // Shape and expression coefficients are in standard deviations of the model's
            // directions: far outside the cap they pose no body, only meshes kilometres wide.
            let (cap, unit) = match (exact, key) {
                (false, _) => (MAX_COEFFICIENT, "standard deviations"),
                (true, "transl") => (MAX_TRANSLATION, "metres"),
                (true, _) => (MAX_ANGLE, "radians"),
            };
            if let Some(i) = v.iter().position(|x| x.abs() > cap) {
                return Err(SmplxError::Params(format!(
                    "{which}: key `{key}`[{i}] = {:?} is outside +-{cap} ({unit})",
                    v[i]
                )));
            }
        }
        Ok(())
    }

    /// The full pose as 55 axis-angle triples in model joint order.
    pub fn full_pose(&self) -> Vec<f64> {
        let mut out = vec![0.0; NUM_JOINTS * 3];
        for (key, first, count) in POSE_KEYS {
            let v = self.field(key);
            if !v.is_empty() {
                out[first * 3..(first + count) * 3].copy_from_slice(v);
            }
        }
        out
    }

    /// Parameters from a full pose (55 x 3 axis-angle), betas, expression and translation.
    pub fn from_full_pose(
        pose: &[f64],
        betas: &[f64],
        expression: &[f64],
        transl: [f64; 3],
    ) -> Self {
        let mut p = SmplxParams::default();
        for (key, first, count) in POSE_KEYS {
            *p.field_mut(key) = pose[first * 3..(first + count) * 3].to_vec();
        }
        p.betas = betas.to_vec();
        p.expression = expression.to_vec();
        p.transl = transl.to_vec();
        p
    }

    fn padded(&self, key: &str, len: usize) -> Vec<f64> {
        let mut v = self.field(key).clone();
        v.resize(len, 0.0);
        v
    }

    /// Read one body or a list of bodies from a JSON file, validated.
    pub fn read_json(path: &Path) -> Result<Vec<SmplxParams>, SmplxError> {
        let text = std::fs::read_to_string(path).map_err(|source| SmplxError::Io {
            path: path.into(),
            source,
        })?;
        let parsed: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| SmplxError::File {
                path: path.into(),
                what: format!("malformed JSON: {e}"),
            })?;
        let err = |what: String| SmplxError::File {
            path: path.into(),
            what,
        };
        // Typed parses of the text itself, so that a wrong value's message gives its line and column;
        // for a list, also which body.
        let bodies: Vec<SmplxParams> = match parsed {
            serde_json::Value::Array(items) => serde_json::from_str(&text).map_err(|e| {
                let i = items
                    .into_iter()
                    .position(|it| serde_json::from_value::<SmplxParams>(it).is_err())
                    .unwrap_or(0);
                err(format!("bodies[{i}]: {e}"))
            })?,
            serde_json::Value::Object(_) => {
                vec![serde_json::from_str(&text).map_err(|e| err(e.to_string()))?]
            }
            _ => {
                return Err(err(
                    "expected an object with smplx keys (global_orient, body_pose, jaw_pose, \
                     leye_pose, reye_pose, left_hand_pose, right_hand_pose, betas, expression, \
                     transl) or a list of them"
                        .into(),
                ));
            }
        };
        if bodies.is_empty() {
            return Err(err("the list of bodies is empty".into()));
        }
        if bodies.len() > MAX_BODIES {
            return Err(err(format!(
                "{} bodies: at most {MAX_BODIES} per file (each is posed at once, 10475 vertices)",
                bodies.len()
            )));
        }
        for (i, b) in bodies.iter().enumerate() {
            b.validate(&format!("bodies[{i}]"))
                .map_err(|e| err(e.to_string().trim_start_matches("parameters: ").to_string()))?;
        }
        Ok(bodies)
    }
}

/// A batch of parameters as tensors.
#[derive(Debug, Clone)]
pub struct ParamTensors {
    /// `[N, 55, 3]` axis-angle.
    pub pose: Tensor<3>,
    /// `[N, 10]`
    pub betas: Tensor<2>,
    /// `[N, 10]`
    pub expression: Tensor<2>,
    /// `[N, 3]`
    pub transl: Tensor<2>,
}

impl ParamTensors {
    pub fn from_params(bodies: &[SmplxParams], device: &Device) -> Self {
        let n = bodies.len();
        let cat = |f: &dyn Fn(&SmplxParams) -> Vec<f64>| -> Vec<f32> {
            bodies.iter().flat_map(f).map(|x| x as f32).collect()
        };
        let pose = cat(&|b| b.full_pose());
        let betas = cat(&|b| b.padded("betas", NUM_BETAS));
        let expr = cat(&|b| b.padded("expression", NUM_EXPRESSION));
        let transl = cat(&|b| b.padded("transl", 3));
        ParamTensors {
            pose: Tensor::from_data(TensorData::new(pose, [n, NUM_JOINTS, 3]), device),
            betas: Tensor::from_data(TensorData::new(betas, [n, NUM_BETAS]), device),
            expression: Tensor::from_data(TensorData::new(expr, [n, NUM_EXPRESSION]), device),
            transl: Tensor::from_data(TensorData::new(transl, [n, 3]), device),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Values no body has are named with their key, index and cap; values at the caps are accepted.
    #[test]
    fn out_of_range_values_name_their_key_and_the_cap() {
        let cases: [(&str, usize, f64, &str); 4] = [
            ("betas", 10, 1e30, "standard deviations"),
            ("global_orient", 3, 1e30, "radians"),
            ("left_hand_pose", 45, -1e6, "radians"),
            ("transl", 3, 1e39, "metres"),
        ];
        for (key, len, bad, unit) in cases {
            let mut p = SmplxParams::default();
            *p.field_mut(key) = vec![0.0; len];
            p.field_mut(key)[len - 1] = bad;
            let e = p.validate("bodies[1]").unwrap_err().to_string();
            assert!(
                e.contains("bodies[1]")
                    && e.contains(&format!("`{key}`[{}]", len - 1))
                    && e.contains(unit),
                "{e}"
            );
        }
        let p = SmplxParams {
            global_orient: vec![MAX_ANGLE, -MAX_ANGLE, 0.0],
            transl: vec![MAX_TRANSLATION, 0.0, -MAX_TRANSLATION],
            betas: vec![MAX_COEFFICIENT],
            ..Default::default()
        };
        p.validate("bodies[0]").unwrap();
    }
}
