//! The malformed-input corpus: every number in every kind of file mvmp reads (model, training and
//! synthesis configs; rigs, annotations and the scene index of a dataset; SMPL-X parameter files) is
//! replaced in turn by values no reader may accept, and the file goes through the command that reads it.
//! Every case must exit non-zero without a panic, name the file and the key (or the line), and leave no
//! output behind. Values that once got through are in the lists below; add every new one found.
use std::path::{Path, PathBuf};
use std::process::Command;

fn mvmp(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_mvmp"))
        .args(args)
        .output()
        .unwrap()
}

/// One malformed input: which file, which key (its path), the value put there, the command, and the
/// output the command would have made.
struct Case {
    file: PathBuf,
    key: String,
    value: String,
    args: Vec<String>,
    out: Option<PathBuf>,
}

/// What went wrong with a command that had to refuse its input, if anything: it succeeded, crashed,
/// its message (standard error and output) fails `names`, or it left `out` behind. `what` names the case.
fn verdict(
    o: &std::process::Output,
    what: &str,
    names: impl Fn(&str) -> bool,
    out: Option<&Path>,
) -> Option<String> {
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stderr),
        String::from_utf8_lossy(&o.stdout)
    );
    if o.status.success() {
        return Some(format!("{what}: accepted"));
    }
    if text.contains("panicked") || o.status.code().is_none() {
        return Some(format!("{what}: crashed: {text}"));
    }
    if !names(&text) {
        return Some(format!(
            "{what}: the message names neither file and key nor line: {text}"
        ));
    }
    match out {
        Some(out) if out.exists() => Some(format!("{what}: left {}", out.display())),
        _ => None,
    }
}

/// Run a case; a description of what went wrong, if anything.
fn failure(c: &Case) -> Option<String> {
    let args: Vec<&str> = c.args.iter().map(String::as_str).collect();
    let name = c.file.file_name().unwrap().to_string_lossy().into_owned();
    // The key's last name (`stage1.lr` -> `lr`, `grid.shape[2]` -> `shape`).
    let leaf = c.key.rsplit('.').next().unwrap().split('[').next().unwrap();
    let names = |t: &str| t.contains(&name) && (t.contains(leaf) || t.contains("line"));
    let what = format!("{} = {} in {name}", c.key, c.value);
    verdict(&mvmp(&args), &what, names, c.out.as_deref())
}

/// At least `min` cases ran (`n`) and none got through.
fn all_refused(n: usize, min: usize, failures: &[String]) {
    assert!(n > min, "{n} cases");
    assert!(
        failures.is_empty(),
        "{} of {n} cases failed:\n{}",
        failures.len(),
        failures.join("\n")
    );
}

/// The corpus's small valid dataset, synthesised into `dir/ds`.
fn synth_dataset(dir: &Path) -> PathBuf {
    std::fs::write(dir.join("synth.toml"), SYNTH).unwrap();
    let ds = dir.join("ds");
    let o = mvmp(&[
        "data",
        "synth",
        "--config",
        &s(&dir.join("synth.toml")),
        "--out",
        &s(&ds),
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    ds
}

/// Paths of the numeric leaves of a TOML document (`a.b`, `a.c[1]`).
fn toml_leaves(v: &toml::Value, path: &str, out: &mut Vec<String>) {
    match v {
        toml::Value::Integer(_) | toml::Value::Float(_) => out.push(path.to_string()),
        toml::Value::Table(t) => {
            for (k, x) in t {
                let p = if path.is_empty() {
                    k.clone()
                } else {
                    format!("{path}.{k}")
                };
                toml_leaves(x, &p, out);
            }
        }
        toml::Value::Array(a) => {
            for (i, x) in a.iter().enumerate() {
                toml_leaves(x, &format!("{path}[{i}]"), out);
            }
        }
        _ => {}
    }
}

/// The value at a leaf path, mutably (`a.b[1].c`).
fn toml_at<'a>(v: &'a mut toml::Value, path: &str) -> &'a mut toml::Value {
    path.split('.').fold(v, |v, part| {
        let mut pieces = part.split('[');
        let mut v = &mut v[pieces.next().unwrap()];
        for idx in pieces {
            v = &mut v[idx.trim_end_matches(']').parse::<usize>().unwrap()];
        }
        v
    })
}

/// Paths of the numeric leaves of a JSON document, through the first element of every array only (a
/// dataset file holds thousands of numbers of a few kinds).
fn json_leaves(v: &serde_json::Value, path: &str, out: &mut Vec<String>) {
    match v {
        serde_json::Value::Number(_) => out.push(path.to_string()),
        serde_json::Value::Object(m) => {
            for (k, x) in m {
                json_leaves(x, &format!("{path}/{k}"), out);
            }
        }
        serde_json::Value::Array(a) => {
            if let Some(x) = a.first() {
                json_leaves(x, &format!("{path}/0"), out);
            }
        }
        _ => {}
    }
}

/// Cases for every numeric leaf of a TOML file: `write` puts the mutated text in place and returns the
/// command and its output.
fn toml_cases(
    base: &str,
    file: &Path,
    values: &[toml::Value],
    command: &dyn Fn() -> (Vec<String>, Option<PathBuf>),
) -> Vec<(Case, String)> {
    let doc: toml::Value = toml::from_str(base).unwrap();
    let mut leaves = Vec::new();
    toml_leaves(&doc, "", &mut leaves);
    let mut cases = Vec::new();
    for key in leaves {
        for value in values {
            let mut d = doc.clone();
            *toml_at(&mut d, &key) = value.clone();
            let (args, out) = command();
            let case = Case {
                file: file.to_path_buf(),
                key: key.clone(),
                value: value.to_string(),
                args,
                out,
            };
            cases.push((case, toml::to_string(&d).unwrap()));
        }
    }
    cases
}

/// One case per `(key, value)`: `value` (TOML) put at `key` of `base`.
fn capped_cases(
    base: &str,
    file: &Path,
    values: &[(&str, &str)],
    command: &dyn Fn() -> (Vec<String>, Option<PathBuf>),
) -> Vec<(Case, String)> {
    let doc: toml::Value = toml::from_str(base).unwrap();
    values
        .iter()
        .map(|&(key, value)| {
            let mut d = doc.clone();
            let v: toml::Value =
                toml::from_str::<toml::Table>(&format!("v = {value}")).unwrap()["v"].clone();
            *toml_at(&mut d, key) = v;
            let (args, out) = command();
            let case = Case {
                file: file.to_path_buf(),
                key: key.into(),
                value: value.into(),
                args,
                out,
            };
            (case, toml::to_string(&d).unwrap())
        })
        .collect()
}

/// A JSON pointer as a key path: `/people/0/smplx/betas/0` -> `people[0].smplx.betas[0]`.
fn dotted(pointer: &str) -> String {
    let mut out = String::new();
    for seg in pointer.split('/').skip(1) {
        if seg.parse::<usize>().is_ok() {
            out += &format!("[{seg}]");
        } else {
            if !out.is_empty() {
                out.push('.');
            }
            out += seg;
        }
    }
    out
}

