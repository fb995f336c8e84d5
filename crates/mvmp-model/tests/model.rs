//! The assembled model: every shipped config validates; forward shapes with detected and given roots;
//! a loss on the outputs reaches every trainable parameter.
use std::path::Path;
use std::sync::Arc;

use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Bool, Device, Tensor, TensorData};
use mvmp_geom::{Camera, Letterbox, VoxelGrid};
use mvmp_model::{ModelConfig, RigGrids};
use mvmp_smplx::standin_model;
use nalgebra::{Matrix3, Vector3};

fn configs_dir() -> std::path::PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../configs/model")
}

#[test]
fn every_shipped_config_validates() {
    let mut n = 0;
    for dir in [configs_dir(), configs_dir().join("ablations")] {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_some_and(|x| x == "toml") {
                ModelConfig::read(&p).unwrap_or_else(|e| panic!("{}: {e}", p.display()));
                n += 1;
            }
        }
    }
    assert!(n >= 8, "{n} configs");
    let mut bad = ModelConfig::default();
    bad.grid.shape = [30, 30, 6];
    assert!(
        bad.validate()
            .unwrap_err()
            .to_string()
            .contains("grid.shape")
    );
}

fn small_config() -> ModelConfig {
    let mut c = ModelConfig::read(&configs_dir().join("tiny.toml")).unwrap();
    c.image_size = 64;
    c.grid = VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [16, 16, 4]).unwrap();
    c.max_people = 3;
    c.decoder.dim = 32;
    c.rootnet_width = 0.25;
    c
}

fn rig() -> Vec<Camera> {
    (0..2)
        .map(|i| {
            let a = i as f64 * 1.7;
            let pos = Vector3::new(6.0 * a.cos(), 6.0 * a.sin(), 2.5);
            let z = (Vector3::new(0.0, 0.0, 1.0) - pos).normalize();
            let x = z.cross(&Vector3::z()).normalize();
            let y = z.cross(&x);
            let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
            let k = Matrix3::new(120.0, 0.0, 79.5, 0.0, 120.0, 59.5, 0.0, 0.0, 1.0);
            Camera::new(format!("{i}"), k, r, -(r * pos), [0.0; 5], 160, 120).unwrap()
        })
        .collect()
}

/// The sampling grids of [`rig`] for 64 px inputs, one batch item.
fn grids_on(cfg: &ModelConfig, d: &Device) -> Vec<RigGrids> {
    let cams = rig();
    let lbs: Vec<Letterbox> = cams
        .iter()
        .map(|c| Letterbox::new(c.width, c.height, 64).unwrap())
        .collect();
    vec![RigGrids::new(cfg, &cams, &lbs, d)]
}

fn images(d: &Device) -> Tensor<5> {
    let v: Vec<f32> = (0..2 * 3 * 64 * 64)
        .map(|i| ((i * 31) % 97) as f32 / 97.0 - 0.5)
        .collect();
    Tensor::from_data(TensorData::new(v, [1, 2, 3, 64, 64]), d)
}

#[test]
fn forward_shapes_with_detected_and_given_roots() {
    for fusion in [
        mvmp_fusion::FusionMode::Mean,
        mvmp_fusion::FusionMode::Max,
        mvmp_fusion::FusionMode::Deformable,
    ] {
        let mut cfg = small_config();
        cfg.fusion = fusion;
        forward_shapes(cfg);
    }
}

fn forward_shapes(cfg: ModelConfig) {
    let d = Device::flex();
    let net = cfg.init(&d).with_body(Arc::new(standin_model(0)));
    let grids = grids_on(&cfg, &d);
    let out = net.forward(images(&d), &grids, None);
    assert_eq!(out.heatmaps.dims(), [1, 2, 17, 16, 16]);
    assert_eq!(out.likelihood.dims(), [1, 1, 16, 16, 4]);
    assert_eq!(out.vertices.dims(), [1, 3, 10475, 3]);
    assert_eq!(out.joints.dims(), [1, 3, 127, 3]);
    assert_eq!(out.detections.len(), 1);
    let roots = Tensor::<3>::from_data(
        TensorData::new(vec![0.5f32, 0.2, 0.9, -1.0, 1.0, 1.0], [1, 2, 3]),
        &d,
    );
    let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true, false], [1, 2]), &d);
    let out = net.forward(images(&d), &grids, Some((roots, present)));
    assert_eq!(out.rotmats.dims(), [1, 2, 53, 3, 3]);
    assert_eq!(out.transl.dims(), [1, 2, 3]);
}

