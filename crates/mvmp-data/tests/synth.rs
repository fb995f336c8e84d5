//! Synthetic data: geometry of the renders against the annotations, determinism, round trips, the loader,
//! and clear errors for broken datasets.
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use burn::data::dataloader::batcher::Batcher;
use burn::data::dataset::Dataset;
use burn::tensor::{Device, Tensor, TensorData};
use mvmp_data::check::check_dataset;
use mvmp_data::dataset::FrameDataset;
use mvmp_data::layout::{Annotation, DatasetLayout};
use mvmp_data::loader::{FrameBatcher, Split, ViewChoice, project_to_network, split_scenes};
use mvmp_data::synth::{SynthConfig, generate};
use mvmp_smplx::{ParamTensors, SmplxLayer, Translation};
use nalgebra::{Vector2, Vector3};

fn small_config(seed: u64) -> SynthConfig {
    let mut c = SynthConfig {
        name: "test".into(),
        seed,
        scenes: 3,
        frames_per_scene: 2,
        people: [3, 4],
        area: [4.0, 4.0],
        image_size: [160, 120],
        ..Default::default()
    };
    c.cameras.count = 3;
    c.cameras.rings[0].radius = 6.0;
    c.cameras.k1 = [-0.05, 0.02];
    c
}

/// One dataset shared by the tests (made once).
fn dataset() -> &'static Path {
    static DIR: OnceLock<(tempfile::TempDir, PathBuf)> = OnceLock::new();
    let (_, p) = DIR.get_or_init(|| {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("ds");
        generate(&small_config(11), &out, Path::new("."), &|| {}).unwrap();
        (dir, out)
    });
    p
}

fn read_gray(path: &Path) -> image::GrayImage {
    image::open(path).unwrap().to_luma8()
}

fn read_depth(path: &Path) -> image::ImageBuffer<image::Luma<u16>, Vec<u16>> {
    image::open(path).unwrap().to_luma16()
}

#[test]
fn visible_joints_fall_inside_their_persons_mask() {
    let layout = DatasetLayout::open(dataset()).unwrap();
    let (mut inside, mut total) = (0, 0);
    for f in layout.frames() {
        let rig = &layout.scenes[f.scene].rig;
        let ann = Annotation::read(&f.dir.join("annotation.json"), rig.len()).unwrap();
        for (v, cam) in rig.cameras.iter().enumerate() {
            let mask = read_gray(&f.dir.join(&ann.masks.as_ref().unwrap()[v]));
            for (pi, p) in ann.people.iter().enumerate() {
                for (ji, j) in p.views[v].joints_2d.iter().enumerate() {
                    if j[2] == 0.0 {
                        continue;
                    }
                    // The annotation's pixel is the camera projection of the 3D joint.
                    let (uv, _) = cam.project(&Vector3::from(p.joints_3d[ji]));
                    assert!((uv - Vector2::new(j[0], j[1])).norm() < 1e-6);
                    total += 1;
                    let (x, y) = (j[0].round() as i64, j[1].round() as i64);
                    let hit = (-1..=1).any(|dy| {
                        (-1..=1).any(|dx| {
                            let (xx, yy) = (x + dx, y + dy);
                            xx >= 0
                                && yy >= 0
                                && (xx as u32) < mask.width()
                                && (yy as u32) < mask.height()
                                && mask.get_pixel(xx as u32, yy as u32).0[0] as usize == pi + 1
                        })
                    });
                    if hit {
                        inside += 1;
                    }
                }
            }
        }
    }
    assert!(total > 500, "too few visible joints: {total}");
    // Joints are inside the body or on its surface; a few surface points may fall a pixel off at edges.
    assert!(
        inside as f64 >= 0.98 * total as f64,
        "{inside} of {total} visible joints inside their mask"
    );
}