fn json_cases(
    file: &Path,
    values: &[serde_json::Value],
    command: &[String],
) -> Vec<(Case, String)> {
    let doc: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(file).unwrap()).unwrap();
    let mut leaves = Vec::new();
    json_leaves(&doc, "", &mut leaves);
    let mut cases = Vec::new();
    for key in leaves {
        for value in values {
            let mut d = doc.clone();
            *d.pointer_mut(&key).unwrap() = value.clone();
            let case = Case {
                file: file.to_path_buf(),
                key: dotted(&key),
                value: value.to_string(),
                args: command.to_vec(),
                out: None,
            };
            cases.push((case, serde_json::to_string_pretty(&d).unwrap()));
        }
    }
    cases
}

/// Write each case's text, run it, restore the file; every failure is collected.
fn run_all(cases: Vec<(Case, String)>, failures: &mut Vec<String>) -> usize {
    let n = cases.len();
    for (case, text) in cases {
        let original = std::fs::read(&case.file).ok();
        std::fs::write(&case.file, text).unwrap();
        failures.extend(failure(&case));
        // An accepted case's output would make the next one fail for the wrong reason.
        if let Some(out) = case.out.as_ref().filter(|o| o.exists()) {
            if out.is_dir() {
                std::fs::remove_dir_all(out).unwrap();
            } else {
                std::fs::remove_file(out).unwrap();
            }
        }
        match original {
            Some(b) => std::fs::write(&case.file, b).unwrap(),
            None => std::fs::remove_file(&case.file).unwrap(),
        }
    }
    n
}

/// The tiny model at 56 px on a 4 m grid: what the corpus's commands read and train.
fn small_model() -> String {
    std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/model/tiny.toml"),
    )
    .unwrap()
    .replace("image_size = 224", "image_size = 56")
    .replace("size = [4.5, 4.5, 2.0]", "size = [4.0, 4.0, 2.0]")
    .replace("shape = [32, 32, 8]", "shape = [8, 8, 4]")
    .replace("dim = 128", "dim = 16\nffn_ratio = 4")
}

fn s(p: &Path) -> String {
    p.to_string_lossy().into_owned()
}

const SYNTH: &str = r#"name = "corpus"
seed = 1
scenes = 2
frames_per_scene = 1
people = [1, 2]
area = [3.0, 3.0]
image_size = [48, 32]
[cameras]
count = 2
rings = [{ height = 2.5, radius = 5.0 }]
fov_deg = [55.0, 65.0]
k1 = [-0.05, 0.02]
look_at_height = 0.9
[lighting]
night_fraction = 0.5
"#;

const TRAIN: &str = r#"model = "model.toml"
seed = 3
batch_size = 1
train_views = 2
test_views = 2
match_gate = 0.5
keep_checkpoints = 2
val_frames = 1
[stage1]
epochs = 1
lr = 1e-3
warmup_steps = 2
final_lr_factor = 0.1
grad_clip = 1.0
average_decay = 0.9
[stage2]
epochs = 1
lr = 1e-3
decoder_lr = 1e-4
warmup_steps = 2
final_lr_factor = 0.1
grad_clip = 1.0
average_decay = 0.9
[loss]
detection = 1.0
parameters = 10.0
mesh_3d = 100.0
mesh_2d = 1.0
orientation = 5.0
density = 1.0
density_sigma = 0.1
density_grid = 8
density_extent = 2.2
detection_offset = 1.0
detection_positive = 0.5
detection_sigma = 0.2
heatmap_2d = 1.0
heatmap_sigma = 2.0
"#;

const PARAMS: &str = r#"{"betas": [0.5, -0.2], "expression": [0.1], "global_orient": [0.1, 0.2, 0.3],
"body_pose": [0.0, 0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
0.0, 0.0, 0.0], "transl": [1.0, 2.0, 0.9]}"#;

