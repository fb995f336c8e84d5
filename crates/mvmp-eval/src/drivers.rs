//! Evaluation drivers: one scoring loop over the sequences of any dataset (MVMP-HMR scenes, Panoptic,
//! Human3.6M; [`evaluate_sequences`]) with a predictor, stored predictions or a reference baseline as the
//! prediction, ground-truth meshes posed from SMPL-X annotations or taken from pseudo-ground-truth fits.
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS, NUM_REGRESSED, REGRESSED_TO_JOINT};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use rayon::prelude::*;

use burn::tensor::{Device, Tensor, TensorData};

use mvmp_data::DatasetLayout;
use mvmp_data::dataset::{read_frame_images, smplx_values};
use mvmp_data::layout::{Person, check_joints};
use mvmp_data::loader::Split;
use mvmp_data::mean::{MeanAccumulator, MeanParams};
use mvmp_data::sequence::{FramePeople, MvmpScene, Sequence, SequenceFrame, frame_pairs};
use mvmp_geom::Camera;
use mvmp_infer::{InferError, PersonPrediction, Predictor};
use mvmp_smplx::people::read_people_npz;
use mvmp_smplx::{SmplxLayer, SmplxParams, regressed_to_full_pose};

use crate::joint_sets::JointSet;
use crate::truth_parts::{TruthPart, pose_with_truth};
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
    /// Parameter groups taken from the matched annotation before scoring (an error budget; empty for the
    /// model's own figures). SMPL-X annotations only.
    pub truth: Vec<TruthPart>,
}

/// One scored frame's predictions.
pub struct FramePredictions {
    pub scene: String,
    pub frame: String,
    pub people: Vec<PersonPrediction>,
    pub cameras: Vec<Camera>,
}

/// What scores a frame's people besides their annotations: the layer that poses SMPL-X ground truth
/// (with its body model's name: such people must hold the joints it outputs) and the pseudo-ground-truth
/// meshes of joint-annotated people.
#[derive(Clone, Default)]
pub struct Truth {
    pub body: Option<(SmplxLayer, String)>,
    pub pseudo: Option<PseudoGt>,
}

/// A frame as the scoring loop hands it to a predictor.
pub struct EvalFrame<'a> {
    pub sequence: &'a dyn Sequence,
    pub index: usize,
    pub frame: &'a SequenceFrame,
}

impl EvalFrame<'_> {
    /// The sequence's name and the frame's key (where predictions of it are stored).
    pub fn names(&self) -> (String, String) {
        (self.sequence.name(), self.sequence.frame_key(self.index))
    }

    /// The first `views` cameras.
    pub fn cameras(&self, views: usize) -> &[Camera] {
        let cams = self.sequence.cameras();
        &cams[..views.min(cams.len())]
    }

    /// The images of the first `views` cameras, each checked against its camera.
    pub fn images(&self, views: usize) -> Result<Vec<image::RgbImage>, InferError> {
        let cams = self.cameras(views);
        Ok(read_frame_images(&self.frame.images[..cams.len()], cams)?)
    }

    /// The annotated SMPL-X people; an error naming the frame for a joint-annotated one.
    pub fn smplx_people(&self) -> Result<&[Person], InferError> {
        match &self.frame.people {
            FramePeople::Smplx(people) => Ok(people),
            FramePeople::Joints(set, _) => Err(InferError::file(
                &self.frame.source,
                format!(
                    "annotated with {} joints, not SMPL-X parameters: --truth needs SMPL-X annotations",
                    set.name()
                ),
            )),
        }
    }

    /// Each annotated person's root: the SMPL-X pelvis, or the joint set's root joint.
    pub fn roots(&self) -> Vec<[f32; 3]> {
        match &self.frame.people {
            FramePeople::Smplx(people) => {
                people.iter().map(|p| p.pelvis.map(|x| x as f32)).collect()
            }
            FramePeople::Joints(set, people) => people
                .iter()
                .map(|p| p.joints[set.root()].map(|x| x as f32))
                .collect(),
        }
    }
}

