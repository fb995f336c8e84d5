//! Property tests of the file readers: a valid model, training or synthesis config, camera rig,
//! annotation, SMPL-X parameter file, Panoptic calibration or body file, Human3.6M camera file, body-model
//! npz or run state (`state.json`) with one number replaced by an arbitrary value (any float, infinities and
//! NaN included, huge integers, another type) is either refused with an error or read into values that are
//! all finite and pass validation; so is a stored `people.npz` with one array damaged (a value, a row or a
//! column too few, flattened, or missing), or with one array's `.npy` header lying (any shape, its
//! product beyond the readers' caps or overflowing 64 bits included, any dtype, either order, with as many
//! values after it as it claims or others), and so is a body-model npz with such a header. A synthetic
//! dataset whose `dataset.json` or `scene.json` has one value replaced (or its scene or frame list spelled
//! otherwise) either fails to open or opens, summarises and loads into valid, finite values. No input
//! panics.
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use mvmp::data::Annotation;
use mvmp::data::synth::{SynthConfig, generate};
use mvmp::data::{h36m, panoptic};
use mvmp::geom::Rig;
use mvmp::model::ModelConfig;
use mvmp::smplx::SmplxParams;
use mvmp::train::{RunDir, RunState, TrainConfig};
use proptest::prelude::*;
use proptest::sample::Index;

/// A small synthetic dataset: its rig and annotation are the valid JSON documents mutated below.
fn dataset() -> &'static Path {
    static DIR: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    let (_, p) = DIR.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("ds");
        let mut c = SynthConfig {
            name: "readers".into(),
            scenes: 1,
            frames_per_scene: 1,
            people: [1, 2],
            area: [3.0, 3.0],
            image_size: [48, 32],
            ..Default::default()
        };
        c.cameras.count = 2;
        generate(&c, &out, Path::new("."), &|| {}).unwrap();
        (dir, out)
    });
    p
}

fn repo(rel: &str) -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join(rel)).unwrap()
}

/// Any float (NaN, infinities, subnormals and extremes included).
fn float() -> impl Strategy<Value = f64> {
    prop_oneof![
        any::<f64>(),
        Just(f64::NAN),
        Just(f64::INFINITY),
        Just(f64::NEG_INFINITY),
        -1e3..1e3f64,
    ]
}

fn toml_value() -> impl Strategy<Value = toml::Value> {
    prop_oneof![
        float().prop_map(toml::Value::Float),
        any::<i64>().prop_map(toml::Value::Integer),
        (-5i64..50).prop_map(toml::Value::Integer),
        Just(toml::Value::String("x".into())),
        Just(toml::Value::Array(vec![])),
    ]
}

fn json_value() -> impl Strategy<Value = serde_json::Value> {
    prop_oneof![
        float()
            .prop_filter("JSON numbers are finite", |x| x.is_finite())
            .prop_map(|x| serde_json::json!(x)),
        any::<i64>().prop_map(|x| serde_json::json!(x)),
        (-5i64..50).prop_map(|x| serde_json::json!(x)),
        Just(serde_json::Value::Null),
        Just(serde_json::json!("x")),
        Just(serde_json::json!([])),
    ]
}

/// Replace the `k`-th number (in walk order) of a TOML tree; true once replaced.
fn toml_set(v: &mut toml::Value, k: &mut usize, value: &toml::Value) -> bool {
    match v {
        toml::Value::Integer(_) | toml::Value::Float(_) => {
            if *k == 0 {
                *v = value.clone();
                return true;
            }
            *k -= 1;
            false
        }
        toml::Value::Table(t) => t.iter_mut().any(|(_, x)| toml_set(x, k, value)),
        toml::Value::Array(a) => a.iter_mut().any(|x| toml_set(x, k, value)),
        _ => false,
    }
}

/// `doc` with one of its numbers (chosen by `at`) replaced by `value`.
fn mutate_toml(doc: &str, at: Index, value: toml::Value) -> String {
    let mut d: toml::Value = toml::from_str(doc).unwrap();
    // A walk from usize::MAX never reaches 0: it only counts the numbers.
    let mut count = usize::MAX;
    toml_set(&mut d.clone(), &mut count, &value);
    let mut k = at.index(usize::MAX - count);
    assert!(toml_set(&mut d, &mut k, &value));
    toml::to_string(&d).unwrap()
}

fn json_set(v: &mut serde_json::Value, k: &mut usize, value: &serde_json::Value) -> bool {
    match v {
        serde_json::Value::Number(_) => {
            if *k == 0 {
                *v = value.clone();
                return true;
            }
            *k -= 1;
            false
        }
        serde_json::Value::Object(m) => m.values_mut().any(|x| json_set(x, k, value)),
        serde_json::Value::Array(a) => a.iter_mut().any(|x| json_set(x, k, value)),
        _ => false,
    }
}

fn mutate_json(doc: &str, at: Index, value: serde_json::Value) -> String {
    let mut d: serde_json::Value = serde_json::from_str(doc).unwrap();
    // A walk from usize::MAX never reaches 0: it only counts the numbers.
    let mut count = usize::MAX;
    json_set(&mut d.clone(), &mut count, &value);
    let mut k = at.index(usize::MAX - count);
    assert!(json_set(&mut d, &mut k, &value));
    d.to_string()
}

/// Every number in a serialisable value is finite (through TOML, which keeps NaN and infinities as
/// such where JSON would write null).
fn all_finite(v: &impl serde::Serialize) -> bool {
    fn walk(v: &toml::Value) -> bool {
        match v {
            toml::Value::Float(x) => x.is_finite(),
            toml::Value::Array(a) => a.iter().all(walk),
            toml::Value::Table(t) => t.iter().all(|(_, x)| walk(x)),
            _ => true,
        }
    }
    walk(&toml::Value::try_from(v).expect("serialisable as TOML"))
}