#[test]
fn no_malformed_input_gets_through() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    // The valid starting points: a small dataset, the tiny model at a small size, a training config.
    synth_dataset(dir.path());
    let model = small_model();
    std::fs::write(p("model.toml"), &model).unwrap();
    // Top-level keys go before the first table.
    std::fs::write(
        p("train.toml"),
        format!("data = {:?}\n", s(&p("ds"))) + TRAIN,
    )
    .unwrap();
    std::fs::write(p("params.json"), PARAMS).unwrap();
    for (args, what) in [
        (
            vec!["model", "summary", "--config", &s(&p("model.toml"))],
            "model config",
        ),
        (vec!["data", "check", &s(&p("ds"))], "dataset"),
        (
            vec![
                "train",
                "--config",
                &s(&p("train.toml")),
                "--out",
                &s(&p("run")),
                "--stop-after-steps",
                "1",
            ],
            "training config",
        ),
        (
            vec![
                "body",
                "forward",
                "--params",
                &s(&p("params.json")),
                "--out",
                &s(&p("body")),
            ],
            "params",
        ),
    ] {
        let o = mvmp(&args);
        assert!(
            o.status.success(),
            "the valid {what}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
    std::fs::remove_dir_all(p("body")).unwrap();
    std::fs::remove_dir_all(p("run")).unwrap();

    let floats = [
        toml::Value::Float(f64::NAN),
        toml::Value::Float(f64::INFINITY),
        toml::Value::String("x".into()),
        toml::Value::Array(vec![]),
    ];
    let mut failures = Vec::new();
    let mut n = 0;
    let model_cmd = || {
        (
            vec![
                "model".into(),
                "summary".into(),
                "--config".into(),
                s(&p("model.toml")),
            ],
            None,
        )
    };
    n += run_all(
        toml_cases(&model, &p("model.toml"), &floats, &model_cmd),
        &mut failures,
    );
    // Counts within their type that would exhaust memory or overflow a step count.
    n += run_all(
        capped_cases(
            &model,
            &p("model.toml"),
            &[
                ("image_size", "100000"),
                ("feature_channels", "100000000"),
                ("max_people", "100000000"),
                ("grid.shape", "[4096, 4096, 4096]"),
                ("decoder.dim", "1073741824"),
                ("decoder.depth", "100000000"),
                ("decoder.ffn_ratio", "100000000"),
                // A factor that divides none of the grid's sides would pool nothing, silently.
                ("decoder.pool", "3"),
                ("decoder.height_features", "1000000000"),
            ],
            &model_cmd,
        ),
        &mut failures,
    );
    let train_text = std::fs::read_to_string(p("train.toml")).unwrap();
    let train_cmd = || {
        let args = [
            "train",
            "--config",
            &s(&p("train.toml")),
            "--out",
            &s(&p("run")),
            "--stop-after-steps",
            "1",
        ];
        (args.map(String::from).to_vec(), Some(p("run")))
    };
    n += run_all(
        toml_cases(&train_text, &p("train.toml"), &floats, &train_cmd),
        &mut failures,
    );
    n += run_all(
        capped_cases(
            &train_text,
            &p("train.toml"),
            &[
                ("batch_size", "1000000000"),
                ("stage1.epochs", "1000000000000000000"),
                ("stage2.warmup_steps", "1000000000000000000"),
                ("loss.density_grid", "100000"),
            ],
            &train_cmd,
        ),
        &mut failures,
    );
    let synth_cmd = || {
        let args = [
            "data",
            "synth",
            "--config",
            &s(&p("synth.toml")),
            "--out",
            &s(&p("ds2")),
        ];
        (args.map(String::from).to_vec(), Some(p("ds2")))
    };
    n += run_all(
        toml_cases(SYNTH, &p("synth.toml"), &floats, &synth_cmd),
        &mut failures,
    );
    n += run_all(
        capped_cases(
            SYNTH,
            &p("synth.toml"),
            &[
                ("scenes", "1000000000000000"),
                ("frames_per_scene", "1000000000000000"),
                ("cameras.rings", "[{ height = 1e9, radius = 5.0 }]"),
            ],
            &synth_cmd,
        ),
        &mut failures,
    );

    // Dataset files through `data check`, parameter files through `body forward`.
    let json_values = [
        serde_json::Value::Null,
        serde_json::json!("x"),
        serde_json::json!([]),
    ];
    let check = ["data", "check", &s(&p("ds"))].map(String::from).to_vec();
    for f in [
        "dataset.json",
        "scene_000/cameras.json",
        "scene_000/scene.json",
        "scene_000/frame_000000/annotation.json",
    ] {
        n += run_all(
            json_cases(&p("ds").join(f), &json_values, &check),
            &mut failures,
        );
    }
    // Finite in JSON, past every float32 the values become (a pelvis of 1e300 m once scored an
    // infinite PVE), and the sizes' signs.
    let extreme = [serde_json::json!(1e300), serde_json::json!(-1e300)];
    for f in [
        "scene_000/scene.json",
        "scene_000/frame_000000/annotation.json",
    ] {
        n += run_all(
            json_cases(&p("ds").join(f), &extreme, &check),
            &mut failures,
        );
    }
    let body = [
        "body",
        "forward",
        "--params",
        &s(&p("params.json")),
        "--out",
        &s(&p("body")),
    ]
    .map(String::from)
    .to_vec();
    // A shape coefficient of 1e30 once posed meshes 1e28 m wide.
    let mut cases = json_cases(&p("params.json"), &json_values, &body);
    let mut huge: serde_json::Value = serde_json::from_str(PARAMS).unwrap();
    huge["betas"][0] = serde_json::json!(1e30);
    cases.push((
        Case {
            file: p("params.json"),
            key: "betas[0]".into(),
            value: "1e30".into(),
            args: body.clone(),
            out: None,
        },
        huge.to_string(),
    ));
    for (c, _) in &mut cases {
        c.out = Some(p("body"));
    }
    n += run_all(cases, &mut failures);
    all_refused(n, 300, &failures);
}

/// Dataset files through `data stats --sheet`: every number of the index, a rig, a scene and an
/// annotation replaced by null, text or an empty list, and by +-1e300. Every case must exit non-zero
/// naming the file and the key, and leave no contact sheet behind.
#[test]
fn no_malformed_dataset_gets_through_stats() {
    let dir = tempfile::tempdir().unwrap();
    let ds = synth_dataset(dir.path());
    let sheet = dir.path().join("sheet.png");
    let stats = ["data", "stats", &s(&ds), "--sheet", &s(&sheet)]
        .map(String::from)
        .to_vec();
    let o = mvmp(&stats.iter().map(String::as_str).collect::<Vec<_>>());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    std::fs::remove_file(&sheet).unwrap();
    let values = [
        serde_json::Value::Null,
        serde_json::json!("x"),
        serde_json::json!([]),
        serde_json::json!(1e300),
        serde_json::json!(-1e300),
    ];
    let (mut failures, mut n) = (Vec::new(), 0);
    for f in [
        "dataset.json",
        "scene_000/cameras.json",
        "scene_000/scene.json",
        "scene_000/frame_000000/annotation.json",
    ] {
        let mut cases = json_cases(&ds.join(f), &values, &stats);
        for (c, _) in &mut cases {
            c.out = Some(sheet.clone());
        }
        n += run_all(cases, &mut failures);
    }
    all_refused(n, 100, &failures);
}

/// The corpus's dataset (`dir/ds`) and a run trained on it for one step (`dir/run`).
fn one_step_run(dir: &Path) -> (PathBuf, PathBuf) {
    let ds = synth_dataset(dir);
    std::fs::write(dir.join("model.toml"), small_model()).unwrap();
    let train = format!("data = {:?}\n", s(&ds)) + TRAIN;
    std::fs::write(dir.join("train.toml"), train).unwrap();
    let run = dir.join("run");
    let o = mvmp(&[
        "train",
        "--config",
        &s(&dir.join("train.toml")),
        "--out",
        &s(&run),
        "--stop-after-steps",
        "1",
    ]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    (ds, run)
}

/// Panoptic and Human3.6M trees read in place, through `eval --format`: every number of a Panoptic
/// calibration and of a frame's bodies, and of the Human3.6M camera file, replaced by null, text, an
/// empty list or 1e300. Every case must exit non-zero naming the file and the key, and leave no report.
#[test]
fn no_malformed_panoptic_or_h36m_file_gets_through_eval() {
    let dir = tempfile::tempdir().unwrap();
    let (_, run) = one_step_run(dir.path());
    let report = dir.path().join("report.json");
    let seq = "160906_pizza1";
    let pan = mvmp_data::fixtures::panoptic_sequence(dir.path(), seq, 1).unwrap();
    let h36m = dir.path().join("h36m");
    let files = Path::new(env!("CARGO_MANIFEST_DIR")).join("../mvmp-data/tests/fixtures/h36m");
    mvmp_data::fixtures::h36m_tree(&h36m, &files, &[("S9", "Walking")], 2).unwrap();
    let eval = |format: &str, data: &Path, split: &str, extra: &[&str]| {
        let mut a = owned(&["eval", "--run", &s(&run), "--format", format, "--data"]);
        a.extend(owned(&[
            &s(data),
            "--split",
            split,
            "--stride",
            "1",
            "--views",
            "2",
        ]));
        a.extend(owned(extra));
        a.extend(owned(&["--out", &s(&report)]));
        a
    };
    let panoptic = eval("panoptic", dir.path(), seq, &[]);
    let human = eval("h36m", &h36m, "S9", &[]);
    for args in [&panoptic, &human] {
        let o = mvmp(&args.iter().map(String::as_str).collect::<Vec<_>>());
        assert!(
            o.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
        std::fs::remove_file(&report).unwrap();
    }
    let values = [
        serde_json::Value::Null,
        serde_json::json!("x"),
        serde_json::json!([]),
        serde_json::json!(1e300),
    ];
    let mut cases = json_cases(
        &pan.join(format!("calibration_{seq}.json")),
        &values,
        &panoptic,
    );
    let pose = pan.join("hdPose3d_stage1_coco19/body3DScene_00000000.json");
    cases.extend(json_cases(&pose, &values, &panoptic));
    let cameras = mvmp_data::h36m::camera_file(&h36m);
    cases.extend(json_cases(&cameras, &values, &human));
    // Keys the readers do not read (a camera's panel and node, the body file's version), as the
    // reference loaders do not.
    let unread =
        |key: &str| ["panel", "node", "version"].contains(&key.rsplit('.').next().unwrap());
    cases.retain(|(c, _)| !unread(&c.key));
    for (c, _) in &mut cases {
        c.out = Some(report.clone());
    }
    let mut failures = Vec::new();
    let n = run_all(cases, &mut failures);
    all_refused(n, 100, &failures);
}

/// One defect planted in a body model.
type Defect = Box<dyn Fn(&mut mvmp_smplx::BodyModel)>;

/// Body-model files: the stand-in written in the official layout with one defect at a time, through
/// `body forward --model`. Every case must fail naming the file and the array, leaving no output. The
/// empty model once crashed the forward (`chunk size must be non-zero`); a NaN landmark weight was caught
/// only after the forward, naming no array.
#[test]
fn no_malformed_body_model_gets_through() {
    use mvmp_smplx::BodyModel;
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    std::fs::write(p("params.json"), PARAMS).unwrap();
    let good = mvmp_smplx::standin_model(0);
    let nan_at = |key: &'static str, f: fn(&mut BodyModel) -> &mut Vec<f32>| {
        (key, move |m: &mut BodyModel| {
            let v = f(m);
            let i = v.len() / 2;
            v[i] = f32::NAN;
        })
    };
    let mut cases: Vec<(&str, Defect)> = Vec::new();
    for (key, f) in [
        nan_at("v_template", |m| &mut m.v_template),
        nan_at("shapedirs", |m| &mut m.shapedirs),
        nan_at("posedirs", |m| &mut m.posedirs),
        nan_at("J_regressor", |m| &mut m.j_regressor),
        nan_at("weights", |m| &mut m.weights),
        nan_at("lmk_bary_coords", |m| &mut m.landmarks.as_mut().unwrap().1),
        nan_at("hands_meanl", |m| &mut m.hands_mean.as_mut().unwrap().0),
    ] {
        cases.push((key, Box::new(f)));
    }
    // Finite but absurd: a template of 1e30 m once posed meshes of that size without a word, and a model
    // in millimetres is a model 1000 times too large.
    cases.push((
        "v_template",
        Box::new(|m: &mut BodyModel| m.v_template[7] = 1e30),
    ));
    cases.push((
        "v_template",
        Box::new(|m: &mut BodyModel| m.v_template.iter_mut().for_each(|x| *x *= 1000.0)),
    ));
    cases.push((
        "shapedirs",
        Box::new(|m: &mut BodyModel| m.shapedirs[11] = -1e30),
    ));
    cases.push((
        "v_template",
        Box::new(|m: &mut BodyModel| {
            // No vertices at all: every per-vertex array empty alike.
            let l = m.num_shape_components;
            m.v_template.clear();
            m.shapedirs.clear();
            m.posedirs.clear();
            m.j_regressor.clear();
            m.weights.clear();
            m.faces.clear();
            m.landmarks = None;
            m.num_shape_components = l;
        }),
    ));
    cases.push((
        "f",
        Box::new(|m: &mut BodyModel| m.faces[3][1] = (m.v_template.len() / 3) as u32),
    ));
    // Finite but no body: a vertex no joint moves, a negative share, a joint regressed from nothing.
    cases.push((
        "weights",
        Box::new(|m: &mut BodyModel| m.weights[55 * 9..55 * 10].fill(0.0)),
    ));
    cases.push((
        "weights",
        Box::new(|m: &mut BodyModel| {
            let row = &mut m.weights[55 * 4..55 * 5];
            let first = row[0];
            row[0] = -0.5;
            row[1] += first + 0.5;
        }),
    ));
    cases.push((
        "J_regressor",
        Box::new(|m: &mut BodyModel| {
            let v = m.v_template.len() / 3;
            m.j_regressor[3 * v..4 * v].fill(0.0);
        }),
    ));
    cases.push((
        "kintree_table",
        Box::new(|m: &mut BodyModel| m.parents[5] = 7),
    ));
    cases.push((
        "lmk_faces_idx",
        Box::new(|m: &mut BodyModel| {
            let nf = m.faces.len() as u32;
            m.landmarks.as_mut().unwrap().0[2] = nf;
        }),
    ));
    let mut failures = Vec::new();
    for (i, (key, mutate)) in cases.iter().enumerate() {
        let mut m = good.clone();
        mutate(&mut m);
        let file = p(&format!("bad{i}.npz"));
        m.write_npz(&file).unwrap();
        let out = p("body");
        let o = mvmp(&[
            "body",
            "forward",
            "--model",
            &s(&file),
            "--params",
            &s(&p("params.json")),
            "--out",
            &s(&out),
        ]);
        let name = file.file_name().unwrap().to_string_lossy().into_owned();
        let names = |t: &str| t.contains(&name) && t.contains(key);
        failures.extend(verdict(&o, &format!("{key} defect {i}"), names, Some(&out)));
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}

/// A change to one array's shape and values.
type ArrayDefect = fn(&mut Vec<u64>, &mut Vec<f32>);

/// The arrays of an npz file: name, shape, values.
type Arrays = Vec<(String, Vec<u64>, Vec<f32>)>;

fn read_arrays(path: &Path) -> Arrays {
    let mut npz = npyz::npz::NpzArchive::open(path).unwrap();
    let names: Vec<String> = npz.array_names().map(str::to_string).collect();
    names
        .into_iter()
        .map(|n| {
            let a = npz.by_name(&n).unwrap().unwrap();
            let shape = a.shape().to_vec();
            (n, shape, a.into_vec::<f32>().unwrap())
        })
        .collect()
}

fn write_arrays(path: &Path, arrays: &Arrays) {
    use npyz::WriterBuilder;
    let mut w = npyz::npz::NpzWriter::create(path).unwrap();
    for (name, shape, data) in arrays {
        let mut out = w
            .array::<f32>(name, Default::default())
            .unwrap()
            .default_dtype()
            .shape(shape)
            .begin_nd()
            .unwrap();
        out.extend(data.iter().copied()).unwrap();
        out.finish().unwrap();
    }
    w.zip_writer().finish().unwrap();
}

/// Stored predictions (`people.npz`, infer's layout) through `eval --predictions`: every array of one
/// frame's file in turn gets a NaN, an infinity, a column or a row too few. Every case must exit non-zero
/// naming the file and the array.
#[test]
fn no_malformed_predictions_get_through() {
    use mvmp_smplx::SmplxParams;
    use mvmp_smplx::people::{StoredPerson, write_people_npz};
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    synth_dataset(dir.path());
    // Two people per frame at the scene's middle, for every frame of the dataset.
    let mut files = Vec::new();
    for scene in std::fs::read_dir(p("ds")).unwrap().flatten() {
        if !scene.path().is_dir() {
            continue;
        }
        for frame in std::fs::read_dir(scene.path()).unwrap().flatten() {
            if !frame.path().join("annotation.json").exists() {
                continue;
            }
            let rel = frame.path().strip_prefix(p("ds")).unwrap().to_path_buf();
            let out = p("pred").join(&rel);
            std::fs::create_dir_all(&out).unwrap();
            let person = |x: f64| StoredPerson {
                params: SmplxParams {
                    transl: vec![x, 0.0, 0.9],
                    ..Default::default()
                },
                score: 0.9,
                pelvis: Some([x, 0.0, 0.9]),
            };
            write_people_npz(&out.join("people.npz"), &[person(-0.5), person(0.5)]).unwrap();
            files.push(out.join("people.npz"));
        }
    }
    files.sort();
    let eval = [
        "eval",
        "--predictions",
        &s(&p("pred")),
        "--data",
        &s(&p("ds")),
        "--split",
        "all",
    ]
    .map(String::from)
    .to_vec();
    let args: Vec<&str> = eval.iter().map(String::as_str).collect();
    let o = mvmp(&args);
    assert!(
        o.status.success(),
        "the valid predictions: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    let file = &files[0];
    let good = read_arrays(file);
    let mut failures = Vec::new();
    let mut n = 0;
    for (i, (key, shape, _)) in good.iter().enumerate() {
        let defects: [(&str, ArrayDefect); 4] = [
            ("NaN", |_, d| {
                let last = d.len() - 1;
                d[last] = f32::NAN;
            }),
            ("infinity", |_, d| d[0] = f32::INFINITY),
            ("a column too few", |s, d| {
                let last = *s.last().unwrap() as usize;
                *d = d
                    .chunks(last)
                    .flat_map(|r| r[..last - 1].to_vec())
                    .collect();
                *s.last_mut().unwrap() -= 1;
            }),
            ("a row too few", |s, d| {
                let row = d.len() / s[0] as usize;
                d.truncate(d.len() - row);
                s[0] -= 1;
            }),
        ];
        for (what, defect) in defects {
            // A 1-D array has no column to drop; betas and expression may have fewer than 10.
            let optional_columns = ["betas", "expression"].contains(&key.as_str());
            if what == "a column too few" && (shape.len() < 2 || optional_columns) {
                continue;
            }
            let mut arrays = good.clone();
            let (_, s, d) = &mut arrays[i];
            defect(s, d);
            write_arrays(file, &arrays);
            n += 1;
            let names = |t: &str| t.contains("people.npz") && t.contains(key.as_str());
            failures.extend(verdict(
                &mvmp(&args),
                &format!("{key} with {what}"),
                names,
                None,
            ));
        }
    }
    all_refused(n, 39, &failures);
}

/// A PNG of `w` x `h` grey pixels.
fn png(w: u32, h: u32) -> Vec<u8> {
    let mut bytes = Vec::new();
    image::RgbImage::from_pixel(w, h, image::Rgb([128, 128, 128]))
        .write_to(
            &mut std::io::Cursor::new(&mut bytes),
            image::ImageFormat::Png,
        )
        .unwrap();
    bytes
}

/// `args` as owned strings.
fn owned(args: &[&str]) -> Vec<String> {
    args.iter().map(|a| a.to_string()).collect()
}

/// Images, rigs, run directories and command-line numbers: a broken view image through `infer`, `eval
/// --save-predictions` and `data check --deep`; every number of a rig through `infer`; broken weights
/// and a broken `state.json` through `eval --run` and `train --resume`; and bad numbers for every numeric
/// flag. Each must exit non-zero without a panic, name the file (and key) or the flag, and leave no
/// output behind.
#[test]
fn no_malformed_image_rig_run_or_flag_gets_through() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let (ds, run) = one_step_run(dir.path());
    let frame = ds.join("scene_000/frame_000000");
    let rig = ds.join("scene_000/cameras.json");
    let views = [frame.join("view_00.png"), frame.join("view_01.png")];
    let infer = owned(&[
        "infer",
        "--run",
        &s(&run),
        "--rig",
        &s(&rig),
        "--images",
        &s(&views[0]),
        &s(&views[1]),
        "--out",
        &s(&p("infer")),
    ]);
    let eval = |extra: &[&str]| {
        let mut a = owned(&[
            "eval",
            "--run",
            &s(&run),
            "--data",
            &s(&ds),
            "--split",
            "all",
        ]);
        a.extend(owned(extra));
        a
    };
    let save = eval(&["--save-predictions", &s(&p("pred"))]);
    for args in [&infer, &save] {
        let o = mvmp(&args.iter().map(String::as_str).collect::<Vec<_>>());
        assert!(
            o.status.success(),
            "{args:?}: {}",
            String::from_utf8_lossy(&o.stderr)
        );
    }
    std::fs::remove_dir_all(p("infer")).unwrap();
    std::fs::remove_dir_all(p("pred")).unwrap();
    let mut failures = Vec::new();
    let mut n = 0;
    let mut check =
        |args: &[String], what: &str, names: &dyn Fn(&str) -> bool, out: Option<PathBuf>| {
            n += 1;
            let o = mvmp(&args.iter().map(String::as_str).collect::<Vec<_>>());
            failures.extend(verdict(&o, what, names, out.as_deref()));
            if let Some(out) = out.filter(|o| o.exists()) {
                std::fs::remove_dir_all(out).unwrap();
            }
        };

    // A view image, broken five ways.
    let good = std::fs::read(&views[0]).unwrap();
    let deep = owned(&["data", "check", "--deep", &s(&ds)]);
    for (what, bytes) in [
        ("empty", Vec::new()),
        ("cut after its header", good[..40].to_vec()),
        ("cut in half", good[..good.len() / 2].to_vec()),
        ("not an image", b"not an image ".repeat(20)),
        ("of another size", png(10, 10)),
    ] {
        std::fs::write(&views[0], bytes).unwrap();
        let names = |t: &str| t.contains("view_00.png");
        for (args, out) in [
            (&infer, Some(p("infer"))),
            (&save, Some(p("pred"))),
            (&deep, None),
        ] {
            check(
                args,
                &format!("view_00.png {what} via {}", args[0]),
                &names,
                out,
            );
        }
    }
    std::fs::write(&views[0], &good).unwrap();

    // A broken image in a later frame: the frames before it were written, and must not stay. `eval`
    // scores both scenes (either may come first); `infer --frames` reads two frames of one rig.
    let later = ds.join("scene_001/frame_000000/view_00.png");
    let later_good = std::fs::read(&later).unwrap();
    std::fs::write(&later, &good[..good.len() / 2]).unwrap();
    let named = |t: &str| t.contains("view_00.png");
    check(
        &save,
        "a later scene's view cut in half via eval",
        &named,
        Some(p("pred")),
    );
    std::fs::write(&later, &later_good).unwrap();
    let frames = p("frames");
    for f in ["f0", "f1"] {
        copy_dir(&frame, &frames.join(f));
    }
    std::fs::write(frames.join("f1/view_00.png"), &good[..good.len() / 2]).unwrap();
    let sequence = owned(&[
        "infer",
        "--run",
        &s(&run),
        "--rig",
        &s(&rig),
        "--frames",
        &s(&frames),
        "--out",
        &s(&p("sequence")),
    ]);
    let f1 = |t: &str| t.contains("f1") && t.contains("view_00.png");
    check(
        &sequence,
        "the second frame's view cut in half via infer --frames",
        &f1,
        Some(p("sequence")),
    );

    // Every number of the rig through `infer`. A camera 1e30 m away once made the top-down picture
    // overflow while counting its 1 m grid lines.
    let json_values = [
        serde_json::Value::Null,
        serde_json::json!("x"),
        serde_json::json!([]),
        serde_json::json!(-1e30),
    ];
    let rig_text = std::fs::read_to_string(&rig).unwrap();
    for (case, text) in json_cases(&rig, &json_values, &infer) {
        std::fs::write(&rig, text).unwrap();
        let leaf = case
            .key
            .rsplit('.')
            .next()
            .unwrap()
            .split('[')
            .next()
            .unwrap()
            .to_string();
        let names =
            move |t: &str| t.contains("cameras.json") && (t.contains(&leaf) || t.contains("line"));
        let what = format!("{} = {} in cameras.json via infer", case.key, case.value);
        check(&case.args, &what, &names, Some(p("infer")));
    }
    std::fs::write(&rig, rig_text).unwrap();

    // The weights eval reads (the newest checkpoint's average: the run stopped in a stage that keeps
    // one), broken; then its state through `train --resume` (on a copy each time, so that an accepted
    // case cannot change the run the next one reads).
    let state: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("state.json")).unwrap()).unwrap();
    let weights = vec![run.join(state["average"].as_str().expect("an average in state.json"))];
    assert!(!weights.is_empty());
    for w in &weights {
        let good = std::fs::read(w).unwrap();
        let name = w.file_name().unwrap().to_string_lossy().into_owned();
        for (what, bytes) in [
            ("empty", Vec::new()),
            ("cut in half", good[..good.len() / 2].to_vec()),
        ] {
            std::fs::write(w, bytes).unwrap();
            let names = |t: &str| t.contains(&name);
            check(
                &save,
                &format!("{name} {what} via eval"),
                &names,
                Some(p("pred")),
            );
        }
        std::fs::write(w, good).unwrap();
    }
    // Weights outside the run, as eval reads state.json (a run without its final weights).
    let good_state = std::fs::read_to_string(run.join("state.json")).unwrap();
    for outside in ["../outside.bpk", "/checkpoints/absolute.bpk"] {
        let mut bad = state.clone();
        bad["average"] = serde_json::json!(outside);
        std::fs::write(run.join("state.json"), bad.to_string()).unwrap();
        let names = |t: &str| t.contains("state.json") && t.contains("average");
        check(
            &save,
            &format!("average = {outside} in state.json via eval"),
            &names,
            Some(p("pred")),
        );
    }
    std::fs::write(run.join("state.json"), good_state).unwrap();
    let copy = p("resumed");
    let resume = owned(&["train", "--resume", &s(&copy), "--stop-after-steps", "2"]);
    // Beyond the run's epochs and steps (an overflow of the step count once), and weights outside the
    // run directory.
    let state_values = [
        serde_json::Value::Null,
        serde_json::json!("x"),
        serde_json::json!(-1),
        serde_json::json!(1_000_000),
        serde_json::json!(u64::MAX),
        serde_json::json!("../outside.bpk"),
        serde_json::json!("/checkpoints/absolute.bpk"),
    ];
    for (case, text) in json_cases(&run.join("state.json"), &state_values, &resume) {
        copy_dir(&run, &copy);
        std::fs::write(copy.join("state.json"), text).unwrap();
        let leaf = case
            .key
            .rsplit('.')
            .next()
            .unwrap()
            .split('[')
            .next()
            .unwrap()
            .to_string();
        let names = move |t: &str| t.contains("state.json") && t.contains(&leaf);
        let what = format!(
            "{} = {} in state.json via train --resume",
            case.key, case.value
        );
        check(&case.args, &what, &names, None);
        std::fs::remove_dir_all(&copy).unwrap();
    }
    // The checkpoint, optimizer and weight-average files state.json names, damaged after they were
    // written (64 bytes flipped in the middle; such weights once resumed without a word).
    for key in ["checkpoint", "optimizer", "average"] {
        copy_dir(&run, &copy);
        let state: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(copy.join("state.json")).unwrap())
                .unwrap();
        let file = copy.join(state[key].as_str().unwrap());
        let mut bytes = std::fs::read(&file).unwrap();
        let mid = bytes.len() / 2;
        for b in &mut bytes[mid..mid + 64] {
            *b ^= 0xff;
        }
        std::fs::write(&file, bytes).unwrap();
        let name = file.file_name().unwrap().to_string_lossy().into_owned();
        let names = move |t: &str| t.contains(&name) && t.contains("damaged");
        check(
            &resume,
            &format!("a damaged {key} file via train --resume"),
            &names,
            None,
        );
        std::fs::remove_dir_all(&copy).unwrap();
    }

    // Numbers on the command line: each must be refused naming its flag.
    let tiny = s(&p("model.toml"));
    // A new run with one flag set, and that flag.
    let train_with = |flag: &'static str, value: &str| {
        let config = s(&p("train.toml"));
        let out = s(&p("run2"));
        (
            owned(&["train", "--config", &config, "--out", &out, flag, value]),
            flag,
        )
    };
    let flags: Vec<(Vec<String>, &str)> = vec![
        (eval(&["--views", "0"]), "--views"),
        (eval(&["--views", "1000000"]), "--views"),
        (eval(&["--frames", "-1"]), "--frames"),
        (eval(&["--gate", "nan"]), "--gate"),
        (eval(&["--gate", "-1"]), "--gate"),
        (eval(&["--gate", "inf"]), "--gate"),
        (
            owned(&["model", "summary", "--config", &tiny, "--views", "0"]),
            "--views",
        ),
        (
            owned(&[
                "model",
                "summary",
                "--config",
                &tiny,
                "--training",
                "--batch",
                "0",
            ]),
            "--batch",
        ),
        (
            owned(&["bench", "model", "--config", &tiny, "--iters", "0"]),
            "--iters",
        ),
        (
            owned(&["bench", "model", "--config", &tiny, "--views", "0"]),
            "--views",
        ),
        (
            owned(&["bench", "fusion", "--config", &tiny, "--views", "0"]),
            "--views",
        ),
        (
            owned(&["bench", "fusion", "--config", &tiny, "--iters", "0"]),
            "--iters",
        ),
        (owned(&["bench", "smplx", "--batch", "0"]), "--batch"),
        (
            owned(&["bench", "smplx", "--batch", "18446744073709551615"]),
            "--batch",
        ),
        (owned(&["bench", "smplx", "--iters", "0"]), "--iters"),
        (owned(&["bench", "attention", "--tokens", "0"]), "--tokens"),
        (owned(&["bench", "attention", "--heads", "0"]), "--heads"),
        (
            owned(&["bench", "attention", "--head-dim", "0"]),
            "--head-dim",
        ),
        (owned(&["bench", "attention", "--tile", "0"]), "--tile"),
        (owned(&["bench", "train", "--steps", "0"]), "--steps"),
        (owned(&["bench", "train", "--scenes", "0"]), "--scenes"),
        (
            owned(&[
                "bench",
                "learn",
                "--minutes",
                "nan",
                "--out",
                &s(&p("learn")),
            ]),
            "--minutes",
        ),
        (
            owned(&["bench", "learn", "--minutes", "0", "--out", &s(&p("learn"))]),
            "--minutes",
        ),
        (
            owned(&["bench", "learn", "--scenes", "0", "--out", &s(&p("learn"))]),
            "--scenes",
        ),
        (
            owned(&["body", "render", "--size", "0", "--out", &s(&p("r.png"))]),
            "--size",
        ),
        (
            owned(&[
                "body",
                "render",
                "--size",
                "1000000",
                "--out",
                &s(&p("r.png")),
            ]),
            "--size",
        ),
        (
            owned(&["demo", "--seed", "-1", "--out", &s(&p("demo"))]),
            "--seed",
        ),
        train_with("--stop-after-steps", "0"),
        train_with("--stop-after-minutes", "nan"),
        // Counts that size an allocation, and a duration past what a timer holds.
        train_with("--stop-after-minutes", "1e18"),
        (
            owned(&[
                "model",
                "summary",
                "--config",
                &tiny,
                "--training",
                "--people",
                "100000000",
            ]),
            "--people",
        ),
        (
            owned(&[
                "model",
                "summary",
                "--config",
                &tiny,
                "--views",
                "100000000",
            ]),
            "--views",
        ),
        (
            owned(&["bench", "fusion", "--config", &tiny, "--views", "100000000"]),
            "--views",
        ),
        (
            owned(&["bench", "attention", "--tokens", "1000000000000"]),
            "--tokens",
        ),
        (
            owned(&["bench", "attention", "--head-dim", "1000000000"]),
            "--head-dim",
        ),
        (
            owned(&[
                "import",
                "hrnet",
                "--joints",
                "1000000000",
                "--from",
                "x.pth",
                "--out",
                "y.bpk",
            ]),
            "--joints",
        ),
    ];
    for (args, flag) in flags {
        let value = args
            .iter()
            .skip_while(|a| *a != flag)
            .nth(1)
            .cloned()
            .unwrap();
        let what = format!("{} {flag} {value}", args[..2].join(" "));
        let names = |t: &str| t.contains(flag);
        let out = ["--out"]
            .iter()
            .find_map(|f| args.iter().skip_while(|a| a != f).nth(1).map(PathBuf::from));
        check(&args, &what, &names, out);
    }
    all_refused(n, 60, &failures);
}

