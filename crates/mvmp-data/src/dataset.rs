//! The frame dataset: the frames of any [`Sequence`]s as training samples (a burn `Dataset`), each seen
//! by the selected views, letterboxed and normalised, with every person's ground truth in those views.
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};

use burn::data::dataset::{Dataset, DatasetError};
use nalgebra::{Vector2, Vector3};

use crate::DataError;
use crate::layout::{DatasetLayout, FrameRef, Person, check_joints};
use crate::loader::{FrameSample, PersonGt, Split, ViewChoice, letterbox_views, select_views};
use crate::sequence::{AnnotatedPerson, FramePeople, MvmpScene, Sequence, frame_pairs};
use mvmp_geom::{Camera, Letterbox};
use mvmp_smplx::joint_sets::JointSet;
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS, NUM_JOINTS_WITH_LANDMARKS};

/// Gives the people of a joint-annotated sample SMPL-X ground truth from elsewhere (pseudo-ground-truth
/// fits), after the sample is loaded.
pub trait MeshSource: Send + Sync {
    fn attach(&self, sample: &mut FrameSample) -> Result<(), DataError>;
}

/// The smallest network input a sample is letterboxed to (one ViT patch).
pub const MIN_INPUT_SIZE: u32 = 14;

/// Training samples: every frame of some sequences.
pub struct FrameDataset {
    seqs: Vec<Box<dyn Sequence>>,
    frames: Vec<(usize, usize)>,
    views: ViewChoice,
    size: u32,
    epoch: AtomicU64,
    /// The joints per person every SMPL-X annotation must hold (the body layer's output) and that layer's
    /// body model, once known.
    joints: Option<(usize, String)>,
    meshes: Option<Arc<dyn MeshSource>>,
    /// The MVMP-HMR dataset the sequences are scenes of, and their frames, when opened from one.
    mvmp: Option<(Arc<DatasetLayout>, Vec<FrameRef>)>,
}

impl FrameDataset {
    /// The frames of an MVMP-HMR dataset's split, with images letterboxed to `size`.
    pub fn open(
        root: &Path,
        split: Split,
        views: ViewChoice,
        size: u32,
    ) -> Result<Self, DataError> {
        let layout = Arc::new(DatasetLayout::open(root)?);
        check_layout_views(&layout, &views)?;
        let scenes = MvmpScene::split(layout.clone(), split)?;
        let refs = scenes.iter().flat_map(|s| s.frames().to_vec()).collect();
        let seqs = scenes
            .into_iter()
            .map(|s| Box::new(s) as Box<dyn Sequence>)
            .collect();
        let mut ds = Self::new(&root.display().to_string(), seqs, views, size)?;
        ds.mvmp = Some((layout, refs));
        Ok(ds)
    }

    /// Every frame of `seqs` (each must have the cameras `views` asks for). `label` names the source in
    /// errors.
    pub fn new(
        label: &str,
        seqs: Vec<Box<dyn Sequence>>,
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
        if size < MIN_INPUT_SIZE {
            return Err(DataError::file(
                label,
                format!("input size {size} is too small"),
            ));
        }
        Ok(FrameDataset {
            frames: frame_pairs(&seqs),
            seqs,
            views,
            size,
            epoch: AtomicU64::new(0),
            joints: None,
            meshes: None,
            mvmp: None,
        })
    }

    /// Samples whose people `meshes` gives SMPL-X ground truth to.
    pub fn with_meshes(self, meshes: Arc<dyn MeshSource>) -> Self {
        FrameDataset {
            meshes: Some(meshes),
            ..self
        }
    }

    /// From now on a frame whose SMPL-X people hold another number of joints than `n` (what the body layer
    /// that consumes them outputs) is an error naming the file, instead of a mismatch deep in a loss or
    /// metric.
    pub fn expect_joints(&mut self, n: usize, body_model: &str) {
        self.joints = Some((n, body_model.to_string()));
    }

    /// The MVMP-HMR dataset this was opened from.
    pub fn layout(&self) -> Option<&DatasetLayout> {
        self.mvmp.as_ref().map(|(l, _)| l.as_ref())
    }

    /// The MVMP-HMR frames, in sample order (empty for other datasets).
    pub fn frame_refs(&self) -> &[FrameRef] {
        self.mvmp.as_ref().map_or(&[], |(_, f)| f.as_slice())
    }

    pub fn sequences(&self) -> &[Box<dyn Sequence>] {
        &self.seqs
    }

    pub fn len(&self) -> usize {
        self.frames.len()
    }

    pub fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Set the epoch that seeds random view choices.
    pub fn set_epoch(&self, epoch: u64) {
        self.epoch.store(epoch, Ordering::Relaxed);
    }

    /// Load sample `index`.
    pub fn load(&self, index: usize) -> Result<FrameSample, DataError> {
        self.load_with_draw(index, index)
    }

    /// Sample `n` of a dataset drawn repeatedly: frame `n mod len`, views drawn for `n` (so each repeat of
    /// a frame sees its own views).
    pub fn load_repeated(&self, n: usize) -> Result<FrameSample, DataError> {
        self.load_with_draw(n % self.len(), n)
    }