/// A Panoptic calibration holding two HD cameras (cm, y down).
fn panoptic_calibration() -> String {
    let cam = |name: &str, s: f64| {
        let c = (1.0 - s * s).sqrt();
        serde_json::json!({
            "name": name, "type": "hd", "resolution": [1920, 1080], "panel": 0, "node": 1,
            "K": [[1400.0, 0.0, 960.0], [0.0, 1400.0, 540.0], [0.0, 0.0, 1.0]],
            "distCoef": [-0.2, 0.1, 0.001, -0.001, 0.0],
            "R": [[c, 0.0, -s], [0.0, 1.0, 0.0], [s, 0.0, c]],
            "t": [[10.0], [-20.0], [400.0]],
        })
    };
    serde_json::json!({"calibDataSource": "readers", "cameras": [cam("00_03", 0.6), cam("00_06", -0.8)]})
        .to_string()
}

/// A Panoptic `body3DScene` file with two people of 19 joints (x, y, z, confidence).
fn panoptic_bodies() -> String {
    let body = |id: i64| {
        let j: Vec<f64> = (0..19)
            .flat_map(|i| [30.0 * id as f64, -100.0 - i as f64, 10.0, 0.8])
            .collect();
        serde_json::json!({"id": id, "joints19": j})
    };
    serde_json::json!({"version": 0.7, "univTime": 1.0, "fpsType": "hd_29_97", "bodies": [body(0), body(1)]})
        .to_string()
}

fn rig_is_finite(rig: &Rig) -> bool {
    cameras_are_finite(&rig.cameras)
}

fn cameras_are_finite(cameras: &[mvmp::geom::Camera]) -> bool {
    cameras.iter().all(|c| {
        c.k.iter()
            .chain(c.r.iter())
            .chain(c.t.iter())
            .all(|x| x.is_finite())
            && c.width > 0
            && c.height > 0
    })
}

fn write(dir: &Path, name: &str, text: &str) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(192))]

    #[test]
    fn model_configs(at in any::<Index>(), value in toml_value()) {
        let dir = tempfile::tempdir().unwrap();
        let text = mutate_toml(&repo("configs/model/tiny.toml"), at, value);
        if let Ok(cfg) = ModelConfig::read(&write(dir.path(), "model.toml", &text)) {
            prop_assert!(cfg.validate().is_ok());
            prop_assert!(all_finite(&cfg), "{text}");
        }
    }

    #[test]
    fn training_configs(at in any::<Index>(), value in toml_value()) {
        let dir = tempfile::tempdir().unwrap();
        write(dir.path(), "model.toml", &repo("configs/model/tiny.toml"));
        let base = repo("configs/train/tiny.toml").replace("../model/tiny.toml", "model.toml");
        let text = mutate_toml(&base, at, value);
        if let Ok((cfg, _)) = TrainConfig::read(&write(dir.path(), "train.toml", &text)) {
            prop_assert!(all_finite(&cfg), "{text}");
            prop_assert!(cfg.stage1.lr > 0.0 && cfg.stage2.lr > 0.0);
        }
    }

    #[test]
    fn synthesis_configs(at in any::<Index>(), value in toml_value()) {
        let dir = tempfile::tempdir().unwrap();
        let text = mutate_toml(&repo("configs/synth/tiny.toml"), at, value);
        if let Ok(cfg) = SynthConfig::read(&write(dir.path(), "synth.toml", &text)) {
            prop_assert!(all_finite(&cfg), "{text}");
        }
    }

    #[test]
    fn rigs(at in any::<Index>(), value in json_value()) {
        let dir = tempfile::tempdir().unwrap();
        let base = std::fs::read_to_string(dataset().join("scene_000/cameras.json")).unwrap();
        let text = mutate_json(&base, at, value);
        if let Ok(rig) = Rig::read(&write(dir.path(), "cameras.json", &text)) {
            prop_assert!(rig_is_finite(&rig), "{text}");
        }
    }

    #[test]
    fn panoptic_calibrations(at in any::<Index>(), value in json_value()) {
        let dir = tempfile::tempdir().unwrap();
        let text = mutate_json(&panoptic_calibration(), at, value);
        let path = write(dir.path(), "calibration_x.json", &text);
        if let Ok(rig) = panoptic::read_calibration(&path, &["00_03", "00_06"]) {
            prop_assert!(rig_is_finite(&rig), "{text}");
            prop_assert_eq!(rig.cameras.len(), 2);
        }
    }

    #[test]
    fn panoptic_body_files(at in any::<Index>(), value in json_value()) {
        let dir = tempfile::tempdir().unwrap();
        let text = mutate_json(&panoptic_bodies(), at, value);
        if let Ok(bodies) = panoptic::read_bodies(&write(dir.path(), "body3DScene_0.json", &text)) {
            for b in &bodies {
                prop_assert_eq!((b.joints.len(), b.confidence.len()), (19, 19), "{}", text);
                prop_assert!(b.joints.iter().flatten().chain(&b.confidence).all(|x| x.is_finite()));
            }
        }
    }

    #[test]
    fn human36m_camera_files(at in any::<Index>(), value in json_value()) {
        let dir = tempfile::tempdir().unwrap();
        let base = repo("crates/mvmp-data/tests/fixtures/h36m/camera-parameters.json");
        let text = mutate_json(&base, at, value);
        let path = write(dir.path(), "camera-parameters.json", &text);
        if let Ok(rig) = h36m::read_cameras(&path, "S9") {
            prop_assert!(rig_is_finite(&rig), "{text}");
            prop_assert_eq!(rig.cameras.len(), 4);
        }
    }

    #[test]
    fn annotations(at in any::<Index>(), value in json_value()) {
        let dir = tempfile::tempdir().unwrap();
        let base =
            std::fs::read_to_string(dataset().join("scene_000/frame_000000/annotation.json")).unwrap();
        let text = mutate_json(&base, at, value);
        if let Ok(a) = Annotation::read(&write(dir.path(), "annotation.json", &text), 2) {
            prop_assert!(all_finite(&a), "{text}");
            for p in &a.people {
                prop_assert!(p.smplx.validate("person").is_ok());
            }
        }
    }

    #[test]
    fn parameter_files(at in any::<Index>(), value in json_value()) {
        let dir = tempfile::tempdir().unwrap();
        let base = r#"{"betas": [0.5, -0.2], "expression": [0.1], "global_orient": [0.1, 0.2, 0.3],
            "jaw_pose": [0.1, 0.0, 0.0], "transl": [1.0, 2.0, 0.9]}"#;
        let text = mutate_json(base, at, value);
        if let Ok(bodies) = SmplxParams::read_json(&write(dir.path(), "params.json", &text)) {
            for b in &bodies {
                prop_assert!(b.validate("body").is_ok());
                prop_assert!(all_finite(b), "{text}");
            }
        }
    }
}

