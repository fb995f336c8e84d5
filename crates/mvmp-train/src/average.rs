//! An exponential moving average of a model's weights, for validation and the final weights: the last
//! steps of a stage move each weight by noise the average smooths out (docs/architecture.md, Weight
//! averaging).
use burn::module::{Module, ModuleMapper, ModuleVisitor, Param};
use burn::tensor::Tensor;

/// Every float tensor of a model (parameters and running statistics), flattened, in the order the
/// module tree visits them, averaged over the steps since the average started.
#[derive(Debug, Clone)]
pub struct WeightAverage {
    decay: f64,
    steps: usize,
    values: Vec<Tensor<1>>,
}

impl WeightAverage {
    /// An average that starts at `model`'s weights, `steps` steps into its warm-up (0 for a new one; a
    /// resumed one continues the count so that it follows the same rates).
    pub fn start<M: Module>(model: &M, decay: f64, steps: usize) -> Self {
        WeightAverage {
            decay,
            steps,
            values: flat_values(model),
        }
    }

    /// The weight of the old average after `steps` updates: the decay, lower at first so that the
    /// average forgets its starting point quickly (1/10, 2/11, 3/12, ... until the decay is reached).
    fn rate(&self) -> f64 {
        let n = self.steps as f64;
        self.decay.min((1.0 + n) / (10.0 + n))
    }

    /// Fold in `model`'s weights after a step.
    pub fn update<M: Module>(&mut self, model: &M) {
        let r = self.rate();
        let new = flat_values(model);
        assert_eq!(
            new.len(),
            self.values.len(),
            "the averaged model changed shape"
        );
        // Moved out, so that each average's buffer is its own to update in place.
        let old = std::mem::take(&mut self.values);
        self.values = (old.into_iter().zip(new))
            .map(|(avg, w)| mvmp_kernels::blend::blend(avg, w, r, 1.0 - r))
            .collect();
        self.steps += 1;
    }

    /// `model` with the averaged weights in place of its own (same parameter ids and gradient flags).
    pub fn apply<M: Module>(&self, model: M) -> M {
        struct Put<'a> {
            values: std::slice::Iter<'a, Tensor<1>>,
        }
        impl ModuleMapper for Put<'_> {
            fn map_float<const D: usize>(&mut self, param: Param<Tensor<D>>) -> Param<Tensor<D>> {
                let avg = self.values.next().expect("one value per tensor").clone();
                param.map(|t| {
                    let grad = t.is_require_grad();
                    avg.reshape(t.shape()).set_require_grad(grad)
                })
            }
        }
        model.map(&mut Put {
            values: self.values.iter(),
        })
    }
}

fn flat_values<M: Module>(model: &M) -> Vec<Tensor<1>> {
    struct Collect(Vec<Tensor<1>>);
    impl ModuleVisitor for Collect {
        fn visit_float<const D: usize>(&mut self, param: &Param<Tensor<D>>) {
            // Kept off autodiff: the average is read by plain-device copies of the model.
            let t = param.val().without_autodiff();
            let n = t.shape().num_elements();
            self.0.push(t.reshape([n]));
        }
    }
    let mut c = Collect(Vec::new());
    model.visit(&mut c);
    c.0
}

#[cfg(test)]
mod tests {
    use super::*;
    use burn::nn::{Linear, LinearConfig};
    use burn::tensor::{Device, TensorData};

    fn linear_with(w: f32, device: &Device) -> Linear {
        let l = LinearConfig::new(2, 1).init(device);
        l.map(&mut Fill(w))
    }

    struct Fill(f32);
    impl ModuleMapper for Fill {
        fn map_float<const D: usize>(&mut self, p: Param<Tensor<D>>) -> Param<Tensor<D>> {
            let v = self.0;
            p.map(|t| t.zeros_like() + v)
        }
    }

    fn values(l: &Linear) -> Vec<f32> {
        let mut out: Vec<f32> = l.weight.val().into_data().try_to_vec().unwrap();
        out.extend(
            l.bias
                .as_ref()
                .unwrap()
                .val()
                .into_data()
                .try_to_vec::<f32>()
                .unwrap(),
        );
        out
    }

    /// The rates 1/10, 2/11, then the decay (0.2, below 3/12), worked by hand: starting at 0 and folding
    /// in 1 four times leaves 1 - (1/10)(2/11)(1/5)(1/5) = 1 - 4/5500.
    #[test]
    fn the_average_follows_its_rates() {
        let device = Device::default();
        let mut avg = WeightAverage::start(&linear_with(0.0, &device), 0.2, 0);
        let ones = linear_with(1.0, &device);
        for _ in 0..4 {
            avg.update(&ones);
        }
        let got = values(&avg.apply(linear_with(7.0, &device)));
        let want = 1.0 - 4.0 / 5500.0;
        for v in got {
            assert!((v - want).abs() < 1e-6, "{v} against {want}");
        }
    }

    /// Applying keeps shapes and ids and touches nothing but the values.
    #[test]
    fn applying_keeps_the_model_s_shape_and_ids() {
        let device = Device::default();
        let a = linear_with(2.0, &device);
        let avg = WeightAverage::start(&a, 0.9, 0);
        let b = linear_with(5.0, &device);
        let id = b.weight.id;
        let out = avg.apply(b);
        assert_eq!(out.weight.id, id);
        assert_eq!(out.weight.val().dims(), [2, 1]);
        out.weight
            .val()
            .into_data()
            .assert_eq(&TensorData::from([[2.0f32], [2.0]]), true);
    }
}