/// Nearest intersection of a ray with a triangle mesh (Moller-Trumbore), as a distance along the ray.
fn ray_mesh(
    o: Vector3<f64>,
    d: Vector3<f64>,
    verts: &[[f32; 3]],
    faces: &[[u32; 3]],
) -> Option<f64> {
    let mut best: Option<f64> = None;
    for f in faces {
        let [a, b, c] = f.map(|i| {
            let v = verts[i as usize];
            Vector3::new(v[0] as f64, v[1] as f64, v[2] as f64)
        });
        let (e1, e2) = (b - a, c - a);
        let p = d.cross(&e2);
        let det = e1.dot(&p);
        if det.abs() < 1e-12 {
            continue;
        }
        let t0 = o - a;
        let u = t0.dot(&p) / det;
        if !(0.0..=1.0).contains(&u) {
            continue;
        }
        let q = t0.cross(&e1);
        let v = d.dot(&q) / det;
        if v < 0.0 || u + v > 1.0 {
            continue;
        }
        let t = e2.dot(&q) / det;
        if t > 0.0 && best.is_none_or(|b| t < b) {
            best = Some(t);
        }
    }
    best
}

#[test]
fn depth_at_mask_pixels_is_the_mesh_depth_and_parameters_reproduce_the_joints() {
    let layout = DatasetLayout::open(dataset()).unwrap();
    let model = layout.body_model().unwrap();
    let device = Device::flex();
    let layer = SmplxLayer::new(&model, &device);
    let f = &layout.frames()[1];
    let rig = &layout.scenes[f.scene].rig;
    let ann = Annotation::read(&f.dir.join("annotation.json"), rig.len()).unwrap();
    // The stored parameters (smplx transl) reproduce the stored joints and pelvis.
    let params: Vec<_> = ann.people.iter().map(|p| p.smplx.clone()).collect();
    let pt = ParamTensors::from_params(&params, &device);
    let out = layer.forward_axis_angle(
        pt.pose,
        pt.betas,
        pt.expression,
        pt.transl,
        Translation::Standard,
    );
    let verts: Vec<f32> = out.vertices.into_data().try_into_vec().unwrap();
    let joints: Vec<f32> = out.joints.into_data().try_into_vec().unwrap();
    let nv = layer.num_vertices();
    let nj = layer.num_joints();
    for (i, p) in ann.people.iter().enumerate() {
        for (k, j) in p.joints_3d.iter().enumerate() {
            for a in 0..3 {
                assert!(
                    (joints[(i * nj + k) * 3 + a] as f64 - j[a]).abs() < 1e-4,
                    "person {i} joint {k}"
                );
            }
        }
        for a in 0..3 {
            assert!((p.pelvis[a] - p.joints_3d[0][a]).abs() < 1e-9);
        }
    }
    let meshes: Vec<Vec<[f32; 3]>> = (0..ann.people.len())
        .map(|i| {
            verts[i * nv * 3..(i + 1) * nv * 3]
                .chunks_exact(3)
                .map(|c| [c[0], c[1], c[2]])
                .collect()
        })
        .collect();
    let mut checked = 0;
    for (v, cam) in rig.cameras.iter().enumerate() {
        let mask = read_gray(&f.dir.join(&ann.masks.as_ref().unwrap()[v]));
        let depth = read_depth(&f.dir.join(&ann.depth.as_ref().unwrap()[v]));
        for (x, y, m) in mask.enumerate_pixels() {
            let id = m.0[0] as usize;
            if id == 0 || (x + 3 * y) % 7 != 0 {
                continue;
            }
            let (o, d) = cam.back_project(Vector2::new(x as f64, y as f64)).unwrap();
            let t = ray_mesh(o, d, &meshes[id - 1], &model.faces)
                .expect("the ray hits the masked person");
            let z_cam = cam.to_camera(&(o + d * t)).z;
            let stored = depth.get_pixel(x, y).0[0] as f64 / 1000.0;
            // Depth is stored in whole millimetres.
            assert!(
                (stored - z_cam).abs() < 2e-3,
                "view {v} pixel ({x}, {y}): {stored} vs {z_cam}"
            );
            checked += 1;
        }
    }
    assert!(checked > 100, "checked {checked} pixels");
}

