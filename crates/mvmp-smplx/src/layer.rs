//! The batched, differentiable SMPL-X layer on tensors (smplx's `lbs.py`).
//!
//! Forward, for N bodies:
//! 1. `v_shaped = v_template + [betas, expression] . shapedirs`            `[N, V, 3]`
//! 2. `J = J_regressor . v_shaped` (precomputed as a blend of joint templates) `[N, 55, 3]`
//! 3. `v_posed = v_shaped + (R_j - I)_{j=1..54} . posedirs`                `[N, V, 3]`
//! 4. kinematic chain, level by level of the tree: `G_j = G_parent(j) [R_j | J_j - J_parent(j)]`
//! 5. skinning `v = sum_j w_vj (G_j with translation G_j.t - G_j.R J_j) [v_posed; 1]`
//! 6. joints: the 55 posed joints, the 21 vertex joints and, when the file has them, the 51 face
//!    landmarks (barycentric over faces), all from the posed mesh; then the translation.
//!
//! Hands are relative to a flat hand (smplx's `flat_hand_mean = True`): the file's hand means are not added.
use std::sync::Arc;

use burn::tensor::{Device, Int, Tensor, TensorData};

use crate::BodyModel;
use crate::fused::FusedLbs;
use crate::names::{
    EXTRA_VERTEX_JOINTS, NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS, NUM_POSE_JOINTS, NUM_REGRESSED,
};
pub use crate::params::Translation;
use mvmp_geom::rotation::axis_angle_to_matrix;

/// Output of the layer.
#[derive(Debug, Clone)]
pub struct SmplxOutput {
    /// `[N, V, 3]` posed vertices (metres).
    pub vertices: Tensor<3>,
    /// `[N, J, 3]` joints: 55 LBS joints, 21 vertex joints, then 51 landmarks when available.
    pub joints: Tensor<3>,
}

/// The SMPL-X layer with the model's arrays on a device.
#[derive(Debug, Clone)]
pub struct SmplxLayer {
    /// `[1, 3*V]`, planar: all x, then all y, then all z (elementwise skinning runs on contiguous planes).
    v_template: Tensor<2>,
    /// `[B+E, 3*V]` shape then expression directions, planar.
    shapedirs: Tensor<2>,
    /// `[1, 55*3]` joints of the template.
    j_template: Tensor<2>,
    /// `[B+E, 55*3]` joint displacement per shape/expression unit.
    j_shapedirs: Tensor<2>,
    /// `[3*V, 486]`, planar rows: the pose-corrective GEMM runs as `[3V, 486] x [486, N]`, which flex's GEMM
    /// does 1.7x faster than the skinny `[N, 486] x [486, 3V]` (8.0 vs 13.4 ms at N = 30).
    posedirs_t: Tensor<2>,
    /// `[55, V]` skinning weights, transposed.
    weights_t: Tensor<2>,
    /// Extra joints as weighted sums of 3 vertices each: `[3X]` vertex indices and `[1, X, 3, 1]` weights.
    extra_index: Tensor<1, Int>,
    extra_weight: Tensor<4>,
    /// Tree levels: for each depth, the joints at that depth and the positions of their parents in the
    /// concatenation of the previous levels.
    levels: Vec<(Tensor<1, Int>, Tensor<1, Int>, Vec<usize>)>,
    /// Joint order of the concatenated levels back to model order.
    level_to_joint: Tensor<1, Int>,
    parents: Tensor<1, Int>,
    num_vertices: usize,
    num_extra: usize,
    faces: Vec<[u32; 3]>,
    device: Device,
    /// The fused CPU pass, made when the layer lives on the CPU backend (flex), with or without autodiff.
    fused: Option<Arc<FusedLbs>>,
}