/// Whether a loaded body model is one a forward can use: finite arrays, convex skinning rows, regressor
/// rows that sum to 1.
fn body_model_is_sound(m: &mvmp::smplx::BodyModel) -> bool {
    let v = m.v_template.len() / 3;
    let j = mvmp::smplx::names::NUM_JOINTS;
    let finite = [
        &m.v_template,
        &m.shapedirs,
        &m.posedirs,
        &m.j_regressor,
        &m.weights,
    ]
    .iter()
    .all(|a| a.iter().all(|x| x.is_finite()));
    let sums_to_one = |r: &[f32]| (r.iter().sum::<f32>() - 1.0).abs() <= 1e-2;
    finite
        && m.weights
            .chunks(j)
            .all(|r| sums_to_one(r) && r.iter().all(|&w| w >= -1e-2))
        && m.j_regressor.chunks(v).all(sums_to_one)
}

proptest! {
    // Each case writes a whole model: fewer cases than the text readers.
    #![proptest_config(ProptestConfig::with_cases(8))]

    #[test]
    fn body_model_files(array in 0usize..5, at in any::<Index>(), value in float()) {
        use mvmp::smplx::BodyModel;
        static GOOD: OnceLock<BodyModel> = OnceLock::new();
        let mut m = GOOD.get_or_init(|| mvmp::smplx::standin_model(0)).clone();
        let a = match array {
            0 => &mut m.v_template,
            1 => &mut m.shapedirs,
            2 => &mut m.posedirs,
            3 => &mut m.j_regressor,
            _ => &mut m.weights,
        };
        let i = at.index(a.len());
        a[i] = value as f32;
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("SMPLX_NEUTRAL.npz");
        m.write_npz(&path).unwrap();
        if let Ok(read) = BodyModel::load(&path) {
            prop_assert!(body_model_is_sound(&read), "array {array}, entry {i} = {value}");
        }
    }
}

/// A run's `state.json` as training writes it.
fn run_state_text() -> String {
    let s = RunState {
        format: mvmp::train::run::STATE_FORMAT.into(),
        version: 1,
        stage: mvmp::train::Stage::Whole,
        epoch: 2,
        step_in_epoch: 3,
        global_step: 480,
        checkpoint: "checkpoints/step0000480-stage2-epoch002.bpk".into(),
        optimizer: Some("checkpoints/optim-step0000480-stage2-epoch002.bpk".into()),
        finished: false,
        model_sha256: "ab".repeat(32),
        checkpoint_sha256: "cd".repeat(32),
        optimizer_sha256: "ef".repeat(32),
        average: Some("checkpoints/average-step0000480-stage2-epoch002.bpk".into()),
        average_sha256: "01".repeat(32),
    };
    serde_json::to_string_pretty(&s).unwrap()
}

/// Strings a damaged or hand-edited `state.json` may hold where a file name belongs.
fn path_text() -> impl Strategy<Value = String> {
    prop_oneof![
        Just(String::new()),
        Just("/etc/passwd".to_string()),
        Just("../outside.bpk".to_string()),
        Just("checkpoints/../../outside.bpk".to_string()),
        Just("./checkpoints/x.bpk".to_string()),
        Just("checkpoints/\u{0}.bpk".to_string()),
        "[a-z./]{0,12}",
    ]
}

/// An npz array (of `people.npz` or a body model): name, shape, values.
type NpzArray = (String, Vec<u64>, Vec<f64>);

/// A valid two-person `people.npz`.
fn write_two_people(path: &Path) {
    let person = |x: f64| mvmp::smplx::people::StoredPerson {
        params: SmplxParams {
            betas: vec![0.3, -0.2],
            global_orient: vec![0.1, 0.2, x],
            body_pose: vec![0.05; 63],
            transl: vec![x, 1.0, 0.9],
            ..Default::default()
        },
        score: 0.8,
        pelvis: Some([x, 1.0, 0.9]),
    };
    mvmp::smplx::people::write_people_npz(path, &[person(0.5), person(-1.0)]).unwrap();
}

/// The arrays of a valid two-person `people.npz`.
fn people_arrays() -> Vec<NpzArray> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("people.npz");
    write_two_people(&path);
    let mut npz = npyz::npz::NpzArchive::open(&path).unwrap();
    let names: Vec<String> = npz.array_names().map(str::to_string).collect();
    names
        .into_iter()
        .map(|name| {
            let arr = npz.by_name(&name).unwrap().unwrap();
            let shape = arr.shape().to_vec();
            let data = arr
                .into_vec::<f32>()
                .unwrap()
                .into_iter()
                .map(f64::from)
                .collect();
            (name, shape, data)
        })
        .collect()
}

/// Writes `arrays` as an npz, as float64 or float32.
fn write_npz(path: &Path, arrays: &[NpzArray], f64s: bool) {
    use npyz::WriterBuilder;
    let mut w = npyz::npz::NpzWriter::create(path).unwrap();
    for (name, shape, data) in arrays {
        if f64s {
            let out = w
                .array::<f64>(name, Default::default())
                .unwrap()
                .default_dtype();
            let mut out = out.shape(shape).begin_nd().unwrap();
            out.extend(data.iter().copied()).unwrap();
            out.finish().unwrap();
        } else {
            let out = w
                .array::<f32>(name, Default::default())
                .unwrap()
                .default_dtype();
            let mut out = out.shape(shape).begin_nd().unwrap();
            out.extend(data.iter().map(|&x| x as f32)).unwrap();
            out.finish().unwrap();
        }
    }
    w.zip_writer().finish().unwrap();
}