fn all_files(root: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

#[test]
fn same_seed_gives_byte_identical_output() {
    let dir = tempfile::tempdir().unwrap();
    let mut cfg = small_config(5);
    cfg.scenes = 2;
    cfg.frames_per_scene = 1;
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    generate(&cfg, &a, Path::new("."), &|| {}).unwrap();
    generate(&cfg, &b, Path::new("."), &|| {}).unwrap();
    let (fa, fb) = (all_files(&a), all_files(&b));
    assert_eq!(fa.len(), fb.len());
    assert!(fa.len() > 20);
    for (x, y) in fa.iter().zip(&fb) {
        assert_eq!(x.strip_prefix(&a).unwrap(), y.strip_prefix(&b).unwrap());
        assert_eq!(
            std::fs::read(x).unwrap(),
            std::fs::read(y).unwrap(),
            "{} differs",
            x.display()
        );
    }
    // A different seed gives a different dataset.
    cfg.seed = 6;
    let c = dir.path().join("c");
    generate(&cfg, &c, Path::new("."), &|| {}).unwrap();
    let ann =
        |root: &Path| std::fs::read(root.join("scene_000/frame_000000/annotation.json")).unwrap();
    assert_ne!(ann(&a), ann(&c));
}

#[test]
fn annotation_round_trip() {
    let layout = DatasetLayout::open(dataset()).unwrap();
    let f = &layout.frames()[0];
    let rig = &layout.scenes[f.scene].rig;
    let ann = Annotation::read(&f.dir.join("annotation.json"), rig.len()).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("annotation.json");
    mvmp_data::layout::write_json(&p, &ann).unwrap();
    assert_eq!(Annotation::read(&p, rig.len()).unwrap(), ann);
}

#[test]
fn loader_letterboxes_images_and_joints() {
    let ds = FrameDataset::open(dataset(), Split::All, ViewChoice::Fixed(vec![2, 0]), 112).unwrap();
    assert_eq!(ds.len(), 6);
    let s = ds.get(3).unwrap();
    assert_eq!(s.images.len(), 2 * 3 * 112 * 112);
    // 160 x 120 into 112: content 112 x 84, 14 rows of padding above and below.
    assert_eq!(
        (
            s.letterboxes[0].content_width,
            s.letterboxes[0].content_height
        ),
        (112, 84)
    );
    assert_eq!(s.images[0], 0.0);
    let p = &s.people[0];
    for (vi, (cam, lb)) in s.cameras.iter().zip(&s.letterboxes).enumerate() {
        for (ji, j3) in p.joints_3d.iter().enumerate() {
            let want = project_to_network(cam, lb, j3.map(|x| x as f64)).unwrap();
            let got = p.joints_2d[vi][ji];
            assert!((got[0] as f64 - want.x).abs() < 1e-3 && (got[1] as f64 - want.y).abs() < 1e-3);
        }
    }
    assert_eq!(s.cameras[0].name, "cam02");
    // Random views: the same epoch and index give the same choice; the batcher pads people.
    let rnd = FrameDataset::open(
        dataset(),
        Split::Train,
        ViewChoice::Random { count: 2, seed: 1 },
        56,
    )
    .unwrap();
    assert_eq!(rnd.len(), 4, "2 of 3 scenes train, 2 frames each");
    let a = rnd.get(0).unwrap();
    let b = rnd.get(0).unwrap();
    assert_eq!(a.cameras, b.cameras);
    let batch = FrameBatcher::default().batch(vec![a, rnd.get(3).unwrap()], &Device::flex());
    let p = batch.counts.iter().max().copied().unwrap();
    assert_eq!(batch.images.dims(), [2, 2, 3, 56, 56]);
    assert_eq!(batch.pelvis.dims(), [2, p, 3]);
    assert_eq!(batch.joints_2d.dims()[..3], [2, 2, p]);
    let mask: Vec<bool> = batch.mask.into_data().try_into_vec().unwrap();
    assert_eq!(
        mask.iter().filter(|m| **m).count(),
        batch.counts.iter().sum::<usize>()
    );
    let _ = Tensor::<1>::from_data(TensorData::new(vec![0f32], [1]), &Device::flex());
}

#[test]
fn splits_are_disjoint_two_to_one() {
    let layout = DatasetLayout::open(dataset()).unwrap();
    let train = split_scenes(&layout, Split::Train).unwrap();
    let test = split_scenes(&layout, Split::Test).unwrap();
    assert_eq!((train.len(), test.len()), (2, 1));
    assert!(train.iter().all(|s| !test.contains(s)));
}

fn copy_tree(from: &Path, to: &Path) {
    for f in all_files(from) {
        let rel = f.strip_prefix(from).unwrap();
        let dst = to.join(rel);
        std::fs::create_dir_all(dst.parent().unwrap()).unwrap();
        std::fs::copy(&f, &dst).unwrap();
    }
}

/// Rewrite the annotation at `path` through `edit`.
fn edit_annotation(path: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let mut a: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    edit(&mut a);
    std::fs::write(path, serde_json::to_string(&a).unwrap()).unwrap();
}

/// `data check`'s problems as "path: what" lines.
fn check_messages(root: &Path, deep: bool) -> Vec<String> {
    check_dataset(root, deep)
        .problems
        .iter()
        .map(|p| format!("{}: {}", p.path.display(), p.what))
        .collect()
}

#[test]
fn broken_datasets_give_errors_that_name_the_file() {
    let good = check_dataset(dataset(), true);
    assert!(good.problems.is_empty(), "{:?}", good.problems);
    assert_eq!((good.scenes, good.frames, good.views), (3, 6, 3));

    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("broken");
    copy_tree(dataset(), &root);
    let frame = root.join("scene_001/frame_000001");
    // A missing view image.
    std::fs::remove_file(frame.join("view_01.png")).unwrap();
    // A rig with fewer cameras than images.
    let rig_path = root.join("scene_002/cameras.json");
    let mut rig: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&rig_path).unwrap()).unwrap();
    rig["cameras"].as_array_mut().unwrap().pop();
    std::fs::write(&rig_path, serde_json::to_string(&rig).unwrap()).unwrap();
    // A wrong schema version.
    let a0 = root.join("scene_000/frame_000000/annotation.json");
    let text =
        std::fs::read_to_string(&a0)
            .unwrap()
            .replacen("\"version\": 1", "\"version\": 9", 1);
    std::fs::write(&a0, text).unwrap();
    // NaN in an annotation (not valid JSON: the reader must say where).
    let a1 = root.join("scene_000/frame_000001/annotation.json");
    let text = std::fs::read_to_string(&a1).unwrap();
    let i = text.find("\"pelvis\": [").unwrap() + "\"pelvis\": [".len();
    std::fs::write(
        &a1,
        format!(
            "{}NaN{}",
            &text[..i],
            &text[i + text[i..].find(',').unwrap()..]
        ),
    )
    .unwrap();

    let msgs = check_messages(&root, false);
    let has = |needle: &str, file: &str| {
        assert!(
            msgs.iter().any(|m| m.contains(needle) && m.contains(file)),
            "no {needle:?} for {file} in {msgs:#?}"
        )
    };
    has(
        "missing or unreadable",
        "scene_001/frame_000001/view_01.png",
    );
    has(
        "the rig has 2 cameras",
        "scene_002/frame_000000/annotation.json",
    );
    has("version", "scene_000/frame_000000/annotation.json");
    has("invalid", "scene_000/frame_000001/annotation.json");
    // The loader fails on a missing image with the same clarity.
    let root2 = dir.path().join("missing_image");
    copy_tree(dataset(), &root2);
    std::fs::remove_file(root2.join("scene_001/frame_000001/view_01.png")).unwrap();
    let ds = FrameDataset::open(&root2, Split::All, ViewChoice::Fixed(vec![0, 1]), 56).unwrap();
    let errs: Vec<String> = (0..ds.len())
        .filter_map(|i| ds.load(i).err())
        .map(|e| e.to_string())
        .collect();
    assert!(errs.iter().any(|e| e.contains("view_01.png")), "{errs:#?}");
}

