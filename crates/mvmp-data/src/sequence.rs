//! One abstraction over every dataset mvmp reads: a [`Sequence`] of synchronized multiview frames seen by
//! fixed cameras, each frame with its images and its annotated people. A scene of the MVMP-HMR layout, a
//! CMU Panoptic sequence and a Human3.6M subject's action are sequences; their ground truth is SMPL-X
//! (MVMP-HMR) or 3D joints of the dataset's own joint set (Panoptic, Human3.6M). Reading a frame's
//! ground truth opens no image.
use std::path::{Path, PathBuf};
use std::sync::Arc;

use crate::DataError;
use crate::h36m::H36mSequence;
use crate::layout::{Annotation, DatasetLayout, FrameRef, Person};
use crate::loader::{Split, split_frames};
use crate::panoptic::PanopticSequence;
use mvmp_geom::Camera;
use mvmp_smplx::joint_sets::JointSet;
use mvmp_smplx::names::NUM_JOINTS_WITH_LANDMARKS;

/// One annotated person of a joint-annotated frame, in the dataset's joint set (world metres).
#[derive(Debug, Clone, PartialEq)]
pub struct AnnotatedPerson {
    pub id: i64,
    pub joints: Vec<[f64; 3]>,
    /// Whether each joint is annotated.
    pub valid: Vec<bool>,
}

/// The people of one frame, as the dataset annotates them.
#[derive(Debug, Clone)]
pub enum FramePeople {
    /// SMPL-X parameters, their 127 joints and each camera's 2D joints (MVMP-HMR).
    Smplx(Vec<Person>),
    /// 3D joints of a dataset's joint set (Panoptic, Human3.6M).
    Joints(JointSet, Vec<AnnotatedPerson>),
}

