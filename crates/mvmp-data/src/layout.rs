//! The on-disk MVMP-HMR dataset layout, version 1 (docs/dataset-format.md).
//!
//! ```text
//! ROOT/dataset.json                       index: format, version, name, body model, scene list
//! ROOT/<scene>/scene.json                 frame list
//! ROOT/<scene>/cameras.json               the rig (mvmp-rig file, metres)
//! ROOT/<scene>/<frame>/annotation.json    people: SMPL-X, 3D joints, per-view 2D joints, boxes, occlusion
//! ROOT/<scene>/<frame>/<image per view>   RGB, PNG or JPEG, named in the annotation
//! ROOT/<scene>/<frame>/depth_VV.png       optional: 16-bit depth along the optical axis, millimetres
//! ROOT/<scene>/<frame>/mask_VV.png        optional: 8-bit instance masks, person index + 1, 0 = none
//! ```
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::DataError;
use mvmp_geom::Rig;
use mvmp_io::write_atomic;
use mvmp_smplx::SmplxParams;

pub const DATASET_FORMAT: &str = "mvmp-dataset";
pub const SCENE_FORMAT: &str = "mvmp-scene";
pub const ANNOTATION_FORMAT: &str = "mvmp-annotation";
/// The layout version this build reads and writes.
pub const SCHEMA_VERSION: u32 = 1;

/// `dataset.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetIndex {
    pub format: String,
    pub version: u32,
    pub name: String,
    /// The body model the SMPL-X parameters refer to: `standin:SEED` for the stand-in, else a path
    /// (relative to the dataset root or absolute) to an `SMPLX_*.npz`.
    pub body_model: String,
    pub scenes: Vec<String>,
}

/// `scene.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneIndex {
    pub format: String,
    pub version: u32,
    pub frames: Vec<String>,
    /// Size of the capture area (metres, x and y), centred at the world origin.
    pub area: [f64; 2],
}

/// `annotation.json` of one frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Annotation {
    pub format: String,
    pub version: u32,
    /// Image file per view, relative to the frame directory, in rig order.
    pub images: Vec<String>,
    /// Depth file per view (16-bit PNG, millimetres along the optical axis; 0 = no surface).
    #[serde(default)]
    pub depth: Option<Vec<String>>,
    /// Instance mask per view (8-bit PNG, person index + 1; 0 = background).
    #[serde(default)]
    pub masks: Option<Vec<String>>,
    pub people: Vec<Person>,
}

/// One person in a frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Person {
    /// Identity, stable across the frames of a scene.
    pub id: u32,
    /// SMPL-X parameters in the world (standard smplx keys, axis-angle; `transl` in smplx's meaning).
    pub smplx: SmplxParams,
    /// The pelvis in the world (metres): the model's translation `T_wld` (docs/architecture.md, SMPL-X).
    pub pelvis: [f64; 3],
    /// The 127 SMPL-X joints in the world (metres).
    pub joints_3d: Vec<[f64; 3]>,
    /// Per view, in rig order.
    pub views: Vec<PersonView>,
}

/// A person as seen by one view.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PersonView {
    /// Per joint `[u, v, visible]` in original image pixels; visible = 1 when the joint is in the image,
    /// in front of the camera and not hidden by another person.
    pub joints_2d: Vec<[f64; 3]>,
    /// Bounding box `[x0, y0, x1, y1]` of the visible silhouette, `null` when no pixel is visible.
    pub bbox: Option<[f64; 4]>,
    /// Pixels of the person's whole silhouette in the image (others ignored) and of its visible part.
    pub silhouette_pixels: u32,
    pub visible_pixels: u32,
}

impl PersonView {
    /// Fraction of the silhouette hidden by other people; `None` when the person is outside the view.
    pub fn occlusion(&self) -> Option<f64> {
        (self.silhouette_pixels > 0)
            .then(|| 1.0 - self.visible_pixels as f64 / self.silhouette_pixels as f64)
    }
}

fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, DataError> {
    let text = std::fs::read_to_string(path).map_err(|e| DataError::io(path, e))?;
    mvmp_io::parse_json(&text).map_err(|e| DataError::file(path, format!("invalid: {e}")))
}

fn check_header(path: &Path, format: &str, want: &str, version: u32) -> Result<(), DataError> {
    if format != want {
        return Err(DataError::file(
            path,
            format!("key `format` is {format:?}, expected {want:?}"),
        ));
    }
    if version != SCHEMA_VERSION {
        return Err(DataError::file(
            path,
            format!("key `version` is {version}, this build reads version {SCHEMA_VERSION}"),
        ));
    }
    Ok(())
}

/// Write a value as pretty JSON, atomically.
pub fn write_json<T: Serialize>(path: &Path, value: &T) -> Result<(), DataError> {
    let text = serde_json::to_string_pretty(value).expect("serialisable");
    Ok(write_atomic(path, text.as_bytes())?)
}