/// How one array of a `people.npz` is damaged.
#[derive(Debug, Clone)]
enum Damage {
    /// One value replaced.
    Value(Index, f64),
    /// The last row or the last column dropped.
    DropRow,
    DropColumn,
    /// Flattened to one dimension.
    Flatten,
    /// Left out of the file.
    Missing,
}

fn damage() -> impl Strategy<Value = Damage> {
    prop_oneof![
        4 => (any::<Index>(), float()).prop_map(|(i, x)| Damage::Value(i, x)),
        1 => Just(Damage::DropRow),
        1 => Just(Damage::DropColumn),
        1 => Just(Damage::Flatten),
        1 => Just(Damage::Missing),
    ]
}

/// `arrays` with array `which` damaged.
fn damaged(mut arrays: Vec<NpzArray>, which: Index, how: &Damage) -> Vec<NpzArray> {
    let k = which.index(arrays.len());
    let (_, shape, data) = &mut arrays[k];
    let cols = if shape.len() == 2 {
        shape[1] as usize
    } else {
        1
    };
    match how {
        Damage::Value(i, x) => {
            let i = i.index(data.len());
            data[i] = *x;
        }
        Damage::DropRow => {
            data.truncate(data.len() - cols);
            shape[0] -= 1;
        }
        Damage::DropColumn if shape.len() == 2 => {
            *data = data
                .chunks(cols)
                .flat_map(|r| r[..cols - 1].to_vec())
                .collect();
            shape[1] -= 1;
        }
        Damage::DropColumn => {}
        Damage::Flatten => *shape = vec![data.len() as u64],
        Damage::Missing => {
            arrays.remove(k);
        }
    }
    arrays
}

proptest! {
    #[test]
    fn run_states(
        at in any::<Index>(),
        value in json_value(),
        key in 0usize..4,
        text in path_text(),
    ) {
        let dir = tempfile::tempdir().unwrap();
        let mut doc: serde_json::Value =
            serde_json::from_str(&mutate_json(&run_state_text(), at, value)).unwrap();
        let key = ["checkpoint", "optimizer", "average", "format"][key];
        doc[key] = serde_json::json!(text);
        let doc = doc.to_string();
        write(dir.path(), "state.json", &doc);
        let run = RunDir { root: dir.path().to_path_buf() };
        if let Ok(Some(s)) = run.state() {
            prop_assert_eq!(&s.format, mvmp::train::run::STATE_FORMAT);
            prop_assert_eq!(s.version, 1);
            let inside = |f: &str| {
                let p = Path::new(f);
                p.components().next().is_some()
                    && p.components().all(|c| matches!(c, std::path::Component::Normal(_)))
            };
            prop_assert!(inside(&s.checkpoint), "{doc}");
            prop_assert!(s.optimizer.as_deref().is_none_or(inside), "{doc}");
            prop_assert!(s.average.as_deref().is_none_or(inside), "{doc}");
            // The files it names are not there: the checks refuse, they do not panic.
            prop_assert!(run.check_checkpoint_files(&s).is_err());
        }
    }

    #[test]
    fn people_files(which in any::<Index>(), how in damage(), f64s in any::<bool>()) {
        static GOOD: OnceLock<Vec<NpzArray>> = OnceLock::new();
        let arrays = damaged(GOOD.get_or_init(people_arrays).clone(), which, &how);
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("people.npz");
        write_npz(&path, &arrays, f64s);
        if let Ok(people) = mvmp::smplx::people::read_people_npz(&path) {
            prop_assert!(people.len() <= 2, "{how:?}");
            for (i, p) in people.iter().enumerate() {
                prop_assert!(p.params.validate("person").is_ok(), "{how:?}");
                prop_assert!(all_finite(&p.params), "{how:?}");
                prop_assert!(p.score.is_finite(), "{how:?}");
                let near = |c: &[f64; 3]| c.iter().all(|x| x.abs() <= mvmp::smplx::params::MAX_TRANSLATION);
                prop_assert!(p.pelvis.as_ref().is_none_or(near), "person {i}: {how:?}");
            }
        }
    }
}

/// A copy of the directory tree `from` at `to`.
fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let dst = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_tree(&e.path(), &dst);
        } else {
            std::fs::copy(e.path(), &dst).unwrap();
        }
    }
}

/// Replace the `k`-th value (walk order, containers before what they hold, the document itself not
/// counted); true once replaced.
fn json_set_any(v: &mut serde_json::Value, k: &mut usize, value: &serde_json::Value) -> bool {
    let children: Vec<&mut serde_json::Value> = match v {
        serde_json::Value::Object(m) => m.values_mut().collect(),
        serde_json::Value::Array(a) => a.iter_mut().collect(),
        _ => return false,
    };
    for c in children {
        if *k == 0 {
            *c = value.clone();
            return true;
        }
        *k -= 1;
        if json_set_any(c, k, value) {
            return true;
        }
    }
    false
}

/// `doc` with one of its values (a number, a string, a list or an entry of one, chosen by `at`) replaced
/// by `value`.
fn mutate_json_any(doc: &str, at: Index, value: serde_json::Value) -> String {
    let mut d: serde_json::Value = serde_json::from_str(doc).unwrap();
    let mut count = usize::MAX;
    json_set_any(&mut d.clone(), &mut count, &value);
    let mut k = at.index(usize::MAX - count);
    assert!(json_set_any(&mut d, &mut k, &value));
    d.to_string()
}

/// What a damaged or hand-edited `dataset.json` or `scene.json` may hold where a number, a name or a
/// list belongs.
fn index_value() -> impl Strategy<Value = serde_json::Value> {
    prop_oneof![
        3 => json_value(),
        2 => path_text().prop_map(serde_json::Value::from),
        2 => prop::sample::select(vec![
            "scene_000",
            "frame_000000",
            "mvmp-dataset",
            "mvmp-scene",
            "standin:",
            "standin:-1",
            "standin:18446744073709551616",
            "SMPLX_NEUTRAL.npz",
            "/",
        ])
        .prop_map(serde_json::Value::from),
        1 => Just(serde_json::json!({})),
        1 => Just(serde_json::json!(true)),
    ]
}

