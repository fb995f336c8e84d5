//! Property tests of the file readers: a valid model, training or synthesis config, camera rig,
//! annotation, SMPL-X parameter file, Panoptic calibration or body file, Human3.6M camera file, body-model
//! npz or run state (`state.json`) with one number replaced by an arbitrary value (any float, infinities and
//! NaN included, huge integers, another type) is either refused with an error or read into values that are
//! all finite and pass validation; so is a stored `people.npz` with one array damaged (a value, a row or a
//! column too few, flattened, or missing). No input panics.
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
    rig.cameras.iter().all(|c| {
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

/// An npz array as `people.npz` holds it: name, shape, values.
type NpzArray = (String, Vec<u64>, Vec<f64>);

/// The arrays of a valid two-person `people.npz`.
fn people_arrays() -> Vec<NpzArray> {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("people.npz");
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
    mvmp::smplx::people::write_people_npz(&path, &[person(0.5), person(-1.0)]).unwrap();
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