impl FramePeople {
    pub fn len(&self) -> usize {
        match self {
            FramePeople::Smplx(p) => p.len(),
            FramePeople::Joints(_, p) => p.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The 127 SMPL-X joint slots the ground truth fills: all of an SMPL-X person's joints (as many as
    /// its body model outputs), a joint set's slots.
    pub fn cover(&self) -> Vec<bool> {
        match self {
            FramePeople::Smplx(p) => vec![
                true;
                p.first().map_or(NUM_JOINTS_WITH_LANDMARKS, |p| p
                    .joints_3d
                    .len())
            ],
            FramePeople::Joints(set, _) => covered_slots(*set),
        }
    }
}

/// One frame of a sequence: an image per camera and the people.
#[derive(Debug, Clone)]
pub struct SequenceFrame {
    /// The file the annotations came from (named in errors about them).
    pub source: PathBuf,
    pub images: Vec<PathBuf>,
    pub people: FramePeople,
}

/// A sequence of frames seen by fixed, calibrated cameras, read in place.
pub trait Sequence: Send + Sync {
    /// The name reports group by and output layouts use (a scene, a sequence, subject/action).
    fn name(&self) -> String;
    /// The cameras, in the order of each frame's images.
    fn cameras(&self) -> &[Camera];
    fn len(&self) -> usize;
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Frame `i`'s name in file layouts (predictions, pseudo-ground-truth): `<name>/<frame key>/`.
    fn frame_key(&self, i: usize) -> String;
    /// Frame `i`: its images' paths and its people (no image is opened).
    fn frame(&self, i: usize) -> Result<SequenceFrame, DataError>;
}

/// The 127 SMPL-X joint slots a joint set fills.
pub fn covered_slots(set: JointSet) -> Vec<bool> {
    let mut cover = vec![false; NUM_JOINTS_WITH_LANDMARKS];
    for i in set.smplx_indices() {
        cover[i] = true;
    }
    cover
}

/// The frames of one scene of an MVMP-HMR dataset (those of a split).
pub struct MvmpScene {
    layout: Arc<DatasetLayout>,
    scene: usize,
    frames: Vec<FrameRef>,
}

impl MvmpScene {
    /// The scenes of `split`, each with its frames of the split, in the layout's order.
    pub fn split(layout: Arc<DatasetLayout>, split: Split) -> Result<Vec<MvmpScene>, DataError> {
        let mut out: Vec<MvmpScene> = Vec::new();
        for f in split_frames(&layout, split)? {
            match out.last_mut() {
                Some(s) if s.scene == f.scene => s.frames.push(f),
                _ => out.push(MvmpScene {
                    layout: layout.clone(),
                    scene: f.scene,
                    frames: vec![f],
                }),
            }
        }
        Ok(out)
    }

    /// [`MvmpScene::split`] as sequences.
    pub fn sequences(
        layout: Arc<DatasetLayout>,
        split: Split,
    ) -> Result<Vec<Box<dyn Sequence>>, DataError> {
        Ok(MvmpScene::split(layout, split)?
            .into_iter()
            .map(|s| Box::new(s) as Box<dyn Sequence>)
            .collect())
    }

    pub fn frames(&self) -> &[FrameRef] {
        &self.frames
    }

    pub fn layout(&self) -> &DatasetLayout {
        &self.layout
    }

    fn annotation_path(&self, i: usize) -> PathBuf {
        self.frames[i].dir.join("annotation.json")
    }
}

impl Sequence for MvmpScene {
    fn name(&self) -> String {
        self.layout.scenes[self.scene].name.clone()
    }
    fn cameras(&self) -> &[Camera] {
        &self.layout.scenes[self.scene].rig.cameras
    }
    fn len(&self) -> usize {
        self.frames.len()
    }
    fn frame_key(&self, i: usize) -> String {
        self.frames[i].frame_name.clone()
    }
    fn frame(&self, i: usize) -> Result<SequenceFrame, DataError> {
        let source = self.annotation_path(i);
        let ann = Annotation::read(&source, self.cameras().len())?;
        let dir = &self.frames[i].dir;
        Ok(SequenceFrame {
            images: ann.images.iter().map(|n| dir.join(n)).collect(),
            people: FramePeople::Smplx(ann.people),
            source,
        })
    }
}

/// A frame of a joint-annotated sequence: images and people of `set`, named by `source`.
fn joints_frame(
    source: PathBuf,
    images: Vec<PathBuf>,
    set: JointSet,
    people: Vec<AnnotatedPerson>,
) -> SequenceFrame {
    SequenceFrame {
        source,
        images,
        people: FramePeople::Joints(set, people),
    }
}

impl Sequence for PanopticSequence {
    fn name(&self) -> String {
        self.name.clone()
    }
    fn cameras(&self) -> &[Camera] {
        &self.rig.cameras
    }
    fn len(&self) -> usize {
        self.frames.len()
    }
    /// The 8-digit HD frame index of the file names.
    fn frame_key(&self, i: usize) -> String {
        self.frames[i].index.clone()
    }
    /// The first 15 joints of people whose body centre is annotated; validity from the confidence.
    fn frame(&self, i: usize) -> Result<SequenceFrame, DataError> {
        use crate::panoptic::EVAL_JOINTS;
        let f = &self.frames[i];
        let people = PanopticSequence::people(self, f)?
            .into_iter()
            .map(|b| AnnotatedPerson {
                id: b.id,
                joints: b.joints[..EVAL_JOINTS].to_vec(),
                valid: (0..EVAL_JOINTS).map(|j| b.valid(j)).collect(),
            })
            .collect();
        let source = PathBuf::from(format!("{} frame {}", self.name, f.index));
        Ok(joints_frame(
            source,
            f.images.clone(),
            JointSet::Panoptic15,
            people,
        ))
    }
}

impl Sequence for H36mSequence {
    fn name(&self) -> String {
        H36mSequence::name(self)
    }
    fn cameras(&self) -> &[Camera] {
        &self.rig.cameras
    }
    fn len(&self) -> usize {
        self.frames.len()
    }
    /// The image number (6 digits, from 1) of the extracted video frames.
    fn frame_key(&self, i: usize) -> String {
        format!("{:06}", self.frames[i].row + 1)
    }
    /// One subject per frame, every joint annotated.
    fn frame(&self, i: usize) -> Result<SequenceFrame, DataError> {
        let person = AnnotatedPerson {
            id: 0,
            joints: self.joints[i].to_vec(),
            valid: vec![true; self.joints[i].len()],
        };
        let source = PathBuf::from(format!("{} frame {}", self.name(), self.frame_key(i)));
        Ok(joints_frame(
            source,
            self.frames[i].images.clone(),
            JointSet::H36m17,
            vec![person],
        ))
    }
}

/// Every frame of `seqs` as (sequence, frame) pairs, sequence by sequence.
pub fn frame_pairs(seqs: &[Box<dyn Sequence>]) -> Vec<(usize, usize)> {
    seqs.iter()
        .enumerate()
        .flat_map(|(si, s)| (0..s.len()).map(move |fi| (si, fi)))
        .collect()
}

/// The scenes of an MVMP-HMR dataset's split as sequences.
pub fn open_mvmp(root: &Path, split: Split) -> Result<Vec<Box<dyn Sequence>>, DataError> {
    MvmpScene::sequences(Arc::new(DatasetLayout::open(root)?), split)
}