/// The first problem of a list of names of entries in one directory: at least one, each a plain name (no
/// path, no `..`) and none twice (an entry listed twice is read, trained on and scored twice).
pub fn name_problem(key: &str, names: &[String]) -> Option<String> {
    if names.is_empty() {
        return Some(format!("key `{key}` is empty"));
    }
    for (i, name) in names.iter().enumerate() {
        let mut parts = Path::new(name).components();
        let plain =
            matches!(parts.next(), Some(std::path::Component::Normal(_))) && parts.next().is_none();
        if !plain {
            return Some(format!(
                "key `{key}[{i}]` = {name:?} is not a name in its directory"
            ));
        }
        // Compared as paths: `a` and `a/` (or `a/.`) are the same entry.
        if let Some(j) = names[..i]
            .iter()
            .position(|n| Path::new(n) == Path::new(name))
        {
            return Some(format!("key `{key}[{i}]` = {name:?} repeats `{key}[{j}]`"));
        }
    }
    None
}

impl DatasetIndex {
    pub fn read(root: &Path) -> Result<Self, DataError> {
        let path = root.join("dataset.json");
        let d: DatasetIndex = read_json(&path)?;
        check_header(&path, &d.format, DATASET_FORMAT, d.version)?;
        if let Some(what) = name_problem("scenes", &d.scenes) {
            return Err(DataError::file(&path, what));
        }
        Ok(d)
    }
}

impl SceneIndex {
    pub fn read(scene_dir: &Path) -> Result<Self, DataError> {
        let path = scene_dir.join("scene.json");
        let s: SceneIndex = read_json(&path)?;
        check_header(&path, &s.format, SCENE_FORMAT, s.version)?;
        if let Some(what) = name_problem("frames", &s.frames) {
            return Err(DataError::file(&path, what));
        }
        use mvmp_smplx::params::MAX_TRANSLATION;
        if !s
            .area
            .iter()
            .all(|&a| a > 0.0 && a <= 2.0 * MAX_TRANSLATION)
        {
            return Err(DataError::file(
                &path,
                format!(
                    "key `area` = {:?}: expected two sides of 0 to {} m",
                    s.area,
                    2.0 * MAX_TRANSLATION
                ),
            ));
        }
        Ok(s)
    }
}

impl Annotation {
    /// Read and validate an annotation against the number of views of its rig.
    pub fn read(path: &Path, num_views: usize) -> Result<Self, DataError> {
        let a: Annotation = read_json(path)?;
        check_header(path, &a.format, ANNOTATION_FORMAT, a.version)?;
        a.validate(path, num_views)?;
        Ok(a)
    }

    /// Read an annotation and list every problem [`Annotation::validate`] would stop at the first of
    /// (an unreadable file or a wrong header is still an error).
    pub fn read_with_problems(
        path: &Path,
        num_views: usize,
    ) -> Result<(Self, Vec<String>), DataError> {
        let a: Annotation = read_json(path)?;
        check_header(path, &a.format, ANNOTATION_FORMAT, a.version)?;
        let problems = a.problems(num_views);
        Ok((a, problems))
    }

    /// The people hold `n` joints, what the body model `body_model` outputs (losses and metrics index them
    /// by its layout); `validate` has checked that every person holds as many as the first.
    pub fn check_joints(&self, n: usize, body_model: &str) -> Result<(), String> {
        check_joints(&self.people, n, body_model)
    }

    /// Consistency of counts and values; errors name the key path and the value.
    pub fn validate(&self, path: &Path, num_views: usize) -> Result<(), DataError> {
        match self.problems(num_views).into_iter().next() {
            Some(what) => Err(DataError::file(path, what)),
            None => Ok(()),
        }
    }

    /// Every problem of the annotation against a rig of `num_views` cameras, in file order (empty when
    /// it is valid): `data check` lists them all, readers stop at the first.
    pub fn problems(&self, num_views: usize) -> Vec<String> {
        let mut out = Vec::new();
        if self.images.len() != num_views {
            out.push(format!(
                "key `images` lists {} images, the rig has {num_views} cameras",
                self.images.len()
            ));
        }
        out.extend(name_problem("images", &self.images));
        for (key, list) in [("depth", &self.depth), ("masks", &self.masks)] {
            if let Some(l) = list
                && l.len() != num_views
            {
                out.push(format!(
                    "key `{key}` lists {} files, the rig has {num_views} cameras",
                    l.len()
                ));
            }
            out.extend(list.as_ref().and_then(|l| name_problem(key, l)));
        }
        if self.people.len() > MAX_PEOPLE_PER_FRAME {
            out.push(format!(
                "key `people` lists {} people; at most {MAX_PEOPLE_PER_FRAME} per frame",
                self.people.len()
            ));
            return out;
        }
        // People are compared with the first only when its count is one the layout allows.
        let first = self
            .people
            .first()
            .map(|p| p.joints_3d.len())
            .filter(|n| joint_counts().contains(n));
        for (i, p) in self.people.iter().enumerate() {
            if let Some(j) = self.people[..i].iter().position(|q| q.id == p.id) {
                out.push(format!("people[{i}].id = {} repeats people[{j}].id", p.id));
            }
            person_problems(i, p, first, num_views, &mut out);
        }
        out
    }
}

