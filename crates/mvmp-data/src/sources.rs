//! Training sources: MVMP-HMR (SMPL-X ground truth) and the joint-annotated datasets CMU Panoptic and
//! Human3.6M (3D joints only), read in place and served as one dataset of [`FrameSample`]s.
//!
//! A joint-annotated person becomes a sample person whose 127 joint slots hold the dataset's joints at the
//! SMPL-X joints they map to ([`JointSet`]), with a validity per slot (0 for every slot the dataset does not
//! annotate, and for annotated joints below Panoptic's confidence threshold), and no SMPL-X parameters
//! (`smplx == false`). The losses use this: parameter, vertex, orientation and density terms only for people
//! with SMPL-X, joint terms on valid slots, heatmaps only for the joints the source covers.
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use burn::data::dataset::{Dataset, DatasetError};
use nalgebra::{Vector2, Vector3};
use serde::{Deserialize, Serialize};

use crate::DataError;
use crate::augment::Photometric;
use crate::h36m::H36mSequence;
use crate::loader::{
    FrameDataset, FrameSample, PersonGt, Split, ViewChoice, draw_seed, letterbox_views,
    select_views,
};
use crate::panoptic::PanopticSequence;
use mvmp_geom::{Camera, Letterbox};
use mvmp_smplx::joint_sets::JointSet;
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS_WITH_LANDMARKS};

/// One annotated person of a joint-annotated frame, in the dataset's joint set (world metres).
#[derive(Debug, Clone, PartialEq)]
pub struct AnnotatedPerson {
    pub id: i64,
    pub joints: Vec<[f64; 3]>,
    /// Whether each joint is annotated.
    pub valid: Vec<bool>,
}

/// A sequence of a joint-annotated dataset read in place: its cameras, frames and people.
pub trait JointAnnotated: Send + Sync {
    /// The name reports group by (a sequence, or subject/action).
    fn name(&self) -> String;
    /// The cameras, in the order of each frame's images.
    fn cameras(&self) -> &[Camera];
    fn len(&self) -> usize;
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// The image of every camera at frame `i`.
    fn images(&self, i: usize) -> Vec<PathBuf>;
    /// Frame `i`'s name in file layouts (predictions, pseudo-ground-truth): `<name>/<frame key>/`.
    fn frame_key(&self, i: usize) -> String;
    /// The joint set of [`people`](Self::people).
    fn joint_set(&self) -> JointSet;
    /// The annotated people at frame `i`.
    fn people(&self, i: usize) -> Result<Vec<AnnotatedPerson>, DataError>;
}

impl JointAnnotated for PanopticSequence {
    fn name(&self) -> String {
        self.name.clone()
    }
    fn cameras(&self) -> &[Camera] {
        &self.rig.cameras
    }
    fn len(&self) -> usize {
        self.frames.len()
    }
    fn images(&self, i: usize) -> Vec<PathBuf> {
        self.frames[i].images.clone()
    }
    /// The 8-digit HD frame index of the file names.
    fn frame_key(&self, i: usize) -> String {
        self.frames[i].index.clone()
    }
    fn joint_set(&self) -> JointSet {
        JointSet::Panoptic15
    }
    /// The first 15 joints of people whose body centre is annotated; validity from the confidence.
    fn people(&self, i: usize) -> Result<Vec<AnnotatedPerson>, DataError> {
        use crate::panoptic::EVAL_JOINTS;
        Ok(PanopticSequence::people(self, &self.frames[i])?
            .into_iter()
            .map(|b| AnnotatedPerson {
                id: b.id,
                joints: b.joints[..EVAL_JOINTS].to_vec(),
                valid: (0..EVAL_JOINTS).map(|j| b.valid(j)).collect(),
            })
            .collect())
    }
}