impl SmplxLayer {
    /// Put a body model on a device, keeping 10 shape and 10 expression components.
    pub fn new(model: &BodyModel, device: &Device) -> Self {
        let v = model.num_vertices();
        let (sd, nc) = selected_shapedirs(model);
        // Joints are linear in the shaped vertices: J = Jr v_template + sum_c beta_c (Jr sd_c).
        let j_template = regress(&model.j_regressor, v, &model.v_template);
        let j_sd: Vec<f32> = (0..nc)
            .flat_map(|ci| regress(&model.j_regressor, v, &sd[ci * v * 3..(ci + 1) * v * 3]))
            .collect();
        let p = NUM_POSE_JOINTS * 9;
        let extra_rows = extra_joint_rows(model);
        let nx = extra_rows.len();
        let taps: Vec<[(usize, f32); 3]> = extra_rows
            .iter()
            .map(|row| std::array::from_fn(|k| row.get(k).copied().unwrap_or((row[0].0, 0.0))))
            .collect();
        // A model without vertex joints still gets one all-zero tap, so the tensors are not empty.
        let (extra_index, extra_weight): (Vec<usize>, Vec<f32>) = match nx {
            0 => (vec![0; 3], vec![0.0; 3]),
            _ => taps.iter().flatten().copied().unzip(),
        };
        let (levels, level_to_joint) = tree_levels(&model.parents, device);
        let parents: Vec<usize> = (0..NUM_JOINTS)
            .map(|j| model.parents[j].max(0) as usize)
            .collect();
        let fused = (*device == Device::flex())
            .then(|| FusedLbs::new(model, j_template.clone(), j_sd.clone(), taps));
        let f2 = |d: Vec<f32>, s: [usize; 2]| Tensor::<2>::from_data(TensorData::new(d, s), device);
        SmplxLayer {
            v_template: f2(planar(&model.v_template, 1, v), [1, v * 3]),
            shapedirs: f2(planar(&sd, nc, v), [nc, v * 3]),
            j_template: f2(j_template, [1, NUM_JOINTS * 3]),
            j_shapedirs: f2(j_sd, [nc, NUM_JOINTS * 3]),
            posedirs_t: f2(planar_posedirs(model), [v * 3, p]),
            weights_t: f2(transposed_weights(model), [NUM_JOINTS, v]),
            extra_weight: Tensor::from_data(
                TensorData::new(extra_weight, [1, nx.max(1), 3, 1]),
                device,
            ),
            extra_index: int1(&extra_index, device),
            levels,
            level_to_joint: int1(&level_to_joint, device),
            parents: int1(&parents, device),
            num_vertices: v,
            num_extra: nx,
            faces: model.faces.clone(),
            device: device.clone(),
            fused,
        }
    }

    pub fn num_vertices(&self) -> usize {
        self.num_vertices
    }

    /// Joints in the output: 55 plus the extra joints (127 with landmarks, 76 without).
    pub fn num_joints(&self) -> usize {
        NUM_JOINTS + self.num_extra
    }

    pub fn faces(&self) -> &[[u32; 3]] {
        &self.faces
    }

    pub fn device(&self) -> &Device {
        &self.device
    }

    /// Joints of the shaped rest pose `[N, 55, 3]` (no pose, no translation).
    pub fn rest_joints(&self, betas: Tensor<2>, expression: Tensor<2>) -> Tensor<3> {
        let n = betas.dims()[0];
        let coeffs = Tensor::cat(vec![betas, expression], 1);
        (self.j_template.clone() + coeffs.matmul(self.j_shapedirs.clone()))
            .reshape([n, NUM_JOINTS, 3])
    }

    /// Forward from axis-angle: `pose [N, 55, 3]` (full pose in model joint order).
    pub fn forward_axis_angle(
        &self,
        pose: Tensor<3>,
        betas: Tensor<2>,
        expression: Tensor<2>,
        transl: Tensor<2>,
        mode: Translation,
    ) -> SmplxOutput {
        let n = pose.dims()[0];
        let rot =
            axis_angle_to_matrix(pose.reshape([n * NUM_JOINTS, 3])).reshape([n, NUM_JOINTS, 3, 3]);
        self.forward(rot, betas, expression, transl, mode)
    }

    /// Forward from rotation matrices `[N, 55, 3, 3]`, betas `[N, 10]`, expression `[N, 10]`,
    /// translation `[N, 3]`.
    ///
    /// On the CPU backend (flex) this runs the fused pass of `fused.rs`: as it is for inference, and under
    /// autodiff as one operation with its own backward (`op.rs`; off with
    /// [`crate::set_fused_backward`]). Elsewhere it runs the tensor ops of
    /// [`SmplxLayer::forward_tensor_ops`]. They compute the same function (tested to 1e-5 m) and the same
    /// gradients.
    pub fn forward(
        &self,
        rot: Tensor<4>,
        betas: Tensor<2>,
        expression: Tensor<2>,
        transl: Tensor<2>,
        mode: Translation,
    ) -> SmplxOutput {
        if let Some(fused) = &self.fused {
            let autodiff = [
                rot.device(),
                betas.device(),
                expression.device(),
                transl.device(),
            ]
            .iter()
            .any(|d| d.is_autodiff());
            if !autodiff
                && let Some(out) =
                    self.forward_fused(fused, &rot, &betas, &expression, &transl, mode)
            {
                return out;
            }
            if autodiff && crate::op::fused_backward() && rot.dims()[0] > 0 {
                return self.forward_op(fused, rot, betas, expression, transl, mode);
            }
        }
        self.forward_tensor_ops(rot, betas, expression, transl, mode)
    }

