//! Body rotations swung to point each bone at given joints: the last step of a decoder that gives the
//! body joints' offsets as well as rotations ([`mvmp_decoder::DecoderOptions::joint_offsets`]). Each body
//! joint with a child among the 22 body joints turns by the smallest rotation that takes its bone to that
//! child, as the rotations above it have placed it, onto the direction the target joints give; its twist
//! about the bone stays the decoder's. Joints whose children are not body joints (the feet, the head,
//! the wrists) keep their rotations.
use burn::tensor::{Tensor, TensorData};
use nalgebra::{Matrix3, Rotation3, Unit, Vector3};

use mvmp_smplx::names::{NUM_BODY, PARENTS};

/// Body joints: the pelvis and the 21 whose rotations the body pose holds.
pub const BODY_JOINTS: usize = 22;

/// The child each body joint's bone points at (SMPL-X order), where it has one among the body joints:
/// the spine's top (9) points at the neck, not at the collars.
const CHILD: [Option<usize>; BODY_JOINTS] = [
    None,     // pelvis: its rotation is the global orientation, left as given
    Some(4),  // left hip -> left knee
    Some(5),  // right hip -> right knee
    Some(6),  // spine1 -> spine2
    Some(7),  // left knee -> left ankle
    Some(8),  // right knee -> right ankle
    Some(9),  // spine2 -> spine3
    Some(10), // left ankle -> left foot
    Some(11), // right ankle -> right foot
    Some(12), // spine3 -> neck
    None,     // left foot
    None,     // right foot
    Some(15), // neck -> head
    Some(16), // left collar -> left shoulder
    Some(17), // right collar -> right shoulder
    None,     // head
    Some(18), // left shoulder -> left elbow
    Some(19), // right shoulder -> right elbow
    Some(20), // left elbow -> left wrist
    Some(21), // right elbow -> right wrist
    None,     // left wrist
    None,     // right wrist
];

/// The local rotations `local[0..22]` (index 0 the global orientation) swung so that, posed from the
/// rest joints `rest` (the shaped T-pose's), each bone with a child points along the target joints'
/// `target` (any origin; only directions between them count). Bones of zero length in either keep
/// their rotation.
pub fn swing_to_joints(
    local: &[Matrix3<f64>; BODY_JOINTS],
    rest: &[Vector3<f64>; BODY_JOINTS],
    target: &[Vector3<f64>; BODY_JOINTS],
) -> [Matrix3<f64>; BODY_JOINTS] {
    let mut out = *local;
    let mut global = [Matrix3::identity(); BODY_JOINTS];
    global[0] = local[0];
    for j in 1..BODY_JOINTS {
        let above = global[PARENTS[j] as usize];
        let mut g = above * local[j];
        if let Some(c) = CHILD[j] {
            let now = g * (rest[c] - rest[j]);
            let want = target[c] - target[j];
            if let Some(swing) = smallest_rotation(now, want) {
                g = swing * g;
                out[j] = above.transpose() * g;
            }
        }
        global[j] = g;
    }
    out
}

/// The smallest rotation taking the direction of `a` onto that of `b`; `None` when either is zero.
fn smallest_rotation(a: Vector3<f64>, b: Vector3<f64>) -> Option<Matrix3<f64>> {
    let (na, nb) = (a.norm(), b.norm());
    if na < 1e-9 || nb < 1e-9 {
        return None;
    }
    let (a, b) = (a / na, b / nb);
    let axis = a.cross(&b);
    let angle = axis.norm().atan2(a.dot(&b));
    if axis.norm() < 1e-12 {
        if a.dot(&b) > 0.0 {
            return Some(Matrix3::identity());
        }
        // Opposite: a half turn about any axis square to `a`.
        let other = match a.x.abs() < 0.9 {
            true => Vector3::x(),
            false => Vector3::y(),
        };
        let axis = Unit::new_normalize(a.cross(&other));
        return Some(Rotation3::from_axis_angle(&axis, std::f64::consts::PI).into_inner());
    }
    let axis = Unit::new_normalize(axis);
    Some(Rotation3::from_axis_angle(&axis, angle).into_inner())
}