/// How the dataset's `dataset.json` (`scene` false) or its scene's `scene.json` is edited.
#[derive(Debug, Clone)]
enum IndexEdit {
    /// One value replaced.
    Value {
        scene: bool,
        at: Index,
        value: serde_json::Value,
    },
    /// The list of scenes or frames replaced by names of its one entry, spelled in several ways, or
    /// other names.
    Names {
        scene: bool,
        names: Vec<&'static str>,
    },
}

fn index_edit() -> impl Strategy<Value = IndexEdit> {
    let spelling = prop::sample::select(vec![
        "{}", "{}/", "{}/.", "./{}", "{}//", "{}/../{}", "", "..", "x", "/",
    ]);
    prop_oneof![
        4 => (any::<bool>(), any::<Index>(), index_value())
            .prop_map(|(scene, at, value)| IndexEdit::Value { scene, at, value }),
        1 => (any::<bool>(), prop::collection::vec(spelling, 0..4))
            .prop_map(|(scene, names)| IndexEdit::Names { scene, names }),
    ]
}

/// A name of an entry in a directory: one plain component.
fn plain_name(name: &str) -> bool {
    let mut parts = Path::new(name).components();
    matches!(parts.next(), Some(std::path::Component::Normal(_))) && parts.next().is_none()
}

/// Names, each of an entry in one directory, no entry named twice (however spelled).
fn distinct_entries(names: &[String]) -> bool {
    names.iter().all(|n| plain_name(n))
        && names
            .iter()
            .enumerate()
            .all(|(i, n)| names[..i].iter().all(|m| Path::new(m) != Path::new(n)))
}

fn person_gt_is_finite(p: &mvmp::data::loader::PersonGt) -> bool {
    p.pose
        .iter()
        .chain(&p.betas)
        .chain(&p.expression)
        .chain(&p.pelvis)
        .chain(p.joints_3d.iter().flatten())
        .chain(p.joints_2d.iter().flatten().flatten())
        .chain(&p.joint_valid)
        .all(|x| x.is_finite())
}

/// What an array reads back as where its header claims `written` (the values after the header, in the
/// order stored): C-order values of `shape`.
fn c_order(written: &[f64], shape: &[usize], fortran: bool) -> Vec<f64> {
    if !fortran {
        return written.to_vec();
    }
    (0..written.len())
        .map(|c| {
            // Row-major position `c` as an index per dimension, then as a column-major position.
            let (mut rem, mut at, mut stride) = (c, 0, 1);
            let mut idx = vec![0; shape.len()];
            for d in (0..shape.len()).rev() {
                idx[d] = rem % shape[d];
                rem /= shape[d];
            }
            for d in 0..shape.len() {
                at += idx[d] * stride;
                stride *= shape[d];
            }
            written[at]
        })
        .collect()
}

/// dtypes a header may declare: floats and integers in either byte order, then kinds no reader takes
/// (bytes, booleans, half floats, complex numbers, strings, pickled objects).
const DTYPES: [(&str, usize); 14] = [
    ("<f8", 8),
    (">f8", 8),
    ("<f4", 4),
    (">f4", 4),
    ("<i8", 8),
    (">i4", 4),
    ("<u8", 8),
    ("<u4", 4),
    ("|u1", 1),
    ("|b1", 1),
    ("<f2", 2),
    ("<c16", 16),
    ("|S3", 3),
    ("|O", 8),
];

/// The value a file of dtype `descr` holds for `x` (numeric dtypes only).
fn cast(descr: &str, x: f64) -> f64 {
    match &descr[1..] {
        "f8" => x,
        "f4" => x as f32 as f64,
        "i8" => x as i64 as f64,
        "i4" => x as i32 as f64,
        "u8" => x as u64 as f64,
        "u4" => x as u32 as f64,
        _ => 0.0,
    }
}

/// `x` stored as dtype `descr` (zero bytes for the kinds no reader takes).
fn encode(descr: &str, size: usize, x: f64) -> Vec<u8> {
    macro_rules! bytes {
        ($v:expr) => {
            if descr.starts_with('>') {
                $v.to_be_bytes().to_vec()
            } else {
                $v.to_le_bytes().to_vec()
            }
        };
    }
    match &descr[1..] {
        "f8" => bytes!(x),
        "f4" => bytes!(x as f32),
        "i8" => bytes!(x as i64),
        "i4" => bytes!(x as i32),
        "u8" => bytes!(x as u64),
        "u4" => bytes!(x as u32),
        _ => vec![0; size],
    }
}

/// A `.npy` written by hand (no writer makes a header that lies): magic, version 1.0, header length, the
/// header dictionary padded to 64 bytes, then `payload`.
fn npy(descr: &str, fortran: bool, shape: &[u64], payload: &[u8]) -> Vec<u8> {
    let dims: Vec<String> = shape.iter().map(u64::to_string).collect();
    let shape = match dims.len() {
        1 => format!("({},)", dims[0]),
        _ => format!("({})", dims.join(", ")),
    };
    let order = if fortran { "True" } else { "False" };
    let mut h = format!("{{'descr': '{descr}', 'fortran_order': {order}, 'shape': {shape}, }}");
    while !(10 + h.len() + 1).is_multiple_of(64) {
        h.push(' ');
    }
    h.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend((h.len() as u16).to_le_bytes());
    out.extend(h.as_bytes());
    out.extend(payload);
    out
}

/// A copy of the npz `base` at `dst` with array `key` replaced by the raw `.npy` bytes `npy`.
fn npz_replacing(base: &Path, dst: &Path, key: &str, npy: &[u8]) {
    use npyz::zip;
    use std::io::Write;
    let mut zin = zip::ZipArchive::new(std::fs::File::open(base).unwrap()).unwrap();
    let mut zout = zip::ZipWriter::new(std::fs::File::create(dst).unwrap());
    let entry = format!("{key}.npy");
    for i in 0..zin.len() {
        let f = zin.by_index_raw(i).unwrap();
        if f.name() != entry {
            zout.raw_copy_file(f).unwrap();
        }
    }
    zout.start_file(entry, zip::write::FileOptions::default())
        .unwrap();
    zout.write_all(npy).unwrap();
    zout.finish().unwrap();
}

