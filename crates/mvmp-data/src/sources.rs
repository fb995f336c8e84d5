//! Training sources: MVMP-HMR (SMPL-X ground truth) and the joint-annotated datasets CMU Panoptic and
//! Human3.6M (3D joints only), read in place as [`Sequence`]s and served as one dataset of
//! [`FrameSample`]s.
//!
//! A joint-annotated person becomes a sample person whose 127 joint slots hold the dataset's joints at the
//! SMPL-X joints they map to ([`JointSet`]), with a validity per slot (0 for every slot the dataset does not
//! annotate, and for annotated joints below Panoptic's confidence threshold), and no SMPL-X parameters
//! (`smplx == false`). The losses use this: parameter, vertex, orientation and density terms only for people
//! with SMPL-X, joint terms on valid slots, heatmaps only for the joints the source covers.
use std::path::Path;
use std::sync::atomic::{AtomicU64, Ordering};

use burn::data::dataset::{Dataset, DatasetError};
use serde::{Deserialize, Serialize};

use crate::DataError;
use crate::augment::Photometric;
use crate::dataset::FrameDataset;
use crate::h36m::H36mSequence;
use crate::loader::{FrameSample, Split, ViewChoice, draw_seed};
use crate::panoptic::PanopticSequence;
use crate::sequence::{Sequence, open_mvmp};
use mvmp_smplx::joint_sets::JointSet;

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
        // Compared as paths: `a` and `a/` name the same directory.
        if names[..i].iter().any(|n| Path::new(n) == Path::new(name)) {
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
) -> Result<Vec<Box<dyn Sequence>>, DataError> {
    check_split_names(root, names, "sequence")?;
    let mut out: Vec<Box<dyn Sequence>> = Vec::new();
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
) -> Result<Vec<Box<dyn Sequence>>, DataError> {
    check_split_names(root, subjects, "subject")?;
    let mut out: Vec<Box<dyn Sequence>> = Vec::new();
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

    /// The sequences of this source's split (`default_split` when the spec names none): the scenes of an
    /// MVMP-HMR dataset, Panoptic's sequences, Human3.6M's actions.
    pub fn open_sequences(&self, default_split: &str) -> Result<Vec<Box<dyn Sequence>>, DataError> {
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
            SourceFormat::Mvmp => open_mvmp(root, self.mvmp_split(&split)?),
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

    /// An MVMP-HMR source's split; its options other than the split belong to the other formats.
    fn mvmp_split(&self, split: &str) -> Result<Split, DataError> {
        let split: Split = split
            .parse()
            .map_err(|e: String| DataError::file(&self.root, e))?;
        if self.stride.is_some() || self.cameras.is_some() || self.pseudo_gt.is_some() {
            return Err(DataError::file(
                &self.root,
                "stride, cameras and pseudo_gt apply to panoptic and h36m sources; an mvmp source uses every frame, draws its views and has SMPL-X ground truth",
            ));
        }
        Ok(split)
    }

    /// The training samples of this source's split (default `train`).
    pub fn open_training(&self, views: ViewChoice, size: u32) -> Result<FrameDataset, DataError> {
        match self.format {
            SourceFormat::Mvmp => {
                let split = self.mvmp_split(&self.split_or("train"))?;
                FrameDataset::open(Path::new(&self.root), split, views, size)
            }
            _ => {
                let label = format!("{} source {}", self.format.name(), self.root);
                FrameDataset::new(&label, self.open_sequences("train")?, views, size)
            }
        }
    }

    /// How many times each frame is drawn per epoch.
    pub fn repeat(&self) -> usize {
        self.repeat.unwrap_or(1)
    }
}

/// Several sources as one dataset: the samples of each (each frame `repeat` times), one after the other.
pub struct TrainingSet {
    pub parts: Vec<FrameDataset>,
    repeats: Vec<usize>,
    starts: Vec<usize>,
    augment: Photometric,
    /// Seeds the augmentation draws, with the epoch and the sample's number.
    seed: u64,
    epoch: AtomicU64,
}

impl TrainingSet {
    /// Sources whose frames are drawn `repeats[i]` times per epoch (at least once).
    pub fn with_repeats(parts: Vec<FrameDataset>, repeats: Vec<usize>) -> Self {
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

    /// Every SMPL-X person must hold `n` joints (the output of the body model `body_model`, whose joints
    /// the losses compare them with): see [`FrameDataset::expect_joints`].
    pub fn expect_joints(&mut self, n: usize, body_model: &str) {
        for p in &mut self.parts {
            p.expect_joints(n, body_model);
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn split_names_are_plain_and_distinct_as_paths() {
        let root = Path::new("/data");
        let names = |v: &[&str]| v.iter().map(|s| s.to_string()).collect::<Vec<_>>();
        assert!(check_split_names(root, &names(&["a", "b"]), "sequence").is_ok());
        for bad in [&["a", "a/"][..], &["a/", "a"], &["a", "a/."]] {
            let e = check_split_names(root, &names(bad), "sequence").unwrap_err();
            assert!(e.to_string().contains("listed twice"), "{bad:?}: {e}");
        }
        for bad in [&["../a"][..], &["a/b"], &["/a"], &[]] {
            assert!(
                check_split_names(root, &names(bad), "subject").is_err(),
                "{bad:?}"
            );
        }
    }
}
