//! What a frame dataset ([`crate::dataset`]) serves and how it is batched: samples, view selection,
//! letterboxed and normalised images, splits of an MVMP-HMR dataset by scene, and the padding batcher that
//! makes ground-truth tensors.
use std::sync::Arc;

use burn::data::dataloader::batcher::Batcher;
use burn::tensor::{Bool, Device, Tensor, TensorData};
use nalgebra::{Vector2, Vector3};

use crate::DataError;
use crate::layout::{Annotation, DatasetLayout, FrameRef};
use mvmp_geom::{Camera, Letterbox};
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS};

/// ImageNet normalisation (RGB).
pub const IMAGENET_MEAN: [f32; 3] = [0.485, 0.456, 0.406];
pub const IMAGENET_STD: [f32; 3] = [0.229, 0.224, 0.225];

/// Which views a sample uses.
#[derive(Debug, Clone, PartialEq)]
pub enum ViewChoice {
    /// These camera indices, in this order.
    Fixed(Vec<usize>),
    /// `count` views drawn at random per sample (training); the draw depends on `seed`, the epoch set with
    /// [`crate::dataset::FrameDataset::set_epoch`] and the sample index only.
    Random { count: usize, seed: u64 },
}

/// The seed of one random draw of a training sample: a mix of the run's seed, the epoch and the sample's
/// number, so that a resumed run draws the same.
pub fn draw_seed(seed: u64, epoch: u64, index: usize) -> u64 {
    seed ^ epoch.wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (index as u64).wrapping_mul(0xD6E8_FEB8_6659_FD93)
}

/// The views of sample `index` (shared by every dataset so that draws depend on the seed, epoch and index).
pub fn select_views(views: &ViewChoice, epoch: u64, index: usize, available: usize) -> Vec<usize> {
    use rand::SeedableRng;
    use rand::seq::SliceRandom;
    match views {
        ViewChoice::Fixed(v) => v.clone(),
        ViewChoice::Random { count, seed } => {
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(draw_seed(*seed, epoch, index));
            let mut all: Vec<usize> = (0..available).collect();
            all.shuffle(&mut rng);
            all.truncate(*count);
            all
        }
    }
}

/// A dataset split.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Split {
    Train,
    Test,
    All,
}

impl Split {
    pub const ALL: [Split; 3] = [Split::Train, Split::Test, Split::All];

    /// The split's name, as configs and flags spell it.
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
            Split::All => "all",
        }
    }
}

impl std::fmt::Display for Split {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Split {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        (Split::ALL.into_iter().find(|x| x.name() == s))
            .ok_or_else(|| format!("{s:?} is not a split; expected train, test or all"))
    }
}

/// The frames of a split's scenes ([`split_scenes`]), read without opening an image.
pub fn split_frames(layout: &DatasetLayout, split: Split) -> Result<Vec<FrameRef>, DataError> {
    let scenes = split_scenes(layout, split)?;
    Ok(layout
        .frames()
        .into_iter()
        .filter(|f| scenes.contains(&f.scene))
        .collect())
}

/// The scenes of a split: scenes sorted by their mean people count (then by name), every third one to test,
/// so train:test is 2:1 and both cover the range of crowd sizes. Deterministic.
pub fn split_scenes(layout: &DatasetLayout, split: Split) -> Result<Vec<usize>, DataError> {
    let mut keyed = Vec::new();
    for (i, s) in layout.scenes.iter().enumerate() {
        let Some(first) = s.index.frames.first() else {
            continue;
        };
        let path = s.dir.join(first).join("annotation.json");
        let n = Annotation::read(&path, s.rig.len())?.people.len();
        keyed.push((n, s.name.clone(), i));
    }
    keyed.sort();
    Ok(keyed
        .into_iter()
        .enumerate()
        .filter(|(k, _)| match split {
            Split::All => true,
            Split::Test => k % 3 == 2,
            Split::Train => k % 3 != 2,
        })
        .map(|(_, (_, _, i))| i)
        .collect())
}

/// Ground truth of one person in a sample.
#[derive(Debug, Clone)]
pub struct PersonGt {
    pub id: u32,
    /// 55 x 3 axis-angle.
    pub pose: Vec<f32>,
    pub betas: [f32; NUM_BETAS],
    pub expression: [f32; NUM_EXPRESSION],
    /// Pelvis in the world (T_wld).
    pub pelvis: [f32; 3],
    /// `[J][3]` world joints.
    pub joints_3d: Vec<[f32; 3]>,
    /// Per selected view, `[J][3]`: network-pixel u, v and visibility.
    pub joints_2d: Vec<Vec<[f32; 3]>>,
    /// `[J]`: 1 where the joint is annotated (every joint of an MVMP-HMR person; a joint-annotated dataset
    /// fills only the slots of its joint set).
    pub joint_valid: Vec<f32>,
    /// Whether `pose`, `betas` and `expression` are ground truth (false: joints only, the rest zero).
    pub smplx: bool,
}