/// A PNG cut short after its header passes the plain check (headers only) and fails the deep one and the
/// loader; an annotation with fewer joints than the layout holds fails both checks, naming the key.
#[test]
fn deep_checks_decode_images_and_joint_counts_are_checked() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    copy_tree(dataset(), &root);
    let png = root.join("scene_001/frame_000000/view_00.png");
    let bytes = std::fs::read(&png).unwrap();
    std::fs::write(&png, &bytes[..200]).unwrap();
    edit_annotation(&root.join("scene_002/frame_000001/annotation.json"), |a| {
        a["people"][0]["joints_3d"]
            .as_array_mut()
            .unwrap()
            .truncate(10)
    });
    let (plain, deep) = (check_messages(&root, false), check_messages(&root, true));
    let joints = |m: &Vec<String>| {
        m.iter().any(|s| {
            s.contains("scene_002/frame_000001/annotation.json")
                && s.contains("people[0].joints_3d has 10 joints")
        })
    };
    assert!(joints(&plain) && joints(&deep), "{plain:#?} {deep:#?}");
    let cut = |m: &Vec<String>| {
        m.iter()
            .any(|s| s.contains("scene_001/frame_000000/view_00.png"))
    };
    assert!(!cut(&plain), "{plain:#?}");
    assert!(cut(&deep), "{deep:#?}");
    assert_eq!(deep.len(), 2, "{deep:#?}");
    // The loader refuses both, naming each file.
    let ds = FrameDataset::open(&root, Split::All, ViewChoice::Fixed(vec![0]), 56).unwrap();
    let errs: Vec<String> = (0..ds.len())
        .filter_map(|i| ds.load(i).err())
        .map(|e| e.to_string())
        .collect();
    assert_eq!(errs.len(), 2, "{errs:#?}");
    assert!(
        errs.iter()
            .any(|e| e.contains("view_00.png") && e.contains("unreadable")),
        "{errs:#?}"
    );
    assert!(
        errs.iter()
            .any(|e| e.contains("annotation.json") && e.contains("joints_3d has 10 joints")),
        "{errs:#?}"
    );
}

