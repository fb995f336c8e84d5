//! Adam as burn's `AdamConfig::new()` builds it (beta 0.9 / 0.999, epsilon 1e-5, no weight decay), with
//! each parameter's step on flex as one pass over its values instead of burn's dozen tensor operations.
//!
//! Burn's step allocates and writes a tensor per operation (two moments, their scalings and sums, the
//! square root, the quotient, the scaled step, the new weights), on the thread that runs a step's
//! serial work: the optimizer phase of a stage-2 step of the tiny config took 23-27 ms with it and
//! 19-20 with this pass (README, Benchmarks). Here the weights and both moments are
//! taken over where their buffers are not shared (flex hands a unique contiguous buffer out without a
//! copy) and updated in place, over both cores. Every value is computed with the same float32
//! operations in the same order as burn-flex computes them, so training is bit for bit as with burn's
//! Adam; the state is burn's `AdamState`, so checkpoints are the same files either way.
use std::sync::atomic::{AtomicBool, Ordering};

use burn::optim::{
    Adam, AdamConfig, AdamState, AdaptiveMomentumState, LearningRate, ModuleOptimizer, Optimizer,
};
use burn::tensor::{DType, Device, Tensor, TensorData};
use rayon::prelude::*;

/// Burn's `AdamConfig` defaults, which training has always used.
const BETA_1: f32 = 0.9;
const BETA_2: f32 = 0.999;
const EPSILON: f32 = 1e-5;

/// Values per parallel task.
const CHUNK: usize = 1 << 15;

static FUSED_ADAM: AtomicBool = AtomicBool::new(true);

/// Whether Adam's step on flex takes its one pass (the default) or burn's tensor operations;
/// process-wide, so that a benchmark can time both. The values are the same either way.
pub fn set_fused_adam(on: bool) {
    FUSED_ADAM.store(on, Ordering::Relaxed);
}

/// Whether `t` takes the one-pass step: float32 on flex, with the pass on.
fn fused_update<const D: usize>(t: &Tensor<D>) -> bool {
    t.dtype() == DType::F32 && t.device() == Device::flex() && FUSED_ADAM.load(Ordering::Relaxed)
}

/// The optimizer training uses: burn's Adam at its defaults, each step on flex in one pass.
pub fn adam() -> ModuleOptimizer {
    ModuleOptimizer::from(FusedAdam::new())
}

/// See the module's notes.
#[derive(Clone)]
pub struct FusedAdam {
    burn: Adam,
}

impl FusedAdam {
    pub fn new() -> Self {
        let config = AdamConfig::new()
            .with_beta_1(BETA_1)
            .with_beta_2(BETA_2)
            .with_epsilon(EPSILON);
        FusedAdam {
            burn: config.build(),
        }
    }
}

impl Default for FusedAdam {
    fn default() -> Self {
        Self::new()
    }
}

impl Optimizer for FusedAdam {
    type State<const D: usize> = AdamState<D>;

    fn step<const D: usize>(
        &self,
        lr: LearningRate,
        tensor: Tensor<D>,
        grad: Tensor<D>,
        state: Option<Self::State<D>>,
    ) -> (Tensor<D>, Option<Self::State<D>>) {
        let amsgrad = |s: &AdamState<D>| s.momentum.max_moment_2.is_some();
        if !(fused_update(&tensor) && grad.dtype() == DType::F32)
            || state.as_ref().is_some_and(amsgrad)
        {
            return self.burn.step(lr, tensor, grad, state);
        }
        let device = tensor.device();
        let shape = tensor.shape();
        let (time, moments) = match state {
            Some(s) => (
                s.momentum.time + 1,
                Some((s.momentum.moment_1, s.momentum.moment_2)),
            ),
            None => (1, None),
        };
        // Flex hands a unique contiguous buffer over as it is, without a copy.
        let mut p = tensor.into_data();
        let g = grad.into_data();
        let g = g
            .as_slice::<f32>()
            .expect("float32 gradients beside float32 weights");
        let (mut m1, mut m2, fresh) = match moments {
            Some((a, b)) => (a.into_data(), b.into_data(), false),
            None => (
                zeros_like(g.len(), &shape),
                zeros_like(g.len(), &shape),
                true,
            ),
        };
        let c = Coefficients::new(time, lr);
        update(
            values(&mut p),
            g,
            values(&mut m1),
            values(&mut m2),
            &c,
            fresh,
        );
        let t = |d: TensorData| Tensor::<D>::from_data(d, &device);
        let momentum = AdaptiveMomentumState::new(time, t(m1), t(m2));
        (t(p), Some(AdamState::new(momentum)))
    }

    fn to_device<const D: usize>(state: Self::State<D>, device: &Device) -> Self::State<D> {
        <Adam as Optimizer>::to_device(state, device)
    }
}