impl JointAnnotated for H36mSequence {
    fn name(&self) -> String {
        H36mSequence::name(self)
    }
    fn cameras(&self) -> &[Camera] {
        &self.rig.cameras
    }
    fn len(&self) -> usize {
        self.frames.len()
    }
    fn images(&self, i: usize) -> Vec<PathBuf> {
        self.frames[i].images.clone()
    }
    /// The image number (6 digits, from 1) of the extracted video frames.
    fn frame_key(&self, i: usize) -> String {
        format!("{:06}", self.frames[i].row + 1)
    }
    fn joint_set(&self) -> JointSet {
        JointSet::H36m17
    }
    /// One subject per frame, every joint annotated.
    fn people(&self, i: usize) -> Result<Vec<AnnotatedPerson>, DataError> {
        Ok(vec![AnnotatedPerson {
            id: 0,
            joints: self.joints[i].to_vec(),
            valid: vec![true; self.joints[i].len()],
        }])
    }
}

/// Read and check the images of one frame against its cameras.
pub fn read_frame_images(
    paths: &[PathBuf],
    cameras: &[Camera],
) -> Result<Vec<image::RgbImage>, DataError> {
    (paths.iter().zip(cameras))
        .map(|(path, cam)| crate::check::read_view_image(path, cam))
        .collect()
}

/// The 127 SMPL-X joint slots a joint set fills.
pub fn covered_slots(set: JointSet) -> Vec<bool> {
    let mut cover = vec![false; NUM_JOINTS_WITH_LANDMARKS];
    for i in set.smplx_indices() {
        cover[i] = true;
    }
    cover
}

/// A joint-annotated person as a sample person: joints in their SMPL-X slots, 2D joints in each selected
/// view (network pixels; visible where annotated, in front of the camera and inside the image), no SMPL-X.
pub fn person_from_joints(
    p: &AnnotatedPerson,
    set: JointSet,
    cameras: &[Camera],
    letterboxes: &[Letterbox],
) -> PersonGt {
    let n = NUM_JOINTS_WITH_LANDMARKS;
    let mut joints_3d = vec![[0f32; 3]; n];
    let mut valid = vec![0f32; n];
    for ((&slot, j), &ok) in set.smplx_indices().iter().zip(&p.joints).zip(&p.valid) {
        if ok {
            joints_3d[slot] = j.map(|x| x as f32);
            valid[slot] = 1.0;
        }
    }
    let joints_2d = cameras
        .iter()
        .zip(letterboxes)
        .map(|(cam, lb)| {
            (0..n)
                .map(|k| {
                    if valid[k] == 0.0 {
                        return [0.0; 3];
                    }
                    let x = joints_3d[k];
                    let (uv, z) = cam.project(&Vector3::new(x[0] as f64, x[1] as f64, x[2] as f64));
                    let inside = z > 0.0
                        && uv.x >= 0.0
                        && uv.y >= 0.0
                        && uv.x < cam.width as f64
                        && uv.y < cam.height as f64;
                    if !inside {
                        return [0.0; 3];
                    }
                    let q = lb.apply(Vector2::new(uv.x, uv.y));
                    [q.x as f32, q.y as f32, 1.0]
                })
                .collect()
        })
        .collect();
    let root = p.joints[set.root()].map(|x| x as f32);
    PersonGt {
        id: p.id.max(0) as u32,
        pose: vec![0.0; mvmp_smplx::names::NUM_JOINTS * 3],
        betas: [0.0; NUM_BETAS],
        expression: [0.0; NUM_EXPRESSION],
        pelvis: root,
        joints_3d,
        joints_2d,
        joint_valid: valid,
        smplx: false,
    }
}

/// Gives the people of a joint-annotated sample SMPL-X ground truth from elsewhere (pseudo-ground-truth
/// fits), after the sample is loaded.
pub trait MeshSource: Send + Sync {
    fn attach(&self, sample: &mut FrameSample) -> Result<(), DataError>;
}

/// Training samples from joint-annotated sequences.
pub struct JointFrameDataset {
    seqs: Vec<Box<dyn JointAnnotated>>,
    frames: Vec<(usize, usize)>,
    views: ViewChoice,
    size: u32,
    epoch: AtomicU64,
    meshes: Option<std::sync::Arc<dyn MeshSource>>,
}