/// Most people one frame's annotation may hold (every pair's ids are compared, and each person is
/// matched against every prediction).
pub const MAX_PEOPLE_PER_FRAME: usize = 1_000;

/// The joint counts a body layer outputs (with face landmarks, without, the LBS joints alone);
/// downstream code indexes joints by these layouts.
fn joint_counts() -> [usize; 3] {
    use mvmp_smplx::names::{EXTRA_VERTEX_JOINTS, NUM_JOINTS, NUM_JOINTS_WITH_LANDMARKS};
    [
        NUM_JOINTS_WITH_LANDMARKS,
        NUM_JOINTS + EXTRA_VERTEX_JOINTS.len(),
        NUM_JOINTS,
    ]
}

/// The problems of `people[i]`: its joint counts (one of the layouts, the same as the first person's),
/// its SMPL-X parameters, finite positions, one entry per camera.
fn person_problems(
    i: usize,
    p: &Person,
    first: Option<usize>,
    num_views: usize,
    out: &mut Vec<String>,
) {
    let n = p.joints_3d.len();
    let counts_before = out.len();
    let [with_landmarks, without_landmarks, lbs] = joint_counts();
    if !joint_counts().contains(&n) {
        out.push(format!(
            "people[{i}].joints_3d has {n} joints: the layout holds {with_landmarks} \
             ({without_landmarks} for a body model without face landmarks, {lbs} for one \
             with fewer vertices than SMPL-X)"
        ));
    } else if let Some(f) = first.filter(|&f| f != n) {
        out.push(format!(
            "people[{i}].joints_3d has {n} joints, people[0].joints_3d has {f}"
        ));
    }
    // The 2D joints are compared with the 3D ones only when those have a count the layout allows.
    let count_ok = out.len() == counts_before;
    if let Err(e) = p.smplx.validate(&format!("people[{i}].smplx")) {
        out.push(e.to_string().trim_start_matches("parameters: ").into());
    }
    // World positions within the translation cap (metres); image positions within a camera's reach
    // (pixels). Larger values, finite in f64, overflow the f32 tensors they become.
    use mvmp_smplx::params::MAX_TRANSLATION;
    let within = |v: &[f64], cap: f64| v.iter().all(|x| x.abs() <= cap);
    if !within(&p.pelvis, MAX_TRANSLATION) {
        out.push(format!(
            "people[{i}].pelvis = {:?} is not a position within {MAX_TRANSLATION} m",
            p.pelvis
        ));
    }
    if let Some(k) = p.joints_3d.iter().position(|j| !within(j, MAX_TRANSLATION)) {
        out.push(format!(
            "people[{i}].joints_3d[{k}] = {:?} is not a position within {MAX_TRANSLATION} m",
            p.joints_3d[k]
        ));
    }
    if p.views.len() != num_views {
        out.push(format!(
            "people[{i}].views has {} entries, the rig has {num_views} cameras",
            p.views.len()
        ));
    }
    for (v, pv) in p.views.iter().enumerate() {
        if count_ok && pv.joints_2d.len() != n {
            out.push(format!(
                "people[{i}].views[{v}].joints_2d has {} joints, joints_3d has {n}",
                pv.joints_2d.len()
            ));
        }
        let bad_2d = |j: &[f64; 3]| !within(&j[..2], MAX_PIXEL) || !(0.0..=1.0).contains(&j[2]);
        if let Some(k) = pv.joints_2d.iter().position(bad_2d) {
            out.push(format!(
                "people[{i}].views[{v}].joints_2d[{k}] = {:?}: expected [u, v] within {MAX_PIXEL} \
                 pixels and a visibility from 0 to 1",
                pv.joints_2d[k]
            ));
        }
        if let Some(b) = pv.bbox
            && !(within(&b, MAX_PIXEL) && b[0] <= b[2] && b[1] <= b[3])
        {
            out.push(format!(
                "people[{i}].views[{v}].bbox = {b:?}: expected [x0, y0, x1, y1] within {MAX_PIXEL} \
                 pixels with x0 <= x1 and y0 <= y1"
            ));
        }
        if pv.visible_pixels > pv.silhouette_pixels {
            out.push(format!(
                "people[{i}].views[{v}]: visible_pixels {} exceeds silhouette_pixels {}",
                pv.visible_pixels, pv.silhouette_pixels
            ));
        }
    }
}