/// One training sample: a frame seen by the selected views.
#[derive(Debug, Clone)]
pub struct FrameSample {
    pub scene: String,
    pub frame: String,
    /// `[V * 3 * S * S]` normalised, letterboxed images.
    pub images: Vec<f32>,
    pub size: usize,
    /// The selected cameras and their letterboxes.
    pub cameras: Vec<Camera>,
    pub letterboxes: Vec<Letterbox>,
    pub people: Vec<PersonGt>,
    /// `[J]`: the joints this sample's dataset annotates (its 2D heatmaps are supervised only for these).
    pub cover: Vec<bool>,
}

/// Views letterboxed into the network's `size` x `size` input: the images `[V * 3 * size * size]`
/// (planar, normalised) and each view's letterbox.
pub fn letterbox_views(
    imgs: &[image::RgbImage],
    cameras: &[Camera],
    size: u32,
) -> Result<(Vec<f32>, Vec<Letterbox>), DataError> {
    let s = size as usize;
    let mut images = vec![0f32; imgs.len() * 3 * s * s];
    let mut letterboxes = Vec::with_capacity(imgs.len());
    for (vi, (img, cam)) in imgs.iter().zip(cameras).enumerate() {
        let lb = Letterbox::new(cam.width, cam.height, size)?;
        letterbox_into(img, &lb, &mut images[vi * 3 * s * s..(vi + 1) * 3 * s * s]);
        letterboxes.push(lb);
    }
    Ok((images, letterboxes))
}

/// Resize an image into its letterbox (aspect kept, zero padding) and normalise, writing `[3, S, S]`.
pub fn letterbox_into(img: &image::RgbImage, lb: &Letterbox, out: &mut [f32]) {
    let s = lb.size as usize;
    let resized = image::imageops::resize(
        img,
        lb.content_width,
        lb.content_height,
        image::imageops::FilterType::Triangle,
    );
    // Padding is zero *after* normalisation (what the network sees for "no image").
    out.fill(0.0);
    for (x, y, p) in resized.enumerate_pixels() {
        let (u, v) = (
            x as usize + lb.offset_x as usize,
            y as usize + lb.offset_y as usize,
        );
        for c in 0..3 {
            out[c * s * s + v * s + u] =
                (p.0[c] as f32 / 255.0 - IMAGENET_MEAN[c]) / IMAGENET_STD[c];
        }
    }
}

/// A batch: `B` samples with `V` views each, people padded to the most in the batch (`P`).
#[derive(Debug, Clone)]
pub struct FrameBatch {
    /// `[B, V, 3, S, S]`
    pub images: Tensor<5>,
    /// Per sample, the selected cameras and letterboxes (the rig of each sample).
    pub cameras: Vec<Vec<Camera>>,
    pub letterboxes: Vec<Vec<Letterbox>>,
    /// `[B, P]` true where a person is present.
    pub mask: Tensor<2, Bool>,
    /// `[B, P, 55, 3]` axis-angle.
    pub pose: Tensor<4>,
    /// `[B, P, 10]`
    pub betas: Tensor<3>,
    /// `[B, P, 10]`
    pub expression: Tensor<3>,
    /// `[B, P, 3]` pelvis (T_wld).
    pub pelvis: Tensor<3>,
    /// `[B, P, J, 3]` world joints.
    pub joints_3d: Tensor<4>,
    /// `[B, V, P, J, 3]` network-pixel joints with visibility.
    pub joints_2d: Tensor<5>,
    /// `[B, P, J]` 1 where a joint is annotated.
    pub joint_valid: Tensor<3>,
    /// `[B, P]` 1 where the person has SMPL-X ground truth (pose, betas, expression, vertices).
    pub smplx: Tensor<2>,
    /// `[B, J]` 1 for the joints the sample's dataset annotates.
    pub cover: Tensor<2>,
    /// `[B, P, V, 3]` ground-truth vertices (world metres) when the batcher was asked for them.
    pub vertices: Option<Tensor<4>>,
    /// Number of people per sample.
    pub counts: Vec<usize>,
    pub names: Vec<(String, String)>,
    /// Each sample's people and annotated joints as loaded (what the tensors above pad and stack), so that
    /// targets and metrics are read on the host rather than back from the device.
    pub people: Vec<Vec<PersonGt>>,
    pub covers: Vec<Vec<bool>>,
}