impl JointFrameDataset {
    /// Every frame of `seqs` (each must have the cameras `views` asks for). `label` names the source in
    /// errors.
    pub fn new(
        label: &str,
        seqs: Vec<Box<dyn JointAnnotated>>,
        views: ViewChoice,
        size: u32,
    ) -> Result<Self, DataError> {
        for s in &seqs {
            let n = s.cameras().len();
            let need = match &views {
                ViewChoice::Fixed(v) => v.iter().max().map_or(0, |m| m + 1),
                ViewChoice::Random { count, .. } => *count,
            };
            if need == 0 || need > n {
                return Err(DataError::file(
                    label,
                    format!(
                        "{}: {need} views needed but the sequence has {n} cameras",
                        s.name()
                    ),
                ));
            }
        }
        let frames = seqs
            .iter()
            .enumerate()
            .flat_map(|(si, s)| (0..s.len()).map(move |fi| (si, fi)))
            .collect();
        Ok(JointFrameDataset {
            seqs,
            frames,
            views,
            size,
            epoch: AtomicU64::new(0),
            meshes: None,
        })
    }

    /// Samples whose people `meshes` gives SMPL-X ground truth to.
    pub fn with_meshes(self, meshes: std::sync::Arc<dyn MeshSource>) -> Self {
        JointFrameDataset {
            meshes: Some(meshes),
            ..self
        }
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    pub fn set_epoch(&self, epoch: u64) {
        self.epoch.store(epoch, Ordering::Relaxed);
    }

    pub fn load(&self, index: usize) -> Result<FrameSample, DataError> {
        self.load_with_draw(index, index)
    }

    /// Frame `index` with the views of draw number `draw`.
    pub fn load_with_draw(&self, index: usize, draw: usize) -> Result<FrameSample, DataError> {
        let (si, fi) = self.frames[index];
        let seq = &self.seqs[si];
        let all = seq.cameras();
        let views = select_views(
            &self.views,
            self.epoch.load(Ordering::Relaxed),
            draw,
            all.len(),
        );
        let paths = seq.images(fi);
        let cameras: Vec<Camera> = views.iter().map(|&v| all[v].clone()).collect();
        let imgs = read_frame_images(
            &views.iter().map(|&v| paths[v].clone()).collect::<Vec<_>>(),
            &cameras,
        )?;
        let (images, letterboxes) = letterbox_views(&imgs, &cameras, self.size)?;
        let set = seq.joint_set();
        let people = seq
            .people(fi)?
            .iter()
            .map(|p| person_from_joints(p, set, &cameras, &letterboxes))
            .collect();
        let mut sample = FrameSample {
            scene: seq.name(),
            frame: seq.frame_key(fi),
            images,
            size: self.size as usize,
            cameras,
            letterboxes,
            people,
            cover: covered_slots(set),
        };
        if let Some(m) = &self.meshes {
            m.attach(&mut sample)?;
        }
        Ok(sample)
    }
}

/// The dataset format of a source.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum SourceFormat {
    /// The MVMP-HMR layout (SMPL-X ground truth).
    Mvmp,
    /// CMU Panoptic read in place (joints19, first 15 joints).
    Panoptic,
    /// Human3.6M read in place (17 joints).
    H36m,
}

impl SourceFormat {
    pub fn name(self) -> &'static str {
        match self {
            SourceFormat::Mvmp => "mvmp",
            SourceFormat::Panoptic => "panoptic",
            SourceFormat::H36m => "h36m",
        }
    }

    /// Every format, in the order messages list them.
    pub const ALL: [SourceFormat; 3] = [
        SourceFormat::Mvmp,
        SourceFormat::Panoptic,
        SourceFormat::H36m,
    ];

    /// The joint set of the ground truth.
    pub fn joint_set(self) -> JointSet {
        match self {
            SourceFormat::Mvmp => JointSet::Smplx127,
            SourceFormat::Panoptic => JointSet::Panoptic15,
            SourceFormat::H36m => JointSet::H36m17,
        }
    }
}

impl std::str::FromStr for SourceFormat {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        SourceFormat::ALL
            .into_iter()
            .find(|f| f.name() == s)
            .ok_or_else(|| format!("{s:?}: expected mvmp, panoptic or h36m"))
    }
}

