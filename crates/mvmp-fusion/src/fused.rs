//! The fused CPU pass of [`crate::fuse_views`] as one operation of burn's flex backend, with its own
//! backward under autodiff.
//!
//! As tensor ops, training samples every view with `grid_sample` and keeps each view's samples and
//! masks for a backward that runs grid_sample's gradient per view. Here the forward is the fused pass
//! (`cpu::fuse`) and the backward scatters the volume's gradient straight to the four bilinear taps of
//! every view that sees a voxel (`cpu::fuse_backward`); the graph keeps nothing for the mean and the
//! maps for the maximum. [`set_fused_backward`] turns the operation off under autodiff, so that the
//! tensor-op path can be timed beside it.
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Device, Tensor, TensorData};

use mvmp_kernels::host::{HostF32, dims};

use crate::FusionMode;
use crate::cpu::HostGrid;

static FUSED_BACKWARD: AtomicBool = AtomicBool::new(true);

/// Whether training (autodiff on flex) fuses views with the fused pass and its scatter backward (the
/// default) or with tensor ops; process-wide. Inference on flex always takes the fused pass.
pub fn set_fused_backward(on: bool) {
    FUSED_BACKWARD.store(on, Ordering::Relaxed);
}

/// See [`set_fused_backward`].
pub fn fused_backward() -> bool {
    FUSED_BACKWARD.load(Ordering::Relaxed)
}

/// What the fused pass needs besides the maps: each batch item's host grid, the voxel grid's shape and
/// the mode.
#[derive(Debug, Clone)]
pub struct FusePlan {
    grids: Vec<Arc<HostGrid>>,
    shape: [usize; 3],
    max: bool,
}

impl FusePlan {
    /// The plan for `maps [B, V, C, h, w]` on `grids`, or `None` where the fused pass does not apply:
    /// deformable fusion, a device other than flex, a grid without a host copy, autodiff with the fused
    /// backward off, or the maximum over 255 views or more.
    pub(crate) fn new(
        device: &Device,
        hosts: Option<Vec<Arc<HostGrid>>>,
        shape: [usize; 3],
        mode: FusionMode,
    ) -> Option<Self> {
        let max = match mode {
            FusionMode::Mean => false,
            FusionMode::Max => true,
            FusionMode::Deformable => return None,
        };
        if *device != Device::flex() || (device.is_autodiff() && !fused_backward()) {
            return None;
        }
        let grids = hosts?;
        if max && grids.iter().any(|g| g.views >= u8::MAX as usize) {
            return None;
        }
        Some(FusePlan { grids, shape, max })
    }
}

/// Fuse `maps [B, V, C, h, w]` into `[B, C, X, Y, Z]` with the fused pass.
pub(crate) fn fuse(maps: Tensor<5>, plan: FusePlan) -> Tensor<5> {
    Tensor::from_dispatch(<Dispatch as FuseBackend>::fused_views(
        maps.into_dispatch(),
        plan,
    ))
}

/// The backend side of [`fuse`]: any backend whose tensors can be read on the host runs the fused pass;
/// autodiff adds the scatter backward.
#[backend_extension(Flex, Autodiff)]
pub trait FuseBackend: Backend {
    fn fused_views(maps: FloatTensor<Self>, plan: FusePlan) -> FloatTensor<Self> {
        forward::<Self>(maps, &plan)
    }
}

impl FuseBackend for Flex {}

impl<B: Backend + FuseBackend, C: CheckpointStrategy> FuseBackend for Autodiff<B, C> {
    fn fused_views(maps: FloatTensor<Self>, plan: FusePlan) -> FloatTensor<Self> {
        let guards = [maps.node()];
        let maps = maps.into_primitive();
        let dims = dims(&maps);
        let out = forward::<B>(maps.clone(), &plan);
        match FusedBackward
            .prepare::<C>(guards)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => {
                let maps = plan.max.then_some(maps);
                prep.finish(Saved { plan, maps, dims }, out)
            }
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

fn forward<B: Backend>(maps: FloatTensor<B>, plan: &FusePlan) -> FloatTensor<B> {
    let device = maps.device();
    let [b, v, c, h, w] = dims(&maps);
    assert_eq!(plan.grids.len(), b, "one sampling grid per batch item");
    let values = HostF32::read::<B>(maps);
    let p: usize = plan.shape.iter().product();
    let mode = if plan.max {
        FusionMode::Max
    } else {
        FusionMode::Mean
    };
    // Every element is written by `cpu::fuse`, so the volume is not zeroed first.
    let mut out: Vec<f32> = Vec::with_capacity(b * c * p);
    let per_item = v * c * h * w;
    for (bi, (dst, g)) in out.spare_capacity_mut()[..b * c * p]
        .chunks_exact_mut(c * p)
        .zip(&plan.grids)
        .enumerate()
    {
        crate::cpu::fuse(g, &values[bi * per_item..(bi + 1) * per_item], c, mode, dst);
    }
    // SAFETY: the loop above initialised all b * c * p elements.
    unsafe { out.set_len(b * c * p) };
    let [x, y, z] = plan.shape;
    B::float_from_data(TensorData::new(out, [b, c, x, y, z]), &device)
}

#[derive(Debug)]
struct FusedBackward;

/// The plan, the maps' shape, and the maps themselves for the maximum (to find the winning views).
#[derive(Debug, Clone)]
struct Saved<B: Backend> {
    plan: FusePlan,
    maps: Option<FloatTensor<B>>,
    dims: [usize; 5],
}

impl<B: Backend> Backward<B, 1> for FusedBackward {
    type State = Saved<B>;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let [parent] = ops.parents;
        let Some(node) = parent else { return };
        let Saved { plan, maps, dims } = ops.state;
        let device = grad.device();
        let grad = HostF32::read::<B>(grad);
        let maps = maps.map(HostF32::read::<B>);
        let [b, v, c, h, w] = dims;
        let p: usize = plan.shape.iter().product();
        let per_item = v * c * h * w;
        let mut out = Vec::with_capacity(b * per_item);
        for (bi, g) in plan.grids.iter().enumerate() {
            let m = maps
                .as_ref()
                .map(|m| &m[bi * per_item..(bi + 1) * per_item]);
            out.extend(crate::cpu::fuse_backward(
                g,
                &grad[bi * c * p..(bi + 1) * c * p],
                m,
                c,
            ));
        }
        let out = B::float_from_data(TensorData::new(out, dims), &device);
        grads.register::<B>(node.id, out);
    }
}