/// Every array of an npz (float, signed or unsigned integer) as f64 values.
fn npz_arrays(path: &Path) -> Vec<NpzArray> {
    let mut npz = npyz::npz::NpzArchive::open(path).unwrap();
    let names: Vec<String> = npz.array_names().map(str::to_string).collect();
    names
        .into_iter()
        .map(|name| {
            let arr = npz.by_name(&name).unwrap().unwrap();
            let shape = arr.shape().to_vec();
            let data = match arr.try_data::<f64>() {
                Ok(r) => r.map(Result::unwrap).collect(),
                Err(arr) => match arr.try_data::<f32>() {
                    Ok(r) => r.map(|x| f64::from(x.unwrap())).collect(),
                    Err(arr) => match arr.try_data::<i64>() {
                        Ok(r) => r.map(|x| x.unwrap() as f64).collect(),
                        Err(arr) => arr
                            .into_vec::<u32>()
                            .unwrap()
                            .into_iter()
                            .map(f64::from)
                            .collect(),
                    },
                },
            };
            (name, shape, data)
        })
        .collect()
}

/// Dimensions a lying header declares: none, a few, the readers' caps and around them, and ones whose
/// products overflow 64 bits.
fn dim() -> impl Strategy<Value = u64> {
    prop_oneof![
        Just(0u64),
        1..6u64,
        prop::sample::select(vec![
            1 << 20,
            1 << 25,
            (1 << 25) + 1,
            4_000_000_000,
            1 << 32,
            1 << 63,
            (1 << 63) + 1,
            6_148_914_691_236_517_206,
            u64::MAX,
        ]),
    ]
}

/// A header's shape, relative to that of the array it replaces.
#[derive(Debug, Clone)]
enum ShapeLie {
    Own,
    /// One dimension replaced.
    Dim(Index, u64),
    /// A dimension appended.
    Extra(u64),
    /// The last dimension dropped.
    Dropped,
    /// Any shape of up to four dimensions.
    Any(Vec<u64>),
    /// A shape whose product wraps in 64 bits to a small count (2, 0, 1, 0, 3 values).
    Wrapping(Vec<u64>),
}

/// How many values follow the header.
#[derive(Debug, Clone)]
enum Held {
    /// What the header claims, counted in 64 bits that wrap (the array's own count where that is more
    /// than 2^16: no file holds hundreds of megabytes here).
    Claimed,
    /// The array's own count.
    Own,
    /// One fewer than claimed.
    Fewer,
    Few(usize),
}

/// An array's `.npy` header and the values after it.
#[derive(Debug, Clone)]
struct Lie {
    dtype: usize,
    fortran: bool,
    shape: ShapeLie,
    held: Held,
}

fn lie() -> impl Strategy<Value = Lie> {
    let dtype = prop_oneof![4 => 0..4usize, 2 => 4..8usize, 1 => 8..DTYPES.len()];
    let shape = prop_oneof![
        3 => Just(ShapeLie::Own),
        2 => (any::<Index>(), dim()).prop_map(|(i, d)| ShapeLie::Dim(i, d)),
        1 => dim().prop_map(ShapeLie::Extra),
        1 => Just(ShapeLie::Dropped),
        2 => prop::collection::vec(dim(), 0..5).prop_map(ShapeLie::Any),
        3 => prop::sample::select(vec![
            vec![(1u64 << 63) + 1, 2],
            vec![1 << 32, 1 << 32, 1],
            vec![6_148_914_691_236_517_206, 3],
            vec![u64::MAX, u64::MAX],
            vec![1 << 63, 2],
            vec![u64::MAX, 3, u64::MAX],
        ])
        .prop_map(ShapeLie::Wrapping),
    ];
    let held = prop_oneof![
        4 => Just(Held::Claimed),
        1 => Just(Held::Own),
        1 => Just(Held::Fewer),
        1 => (0..8usize).prop_map(Held::Few),
    ];
    (dtype, any::<bool>(), shape, held).prop_map(|(dtype, fortran, shape, held)| Lie {
        dtype,
        fortran,
        shape,
        held,
    })
}

impl Lie {
    /// The header's shape and the values after it, for an array of shape `own` holding `values`.
    fn resolve(&self, own: &[u64], values: &[f64]) -> (Vec<u64>, Vec<f64>) {
        let shape = match &self.shape {
            ShapeLie::Own => own.to_vec(),
            ShapeLie::Dim(i, d) => {
                let mut s = own.to_vec();
                let k = i.index(s.len());
                s[k] = *d;
                s
            }
            ShapeLie::Extra(d) => own.iter().chain([d]).copied().collect(),
            ShapeLie::Dropped => own[..own.len() - 1].to_vec(),
            ShapeLie::Any(s) | ShapeLie::Wrapping(s) => s.clone(),
        };
        let claimed = shape.iter().fold(1u64, |a, &d| a.wrapping_mul(d));
        let claimed = if claimed <= 1 << 16 {
            claimed as usize
        } else {
            values.len()
        };
        let held = match self.held {
            Held::Claimed => claimed,
            Held::Own => values.len(),
            Held::Fewer => claimed.saturating_sub(1),
            Held::Few(n) => n,
        };
        let (descr, _) = DTYPES[self.dtype];
        let written = values
            .iter()
            .cycle()
            .take(held)
            .map(|&x| cast(descr, x))
            .collect();
        (shape, written)
    }

    /// The `.npy` bytes of an array of shape `own` holding `values`, and what follows its header.
    fn npy(&self, own: &[u64], values: &[f64]) -> (Vec<u8>, Vec<u64>, Vec<f64>) {
        let (shape, written) = self.resolve(own, values);
        let (descr, size) = DTYPES[self.dtype];
        let payload: Vec<u8> = written
            .iter()
            .flat_map(|&x| encode(descr, size, x))
            .collect();
        (npy(descr, self.fortran, &shape, &payload), shape, written)
    }
}