impl std::fmt::Display for SourceFormat {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One dataset to train or validate on (a `[[sources]]` or `[validation]` table of a training config).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SourceSpec {
    pub format: SourceFormat,
    /// The dataset's root (relative paths: to the working directory).
    pub root: String,
    /// `train`, `test`, `all` (mvmp); `train`, `test`, a split name or comma-separated sequences
    /// (panoptic); `train`, `test` or comma-separated subjects (h36m). Default: `train` for training sources,
    /// `test` for validation.
    #[serde(default)]
    pub split: Option<String>,
    /// Every N-th frame (default: the Panoptic split's stride, 5 for Human3.6M; mvmp keeps every frame).
    #[serde(default)]
    pub stride: Option<usize>,
    /// Camera names (default: VoxelPose's 5 HD cameras for Panoptic, the 4 cameras for Human3.6M).
    #[serde(default)]
    pub cameras: Option<Vec<String>>,
    /// Training only: each frame of this source is drawn this many times per epoch (each time with its
    /// own view draw), to balance a small source against a large one. Default 1.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub repeat: Option<usize>,
    /// Training only, panoptic and h36m: SMPL-X pseudo-ground-truth fits in infer's layout
    /// (`DIR/<sequence>/<frame>/people.npz`). Each annotated person takes the nearest fit within the match
    /// gate (pelvis to the dataset's root) and is trained with the SMPL-X terms as well.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pseudo_gt: Option<String>,
}

/// Panoptic's split by a name: `train` (VoxelPose's training sequences), `test` (its validation sequences),
/// a split's name, or comma-separated sequences (every frame). Returns the sequences, the stride and a label.
pub fn panoptic_split(name: &str) -> (Vec<String>, usize, String) {
    use crate::panoptic::{VOXELPOSE_TRAIN, VOXELPOSE_VALIDATION, split_by_name};
    let split = match name {
        "test" => Some(VOXELPOSE_VALIDATION),
        "train" => Some(VOXELPOSE_TRAIN),
        name => split_by_name(name),
    };
    match split {
        Some(sp) => (
            sp.sequences.iter().map(|s| s.to_string()).collect(),
            sp.stride,
            sp.name.to_string(),
        ),
        None => (
            name.split(',').map(|s| s.trim().to_string()).collect(),
            1,
            name.to_string(),
        ),
    }
}

/// A split given as a list names directories directly under the dataset's root, each once: a name that
/// leaves the root (`..`, a path) or repeats (its frames counted twice) is refused.
fn check_split_names(root: &Path, names: &[String], what: &str) -> Result<(), DataError> {
    if names.is_empty() {
        return Err(DataError::file(root, format!("the split names no {what}")));
    }
    for (i, name) in names.iter().enumerate() {
        let mut parts = Path::new(name).components();
        let plain =
            matches!(parts.next(), Some(std::path::Component::Normal(_))) && parts.next().is_none();
        if !plain {
            return Err(DataError::file(
                root,
                format!("split: {what} {name:?} is not a directory name under the root"),
            ));
        }
        if names[..i].contains(name) {
            return Err(DataError::file(
                root,
                format!("split: {what} {name:?} is listed twice"),
            ));
        }
    }
    Ok(())
}

/// Panoptic sequences `names` under `root` with the named cameras, every `stride`-th frame.
pub fn open_panoptic(
    root: &Path,
    names: &[String],
    cameras: &[&str],
    stride: usize,
) -> Result<Vec<Box<dyn JointAnnotated>>, DataError> {
    check_split_names(root, names, "sequence")?;
    let mut out: Vec<Box<dyn JointAnnotated>> = Vec::new();
    for name in names {
        let dir = root.join(name);
        if !dir.is_dir() {
            return Err(DataError::file(
                &dir,
                format!(
                    "sequence {name:?} of the split is not under {}",
                    root.display()
                ),
            ));
        }
        out.push(Box::new(PanopticSequence::open(&dir, cameras, stride)?));
    }
    Ok(out)
}

/// Every action of the Human3.6M `subjects` under `root` with the named cameras, every `stride`-th frame.
pub fn open_h36m(
    root: &Path,
    subjects: &[String],
    cameras: &[&str],
    stride: usize,
) -> Result<Vec<Box<dyn JointAnnotated>>, DataError> {
    check_split_names(root, subjects, "subject")?;
    let mut out: Vec<Box<dyn JointAnnotated>> = Vec::new();
    for subject in subjects {
        for action in crate::h36m::actions(root, subject)? {
            out.push(Box::new(H36mSequence::open(
                root, subject, &action, cameras, stride,
            )?));
        }
    }
    Ok(out)
}

/// Human3.6M's default frame stride (50 Hz video; every 5th frame).
pub const H36M_STRIDE: usize = 5;

impl SourceSpec {
    fn split_or(&self, default: &str) -> String {
        self.split.clone().unwrap_or_else(|| default.to_string())
    }