/// `zero_volume` hands the decoder the volume a silent feature reduction (zero weights and bias) makes:
/// zeros; without it the decoder's output depends on the features.
#[test]
fn zero_volume_hands_the_decoder_a_zero_feature_volume() {
    let d = Device::flex();
    let cfg = small_config();
    let net = cfg.init(&d).with_body(Arc::new(standin_model(0)));
    let grids = grids_on(&cfg, &d);
    let rot6d = |n: &mvmp_model::MvmpHmr| {
        let roots = Tensor::<3>::from_data(
            TensorData::new(vec![0.5f32, 0.2, 0.9, -1.0, 1.0, 1.0], [1, 2, 3]),
            &d,
        );
        let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true, true], [1, 2]), &d);
        let out = n.forward(images(&d), &grids, Some((roots, present)));
        out.rot6d.into_data().try_to_vec::<f32>().unwrap()
    };
    let plain = rot6d(&net);
    let mut zeroed = net.clone();
    zeroed.zero_volume = true;
    let ablated = rot6d(&zeroed);
    let mut silent = net.clone();
    silent.reduce.weight = silent.reduce.weight.map(|w| w.zeros_like());
    silent.reduce.bias = silent.reduce.bias.map(|b| b.map(|b| b.zeros_like()));
    let reference = rot6d(&silent);
    let gap = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
    };
    assert!(
        gap(&ablated, &reference) < 1e-6,
        "{}",
        gap(&ablated, &reference)
    );
    assert!(gap(&plain, &ablated) > 1e-4, "{}", gap(&plain, &ablated));
}

/// A `vit_heatmaps` head maps the reduced ViT features to one map per heatmap joint at the patch grid,
/// in training; inference does not run it.
#[test]
fn a_vit_heatmap_head_runs_in_training_only() {
    let mut cfg = small_config();
    cfg.vit_heatmaps = true;
    cfg.validate().unwrap();
    let body = Arc::new(standin_model(0));
    let forward = |d: &Device| {
        let net = cfg.init(d).with_body(body.clone());
        let roots = Tensor::<3>::from_data(TensorData::new(vec![0.5f32, 0.2, 0.9], [1, 1, 3]), d);
        let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true], [1, 1]), d);
        net.forward(images(d), &grids_on(&cfg, d), Some((roots, present)))
    };
    let maps = forward(&Device::flex().autodiff()).vit_heatmaps.unwrap();
    let side = cfg.image_size as usize / mvmp_backbone::vit::PATCH;
    let [b, v, j, h, w] = maps.dims();
    assert_eq!([b, j, h, w], [1, cfg.heatmap_joints.len(), side, side]);
    assert_eq!(v, images(&Device::flex()).dims()[1]);
    assert!(forward(&Device::flex()).vit_heatmaps.is_none());
}

