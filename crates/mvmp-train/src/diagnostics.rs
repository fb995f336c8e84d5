//! What a training step's gradients say about where learning happens: the gradient norm of each of the
//! model's top-level modules, logged with every step (`grad_norm` in `metrics.jsonl`). A module whose norm
//! stays orders of magnitude below the others' barely moves under a shared learning rate.
use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Gradients, Tensor};

use mvmp_model::MvmpHmr;

/// Sum of squared gradients over every parameter a visitor meets (`None` until one has a gradient).
struct SquaredNorm<'a> {
    grads: &'a Gradients,
    sum: Option<Tensor<1>>,
}

impl ModuleVisitor for SquaredNorm<'_> {
    fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
        if let Some(g) = p.val().grad(self.grads) {
            let s = g.powi_scalar(2).sum();
            self.sum = Some(match self.sum.take() {
                Some(acc) => acc + s,
                None => s,
            });
        }
    }
}

fn norm<M: Module>(m: &M, grads: &Gradients) -> f32 {
    let mut v = SquaredNorm { grads, sum: None };
    m.visit(&mut v);
    v.sum.map_or(0.0, |s| s.into_scalar::<f32>().sqrt())
}

/// The L2 norm of the gradient of each top-level module, in the model's order (0 where a module is not
/// in the step's graph, such as the ViT and the decoder in stage 1).
pub fn module_grad_norms(model: &MvmpHmr, grads: &Gradients) -> Vec<(&'static str, f32)> {
    let mut out = vec![
        ("vit", norm(&model.vit, grads)),
        ("reduce", norm(&model.reduce, grads)),
        ("hrnet", norm(&model.hrnet, grads)),
        ("rootnet", norm(&model.rootnet, grads)),
        ("decoder", norm(&model.decoder, grads)),
    ];
    if let Some(d) = &model.deformable {
        out.push(("deformable", norm(d, grads)));
    }
    out
}