/// Copy a directory tree.
fn copy_dir(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap() {
        let e = e.unwrap();
        let target = to.join(e.file_name());
        if e.file_type().unwrap().is_dir() {
            copy_dir(&e.path(), &target);
        } else {
            std::fs::copy(e.path(), target).unwrap();
        }
    }
}

/// A module's weights as a PyTorch-layout `.safetensors` file (PyTorch names and layouts): for the
/// tiny ViT that is a torch-hub DINOv2 checkpoint.
fn pytorch_safetensors<M: burn::module::Module>(module: &M, path: &Path) {
    use burn::store::{BurnToPyTorchAdapter, ModuleSnapshot, SafetensorsStore};
    let mut store = SafetensorsStore::from_file(path).with_to_adapter(BurnToPyTorchAdapter);
    module.save_into(&mut store).unwrap();
}

/// The tensors of a safetensors file, each passed through `edit` (which may rename it, change its
/// dtype, shape or bytes, or drop it), serialised again.
fn rewrite(
    bytes: &[u8],
    edit: impl Fn(&str, safetensors::Dtype, &[usize], &[u8]) -> Option<Raw>,
) -> Vec<u8> {
    let st = safetensors::SafeTensors::deserialize(bytes).unwrap();
    let raws: Vec<(String, Raw)> = st
        .tensors()
        .into_iter()
        .filter_map(|(n, v)| edit(&n, v.dtype(), v.shape(), v.data()).map(|r| (n, r)))
        .map(|(n, (name, dt, shape, data))| (name.unwrap_or(n), (None, dt, shape, data)))
        .collect();
    let views: Vec<(String, safetensors::tensor::TensorView)> = raws
        .iter()
        .map(|(n, (_, dt, shape, data))| {
            let v = safetensors::tensor::TensorView::new(*dt, shape.clone(), data).unwrap();
            (n.clone(), v)
        })
        .collect();
    safetensors::serialize(views, None).unwrap()
}

