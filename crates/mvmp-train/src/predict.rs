//! Prediction with a trained model and scoring against a dataset split.
use std::path::Path;

use burn::data::dataloader::batcher::Batcher;
use burn::module::Module;
use burn::tensor::{Device, Tensor};

use mvmp_data::loader::{FrameBatch, FrameBatcher, FrameDataset, Split, ViewChoice};
use mvmp_data::sources::JointAnnotated;
use mvmp_eval::{Evaluator, PersonPose};
use mvmp_fusion::{Root, extract_roots};
use mvmp_geom::rotation::matrix_to_axis_angle;
use mvmp_geom::{Camera, Letterbox};
use mvmp_model::{ModelConfig, MvmpHmr, RigGrids};
use mvmp_smplx::names::NUM_JOINTS;
use mvmp_smplx::{BodyModel, SmplxLayer, SmplxParams, regressed_to_full_pose};

use crate::TrainError;
use crate::run::RunDir;

/// One predicted person in the world.
#[derive(Debug, Clone, PartialEq)]
pub struct PersonPrediction {
    /// Root likelihood of the detection.
    pub score: f32,
    /// 55 x 3 axis-angle, model joint order.
    pub pose: Vec<f32>,
    pub betas: [f32; 10],
    pub expression: [f32; 10],
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

    pub fn to_pose(&self) -> PersonPose {
        PersonPose {
            joints: self.joints.iter().map(|p| p.map(|x| x as f64)).collect(),
            vertices: Some(self.vertices.iter().map(|p| p.map(|x| x as f64)).collect()),
            score: self.score as f64,
            valid: None,
        }
    }
}

/// A model ready to predict (inference mode, no autodiff) with its config and body model.
pub struct Predictor {
    pub model: MvmpHmr,
    pub cfg: ModelConfig,
    pub layer: SmplxLayer,
    pub body: BodyModel,
    pub device: Device,
}

impl Predictor {
    /// The model of a run directory (final weights, else the newest checkpoint). Returns the weights file.
    pub fn from_run(
        root: &Path,
        device: &Device,
    ) -> Result<(Predictor, std::path::PathBuf), TrainError> {
        let (run, _, cfg) = RunDir::open(root)?;
        let weights = run.weights()?;
        let mut model = cfg.init(device);
        load_weights(&mut model, &weights)?;
        let body = mvmp_data::layout::load_body_model(&cfg.body_model, &run.root)?;
        Ok((Predictor::new(model, cfg, body, device), weights))
    }

    pub fn new(model: MvmpHmr, cfg: ModelConfig, body: BodyModel, device: &Device) -> Predictor {
        let layer = SmplxLayer::new(&body, device);
        Predictor::with_layer(model, cfg, body, layer, device)
    }

    /// As [`Predictor::new`] with a body layer already built for `device`.
    pub fn with_layer(
        model: MvmpHmr,
        cfg: ModelConfig,
        body: BodyModel,
        layer: SmplxLayer,
        device: &Device,
    ) -> Predictor {
        Predictor {
            model: model.valid(),
            cfg,
            layer,
            body,
            device: device.clone(),
        }
    }

    /// Detected roots only (the detection branch), per batch item, best first.
    pub fn detect(
        &self,
        images: Tensor<5>,
        cameras: &[Vec<Camera>],
        letterboxes: &[Vec<Letterbox>],
    ) -> Vec<Vec<Root>> {
        let grids: Vec<RigGrids> = cameras
            .iter()
            .zip(letterboxes)
            .map(|(c, l)| RigGrids::new(&self.cfg, c, l, &self.device))
            .collect();
        let det = self.model.detect(images, &grids);
        extract_roots(
            det.likelihood,
            Some(det.offset),
            &self.cfg.grid,
            self.cfg.max_people,
            self.cfg.root_threshold,
        )
    }