/// Pads people and stacks views; with a body model it also poses the ground truth into vertices.
#[derive(Debug, Clone, Default)]
pub struct FrameBatcher {
    body: Option<Arc<mvmp_smplx::BodyModel>>,
    /// The body layer of the last device used (building one transposes the pose correctives).
    layer: Arc<std::sync::Mutex<Option<mvmp_smplx::SmplxLayer>>>,
}

impl FrameBatcher {
    /// A batcher that also returns ground-truth vertices, posed with `model` (the dataset's body model).
    pub fn with_vertices(model: mvmp_smplx::BodyModel) -> Self {
        FrameBatcher {
            body: Some(Arc::new(model)),
            layer: Default::default(),
        }
    }

    /// [`FrameBatcher::with_vertices`] that poses with `layer`, already built from `model` for the device
    /// the batches go to, instead of building a second copy of it.
    pub fn with_layer(model: Arc<mvmp_smplx::BodyModel>, layer: mvmp_smplx::SmplxLayer) -> Self {
        FrameBatcher {
            body: Some(model),
            layer: Arc::new(std::sync::Mutex::new(Some(layer))),
        }
    }

    fn layer(&self, model: &mvmp_smplx::BodyModel, device: &Device) -> mvmp_smplx::SmplxLayer {
        let mut cached = self.layer.lock().unwrap_or_else(|e| e.into_inner());
        match cached.as_ref() {
            // `Device` equality does not tell autodiff from plain flex; the layer's path depends on it.
            Some(l) if l.device() == device && l.device().is_autodiff() == device.is_autodiff() => {
                l.clone()
            }
            _ => {
                let l = mvmp_smplx::SmplxLayer::new(model, device);
                *cached = Some(l.clone());
                l
            }
        }
    }
}

impl Batcher<FrameSample, FrameBatch> for FrameBatcher {
    fn batch(&self, items: Vec<FrameSample>, device: &Device) -> FrameBatch {
        let b = items.len();
        let v = items.first().map_or(0, |i| i.cameras.len());
        let s = items.first().map_or(0, |i| i.size);
        let p = items
            .iter()
            .map(|i| i.people.len())
            .max()
            .unwrap_or(0)
            .max(1);
        let j = items
            .iter()
            .flat_map(|i| i.people.first())
            .map(|q| q.joints_3d.len())
            .next()
            .unwrap_or(mvmp_smplx::names::NUM_JOINTS_WITH_LANDMARKS);
        let h = Padded::new(&items, [b, v, s, p, j]);
        let t = |data: Vec<f32>, shape: Vec<usize>| TensorData::new(data, shape);
        // Only people with SMPL-X ground truth have vertices; a batch of joint-annotated frames needs none.
        let any_smplx = h.smplx.iter().any(|&x| x > 0.0);
        let vertices = self.body.as_ref().filter(|_| any_smplx).map(|model| {
            let layer = self.layer(model, device);
            let n = b * p;
            let out = layer.forward_axis_angle(
                Tensor::from_data(t(h.pose.clone(), vec![n, NUM_JOINTS, 3]), device),
                Tensor::from_data(t(h.betas.clone(), vec![n, NUM_BETAS]), device),
                Tensor::from_data(t(h.expr.clone(), vec![n, NUM_EXPRESSION]), device),
                Tensor::from_data(t(h.pelvis.clone(), vec![n, 3]), device),
                mvmp_smplx::Translation::Pelvis,
            );
            let nv = layer.num_vertices();
            out.vertices.reshape([b, p, nv, 3])
        });
        FrameBatch {
            vertices,
            images: Tensor::from_data(t(h.images, vec![b, v, 3, s, s]), device),
            cameras: items.iter().map(|i| i.cameras.clone()).collect(),
            letterboxes: items.iter().map(|i| i.letterboxes.clone()).collect(),
            mask: Tensor::from_data(TensorData::new(h.mask, [b, p]), device),
            pose: Tensor::from_data(t(h.pose, vec![b, p, NUM_JOINTS, 3]), device),
            betas: Tensor::from_data(t(h.betas, vec![b, p, NUM_BETAS]), device),
            expression: Tensor::from_data(t(h.expr, vec![b, p, NUM_EXPRESSION]), device),
            pelvis: Tensor::from_data(t(h.pelvis, vec![b, p, 3]), device),
            joints_3d: Tensor::from_data(t(h.j3, vec![b, p, j, 3]), device),
            joints_2d: Tensor::from_data(t(h.j2, vec![b, v, p, j, 3]), device),
            joint_valid: Tensor::from_data(t(h.valid, vec![b, p, j]), device),
            smplx: Tensor::from_data(t(h.smplx, vec![b, p]), device),
            cover: Tensor::from_data(t(h.cover, vec![b, j]), device),
            counts: items.iter().map(|i| i.people.len()).collect(),
            names: items
                .iter()
                .map(|i| (i.scene.clone(), i.frame.clone()))
                .collect(),
            covers: items.iter().map(|i| i.cover.clone()).collect(),
            people: items.into_iter().map(|i| i.people).collect(),
        }
    }
}

