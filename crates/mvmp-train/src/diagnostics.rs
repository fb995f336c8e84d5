//! What a training step's gradients say about where learning happens: the gradient norm of each of the
//! model's top-level modules, logged with every step (`grad_norm` in `metrics.jsonl`), and, on request,
//! the same under each loss term alone (`grad_terms`). A module whose norm stays orders of magnitude below
//! the others' barely moves under a shared learning rate; a term that reaches a module only faintly does
//! not teach it.
use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Gradients, Tensor};

use mvmp_model::MvmpHmr;
use serde_json::{Value, json};

use crate::step::StepLoss;

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
    if let Some(f) = &model.facing {
        out.push(("facing", norm(f, grads)));
    }
    if let Some(h) = &model.vit_joints {
        out.push(("vit_joints", norm(h, grads)));
    }
    out
}

/// For each loss term of a step, the module gradient norms of that term alone, as a JSON object
/// `{term: {module: norm}}` (empty for a term that reaches no trained module). `loss_of` recomputes the step's loss (a backward consumes its graph), once
/// per term.
pub fn term_grad_norms(model: &MvmpHmr, loss_of: impl Fn(&MvmpHmr) -> StepLoss) -> Value {
    let mut first = Some(loss_of(model));
    let names: Vec<&'static str> = first
        .iter()
        .flat_map(|l| l.terms.iter().map(|t| t.0))
        .collect();
    let mut out = serde_json::Map::new();
    for (i, name) in names.into_iter().enumerate() {
        let loss = first.take().unwrap_or_else(|| loss_of(model));
        let term = loss
            .terms
            .into_iter()
            .nth(i)
            .expect("the same terms every time")
            .1;
        // A term no trained module feeds (its inputs fixed) has no graph to go back through.
        if !term.is_tracked() {
            out.insert(name.to_string(), json!({}));
            continue;
        }
        let norms = module_grad_norms(model, &term.backward());
        let obj: serde_json::Map<String, Value> = norms
            .into_iter()
            .map(|(k, v)| (k.to_string(), json!(v)))
            .collect();
        out.insert(name.to_string(), Value::Object(obj));
    }
    Value::Object(out)
}