/// The largest image coordinate an annotation may hold (pixels): a joint just in front of a camera
/// projects far outside its image and is kept; one beyond this is a damaged file.
pub const MAX_PIXEL: f64 = 1.0e12;

/// The people hold `n` joints, what the body model `body_model` outputs (losses and metrics index them
/// by its layout); an annotation's validation has checked that every person holds as many as the first.
pub fn check_joints(people: &[Person], n: usize, body_model: &str) -> Result<(), String> {
    match people.first() {
        Some(p) if p.joints_3d.len() != n => Err(format!(
            "people[0].joints_3d has {} joints, the body model `{body_model}` outputs {n}",
            p.joints_3d.len()
        )),
        _ => Ok(()),
    }
}

/// One frame of a dataset: where it is and what it holds.
#[derive(Debug, Clone)]
pub struct FrameRef {
    pub scene: usize,
    pub scene_name: String,
    pub frame_name: String,
    pub dir: PathBuf,
}

/// An opened dataset: the index, every scene's rig and frame list.
#[derive(Debug, Clone)]
pub struct DatasetLayout {
    pub root: PathBuf,
    pub index: DatasetIndex,
    pub scenes: Vec<SceneEntry>,
}

#[derive(Debug, Clone)]
pub struct SceneEntry {
    pub name: String,
    pub dir: PathBuf,
    pub rig: Rig,
    pub index: SceneIndex,
}

impl DatasetLayout {
    /// Open a dataset root: reads `dataset.json`, each `scene.json` and `cameras.json`.
    pub fn open(root: &Path) -> Result<Self, DataError> {
        let index = DatasetIndex::read(root)?;
        let mut scenes = Vec::with_capacity(index.scenes.len());
        for name in &index.scenes {
            let dir = root.join(name);
            let si = SceneIndex::read(&dir)?;
            let rig = Rig::read(&dir.join("cameras.json"))?;
            scenes.push(SceneEntry {
                name: name.clone(),
                dir,
                rig,
                index: si,
            });
        }
        Ok(DatasetLayout {
            root: root.to_path_buf(),
            index,
            scenes,
        })
    }

    /// Every frame, scene by scene.
    pub fn frames(&self) -> Vec<FrameRef> {
        self.scenes
            .iter()
            .enumerate()
            .flat_map(|(si, s)| {
                s.index.frames.iter().map(move |f| FrameRef {
                    scene: si,
                    scene_name: s.name.clone(),
                    frame_name: f.clone(),
                    dir: s.dir.join(f),
                })
            })
            .collect()
    }

    /// The body model the dataset's parameters refer to.
    pub fn body_model(&self) -> Result<mvmp_smplx::BodyModel, DataError> {
        load_body_model(&self.index.body_model, &self.root)
    }
}

/// Whether two body-model references name the same model: the same stand-in seed, or paths to the same
/// file (each relative to its own base).
pub fn same_body_model(a: &str, a_base: &Path, b: &str, b_base: &Path) -> bool {
    let key = |r: &str, base: &Path| match r.strip_prefix("standin:") {
        Some(seed) => Some(format!("standin:{seed}")),
        None => std::fs::canonicalize(base.join(r))
            .ok()
            .map(|p| p.display().to_string()),
    };
    matches!((key(a, a_base), key(b, b_base)), (Some(x), Some(y)) if x == y)
}

/// Resolve a body-model reference: `standin:SEED` or a path (relative to `base` or absolute).
pub fn load_body_model(reference: &str, base: &Path) -> Result<mvmp_smplx::BodyModel, DataError> {
    if let Some(seed) = reference.strip_prefix("standin:") {
        let seed: u64 = seed.parse().map_err(|_| {
            DataError::file(
                base.join("dataset.json"),
                format!("key `body_model` is {reference:?}: expected `standin:SEED` or a path"),
            )
        })?;
        return Ok(mvmp_smplx::standin_model(seed));
    }
    let p = base.join(reference);
    if !p.exists() {
        return Err(DataError::file(
            p,
            "no such file (the body model that key `body_model` names)",
        ));
    }
    Ok(mvmp_smplx::BodyModel::load(&p)?)
}

#[cfg(test)]
mod tests {
    use super::load_body_model;

    #[test]
    fn a_missing_body_model_is_named_with_its_key() {
        let base = std::env::temp_dir().join("mvmp-no-such-dir");
        let err = load_body_model("SMPLX_NEUTRAL.npz", &base)
            .expect_err("a missing file is refused")
            .to_string();
        assert!(err.contains("SMPLX_NEUTRAL.npz"), "{err}");
        assert!(err.contains("`body_model`"), "{err}");
        let err = load_body_model("standin:x", &base).expect_err("refused");
        assert!(err.to_string().contains("standin:x"), "{err}");
    }
}