#[test]
fn a_loss_reaches_every_trainable_parameter() {
    let d = Device::flex().autodiff();
    let cfg = small_config();
    let net = cfg.init(&d).with_body(Arc::new(standin_model(0)));
    let grids = grids_on(&cfg, &d);
    let roots = Tensor::<3>::from_data(
        TensorData::new(vec![0.5f32, 0.2, 0.9, -1.0, 1.0, 1.0], [1, 2, 3]),
        &d,
    );
    let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true, true], [1, 2]), &d);
    let out = net.forward(images(&d), &grids, Some((roots, present)));
    let facing = out.facing.expect("tiny.toml has a facing head");
    let loss = out.likelihood.powi_scalar(2).sum() * 1e3
        + facing.powi_scalar(2).sum()
        + out.offset.abs().sum()
        + out.heatmaps.powi_scalar(2).sum()
        + out.vertices.abs().mean()
        + out.betas.abs().sum()
        + out.expression.abs().sum();
    let grads = loss.backward();
    struct Check<'a>(&'a burn::tensor::Gradients, Vec<Vec<usize>>, usize);
    impl ModuleVisitor for Check<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            if !p.is_require_grad() {
                return;
            }
            self.2 += 1;
            let ok = p
                .val()
                .grad(self.0)
                .is_some_and(|g| g.abs().sum().into_scalar::<f32>() > 0.0);
            if !ok {
                self.1.push(p.val().dims().to_vec());
            }
        }
    }
    let mut c = Check(&grads, Vec::new(), 0);
    net.visit(&mut c);
    assert!(c.2 > 150, "{} parameters", c.2);
    assert!(
        c.1.is_empty(),
        "{} of {} parameters without gradient: {:?}",
        c.1.len(),
        c.2,
        c.1
    );
}

#[test]
fn every_shipped_config_builds_and_summarises() {
    // Building every configuration (paper scale included) checks that all module shapes fit together;
    // the summary reports the main tensors of a forward at that configuration.
    let d = Device::flex().autodiff();
    for dir in [configs_dir(), configs_dir().join("ablations")] {
        for e in std::fs::read_dir(&dir).unwrap() {
            let p = e.unwrap().path();
            if p.extension().is_none_or(|x| x != "toml") {
                continue;
            }
            let cfg = ModelConfig::read(&p).unwrap();
            let s = mvmp_model::summary::summarize(&cfg, 5, &d);
            let params: usize = s.rows.iter().map(|r| r.params).sum();
            assert!(params > 1_000_000, "{}: {params} parameters", p.display());
            let fused = s
                .activations
                .iter()
                .find(|(n, _)| n.starts_with("fused volume"))
                .unwrap()
                .1;
            assert_eq!(
                fused,
                cfg.feature_channels * cfg.grid.num_voxels() * 4,
                "{}",
                p.display()
            );
        }
    }
}

/// The per-view features are the 1x1 `reduce` convolution of the ViT's feature map, computed as a matrix
/// product on the tokens: both ways agree (float32 summation order only).
#[test]
fn view_features_equal_the_reduce_convolution() {
    let d = Device::default();
    let net = small_config().init(&d);
    let x = images(&d).reshape([2, 3, 64, 64]);
    let conv: Vec<f32> = net
        .reduce
        .forward(net.vit.forward(x.clone()))
        .into_data()
        .try_to_vec::<f32>()
        .unwrap();
    let feats = net.view_features(x);
    assert_eq!(feats.dims()[0], 2);
    let mm: Vec<f32> = feats.into_data().try_to_vec::<f32>().unwrap();
    assert_eq!(conv.len(), mm.len());
    let scale = conv.iter().fold(0f32, |m, x| m.max(x.abs()));
    let diff = conv
        .iter()
        .zip(&mm)
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(scale > 1e-3, "features are not all zero");
    assert!(
        diff <= 1e-5 * scale,
        "largest difference {diff} (scale {scale})"
    );
}

/// An edit of a config that makes it invalid.
type Edit = fn(&mut ModelConfig);

