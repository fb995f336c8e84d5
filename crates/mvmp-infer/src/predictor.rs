//! The predictor: a trained model in inference mode with its config and body model; images and cameras
//! in, people in the world out.
use std::path::Path;
use std::sync::Arc;

use burn::module::Module;
use burn::tensor::{Device, Tensor};

use mvmp_fusion::Root;
use mvmp_geom::rotation::matrix_to_axis_angle;
use mvmp_geom::{Camera, Letterbox};
use mvmp_model::{Detection, ModelConfig, MvmpHmr, RigGrids};
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS, NUM_REGRESSED};
use mvmp_smplx::people::StoredPerson;
use mvmp_smplx::{BodyModel, SmplxLayer, SmplxParams, regressed_to_full_pose};

use crate::InferError;
use crate::run_files;

/// One predicted person in the world.
#[derive(Debug, Clone, PartialEq)]
pub struct PersonPrediction {
    /// Root likelihood of the detection.
    pub score: f32,
    /// 55 x 3 axis-angle, model joint order.
    pub pose: Vec<f32>,
    pub betas: [f32; NUM_BETAS],
    pub expression: [f32; NUM_EXPRESSION],
    /// The pelvis in the world (T_wld).
    pub pelvis: [f32; 3],
    /// smplx's `transl` (added to the model origin): the pelvis minus the shaped rest pelvis.
    pub transl: [f32; 3],
    /// The 127 joints and the vertices in the world.
    pub joints: Vec<[f32; 3]>,
    pub vertices: Vec<[f32; 3]>,
}

impl PersonPrediction {
    /// The parameters under the standard smplx keys.
    pub fn params(&self) -> SmplxParams {
        let f = |v: &[f32]| v.iter().map(|&x| x as f64).collect::<Vec<_>>();
        SmplxParams::from_full_pose(
            &f(&self.pose),
            &f(&self.betas),
            &f(&self.expression),
            self.transl.map(|x| x as f64),
        )
    }

    /// The person as `people.npz` stores it.
    pub fn stored(&self) -> StoredPerson {
        StoredPerson {
            params: self.params(),
            score: self.score as f64,
            pelvis: Some(self.pelvis.map(|x| x as f64)),
        }
    }
}

/// A model ready to predict (inference mode, no autodiff) with its config and body model.
pub struct Predictor {
    /// The network on the plain device, with its body model.
    pub model: MvmpHmr,
    /// The model's body layer on `device`.
    pub layer: Arc<SmplxLayer>,
    pub device: Device,
}

impl Predictor {
    /// The model of a run directory (final weights, else the newest checkpoint). Returns the weights file.
    pub fn from_run(
        root: &Path,
        device: &Device,
    ) -> Result<(Predictor, std::path::PathBuf), InferError> {
        let cfg = run_files::model_config(root)?;
        let weights = run_files::weights(root)?;
        let mut model = cfg.init(device);
        load_weights(&mut model, &weights)?;
        let body = mvmp_data::layout::load_body_model(&cfg.body_model, root)?;
        Ok((Predictor::new(model, body, device), weights))
    }

    /// `model` (any device: it is taken off autodiff) posing people with `body` on `device`.
    pub fn new(model: MvmpHmr, body: BodyModel, device: &Device) -> Predictor {
        let model = model.valid().with_body(Arc::new(body));
        Predictor {
            layer: model.body_layer(device),
            model,
            device: device.clone(),
        }
    }

    /// The model's config (the one it was built from).
    pub fn cfg(&self) -> &ModelConfig {
        &self.model.config
    }

    /// Detected roots only (the detection branch), per batch item, best first.
    pub fn detect(
        &self,
        images: Tensor<5>,
        cameras: &[Vec<Camera>],
        letterboxes: &[Vec<Letterbox>],
    ) -> Vec<Vec<Root>> {
        self.detect_with_maps(images, cameras, letterboxes).0
    }

    /// [`Predictor::detect`] that also returns the detection branch's maps and the batch's grids.
    pub fn detect_with_maps(
        &self,
        images: Tensor<5>,
        cameras: &[Vec<Camera>],
        letterboxes: &[Vec<Letterbox>],
    ) -> (Vec<Vec<Root>>, Detection, Vec<RigGrids>) {
        let grids = RigGrids::for_batch(self.cfg(), cameras, letterboxes, &self.device);
        let det = self.model.detect(images, &grids);
        let roots = self
            .model
            .detect_roots(det.likelihood.clone(), det.offset.clone());
        (roots, det, grids)
    }