/// A frame whose people hold 76 joints (a layout of a body model without face landmarks) in a dataset
/// whose body model outputs 127: the check names the file and both counts, and a loader told what its
/// body layer outputs refuses the frame instead of letting a loss or a metric index past the end.
#[test]
fn joints_of_another_body_model_are_named_by_the_check_and_the_loader() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    copy_tree(dataset(), &root);
    edit_annotation(&root.join("scene_000/frame_000001/annotation.json"), |a| {
        for p in a["people"].as_array_mut().unwrap() {
            p["joints_3d"].as_array_mut().unwrap().truncate(76);
            for v in p["views"].as_array_mut().unwrap() {
                v["joints_2d"].as_array_mut().unwrap().truncate(76);
            }
        }
    });
    let problems = check_messages(&root, false);
    assert_eq!(problems.len(), 1, "{problems:#?}");
    assert!(
        problems[0].contains("scene_000/frame_000001/annotation.json")
            && problems[0].contains("has 76 joints")
            && problems[0].contains("outputs 127"),
        "{problems:#?}"
    );
    let mut ds = FrameDataset::open(&root, Split::All, ViewChoice::Fixed(vec![0]), 56).unwrap();
    let bad = ds
        .frame_refs()
        .iter()
        .position(|f| f.dir.ends_with("scene_000/frame_000001"))
        .unwrap();
    assert!(ds.load(bad).is_ok(), "a layout the data format allows");
    ds.expect_joints(127, "standin:0");
    let e = ds.load(bad).unwrap_err().to_string();
    assert!(
        e.contains("frame_000001/annotation.json") && e.contains("76 joints") && e.contains("127"),
        "{e}"
    );
    assert!(ds.load(if bad == 0 { 1 } else { 0 }).is_ok());
}