#[test]
fn unusable_people_caps_thresholds_and_lattices_name_the_key() {
    let cases: [(&str, Edit); 14] = [
        ("max_people", |c| c.max_people = 100_000_000),
        ("max_people", |c| c.max_people = 0),
        ("root_threshold", |c| c.root_threshold = f32::NAN),
        ("root_threshold", |c| c.root_threshold = f32::INFINITY),
        ("root_threshold", |c| c.root_threshold = 1.5),
        ("decoder.query_lattice", |c| {
            c.decoder.query_lattice = [3, 0, 8]
        }),
        ("decoder.query_lattice", |c| {
            c.decoder.query_lattice = [usize::MAX, 2, 1]
        }),
        ("decoder.query_span", |c| {
            c.decoder.query_span = [1.0, f64::NAN, 1.0]
        }),
        ("decoder.query_span", |c| {
            c.decoder.query_span = [-1.0, 1.0, 1.0]
        }),
        // A lattice to turn, but no facing head to turn it with (the default config has none).
        ("decoder.heading_lattice", |c| {
            c.decoder.query_lattice = [3, 3, 8];
            c.decoder.heading_lattice = true;
        }),
        // A facing head, but one point: nothing to turn.
        ("decoder.heading_lattice", |c| {
            c.facing = true;
            c.decoder.heading_lattice = true;
        }),
        // How the joint volume is read, without reading it.
        ("decoder.joint_samples", |c| c.decoder.joint_samples = true),
        // A read of the joint samples, without them.
        ("decoder.pose_read", |c| {
            c.decoder.query_joints = true;
            c.decoder.pose_read = true;
        }),
        // Offsets in a heading frame, without a facing head to give it.
        ("decoder.joint_offsets", |c| {
            c.decoder.query_joints = true;
            c.decoder.joint_samples = true;
            c.decoder.joint_offsets = true;
        }),
    ];
    for (key, edit) in cases {
        let mut c = ModelConfig::default();
        edit(&mut c);
        let e = c.validate().expect_err(key).to_string();
        assert!(e.contains(key), "{e}");
    }
    let c = ModelConfig {
        max_people: mvmp_model::config::MAX_PEOPLE,
        ..Default::default()
    };
    c.validate().unwrap();
    // The joint samples alone are a lattice to turn.
    let mut c = ModelConfig {
        facing: true,
        ..Default::default()
    };
    c.decoder.query_joints = true;
    c.decoder.joint_samples = true;
    c.decoder.heading_lattice = true;
    c.decoder.pose_read = true;
    c.validate().unwrap();
}

/// A relative body-model path names a file beside the config that names it, wherever the config is read
/// from later (a run keeps a copy of it in its own directory); `standin:SEED` and absolute paths stay.
#[test]
fn a_relative_body_model_path_is_relative_to_its_config() {
    let dir = tempfile::tempdir().unwrap();
    let base = std::fs::read_to_string(configs_dir().join("tiny.toml")).unwrap();
    let read = |body: &str| {
        let text = base.replace(
            "body_model = \"standin:0\"",
            &format!("body_model = {body:?}"),
        );
        assert!(text.contains(body));
        let p = dir.path().join("m.toml");
        std::fs::write(&p, text).unwrap();
        ModelConfig::read(&p).unwrap().body_model
    };
    let abs = std::path::absolute(dir.path()).unwrap();
    assert_eq!(
        read("models/SMPLX_NEUTRAL.npz"),
        abs.join("models/SMPLX_NEUTRAL.npz").to_string_lossy()
    );
    assert_eq!(read("standin:3"), "standin:3");
    assert_eq!(
        read("/opt/smplx/SMPLX_MALE.npz"),
        "/opt/smplx/SMPLX_MALE.npz"
    );
}

#[test]
fn relative_heading_by_hand() {
    use mvmp_model::facing::relative_heading;
    // The camera due +x of the person: facing it is (1, 0); facing +y is a quarter turn anticlockwise
    // from it, (0, 1); facing -x is (-1, 0).
    let (at, cam) = ([1.0, 2.0, 0.9], [5.0, 2.0, 2.5]);
    for (heading, want) in [
        ([1.0, 0.0], [1.0, 0.0]),
        ([0.0, 1.0], [0.0, 1.0]),
        ([-1.0, 0.0], [-1.0, 0.0]),
    ] {
        let got = relative_heading(heading, at, cam).unwrap();
        for a in 0..2 {
            assert!((got[a] - want[a]).abs() < 1e-6, "{heading:?}: {got:?}");
        }
    }
    assert_eq!(relative_heading([1.0, 0.0], at, [1.0, 2.0, 4.0]), None);
}