/// The one scoring loop: every frame of `seqs` (at most `opts.max_frames`; 0 = all, in sequence order),
/// `predict`'s people against the annotated ones, on the joints of `opts.joints` (predicted SMPL-X joints
/// are mapped to a dataset's set), matched on that set's root. PVE and PA-PVE need ground-truth meshes:
/// SMPL-X people are posed with `truth.body`, joint-annotated ones take `truth.pseudo`'s fits.
/// `at_once` frames are loaded and predicted at a time, in parallel ([`frames_at_once`]); what `predict`
/// keeps of each (`T`) reaches `each` in frame order, with the frame's number and the count.
pub fn evaluate_sequences<T: Send>(
    seqs: &[Box<dyn Sequence>],
    truth: &Truth,
    opts: &EvalOptions,
    at_once: usize,
    predict: impl Fn(&EvalFrame) -> Result<(Vec<PersonPose>, T), InferError> + Sync,
    mut each: impl FnMut(usize, usize, T) -> Result<(), InferError>,
) -> Result<(Evaluator, PseudoGtCount), InferError> {
    for s in seqs {
        let n = s.cameras().len();
        if opts.views == 0 || opts.views > n {
            return Err(InferError::file(
                s.name(),
                format!(
                    "{} views requested, but the sequence has {n} cameras",
                    opts.views
                ),
            ));
        }
    }
    let mut frames = frame_pairs(seqs);
    if opts.max_frames > 0 {
        frames.truncate(opts.max_frames);
    }
    let mut ev = Evaluator::new(opts.gate);
    ev.root = opts.joints.root();
    let mut count = PseudoGtCount::default();
    let n = frames.len();
    let at_once = at_once.max(1);
    for (w, window) in frames.chunks(at_once).enumerate() {
        let scored: Vec<_> = window
            .par_iter()
            .map(|&(si, fi)| score_frame(seqs[si].as_ref(), fi, truth, opts, &predict))
            .collect();
        for (k, frame) in scored.into_iter().enumerate() {
            let f = frame?;
            count.with_mesh += f.count.with_mesh;
            count.people += f.count.people;
            each(w * at_once + k, n, f.kept)?;
            ev.add_frame(&f.scene, &f.poses, &f.gt);
        }
    }
    Ok((ev, count))
}

/// How many frames [`evaluate_sequences`] should score at once for a predictor on `device`: on flex
/// one per thread (a frame's forward leaves the other cores idle in its serial parts, and frames are
/// independent), elsewhere one.
pub fn frames_at_once(device: &Device) -> usize {
    match *device == Device::flex() {
        true => rayon::current_num_threads(),
        false => 1,
    }
}

/// One frame's part of [`evaluate_sequences`], in any order.
struct ScoredFrame<T> {
    scene: String,
    poses: Vec<PersonPose>,
    gt: Vec<PersonPose>,
    count: PseudoGtCount,
    kept: T,
}

fn score_frame<T>(
    sequence: &dyn Sequence,
    index: usize,
    truth: &Truth,
    opts: &EvalOptions,
    predict: &impl Fn(&EvalFrame) -> Result<(Vec<PersonPose>, T), InferError>,
) -> Result<ScoredFrame<T>, InferError> {
    let frame = sequence.frame(index)?;
    let at = EvalFrame {
        sequence,
        index,
        frame: &frame,
    };
    let mut count = PseudoGtCount::default();
    let (gt, meshes) = truth.people(&at, opts.joints, &mut count)?;
    let (mut poses, kept) = predict(&at)?;
    if !meshes {
        poses.iter_mut().for_each(|p| p.vertices = None);
    }
    let poses = pick_joints(poses, opts.joints, &frame.source, "predictions")?;
    Ok(ScoredFrame {
        scene: sequence.name(),
        poses,
        gt,
        count,
        kept,
    })
}

impl Truth {
    /// The annotated people of a frame as eval poses on `set`, and whether they can have meshes.
    fn people(
        &self,
        at: &EvalFrame,
        set: JointSet,
        count: &mut PseudoGtCount,
    ) -> Result<(Vec<PersonPose>, bool), InferError> {
        let source = &at.frame.source;
        match &at.frame.people {
            FramePeople::Smplx(people) => {
                let posed = match &self.body {
                    Some((layer, name)) => {
                        check_joints(people, layer.num_joints(), name)
                            .map_err(|what| InferError::file(source, what))?;
                        smplx_truth(layer, people)
                    }
                    None => people
                        .iter()
                        .map(|p| joints_pose(&p.joints_3d, None))
                        .collect(),
                };
                Ok((
                    pick_joints(posed, set, source, "annotations")?,
                    self.body.is_some(),
                ))
            }
            FramePeople::Joints(jset, people) => {
                let mut gt: Vec<PersonPose> = people
                    .iter()
                    .map(|p| joints_pose(&p.joints, Some(p.valid.clone())))
                    .collect();
                if let Some(pseudo) = &self.pseudo {
                    let roots: Vec<[f64; 3]> = gt.iter().map(|g| g.joints[jset.root()]).collect();
                    let (name, key) = at.names();
                    for (g, fit) in gt.iter_mut().zip(pseudo.fits(&name, &key, &roots)?) {
                        g.vertices = fit.and_then(|f| f.posed.vertices);
                    }
                    count.people += gt.len();
                    count.with_mesh += gt.iter().filter(|g| g.vertices.is_some()).count();
                }
                Ok((gt, self.pseudo.is_some()))
            }
        }
    }
}

/// An annotated person's joints as an eval pose (no mesh).
fn joints_pose(joints: &[[f64; 3]], valid: Option<Vec<bool>>) -> PersonPose {
    PersonPose {
        joints: joints.to_vec(),
        vertices: None,
        score: 1.0,
        valid,
    }
}