    /// Whether [`SmplxLayer::forward`] runs the fused CPU pass (the layer lives on flex).
    pub fn is_fused(&self) -> bool {
        self.fused.is_some()
    }

    /// The fused pass as one differentiable operation.
    fn forward_op(
        &self,
        fused: &Arc<FusedLbs>,
        rot: Tensor<4>,
        betas: Tensor<2>,
        expression: Tensor<2>,
        transl: Tensor<2>,
        mode: Translation,
    ) -> SmplxOutput {
        let n = rot.dims()[0];
        let inputs = Tensor::cat(
            vec![rot.reshape([n, NUM_JOINTS * 9]), betas, expression, transl],
            1,
        );
        let plan = crate::op::LbsPlan {
            lbs: fused.clone(),
            mode,
        };
        let out = crate::op::pose(inputs, plan);
        let v = self.num_vertices;
        SmplxOutput {
            vertices: out.clone().narrow(1, 0, v),
            joints: out.narrow(1, v, self.num_joints()),
        }
    }

    fn forward_fused(
        &self,
        fused: &FusedLbs,
        rot: &Tensor<4>,
        betas: &Tensor<2>,
        expression: &Tensor<2>,
        transl: &Tensor<2>,
        mode: Translation,
    ) -> Option<SmplxOutput> {
        let n = rot.dims()[0];
        let host = |t: Tensor<2>| t.into_data_as::<f32>().try_into_vec::<f32>().ok();
        let rot = host(rot.clone().reshape([n, NUM_JOINTS * 9]))?;
        let coeffs = host(Tensor::cat(vec![betas.clone(), expression.clone()], 1))?;
        let transl = host(transl.clone())?;
        let out = fused.forward(n, &rot, &coeffs, &transl, mode, false);
        let nj = self.num_joints();
        Some(SmplxOutput {
            vertices: Tensor::from_data(
                TensorData::new(out.vertices, [n, self.num_vertices, 3]),
                &self.device,
            ),
            joints: Tensor::from_data(TensorData::new(out.joints, [n, nj, 3]), &self.device),
        })
    }