#[test]
fn facing_readout_turns_each_views_relative_heading_into_the_world() {
    use mvmp_model::facing::{facing_readout, relative_heading};
    let d = Device::flex();
    let cfg = small_config();
    let cams = rig();
    let lbs: Vec<Letterbox> = cams
        .iter()
        .map(|c| Letterbox::new(c.width, c.height, 64).unwrap())
        .collect();
    let grids = RigGrids::new(&cfg, &cams, &lbs, &d);
    let [h, w] = grids.heatmaps.map_hw;
    let root = [0.3, -0.4, 0.9];
    let turn = 2.2f64;
    let heading = [turn.cos(), turn.sin()];
    // Each view's maps hold, everywhere, the heading relative to that camera, shortened (as an unsure
    // head's are) by a different factor per view: every view then reads the same world direction,
    // whatever pixel the root falls on, and the readout is that direction at unit length.
    let mut maps = Vec::new();
    for (cam, scale) in cams.iter().zip([0.4, 0.7]) {
        let rel = relative_heading(heading, root, cam.centre().into()).unwrap();
        for r in rel {
            maps.extend(std::iter::repeat_n(r * scale, h * w));
        }
    }
    let facing = Tensor::<5>::from_data(TensorData::new(maps, [1, 2, 2, h, w]), &d);
    let roots = Tensor::<3>::from_data(
        TensorData::new(root.iter().map(|&x| x as f32).collect(), [1, 1, 3]),
        &d,
    );
    let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true], [1, 1]), &d);
    let got: Vec<f32> = facing_readout(
        facing,
        std::slice::from_ref(&grids),
        &cfg.grid,
        roots,
        present,
    )
    .into_data()
    .try_into_vec()
    .unwrap();
    for a in 0..2 {
        assert!(
            (got[a] as f64 - heading[a]).abs() < 1e-5,
            "{got:?} vs {heading:?}"
        );
    }
}

#[test]
fn turn_to_heading_makes_the_upright_default_face_the_heading() {
    use mvmp_model::facing::turn_to_heading;
    let d = Device::flex();
    let j = mvmp_smplx::names::NUM_REGRESSED;
    // Joint 0: the upright default (+90 degrees about x); joint 1: some other rotation, to stay as it is.
    let up = [1.0f32, 0., 0., 0., 0., -1., 0., 1., 0.];
    let other = [0.0f32, -1., 0., 1., 0., 0., 0., 0., 1.];
    let mut m = Vec::new();
    for _ in 0..2 {
        m.extend(up);
        for _ in 1..j {
            m.extend(other);
        }
    }
    let rotmats = Tensor::<4>::from_data(TensorData::new(m, [2, j, 3, 3]), &d);
    let headings = [[0.6f32, 0.8], [0.0, -1.0]];
    let h = Tensor::<2>::from_data(TensorData::new(headings.concat(), [2, 2]), &d);
    let out: Vec<f32> = turn_to_heading(rotmats, h)
        .into_data()
        .try_into_vec()
        .unwrap();
    for (n, want) in headings.iter().enumerate() {
        let g = &out[n * j * 9..n * j * 9 + 9];
        // Where the global orientation sends the body's forward axis (+z): its third column.
        let ahead = [g[2], g[5], g[8]];
        for (a, w) in [want[0], want[1], 0.0].iter().enumerate() {
            assert!((ahead[a] - w).abs() < 1e-6, "{n}: {ahead:?} vs {want:?}");
        }
        // Still upright: the body's up axis (+y, second column) is the world's +z.
        assert!((g[7] - 1.0).abs() < 1e-6, "{n}: {g:?}");
        assert_eq!(
            &out[n * j * 9 + 9..n * j * 9 + 18],
            &other,
            "joint 1 unchanged"
        );
    }
}