/// A tensor as [`rewrite`] writes it: a new name (or the old), dtype, shape, bytes.
type Raw = (Option<String>, safetensors::Dtype, Vec<usize>, Vec<u8>);

/// A change to one tensor's shape and bytes.
type Change = Box<dyn Fn(&[usize], &[u8]) -> Raw>;

/// The malformed checkpoints of `good` (a PyTorch-layout safetensors file holding `key`, a float
/// tensor of at least two dimensions), each with the message it must name beside the file.
fn checkpoint_cases(good: &[u8], key: &str) -> Vec<(&'static str, Vec<u8>)> {
    let at_key = |f: Change| {
        move |n: &str, dt, shape: &[usize], data: &[u8]| {
            Some(if n == key {
                f(shape, data)
            } else {
                (None, dt, shape.to_vec(), data.to_vec())
            })
        }
    };
    let first_to = |x: f32| -> Change {
        Box::new(move |shape, data| {
            let mut d = data.to_vec();
            d[..4].copy_from_slice(&x.to_le_bytes());
            (None, safetensors::Dtype::F32, shape.to_vec(), d)
        })
    };
    let mut huge_header = good.to_vec();
    huge_header[..8].copy_from_slice(&(1u64 << 60).to_le_bytes());
    vec![
        ("empty", Vec::new()),
        ("cut short", good[..good.len() / 2].to_vec()),
        ("header only", good[..8].to_vec()),
        ("a header length of 2^60", huge_header),
        ("a NaN weight", rewrite(good, at_key(first_to(f32::NAN)))),
        (
            "an infinite weight",
            rewrite(good, at_key(first_to(f32::INFINITY))),
        ),
        (
            "a tensor one row short",
            rewrite(
                good,
                at_key(Box::new(|shape, data| {
                    let mut s = shape.to_vec();
                    let row = data.len() / s[0];
                    s[0] -= 1;
                    (None, safetensors::Dtype::F32, s, data[row..].to_vec())
                })),
            ),
        ),
        (
            "an integer tensor",
            rewrite(
                good,
                at_key(Box::new(|shape, data| {
                    (None, safetensors::Dtype::I32, shape.to_vec(), data.to_vec())
                })),
            ),
        ),
        (
            "no known key",
            rewrite(good, |n, dt, shape, data| {
                Some((
                    Some(format!("other.{n}")),
                    dt,
                    shape.to_vec(),
                    data.to_vec(),
                ))
            }),
        ),
    ]
}