/// A copy of the npz `base` named `name` in a new directory with one of its `arrays` (picked by
/// `which`) replaced as `lie` says: the directory, the file, the array's key, the shape its header
/// claims, the values it holds and a description of the case.
struct LiedNpz {
    _dir: tempfile::TempDir,
    path: PathBuf,
    key: String,
    shape: Vec<u64>,
    written: Vec<f64>,
    case: String,
}

fn lied_npz(base: &Path, name: &str, arrays: &[NpzArray], which: Index, lie: &Lie) -> LiedNpz {
    let (key, own, values) = &arrays[which.index(arrays.len())];
    let (bytes, shape, written) = lie.npy(own, values);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join(name);
    npz_replacing(base, &path, key, &bytes);
    let (descr, _) = DTYPES[lie.dtype];
    let held = written.len();
    let case = format!(
        "{key}: {descr}, fortran {}, shape {shape:?}, {held} values",
        lie.fortran
    );
    LiedNpz {
        _dir: dir,
        path,
        key: key.clone(),
        shape,
        written,
        case,
    }
}

/// The values the header's shape claims, where the file holds that many (its product not overflowing;
/// values after the claimed ones are ignored, as numpy does).
fn claimed(shape: &[u64], written: &[f64]) -> Option<usize> {
    let n = shape.iter().try_fold(1u64, |a, &d| a.checked_mul(d))?;
    (n <= written.len() as u64).then_some(n as usize)
}

/// A body model of 4 vertices that loads: the layout of SMPL-X's file (every key, the 55-joint tree,
/// landmarks, hand means) at a size that is cheap to write for every case.
fn tiny_body_model() -> mvmp::smplx::BodyModel {
    use mvmp::smplx::names::{NUM_JOINTS, NUM_POSE_JOINTS, PARENTS};
    let v = 4;
    mvmp::smplx::BodyModel {
        v_template: vec![0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.1, 0.0, 0.0, 0.0, 0.1],
        faces: vec![[0, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]],
        shapedirs: (0..v * 3 * 20).map(|i| (i % 7) as f32 * 0.01).collect(),
        num_shape_components: 20,
        posedirs: (0..v * 3 * NUM_POSE_JOINTS * 9)
            .map(|i| (i % 5) as f32 * 0.001)
            .collect(),
        j_regressor: vec![0.25; NUM_JOINTS * v],
        weights: (0..v * NUM_JOINTS)
            .map(|i| {
                if i % NUM_JOINTS == i / NUM_JOINTS {
                    1.0
                } else {
                    0.0
                }
            })
            .collect(),
        parents: PARENTS.to_vec(),
        landmarks: Some(((0..51).map(|i| i % 4).collect(), vec![0.25; 51 * 3])),
        hands_mean: Some((vec![0.1; 45], vec![-0.1; 45])),
    }
}

/// What a loaded body model holds of the file's array `key` (C order), where it keeps the array.
fn model_array(m: &mvmp::smplx::BodyModel, key: &str) -> Vec<f64> {
    let f64s = |v: &[f32]| v.iter().map(|&x| f64::from(x)).collect::<Vec<_>>();
    let (lmk_faces, lmk_bary) = m.landmarks.clone().unwrap_or_default();
    let (hands_l, hands_r) = m.hands_mean.clone().unwrap_or_default();
    match key {
        "v_template" => f64s(&m.v_template),
        "shapedirs" => f64s(&m.shapedirs),
        "posedirs" => f64s(&m.posedirs),
        "J_regressor" => f64s(&m.j_regressor),
        "weights" => f64s(&m.weights),
        "lmk_bary_coords" => f64s(&lmk_bary),
        "hands_meanl" => f64s(&hands_l),
        "hands_meanr" => f64s(&hands_r),
        "f" => m.faces.iter().flatten().map(|&i| f64::from(i)).collect(),
        "lmk_faces_idx" => lmk_faces.iter().map(|&i| f64::from(i)).collect(),
        // The first row: each joint's parent (the root's marker read as -1).
        _ => m.parents.iter().map(|&p| f64::from(p)).collect(),
    }
}