/// With `hrnet_downsample = 2` HRNet and the facing head read the input average-pooled 2 x 2: the
/// heatmaps are S/8 on a side, equal to HRNet's maps of the pooled images, and the heatmap grid samples
/// them at 8 network pixels per map pixel.
#[test]
fn a_downsampled_hrnet_reads_the_pooled_input() {
    let mut cfg = small_config();
    cfg.facing = true;
    cfg.hrnet_downsample = 2;
    cfg.validate().unwrap();
    let d = Device::flex();
    let net = cfg.init(&d);
    let grids = grids_on(&cfg, &d);
    assert_eq!(grids[0].heatmaps.map_hw, [8, 8]);
    assert_eq!(grids[0].heatmaps.stride, 8.0);
    let det = net.detect(images(&d), &grids);
    assert_eq!(det.heatmaps.dims(), [1, 2, 17, 8, 8]);
    assert_eq!(det.facing.unwrap().dims(), [1, 2, 2, 8, 8]);
    // By hand: each 2 x 2 block's mean, then HRNet.
    let x: Vec<f32> = images(&d).into_data().try_into_vec().unwrap();
    let pooled: Vec<f32> = (0..2 * 3 * 32 * 32)
        .map(|i| {
            let (plane, y, xx) = (i / 1024, i / 32 % 32, i % 32);
            let at = |dy: usize, dx: usize| x[plane * 4096 + (2 * y + dy) * 64 + 2 * xx + dx];
            (at(0, 0) + at(0, 1) + at(1, 0) + at(1, 1)) / 4.0
        })
        .collect();
    let pooled = Tensor::<4>::from_data(TensorData::new(pooled, [2, 3, 32, 32]), &d);
    let want = net
        .hrnet
        .final_layer
        .forward(net.hrnet.features(pooled))
        .reshape([1, 2, 17, 8, 8]);
    let diff = (det.heatmaps - want).abs().max().into_scalar::<f32>();
    assert!(diff < 1e-5, "{diff}");
    let mut bad = small_config();
    bad.hrnet_downsample = 3;
    let e = bad.validate().unwrap_err().to_string();
    assert!(e.contains("hrnet_downsample"), "{e}");
}

#[test]
fn chest_view_weights_drop_the_views_another_person_stands_in() {
    use mvmp_model::facing::chest_view_weights;
    // Camera 0 looks along +y at the chest of the person at the origin (root height 1.0, chest 1.3);
    // camera 1 along -x. The second root is that of the other person.
    let cams = [[0.0, -5.0, 1.3], [5.0, 0.0, 1.3]];
    let weights = |other: [f32; 3], present: bool| {
        let roots = [0.0, 0.0, 1.0, other[0], other[1], other[2]];
        let w = chest_view_weights(&cams, &roots, &[true, present]);
        // Row-major [view, person]: the first person's weight in each view.
        [w[0], w[2]]
    };
    // Right in the line of camera 0, between it and the chest: hidden there, seen by camera 1.
    assert_eq!(weights([0.0, -2.0, 1.0], true), [0.0, 1.0]);
    // 0.2 m off the line: halfway along the ramp from 0.3 m (seen) to 0.1 m (hidden).
    let w = weights([0.2, -2.0, 1.0], true);
    assert!((w[0] - 0.5).abs() < 1e-6 && w[1] == 1.0, "{w:?}");
    // Behind the chest, a metre aside, above the line's reach, or not a person: seen by both.
    for other in [[0.0, 2.0, 1.0], [1.0, -2.0, 1.0], [0.0, -2.0, 3.5]] {
        assert_eq!(weights(other, true), [1.0, 1.0], "{other:?}");
    }
    assert_eq!(weights([0.0, -2.0, 1.0], false), [1.0, 1.0]);
    // Hidden from the only camera: that view is all there is.
    let w = chest_view_weights(&cams[..1], &[0.0, 0.0, 1.0, 0.0, -2.0, 1.0], &[true, true]);
    assert_eq!(w, vec![1.0, 1.0]);
}