/// An annotation with three problems in two people: the check lists each, naming the key and value; a
/// loader stops at the first.
#[test]
fn the_check_lists_every_problem_of_an_annotation() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("ds");
    copy_tree(dataset(), &root);
    let ann = root.join("scene_001/frame_000000/annotation.json");
    edit_annotation(&ann, |a| {
        let people = a["people"].as_array_mut().unwrap();
        for i in [0, 2] {
            let v = &mut people[i]["views"][1];
            v["visible_pixels"] = serde_json::json!(v["silhouette_pixels"].as_u64().unwrap() + 7);
        }
        people[2]["views"][0]["joints_2d"]
            .as_array_mut()
            .unwrap()
            .truncate(5);
    });
    let problems = check_messages(&root, false);
    assert_eq!(problems.len(), 3, "{problems:#?}");
    let at = |key: &str| {
        problems
            .iter()
            .any(|p| p.contains("scene_001/frame_000000/annotation.json") && p.contains(key))
    };
    assert!(at("people[0].views[1]: visible_pixels"), "{problems:#?}");
    assert!(
        at("people[2].views[0].joints_2d has 5 joints"),
        "{problems:#?}"
    );
    assert!(at("people[2].views[1]: visible_pixels"), "{problems:#?}");
    let e = Annotation::read(&ann, 3).unwrap_err().to_string();
    assert!(e.contains("people[0].views[1]: visible_pixels"), "{e}");
}

#[test]
fn batches_with_vertices_load_in_several_workers() {
    use burn::data::dataloader::DataLoaderBuilder;
    let ds = FrameDataset::open(
        dataset(),
        Split::All,
        ViewChoice::Random { count: 2, seed: 3 },
        56,
    )
    .unwrap();
    let layout = DatasetLayout::open(dataset()).unwrap();
    let batcher = FrameBatcher::with_vertices(layout.body_model().unwrap());
    let loader = DataLoaderBuilder::new(batcher)
        .batch_size(2)
        .shuffle(7)
        .num_workers(2)
        .set_device(Device::flex())
        .build(ds);
    let mut frames = 0;
    for batch in loader.iter() {
        let batch = batch.unwrap();
        frames += batch.counts.len();
        let v = batch.vertices.expect("vertices were asked for");
        let p = batch.counts.iter().max().copied().unwrap();
        assert_eq!(v.dims(), [batch.counts.len(), p, 10475, 3]);
        // The posed ground truth agrees with the annotated joints: the pelvis of the mesh's regressed
        // joints is the annotated pelvis (checked through the lowest vertex touching the ground).
        let vv: Vec<f32> = v.into_data().try_into_vec().unwrap();
        let zmin = vv[..10475 * 3]
            .iter()
            .skip(2)
            .step_by(3)
            .cloned()
            .fold(f32::MAX, f32::min);
        assert!(
            zmin.abs() < 1e-3,
            "feet on the ground: lowest vertex at z = {zmin}"
        );
    }
    assert_eq!(frames, 6);
}

#[test]
fn shipped_synth_configs_validate() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/synth");
    let tiny = SynthConfig::read(&dir.join("tiny.toml")).unwrap();
    assert_eq!((tiny.cameras.count, tiny.image_size), (4, [256, 256]));
    let paper = SynthConfig::read(&dir.join("paper.toml")).unwrap();
    assert_eq!(
        (paper.scenes, paper.people, paper.area),
        (15, [10, 30], [30.0, 30.0])
    );
    assert_eq!((paper.cameras.count, paper.image_size), (50, [1920, 1080]));
    // Unknown keys are errors that name the key.
    let bad = std::env::temp_dir().join(format!("mvmp-bad-synth-{}.toml", std::process::id()));
    std::fs::write(&bad, "scenes = 2\nviews = 4\n").unwrap();
    let e = SynthConfig::read(&bad).unwrap_err().to_string();
    std::fs::remove_file(&bad).ok();
    assert!(e.contains("views"), "{e}");
}