/// What a person read from `people.npz` holds of array `key`.
fn stored_row(p: &mvmp::smplx::people::StoredPerson, key: &str) -> Vec<f64> {
    let q = &p.params;
    match key {
        "global_orient" => q.global_orient.clone(),
        "body_pose" => q.body_pose.clone(),
        "jaw_pose" => q.jaw_pose.clone(),
        "leye_pose" => q.leye_pose.clone(),
        "reye_pose" => q.reye_pose.clone(),
        "left_hand_pose" => q.left_hand_pose.clone(),
        "right_hand_pose" => q.right_hand_pose.clone(),
        "betas" => q.betas.clone(),
        "expression" => q.expression.clone(),
        "transl" => q.transl.clone(),
        "scores" => vec![p.score],
        _ => p.pelvis.map_or(vec![], |c| c.to_vec()),
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(192))]

    /// `dataset.json` or `scene.json` edited, then the dataset opened, summarised and its frame loaded as
    /// training does.
    #[test]
    fn dataset_indexes(edit in index_edit()) {
        use mvmp::data::dataset::FrameDataset;
        use mvmp::data::layout::{DATASET_FORMAT, SCENE_FORMAT, SCHEMA_VERSION};
        use mvmp::data::loader::{Split, ViewChoice};
        use mvmp::smplx::params::MAX_TRANSLATION;
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("ds");
        copy_tree(dataset(), &root);
        let (scene, file) = match &edit {
            IndexEdit::Value { scene, .. } | IndexEdit::Names { scene, .. } => {
                (*scene, if *scene { "scene_000/scene.json" } else { "dataset.json" })
            }
        };
        let base = std::fs::read_to_string(root.join(file)).unwrap();
        let text = match &edit {
            IndexEdit::Value { at, value, .. } => mutate_json_any(&base, *at, value.clone()),
            IndexEdit::Names { names, .. } => {
                let (key, own) =
                    if scene { ("frames", "frame_000000") } else { ("scenes", "scene_000") };
                let mut d: serde_json::Value = serde_json::from_str(&base).unwrap();
                d[key] = names.iter().map(|n| n.replace("{}", own)).collect();
                d.to_string()
            }
        };
        write(&root, file, &text);
        let Ok(layout) = mvmp::data::DatasetLayout::open(&root) else {
            return Ok(());
        };
        let index = &layout.index;
        prop_assert_eq!(
            (index.format.as_str(), index.version),
            (DATASET_FORMAT, SCHEMA_VERSION),
            "{}",
            text
        );
        prop_assert!(distinct_entries(&index.scenes), "{text}");
        prop_assert_eq!(layout.scenes.len(), index.scenes.len());
        for s in &layout.scenes {
            let si = &s.index;
            prop_assert_eq!(
                (si.format.as_str(), si.version),
                (SCENE_FORMAT, SCHEMA_VERSION),
                "{}",
                text
            );
            prop_assert!(distinct_entries(&si.frames), "{text}");
            prop_assert!(
                si.area.iter().all(|&a| a > 0.0 && a <= 2.0 * MAX_TRANSLATION),
                "{text}"
            );
            prop_assert!(rig_is_finite(&s.rig));
        }
        if let Ok(stats) = mvmp::data::stats::dataset_stats(&root) {
            prop_assert!(all_finite(&stats), "{text}");
        }
        // Another body model than the stand-in the dataset was made with: only ones that fail to load
        // are generated (a stand-in takes long to build).
        if index.body_model != "standin:0"
            && let Ok(m) = layout.body_model()
        {
            prop_assert!(body_model_is_sound(&m), "{text}");
        }
        if let Ok(ds) = FrameDataset::open(&root, Split::All, ViewChoice::Fixed(vec![0, 1]), 28) {
            prop_assert_eq!(ds.len(), layout.frames().len(), "{}", text);
            if let Ok(sample) = ds.load(0) {
                prop_assert_eq!(sample.images.len(), 2 * 3 * 28 * 28);
                prop_assert!(sample.images.iter().all(|x| x.is_finite()), "{text}");
                prop_assert!(cameras_are_finite(&sample.cameras), "{text}");
                prop_assert!(sample.people.iter().all(person_gt_is_finite), "{text}");
            }
        }
    }

    /// One array of a valid body-model npz replaced by one whose header declares any shape (its product
    /// beyond the reader's cap or overflowing 64 bits included), dtype and order, followed by as many
    /// values as it claims, or fewer, or others.
    #[test]
    fn body_model_headers(which in any::<Index>(), lie in lie()) {
        use mvmp::smplx::BodyModel;
        static BASE: OnceLock<(tempfile::TempDir, PathBuf, Vec<NpzArray>)> = OnceLock::new();
        let (_, base, arrays) = BASE.get_or_init(|| {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("SMPLX_NEUTRAL.npz");
            let model = tiny_body_model();
            model.write_npz(&path).unwrap();
            assert_eq!(BodyModel::load(&path).unwrap(), model);
            // The arrays the reader reads (the hand components are written for round trips only).
            let arrays = npz_arrays(&path)
                .into_iter()
                .filter(|(name, ..)| !name.starts_with("hands_components"))
                .collect();
            (dir, path, arrays)
        });
        let LiedNpz { _dir, path, key, shape, written, case } =
            lied_npz(base, "SMPLX_NEUTRAL.npz", arrays, which, &lie);
        if let Ok(m) = BodyModel::load(&path) {
            let n = claimed(&shape, &written);
            prop_assert!(n.is_some(), "{case}");
            prop_assert!(lie.dtype < 8, "{case}");
            prop_assert!(body_model_is_sound(&m), "{case}");
            let dims: Vec<usize> = shape.iter().map(|&d| d as usize).collect();
            let mut want = c_order(&written[..n.unwrap_or(0)], &dims, lie.fortran);
            if key == "kintree_table" {
                want.truncate(dims[1]);
                want[0] = -1.0;
            }
            // Float arrays are kept as float32; index arrays as integers.
            let index = ["f", "kintree_table", "lmk_faces_idx"].contains(&key.as_str());
            let want: Vec<f64> = want
                .iter()
                .map(|&x| if index { x } else { f64::from(x as f32) })
                .collect();
            prop_assert_eq!(model_array(&m, &key), want, "{}", case);
        }
    }

    /// One array of a valid `people.npz` replaced as in `body_model_headers`.
    #[test]
    fn people_file_headers(which in any::<Index>(), lie in lie()) {
        static BASE: OnceLock<(tempfile::TempDir, PathBuf, Vec<NpzArray>)> = OnceLock::new();
        let (_, base, arrays) = BASE.get_or_init(|| {
            let dir = tempfile::tempdir().unwrap();
            let path = dir.path().join("people.npz");
            write_two_people(&path);
            let arrays = npz_arrays(&path);
            (dir, path, arrays)
        });
        let LiedNpz { _dir, path, key, shape, written, case } =
            lied_npz(base, "people.npz", arrays, which, &lie);
        if let Ok(people) = mvmp::smplx::people::read_people_npz(&path) {
            let n = claimed(&shape, &written);
            prop_assert!(n.is_some(), "{case}");
            prop_assert!(lie.dtype < 4, "{case}");
            prop_assert_eq!(people.len(), 2, "{}", case);
            let dims: Vec<usize> = shape.iter().map(|&d| d as usize).collect();
            let want = c_order(&written[..n.unwrap_or(0)], &dims, lie.fortran);
            let width = want.len() / 2;
            for (i, p) in people.iter().enumerate() {
                prop_assert!(p.params.validate("person").is_ok(), "{case}");
                prop_assert!(all_finite(&p.params) && p.score.is_finite(), "{case}");
                let near = |c: &[f64; 3]| {
                    c.iter().all(|x| x.abs() <= mvmp::smplx::params::MAX_TRANSLATION)
                };
                prop_assert!(p.pelvis.as_ref().is_none_or(near), "{case}");
                let row = want[i * width..(i + 1) * width].to_vec();
                prop_assert_eq!(stored_row(p, &key), row, "{}", case);
            }
        }
    }
}
