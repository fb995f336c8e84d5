//! GELU on flex, forward and backward over both cores.
//!
//! Flex computes GELU and its backward as one element-wise pass each, but on the calling thread alone,
//! with libm's scalar `erff`: in a `perf` profile of `mvmp bench train` the error function was the
//! largest leaf of the thread that runs a step's serial work. Here `gelu(x) = x / 2 * (1 + erf(x /
//! sqrt 2))` and `gelu'(x) = cdf(x) + x * pdf(x)` run over chunks in parallel, vectorised
//! ([`crate::vmath`]: within 1e-5 relative of the libm forms for |x| <= 10, and of burn's values).
use std::sync::atomic::{AtomicBool, Ordering};

use burn::backend::autodiff::checkpoint::base::Checkpointer;
use burn::backend::autodiff::checkpoint::strategy::CheckpointStrategy;
use burn::backend::autodiff::grads::Gradients;
use burn::backend::autodiff::ops::{Backward, Ops, OpsKind};
use burn::backend::tensor::FloatTensor;
use burn::backend::{Autodiff, Backend, Dispatch, Flex, TensorMetadata, backend_extension};
use burn::tensor::{Device, Tensor, TensorData};
use rayon::prelude::*;

use crate::host::HostF32;

/// Elements per parallel chunk.
const CHUNK: usize = 1 << 14;

static PARALLEL_GELU: AtomicBool = AtomicBool::new(true);

/// Whether flex takes this operation (the default) or burn's GELU; process-wide, so that a benchmark
/// can time both.
pub fn set_parallel_gelu(on: bool) {
    PARALLEL_GELU.store(on, Ordering::Relaxed);
}

/// `burn::tensor::activation::gelu(x)`: on flex in parallel and vectorised, in training and outside
/// it (the values within 1e-5 relative of burn-flex's); otherwise burn's own.
pub fn gelu<const D: usize>(x: Tensor<D>) -> Tensor<D> {
    let parallel = x.device() == Device::flex() && PARALLEL_GELU.load(Ordering::Relaxed);
    if !parallel {
        return burn::tensor::activation::gelu(x);
    }
    Tensor::from_dispatch(<Dispatch as GeluBackend>::parallel_gelu(x.into_dispatch()))
}

/// The backend side: a host pass on any backend whose tensors can be read on the host; autodiff adds
/// the backward.
#[backend_extension(Flex, Autodiff)]
pub trait GeluBackend: Backend {
    fn parallel_gelu(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let device = x.device();
        let shape = x.shape().to_vec();
        let x = HostF32::read::<Self>(x);
        let mut v = vec![0f32; x.len()];
        (v.par_chunks_mut(CHUNK).zip(x.par_chunks(CHUNK)))
            .for_each(|(out, x)| crate::vmath::gelu_into(x, out));
        Self::float_from_data(TensorData::new(v, shape), &device)
    }
}

impl GeluBackend for Flex {}

impl<B: Backend + GeluBackend, C: CheckpointStrategy> GeluBackend for Autodiff<B, C> {
    fn parallel_gelu(x: FloatTensor<Self>) -> FloatTensor<Self> {
        let guards = [x.node()];
        let x = x.into_primitive();
        let out = B::parallel_gelu(x.clone());
        match GeluBackward.prepare::<C>(guards).compute_bound().stateful() {
            OpsKind::Tracked(prep) => prep.finish(x, out),
            OpsKind::UnTracked(prep) => prep.finish(out),
        }
    }
}

#[derive(Debug)]
struct GeluBackward;

impl<B: Backend> Backward<B, 1> for GeluBackward {
    /// The input.
    type State = FloatTensor<B>;

    fn backward(self, ops: Ops<Self::State, 1>, grads: &mut Gradients, _: &mut Checkpointer) {
        let grad = grads.consume::<B>(&ops.node);
        let [parent] = ops.parents;
        let Some(node) = parent else { return };
        let device = grad.device();
        let shape = ops.state.shape().to_vec();
        let x = HostF32::read::<B>(ops.state);
        let g = HostF32::read::<B>(grad);
        let mut dx = vec![0f32; x.len()];
        (dx.par_chunks_mut(CHUNK)
            .zip(g.par_chunks(CHUNK).zip(x.par_chunks(CHUNK))))
        .for_each(|(out, (g, x))| crate::vmath::gelu_backward_into(g, x, out));
        grads.register::<B>(
            node.id,
            B::float_from_data(TensorData::new(dx, shape), &device),
        );
    }
}