/// The facing head's flip test makes its heading maps mirror-equivariant: the maps of a view mirrored
/// left to right, mirrored back with the sine negated, are the view's own (exactly, as the mean of a map
/// and its mirror image is), for regressed maps and for heading bins; the plain head's are not, and in
/// training (autodiff) the maps are the plain ones.
#[test]
fn the_facing_flip_test_makes_the_heading_maps_mirror_equivariant() {
    use mvmp_model::facing::heading_vectors;
    for bins in [0, 8] {
        let mut cfg = small_config();
        cfg.facing = true;
        cfg.facing_bins = bins;
        cfg.facing_flip = true;
        cfg.validate().unwrap();
        let d = Device::flex();
        let net = cfg.init(&d);
        let mut plain_net = net.clone();
        plain_net.config.facing_flip = false;
        let grids = grids_on(&cfg, &d);
        let sign = Tensor::<1>::from_data(TensorData::new(vec![1.0f32, -1.0], [2]), &d);
        // The largest difference between a view's heading maps and its mirror image's read back.
        let asymmetry = |net: &mvmp_model::MvmpHmr| {
            let vectors = |x: Tensor<5>| heading_vectors(net.detect(x, &grids).facing.unwrap());
            let plain = vectors(images(&d));
            let mirrored =
                vectors(images(&d).flip([4])).flip([4]) * sign.clone().reshape([1, 1, 2, 1, 1]);
            (plain - mirrored).abs().max().into_scalar::<f32>()
        };
        let (flipped, plain) = (asymmetry(&net), asymmetry(&plain_net));
        assert!(flipped < 1e-5, "bins {bins}: {flipped}");
        assert!(plain > 1e-3, "bins {bins}: {plain}");
        // Training reads each view once.
        let a = Device::flex().autodiff();
        let train = cfg.init(&a);
        let mut train_plain = train.clone();
        train_plain.config.facing_flip = false;
        let train_grids = grids_on(&cfg, &a);
        let facing = |n: &mvmp_model::MvmpHmr| n.detect(images(&a), &train_grids).facing.unwrap();
        let diff = (facing(&train) - facing(&train_plain))
            .abs()
            .max()
            .into_scalar::<f32>();
        assert_eq!(diff, 0.0, "bins {bins}");
    }
    let mut bad = small_config();
    bad.facing = false;
    bad.facing_flip = true;
    let e = bad.validate().unwrap_err().to_string();
    assert!(e.contains("facing_flip"), "{e}");
}

#[test]
fn heading_bins_read_as_directions_and_label_as_von_mises() {
    use mvmp_model::facing::{bin_angle, bin_labels, heading_vectors};
    let d = Device::flex();
    let n = 8;
    // Logits far above the rest at bin 3 of 8 read as that bin's direction (135 degrees); equal logits
    // in two opposite bins as nothing (the head torn between front and back).
    let mut logits = vec![0.0f32; n * 2];
    logits[3 * 2] = 40.0;
    logits[2 * 2 + 1] = 40.0;
    logits[6 * 2 + 1] = 40.0;
    let maps = Tensor::<5>::from_data(TensorData::new(logits, [1, 1, n, 1, 2]), &d);
    let v: Vec<f32> = heading_vectors(maps).into_data().try_into_vec().unwrap();
    let a = bin_angle(3, n);
    // Channel-major [2, 1, 2]: (cos at pixel 0, cos at pixel 1, sin at pixel 0, sin at pixel 1).
    assert!(
        (v[0] as f64 - a.cos()).abs() < 1e-5 && (v[2] as f64 - a.sin()).abs() < 1e-5,
        "{v:?}"
    );
    assert!(v[1].abs() < 1e-5 && v[3].abs() < 1e-5, "{v:?}");
    // Two channels are already (cosine, sine).
    let two = Tensor::<5>::from_data(TensorData::new(vec![0.3f32, -0.4], [1, 1, 2, 1, 1]), &d);
    let same: Vec<f32> = heading_vectors(two).into_data().try_into_vec().unwrap();
    assert_eq!(same, vec![0.3, -0.4]);
    // The label of a heading 10 degrees past bin 2: softmax of kappa cos(theta - theta_k), kappa =
    // (8 / 2 pi)^2, by hand; it sums to 1 and peaks at bin 2.
    let theta = bin_angle(2, n) + 10f64.to_radians();
    let target = Tensor::<5>::from_data(
        TensorData::new(
            vec![theta.cos() as f32, theta.sin() as f32],
            [1, 1, 2, 1, 1],
        ),
        &d,
    );
    let got: Vec<f32> = bin_labels(target, n).into_data().try_into_vec().unwrap();
    let kappa = (n as f64 / std::f64::consts::TAU).powi(2);
    let e: Vec<f64> = (0..n)
        .map(|k| (kappa * (theta - bin_angle(k, n)).cos()).exp())
        .collect();
    let z: f64 = e.iter().sum();
    for k in 0..n {
        assert!((got[k] as f64 - e[k] / z).abs() < 1e-6, "{k}: {got:?}");
    }
    assert!((got.iter().sum::<f32>() - 1.0).abs() < 1e-5);
    assert!((0..n).all(|k| got[k] <= got[2]));
}

