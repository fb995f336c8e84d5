//! The fused SMPL-X pass as one operation of burn's flex backend, with its own backward under autodiff
//! (`fused/backward.rs`).
//!
//! As tensor ops, training runs every step of the layer as its own node over `[N, V, 3]` planes and
//! keeps them all for the backward. Here the inputs travel as one row per body (rotations, betas,
//! expression, translation) and the output as one `[N, V + J, 3]` block (vertices, then joints); the
//! graph keeps only the inputs, and the backward recomputes the rest. [`set_fused_backward`] turns the
//! operation off, so that the tensor-op path can be timed beside it.
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Tensor, TensorData};

use mvmp_kernels::host::{HostF32, dims};

use crate::fused::FusedLbs;
use crate::names::NUM_JOINTS;
use crate::params::Translation;

static FUSED_BACKWARD: AtomicBool = AtomicBool::new(true);

/// Whether training (autodiff on flex) poses bodies with the fused pass and its backward (the default)
/// or with tensor ops; process-wide. Inference on flex always takes the fused pass.
pub fn set_fused_backward(on: bool) {
    FUSED_BACKWARD.store(on, Ordering::Relaxed);
}

/// See [`set_fused_backward`].
pub fn fused_backward() -> bool {
    FUSED_BACKWARD.load(Ordering::Relaxed)
}

/// Columns of an input row: 55 row-major rotations, then the coefficients, then the translation.
pub(crate) fn input_width(components: usize) -> usize {
    NUM_JOINTS * 9 + components + 3
}

/// The model's packed arrays and the translation mode of one call.
#[derive(Debug, Clone)]
pub struct LbsPlan {
    pub(crate) lbs: Arc<FusedLbs>,
    pub(crate) mode: Translation,
}

/// Pose `inputs [N, 55 * 9 + 20 + 3]` with the fused pass: `[N, V + J, 3]`.
pub(crate) fn pose(inputs: Tensor<2>, plan: LbsPlan) -> Tensor<3> {
    Tensor::from_dispatch(<Dispatch as LbsBackend>::fused_lbs(
        inputs.into_dispatch(),
        plan,
    ))
}

/// The backend side of [`pose`]: any backend whose tensors can be read on the host runs the fused pass;
/// autodiff adds its backward.
#[backend_extension(Flex, Autodiff)]
pub trait LbsBackend: Backend {
    fn fused_lbs(inputs: FloatTensor<Self>, plan: LbsPlan) -> FloatTensor<Self> {
        let device = inputs.device();
        forward::<Self>(&HostF32::read::<Self>(inputs), &device, &plan, false).0
    }
}

impl LbsBackend for Flex {}

impl<B: Backend + LbsBackend, C: CheckpointStrategy> LbsBackend for Autodiff<B, C> {
    fn fused_lbs(inputs: FloatTensor<Self>, plan: LbsPlan) -> FloatTensor<Self> {
        let guards = [inputs.node()];
        let inputs = inputs.into_primitive();
        let device = inputs.device();
        let host = HostF32::read::<B>(inputs).to_vec();
        match LbsBackward.prepare::<C>(guards).compute_bound().stateful() {
            OpsKind::Tracked(prep) => {
                let (out, unposed) = forward::<B>(&host, &device, &plan, true);
                let saved = Saved {
                    plan,
                    inputs: host,
                    unposed,
                };
                prep.finish(saved, out)
            }
            OpsKind::UnTracked(prep) => prep.finish(forward::<B>(&host, &device, &plan, false).0),
        }
    }
}

/// Split one input row block into rotations, coefficients and translations.
fn split(inputs: &[f32], n: usize, nc: usize) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
    let w = input_width(nc);
    let mut rot = Vec::with_capacity(n * NUM_JOINTS * 9);
    let mut coeffs = Vec::with_capacity(n * nc);
    let mut transl = Vec::with_capacity(n * 3);
    for row in inputs.chunks_exact(w) {
        rot.extend_from_slice(&row[..NUM_JOINTS * 9]);
        coeffs.extend_from_slice(&row[NUM_JOINTS * 9..NUM_JOINTS * 9 + nc]);
        transl.extend_from_slice(&row[NUM_JOINTS * 9 + nc..]);
    }
    (rot, coeffs, transl)
}

/// The posed block `[N, V + J, 3]` and, with `keep`, the unposed vertices for the backward.
fn forward<B: Backend>(
    inputs: &[f32],
    device: &B::Device,
    plan: &LbsPlan,
    keep: bool,
) -> (FloatTensor<B>, Vec<f32>) {
    let nc = plan.lbs.num_components();
    let n = inputs.len() / input_width(nc);
    let (rot, coeffs, transl) = split(inputs, n, nc);
    let out = plan.lbs.forward(n, &rot, &coeffs, &transl, plan.mode, keep);
    let (v, j) = (plan.lbs.num_vertices(), plan.lbs.num_joints());
    let mut all = Vec::with_capacity(n * (v + j) * 3);
    for b in 0..n {
        all.extend_from_slice(&out.vertices[b * v * 3..(b + 1) * v * 3]);
        all.extend_from_slice(&out.joints[b * j * 3..(b + 1) * j * 3]);
    }
    let posed = B::float_from_data(TensorData::new(all, [n, v + j, 3]), device);
    (posed, out.unposed)
}

#[derive(Debug)]
struct LbsBackward;

/// The plan, the inputs' values and the unposed vertices: the backward recomputes the rest.
#[derive(Debug, Clone)]
struct Saved {
    plan: LbsPlan,
    inputs: Vec<f32>,
    unposed: Vec<f32>,
}

impl<B: Backend> Backward<B, 1> for LbsBackward {
    type State = Saved;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let [parent] = ops.parents;
        let Some(node) = parent else { return };
        let Saved {
            plan,
            inputs,
            unposed,
        } = ops.state;
        let device = grad.device();
        let [n, points, _] = dims(&grad);
        let grad = HostF32::read::<B>(grad);
        let nc = plan.lbs.num_components();
        let v = plan.lbs.num_vertices();
        let (rot, coeffs, transl) = split(&inputs, n, nc);
        let (mut gv, mut gj) = (Vec::with_capacity(n * v * 3), Vec::new());
        for body in grad.chunks_exact(points * 3) {
            gv.extend_from_slice(&body[..v * 3]);
            gj.extend_from_slice(&body[v * 3..]);
        }
        let g = plan
            .lbs
            .backward(n, &rot, &coeffs, &transl, plan.mode, &unposed, &gv, &gj);
        let w = input_width(nc);
        let mut out = Vec::with_capacity(n * w);
        for b in 0..n {
            out.extend_from_slice(&g.rot[b * NUM_JOINTS * 9..(b + 1) * NUM_JOINTS * 9]);
            out.extend_from_slice(&g.coeffs[b * nc..(b + 1) * nc]);
            out.extend_from_slice(&g.transl[b * 3..(b + 1) * 3]);
        }
        let out = B::float_from_data(TensorData::new(out, [n, w]), &device);
        grads.register::<B>(node.id, out);
    }
}
