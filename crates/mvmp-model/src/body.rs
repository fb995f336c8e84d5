//! The body model a network poses its people with, as a layer on whichever device the network runs.
use std::sync::{Arc, Mutex};

use burn::tensor::Device;
use mvmp_smplx::{BodyModel, SmplxLayer};

/// A body model and the layers built from it, one per device (the autodiff device in training, the plain
/// one in validation and inference: only a plain CPU layer takes the fused skinning pass).
pub struct BodyLayers {
    model: Arc<BodyModel>,
    built: Mutex<Vec<Arc<SmplxLayer>>>,
}

impl BodyLayers {
    pub fn new(model: Arc<BodyModel>) -> Self {
        BodyLayers {
            model,
            built: Mutex::new(Vec::new()),
        }
    }

    pub fn model(&self) -> &Arc<BodyModel> {
        &self.model
    }

    /// The layer on `device` (with or without autodiff, as `device` is), built on first use.
    pub fn on(&self, device: &Device) -> Arc<SmplxLayer> {
        let same = |l: &SmplxLayer| {
            let d = l.device();
            d == device && d.is_autodiff() == device.is_autodiff()
        };
        let mut built = self.built.lock().unwrap_or_else(|e| e.into_inner());
        if let Some(l) = built.iter().find(|l| same(l)) {
            return l.clone();
        }
        let layer = Arc::new(SmplxLayer::new(&self.model, device));
        built.push(layer.clone());
        layer
    }
}

/// A copy shares the body model but builds its own layers: a model copied for validation (`valid()`)
/// then drops its plain-device layer with itself instead of keeping it through training.
impl Clone for BodyLayers {
    fn clone(&self) -> Self {
        BodyLayers::new(self.model.clone())
    }
}

impl std::fmt::Debug for BodyLayers {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "BodyLayers({} vertices, {} joints)",
            self.model.num_vertices(),
            self.model.num_output_joints()
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_layer_per_device_and_copies_build_their_own() {
        let layers = BodyLayers::new(Arc::new(mvmp_smplx::standin_model(0)));
        let plain = Device::flex();
        let ad = plain.clone().autodiff();
        let (a, b) = (layers.on(&plain), layers.on(&plain));
        assert!(Arc::ptr_eq(&a, &b));
        let c = layers.on(&ad);
        assert!(!Arc::ptr_eq(&a, &c));
        assert!(c.device().is_autodiff() && !a.device().is_autodiff());
        let copy = layers.clone();
        assert!(Arc::ptr_eq(copy.model(), layers.model()));
        assert!(!Arc::ptr_eq(&copy.on(&plain), &a));
    }
}