#[test]
fn no_malformed_checkpoint_gets_through_import() {
    let dir = tempfile::tempdir().unwrap();
    let device = burn::tensor::Device::flex();
    let out = dir.path().join("w.bpk");
    let nets = [
        (
            "dinov2",
            "blocks.0.attn.qkv.weight",
            dir.path().join("hub.safetensors"),
        ),
        (
            "hrnet",
            "conv1.weight",
            dir.path().join("pose_hrnet.safetensors"),
        ),
    ];
    pytorch_safetensors(
        &mvmp_backbone::VitVariant::Tiny.config().init(&device),
        &nets[0].2,
    );
    pytorch_safetensors(
        &mvmp_backbone::HrnetVariant::Tiny.config(17).init(&device),
        &nets[1].2,
    );
    let args = |net: &str, from: &Path| {
        owned(&[
            "import",
            net,
            "--variant",
            "tiny",
            "--from",
            &s(from),
            "--out",
            &s(&out),
        ])
    };
    // A file that must import: it does, and its output is removed for the next case.
    let imports = |net: &str, from: &Path| {
        let a = args(net, from);
        let ok = mvmp(&a.iter().map(String::as_str).collect::<Vec<_>>());
        let err = String::from_utf8_lossy(&ok.stderr);
        assert!(ok.status.success(), "{net}: {err}");
        std::fs::remove_file(&out).unwrap();
    };
    let (mut n, mut failures) = (0, Vec::new());
    for (net, key, good) in &nets {
        // The file the cases are made from imports: each case differs from it in one thing.
        imports(net, good);
        // So does the same file through `rewrite` unchanged: the cases are refused for what they change.
        let same = dir.path().join(format!("{net}-same.safetensors"));
        let bytes = std::fs::read(good).unwrap();
        let unchanged = |_: &str, dt, shape: &[usize], data: &[u8]| {
            Some((None, dt, shape.to_vec(), data.to_vec()))
        };
        std::fs::write(&same, rewrite(&bytes, unchanged)).unwrap();
        imports(net, &same);
        for (what, bytes) in checkpoint_cases(&bytes, key) {
            let bad = dir.path().join(format!("{net}-case.safetensors"));
            std::fs::write(&bad, bytes).unwrap();
            let a = args(net, &bad);
            let o = mvmp(&a.iter().map(String::as_str).collect::<Vec<_>>());
            let name = bad.file_name().unwrap().to_string_lossy().into_owned();
            let what = format!("import {net}: {what}");
            failures.extend(verdict(&o, &what, |t| t.contains(&name), Some(&out)));
            if out.exists() {
                std::fs::remove_file(&out).unwrap();
            }
            n += 1;
        }
    }
    all_refused(n, 17, &failures);
}

