//! The `mvmp` binary end to end: outputs that load back, and clear errors with a non-zero exit.
use std::path::Path;
use std::process::{Command, Output};

fn mvmp(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_mvmp"))
        .args(args)
        .output()
        .unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn body_forward_writes_npz_json_and_meshes() {
    let dir = tempfile::tempdir().unwrap();
    let params = dir.path().join("p.json");
    std::fs::write(
        &params,
        r#"[{"body_pose": [0.0, 0.0, 0.3, 0,0,0, 0,0,0, 0.8,0,0, 0,0,0, 0,0,0, 0,0,0, 0,0,0, 0,0,0, 0,0,0,
              0,0,0, 0,0,0, 0,0,0, 0,0,0, 0,0,0, 0,0,0, 0,0,0, 0,0,0, 0,0,0, 0,0,0, 0,0,0],
            "betas": [1.0, -0.5], "transl": [1.0, 2.0, 3.0]},
           {"global_orient": [1.5708, 0, 0]}]"#,
    )
    .unwrap();
    let out = dir.path().join("out");
    let o = mvmp(&[
        "body",
        "forward",
        "--params",
        params.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let mut npz = npyz::npz::NpzArchive::open(out.join("output.npz")).unwrap();
    let v = npz.by_name("vertices").unwrap().unwrap();
    assert_eq!(v.shape(), &[2, 10475, 3]);
    let verts: Vec<f32> = v.into_vec().unwrap();
    let j = npz.by_name("joints").unwrap().unwrap();
    assert_eq!(j.shape(), &[2, 127, 3]);
    let joints: Vec<f32> = j.into_vec().unwrap();
    // The first body is translated by (1, 2, 3): its pelvis sits near (1, 2 - 0.35, 3).
    assert!(
        (joints[0] - 1.0).abs() < 0.05
            && (joints[1] - 1.65).abs() < 0.05
            && (joints[2] - 3.0).abs() < 0.05
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("output.json")).unwrap()).unwrap();
    assert_eq!(json["vertices"][1].as_array().unwrap().len(), 10475);
    assert!((json["vertices"][0][0][0].as_f64().unwrap() - verts[0] as f64).abs() < 1e-6);
    for f in [
        "body_000.obj",
        "body_000.ply",
        "body_001.obj",
        "body_001.ply",
    ] {
        assert!(out.join(f).metadata().unwrap().len() > 1000, "{f}");
    }
}

fn expect_error(args: &[&str], needles: &[&str]) {
    let o = mvmp(args);
    assert!(!o.status.success(), "{args:?} should fail");
    let e = stderr(&o);
    assert!(!e.contains("panicked"), "{args:?} panicked: {e}");
    for n in needles {
        assert!(e.contains(n), "{args:?}: {n:?} not in {e:?}");
    }
}