    /// The cameras used: `cameras`, or the format's default list.
    pub fn camera_names(&self) -> Vec<String> {
        match (&self.cameras, self.format) {
            (Some(c), _) => c.clone(),
            (None, SourceFormat::Panoptic) => crate::panoptic::VOXELPOSE_CAMERAS
                .iter()
                .map(|s| s.to_string())
                .collect(),
            (None, _) => crate::h36m::CAMERAS.iter().map(|s| s.to_string()).collect(),
        }
    }

    /// The sequences of a joint-annotated source (`default_split` when the spec names none).
    pub fn open_sequences(
        &self,
        default_split: &str,
    ) -> Result<Vec<Box<dyn JointAnnotated>>, DataError> {
        let root = Path::new(&self.root);
        let split = self.split_or(default_split);
        let names = self.camera_names();
        let cams: Vec<&str> = names.iter().map(String::as_str).collect();
        if self.stride == Some(0) {
            return Err(DataError::file(
                root,
                "stride 0: keep every N-th frame, N >= 1",
            ));
        }
        match self.format {
            SourceFormat::Mvmp => Err(DataError::file(
                root,
                "an mvmp source has scenes, not joint-annotated sequences",
            )),
            SourceFormat::Panoptic => {
                let (seqs, stride, _) = panoptic_split(&split);
                open_panoptic(root, &seqs, &cams, self.stride.unwrap_or(stride))
            }
            SourceFormat::H36m => open_h36m(
                root,
                &crate::h36m::split_subjects(&split),
                &cams,
                self.stride.unwrap_or(H36M_STRIDE),
            ),
        }
    }

    /// The training samples of this source's split (default `train`).
    pub fn open_training(&self, views: ViewChoice, size: u32) -> Result<SourceDataset, DataError> {
        let label = format!("{} source {}", self.format.name(), self.root);
        match self.format {
            SourceFormat::Mvmp => {
                let split: Split = self
                    .split_or("train")
                    .parse()
                    .map_err(|e: String| DataError::file(&self.root, e))?;
                if self.stride.is_some() || self.cameras.is_some() || self.pseudo_gt.is_some() {
                    return Err(DataError::file(
                        &self.root,
                        "stride, cameras and pseudo_gt apply to panoptic and h36m sources; an mvmp source uses every frame, draws its views and has SMPL-X ground truth",
                    ));
                }
                Ok(SourceDataset::Mvmp(FrameDataset::open(
                    Path::new(&self.root),
                    split,
                    views,
                    size,
                )?))
            }
            _ => Ok(SourceDataset::Joints(JointFrameDataset::new(
                &label,
                self.open_sequences("train")?,
                views,
                size,
            )?)),
        }
    }