/// Flags whose values size an allocation, string references, lists with a repeated entry, and outputs
/// over their own inputs: each refused naming the flag or the file and key, with nothing written.
#[test]
fn no_huge_flag_bad_reference_or_output_over_input_gets_through() {
    let dir = tempfile::tempdir().unwrap();
    let p = |n: &str| dir.path().join(n);
    let ds = synth_dataset(dir.path());
    let mut failures = Vec::new();
    let mut n = 0;
    let mut check = |args: &[&str], names: &[&str], out: Option<PathBuf>| {
        n += 1;
        let has = |t: &str| names.iter().all(|w| t.contains(w));
        failures.extend(verdict(&mvmp(args), &args.join(" "), has, out.as_deref()));
    };
    let huge = "18446744073709551615";
    for bench in ["smplx", "model", "fusion"] {
        check(&["bench", bench, "--iters", huge], &["--iters"], None);
    }
    check(
        &["bench", "attention", "--tokens", "65536", "--tile", "65536"],
        &["--tile"],
        None,
    );
    check(
        &[
            "bench",
            "attention",
            "--tokens",
            "65536",
            "--plain-up-to",
            "65536",
        ],
        &["--plain-up-to"],
        None,
    );
    let model = |edit: &dyn Fn(String) -> String| {
        let path = p("model.toml");
        std::fs::write(&path, edit(small_model())).unwrap();
        s(&path)
    };
    for (key, edit) in [
        (
            "heatmap_joints",
            &(|m: String| m.replace("heatmap_joints = [0, 1,", "heatmap_joints = [1, 1,"))
                as &dyn Fn(String) -> String,
        ),
        ("body_model", &|m: String| {
            m.replace("body_model = \"standin:0\"", "body_model = \"standin:x\"")
        }),
    ] {
        let cfg = model(edit);
        check(
            &["model", "summary", "--config", &cfg],
            &["model.toml", key],
            None,
        );
    }
    std::fs::write(p("model.toml"), small_model()).unwrap();
    let train = |extra: &str| {
        let path = p("train.toml");
        std::fs::write(&path, format!("data = {:?}\n{TRAIN}{extra}", s(&ds))).unwrap();
        s(&path)
    };
    for (key, source) in [
        (
            "repeat",
            "[[sources]]\nformat = \"mvmp\"\nroot = \"x\"\nrepeat = 1000000000000\n",
        ),
        (
            "cameras",
            "[[sources]]\nformat = \"panoptic\"\nroot = \"x\"\ncameras = [\"00_03\", \"00_03\"]\n",
        ),
    ] {
        let cfg = train(source);
        let out = p("run");
        check(
            &["train", "--config", &cfg, "--out", &s(&out)],
            &["train.toml", key],
            Some(out),
        );
    }
    let data = s(&ds);
    let mean_pose = |extra: &[&str]| {
        let mut a = owned(&[
            "eval",
            "--baseline",
            "mean-pose",
            "--data",
            &data,
            "--split",
            "all",
        ]);
        a.extend(owned(extra));
        a
    };
    let report = p("report.json");
    let bad_body = mean_pose(&["--body-model", "standin:x", "--out", &s(&report)]);
    check(
        &bad_body.iter().map(String::as_str).collect::<Vec<_>>(),
        &["--body-model", "standin:x"],
        Some(report),
    );
    let index = ds.join("dataset.json");
    let before = std::fs::read(&index).unwrap();
    let over_index = mean_pose(&["--out", &s(&index)]);
    check(
        &over_index.iter().map(String::as_str).collect::<Vec<_>>(),
        &["--out", "dataset.json", "not an evaluation report"],
        None,
    );
    assert_eq!(
        std::fs::read(&index).unwrap(),
        before,
        "dataset.json overwritten"
    );
    let params = p("params.json");
    std::fs::write(&params, PARAMS).unwrap();
    check(
        &[
            "body",
            "render",
            "--params",
            &s(&params),
            "--out",
            &s(&params),
        ],
        &["--out", "params.json"],
        None,
    );
    assert_eq!(std::fs::read_to_string(&params).unwrap(), PARAMS);
    all_refused(n, 10, &failures);
}
