//! A residual join, `relu(a + b)`, in training on flex as one pass each way over both cores.
//!
//! burn computes it as an addition and a ReLU, and the ReLU as a comparison into a mask and a masked
//! fill, forward and again backward: five passes over the activation and three allocations, on the
//! thread that carries a step's serial work. HRNet's residual blocks and multi-resolution sums and the
//! RootNet's residual blocks end this way. Here the forward writes the sum's positive part once, and the
//! backward writes the output gradient where the output is positive (zero elsewhere), the gradient of
//! both inputs.
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::activation::relu;
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use crate::host::HostF32;

/// Elements per parallel chunk.
const CHUNK: usize = 1 << 14;

static FUSED_RESIDUAL: AtomicBool = AtomicBool::new(true);

/// Whether training on flex takes this operation (the default) or burn's addition and ReLU;
/// process-wide, so that a benchmark can time both.
pub fn set_fused_residual(on: bool) {
    FUSED_RESIDUAL.store(on, Ordering::Relaxed);
}

/// `relu(a + b)` for two tensors of one shape: in training on flex one pass each way, otherwise
/// burn's own.
pub fn add_relu<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> Tensor<D> {
    let fused = a.is_autodiff()
        && a.device() == Device::flex()
        && a.dims() == b.dims()
        && FUSED_RESIDUAL.load(Ordering::Relaxed);
    if !fused {
        return relu(a + b);
    }
    Tensor::from_dispatch(<Dispatch as ResidualBackend>::add_relu(
        a.into_dispatch(),
        b.into_dispatch(),
    ))
}

/// burn's ReLU of one value: zero where `y <= 0`, `y` elsewhere (a NaN stays one).
fn positive(y: f32) -> f32 {
    if y <= 0.0 { 0.0 } else { y }
}

/// The backend side: a host pass; autodiff adds the backward.
#[backend_extension(Flex, Autodiff)]
pub trait ResidualBackend: Backend {
    fn add_relu(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        let device = a.device();
        let shape = a.shape().to_vec();
        let (a, b) = (HostF32::read::<Self>(a), HostF32::read::<Self>(b));
        let y: Vec<f32> = (a.par_iter().zip(b.par_iter()))
            .with_min_len(CHUNK)
            .map(|(&a, &b)| positive(a + b))
            .collect();
        Self::float_from_data(TensorData::new(y, shape), &device)
    }
}

impl ResidualBackend for Flex {}

impl<B: Backend + ResidualBackend, C: CheckpointStrategy> ResidualBackend for Autodiff<B, C> {
    fn add_relu(a: FloatTensor<Self>, b: FloatTensor<Self>) -> FloatTensor<Self> {
        let guards = [a.node(), b.node()];
        let y = B::add_relu(a.into_primitive(), b.into_primitive());
        match AddReluBackward
            .prepare::<C>(guards)
            .compute_bound()
            .stateful()
        {
            OpsKind::Tracked(prep) => prep.finish(y.clone(), y),
            OpsKind::UnTracked(prep) => prep.finish(y),
        }
    }
}

#[derive(Debug)]
struct AddReluBackward;

impl<B: Backend> Backward<B, 2> for AddReluBackward {
    /// The output: where it is positive, the gradient passes.
    type State = FloatTensor<B>;

    fn backward(self, ops: Ops<Self::State, 2>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let device = grad.device();
        let shape = ops.state.shape().to_vec();
        let y = HostF32::read::<B>(ops.state);
        let g = HostF32::read::<B>(grad);
        let g: Vec<f32> = (g.par_iter().zip(y.par_iter()))
            .with_min_len(CHUNK)
            .map(|(&g, &y)| if y <= 0.0 { 0.0 } else { g })
            .collect();
        let g = B::float_from_data(TensorData::new(g, shape), &device);
        let [node_a, node_b] = ops.parents;
        match (node_a, node_b) {
            (Some(a), Some(b)) => {
                grads.register::<B>(a.id, g.clone());
                grads.register::<B>(b.id, g);
            }
            (Some(n), None) | (None, Some(n)) => grads.register::<B>(n.id, g),
            (None, None) => {}
        }
    }
}