    /// Frame `index` with the views of draw number `draw` (a frame drawn repeatedly in an epoch gets a
    /// view draw per repeat).
    pub fn load_with_draw(&self, index: usize, draw: usize) -> Result<FrameSample, DataError> {
        let (si, fi) = self.frames[index];
        let seq = &self.seqs[si];
        let frame = seq.frame(fi)?;
        if let (Some((n, body)), FramePeople::Smplx(people)) = (&self.joints, &frame.people) {
            check_joints(people, *n, body).map_err(|what| DataError::file(&frame.source, what))?;
        }
        let all = seq.cameras();
        let views = select_views(
            &self.views,
            self.epoch.load(Ordering::Relaxed),
            draw,
            all.len(),
        );
        let cameras: Vec<Camera> = views.iter().map(|&v| all[v].clone()).collect();
        let paths: Vec<PathBuf> = views.iter().map(|&v| frame.images[v].clone()).collect();
        let imgs = read_frame_images(&paths, &cameras)?;
        let (images, letterboxes) = letterbox_views(&imgs, &cameras, self.size)?;
        let people = people_gt(&frame.people, &views, &cameras, &letterboxes);
        let mut sample = FrameSample {
            scene: seq.name(),
            frame: seq.frame_key(fi),
            images,
            size: self.size as usize,
            cameras,
            letterboxes,
            cover: frame.people.cover(),
            people,
        };
        if let Some(m) = &self.meshes {
            m.attach(&mut sample)?;
        }
        Ok(sample)
    }
}

impl Dataset<FrameSample> for FrameDataset {
    fn get(&self, index: usize) -> Result<FrameSample, DatasetError> {
        self.load(index).map_err(DatasetError::new)
    }

    fn len(&self) -> usize {
        self.frames.len()
    }
}

/// Fixed views must exist in every scene of the dataset, a random draw must fit the smallest rig.
fn check_layout_views(layout: &DatasetLayout, views: &ViewChoice) -> Result<(), DataError> {
    let root = &layout.root;
    let min_views = layout.scenes.iter().map(|s| s.rig.len()).min().unwrap_or(0);
    match views {
        ViewChoice::Fixed(v) => {
            if let Some(&bad) = v.iter().find(|&&i| i >= min_views) {
                let scene = layout.scenes.iter().find(|s| s.rig.len() <= bad);
                let (name, has) = scene.map_or((String::new(), min_views), |s| {
                    (format!(" ({})", s.name), s.rig.len())
                });
                return Err(DataError::file(
                    root,
                    format!(
                        "{} views requested (camera index {bad} among them), but a scene{name} has \
                         only {has} cameras",
                        v.len()
                    ),
                ));
            }
        }
        ViewChoice::Random { count, .. } => {
            if *count == 0 || *count > min_views {
                return Err(DataError::file(
                    root,
                    format!("{count} random views requested, scenes have {min_views} cameras"),
                ));
            }
        }
    }
    Ok(())
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

/// A frame's people as sample people in the chosen `views` (their cameras and letterboxes).
pub fn people_gt(
    people: &FramePeople,
    views: &[usize],
    cameras: &[Camera],
    letterboxes: &[Letterbox],
) -> Vec<PersonGt> {
    match people {
        FramePeople::Smplx(people) => people
            .iter()
            .map(|p| person_gt(p, views, letterboxes))
            .collect(),
        FramePeople::Joints(set, people) => people
            .iter()
            .map(|p| person_from_joints(p, *set, cameras, letterboxes))
            .collect(),
    }
}

/// One person's ground truth for the chosen views: parameters as float32 (the full pose, 10 betas, 10
/// expression values), pelvis, 3D joints, and each view's 2D joints in letterboxed pixels.
fn person_gt(p: &Person, views: &[usize], letterboxes: &[Letterbox]) -> PersonGt {
    let joints_2d = views
        .iter()
        .zip(letterboxes)
        .map(|(&v, lb)| {
            p.views[v]
                .joints_2d
                .iter()
                .map(|j| {
                    let q = lb.apply(Vector2::new(j[0], j[1]));
                    [q.x as f32, q.y as f32, j[2] as f32]
                })
                .collect()
        })
        .collect();
    let (pose, betas, expression) = smplx_values(p);
    PersonGt {
        id: p.id,
        pose,
        betas,
        expression,
        pelvis: p.pelvis.map(|x| x as f32),
        joints_3d: p.joints_3d.iter().map(|j| j.map(|x| x as f32)).collect(),
        joint_valid: vec![1.0; p.joints_3d.len()],
        joints_2d,
        smplx: true,
    }
}

/// A person's SMPL-X parameters as the network's float32 values: the full pose (55 x 3 axis-angle), 10
/// betas, 10 expression values (missing ones zero, extra ones dropped).
pub fn smplx_values(p: &Person) -> (Vec<f32>, [f32; NUM_BETAS], [f32; NUM_EXPRESSION]) {
    let f32s = |v: &[f64], n: usize| -> Vec<f32> {
        let mut o: Vec<f32> = v.iter().map(|&x| x as f32).collect();
        o.resize(n, 0.0);
        o
    };
    let fixed =
        |v: &[f64]| -> [f32; 10] { std::array::from_fn(|i| v.get(i).map_or(0.0, |&x| x as f32)) };
    (
        f32s(&p.smplx.full_pose(), NUM_JOINTS * 3),
        fixed(&p.smplx.betas),
        fixed(&p.smplx.expression),
    )
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
        pose: vec![0.0; NUM_JOINTS * 3],
        betas: [0.0; NUM_BETAS],
        expression: [0.0; NUM_EXPRESSION],
        pelvis: root,
        joints_3d,
        joints_2d,
        joint_valid: valid,
        smplx: false,
    }
}