/// SMPL-X people as eval poses: their annotated joints and their parameters' mesh, posed with the pelvis
/// placed at its annotated position (as training's ground truth is).
fn smplx_truth(layer: &SmplxLayer, people: &[Person]) -> Vec<PersonPose> {
    if people.is_empty() {
        return Vec::new();
    }
    let n = people.len();
    let values: Vec<_> = people.iter().map(smplx_values).collect();
    let device = layer.device();
    let t2 =
        |data: Vec<f32>, w: usize| Tensor::<2>::from_data(TensorData::new(data, [n, w]), device);
    let out = layer.forward_axis_angle(
        Tensor::from_data(
            TensorData::new(
                values.iter().flat_map(|v| v.0.clone()).collect(),
                [n, NUM_JOINTS, 3],
            ),
            device,
        ),
        t2(values.iter().flat_map(|v| v.1).collect(), NUM_BETAS),
        t2(values.iter().flat_map(|v| v.2).collect(), NUM_EXPRESSION),
        t2(
            people
                .iter()
                .flat_map(|p| p.pelvis.map(|x| x as f32))
                .collect(),
            3,
        ),
        mvmp_smplx::Translation::Pelvis,
    );
    to_poses(out.joints, out.vertices, std::iter::repeat(1.0))
        .into_iter()
        .zip(people)
        .map(|(posed, p)| PersonPose {
            joints: p.joints_3d.clone(),
            ..posed
        })
        .collect()
}

/// The scenes of an MVMP-HMR split and what scores them (the dataset's body model on `device`).
pub fn mvmp_split(
    data: &Path,
    split: Split,
    device: &Device,
) -> Result<(Vec<Box<dyn Sequence>>, Truth), InferError> {
    let layout = Arc::new(DatasetLayout::open(data)?);
    let layer = SmplxLayer::new(&layout.body_model()?, device);
    let name = layout.index.body_model.clone();
    let seqs = MvmpScene::sequences(layout, split)?;
    let truth = Truth {
        body: Some((layer, name)),
        pseudo: None,
    };
    Ok((seqs, truth))
}

/// The predictor's people in the first `views` cameras of a frame.
pub fn predict_frame(
    pred: &Predictor,
    views: usize,
    at: &EvalFrame,
) -> Result<Vec<PersonPrediction>, InferError> {
    pred.predict_images(&at.images(views)?, at.cameras(views))
}

/// Score the predictor on an MVMP-HMR dataset split. `each` sees every frame's predictions (for saving
/// them).
pub fn evaluate(
    pred: &Predictor,
    data: &Path,
    opts: &EvalOptions,
    mut each: impl FnMut(usize, usize, FramePredictions) -> Result<(), InferError>,
) -> Result<Evaluator, InferError> {
    let (seqs, truth) = mvmp_split(data, opts.split, &pred.device)?;
    let at_once = frames_at_once(&pred.device);
    let predict = |at: &EvalFrame| scored_frame(pred, opts, at);
    let (ev, _) = evaluate_sequences(&seqs, &truth, opts, at_once, predict, &mut each)?;
    Ok(ev)
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

pub(crate) fn to_poses(
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
/// from `mvmp_data::sources::open_panoptic`) and Human3.6M (`JointSet::H36m17`, `open_h36m`), every camera
/// the sequences were opened with. PVE and PA-PVE are computed only with pseudo-ground-truth meshes
/// (`pseudo`), for the people that have one. At most `max_frames` frames (0: all), in sequence order;
/// `each` sees every frame's predictions (for saving them).
pub fn evaluate_joint_sequences(
    pred: &Predictor,
    seqs: &[Box<dyn Sequence>],
    set: JointSet,
    max_frames: usize,
    gate: f64,
    pseudo: Option<&PseudoGt>,
    mut each: impl FnMut(usize, usize, FramePredictions) -> Result<(), InferError>,
) -> Result<(Evaluator, PseudoGtCount), InferError> {
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
    let opts = EvalOptions {
        split: Split::All,
        views: seqs.iter().map(|s| s.cameras().len()).min().unwrap_or(0),
        max_frames,
        gate,
        joints: set,
        truth: Vec::new(),
    };
    let truth = Truth {
        body: None,
        pseudo: pseudo.cloned(),
    };
    let at_once = frames_at_once(&pred.device);
    let predict = |at: &EvalFrame| scored_frame(pred, &opts, at);
    evaluate_sequences(seqs, &truth, &opts, at_once, predict, &mut each)
}

/// The predictor's people in a frame as eval poses, and the predictions they came from.
fn scored_frame(
    pred: &Predictor,
    opts: &EvalOptions,
    at: &EvalFrame,
) -> Result<(Vec<PersonPose>, FramePredictions), InferError> {
    let people = predict_frame(pred, opts.views, at)?;
    let poses = if opts.truth.is_empty() {
        people.iter().map(pose_of).collect()
    } else {
        let params: Vec<_> = people
            .iter()
            .map(|p| (p.params(), p.score as f64))
            .collect();
        let truth = at.smplx_people()?;
        pose_with_truth(&pred.layer, &params, truth, &opts.truth, opts.gate)
    };
    let (scene, frame) = at.names();
    let kept = FramePredictions {
        scene,
        frame,
        people,
        cameras: at.cameras(opts.views).to_vec(),
    };
    Ok((poses, kept))
}