#[test]
fn a_batcher_given_the_layer_poses_the_same_meshes() {
    let ds = FrameDataset::open(dataset(), Split::All, ViewChoice::Fixed(vec![0]), 56).unwrap();
    let layout = DatasetLayout::open(dataset()).unwrap();
    let body = layout.body_model().unwrap();
    let device = Device::flex();
    let layer = mvmp_smplx::SmplxLayer::new(&body, &device);
    let own = FrameBatcher::with_vertices(body.clone());
    let shared = FrameBatcher::with_layer(std::sync::Arc::new(body), layer);
    let vertices = |b: &FrameBatcher| -> Vec<f32> {
        let batch = b.batch(vec![ds.load(0).unwrap()], &device);
        batch.vertices.unwrap().into_data().try_into_vec().unwrap()
    };
    assert_eq!(vertices(&own), vertices(&shared));
}

#[test]
fn body_model_references_are_the_same_model_only_when_they_name_it() {
    use mvmp_data::layout::same_body_model;
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("a"), dir.path().join("a/b"));
    std::fs::create_dir_all(&b).unwrap();
    std::fs::write(a.join("model.npz"), b"x").unwrap();
    std::fs::write(b.join("other.npz"), b"x").unwrap();
    assert!(same_body_model("standin:0", &a, "standin:0", &b));
    assert!(!same_body_model("standin:0", &a, "standin:1", &a));
    assert!(!same_body_model("standin:0", &a, "model.npz", &a));
    // One file named from two bases.
    assert!(same_body_model("model.npz", &a, "../model.npz", &b));
    assert!(!same_body_model("model.npz", &a, "other.npz", &b));
    // A file that is not there is no model at all.
    assert!(!same_body_model("missing.npz", &a, "missing.npz", &a));
}

/// Every frame's people are read without its images: a tree whose images are all gone still gives each
/// scene's people and image paths, while the frame dataset, which letterboxes the images, names the
/// first one missing.
#[test]
fn ground_truth_is_read_without_images() {
    use mvmp_data::sequence::{FramePeople, open_mvmp};
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("no_images");
    copy_tree(dataset(), &root);
    let mut removed = 0;
    for f in DatasetLayout::open(&root).unwrap().frames() {
        for e in std::fs::read_dir(&f.dir).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "png") {
                std::fs::remove_file(p).unwrap();
                removed += 1;
            }
        }
    }
    assert!(removed > 0);
    let layout = DatasetLayout::open(dataset()).unwrap();
    let seqs = open_mvmp(&root, Split::All).unwrap();
    assert_eq!(seqs.len(), layout.scenes.len());
    for (seq, scene) in seqs.iter().zip(&layout.scenes) {
        assert_eq!(seq.name(), scene.name);
        assert_eq!(seq.len(), scene.index.frames.len());
        for i in 0..seq.len() {
            let frame = seq.frame(i).unwrap();
            let ann = Annotation::read(
                &scene
                    .dir
                    .join(&scene.index.frames[i])
                    .join("annotation.json"),
                scene.rig.len(),
            )
            .unwrap();
            let FramePeople::Smplx(people) = &frame.people else {
                panic!("an MVMP-HMR frame holds SMPL-X people")
            };
            assert_eq!(people.len(), ann.people.len());
            assert_eq!(frame.images.len(), scene.rig.len());
            assert!(frame.images.iter().all(|p| !p.exists()));
        }
    }
    let ds = FrameDataset::open(&root, Split::All, ViewChoice::Fixed(vec![0]), 56).unwrap();
    let err = ds.load(0).unwrap_err().to_string();
    assert!(err.contains(".png"), "{err}");
}