    /// How many times each frame is drawn per epoch.
    pub fn repeat(&self) -> usize {
        self.repeat.unwrap_or(1)
    }
}

/// One source's samples.
pub enum SourceDataset {
    Mvmp(FrameDataset),
    Joints(JointFrameDataset),
}

impl SourceDataset {
    pub fn len(&self) -> usize {
        match self {
            SourceDataset::Mvmp(d) => d.frames().len(),
            SourceDataset::Joints(d) => d.frames.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    pub fn set_epoch(&self, epoch: u64) {
        match self {
            SourceDataset::Mvmp(d) => d.set_epoch(epoch),
            SourceDataset::Joints(d) => d.set_epoch(epoch),
        }
    }

    pub fn load(&self, index: usize) -> Result<FrameSample, DataError> {
        match self {
            SourceDataset::Mvmp(d) => d.load(index),
            SourceDataset::Joints(d) => d.load(index),
        }
    }

    /// Sample `n` of a source drawn repeatedly: frame `n mod len`, views drawn for `n` (so each repeat of
    /// a frame sees its own views).
    pub fn load_repeated(&self, n: usize) -> Result<FrameSample, DataError> {
        match self {
            SourceDataset::Mvmp(d) => d.load_with_draw(n % d.frames().len(), n),
            SourceDataset::Joints(d) => d.load_with_draw(n % d.len(), n),
        }
    }
}

/// Several sources as one dataset: the samples of each (each frame `repeat` times), one after the other.
pub struct TrainingSet {
    pub parts: Vec<SourceDataset>,
    repeats: Vec<usize>,
    starts: Vec<usize>,
    augment: Photometric,
    /// Seeds the augmentation draws, with the epoch and the sample's number.
    seed: u64,
    epoch: AtomicU64,
}

impl TrainingSet {
    /// Sources whose frames are drawn `repeats[i]` times per epoch (at least once).
    pub fn with_repeats(parts: Vec<SourceDataset>, repeats: Vec<usize>) -> Self {
        assert_eq!(parts.len(), repeats.len(), "one repeat count per source");
        let repeats: Vec<usize> = repeats.into_iter().map(|r| r.max(1)).collect();
        let mut starts = Vec::with_capacity(parts.len());
        let mut n = 0;
        for (p, r) in parts.iter().zip(&repeats) {
            starts.push(n);
            n += p.len() * r;
        }
        TrainingSet {
            parts,
            repeats,
            starts,
            augment: Photometric::default(),
            seed: 0,
            epoch: AtomicU64::new(0),
        }
    }

    /// Samples jittered by `augment`, drawn from `seed`, the epoch and the sample's number.
    pub fn with_augment(self, augment: Photometric, seed: u64) -> Self {
        TrainingSet {
            augment,
            seed,
            ..self
        }
    }

    /// Every MVMP-HMR source's people must hold `n` joints (the output of the body model `body_model`,
    /// whose joints the losses compare them with): see [`FrameDataset::expect_joints`].
    pub fn expect_joints(&mut self, n: usize, body_model: &str) {
        for p in &mut self.parts {
            if let SourceDataset::Mvmp(d) = p {
                d.expect_joints(n, body_model);
            }
        }
    }

    /// Samples per epoch of source `i`.
    pub fn samples_of(&self, i: usize) -> usize {
        self.parts[i].len() * self.repeats[i]
    }

    pub fn set_epoch(&self, epoch: u64) {
        self.epoch.store(epoch, Ordering::Relaxed);
        for p in &self.parts {
            p.set_epoch(epoch);
        }
    }

    /// The source of sample `index` and the sample's number within it (frame = number mod frames).
    fn locate(&self, index: usize) -> (usize, usize) {
        let part = self.starts.partition_point(|&s| s <= index) - 1;
        (part, index - self.starts[part])
    }

    pub fn load(&self, index: usize) -> Result<FrameSample, DataError> {
        let (p, i) = self.locate(index);
        let mut sample = self.parts[p].load_repeated(i)?;
        // Its own stream: the view draws (seeded alike) must not move when augmentation is turned on.
        let epoch = self.epoch.load(Ordering::Relaxed);
        let seed = draw_seed(self.seed ^ 0xA076_1D64_78BD_642F, epoch, index);
        self.augment.apply(&mut sample, seed);
        Ok(sample)
    }

    pub fn total(&self) -> usize {
        (0..self.parts.len()).map(|i| self.samples_of(i)).sum()
    }
}

impl Dataset<FrameSample> for TrainingSet {
    fn get(&self, index: usize) -> Result<FrameSample, DatasetError> {
        self.load(index).map_err(DatasetError::new)
    }

    fn len(&self) -> usize {
        self.total()
    }
}