    /// The forward as tensor ops on any backend, differentiable in every input.
    pub fn forward_tensor_ops(
        &self,
        rot: Tensor<4>,
        betas: Tensor<2>,
        expression: Tensor<2>,
        transl: Tensor<2>,
        mode: Translation,
    ) -> SmplxOutput {
        let n = rot.dims()[0];
        let v = self.num_vertices;
        let coeffs = Tensor::cat(vec![betas, expression], 1); // [N, 20]
        let v_shaped = self.v_template.clone() + coeffs.clone().matmul(self.shapedirs.clone()); // [N, 3V]
        let joints_rest = (self.j_template.clone() + coeffs.matmul(self.j_shapedirs.clone()))
            .reshape([n, NUM_JOINTS, 3]);
        // Pose correctives from (R_j - I) of joints 1..54, row-major.
        let eye = Tensor::<2>::eye(3, &self.device).reshape([1, 1, 3, 3]);
        let feat =
            (rot.clone().narrow(1, 1, NUM_POSE_JOINTS) - eye).reshape([n, NUM_POSE_JOINTS * 9]);
        let correctives = self.posedirs_t.clone().matmul(feat.transpose()).transpose(); // [N, 3V]
        let v_posed = (v_shaped + correctives).reshape([n, 3, v]); // planar

        // Kinematic chain, one tree level at a time.
        let parent_rest = joints_rest.clone().select(1, self.parents.clone());
        let rel = joints_rest.clone() - parent_rest; // [N, 55, 3]; the root's row is unused
        let mut g_rot: Vec<Tensor<4>> = Vec::new();
        let mut g_tr: Vec<Tensor<3>> = Vec::new();
        for (d, (joints, parent_pos, _)) in self.levels.iter().enumerate() {
            let r_l = rot.clone().select(1, joints.clone()); // [N, k, 3, 3]
            if d == 0 {
                g_rot.push(r_l);
                g_tr.push(joints_rest.clone().select(1, joints.clone()));
                continue;
            }
            let acc_rot = Tensor::cat(g_rot.clone(), 1).select(1, parent_pos.clone()); // [N, k, 3, 3]
            let acc_tr = Tensor::cat(g_tr.clone(), 1).select(1, parent_pos.clone()); // [N, k, 3]
            let rel_l = rel.clone().select(1, joints.clone()); // [N, k, 3]
            let k = rel_l.dims()[1];
            let t_l = acc_rot
                .clone()
                .matmul(rel_l.reshape([n, k, 3, 1]))
                .reshape([n, k, 3])
                + acc_tr;
            g_rot.push(acc_rot.matmul(r_l));
            g_tr.push(t_l);
        }
        let g_rot = Tensor::cat(g_rot, 1).select(1, self.level_to_joint.clone()); // [N, 55, 3, 3]
        let posed_joints = Tensor::cat(g_tr, 1).select(1, self.level_to_joint.clone()); // [N, 55, 3]
        // Skinning transforms A_j = [G_R | G_t - G_R J_j] as 12 coefficient planes:
        // [12, N, 55] x [55, V] -> [12, N, V], one GEMM for every body.
        let a_t = posed_joints.clone()
            - g_rot
                .clone()
                .matmul(joints_rest.clone().reshape([n, NUM_JOINTS, 3, 1]))
                .reshape([n, NUM_JOINTS, 3]);
        let a = Tensor::cat(vec![g_rot, a_t.reshape([n, NUM_JOINTS, 3, 1])], 3) // [N, 55, 3, 4]
            .reshape([n, NUM_JOINTS, 12])
            .permute([2, 0, 1])
            .reshape([12 * n, NUM_JOINTS]);
        let t = a.matmul(self.weights_t.clone()).reshape([3, 4, n, v]);
        // Apply them to the homogeneous posed vertices [4, N, V]: one broadcast product and one sum over
        // the 4 columns (half the time of 12 plane-by-plane products and adds).
        let ones = Tensor::<3>::ones([1, n, v], &self.device);
        let vh = Tensor::cat(vec![v_posed.swap_dims(0, 1), ones], 0).reshape([1, 4, n, v]);
        let mut verts = (t * vh).sum_dim(1).reshape([3, n, v]).permute([1, 2, 0]); // [N, V, 3]
        let mut joints = posed_joints;
        if self.num_extra > 0 {
            let x = self.num_extra;
            let picked = verts
                .clone()
                .select(1, self.extra_index.clone())
                .reshape([n, x, 3, 3]);
            let extra = (picked * self.extra_weight.clone())
                .sum_dim(2)
                .reshape([n, x, 3]);
            joints = Tensor::cat(vec![joints, extra], 1);
        }
        let shift = match mode {
            Translation::Standard => transl,
            Translation::Pelvis => transl - joints_rest.narrow(1, 0, 1).reshape([n, 3]),
        }
        .reshape([n, 1, 3]);
        verts = verts + shift.clone();
        SmplxOutput {
            vertices: verts,
            joints: joints + shift,
        }
    }
}

/// The 10 shape and 10 expression components of `shapedirs [V, 3, L]` as rows `[20, V*3]` (vertices
/// interleaved), and their number.
fn selected_shapedirs(model: &BodyModel) -> (Vec<f32>, usize) {
    let (v, l) = (model.num_vertices(), model.num_shape_components);
    let e0 = model.expression_offset();
    let comps: Vec<usize> = (0..NUM_BETAS).chain(e0..e0 + NUM_EXPRESSION).collect();
    let mut sd = vec![0f32; comps.len() * v * 3];
    for (ci, &c) in comps.iter().enumerate() {
        for k in 0..v * 3 {
            sd[ci * v * 3 + k] = model.shapedirs[k * l + c];
        }
    }
    (sd, comps.len())
}

/// Interleaved `[rows, V*3]` to planar `[rows, 3*V]` (all x, then y, then z).
fn planar(src: &[f32], rows: usize, v: usize) -> Vec<f32> {
    let mut out = vec![0f32; rows * 3 * v];
    for r in 0..rows {
        for vi in 0..v {
            for a in 0..3 {
                out[r * 3 * v + a * v + vi] = src[r * 3 * v + vi * 3 + a];
            }
        }
    }
    out
}

/// The joint regressor `jr [55, V]` applied to interleaved vertices `[V*3]` -> `[55*3]`.
fn regress(jr: &[f32], v: usize, verts: &[f32]) -> Vec<f32> {
    let mut out = vec![0f32; NUM_JOINTS * 3];
    for j in 0..NUM_JOINTS {
        let row = &jr[j * v..(j + 1) * v];
        for (vi, &w) in row.iter().enumerate() {
            if w != 0.0 {
                for a in 0..3 {
                    out[j * 3 + a] += w * verts[vi * 3 + a];
                }
            }
        }
    }
    out
}