/// The body joints posed by forward kinematics: `rest` joints turned by the local rotations, the pelvis
/// at `rest[0]`.
pub fn pose_joints(
    local: &[Matrix3<f64>; BODY_JOINTS],
    rest: &[Vector3<f64>; BODY_JOINTS],
) -> [Vector3<f64>; BODY_JOINTS] {
    let mut global = [Matrix3::identity(); BODY_JOINTS];
    let mut at = [rest[0]; BODY_JOINTS];
    global[0] = local[0];
    for j in 1..BODY_JOINTS {
        let p = PARENTS[j] as usize;
        global[j] = global[p] * local[j];
        at[j] = at[p] + global[p] * (rest[j] - rest[p]);
    }
    at
}

/// The body joints' offsets from the pelvis, world axes `[N, 21, 3]`: those of the posed `joints`
/// `[N, J >= 22, 3]` plus `correction` `[N, 21 * 3]` given in the body's own frame (its global rotation
/// `global` `[N, 3, 3]`, body to world). The posed joints and the rotation are detached: the offsets are a
/// target for the body's rotations, not a path into them.
pub fn corrected_offsets(joints: Tensor<3>, correction: Tensor<2>, global: Tensor<3>) -> Tensor<3> {
    let n = joints.dims()[0];
    let own = joints.clone().narrow(1, 1, NUM_BODY) - joints.narrow(1, 0, 1);
    // Row vectors: (R c)^T = c^T R^T.
    let turned = correction
        .reshape([n, NUM_BODY, 3])
        .matmul(global.detach().swap_dims(1, 2));
    own.detach() + turned
}

/// The regressed rotations `[N, 53, 3, 3]` (slot 0 the global orientation, 1 to 21 the body) with the
/// body's swung ([`swing_to_joints`]) so that, from the shaped rest joints `rest` `[N, >= 22, 3]`, each
/// bone points along the target offsets `offsets` `[N, 21, 3]` (from the pelvis, world axes). Computed
/// on the host: it is for inference, where nothing flows back.
pub fn swing_body(rotmats: Tensor<4>, rest: Tensor<3>, offsets: Tensor<3>) -> Tensor<4> {
    let device = rotmats.device();
    let [n, slots, _, _] = rotmats.dims();
    let r = host(rotmats);
    let rj = rest.dims()[1];
    let (rest, offsets) = (host(rest), host(offsets));
    let mut out = r.clone();
    for i in 0..n {
        let m = |s: usize| {
            let at = (i * slots + s) * 9;
            Matrix3::from_row_slice(&r[at..at + 9].iter().map(|&v| v as f64).collect::<Vec<_>>())
        };
        let v = |data: &[f32], at: usize| {
            Vector3::new(data[at] as f64, data[at + 1] as f64, data[at + 2] as f64)
        };
        let local: [Matrix3<f64>; BODY_JOINTS] = std::array::from_fn(m);
        let rest_i: [Vector3<f64>; BODY_JOINTS] =
            std::array::from_fn(|j| v(&rest, (i * rj + j) * 3));
        let target: [Vector3<f64>; BODY_JOINTS] = std::array::from_fn(|j| match j {
            0 => Vector3::zeros(),
            _ => v(&offsets, (i * NUM_BODY + j - 1) * 3),
        });
        let swung = swing_to_joints(&local, &rest_i, &target);
        for (s, rot) in swung.iter().enumerate().skip(1) {
            let at = (i * slots + s) * 9;
            for (k, x) in out[at..at + 9].iter_mut().enumerate() {
                *x = rot[(k / 3, k % 3)] as f32;
            }
        }
    }
    Tensor::from_data(TensorData::new(out, [n, slots, 3, 3]), &device)
}

fn host<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data_as::<f32>()
        .try_into_vec::<f32>()
        .unwrap_or_default()
}

#[cfg(test)]
mod tests {
    use super::*;
    use mvmp_geom::rotation::axis_angle_to_matrix_f64;

    fn rest() -> [Vector3<f64>; BODY_JOINTS] {
        // A T-pose-like skeleton: each joint offset from its parent by a distinct vector.
        std::array::from_fn(|j| {
            let mut p = Vector3::zeros();
            let mut k = j;
            while k > 0 {
                let i = k as f64;
                p += Vector3::new(0.05 * (i % 3.0) - 0.05, 0.03 * (i % 2.0), 0.1 + 0.01 * i)
                    * if [1, 2, 4, 5, 7, 8, 10, 11].contains(&k) {
                        -1.0
                    } else {
                        1.0
                    };
                k = PARENTS[k] as usize;
            }
            p
        })
    }