/// A float32 buffer's values, to update in place.
fn values(d: &mut TensorData) -> &mut [f32] {
    d.as_mut_slice::<f32>().expect("float32 data")
}

fn zeros_like(n: usize, shape: &burn::tensor::Shape) -> TensorData {
    TensorData::new(vec![0f32; n], shape.clone())
}

/// The step's scalars, computed as burn's `AdaptiveMomentum` computes them (float32).
struct Coefficients {
    factor_1: f32,
    factor_2: f32,
    combined: f32,
    epsilon: f32,
    lr: f32,
}

impl Coefficients {
    fn new(time: usize, lr: LearningRate) -> Self {
        let time = time as i32;
        let correction_2 = (1.0 - BETA_2.powi(time)).sqrt();
        Coefficients {
            factor_1: 1.0 - BETA_1,
            factor_2: 1.0 - BETA_2,
            combined: correction_2 / (1.0 - BETA_1.powi(time)),
            epsilon: EPSILON * correction_2,
            // Burn's tensor scalars reach float32 tensors as `f64 as f32`.
            lr: lr as f32,
        }
    }
}

/// One Adam step of every value, in place: the moments (started from the gradient alone on the first
/// step, as burn does), then the weights. Each expression is burn-flex's operations in their order.
fn update(p: &mut [f32], g: &[f32], m1: &mut [f32], m2: &mut [f32], c: &Coefficients, first: bool) {
    (p.par_chunks_mut(CHUNK).zip(m1.par_chunks_mut(CHUNK)))
        .zip(m2.par_chunks_mut(CHUNK).zip(g.par_chunks(CHUNK)))
        .for_each(|((p, m1), (m2, g))| {
            for (((p, m1), m2), &g) in p.iter_mut().zip(m1).zip(m2).zip(g) {
                (*m1, *m2) = match first {
                    true => (g * c.factor_1, (g * g) * c.factor_2),
                    false => (
                        *m1 * BETA_1 + g * c.factor_1,
                        *m2 * BETA_2 + (g * g) * c.factor_2,
                    ),
                };
                let step = (*m1 * c.combined) / (m2.sqrt() + c.epsilon);
                *p -= step * c.lr;
            }
        });
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::{Linear, LinearConfig};
    use burn::optim::GradientsParams;
    use burn::tensor::Distribution;

    /// The gradients of a squared error through `model` at a fixed batch.
    fn grads(model: &Linear, x: &Tensor<2>, scale: f32) -> GradientsParams {
        let loss = (model.forward(x.clone()) * scale - 0.3)
            .powi_scalar(2)
            .sum();
        GradientsParams::from_grads(loss.backward(), model)
    }

    fn values(model: &Linear) -> Vec<u32> {
        let w = model.weight.val().into_data().try_to_vec::<f32>().unwrap();
        let b = model
            .bias
            .as_ref()
            .unwrap()
            .val()
            .into_data()
            .try_to_vec::<f32>()
            .unwrap();
        w.into_iter().chain(b).map(f32::to_bits).collect()
    }

    /// Over steps whose gradients change size and sign and learning rates that change, the one-pass
    /// step gives burn's Adam's weights bit for bit, and its state is burn's: a record either writes
    /// goes on in the other to the same bits.
    #[test]
    fn the_one_pass_step_is_burns_adam_bit_for_bit() {
        let d = Device::flex().autodiff();
        let x = Tensor::<2>::random([6, 9], Distribution::Normal(0.0, 1.0), &d);
        // Over 70 000 weights: several parallel tasks.
        let start = LinearConfig::new(9, 70_000 / 9).init(&d);
        let (mut ours, mut theirs) = (start.clone(), start.clone());
        let (mut fused, mut burn) = (adam(), AdamConfig::new().init());
        for (step, (scale, lr)) in [(1.0, 1e-3), (0.01, 3e-3), (-2.0, 1e-4), (0.5, 2e-3)]
            .into_iter()
            .enumerate()
        {
            ours = fused.step(lr, ours.clone(), grads(&ours, &x, scale));
            theirs = burn.step(lr, theirs.clone(), grads(&theirs, &x, scale));
            assert_eq!(values(&ours), values(&theirs), "step {step}");
        }
        assert_ne!(values(&ours), values(&start));
        // Each optimizer's state read by the other.
        let mut fused_from_burn = adam().load_record(burn.to_record());
        let mut burn_from_fused = AdamConfig::new().init().load_record(fused.to_record());
        let g = grads(&ours, &x, 0.7);
        let a = fused_from_burn.step(5e-4, ours.clone(), g);
        let b = burn_from_fused.step(5e-4, ours.clone(), grads(&ours, &x, 0.7));
        let c = burn.step(5e-4, theirs.clone(), grads(&theirs, &x, 0.7));
        assert_eq!(values(&a), values(&c));
        assert_eq!(values(&b), values(&c));
        assert_ne!(values(&c), values(&ours));
    }
}