/// posedirs `[V, 3, 486]` -> `[3*V, 486]`, rows planar.
fn planar_posedirs(model: &BodyModel) -> Vec<f32> {
    let (v, p) = (model.num_vertices(), NUM_POSE_JOINTS * 9);
    let mut pd = vec![0f32; p * v * 3];
    for vi in 0..v {
        for a in 0..3 {
            let row = a * v + vi;
            pd[row * p..(row + 1) * p]
                .copy_from_slice(&model.posedirs[(vi * 3 + a) * p..(vi * 3 + a + 1) * p]);
        }
    }
    pd
}

/// Skinning weights `[V, 55]` -> `[55, V]`.
fn transposed_weights(model: &BodyModel) -> Vec<f32> {
    let v = model.num_vertices();
    let mut w = vec![0f32; NUM_JOINTS * v];
    for vi in 0..v {
        for j in 0..NUM_JOINTS {
            w[j * v + vi] = model.weights[vi * NUM_JOINTS + j];
        }
    }
    w
}

/// The joints beyond the 55 as (vertex, weight) rows: the vertex joints, then the face landmarks (three
/// barycentric taps each). A model with fewer vertices than SMPL-X has no meaningful vertex joints: none.
fn extra_joint_rows(model: &BodyModel) -> Vec<Vec<(usize, f32)>> {
    let v = model.num_vertices();
    let mut rows: Vec<Vec<(usize, f32)>> = EXTRA_VERTEX_JOINTS
        .iter()
        .filter(|(_, vid)| *vid < v)
        .map(|(_, vid)| vec![(*vid, 1.0)])
        .collect();
    if rows.len() < EXTRA_VERTEX_JOINTS.len() {
        return Vec::new();
    }
    if let Some((fi, bary)) = &model.landmarks {
        for (li, &f) in fi.iter().enumerate() {
            let tri = model.faces[f as usize];
            rows.push(
                (0..3)
                    .map(|k| (tri[k] as usize, bary[li * 3 + k]))
                    .collect(),
            );
        }
    }
    rows
}

/// The kinematic tree by depth: per level its joints and their parents' positions in the level order,
/// and each joint's position in that order.
#[allow(clippy::type_complexity)]
fn tree_levels(
    parents: &[i32],
    device: &Device,
) -> (
    Vec<(Tensor<1, Int>, Tensor<1, Int>, Vec<usize>)>,
    Vec<usize>,
) {
    let mut depth = vec![0usize; NUM_JOINTS];
    for j in 1..NUM_JOINTS {
        depth[j] = depth[parents[j] as usize] + 1;
    }
    let max_depth = *depth.iter().max().unwrap_or(&0);
    let mut position = vec![0usize; NUM_JOINTS];
    let mut order = Vec::with_capacity(NUM_JOINTS);
    let mut levels = Vec::new();
    for d in 0..=max_depth {
        let joints: Vec<usize> = (0..NUM_JOINTS).filter(|&j| depth[j] == d).collect();
        let parent_pos: Vec<usize> = joints
            .iter()
            .map(|&j| {
                if d == 0 {
                    0
                } else {
                    position[parents[j] as usize]
                }
            })
            .collect();
        for &j in &joints {
            position[j] = order.len();
            order.push(j);
        }
        levels.push((
            int1(&joints, device),
            int1(&parent_pos, device),
            joints.clone(),
        ));
    }
    (levels, position)
}

fn int1(v: &[usize], device: &Device) -> Tensor<1, Int> {
    let d: Vec<i64> = v.iter().map(|&x| x as i64).collect();
    Tensor::from_data(TensorData::new(d, [v.len()]), device)
}

/// Map the 53 regressed rotations `[N, 53, 3, 3]` (global, 21 body, 15 left hand, 15 right hand, jaw) to
/// the full pose `[N, 55, 3, 3]` with identity eyes.
pub fn regressed_to_full_pose(rot53: Tensor<4>) -> Tensor<4> {
    let n = rot53.dims()[0];
    debug_assert_eq!(rot53.dims()[1], NUM_REGRESSED);
    let eye = Tensor::<2>::eye(3, &rot53.device())
        .reshape([1, 1, 3, 3])
        .repeat_dim(0, n)
        .repeat_dim(1, 2);
    Tensor::cat(
        vec![
            rot53.clone().narrow(1, 0, 22), // global + body -> 0..=21
            rot53.clone().narrow(1, 52, 1), // jaw -> 22
            eye,                            // eyes -> 23, 24
            rot53.narrow(1, 22, 30),        // hands -> 25..=54
        ],
        1,
    )
}