/// A batch's ground truth on the host, every frame padded to `p` people of `j` joints (absent people
/// and joints zero, masked out).
struct Padded {
    images: Vec<f32>,
    mask: Vec<bool>,
    pose: Vec<f32>,
    betas: Vec<f32>,
    expr: Vec<f32>,
    pelvis: Vec<f32>,
    j3: Vec<f32>,
    j2: Vec<f32>,
    valid: Vec<f32>,
    smplx: Vec<f32>,
    cover: Vec<f32>,
}

impl Padded {
    /// `dims`: batch, views, image side, people, joints.
    fn new(items: &[FrameSample], dims: [usize; 5]) -> Self {
        let [b, v, s, p, j] = dims;
        let mut h = Padded {
            images: Vec::with_capacity(b * v * 3 * s * s),
            mask: vec![false; b * p],
            pose: vec![0f32; b * p * NUM_JOINTS * 3],
            betas: vec![0f32; b * p * NUM_BETAS],
            expr: vec![0f32; b * p * NUM_EXPRESSION],
            pelvis: vec![0f32; b * p * 3],
            j3: vec![0f32; b * p * j * 3],
            j2: vec![0f32; b * v * p * j * 3],
            valid: vec![0f32; b * p * j],
            smplx: vec![0f32; b * p],
            cover: vec![0f32; b * j],
        };
        for (bi, it) in items.iter().enumerate() {
            h.images.extend_from_slice(&it.images);
            for (ji, &c) in it.cover.iter().enumerate().take(j) {
                h.cover[bi * j + ji] = if c { 1.0 } else { 0.0 };
            }
            for (pi, q) in it.people.iter().enumerate() {
                h.put_person(q, [bi, pi], dims);
            }
        }
        h
    }

    /// Person `pi` of batch item `bi`.
    fn put_person(&mut self, q: &PersonGt, [bi, pi]: [usize; 2], [_, v, _, p, j]: [usize; 5]) {
        let k = bi * p + pi;
        self.mask[k] = true;
        self.pose[k * NUM_JOINTS * 3..(k + 1) * NUM_JOINTS * 3].copy_from_slice(&q.pose);
        self.betas[k * NUM_BETAS..(k + 1) * NUM_BETAS].copy_from_slice(&q.betas);
        self.expr[k * NUM_EXPRESSION..(k + 1) * NUM_EXPRESSION].copy_from_slice(&q.expression);
        self.pelvis[k * 3..(k + 1) * 3].copy_from_slice(&q.pelvis);
        self.smplx[k] = if q.smplx { 1.0 } else { 0.0 };
        for (ji, &x) in q.joint_valid.iter().enumerate().take(j) {
            self.valid[k * j + ji] = x;
        }
        for (ji, x) in q.joints_3d.iter().enumerate().take(j) {
            self.j3[(k * j + ji) * 3..(k * j + ji) * 3 + 3].copy_from_slice(x);
        }
        for (vi, view) in q.joints_2d.iter().enumerate().take(v) {
            for (ji, x) in view.iter().enumerate().take(j) {
                let o = (((bi * v + vi) * p + pi) * j + ji) * 3;
                self.j2[o..o + 3].copy_from_slice(x);
            }
        }
    }
}

/// World point to network pixel for a selected camera (used by tests and tools).
pub fn project_to_network(cam: &Camera, lb: &Letterbox, p: [f64; 3]) -> Option<Vector2<f64>> {
    let (uv, z) = cam.project(&Vector3::from(p));
    (z > 0.0).then(|| lb.apply(uv))
}