    /// People in one frame: one original image per camera (sizes as the cameras say), letterboxed to the
    /// model's input size and normalised here.
    pub fn predict_images(
        &self,
        images: &[image::RgbImage],
        cameras: &[Camera],
    ) -> Result<Vec<PersonPrediction>, TrainError> {
        let s = self.cfg.image_size as usize;
        let lbs: Vec<Letterbox> = cameras
            .iter()
            .map(|c| Letterbox::new(c.width, c.height, self.cfg.image_size))
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
        let grids: Vec<RigGrids> = cameras
            .iter()
            .zip(letterboxes)
            .map(|(c, l)| RigGrids::new(&self.cfg, c, l, &self.device))
            .collect();
        let out = self
            .model
            .forward(images, &grids, &self.cfg, &self.layer, None);
        let [b, k, nv, _] = out.vertices.dims();
        let nj = out.joints.dims()[2];
        let n = b * k;
        let full = regressed_to_full_pose(out.rotmats.clone().reshape([n, 53, 3, 3]));
        let aa = matrix_to_axis_angle(full.reshape([n * NUM_JOINTS, 3, 3]));
        let vec =
            |t: Tensor<2>| -> Vec<f32> { t.into_data().convert::<f32>().try_into_vec().unwrap() };
        let aa = vec(aa.reshape([n, NUM_JOINTS * 3]));
        let betas = vec(out.betas.reshape([n, 10]));
        let expr = vec(out.expression.reshape([n, 10]));
        let rest = self.layer.rest_joints(
            Tensor::from_data(
                burn::tensor::TensorData::new(betas.clone(), [n, 10]),
                &self.device,
            ),
            Tensor::from_data(
                burn::tensor::TensorData::new(expr.clone(), [n, 10]),
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
                            betas: betas[i * 10..i * 10 + 10].try_into().unwrap(),
                            expression: expr[i * 10..i * 10 + 10].try_into().unwrap(),
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
pub fn load_weights(model: &mut MvmpHmr, path: &Path) -> Result<(), TrainError> {
    let r = mvmp_backbone::import::load_native(model, path)?;
    if let Some(e) = r.errors.first() {
        return Err(TrainError::file(
            path,
            format!(
                "{} tensors could not be applied (first: {e})",
                r.errors.len()
            ),
        ));
    }
    if !r.missing.is_empty() {
        return Err(TrainError::file(
            path,
            format!(
                "{} model tensors are missing from the weights (first: {}); was it written for another model config?",
                r.missing.len(),
                r.missing[0]
            ),
        ));
    }
    Ok(())
}

/// Ground truth of a batch item as eval poses (joints and, when the batch has them, vertices).
pub fn ground_truth(batch: &FrameBatch) -> Vec<Vec<PersonPose>> {
    let [b, p, j, _] = batch.joints_3d.dims();
    let j3: Vec<f32> = batch
        .joints_3d
        .to_data()
        .convert::<f32>()
        .try_into_vec()
        .unwrap();
    let verts: Option<(usize, Vec<f32>)> = batch.vertices.as_ref().map(|v| {
        (
            v.dims()[2],
            v.to_data().convert::<f32>().try_into_vec().unwrap(),
        )
    });
    (0..b)
        .map(|bi| {
            (0..batch.counts[bi])
                .map(|pi| {
                    let k = bi * p + pi;
                    let joints = (0..j)
                        .map(|ji| std::array::from_fn(|a| j3[(k * j + ji) * 3 + a] as f64))
                        .collect();
                    let vertices = verts.as_ref().map(|(nv, v)| {
                        (0..*nv)
                            .map(|vi| std::array::from_fn(|a| v[(k * nv + vi) * 3 + a] as f64))
                            .collect()
                    });
                    PersonPose {
                        joints,
                        vertices,
                        score: 1.0,
                        valid: None,
                    }
                })
                .collect()
        })
        .collect()
}

/// Options of [`evaluate`].
#[derive(Debug, Clone)]
pub struct EvalOptions {
    pub split: Split,
    /// The first N cameras of each rig.
    pub views: usize,
    /// Frames to score (the first N of the split; 0 = all).
    pub max_frames: usize,
    pub gate: f64,
    /// The joints MPJPE is taken on (SMPL-X's 127, or a dataset's set through the documented mapping).
    pub joints: mvmp_eval::joint_sets::JointSet,
}

/// One scored frame's predictions.
pub struct FramePredictions {
    pub scene: String,
    pub frame: String,
    pub people: Vec<PersonPrediction>,
    pub cameras: Vec<Camera>,
}

/// Score any predictor on a dataset split: `predict` returns the people of a one-frame batch.
pub fn evaluate_frames(
    data: &Path,
    opts: &EvalOptions,
    image_size: u32,
    device: &Device,
    mut predict: impl FnMut(usize, usize, &FrameBatch) -> Result<Vec<PersonPose>, TrainError>,
) -> Result<Evaluator, TrainError> {
    let ds = FrameDataset::open(
        data,
        opts.split,
        ViewChoice::Fixed((0..opts.views).collect()),
        image_size,
    )?;
    let batcher = FrameBatcher::with_vertices(ds.layout().body_model()?);
    let n = match opts.max_frames {
        0 => ds.frames().len(),
        m => m.min(ds.frames().len()),
    };
    let mut ev = Evaluator::new(opts.gate);
    ev.root = opts.joints.root();
    let pick = |mut p: PersonPose| {
        p.joints = opts.joints.select(&p.joints);
        p
    };
    for i in 0..n {
        let batch = batcher.batch(vec![ds.load(i)?], device);
        let poses: Vec<PersonPose> = predict(i, n, &batch)?.into_iter().map(pick).collect();
        let gt: Vec<PersonPose> = ground_truth(&batch)
            .remove(0)
            .into_iter()
            .map(pick)
            .collect();
        ev.add_frame(&batch.names[0].0, &poses, &gt);
    }
    Ok(ev)
}

/// Score the predictor on a dataset split. `each` sees every frame's predictions (for saving them).
pub fn evaluate(
    pred: &Predictor,
    data: &Path,
    opts: &EvalOptions,
    mut each: impl FnMut(usize, usize, FramePredictions) -> Result<(), TrainError>,
) -> Result<Evaluator, TrainError> {
    evaluate_frames(
        data,
        opts,
        pred.cfg.image_size,
        &pred.device,
        |i, n, batch| {
            let people = pred
                .predict(batch.images.clone(), &batch.cameras, &batch.letterboxes)
                .remove(0);
            let poses = people.iter().map(PersonPrediction::to_pose).collect();
            let (scene, frame) = batch.names[0].clone();
            each(
                i,
                n,
                FramePredictions {
                    scene,
                    frame,
                    people,
                    cameras: batch.cameras[0].clone(),
                },
            )?;
            Ok(poses)
        },
    )
}

/// Pose stored parameters (smplx `transl` meaning) into eval poses with a body layer.
pub fn pose_params(layer: &SmplxLayer, people: &[(SmplxParams, f64)]) -> Vec<PersonPose> {
    if people.is_empty() {
        return Vec::new();
    }
    let bodies: Vec<SmplxParams> = people.iter().map(|p| p.0.clone()).collect();
    let t = mvmp_smplx::params::ParamTensors::from_params(&bodies, layer.device());
    let out = layer.forward_axis_angle(
        t.pose,
        t.betas,
        t.expression,
        t.transl,
        mvmp_smplx::Translation::Standard,
    );
    to_poses(out.joints, out.vertices, people.iter().map(|p| p.1))
}

fn to_poses(
    joints: Tensor<3>,
    vertices: Tensor<3>,
    scores: impl Iterator<Item = f64>,
) -> Vec<PersonPose> {
    let [n, nj, _] = joints.dims();
    let nv = vertices.dims()[1];
    let j: Vec<f32> = joints.into_data().convert::<f32>().try_into_vec().unwrap();
    let v: Vec<f32> = vertices
        .into_data()
        .convert::<f32>()
        .try_into_vec()
        .unwrap();
    scores
        .take(n)
        .enumerate()
        .map(|(i, score)| PersonPose {
            joints: (0..nj)
                .map(|k| std::array::from_fn(|a| j[(i * nj + k) * 3 + a] as f64))
                .collect(),
            vertices: Some(
                (0..nv)
                    .map(|k| std::array::from_fn(|a| v[(i * nv + k) * 3 + a] as f64))
                    .collect(),
            ),
            score,
            valid: None,
        })
        .collect()
}

/// The reference baseline "mean pose at the ground-truth pelvis": the decoder's initial parameters (mean
/// pose, upright, facing the model's default direction; zero shape and expression) placed at each
/// ground-truth pelvis. What a model must beat to show that it reads pose from the images.
pub fn mean_pose_at(layer: &SmplxLayer, pelvis: &[[f32; 3]]) -> Vec<PersonPose> {
    let n = pelvis.len();
    if n == 0 {
        return Vec::new();
    }
    let device = layer.device();
    let mean = mvmp_decoder::queries::mean_params(device); // [53*6 + 10 + 10]
    let r6 = mean
        .clone()
        .narrow(0, 0, 53 * 6)
        .reshape([1, 53 * 6])
        .repeat_dim(0, n);
    let rot = mvmp_geom::rotation::rot6d_to_matrix(r6.reshape([n * 53, 6])).reshape([n, 53, 3, 3]);
    let betas = mean
        .clone()
        .narrow(0, 53 * 6, 10)
        .reshape([1, 10])
        .repeat_dim(0, n);
    let expr = mean
        .narrow(0, 53 * 6 + 10, 10)
        .reshape([1, 10])
        .repeat_dim(0, n);
    let flat: Vec<f32> = pelvis.iter().flatten().copied().collect();
    let transl = Tensor::from_data(burn::tensor::TensorData::new(flat, [n, 3]), device);
    let out = layer.forward(
        regressed_to_full_pose(rot),
        betas,
        expr,
        transl,
        mvmp_smplx::Translation::Pelvis,
    );
    to_poses(out.joints, out.vertices, std::iter::repeat(1.0))
}

/// SMPL-X pseudo-ground-truth meshes for a joint-annotated dataset: `dir/<sequence>/<frame key>/people.npz`
/// (infer's `people.npz` layout: the standard smplx keys), posed with `layer` (the body model the fits
/// use). Each annotated person takes the mesh whose pelvis is nearest its root joint, within the gate.
pub struct PseudoGt<'a> {
    pub dir: &'a Path,
    pub layer: &'a SmplxLayer,
}

/// What the pseudo-ground-truth covered.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PseudoGtCount {
    /// Annotated people given a pseudo-ground-truth mesh, and all annotated people.
    pub with_mesh: usize,
    pub people: usize,
}

/// Score `pred` on sequences read in place whose ground truth is joints of `set` (the predicted SMPL-X
/// joints are mapped to it), matched on the set's root joint. PVE and PA-PVE are computed only with
/// pseudo-ground-truth meshes (`pseudo`), for the people that have one. At most `max_frames` frames (0:
/// all), in sequence order; `each(i, n)` after every frame.
#[allow(clippy::too_many_arguments)]
pub fn evaluate_joint_sequences(
    pred: &Predictor,
    seqs: &[Box<dyn JointAnnotated>],
    set: mvmp_eval::joint_sets::JointSet,
    max_frames: usize,
    gate: f64,
    pseudo: Option<&PseudoGt>,
    mut each: impl FnMut(usize, usize),
) -> Result<(Evaluator, PseudoGtCount), TrainError> {
    let mut frames: Vec<(usize, usize)> = seqs
        .iter()
        .enumerate()
        .flat_map(|(si, s)| (0..s.len()).map(move |fi| (si, fi)))
        .collect();
    if max_frames > 0 {
        frames.truncate(max_frames);
    }
    if let Some(p) = pseudo
        && p.layer.num_vertices() != pred.layer.num_vertices()
    {
        return Err(TrainError::file(
            p.dir,
            format!(
                "the pseudo-ground-truth body model has {} vertices but the model predicts meshes of {}; \
                 PVE needs one topology (pass the body model the run uses)",
                p.layer.num_vertices(),
                pred.layer.num_vertices()
            ),
        ));
    }
    let mut ev = Evaluator::new(gate);
    ev.root = set.root();
    let mut count = PseudoGtCount::default();
    let n = frames.len();
    for (i, &(si, fi)) in frames.iter().enumerate() {
        let seq = &seqs[si];
        let cams = seq.cameras();
        let images = mvmp_data::sources::read_frame_images(&seq.images(fi), cams)?;
        let people = pred.predict_images(&images, cams)?;
        let poses: Vec<PersonPose> = people
            .iter()
            .map(|p| {
                let mut pose = p.to_pose();
                pose.joints = set.select(&pose.joints);
                if pseudo.is_none() {
                    pose.vertices = None;
                }
                pose
            })
            .collect();
        let mut gt: Vec<PersonPose> = seq
            .people(fi)?
            .into_iter()
            .map(|p| PersonPose {
                joints: p.joints,
                vertices: None,
                score: 1.0,
                valid: Some(p.valid),
            })
            .collect();
        if let Some(p) = pseudo {
            let path = p
                .dir
                .join(seq.name())
                .join(seq.frame_key(fi))
                .join("people.npz");
            if !path.exists() {
                return Err(TrainError::file(
                    &path,
                    "no pseudo-ground-truth for this frame (every scored frame needs one)",
                ));
            }
            let stored = crate::output::read_people_npz(&path)?;
            let fits = pose_params(
                p.layer,
                &stored
                    .into_iter()
                    .map(|s| (s.params, s.score))
                    .collect::<Vec<_>>(),
            );
            let fit_roots: Vec<[f64; 3]> = fits.iter().map(|f| f.joints[0]).collect();
            let gt_roots: Vec<[f64; 3]> = gt.iter().map(|g| g.joints[set.root()]).collect();
            for (fi_, gi) in mvmp_eval::match_people(&fit_roots, &gt_roots, gate) {
                gt[gi].vertices = fits[fi_].vertices.clone();
            }
            count.people += gt.len();
            count.with_mesh += gt.iter().filter(|g| g.vertices.is_some()).count();
        }
        ev.add_frame(&seq.name(), &poses, &gt);
        each(i, n);
    }
    Ok((ev, count))
}

/// Score `pred` on CMU Panoptic sequences read in place (`root/<sequence>/...`): the VoxelPose protocol on
/// the 15 evaluation joints ([`JointSet::Panoptic15`](mvmp_eval::joint_sets::JointSet)), matched on the
/// body centre. Panoptic has no meshes: PVE and PA-PVE need SMPL-X pseudo-ground-truth (`pseudo`).
#[allow(clippy::too_many_arguments)]
pub fn evaluate_panoptic(
    pred: &Predictor,
    root: &Path,
    sequences: &[String],
    stride: usize,
    cameras: &[&str],
    max_frames: usize,
    gate: f64,
    pseudo: Option<&PseudoGt>,
    each: impl FnMut(usize, usize),
) -> Result<(Evaluator, PseudoGtCount), TrainError> {
    let seqs = mvmp_data::sources::open_panoptic(root, sequences, cameras, stride)?;
    evaluate_joint_sequences(
        pred,
        &seqs,
        mvmp_eval::joint_sets::JointSet::Panoptic15,
        max_frames,
        gate,
        pseudo,
        each,
    )
}

/// Score `pred` on Human3.6M read in place (`mvmp_data::h36m`): every action of `subjects` with the named
/// cameras, every `stride`-th frame, MPJPE on the 17 joints
/// ([`JointSet::H36m17`](mvmp_eval::joint_sets::JointSet)) in the world, matched on the pelvis.
#[allow(clippy::too_many_arguments)]
pub fn evaluate_h36m(
    pred: &Predictor,
    root: &Path,
    subjects: &[String],
    stride: usize,
    cameras: &[&str],
    max_frames: usize,
    gate: f64,
    pseudo: Option<&PseudoGt>,
    each: impl FnMut(usize, usize),
) -> Result<(Evaluator, PseudoGtCount), TrainError> {
    let seqs = mvmp_data::sources::open_h36m(root, subjects, cameras, stride)?;
    evaluate_joint_sequences(
        pred,
        &seqs,
        mvmp_eval::joint_sets::JointSet::H36m17,
        max_frames,
        gate,
        pseudo,
        each,
    )
}
