//! Evaluation drivers: a predictor scored on a dataset split (the MVMP-HMR layout through its frame
//! dataset, Panoptic and Human3.6M through their joint-annotated sequences), the reference baselines, and
//! SMPL-X pseudo-ground-truth meshes for joint-annotated data.
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_REGRESSED, REGRESSED_TO_JOINT};
use std::path::{Path, PathBuf};

use burn::data::dataloader::batcher::Batcher;
use burn::tensor::{Device, Tensor};

use mvmp_data::dataset::{FrameDataset, read_frame_images};
use mvmp_data::loader::{FrameBatch, FrameBatcher, Split, ViewChoice};
use mvmp_data::mean::{MeanAccumulator, MeanParams};
use mvmp_data::sequence::{FramePeople, Sequence};
use mvmp_geom::Camera;
use mvmp_infer::{InferError, PersonPrediction, Predictor};
use mvmp_smplx::people::read_people_npz;
use mvmp_smplx::{SmplxLayer, SmplxParams, regressed_to_full_pose};

use crate::joint_sets::JointSet;
use crate::{Evaluator, PersonPose, match_people};

/// A prediction as an eval pose (joints and mesh, its detection score).
pub fn pose_of(p: &PersonPrediction) -> PersonPose {
    PersonPose {
        joints: p.joints.iter().map(|q| q.map(|x| x as f64)).collect(),
        vertices: Some(p.vertices.iter().map(|q| q.map(|x| x as f64)).collect()),
        score: p.score as f64,
        valid: None,
    }
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

/// The people's joints picked to `set`; people with too few joints for it are an error naming `what`
/// and the frame, not an index out of bounds.
fn pick_joints(
    people: Vec<PersonPose>,
    set: JointSet,
    frame: &Path,
    what: &str,
) -> Result<Vec<PersonPose>, InferError> {
    let need = set.smplx_indices().into_iter().max().map_or(0, |m| m + 1);
    people
        .into_iter()
        .map(|mut p| {
            if p.joints.len() < need {
                return Err(InferError::file(
                    frame,
                    format!(
                        "the {what} hold {} joints per person; the joint set {} needs {need}",
                        p.joints.len(),
                        set.name()
                    ),
                ));
            }
            p.joints = set.select(&p.joints);
            Ok(p)
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
    pub joints: JointSet,
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
    mut predict: impl FnMut(usize, usize, &FrameBatch) -> Result<Vec<PersonPose>, InferError>,
) -> Result<Evaluator, InferError> {
    let mut ds = FrameDataset::open(
        data,
        opts.split,
        ViewChoice::Fixed((0..opts.views).collect()),
        image_size,
    )?;
    let layout = ds
        .layout()
        .expect("a dataset opened from a layout keeps it");
    let body = layout.body_model()?;
    let body_name = layout.index.body_model.clone();
    ds.expect_joints(body.num_output_joints(), &body_name);
    let batcher = FrameBatcher::with_vertices(body);
    let n = match opts.max_frames {
        0 => ds.len(),
        m => m.min(ds.len()),
    };
    let mut ev = Evaluator::new(opts.gate);
    ev.root = opts.joints.root();
    for i in 0..n {
        let batch = batcher.batch(vec![ds.load(i)?], device);
        let name = &batch.names[0];
        let frame = data.join(&name.0).join(&name.1);
        let poses = pick_joints(predict(i, n, &batch)?, opts.joints, &frame, "predictions")?;
        let gt = pick_joints(
            ground_truth(&batch).remove(0),
            opts.joints,
            &frame,
            "annotations",
        )?;
        ev.add_frame(&batch.names[0].0, &poses, &gt);
    }
    Ok(ev)
}

/// Score the predictor on a dataset split. `each` sees every frame's predictions (for saving them).
pub fn evaluate(
    pred: &Predictor,
    data: &Path,
    opts: &EvalOptions,
    mut each: impl FnMut(usize, usize, FramePredictions) -> Result<(), InferError>,
) -> Result<Evaluator, InferError> {
    evaluate_frames(
        data,
        opts,
        pred.cfg().image_size,
        &pred.device,
        |i, n, batch| {
            let people = pred
                .predict(batch.images.clone(), &batch.cameras, &batch.letterboxes)
                .remove(0);
            let poses = people.iter().map(pose_of).collect();
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

/// The decoder's parameter vector `[PARAM_DIM]` of a data mean: its rotations in the regressed order, its
/// betas and expression, except the global orientation, which stays the default upright one (headings are
/// spread round the circle, so their mean says nothing).
pub fn mean_vector(m: &MeanParams, device: &Device) -> Tensor<1> {
    let global = mvmp_geom::rotation::y_up_to_z_up();
    let rotations: Vec<[f32; 9]> = REGRESSED_TO_JOINT
        .iter()
        .enumerate()
        .map(|(i, &j)| match i {
            0 => std::array::from_fn(|k| global[(k / 3, k % 3)] as f32),
            _ => m.rotations[j].map(|x| x as f32),
        })
        .collect();
    mvmp_decoder::params_vector(
        &rotations,
        &m.betas.map(|x| x as f32),
        &m.expression.map(|x| x as f32),
        device,
    )
}

/// The mean parameters of a dataset's training split (`None` when it has no people there).
pub fn training_mean(data: &Path) -> Result<Option<MeanParams>, InferError> {
    let layout = mvmp_data::DatasetLayout::open(data)?;
    let frames = mvmp_data::loader::split_frames(&layout, Split::Train)?;
    let mut acc = MeanAccumulator::default();
    acc.add_frames(&layout, &frames)?;
    Ok(acc.finish())
}

/// The parameters of the mean-pose reference on a dataset: its training split's mean ([`mean_vector`])
/// and how many people it is over; without people there, the untrained decoder's parameters and 0.
pub fn reference_mean(data: &Path, device: &Device) -> Result<(Tensor<1>, usize), InferError> {
    Ok(match training_mean(data)? {
        Some(m) => (mean_vector(&m, device), m.people),
        None => (mvmp_decoder::mean_params(device), 0),
    })
}

/// The reference baseline "mean pose at the ground-truth pelvis": the parameters `mean` `[PARAM_DIM]`
/// (the training data's mean, [`mean_vector`], or the untrained decoder's) placed upright at each
/// ground-truth pelvis, facing the model's default direction. What a model must beat to show that it
/// reads pose from the images.
pub fn mean_pose_at(layer: &SmplxLayer, mean: &Tensor<1>, pelvis: &[[f32; 3]]) -> Vec<PersonPose> {
    let n = pelvis.len();
    if n == 0 {
        return Vec::new();
    }
    let device = layer.device();
    let mean = mean.clone().to_device(device);
    let r6 = mean
        .clone()
        .narrow(0, 0, NUM_REGRESSED * 6)
        .reshape([1, NUM_REGRESSED * 6])
        .repeat_dim(0, n);
    let rot = mvmp_geom::rotation::rot6d_to_matrix(r6.reshape([n * NUM_REGRESSED, 6])).reshape([
        n,
        NUM_REGRESSED,
        3,
        3,
    ]);
    let betas = mean
        .clone()
        .narrow(0, NUM_REGRESSED * 6, NUM_BETAS)
        .reshape([1, NUM_BETAS])
        .repeat_dim(0, n);
    let expr = mean
        .narrow(0, NUM_REGRESSED * 6 + NUM_BETAS, NUM_EXPRESSION)
        .reshape([1, NUM_EXPRESSION])
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

/// SMPL-X pseudo-ground-truth for joint-annotated data: fits in infer's layout
/// (`dir/<sequence>/<frame>/people.npz`, the standard smplx keys), posed with `layer` (the body model the
/// fits use). Each annotated person takes the fit whose pelvis is nearest its root joint, within `gate`
/// metres. Training uses the fits as SMPL-X targets; evaluation uses their meshes for PVE and PA-PVE.
#[derive(Clone)]
pub struct PseudoGt {
    pub dir: PathBuf,
    pub layer: SmplxLayer,
    pub gate: f64,
}

/// One annotated person's matched fit.
#[derive(Debug, Clone)]
pub struct Fit {
    pub params: SmplxParams,
    /// The posed fit: joints (the pelvis first) and vertices in the world.
    pub posed: PersonPose,
}

impl PseudoGt {
    /// The fit of each annotated person of `sequence`/`frame` (by its root joint `roots`), if one is within
    /// the gate. A frame without `people.npz` is an error: every frame read this way needs its fits.
    pub fn fits(
        &self,
        sequence: &str,
        frame: &str,
        roots: &[[f64; 3]],
    ) -> Result<Vec<Option<Fit>>, InferError> {
        let path = self.dir.join(sequence).join(frame).join("people.npz");
        if !path.is_file() {
            return Err(InferError::file(
                &path,
                "no pseudo-ground-truth for this frame (every frame read with pseudo-ground-truth needs one)",
            ));
        }
        let stored = read_people_npz(&path)?;
        let mut out = vec![None; roots.len()];
        if stored.is_empty() || roots.is_empty() {
            return Ok(out);
        }
        let fits: Vec<(SmplxParams, f64)> =
            stored.into_iter().map(|s| (s.params, s.score)).collect();
        let posed = pose_params(&self.layer, &fits);
        let pelvis: Vec<[f64; 3]> = posed.iter().map(|p| p.joints[0]).collect();
        for (fi, gi) in match_people(&pelvis, roots, self.gate) {
            out[gi] = Some(Fit {
                params: fits[fi].0.clone(),
                posed: posed[fi].clone(),
            });
        }
        Ok(out)
    }
}

/// What the pseudo-ground-truth covered.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PseudoGtCount {
    /// Annotated people given a pseudo-ground-truth mesh, and all annotated people.
    pub with_mesh: usize,
    pub people: usize,
}

/// Score `pred` on sequences read in place whose ground truth is joints of `set` (the predicted SMPL-X
/// joints are mapped to it), matched on the set's root joint: Panoptic (`JointSet::Panoptic15`, sequences
/// from `mvmp_data::sources::open_panoptic`) and Human3.6M (`JointSet::H36m17`, `open_h36m`). PVE and
/// PA-PVE are computed only with pseudo-ground-truth meshes (`pseudo`), for the people that have one. At
/// most `max_frames` frames (0: all), in sequence order; `each(i, n)` after every frame.
pub fn evaluate_joint_sequences(
    pred: &Predictor,
    seqs: &[Box<dyn Sequence>],
    set: JointSet,
    max_frames: usize,
    gate: f64,
    pseudo: Option<&PseudoGt>,
    mut each: impl FnMut(usize, usize),
) -> Result<(Evaluator, PseudoGtCount), InferError> {
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
        return Err(InferError::file(
            &p.dir,
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
        let sf = seq.frame(fi)?;
        let images = read_frame_images(&sf.images, cams)?;
        let people = pred.predict_images(&images, cams)?;
        let poses = people
            .iter()
            .map(|p| {
                let mut pose = pose_of(p);
                if pseudo.is_none() {
                    pose.vertices = None;
                }
                pose
            })
            .collect();
        let frame = PathBuf::from(format!("{} frame {}", seq.name(), seq.frame_key(fi)));
        let poses = pick_joints(poses, set, &frame, "predictions")?;
        let mut gt: Vec<PersonPose> = annotated_joints(sf.people, set)
            .into_iter()
            .map(|p| PersonPose {
                joints: p.joints,
                vertices: None,
                score: 1.0,
                valid: Some(p.valid),
            })
            .collect();
        if let Some(p) = pseudo {
            let roots: Vec<[f64; 3]> = gt.iter().map(|g| g.joints[set.root()]).collect();
            for (g, fit) in gt
                .iter_mut()
                .zip(p.fits(&seq.name(), &seq.frame_key(fi), &roots)?)
            {
                g.vertices = fit.and_then(|f| f.posed.vertices);
            }
            count.people += gt.len();
            count.with_mesh += gt.iter().filter(|g| g.vertices.is_some()).count();
        }
        ev.add_frame(&seq.name(), &poses, &gt);
        each(i, n);
    }
    Ok((ev, count))
}

/// A frame's people as joints of `set`: a joint set's as annotated, an SMPL-X person's picked from its
/// joints (every one annotated).
fn annotated_joints(
    people: FramePeople,
    set: JointSet,
) -> Vec<mvmp_data::sequence::AnnotatedPerson> {
    match people {
        FramePeople::Joints(_, people) => people,
        FramePeople::Smplx(people) => people
            .into_iter()
            .map(|p| {
                let joints = set.select(&p.joints_3d);
                mvmp_data::sequence::AnnotatedPerson {
                    id: p.id as i64,
                    valid: vec![true; joints.len()],
                    joints,
                }
            })
            .collect(),
    }
}