    fn rotations(seed: f64) -> [Matrix3<f64>; BODY_JOINTS] {
        std::array::from_fn(|j| {
            let t = seed + j as f64;
            axis_angle_to_matrix_f64(Vector3::new(
                0.4 * t.sin(),
                0.3 * (1.7 * t).cos(),
                0.2 * (0.9 * t).sin(),
            ))
        })
    }

    /// Targets posed from other rotations of the same skeleton: after the swing every bone with a child
    /// points where the targets' does, so the joints down the legs and the spine (reached through such
    /// bones alone) land on the targets; leaves and the global orientation keep their rotations.
    #[test]
    fn swinging_points_every_bone_at_its_target() {
        let rest = rest();
        let mut truth = rotations(0.3);
        truth[0] = rotations(5.0)[0];
        let target = pose_joints(&truth, &rest);
        let mut start = rotations(2.1);
        start[0] = truth[0];
        let swung = swing_to_joints(&start, &rest, &target);
        let posed = pose_joints(&swung, &rest);
        for (j, c) in CHILD.iter().enumerate() {
            if let Some(c) = *c {
                let (got, want) = (posed[c] - posed[j], target[c] - target[j]);
                assert!((got - want).norm() < 1e-9, "bone {j}->{c}: {got} vs {want}");
            }
        }
        for j in [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 15] {
            assert!((posed[j] - target[j]).norm() < 1e-9, "joint {j}");
        }
        for j in [0, 10, 11, 15, 20, 21] {
            assert!((swung[j] - start[j]).abs().max() < 1e-12, "joint {j}");
        }
    }

    /// Already pointing the right way: nothing turns. Twist about a bone survives the swing.
    #[test]
    fn a_pose_that_meets_its_targets_is_kept_and_twist_survives() {
        let rest = rest();
        let local = rotations(1.3);
        let target = pose_joints(&local, &rest);
        let swung = swing_to_joints(&local, &rest, &target);
        for j in 0..BODY_JOINTS {
            assert!((swung[j] - local[j]).abs().max() < 1e-9, "joint {j}");
        }
        // Turn the left knee about its own bone (rest knee -> ankle): the ankle does not move, so the
        // swing leaves that twist in place.
        let bone = Unit::new_normalize(rest[7] - rest[4]);
        let mut twisted = local;
        twisted[4] = local[4] * Rotation3::from_axis_angle(&bone, 0.7).into_inner();
        let swung = swing_to_joints(&twisted, &rest, &target);
        assert!((swung[4] - twisted[4]).abs().max() < 1e-9);
    }

    /// The posed joints' offsets from the pelvis, plus the correction turned from the body's frame into
    /// the world: a body turned a quarter about z moves its "ahead" (x) correction along world y.
    #[test]
    fn corrections_turn_from_the_body_frame_into_the_world() {
        let d = burn::tensor::Device::flex();
        let joints: Vec<f32> = (0..22 * 3).map(|i| i as f32 * 0.01).collect();
        let joints = Tensor::<3>::from_data(TensorData::new(joints.clone(), [1, 22, 3]), &d);
        let mut corr = vec![0.0f32; 63];
        corr[3] = 0.5; // joint 2, x
        let corr = Tensor::<2>::from_data(TensorData::new(corr, [1, 63]), &d);
        let quarter = Tensor::<3>::from_data(
            TensorData::new(
                vec![0.0f32, -1.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0],
                [1, 3, 3],
            ),
            &d,
        );
        let got = host(corrected_offsets(joints, corr, quarter));
        for j in 1..22 {
            for a in 0..3 {
                let own = (j * 3 + a) as f32 * 0.01 - a as f32 * 0.01;
                let add = if j == 2 && a == 1 { 0.5 } else { 0.0 };
                let v = got[(j - 1) * 3 + a];
                assert!((v - own - add).abs() < 1e-6, "joint {j} axis {a}: {v}");
            }
        }
    }

    #[test]
    fn smallest_rotation_handles_opposite_and_zero_vectors() {
        let a = Vector3::new(0.0, 0.0, 2.0);
        let r = smallest_rotation(a, -a).unwrap();
        assert!((r * a + a).norm() < 1e-12);
        assert!(smallest_rotation(a, Vector3::zeros()).is_none());
        let b = Vector3::new(1.0, 1.0, 0.0);
        let r = smallest_rotation(a, b).unwrap();
        assert!((r * a.normalize() - b.normalize()).norm() < 1e-12);
        assert!((r.determinant() - 1.0).abs() < 1e-12);
    }
}