/// With `decoder.joint_offsets`, outside training the body's bones are swung onto the corrected joints:
/// every bone from a body joint to its child (the spine's top to the neck) points along the offsets the
/// output holds, though the correction (set here through the read's bias) moves them well away from the
/// decoder's own rotations.
#[test]
fn joint_offsets_swing_the_body_onto_the_corrected_joints_outside_training() {
    let d = Device::flex();
    let mut cfg = small_config();
    cfg.decoder.joint_offsets = true;
    cfg.validate().unwrap();
    let mut net = cfg.init(&d).with_body(Arc::new(standin_model(0)));
    let read = net
        .decoder
        .offsets_read
        .as_mut()
        .expect("a read of the samples");
    let n = read.weight.dims()[0] as f32;
    let bias: Vec<f32> = (0..63)
        .map(|i| 0.15 * ((i * 7 % 11) as f32 / 10.0 - 0.5) * n.sqrt())
        .collect();
    read.bias = Some(Param::from_tensor(Tensor::from_data(
        TensorData::new(bias, [63]),
        &d,
    )));
    let grids = grids_on(&cfg, &d);
    let roots = Tensor::<3>::from_data(
        TensorData::new(vec![0.5f32, 0.2, 0.9, -1.0, 1.0, 1.0], [1, 2, 3]),
        &d,
    );
    let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true, true], [1, 2]), &d);
    let run = |net: &mvmp_model::MvmpHmr| {
        net.forward(images(&d), &grids, Some((roots.clone(), present.clone())))
    };
    let out = run(&net);
    // Without the bias the swing has next to nothing to do: the rotations differ by far more with it.
    let mut plain = net.clone();
    plain.decoder.offsets_read.as_mut().unwrap().bias = None;
    let rot =
        |o: &mvmp_model::MvmpOutput| o.rotmats.clone().into_data().try_to_vec::<f32>().unwrap();
    let moved = (rot(&out).iter().zip(rot(&run(&plain))))
        .map(|(a, b)| (a - b).abs())
        .fold(0f32, f32::max);
    assert!(moved > 0.05, "{moved}");
    let offsets: Vec<f32> = out
        .joint_offsets
        .expect("offsets")
        .into_data()
        .try_to_vec()
        .unwrap();
    let joints: Vec<f32> = out.joints.into_data().try_to_vec().unwrap();
    let bones = [
        (1, 4),
        (2, 5),
        (3, 6),
        (4, 7),
        (5, 8),
        (6, 9),
        (7, 10),
        (8, 11),
        (9, 12),
        (12, 15),
        (13, 16),
        (14, 17),
        (16, 18),
        (17, 19),
        (18, 20),
        (19, 21),
    ];
    for k in 0..2 {
        let joint = |j: usize| {
            let at = (k * 127 + j) * 3;
            Vector3::new(joints[at], joints[at + 1], joints[at + 2])
        };
        let offset = |j: usize| match j {
            0 => Vector3::zeros(),
            _ => {
                let at = (k * 21 + j - 1) * 3;
                Vector3::new(offsets[at], offsets[at + 1], offsets[at + 2])
            }
        };
        for (j, c) in bones {
            let (got, want) = (joint(c) - joint(j), offset(c) - offset(j));
            let cos = got.normalize().dot(&want.normalize());
            assert!(
                cos > 1.0 - 1e-5,
                "person {k}, bone {j}->{c}: {got} against {want}"
            );
        }
    }
}