#[test]
fn bad_inputs_give_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let d = |n: &str| dir.path().join(n).to_str().unwrap().to_string();
    let out = d("out");
    expect_error(
        &[
            "body",
            "forward",
            "--params",
            &d("missing.json"),
            "--out",
            &out,
        ],
        &["missing.json"],
    );
    expect_error(
        &["compare", "--run", &d("never_scored")],
        &["never_scored/eval-test.json: not found", "mvmp eval --run"],
    );
    // A flag with a bad value is refused before the (missing) run and data are read.
    let (run, data) = (d("run"), d("data"));
    let eval_with = |flag: &str, value: &str, needles: &[&str]| {
        expect_error(
            &["eval", "--run", &run, "--data", &data, flag, value],
            needles,
        )
    };
    eval_with("--views", "0", &["--views", "'0'"]);
    for gate in ["-1", "NaN", "inf", "x"] {
        eval_with("--gate", gate, &["--gate", gate]);
    }
    for minutes in ["0", "-5", "NaN"] {
        expect_error(
            &["train", "--resume", &run, "--stop-after-minutes", minutes],
            &["--stop-after-minutes", minutes, "minutes"],
        );
    }
    expect_error(
        &["bench", "smplx", "--batch", "18446744073709551615"],
        &["--batch", "18446744073709551615"],
    );
    std::fs::write(d("bad.json"), "{ \"betas\": [1, 2,").unwrap();
    expect_error(
        &["body", "forward", "--params", &d("bad.json"), "--out", &out],
        &["bad.json", "malformed JSON"],
    );
    std::fs::write(d("len.json"), r#"{"body_pose": [0.1, 0.2]}"#).unwrap();
    expect_error(
        &["body", "forward", "--params", &d("len.json"), "--out", &out],
        &["len.json", "body_pose", "63"],
    );
    std::fs::write(d("key.json"), r#"[{}, {"pose": [0.1]}]"#).unwrap();
    expect_error(
        &["body", "forward", "--params", &d("key.json"), "--out", &out],
        &["key.json", "bodies[1]", "pose"],
    );
    std::fs::write(d("nan.json"), r#"{"transl": [0, NaN, 0]}"#).unwrap();
    expect_error(
        &["body", "forward", "--params", &d("nan.json"), "--out", &out],
        &["nan.json"],
    );
    std::fs::write(d("ok.json"), "{}").unwrap();
    expect_error(
        &[
            "body",
            "forward",
            "--model",
            &d("SMPLX_NEUTRAL.pkl"),
            "--params",
            &d("ok.json"),
            "--out",
            &out,
        ],
        &["SMPLX_NEUTRAL.pkl", "npz"],
    );
    std::fs::write(d("junk.npz"), "not a zip").unwrap();
    expect_error(
        &[
            "body",
            "forward",
            "--model",
            &d("junk.npz"),
            "--params",
            &d("ok.json"),
            "--out",
            &out,
        ],
        &["junk.npz"],
    );
    expect_error(
        &[
            "--device",
            "tpu",
            "body",
            "make-standin",
            "--out",
            &d("m.npz"),
        ],
        &["tpu"],
    );
    // Nothing half-written: failed runs left no output directory.
    assert!(!Path::new(&out).exists());
}

#[test]
fn make_standin_then_use_it() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("SMPLX_STANDIN.npz");
    let o = mvmp(&[
        "body",
        "make-standin",
        "--out",
        model.to_str().unwrap(),
        "--seed",
        "3",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let params = dir.path().join("p.json");
    std::fs::write(&params, r#"{"expression": [1.0]}"#).unwrap();
    let out = dir.path().join("o");
    let o = mvmp(&[
        "body",
        "forward",
        "--model",
        model.to_str().unwrap(),
        "--params",
        params.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let png = dir.path().join("body.png");
    let o = mvmp(&[
        "body",
        "render",
        "--out",
        png.to_str().unwrap(),
        "--size",
        "64",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let img = image::open(&png).unwrap().to_rgb8();
    // The body covers part of the frame: some pixels differ from the background.
    let bg = img.get_pixel(0, 0);
    assert!(img.pixels().filter(|p| *p != bg).count() > 200);
    // A body far from the origin is framed about itself; bodies kilometres apart are refused, naming
    // the file.
    let render = |bodies: &str| {
        std::fs::write(&params, bodies).unwrap();
        mvmp(&[
            "body",
            "render",
            "--params",
            params.to_str().unwrap(),
            "--out",
            png.to_str().unwrap(),
            "--size",
            "64",
        ])
    };
    let o = render(r#"{"transl": [90000.0, 0.0, -90000.0]}"#);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = render(r#"[{"transl": [0.0, 0.0, 0.0]}, {"transl": [90000.0, 0.0, 0.0]}]"#);
    let e = stderr(&o);
    assert!(
        !o.status.success() && e.contains("p.json") && e.contains("span"),
        "{e}"
    );
}

fn config(rel: &str) -> String {
    format!("{}/../../configs/{rel}", env!("CARGO_MANIFEST_DIR"))
}

#[test]
fn model_summary_and_bench_run_and_reject_bad_configs() {
    let o = mvmp(&[
        "model",
        "summary",
        "--config",
        &config("model/tiny.toml"),
        "--views",
        "2",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    for needle in [
        "vit",
        "hrnet",
        "rootnet",
        "decoder",
        "total",
        "fused volume",
    ] {
        assert!(out.contains(needle), "{needle} missing from {out}");
    }
    let tiny = config("model/tiny.toml");
    let bench_model = |extra: &[&str]| {
        let mut args = vec![
            "bench", "model", "--config", &tiny, "--views", "2", "--iters", "1",
        ];
        args.extend_from_slice(extra);
        mvmp(&args)
    };
    let o = bench_model(&[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("% of GEMM"));
    let o = bench_model(&["--backward"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("forward + backward"), "{out}");
    // Every stage with work has a time.
    for stage in [
        "vit+reduce",
        "hrnet",
        "fusion",
        "rootnet",
        "decoder",
        "smplx",
    ] {
        let line = out
            .lines()
            .find(|l| l.starts_with(stage))
            .unwrap_or_else(|| panic!("{stage}: {out}"));
        let ms: f64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
        assert!(ms > 0.0, "{line}");
    }
    let o = mvmp(&[
        "bench",
        "fusion",
        "--config",
        &config("model/tiny.toml"),
        "--views",
        "2",
        "--iters",
        "1",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    for needle in [
        "the fused CPU pass",
        "sampling grids",
        "Mean fusion of 32 channels",
        "Mean fusion of 17 heatmaps",
    ] {
        assert!(out.contains(needle), "{needle} missing from {out}");
    }
    expect_error(
        &[
            "bench",
            "fusion",
            "--config",
            &config("model/ablations/fusion_deformable.toml"),
        ],
        &["fusion_deformable.toml", "deformable", "bench model"],
    );
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.toml");
    std::fs::write(&bad, "image_size = 224\nbackbone = \"vit_huge\"\n").unwrap();
    expect_error(
        &["model", "summary", "--config", bad.to_str().unwrap()],
        &["backbone", "vit_huge"],
    );
    std::fs::write(&bad, "image_sise = 224\n").unwrap();
    expect_error(
        &["model", "summary", "--config", bad.to_str().unwrap()],
        &["bad.toml", "image_sise"],
    );
    expect_error(
        &[
            "model",
            "summary",
            "--config",
            &dir.path().join("none.toml").to_string_lossy(),
        ],
        &["none.toml"],
    );
}

#[test]
fn data_synth_stats_check_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("s.toml");
    std::fs::write(
        &cfg,
        "scenes = 2\nframes_per_scene = 1\npeople = [2, 3]\narea = [4.0, 4.0]\nimage_size = [96, 64]\n[cameras]\ncount = 2\nrings = [{ height = 2.5, radius = 6.0 }]\n",
    )
    .unwrap();
    let out = dir.path().join("ds");
    let o = mvmp(&[
        "data",
        "synth",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let o = mvmp(&["data", "stats", out.to_str().unwrap(), "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let j: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(j["scenes"], 2);
    assert_eq!(j["frames"], 2);
    assert_eq!(j["views"], 2);
    for k in ["people_per_frame", "occlusion_mean", "visible_views_mean"] {
        assert!(!j[k].is_null(), "{k}");
    }
    let sheet = dir.path().join("sheet.png");
    let o = mvmp(&[
        "data",
        "stats",
        out.to_str().unwrap(),
        "--sheet",
        sheet.to_str().unwrap(),
    ]);
    assert!(o.status.success() && sheet.exists(), "{}", stderr(&o));
    let o = mvmp(&["data", "check", "--format", "mvmp", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    std::fs::remove_file(out.join("scene_001/frame_000000/view_00.png")).unwrap();
    let o = mvmp(&["data", "check", "--format", "mvmp", out.to_str().unwrap()]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stdout).contains("scene_001/frame_000000/view_00.png"));
    // A second synth into a non-empty directory is refused; a bad config names the key.
    expect_error(
        &[
            "data",
            "synth",
            "--config",
            cfg.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        &["not empty"],
    );
    for (text, needles) in [
        ("people = [5, 2]\n", ["people", "[5, 2]"]),
        (
            "[cameras]\nlook_at_height = nan\n",
            ["cameras.look_at_height", "NaN"],
        ),
        ("[cameras]\nk1 = [nan, 0.0]\n", ["cameras.k1", "NaN"]),
        (
            "[cameras]\nlisted = [{ position = [5.0, 0.0, 2.0], look_at = [0.0, 0.0, 1.0], fov_deg = 60.0, k1 = nan }]\n",
            ["cameras.listed[0]", "k1"],
        ),
    ] {
        std::fs::write(&cfg, text).unwrap();
        expect_error(
            &[
                "data",
                "synth",
                "--config",
                cfg.to_str().unwrap(),
                "--out",
                &dir.path().join("x").to_string_lossy(),
            ],
            &needles,
        );
        assert!(!dir.path().join("x").exists());
    }
}

#[test]
fn import_rejects_missing_and_unknown_inputs() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("w.safetensors");
    let missing = dir.path().join("dinov2_vitl14_pretrain.pth");
    expect_error(
        &[
            "import",
            "dinov2",
            "--from",
            missing.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        &["dinov2_vitl14_pretrain.pth"],
    );
    expect_error(
        &[
            "import",
            "dinov2",
            "--variant",
            "vit_huge",
            "--from",
            missing.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
        ],
        &["vit_huge"],
    );
    assert!(!out.exists());
    // Checkpoints that are not checkpoints: text, and a zip archive cut short (a torch file is a zip).
    let text = dir.path().join("notes.pth");
    std::fs::write(&text, "not a checkpoint").unwrap();
    let cut = dir.path().join("cut.pth");
    let mut zip = b"PK\x03\x04".to_vec();
    zip.extend(std::iter::repeat_n(0u8, 40));
    std::fs::write(&cut, zip).unwrap();
    for (net, bad) in [
        ("dinov2", &text),
        ("dinov2", &cut),
        ("hrnet", &text),
        ("hrnet", &cut),
    ] {
        let name = bad.file_name().unwrap().to_str().unwrap();
        let args = ["import", net, "--from", bad.to_str().unwrap(), "--out"];
        expect_error(&[&args[..], &[out.to_str().unwrap()]].concat(), &[name]);
        assert!(!out.exists(), "{net} {name}");
    }
}

/// Ground-truth parameters of every frame stored as predictions (infer's layout), with `shift` added to
/// each person's translation.
fn write_gt_predictions(data: &Path, pred: &Path, shift: [f64; 3]) {
    let layout = mvmp_data::DatasetLayout::open(data).unwrap();
    for f in layout.frames() {
        let rig = &layout.scenes[f.scene].rig;
        let ann = mvmp_data::Annotation::read(&f.dir.join("annotation.json"), rig.len()).unwrap();
        let people: Vec<mvmp_infer::PersonPrediction> = ann
            .people
            .iter()
            .map(|p| {
                let s = &p.smplx;
                let arr = |v: &[f64]| -> [f32; 10] {
                    std::array::from_fn(|i| v.get(i).copied().unwrap_or(0.0) as f32)
                };
                mvmp_infer::PersonPrediction {
                    score: 1.0,
                    pose: s.full_pose().iter().map(|&x| x as f32).collect(),
                    betas: arr(&s.betas),
                    expression: arr(&s.expression),
                    pelvis: std::array::from_fn(|a| (p.pelvis[a] + shift[a]) as f32),
                    transl: std::array::from_fn(|a| (s.transl[a] + shift[a]) as f32),
                    joints: Vec::new(),
                    vertices: Vec::new(),
                }
            })
            .collect();
        let scene = &layout.scenes[f.scene].name;
        let frame = f.dir.file_name().unwrap();
        let dir = pred.join(scene).join(frame);
        std::fs::create_dir_all(&dir).unwrap();
        mvmp_infer::output::write_people_npz(&dir.join("people.npz"), &people).unwrap();
    }
}

#[test]
fn eval_scores_planted_predictions_exactly() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("s.toml");
    std::fs::write(
        &cfg,
        "scenes = 2\nframes_per_scene = 2\npeople = [2, 3]\narea = [4.0, 4.0]\nimage_size = [96, 64]\n[cameras]\ncount = 2\nrings = [{ height = 2.5, radius = 6.0 }]\n",
    )
    .unwrap();
    let data = dir.path().join("ds");
    let o = mvmp(&[
        "data",
        "synth",
        "--config",
        cfg.to_str().unwrap(),
        "--out",
        data.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let eval = |pred: &Path, report: &Path| -> serde_json::Value {
        let o = mvmp(&[
            "eval",
            "--predictions",
            pred.to_str().unwrap(),
            "--data",
            data.to_str().unwrap(),
            "--split",
            "all",
            "--out",
            report.to_str().unwrap(),
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(String::from_utf8_lossy(&o.stdout).contains("MPJPE"));
        serde_json::from_str(&std::fs::read_to_string(report).unwrap()).unwrap()
    };
    // The ground truth itself: zero error, everyone found, AP 1 at every threshold.
    let exact = dir.path().join("exact");
    write_gt_predictions(&data, &exact, [0.0; 3]);
    let r = eval(&exact, &dir.path().join("r0.json"));
    assert!(r["mpjpe_mm"].as_f64().unwrap() < 0.05, "{r}");
    assert!(r["pve_mm"].as_f64().unwrap() < 0.05, "{r}");
    assert_eq!(r["recall_500"].as_f64().unwrap(), 1.0);
    for t in ["25", "50", "75", "100", "125", "150"] {
        assert_eq!(r["ap"][t].as_f64().unwrap(), 1.0, "AP{t}");
    }
    assert_eq!(r["protocol"]["gate_m"].as_f64().unwrap(), 0.5);
    assert!(r["protocol"]["joints"].as_str().unwrap().contains("127"));
    // Everyone moved by 3 cm, 4 cm, 0: every joint and vertex is 50 mm off; Procrustes removes it.
    let moved = dir.path().join("moved");
    write_gt_predictions(&data, &moved, [0.03, 0.04, 0.0]);
    let r = eval(&moved, &dir.path().join("r1.json"));
    assert!((r["mpjpe_mm"].as_f64().unwrap() - 50.0).abs() < 0.05, "{r}");
    assert!((r["pve_mm"].as_f64().unwrap() - 50.0).abs() < 0.05, "{r}");
    assert!(r["pa_pve_mm"].as_f64().unwrap() < 0.05, "{r}");
    assert_eq!(r["ap"]["25"].as_f64().unwrap(), 0.0);
    assert_eq!(r["ap"]["75"].as_f64().unwrap(), 1.0);
    // The same on Human3.6M's 17 joints mapped from SMPL-X: a uniform shift stays 50 mm.
    let o = mvmp(&[
        "eval",
        "--predictions",
        moved.to_str().unwrap(),
        "--data",
        data.to_str().unwrap(),
        "--split",
        "all",
        "--joints",
        "h36m17",
        "--out",
        dir.path().join("r2.json").to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("r2.json")).unwrap())
            .unwrap();
    assert!((r["mpjpe_mm"].as_f64().unwrap() - 50.0).abs() < 0.05, "{r}");
    assert_eq!(r["protocol"]["joint_set"], "h36m17");
    assert!(
        r["protocol"]["joints"]
            .as_str()
            .unwrap()
            .contains("r_hip=right_hip")
    );
    expect_error(
        &[
            "eval",
            "--predictions",
            moved.to_str().unwrap(),
            "--data",
            data.to_str().unwrap(),
            "--joints",
            "coco17",
        ],
        &["coco17", "h36m17"],
    );
    expect_error(
        &[
            "eval",
            "--predictions",
            moved.to_str().unwrap(),
            "--data",
            data.to_str().unwrap(),
            "--format",
            "panoptic",
        ],
        &["panoptic", "--run"],
    );
    // A frame without predictions is named.
    std::fs::remove_file(moved.join("scene_000/frame_000001/people.npz")).unwrap();
    expect_error(
        &[
            "eval",
            "--predictions",
            moved.to_str().unwrap(),
            "--data",
            data.to_str().unwrap(),
            "--split",
            "all",
        ],
        &["scene_000/frame_000001/people.npz", "no predictions"],
    );
    // The reference baseline runs and reports every person matched (it sits on the GT pelvis).
    let o = mvmp(&[
        "eval",
        "--baseline",
        "mean-pose",
        "--data",
        data.to_str().unwrap(),
        "--split",
        "all",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    // Bad arguments are refused clearly.
    expect_error(
        &["eval", "--data", data.to_str().unwrap()],
        &["--run", "--predictions"],
    );
    expect_error(
        &[
            "eval",
            "--baseline",
            "mean-pose",
            "--data",
            data.to_str().unwrap(),
            "--split",
            "valid",
        ],
        &["--split", "\"valid\"", "train, test or all"],
    );
    expect_error(
        &[
            "eval",
            "--baseline",
            "zero",
            "--data",
            data.to_str().unwrap(),
        ],
        &["mean-pose"],
    );
    expect_error(
        &["train", "--config", config("model/tiny.toml").as_str()],
        &["model/tiny.toml"],
    );
    expect_error(
        &[
            "infer",
            "--run",
            dir.path().to_str().unwrap(),
            "--rig",
            "x.json",
            "--images",
            "a.png",
            "--out",
            "o",
        ],
        &["x.json"],
    );
}

#[test]
fn train_eval_infer_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let p = |name: &str| dir.path().join(name).to_string_lossy().into_owned();
    std::fs::write(
        p("s.toml"),
        "scenes = 3\nframes_per_scene = 1\npeople = [2, 2]\narea = [3.0, 3.0]\nimage_size = [96, 64]\n[cameras]\ncount = 2\nrings = [{ height = 2.5, radius = 5.0 }]\n",
    )
    .unwrap();
    let o = mvmp(&["data", "synth", "--config", &p("s.toml"), "--out", &p("ds")]);
    assert!(o.status.success(), "{}", stderr(&o));
    // A small model: 64 px input, a 16 x 16 x 4 grid, every top-K peak kept as a person.
    let model = std::fs::read_to_string(config("model/tiny.toml"))
        .unwrap()
        .replace("image_size = 224", "image_size = 64")
        .replace("root_threshold = 0.3", "root_threshold = -1e9")
        .replace("max_people = 10", "max_people = 2")
        .replace("size = [8.0, 8.0, 2.0]", "size = [4.0, 4.0, 2.0]")
        .replace("shape = [32, 32, 8]", "shape = [16, 16, 4]")
        .replace("dim = 128", "dim = 32");
    std::fs::write(p("model.toml"), model).unwrap();
    std::fs::write(
        p("train.toml"),
        "model = \"model.toml\"\ntrain_views = 2\ntest_views = 2\n[stage1]\nepochs = 1\nlr = 1e-3\n[stage2]\nepochs = 1\nlr = 1e-3\n",
    )
    .unwrap();
    // No dataset: the key is named.
    expect_error(
        &["train", "--config", &p("train.toml"), "--out", &p("r0")],
        &["data", "--data"],
    );
    let o = mvmp(&[
        "train",
        "--config",
        &p("train.toml"),
        "--data",
        &p("ds"),
        "--out",
        &p("run"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    for f in [
        "train.toml",
        "model.toml",
        "state.json",
        "metrics.jsonl",
        "model.bpk",
    ] {
        assert!(dir.path().join("run").join(f).exists(), "{f}");
    }
    // Stage-2 validations report how much the predicted people differ (two kept roots per frame).
    let log = std::fs::read_to_string(dir.path().join("run/metrics.jsonl")).unwrap();
    let last_val: serde_json::Value = log
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .rfind(|l| l["kind"] == "val")
        .unwrap();
    for k in ["heading_spread_deg", "body_pose_spread_deg"] {
        let v = last_val[k].as_f64().unwrap_or(-1.0);
        assert!((0.0..=90.0).contains(&v), "{k} in {last_val}");
    }
    // The same directory again is refused; resuming a finished run does nothing and succeeds.
    expect_error(
        &[
            "train",
            "--config",
            &p("train.toml"),
            "--data",
            &p("ds"),
            "--out",
            &p("run"),
        ],
        &["not empty", "--resume"],
    );
    let o = mvmp(&["train", "--resume", &p("run")]);
    assert!(o.status.success(), "{}", stderr(&o));

    let o = mvmp(&[
        "eval",
        "--run",
        &p("run"),
        "--data",
        &p("ds"),
        "--save-predictions",
        &p("pred"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let r: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("run/eval-test.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(r["format"], "mvmp-eval-report");
    assert_eq!(r["source"]["checkpoint_sha256"].as_str().unwrap().len(), 64);
    assert_eq!(r["source"]["config_sha256"].as_str().unwrap().len(), 64);
    for k in [
        "mpjpe_mm",
        "pve_mm",
        "pa_pve_mm",
        "root_mm",
        "rr_mpjpe_mm",
        "pa_mpjpe_mm",
        "recall_500",
        "ap",
        "protocol",
        "per_scene",
    ] {
        assert!(r.get(k).is_some(), "{k}");
    }
    assert_eq!(r["predictions"], 2, "two kept roots in the one test frame");
    assert!(r["source"].get("ablation").is_none(), "{r}");
    // `eval --data ds ARGS --out REPORT`, which must succeed: its report.
    let scored = |args: &[&str], report: &str| -> serde_json::Value {
        let ds = p("ds");
        let mut all = vec!["eval", "--data", &ds];
        all.extend_from_slice(args);
        all.extend_from_slice(&["--out", report]);
        let o = mvmp(&all);
        assert!(o.status.success(), "{}", stderr(&o));
        serde_json::from_str(&std::fs::read_to_string(report).unwrap()).unwrap()
    };
    // The probe of the run's volumes: every feature set scored, for the trained and the initial weights.
    let (run, ds, report, nowhere) = (p("run"), p("ds"), p("probe.json"), p("missing/probe.json"));
    let probe = [
        "model",
        "probe",
        "--run",
        run.as_str(),
        "--data",
        ds.as_str(),
    ];
    let o = mvmp(
        &[
            &probe[..],
            &["--lattice", "2,2,3", "--out", report.as_str()],
        ]
        .concat(),
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let probe_report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(probe_report["train_people"], 4);
    assert_eq!(probe_report["test_people"], 2);
    let rows = probe_report["scores"].as_array().unwrap();
    // The trained model's 15 rows (the height, the volumes, the ground-truth maps, the model's own
    // placement) and the initial weights' 6.
    assert_eq!(rows.len(), 21, "{probe_report}");
    assert!(
        rows.iter().all(|r| r["r2"].as_f64().unwrap().is_finite()),
        "{probe_report}"
    );
    // The model's own prediction in the probe's terms, over the held-out people it finds.
    let own = &probe_report["model_prediction"];
    assert_eq!(own["people"], 2, "{own}");
    let matched = own["matched"].as_u64().unwrap();
    assert!(matched <= 2, "{own}");
    for key in ["mm", "mm_own_heading"] {
        let mm = own[key].as_f64();
        assert_eq!(mm.is_some(), matched > 0, "{own}");
        assert!(mm.is_none_or(|mm| mm.is_finite() && mm > 0.0), "{own}");
    }
    // HRNet's 2D keypoints on the held-out people, for both weights: every shown joint counted, each
    // within the search window (3 map pixels: at most about 4.3 x 4 = 17 network pixels off).
    for label in ["trained", "initial"] {
        let k = &probe_report["keypoints_held_out"][label];
        assert!(k["keypoints"].as_u64().unwrap() > 0, "{probe_report}");
        let median = k["median_px"].as_f64().unwrap();
        assert!((0.0..17.0).contains(&median), "{label}: {k}");
        let (one, two) = (
            k["within_one_map_pixel"].as_f64().unwrap(),
            k["within_two_map_pixels"].as_f64().unwrap(),
        );
        assert!(
            (0.0..=1.0).contains(&one) && one <= two && two <= 1.0,
            "{label}: {k}"
        );
    }
    expect_error(
        &[&probe[..], &["--lattice", "0,3,8"]].concat(),
        &["--lattice", "0,3,8", "1 to 64"],
    );
    expect_error(
        &[&probe[..], &["--lattice", "64,64,2"]].concat(),
        &["--lattice", "64,64,2", "at most 4096 points"],
    );
    expect_error(
        &[&probe[..], &["--frames", "1"]].concat(),
        &["train split", "1 scene", "--frames 1", "at least 2"],
    );
    expect_error(
        &[&probe[..], &["--views", "3"]].concat(),
        &["3 views requested", "only 2 cameras"],
    );
    expect_error(
        &[&probe[..], &["--out", nowhere.as_str()]].concat(),
        &["--out", "missing", "not a directory"],
    );
    // The decoder alone on the truth's joint volume, from fresh weights: on its training frame the body
    // rotations come closer to the truth than the fresh decoder's (measured: 11.2 to 2.1 degrees).
    let fit = [
        "model",
        "fit-decoder",
        "--run",
        run.as_str(),
        "--data",
        ds.as_str(),
    ];
    let report = p("fit.json");
    let args = [
        "--loss",
        "body",
        "--steps",
        "60",
        "--every",
        "30",
        "--out",
        report.as_str(),
    ];
    let o = mvmp(&[&fit[..], &args[..]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let f: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    let points = f["points"].as_array().unwrap();
    let steps: Vec<u64> = points.iter().map(|p| p["step"].as_u64().unwrap()).collect();
    assert_eq!(steps, [0, 30, 60], "{f}");
    let deg = |i: usize, k: &str| points[i][k].as_f64().unwrap();
    eprintln!("fit-decoder: {}", f["points"]);
    assert!(deg(2, "train_deg") < 0.5 * deg(0, "train_deg"), "{f}");
    assert!(deg(2, "held_out_deg").is_finite(), "{f}");
    let o = mvmp(&[&fit[..], &["--maps", "model", "--steps", "2"]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    expect_error(
        &[&fit[..], &["--lr", "-1"]].concat(),
        &["--lr", "-1", "not a positive learning rate"],
    );
    // A rate at which the weights overflow stops the fit, naming the step, and writes no report.
    let diverged = p("diverged.json");
    expect_error(
        &[
            &fit[..],
            &["--lr", "1e30", "--steps", "3", "--out", &diverged],
        ]
        .concat(),
        &[
            "decoder fit, step",
            "learning rate (1000000000000000000000000000000) is too high",
        ],
    );
    assert!(!std::path::Path::new(&diverged).exists());
    expect_error(
        &[&fit[..], &["--out", nowhere.as_str()]].concat(),
        &["--out", "missing", "not a directory"],
    );
    // Another decoder on the same volumes: the run's own config is taken; one on another grid is not.
    let own = format!("{run}/model.toml");
    let o = mvmp(&[&fit[..], &["--steps", "2", "--decoder", own.as_str()]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("the decoder of"));
    let mut cfg: toml::Table = std::fs::read_to_string(&own).unwrap().parse().unwrap();
    let center = &mut cfg["grid"]["center"][0];
    *center = toml::Value::Float(center.as_float().unwrap() + 0.5);
    let shifted = p("shifted.toml");
    std::fs::write(&shifted, toml::to_string(&cfg).unwrap()).unwrap();
    expect_error(
        &[&fit[..], &["--decoder", shifted.as_str()]].concat(),
        &["shifted.toml", "`grid`", "is not the run's"],
    );
    // A run's backbones extracted start another run (`[init]`); files that do not fit are refused
    // before a run directory is made.
    for (module, file) in [("hrnet", p("hrnet.bpk")), ("vit", p("vit.bpk"))] {
        let o = mvmp(&[
            "model", "extract", "--run", &run, "--module", module, "--out", &file,
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
    }
    expect_error(
        &[
            "model",
            "extract",
            "--run",
            &run,
            "--module",
            "vit",
            "--out",
            &p("run/model.bpk"),
        ],
        &["--out", "would overwrite the input"],
    );
    expect_error(
        &[
            "model",
            "extract",
            "--run",
            &ds,
            "--module",
            "vit",
            "--out",
            &p("x.bpk"),
        ],
        &["not a run directory"],
    );
    let init_run = |hrnet: &str, out: &str| {
        let base = std::fs::read_to_string(p("train.toml")).unwrap();
        let text = format!("{base}[init]\nhrnet = \"{hrnet}\"\nvit = \"vit.bpk\"\n");
        std::fs::write(p("init.toml"), text).unwrap();
        let args = [
            "train",
            "--config",
            &p("init.toml"),
            "--data",
            &ds,
            "--out",
            &p(out),
        ];
        mvmp(&[&args[..], &["--stop-after-steps", "1"]].concat())
    };
    let o = init_run("hrnet.bpk", "init-run");
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("starting from pretrained weights"),
        "{}",
        stderr(&o)
    );
    for (file, want) in [
        ("vit.bpk", "are not in the file"),
        ("none.bpk", "no such file"),
    ] {
        let o = init_run(file, "init-bad");
        let err = stderr(&o);
        assert!(!o.status.success(), "{err}");
        assert!(
            err.contains("`init.hrnet`") && err.contains(file) && err.contains(want),
            "{err}"
        );
        assert!(!dir.path().join("init-bad").exists(), "{err}");
    }
    going_on_from_another_runs_stage1(dir.path(), &ds);
    // The diagnostic that zeroes the image-feature volume is recorded in its report, and refused for
    // predictions, whose model is not at hand.
    let z = scored(&["--run", &p("run"), "--zero-volume"], &p("zero.json"));
    assert!(
        z["source"]["ablation"].as_str().unwrap().contains("zeroed"),
        "{z}"
    );
    assert_eq!(z["ground_truth"], r["ground_truth"]);
    expect_error(
        &[
            "eval",
            "--predictions",
            &p("pred"),
            "--data",
            &p("ds"),
            "--zero-volume",
        ],
        &["--zero-volume", "--run"],
    );
    // Scoring the saved predictions gives the same figures under the same protocol.
    let r2 = scored(&["--predictions", &p("pred")], &p("again.json"));
    for k in ["mpjpe_mm", "pve_mm", "recall_500"] {
        let (a, b) = (r[k].as_f64(), r2[k].as_f64());
        assert!(
            a.zip(b).is_none_or(|(a, b)| (a - b).abs() < 0.5) && a.is_some() == b.is_some(),
            "{k}: {a:?} vs {b:?}"
        );
    }
    // The error budget: every parameter group from the annotations leaves only the pelvis error, so the
    // aligned errors vanish (to float precision) while the matching stays the model's; the report says so.
    let all = "orient,body,hands,face,shape";
    for (i, source) in [["--run", &p("run")], ["--predictions", &p("pred")]]
        .iter()
        .enumerate()
    {
        let report = p(&format!("truth{i}.json"));
        let t = scored(&[&source[..], &["--truth", all]].concat(), &report);
        assert_eq!(
            t["truth_parts"]["parts"].as_array().unwrap().len(),
            5,
            "{t}"
        );
        assert_eq!(t["matched"], r["matched"]);
        if let Some(pa) = t["pa_pve_mm"].as_f64() {
            assert!(pa < 0.5, "PA-PVE {pa} with every part from the truth");
        }
        let (mpjpe, rr) = (t["mpjpe_mm"].as_f64(), t["rr_mpjpe_mm"].as_f64());
        if let (Some(m), Some(rr)) = (mpjpe, rr) {
            assert!(
                rr < 1.0,
                "root-relative {rr} with every part from the truth (MPJPE {m})"
            );
        }
    }
    expect_error(
        &[
            "eval",
            "--baseline",
            "mean-pose",
            "--data",
            &p("ds"),
            "--truth",
            "body",
        ],
        &["--truth", "--run or --predictions"],
    );
    expect_error(
        &[
            "eval",
            "--run",
            &p("run"),
            "--data",
            &p("ds"),
            "--truth",
            "legs,body",
        ],
        &["--truth", "\"legs\"", "orient, body"],
    );

    // Infer on a sequence: a scene directory holds one sub-directory per frame.
    let layout = mvmp_data::DatasetLayout::open(&dir.path().join("ds")).unwrap();
    let scene = &layout.scenes[0];
    let rig = scene.dir.join("cameras.json");
    let o = mvmp(&[
        "infer",
        "--run",
        &p("run"),
        "--rig",
        rig.to_str().unwrap(),
        "--frames",
        scene.dir.to_str().unwrap(),
        "--out",
        &p("seq"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let f = dir.path().join("seq/frame_000000");
    for name in [
        "people.npz",
        "person_00.obj",
        "person_01.ply",
        "overlay_00.png",
        "overlay_01.png",
        "topdown.png",
    ] {
        assert!(f.join(name).exists(), "{name}");
    }
    // A sequence whose second frame has a truncated image fails naming it and leaves no output behind:
    // neither the first frame's files nor the staging directory.
    let bad_seq = dir.path().join("bad_seq");
    for (i, name) in ["frame_000000", "frame_000001"].iter().enumerate() {
        let d = bad_seq.join(name);
        std::fs::create_dir_all(&d).unwrap();
        for v in ["view_00.png", "view_01.png"] {
            let src = scene.dir.join("frame_000000").join(v);
            let bytes = std::fs::read(src).unwrap();
            let keep = if i == 1 && v == "view_01.png" {
                bytes.len() / 2
            } else {
                bytes.len()
            };
            std::fs::write(d.join(v), &bytes[..keep]).unwrap();
        }
    }
    let listing = || {
        let mut v: Vec<_> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        v.sort();
        v
    };
    let outputs_before = listing();
    expect_error(
        &[
            "infer",
            "--run",
            &p("run"),
            "--rig",
            rig.to_str().unwrap(),
            "--frames",
            bad_seq.to_str().unwrap(),
            "--out",
            &p("bad_out"),
        ],
        &["frame_000001", "view_01.png"],
    );
    assert_eq!(
        outputs_before,
        listing(),
        "a failed inference left files behind"
    );
    // Predictions are saved only where a model's predictions are scored.
    expect_error(
        &[
            "eval",
            "--baseline",
            "mean-pose",
            "--data",
            &p("ds"),
            "--save-predictions",
            &p("x"),
        ],
        &["--save-predictions", "--run"],
    );

    // Wrong image count, wrong image size and one file for both cameras are named.
    let img = scene.dir.join("frame_000000/view_00.png");
    let (run, out) = (p("run"), p("x"));
    let infer_images = |images: &[&Path], needles: &[&str]| {
        let mut args = vec!["infer", "--run", &run, "--rig", rig.to_str().unwrap()];
        args.push("--images");
        args.extend(images.iter().map(|i| i.to_str().unwrap()));
        args.extend(["--out", &out]);
        expect_error(&args, needles);
    };
    infer_images(&[&img], &["1 images", "2 cameras"]);
    let small = dir.path().join("small.png");
    image::RgbImage::new(10, 10).save(&small).unwrap();
    infer_images(&[&img, &small], &["small.png", "10x10", "96x64"]);
    infer_images(&[&img, &img], &["view_00.png", "camera 1", "camera 0's"]);

    // The same run on a Human3.6M tree read in place (the data crate's fixtures: S9 "Walking", 5 pose
    // rows; images of the first two cameras at the dataset's sizes), with pseudo-ground-truth fits taken
    // from the run's own predictions on those frames.
    let h36m = dir.path().join("h36m");
    let files = Path::new(env!("CARGO_MANIFEST_DIR")).join("../mvmp-data/tests/fixtures/h36m");
    mvmp_data::fixtures::h36m_tree(&h36m, &files, &[("S9", "Walking")], 2).unwrap();
    let report = p("h36m.json");
    let o = mvmp(&[
        "eval",
        "--run",
        &p("run"),
        "--format",
        "h36m",
        "--data",
        h36m.to_str().unwrap(),
        "--split",
        "S9",
        "--stride",
        "2",
        "--views",
        "2",
        "--out",
        &report,
        "--save-predictions",
        &p("h36m_pred"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    // Saved in the layout pseudo-ground-truth is read from: <subject>/<action>/<image number>.
    for row in [0usize, 2, 4] {
        let f = dir
            .path()
            .join(format!("h36m_pred/S9/Walking/{:06}/people.npz", row + 1));
        assert!(f.is_file(), "{} was not written", f.display());
    }
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert_eq!(r["dataset"], "human3.6m");
    assert_eq!(r["stride"], 2);
    assert_eq!(r["ground_truth_people"], 3);
    assert!(r["meshes"].as_str().unwrap().starts_with("none"));
    assert_eq!(r["protocol"]["joint_set"], "h36m17");
    // Fits at every scored frame: a mesh per person, so PVE is reported when people are matched.
    for row in [0usize, 2, 4] {
        let d = dir.path().join(format!("fits/S9/Walking/{:06}", row + 1));
        std::fs::create_dir_all(&d).unwrap();
        std::fs::copy(f.join("people.npz"), d.join("people.npz")).unwrap();
    }
    let o = mvmp(&[
        "eval",
        "--run",
        &p("run"),
        "--format",
        "h36m",
        "--data",
        h36m.to_str().unwrap(),
        "--split",
        "S9",
        "--stride",
        "2",
        "--views",
        "2",
        "--gate",
        "100",
        "--out",
        &report,
        "--pseudo-gt",
        &p("fits"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let r: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
    assert!(
        r["meshes"].as_str().unwrap().contains("3 of 3"),
        "{}",
        r["meshes"]
    );
    assert_eq!(r["matched"], 3);
    assert!(r["pve_mm"].as_f64().is_some_and(f64::is_finite), "{r}");
    // --pseudo-gt and --stride belong to the joint datasets.
    expect_error(
        &[
            "eval",
            "--run",
            &p("run"),
            "--data",
            &p("ds"),
            "--stride",
            "2",
        ],
        &["--stride", "panoptic and h36m"],
    );
    let (run, ds, fits) = (p("run"), p("ds"), p("fits"));
    let run_ds = ["eval", "--run", &run, "--data", &ds];
    expect_error(
        &[&run_ds[..], &["--pseudo-gt", &fits]].concat(),
        &["--pseudo-gt", "fits", "panoptic and h36m"],
    );
    // A body model given where nothing is posed with it (a run's predictions on the mvmp set).
    expect_error(
        &[&run_ds[..], &["--body-model", "standin:3"]].concat(),
        &["--body-model standin:3", "--predictions"],
    );

    // Training on MVMP-HMR (--data) plus this Human3.6M tree as a second source, validated on it: the
    // sources are listed with their frame counts, and a wrong validation path stops before a run exists.
    let h = h36m.to_string_lossy();
    let sources = format!(
        "\n[[sources]]\nformat = \"h36m\"\nroot = \"{h}\"\nsplit = \"S9\"\nstride = 2\ncameras = [\"54138969\", \"55011271\"]\n"
    );
    let validation = |root: &str| {
        format!(
            "\n[validation]\nformat = \"h36m\"\nroot = \"{root}\"\nsplit = \"S9\"\nstride = 2\ncameras = [\"54138969\", \"55011271\"]\n"
        )
    };
    let base = std::fs::read_to_string(p("train.toml")).unwrap();
    std::fs::write(
        p("mixed.toml"),
        format!("{base}{sources}{}", validation(&format!("{h}-missing"))),
    )
    .unwrap();
    expect_error(
        &[
            "train",
            "--config",
            &p("mixed.toml"),
            "--data",
            &p("ds"),
            "--out",
            &p("mixed"),
        ],
        &["h36m-missing"],
    );
    assert!(!dir.path().join("mixed").exists());
    std::fs::write(
        p("mixed.toml"),
        format!("{base}{sources}{}", validation(&h)),
    )
    .unwrap();
    let o = mvmp(&[
        "train",
        "--config",
        &p("mixed.toml"),
        "--data",
        &p("ds"),
        "--out",
        &p("mixed"),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("h36m") && stderr(&o).contains("(3 frames)"),
        "{}",
        stderr(&o)
    );
    let log = std::fs::read_to_string(dir.path().join("mixed/metrics.jsonl")).unwrap();
    let vals: Vec<serde_json::Value> = log
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|l| l["kind"] == "val")
        .collect();
    assert_eq!(vals.len(), 2, "{log}");
    assert!(vals[1]["recall_500"].is_number(), "{}", vals[1]);
    let saved = std::fs::read_to_string(dir.path().join("mixed/train.toml")).unwrap();
    assert!(
        saved.contains("[[sources]]") && saved.contains("[validation]"),
        "{saved}"
    );
}

/// `mvmp train --from-stage1 RUN`: a run of a config that differs only in a stage-2 loss term goes on
/// from RUN's stage-1 checkpoint (its log begins with RUN's own lines); a config whose stage 1 differs
/// is refused, leaving no run directory.
fn going_on_from_another_runs_stage1(dir: &Path, ds: &str) {
    let p = |name: &str| dir.join(name).to_string_lossy().into_owned();
    let base = std::fs::read_to_string(p("train.toml")).unwrap();
    let stage1 = base.clone() + "[init]\nhrnet = \"hrnet.bpk\"\nvit = \"vit.bpk\"\n";
    let from = |text: String, out: &str| {
        std::fs::write(p("branch.toml"), text).unwrap();
        mvmp(&[
            "train",
            "--config",
            &p("branch.toml"),
            "--from-stage1",
            &p("init-run"),
            "--out",
            &p(out),
            "--stop-after-steps",
            "2",
        ])
    };
    let o = from(format!("{stage1}[loss]\ndensity = 0.0\n"), "branched");
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(
        stderr(&o).contains("going on from step 1"),
        "{}",
        stderr(&o)
    );
    let first = |run: &str| {
        let log = std::fs::read_to_string(dir.join(run).join("metrics.jsonl")).unwrap();
        log.lines().next().unwrap().to_string()
    };
    assert_eq!(first("init-run"), first("branched"));
    let train = std::fs::read_to_string(dir.join("branched/train.toml")).unwrap();
    assert!(train.contains("density = 0.0"), "{train}");
    let o = from(base.replace("lr = 1e-3\n", "lr = 2e-3\n"), "refused");
    assert!(!o.status.success());
    for needle in ["--from-stage1", "stage 1 would not train as"] {
        assert!(stderr(&o).contains(needle), "{needle:?}: {}", stderr(&o));
    }
    assert!(!dir.join("refused").exists());
    let o = mvmp(&["train", "--from-stage1", &p("init-run"), "--data", ds]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
}

#[test]
fn data_check_panoptic_reports_an_empty_tree() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path().to_str().unwrap();
    let o = mvmp(&["data", "check", "--format", "panoptic", d]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stdout).contains("no Panoptic sequence"));
    expect_error(
        &["data", "check", "--format", "coco", d],
        &["coco", "mvmp, panoptic or h36m"],
    );
}

#[test]
fn data_check_h36m_lists_subjects_and_names_missing_images() {
    use mvmp_data::h36m::{camera_file, pose_file};
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("../mvmp-data/tests/fixtures/h36m");
    std::fs::copy(fixtures.join("camera-parameters.json"), camera_file(root)).unwrap();
    let p = pose_file(root, "S9", "Sitting 1");
    std::fs::create_dir_all(p.parent().unwrap()).unwrap();
    std::fs::copy(fixtures.join("pose_double_gzip.cdf"), p).unwrap();
    let o = mvmp(&["data", "check", "--format", "h36m", root.to_str().unwrap()]);
    assert!(!o.status.success());
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("S9: 1 actions, 5 frames"), "{out}");
    assert!(
        out.contains("Sitting 1: 4 cameras, 5 frames, 0 with every camera's image"),
        "{out}"
    );
    assert!(
        out.contains("Sitting 1.54138969/000001.jpg: missing image"),
        "{out}"
    );
    assert!(stderr(&o).contains("4 problem(s)"), "{}", stderr(&o));
    // Human3.6M scores a run; the layout's files are named when absent.
    expect_error(
        &[
            "eval",
            "--baseline",
            "mean-pose",
            "--data",
            root.to_str().unwrap(),
            "--format",
            "h36m",
        ],
        &["h36m", "--run"],
    );
}

/// The numbers of a benchmark's table: every line after its title and header.
fn table_rows(out: &str) -> Vec<Vec<f64>> {
    out.lines()
        .skip(2)
        .map(|l| l.split_whitespace().map(|x| x.parse().unwrap()).collect())
        .collect()
}

/// The training benchmark on a tiny synthetic set: one row per stage and path (fused, and with
/// `--baseline` the tensor ops), one timed step each, every phase within the step's seconds, and the
/// ratio of the two paths; a config without data is refused naming it.
#[test]
fn the_training_benchmark_splits_each_stage() {
    let o = mvmp(&[
        "bench",
        "train",
        "--steps",
        "1",
        "--scenes",
        "3",
        "--baseline",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8(o.stdout).unwrap();
    let lines: Vec<&str> = out.lines().skip(2).collect();
    assert_eq!(lines.len(), 6, "{out}");
    for (i, stage) in [1, 2].into_iter().enumerate() {
        for (j, path) in ["fused", "tensor-ops"].into_iter().enumerate() {
            let mut cols = lines[3 * i + j].split_whitespace();
            assert_eq!(cols.next(), Some(stage.to_string().as_str()), "{out}");
            assert_eq!(cols.next(), Some(path), "{out}");
            // A phase the stage has not (stage 1 keeps no weight average, neither stage its volumes)
            // reads "-".
            let r: Vec<f64> = cols.map(|x| x.parse().unwrap_or(0.0)).collect();
            assert_eq!((r[0], r.len()), (1.0, 10), "{out}");
            let col = |k: usize| lines[3 * i + j].split_whitespace().nth(k).unwrap();
            assert_eq!((col(5), col(10) == "-"), ("-", stage == 1), "{out}");
            let phases: f64 = r[2..9].iter().sum();
            // The model alone is 15 MB; training holds it several times over, and far less than 10 GB.
            assert!(r[9] > 30.0 && r[9] < 10000.0, "peak MiB: {out}");
            assert!(r[1] > 0.0 && phases <= r[1] + 2e-3, "{out}");
        }
        let ratio = lines[3 * i + 2];
        assert!(ratio.contains("tensor-ops / fused:"), "{out}");
        let x: f64 = ratio
            .rsplit(' ')
            .next()
            .unwrap()
            .trim_end_matches('x')
            .parse()
            .unwrap();
        assert!(x > 0.0, "{out}");
    }
    assert!(out.lines().nth(1).unwrap().contains("backward"), "{out}");
    let dir = tempfile::tempdir().unwrap();
    let cfg = dir.path().join("t.toml");
    let configs = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs");
    let train = std::fs::read_to_string(configs.join("train/tiny.toml")).unwrap();
    let model = configs.join("model/tiny.toml");
    let train = train.replace(
        "\"../model/tiny.toml\"",
        &format!("{:?}", model.to_str().unwrap()),
    );
    std::fs::write(&cfg, train).unwrap();
    expect_error(
        &["bench", "train", "--config", cfg.to_str().unwrap()],
        &["t.toml", "no training data"],
    );
}

/// The attention benchmark: one row per token count; burn's plain attention grows with the square of
/// the tokens (its backward keeps the probabilities), the tiled one far less; a zero count is refused.
#[test]
fn the_attention_benchmark_shows_the_tiled_memory_growing_slower() {
    let args = [
        "bench",
        "attention",
        "--tokens",
        "256,512",
        "--heads",
        "4",
        "--head-dim",
        "16",
        "--tile",
        "64",
    ];
    let o = mvmp(&args);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8(o.stdout).unwrap();
    let rows = table_rows(&out);
    assert_eq!(rows.len(), 2, "{out}");
    let [small, large] = [&rows[0], &rows[1]];
    assert_eq!((small[0], large[0]), (256.0, 512.0), "{out}");
    // Columns: tokens, tiled s, tiled MiB, plain s, plain MiB.
    assert!(
        large[4] > 3.0 * small[4],
        "plain memory should grow about 4x: {out}"
    );
    // The tiled peak at these sizes is a few hundred KiB, and how many tiles' buffers are live at once
    // depends on the threads' timing (0.8-2.0 MiB at 512 tokens, measured on a loaded machine): so its
    // growth is held against the plain one's, not against its own size at 256 tokens.
    assert!(
        large[2] - small[2] < (large[4] - small[4]) / 4.0 && large[2] < large[4] / 4.0,
        "{out}"
    );
    let huge = mvmp(&["bench", "attention", "--tokens", "100000000"]);
    assert_eq!(huge.status.code(), Some(1), "{}", stderr(&huge));
    assert!(
        stderr(&huge).contains("--tokens 100000000"),
        "{}",
        stderr(&huge)
    );
    assert!(huge.stdout.is_empty(), "nothing printed before the refusal");
    let mut zero = args.to_vec();
    zero[3] = "256,0";
    let o = mvmp(&zero);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("--tokens"), "{}", stderr(&o));
}

/// The learning benchmark end to end at a tiny scale: two variants with two seeds each, trained for a
/// few seconds, the report with its tables and directions, the comparison picture; an unknown variant
/// and a repeated seed are named.
#[test]
fn the_learning_benchmark_compares_variants() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("learn");
    let o = mvmp(&[
        "bench",
        "learn",
        "--minutes",
        "0.02",
        "--scenes",
        "3",
        "--variants",
        "full,no_density",
        "--seeds",
        "3,5",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let report = std::fs::read_to_string(out.join("learning.md")).unwrap();
    for needle in [
        "| full | 3 |",
        "| no_density | 5 |",
        "Over the seeds [3, 5]",
        "the density loss lowers MPJPE",
        "curves.png",
    ] {
        assert!(report.contains(needle), "{needle:?} not in {report}");
    }
    assert!(out.join("curves.png").metadata().unwrap().len() > 1000);
    for run in ["full-s3", "full-s5", "no_density-s3", "no_density-s5"] {
        assert!(out.join("runs").join(run).join("eval-test.json").exists());
        let train =
            std::fs::read_to_string(out.join("configs").join(run).join("train.toml")).unwrap();
        let seed = &run[run.len() - 1..];
        assert!(train.contains(&format!("seed = {seed}")), "{train}");
        // Whether the run trained its whole schedule is recorded, and the report's row says the same.
        let scored =
            std::fs::read_to_string(out.join("runs").join(run).join("bench.json")).unwrap();
        let scored: serde_json::Value = serde_json::from_str(&scored).unwrap();
        let cell = match scored["finished"].as_bool() {
            Some(true) => "| trained |",
            Some(false) => "| stopped by the time guard |",
            None => panic!("no `finished` in {scored}"),
        };
        let (name, seed) = run.split_once("-s").unwrap();
        let row = report
            .lines()
            .find(|l| l.starts_with(&format!("| {name} | {seed} |")))
            .unwrap_or_else(|| panic!("no row of {run} in {report}"));
        let stage1 = match name {
            "full" => "| its own |".to_string(),
            _ => format!("| full-s{seed}'s |"),
        };
        assert!(row.ends_with(&format!("{cell}{}", &stage1[1..])), "{row}");
    }
    stage1_is_shared(&out);
    resume_goes_on_from_what_is_done(&out);
    expect_error(
        &[
            "bench",
            "learn",
            "--seeds",
            "1,2,1",
            "--out",
            dir.path().join("y").to_str().unwrap(),
        ],
        &["--seeds", "seed 1 is given twice"],
    );
    assert!(!dir.path().join("y").exists());
    expect_error(
        &[
            "bench",
            "learn",
            "--variants",
            "full,huge",
            "--out",
            dir.path().join("x").to_str().unwrap(),
        ],
        &["--variants", "huge", "voxelsmplx"],
    );
}

/// `--epochs` fixes the schedule instead of sizing it from the minutes: the plan and the report say so,
/// and the time it is given is what those epochs take at the measured step times. Counts that are not
/// two positive numbers are named, and nothing is left behind; it cannot go with --minutes.
#[test]
fn the_learning_benchmark_trains_a_given_schedule() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("learn");
    let o = mvmp(&[
        "bench",
        "learn",
        "--epochs",
        "1,2",
        "--scenes",
        "3",
        "--variants",
        "full",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let plan = std::fs::read_to_string(out.join("plan.json")).unwrap();
    let plan: serde_json::Value = serde_json::from_str(&plan).unwrap();
    assert_eq!(plan["epochs"], serde_json::json!([1, 2]));
    assert_eq!(plan["fixed_epochs"], serde_json::json!(true));
    // Two training frames: 2 stage-1 steps and 4 stage-2 steps at the measured times, over 0.85.
    let step = |i: usize| plan["step_seconds"][i].as_f64().unwrap();
    let minutes = (2.0 * step(0) + 4.0 * step(1)) / 0.85 / 60.0;
    let given = plan["minutes"].as_f64().unwrap();
    assert!((given - minutes).abs() < 1e-9, "{given} against {minutes}");
    let report = std::fs::read_to_string(out.join("learning.md")).unwrap();
    assert!(
        report.contains("`mvmp bench learn --epochs 1,2 --scenes 3`"),
        "{report}"
    );
    assert!(report.contains("1 + 2 epochs (given;"), "{report}");
    let scored = std::fs::read_to_string(out.join("runs/full/bench.json")).unwrap();
    let scored: serde_json::Value = serde_json::from_str(&scored).unwrap();
    assert_eq!(scored["steps"], serde_json::json!(6), "{scored}");
    for bad in ["2", "3,0", "1,2,3"] {
        let target = dir.path().join(format!("bad-{}", bad.replace(',', "-")));
        expect_error(
            &[
                "bench",
                "learn",
                "--epochs",
                bad,
                "--out",
                target.to_str().unwrap(),
            ],
            &["--epochs", "S1,S2"],
        );
        assert!(!target.exists(), "{}", target.display());
    }
    let o = mvmp(&["bench", "learn", "--epochs", "1,1", "--minutes", "3"]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("--minutes"), "{}", stderr(&o));
    learning_from_a_pretrained_hrnet(dir.path(), &out.join("runs/full"));
}

/// `--init-hrnet`: every variant starts from the HRNet weights given (here the benchmark run's own,
/// extracted); a file that does not fit is named before anything is made. With `--kept-volumes` every
/// variant's stage 2 trains the decoder alone on kept volumes, with the decoder's `pose_trunk`.
fn learning_from_a_pretrained_hrnet(dir: &Path, run: &Path) {
    let file = |name: &str| dir.join(name).to_string_lossy().into_owned();
    for (module, out) in [("hrnet", file("hrnet.bpk")), ("vit", file("vit.bpk"))] {
        let run = run.to_str().unwrap();
        let o = mvmp(&[
            "model", "extract", "--run", run, "--module", module, "--out", &out,
        ]);
        assert!(o.status.success(), "{}", stderr(&o));
    }
    let out = dir.join("learn-init");
    let args = |init: &str| {
        let (out, init) = (out.to_str().unwrap().to_string(), init.to_string());
        let fixed = ["bench", "learn", "--epochs", "1,1", "--scenes", "3"];
        let given = [
            "--variants",
            "full",
            "--init-hrnet",
            &init,
            "--kept-volumes",
            "--out",
            &out,
        ];
        mvmp(&[&fixed[..], &given[..]].concat())
    };
    let o = args(&file("vit.bpk"));
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("--init-hrnet") && stderr(&o).contains("vit.bpk"),
        "{}",
        stderr(&o)
    );
    assert!(!out.exists(), "{}", stderr(&o));
    let o = args(&file("hrnet.bpk"));
    assert!(o.status.success(), "{}", stderr(&o));
    let plan = std::fs::read_to_string(out.join("plan.json")).unwrap();
    assert!(plan.contains(&file("hrnet.bpk")), "{plan}");
    let train = std::fs::read_to_string(out.join("configs/full/train.toml")).unwrap();
    assert!(
        train.contains("[init]") && train.contains(&file("hrnet.bpk")),
        "{train}"
    );
    let (plan, stage2) = (
        plan.replace(' ', ""),
        train.split("[stage2]").nth(1).unwrap(),
    );
    assert!(plan.contains("\"kept_volumes\":true"), "{plan}");
    for key in ["freeze_backbone", "freeze_detection", "cache_volumes"] {
        assert!(stage2.contains(&format!("{key} = true")), "{train}");
    }
    let model = std::fs::read_to_string(out.join("configs/full/model.toml")).unwrap();
    assert!(model.contains("pose_trunk = true"), "{model}");
    // Stage 2 read the volumes it kept.
    let log = std::fs::read_to_string(out.join("runs/full/metrics.jsonl")).unwrap();
    let stage2: Vec<&str> = log
        .lines()
        .filter(|l| l.contains("\"kind\":\"step\"") && l.contains("\"stage\":2"))
        .collect();
    assert!(!stage2.is_empty() && stage2.iter().all(|l| l.contains("\"volumes\":")));
    let report = std::fs::read_to_string(out.join("learning.md")).unwrap();
    assert!(
        report.contains(&format!(
            "--init-hrnet {} --kept-volumes",
            file("hrnet.bpk")
        )),
        "{report}"
    );
}

/// `--pretrain-hrnet SCENES,EPOCHS`: the benchmark pretrains the HRNet every variant starts from (stage
/// 1 alone on a set of the next seed) before the variants, and its plan, configs and report say so;
/// counts that are not a set of at least 3 scenes and a positive number of epochs are named before
/// anything is made, and it cannot go with --init-hrnet.
#[test]
fn the_learning_benchmark_pretrains_its_hrnet() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("learn");
    let o = mvmp(&[
        "bench",
        "learn",
        "--epochs",
        "1,1",
        "--scenes",
        "3",
        "--variants",
        "full",
        "--pretrain-hrnet",
        "3,2",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("(3 scenes, seed 1)"), "{}", stderr(&o));
    let hrnet = std::path::absolute(out.join("pretrain/hrnet.bpk")).unwrap();
    let hrnet = hrnet.to_str().unwrap();
    assert!(std::path::Path::new(hrnet).metadata().unwrap().len() > 1000);
    // Two epochs of the set's two training frames, stage 1 alone.
    let state = std::fs::read_to_string(out.join("pretrain/run/state.json")).unwrap();
    let state: serde_json::Value = serde_json::from_str(&state).unwrap();
    assert_eq!(state["stage"], serde_json::json!(1), "{state}");
    assert_eq!(state["global_step"], serde_json::json!(4), "{state}");
    assert_eq!(state["finished"], serde_json::json!(true), "{state}");
    let plan = std::fs::read_to_string(out.join("plan.json")).unwrap();
    let plan: serde_json::Value = serde_json::from_str(&plan).unwrap();
    assert_eq!(plan["pretrain"], serde_json::json!([3, 2]), "{plan}");
    assert_eq!(plan["init_hrnet"], serde_json::json!(hrnet), "{plan}");
    let train = std::fs::read_to_string(out.join("configs/full/train.toml")).unwrap();
    assert!(train.contains("[init]") && train.contains(hrnet), "{train}");
    let report = std::fs::read_to_string(out.join("learning.md")).unwrap();
    assert!(
        report.contains("`mvmp bench learn --epochs 1,1 --pretrain-hrnet 3,2 --scenes 3`"),
        "{report}"
    );
    for bad in ["2,1", "3,0", "3"] {
        let target = dir.path().join(format!("bad-{}", bad.replace(',', "-")));
        let args = ["bench", "learn", "--pretrain-hrnet", bad, "--out"];
        expect_error(
            &[&args[..], &[target.to_str().unwrap()]].concat(),
            &["--pretrain-hrnet", "SCENES,EPOCHS"],
        );
        assert!(!target.exists(), "{}", target.display());
    }
    let o = mvmp(&[
        "bench",
        "learn",
        "--pretrain-hrnet",
        "3,1",
        "--init-hrnet",
        hrnet,
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("--init-hrnet"), "{}", stderr(&o));
}

/// The density ablation's configs train stage 1 as the full model's do (the term is stage 2's), so
/// its runs go on from the full model's copy at the end of stage 1 (or where the time guard stopped
/// it): the copy's stage-1 log lines are the two runs' own, times and all, not trained again, and
/// the stage-1 losses after them agree.
fn stage1_is_shared(out: &Path) {
    let stage1 = |run: &Path| -> Vec<(String, serde_json::Value)> {
        let log = std::fs::read_to_string(run.join("metrics.jsonl")).unwrap();
        log.lines()
            .map(|l| (l.to_string(), serde_json::from_str(l).unwrap()))
            .filter(|(_, v): &(String, serde_json::Value)| v["kind"] == "step" && v["stage"] == 1)
            .collect()
    };
    let totals = |r: &[(String, serde_json::Value)]| -> Vec<f64> {
        r.iter()
            .map(|(_, v)| v["total"].as_f64().unwrap())
            .collect()
    };
    for seed in [3, 5] {
        let (full, ablated) = (format!("full-s{seed}"), format!("no_density-s{seed}"));
        let scored = out.join("runs").join(&ablated).join("bench.json");
        let scored: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(scored).unwrap()).unwrap();
        assert_eq!(scored["stage1_from"], serde_json::json!(full), "{scored}");
        let kept = stage1(&out.join("stage1").join(&full));
        let a = stage1(&out.join("runs").join(&full));
        let b = stage1(&out.join("runs").join(&ablated));
        assert!(!kept.is_empty() && kept.len() <= a.len());
        for (i, (line, _)) in kept.iter().enumerate() {
            assert_eq!((line, line), (&a[i].0, &b[i].0));
        }
        assert_eq!(totals(&a), totals(&b));
    }
    let full = std::fs::read_to_string(out.join("runs/full-s3/bench.json")).unwrap();
    assert!(!full.contains("stage1_from"), "{full}");
}

/// A benchmark stopped with runs scored, one trained but not scored and one not begun (as an
/// interrupt leaves it) goes on with `--resume`: the scored run is read back, not trained again, the
/// others are finished, and the report has all four. A variant added then trains on the same plan beside
/// them. Without a plan there is nothing to resume, and the plan's settings cannot be given again.
fn resume_goes_on_from_what_is_done(out: &Path) {
    let runs = out.join("runs");
    let kept = std::fs::read_to_string(runs.join("full-s3/bench.json")).unwrap();
    std::fs::remove_dir_all(runs.join("no_density-s5")).unwrap();
    std::fs::remove_file(runs.join("full-s5/bench.json")).unwrap();
    std::fs::remove_file(out.join("learning.md")).unwrap();
    let o = mvmp(&["bench", "learn", "--resume", "--out", out.to_str().unwrap()]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("[full-s3] trained and scored before"));
    assert!(!stderr(&o).contains("[full-s5] trained and scored before"));
    assert_eq!(
        std::fs::read_to_string(runs.join("full-s3/bench.json")).unwrap(),
        kept
    );
    assert!(runs.join("no_density-s5/bench.json").exists());
    let report = std::fs::read_to_string(out.join("learning.md")).unwrap();
    for run in [
        "| full | 3 |",
        "| full | 5 |",
        "| no_density | 3 |",
        "| no_density | 5 |",
    ] {
        assert!(report.contains(run), "{run:?} not in {report}");
    }
    // A finished benchmark takes more variants on its schedule; the runs done stay.
    let o = mvmp(&[
        "bench",
        "learn",
        "--resume",
        "--variants",
        "voxelsmplx",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    for run in ["full-s3", "full-s5", "no_density-s3", "no_density-s5"] {
        let before = format!("[{run}] trained and scored before");
        assert!(stderr(&o).contains(&before), "{before:?}: {}", stderr(&o));
    }
    let plan = std::fs::read_to_string(out.join("plan.json")).unwrap();
    let plan: serde_json::Value = serde_json::from_str(&plan).unwrap();
    assert_eq!(
        plan["variants"],
        serde_json::json!(["full", "voxelsmplx", "no_density"])
    );
    let report = std::fs::read_to_string(out.join("learning.md")).unwrap();
    assert!(report.contains("| voxelsmplx | 5 |"), "{report}");
    assert!(
        report.contains("the full model beats VoxelSMPLX"),
        "{report}"
    );
    expect_error(
        &[
            "bench",
            "learn",
            "--resume",
            "--variants",
            "huge",
            "--out",
            out.to_str().unwrap(),
        ],
        &["--variants", "huge"],
    );
    let unchanged = std::fs::read_to_string(out.join("plan.json")).unwrap();
    assert_eq!(
        serde_json::from_str::<serde_json::Value>(&unchanged).unwrap(),
        plan
    );
    let none = out.with_file_name("none");
    expect_error(
        &[
            "bench",
            "learn",
            "--resume",
            "--out",
            none.to_str().unwrap(),
        ],
        &["plan.json", "start one with --out"],
    );
    let o = mvmp(&[
        "bench",
        "learn",
        "--resume",
        "--minutes",
        "1",
        "--out",
        out.to_str().unwrap(),
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", stderr(&o));
    assert!(stderr(&o).contains("--minutes"), "{}", stderr(&o));
}

/// Output that cannot be written (a full device, a closed pipe) is an error with a message, not a panic.
#[cfg(target_os = "linux")]
#[test]
fn an_unwritable_standard_output_is_an_error_not_a_panic() {
    let full = std::fs::OpenOptions::new()
        .write(true)
        .open("/dev/full")
        .unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_mvmp"))
        .args(["model", "summary", "--config", &config("model/tiny.toml")])
        .stdout(full)
        .output()
        .unwrap();
    let err = stderr(&o);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(err.contains("writing to standard output"), "{err}");
    assert!(!err.contains("panicked"), "{err}");
}

#[test]
fn the_training_memory_estimate_grows_from_weights_to_stage_two() {
    let o = mvmp(&[
        "model",
        "summary",
        "--config",
        &config("model/tiny.toml"),
        "--views",
        "2",
        "--training",
        "--people",
        "2",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    let mb = |label: &str| -> f64 {
        let line = out
            .lines()
            .find(|l| l.trim_start().starts_with(label))
            .unwrap_or_else(|| panic!("{label} missing from {out}"));
        line.split_whitespace()
            .rev()
            .nth(1)
            .unwrap()
            .parse()
            .unwrap()
    };
    let (weights, s1, s2) = (mb("weights"), mb("stage 1: peak"), mb("stage 2: peak"));
    // Stage 2 adds the ViT, the decoder, the body layer's forward and the mesh losses to stage 1.
    assert!(weights > 0.0 && s1 > weights && s2 > s1, "{out}");
    assert_eq!(out.matches("probe:").count(), 6, "{out}");
    // With a ViT heatmap head stage 1 trains the ViT too: its Adam state and activations join stage 1.
    let dir = tempfile::tempdir().unwrap();
    let tiny = std::fs::read_to_string(config("model/tiny.toml")).unwrap();
    let with_head = dir.path().join("tiny-vit-heatmaps.toml");
    std::fs::write(&with_head, format!("vit_heatmaps = true\n{tiny}")).unwrap();
    let args = [
        "model",
        "summary",
        "--views",
        "2",
        "--training",
        "--people",
        "2",
    ];
    let o = mvmp(&[&args[..], &["--config", with_head.to_str().unwrap()]].concat());
    assert!(o.status.success(), "{}", stderr(&o));
    let head_out = String::from_utf8_lossy(&o.stdout).to_string();
    let s1_head = head_out
        .lines()
        .find(|l| l.trim_start().starts_with("stage 1: peak"))
        .and_then(|l| l.split_whitespace().rev().nth(1)?.parse::<f64>().ok())
        .unwrap_or_else(|| panic!("stage 1: peak missing from {head_out}"));
    assert!(s1_head > s1, "{s1_head} vs {s1}: {head_out}");
    let o = mvmp(&[
        "model",
        "summary",
        "--config",
        &config("model/tiny.toml"),
        "--training",
        "--people",
        "0",
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("--people"), "{}", stderr(&o));
}

/// SIGTERM while the demo works removes its unfinished outputs, and the exit status says the signal
/// stopped it (128 + 15), as a shell reports a killed process.
#[cfg(unix)]
#[test]
fn a_terminated_demo_leaves_nothing_and_exits_143() {
    let root = tempfile::tempdir().unwrap();
    let out = root.path().join("demo");
    let mut child = Command::new(env!("CARGO_BIN_EXE_mvmp"))
        .args(["demo", "--out", out.to_str().unwrap()])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    // The configs are the demo's first output; the signal comes while it synthesises the dataset.
    let started = std::time::Instant::now();
    while !out.join("configs/train.toml").exists() {
        assert!(
            started.elapsed().as_secs() < 60,
            "the demo wrote no configs in a minute"
        );
        if let Some(status) = child.try_wait().unwrap() {
            panic!("the demo ended before the signal: {status}");
        }
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let killed = Command::new("kill")
        .args(["-TERM", &child.id().to_string()])
        .status()
        .unwrap();
    assert!(killed.success());
    let o = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(143), "{err}");
    assert!(err.contains("interrupted"), "{err}");
    assert!(!out.exists(), "the demo's directory stays: {err}");
    let left: Vec<_> = std::fs::read_dir(root.path()).unwrap().collect();
    assert!(left.is_empty(), "left behind: {left:?}");
}