    /// People in one frame: one original image per camera (sizes as the cameras say), letterboxed to the
    /// model's input size and normalised here.
    pub fn predict_images(
        &self,
        images: &[image::RgbImage],
        cameras: &[Camera],
    ) -> Result<Vec<PersonPrediction>, InferError> {
        let s = self.cfg().image_size as usize;
        let lbs: Vec<Letterbox> = cameras
            .iter()
            .map(|c| Letterbox::new(c.width, c.height, self.cfg().image_size))
            .collect::<Result<_, _>>()?;
        let mut data = vec![0f32; images.len() * 3 * s * s];
        for (v, (img, lb)) in images.iter().zip(&lbs).enumerate() {
            mvmp_data::loader::letterbox_into(
                img,
                lb,
                &mut data[v * 3 * s * s..(v + 1) * 3 * s * s],
            );
        }
        let t = Tensor::<5>::from_data(
            burn::tensor::TensorData::new(data, [1, images.len(), 3, s, s]),
            &self.device,
        );
        Ok(self.predict(t, &[cameras.to_vec()], &[lbs]).remove(0))
    }

    /// People in each batch item of `images` `[B, V, 3, S, S]` seen by these cameras.
    pub fn predict(
        &self,
        images: Tensor<5>,
        cameras: &[Vec<Camera>],
        letterboxes: &[Vec<Letterbox>],
    ) -> Vec<Vec<PersonPrediction>> {
        let grids = RigGrids::for_batch(self.cfg(), cameras, letterboxes, &self.device);
        let out = self.model.forward(images, &grids, None);
        let [b, k, nv, _] = out.vertices.dims();
        let nj = out.joints.dims()[2];
        let n = b * k;
        let full = regressed_to_full_pose(out.rotmats.clone().reshape([n, NUM_REGRESSED, 3, 3]));
        let aa = matrix_to_axis_angle(full.reshape([n * NUM_JOINTS, 3, 3]));
        let vec =
            |t: Tensor<2>| -> Vec<f32> { t.into_data().convert::<f32>().try_into_vec().unwrap() };
        let aa = vec(aa.reshape([n, NUM_JOINTS * 3]));
        let betas = vec(out.betas.reshape([n, NUM_BETAS]));
        let expr = vec(out.expression.reshape([n, NUM_EXPRESSION]));
        let rest = self.layer.rest_joints(
            Tensor::from_data(
                burn::tensor::TensorData::new(betas.clone(), [n, NUM_BETAS]),
                &self.device,
            ),
            Tensor::from_data(
                burn::tensor::TensorData::new(expr.clone(), [n, NUM_EXPRESSION]),
                &self.device,
            ),
        );
        let rest = vec(rest.narrow(1, 0, 1).reshape([n, 3]));
        let transl = vec(out.transl.reshape([n, 3]));
        let joints = vec(out.joints.reshape([n, nj * 3]));
        let verts = vec(out.vertices.reshape([n, nv * 3]));
        let pts = |v: &[f32]| v.chunks(3).map(|c| [c[0], c[1], c[2]]).collect::<Vec<_>>();
        (0..b)
            .map(|bi| {
                out.detections[bi]
                    .iter()
                    .enumerate()
                    .take(k)
                    .map(|(ki, det)| {
                        let i = bi * k + ki;
                        let pelvis = [transl[i * 3], transl[i * 3 + 1], transl[i * 3 + 2]];
                        PersonPrediction {
                            score: det.score,
                            pose: aa[i * NUM_JOINTS * 3..(i + 1) * NUM_JOINTS * 3].to_vec(),
                            betas: betas[i * NUM_BETAS..(i + 1) * NUM_BETAS]
                                .try_into()
                                .unwrap(),
                            expression: expr[i * NUM_EXPRESSION..(i + 1) * NUM_EXPRESSION]
                                .try_into()
                                .unwrap(),
                            pelvis,
                            transl: std::array::from_fn(|a| pelvis[a] - rest[i * 3 + a]),
                            joints: pts(&joints[i * nj * 3..(i + 1) * nj * 3]),
                            vertices: pts(&verts[i * nv * 3..(i + 1) * nv * 3]),
                        }
                    })
                    .collect()
            })
            .collect()
    }
}

/// Load burnpack weights into a model, with an error naming the file.
pub fn load_weights(model: &mut MvmpHmr, path: &Path) -> Result<(), InferError> {
    let r = mvmp_io::checkpoint::load(model, path)?;
    if let Some(e) = r.errors.first() {
        return Err(InferError::file(
            path,
            format!(
                "{} tensors could not be applied (first: {e})",
                r.errors.len()
            ),
        ));
    }
    // Weights written before the decoder kept its mean parameters were trained from the default mean,
    // which a freshly made model already holds.
    let missing: Vec<&String> = r.missing.iter().filter(|k| *k != "decoder.mean").collect();
    if !missing.is_empty() {
        return Err(InferError::file(
            path,
            format!(
                "{} model tensors are missing from the weights (first: {}); was it written for another model config?",
                missing.len(),
                missing[0]
            ),
        ));
    }
    // Weights no training writes (NaN, infinite, absurdly large) would score and write meshes of NaN.
    mvmp_io::checkpoint::check_finite(model, path)?;
    Ok(())
}
