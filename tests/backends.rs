//! Backend equivalence: the same computations on flex (the reference CPU backend), burn-ndarray and,
//! with the `wgpu` feature, wgpu (a GPU, or lavapipe's software Vulkan on a machine without one) give the
//! same numbers within float32 tolerances: rotation conversions; long reductions; the SMPL-X forward at batch 30 and its
//! gradient in pose and betas; HRNet (conv, batch norm, upsampling) and the ViT (attention, layer norm,
//! GELU); the tiled attention and its backward; a ViT block recomputed in its backward; view projection and mean/max fusion (grid sampling); the RootNet (3D convolutions, pooling),
//! 3D NMS and root extraction; one Human Transformer Block; the whole model's forward; one training step
//! (the stage-2 loss and the gradient norm of every parameter tensor).
//!
//! Every difference is the largest absolute difference over the reference's largest magnitude; the
//! measured values print as a table (`-- --nocapture`).
use std::path::Path;

use burn::data::dataloader::batcher::Batcher;
use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Bool, Device, Gradients, Tensor, TensorData};
use mvmp::data::dataset::FrameDataset;
use mvmp::data::loader::{FrameBatcher, Split, ViewChoice};
use mvmp::data::synth::{SynthConfig, generate};
use mvmp::decoder::{DecoderConfig, DecoderOptions};
use mvmp::fusion::pool::nms3d;
use mvmp::fusion::{FusionMode, RootNetConfig, SamplingGrid, extract_roots, fuse_views};
use mvmp::geom::rotation::{
    axis_angle_to_matrix, matrix_to_axis_angle, matrix_to_rot6d, rot6d_to_matrix,
};
use mvmp::geom::{Camera, Letterbox, VoxelGrid};
use mvmp::model::{ModelConfig, MvmpHmr, RigGrids};
use mvmp::smplx::{SmplxLayer, Translation, standin_model};
use mvmp::train::step::{Stage2, stage2_loss};
use nalgebra::{Matrix3, Vector3};

/// Deterministic pseudo-random values in [-a, a] (a hash, not a progression).
fn values(n: usize, seed: u64, a: f32) -> Vec<f32> {
    (0..n as u64)
        .map(|i| {
            let mut x =
                (i ^ seed.wrapping_mul(0x9E37_79B9_7F4A_7C15)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            x ^= x >> 31;
            x = x.wrapping_mul(0x94D0_49BB_1331_11EB);
            x ^= x >> 29;
            ((x % 20001) as f32 / 10000.0 - 1.0) * a
        })
        .collect()
}

fn t<const D: usize>(v: Vec<f32>, shape: [usize; D], d: &Device) -> Tensor<D> {
    Tensor::from_data(TensorData::new(v, shape), d)
}

fn host<const D: usize>(x: Tensor<D>) -> Vec<f32> {
    x.into_data().convert::<f32>().try_into_vec().unwrap()
}

/// Largest absolute difference relative to the reference's largest magnitude.
fn rel_diff(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len());
    let scale = a.iter().fold(0f32, |m, x| m.max(x.abs())).max(1e-6);
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0f32, f32::max)
        / scale
}

fn rig() -> Vec<Camera> {
    (0..2)
        .map(|i| {
            let a = i as f64 * 1.9 + 0.3;
            let pos = Vector3::new(5.0 * a.cos(), 5.0 * a.sin(), 2.2);
            let z = (Vector3::new(0.0, 0.0, 1.0) - pos).normalize();
            let x = z.cross(&Vector3::z()).normalize();
            let y = z.cross(&x);
            let r = Matrix3::from_rows(&[x.transpose(), y.transpose(), z.transpose()]);
            let k = Matrix3::new(110.0, 0.0, 79.5, 0.0, 110.0, 59.5, 0.0, 0.0, 1.0);
            Camera::new(
                format!("{i}"),
                k,
                r,
                -(r * pos),
                [-0.05, 0.01, 0.0, 0.0, 0.0],
                160,
                120,
            )
            .unwrap()
        })
        .collect()
}

/// The measured differences of one backend against flex.
struct Report {
    backend: &'static str,
    tol: f32,
    rows: Vec<(String, f32)>,
}

impl Report {
    fn new(backend: &'static str, tol: f32) -> Self {
        Report {
            backend,
            tol,
            rows: Vec::new(),
        }
    }

    fn check(&mut self, name: &str, reference: &[f32], other: &[f32]) {
        let d = rel_diff(reference, other);
        assert!(d.is_finite(), "{}: {name}: not finite", self.backend);
        // Printed as it comes: on a software GPU the suite takes minutes.
        println!("{:<8} {name:<44} {d:.2e}", self.backend);
        self.rows.push((name.to_string(), d));
    }

    /// Fail on every check over the tolerance at once.
    fn finish(self) {
        let bad: Vec<String> = self
            .rows
            .iter()
            .filter(|(_, d)| *d > self.tol)
            .map(|(n, d)| format!("{n}: {d:.2e}"))
            .collect();
        assert!(
            bad.is_empty(),
            "{} differs from flex beyond {:e}: {}",
            self.backend,
            self.tol,
            bad.join(", ")
        );
    }
}

fn rotations(other: &Device, r: &mut Report) {
    // Angles below pi (|r| <= 1.5 sqrt 3 = 2.6), where the matrix-to-axis-angle map is well conditioned.
    let aa = values(64 * 3, 11, 1.5);
    let six = values(64 * 6, 12, 1.0);
    let run = |d: &Device| {
        let m = axis_angle_to_matrix(t(aa.clone(), [64, 3], d));
        (
            host(m.clone()),
            host(matrix_to_axis_angle(m.clone())),
            host(matrix_to_rot6d(m)),
            host(rot6d_to_matrix(t(six.clone(), [64, 6], d))),
        )
    };
    let (a, b) = (run(&Device::flex()), run(other));
    r.check("rotation: axis-angle to matrix", &a.0, &b.0);
    r.check("rotation: matrix to axis-angle", &a.1, &b.1);
    r.check("rotation: matrix to 6D", &a.2, &b.2);
    r.check("rotation: 6D to matrix", &a.3, &b.3);
}

fn reductions(other: &Device, r: &mut Report) {
    // Long reductions, as the losses take them at paper scale (a 300 x 300 x 20 volume, the 2D mesh term
    // of a crowded batch): mvmp_losses::sum_all / mean_all / max_rows, and a sum along rows. (burn
    // 0.22.1's own one-kernel reductions over more than 2^18 elements per axis come out wrong on adapters
    // limited to 65535 workgroups per dispatch axis, lavapipe among them; these helpers split them.)
    let n = 1 << 22;
    let v: Vec<f32> = (0..n).map(|i| (i % 7) as f32 - 3.0 + 0.25).collect();
    let run = |d: &Device| {
        let x = t(v.clone(), [n], d);
        let rows = x.clone().reshape([2, n / 2]);
        (
            host(mvmp::losses::sum_all(x.clone())),
            host(mvmp::losses::mean_all(x.clone().reshape([64, n / 64]))),
            host(mvmp::losses::max_rows(rows.clone())),
            host(x.reshape([1 << 12, 1 << 10]).sum_dim(1)),
        )
    };
    let (a, b) = (run(&Device::flex()), run(other));
    // The exact sum: 2^22 / 7 whole cycles of (-2.75 .. 3.25) plus the remainder, all exact in f64.
    let want: f64 = v.iter().map(|&x| x as f64).sum();
    assert!(
        ((a.0[0] as f64) - want).abs() < 1e-3 * want.abs().max(1.0),
        "flex sum_all {} vs {want}",
        a.0[0]
    );
    r.check("sum_all of 2^22 elements", &a.0, &b.0);
    r.check("mean_all of 2^22 elements", &a.1, &b.1);
    r.check("max_rows of 2 x 2^21", &a.2, &b.2);
    r.check("sum along rows, 4096 x 1024", &a.3, &b.3);
}

fn smplx(other: &Device, r: &mut Report) {
    // Batch 30 with its gradient: skinning GEMMs, the kinematic chain, pose correctives, and their backward.
    let model = standin_model(0);
    let nv = model.num_vertices();
    let weights = values(30 * nv * 3, 24, 1.0);
    let run = |d: &Device| {
        let ad = d.clone().autodiff();
        let layer = SmplxLayer::new(&model, &ad);
        let pose = t(values(30 * 55 * 3, 21, 0.4), [30, 55, 3], &ad).require_grad();
        let betas = t(values(300, 22, 1.0), [30, 10], &ad).require_grad();
        let out = layer.forward_axis_angle(
            pose.clone(),
            betas.clone(),
            t(values(300, 23, 1.0), [30, 10], &ad),
            t(values(90, 4, 2.0), [30, 3], &ad),
            Translation::Pelvis,
        );
        // A random linear functional of the vertices, so every vertex's gradient path counts.
        let loss = (out.vertices.clone() * t(weights.clone(), [30, nv, 3], &ad)).sum()
            + out.joints.clone().sum();
        let g = loss.backward();
        (
            host(out.vertices),
            host(out.joints),
            host(pose.grad(&g).expect("pose gradient")),
            host(betas.grad(&g).expect("betas gradient")),
        )
    };
    let (a, b) = (run(&Device::flex()), run(other));
    r.check("SMPL-X batch 30: vertices", &a.0, &b.0);
    r.check("SMPL-X batch 30: joints", &a.1, &b.1);
    r.check("SMPL-X batch 30: d/d pose", &a.2, &b.2);
    r.check("SMPL-X batch 30: d/d betas", &a.3, &b.3);
}

fn backbones(other: &Device, r: &mut Report) {
    let flex = Device::flex();
    let image = values(2 * 3 * 64 * 64, 5, 1.0);
    let hr = mvmp::backbone::HRNetConfig::tiny(4).init(&flex).valid();
    let a = host(hr.forward(t(image.clone(), [2, 3, 64, 64], &flex)));
    let b = host(hr.fork(other).forward(t(image, [2, 3, 64, 64], other)));
    r.check("HRNet heatmaps", &a, &b);

    let vit = mvmp::backbone::ViTConfig::tiny().init(&flex).valid();
    let img = values(3 * 56 * 56, 6, 1.0);
    let a = host(vit.forward(t(img.clone(), [1, 3, 56, 56], &flex)));
    let b = host(vit.fork(other).forward(t(img, [1, 3, 56, 56], other)));
    r.check("ViT features", &a, &b);
}

fn fusion(other: &Device, r: &mut Report) {
    // Every voxel centre into every view, bilinear sampling, mean and max over the views.
    let grid = VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [16, 16, 8]).unwrap();
    let cams = rig();
    let lbs: Vec<Letterbox> = cams
        .iter()
        .map(|c| Letterbox::new(c.width, c.height, 64).unwrap())
        .collect();
    let maps = values(2 * 4 * 16 * 16, 7, 1.0);
    for mode in [FusionMode::Mean, FusionMode::Max] {
        let fused = |d: &Device| {
            let g = SamplingGrid::new(&grid, &cams, &lbs, 4.0, [16, 16], d);
            host(fuse_views(
                t(maps.clone(), [1, 2, 4, 16, 16], d),
                &[g],
                mode,
            ))
        };
        let (a, b) = (fused(&Device::flex()), fused(other));
        r.check(&format!("projection + {mode:?} fusion"), &a, &b);
    }
}

fn rootnet(other: &Device, r: &mut Report) {
    let flex = Device::flex();
    // RootNet: 3D convolutions, batch norm, max pooling, transposed convolutions.
    let rn = RootNetConfig::new(4).with_width(0.25).init(&flex).valid();
    let vol = values(4 * 16 * 16 * 8, 8, 1.0);
    let (la, oa) = rn.forward(t(vol.clone(), [1, 4, 16, 16, 8], &flex));
    let (lb, ob) = rn.fork(other).forward(t(vol, [1, 4, 16, 16, 8], other));
    r.check("RootNet likelihood", &host(la), &host(lb));
    r.check("RootNet offsets", &host(oa), &host(ob));

    // NMS and root extraction on a volume with planted, well-separated peaks over a noise floor, so
    // the kept set does not hinge on float ties.
    let grid = VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [16, 16, 8]).unwrap();
    let mut lik: Vec<f32> = values(2 * 16 * 16 * 8, 9, 0.25)
        .iter()
        .map(|v| v + 0.25)
        .collect();
    for (k, (bi, flat)) in [(0, 37), (0, 1500), (1, 700), (1, 1901), (1, 90)]
        .into_iter()
        .enumerate()
    {
        lik[bi * 2048 + flat] = 0.95 - 0.1 * k as f32;
    }
    let off = values(2 * 3 * 2048, 10, 0.45);
    let run = |d: &Device| {
        let l = t(lik.clone(), [2, 1, 16, 16, 8], d);
        let kept = host(nms3d(l.clone()));
        let roots = extract_roots(
            l,
            mvmp::fusion::Subvoxel::Offset(Box::new(t(off.clone(), [2, 3, 16, 16, 8], d))),
            &grid,
            4,
            0.52,
        );
        (kept, roots)
    };
    let (a, b) = (run(&flex), run(other));
    r.check("3D NMS", &a.0, &b.0);
    let summary = |roots: &Vec<Vec<mvmp::fusion::Root>>| -> (Vec<[usize; 3]>, Vec<f32>) {
        let all = roots.iter().flatten();
        (
            all.clone().map(|x| x.voxel).collect(),
            all.flat_map(|x| {
                [x.score]
                    .into_iter()
                    .chain(x.position.iter().map(|&p| p as f32))
            })
            .collect(),
        )
    };
    let (va, sa) = summary(&a.1);
    let (vb, sb) = summary(&b.1);
    assert_eq!(a.1.iter().map(Vec::len).collect::<Vec<_>>(), [2, 3]);
    assert_eq!(va, vb, "{}: extracted root voxels differ", r.backend);
    r.check("root extraction: scores and positions", &sa, &sb);
}

fn transformer_block(other: &Device, r: &mut Report) {
    let flex = Device::flex();
    let block = DecoderConfig::new(16)
        .with_options(DecoderOptions {
            dim: 32,
            heads: 4,
            ..Default::default()
        })
        .init(&flex)
        .blocks
        .remove(0);
    let q = values(2 * 5 * 32, 13, 1.0);
    let tokens = values(2 * 40 * 32, 14, 1.0);
    let pad = vec![
        false, false, false, true, true, false, false, false, false, true,
    ];
    let run = |b: &mvmp::decoder::HumanTransformerBlock, d: &Device| {
        host(b.forward(
            t(q.clone(), [2, 5, 32], d),
            Tensor::<2, Bool>::from_data(TensorData::new(pad.clone(), [2, 5]), d),
            t(tokens.clone(), [2, 40, 32], d),
        ))
    };
    let a = run(&block, &flex);
    let b = run(&block.fork(other), other);
    // Padded slots hold whatever attention made of them; only people count.
    let keep = |v: Vec<f32>| -> Vec<f32> {
        v.chunks(32)
            .zip(&pad)
            .filter(|(_, p)| !**p)
            .flat_map(|(c, _)| c.to_vec())
            .collect()
    };
    r.check("Human Transformer Block", &keep(a), &keep(b));
}

/// The tiled attention on `other` against burn's plain attention on flex, and strictly (1e-5) against the
/// plain attention on `other` itself: output and the gradients of q, k and v, with tiles that do not
/// divide the tokens and fewer queries than keys.
fn tiled_attention(other: &Device, r: &mut Report) {
    use mvmp::kernels::{attention, plain_attention};
    let (nq, nk, d) = (37, 29, 8);
    let run = |device: &Device, tiled: bool| -> Vec<Vec<f32>> {
        let ad = device.clone().autodiff();
        let input = |seed, n| t(values(2 * 3 * n * d, seed, 1.0), [2, 3, n, d], &ad);
        let (q, k, v) = (input(21, nq), input(22, nk), input(23, nk));
        let (q, k, v) = (q.require_grad(), k.require_grad(), v.require_grad());
        let scale = 1.0 / (d as f64).sqrt();
        let out = if tiled {
            attention(q.clone(), k.clone(), v.clone(), scale, 8)
        } else {
            plain_attention(q.clone(), k.clone(), v.clone(), scale)
        };
        let grads = (out.clone() * input(24, nq)).sum().backward();
        let mut all = vec![host(out.detach())];
        all.extend([q, k, v].map(|x| host(x.grad(&grads).expect("a gradient"))));
        all
    };
    let (reference, tiled, plain) = (
        run(&Device::flex(), false),
        run(other, true),
        run(other, false),
    );
    for (i, name) in ["output", "dq", "dk", "dv"].iter().enumerate() {
        r.check(
            &format!("tiled attention: {name}"),
            &reference[i],
            &tiled[i],
        );
        let same_device = rel_diff(&plain[i], &tiled[i]);
        assert!(
            same_device < 1e-5,
            "{}: tiled attention {name} differs from plain by {same_device:e}",
            r.backend
        );
    }
}

/// A ViT block recomputed in its backward (`mvmp::kernels::recompute`) against the same block with its
/// activations stored, both on `other`: the output and the gradients of the input and of the qkv and fc1
/// weights. (Across backends the block's gradients differ by up to 3e-4 either way: burn's GELU backward
/// is not the same on every backend.)
fn recomputed_block(other: &Device, r: &mut Report) {
    let ad = other.clone().autodiff();
    let vit = mvmp::backbone::vit::ViTConfig::new(32, 1, 4)
        .with_attention_tile(8)
        .init(&Device::flex().autodiff());
    let stored = vit.blocks[0].clone().fork(&ad);
    let mut recomputed = stored.clone();
    recomputed.recompute = true;
    let run = |b: &mvmp::backbone::vit::Block| {
        let x = t(values(2 * 19 * 32, 31, 1.0), [2, 19, 32], &ad).require_grad();
        let y = b.forward(x.clone());
        let w = t(values(2 * 19 * 32, 32, 1.0), [2, 19, 32], &ad);
        let grads = (y.clone() * w).sum().backward();
        let g = |p: Tensor<2>| host(p.grad(&grads).expect("a gradient"));
        [
            host(y.detach()),
            host(x.grad(&grads).expect("d/dx")),
            g(b.attn.qkv.weight.val()),
            g(b.mlp.fc1.weight.val()),
        ]
    };
    let (a, b) = (run(&stored), run(&recomputed));
    for (i, name) in ["output", "d/dx", "d/d qkv weight", "d/d fc1 weight"]
        .iter()
        .enumerate()
    {
        r.check(
            &format!("recomputed ViT block vs stored: {name}"),
            &a[i],
            &b[i],
        );
    }
}

/// A small synthetic dataset (3 views, 160 x 120) in a temporary directory.
fn dataset(dir: &Path) -> std::path::PathBuf {
    let out = dir.join("ds");
    let mut c = SynthConfig {
        name: "backends".into(),
        seed: 2,
        scenes: 1,
        frames_per_scene: 1,
        people: [2, 3],
        area: [3.0, 3.0],
        image_size: [160, 120],
        ..Default::default()
    };
    c.cameras.count = 3;
    c.cameras.rings[0].radius = 5.0;
    generate(&c, &out, Path::new("."), &|| {}).unwrap();
    out
}

/// The tiny model's architecture at 64 px on a 16 x 16 x 4 grid.
fn small_model_config() -> ModelConfig {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("configs/model/tiny.toml");
    let mut c = ModelConfig::read(&path).unwrap();
    c.image_size = 64;
    c.grid = VoxelGrid::new([0.0, 0.0, 1.0], [4.0, 4.0, 2.0], [16, 16, 4]).unwrap();
    c.max_people = 3;
    c.decoder.dim = 32;
    c.rootnet_width = 0.25;
    c
}

/// Every parameter tensor's gradient norm, in visiting order (0 where a tensor has none).
fn grad_norms(m: &MvmpHmr, g: &Gradients) -> Vec<f32> {
    struct Norms<'a>(&'a Gradients, Vec<f32>);
    impl ModuleVisitor for Norms<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            let n = p.val().grad(self.0).map_or(0.0, |g| {
                g.powf_scalar(2.0).sum().sqrt().into_scalar::<f32>()
            });
            self.1.push(n);
        }
    }
    let mut v = Norms(g, Vec::new());
    m.visit(&mut v);
    v.1
}

fn model_and_training_step(other: &Device, r: &mut Report) {
    let dir = tempfile::tempdir().unwrap();
    let data = dataset(dir.path());
    let cfg = small_model_config();
    let ds = FrameDataset::open(&data, Split::Train, ViewChoice::Fixed(vec![0, 1]), 64).unwrap();
    let body = ds.layout().unwrap().body_model().unwrap();
    let sample = ds.load(0).unwrap();
    let flex = Device::flex();
    let model = mvmp::train::seeded_init(&cfg, &flex.clone().autodiff(), 4)
        .with_body(std::sync::Arc::new(body.clone()));

    // Inference: decoded at fixed roots, so no thresholded decision sits between the two backends.
    let infer = |m: &MvmpHmr, d: &Device| {
        let batch = FrameBatcher::with_vertices(body.clone()).batch(vec![sample.clone()], d);
        let grids: Vec<RigGrids> = mvmp::train::step::batch_grids(&cfg, &batch, d);
        let roots = t(vec![0.3, -0.2, 0.9, -0.8, 0.5, 1.0], [1, 2, 3], d);
        let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true, true], [1, 2]), d);
        let o = m.forward(batch.images, &grids, Some((roots, present)));
        [
            host(o.heatmaps),
            host(o.likelihood),
            host(o.offset),
            host(o.rot6d),
            host(o.betas),
            host(o.transl),
            host(o.vertices),
        ]
    };
    let plain = model.valid();
    let a = infer(&plain, &flex);
    let b = infer(&plain.fork(other), other);
    let names = [
        "model: heatmaps",
        "model: root likelihood",
        "model: root offsets",
        "model: 6D rotations",
        "model: betas",
        "model: pelvis",
        "model: vertices",
    ];
    for (n, (x, y)) in names.iter().zip(a.iter().zip(&b)) {
        r.check(n, x, y);
    }

    // One training step: batch-norm statistics of the batch, the five losses with ground-truth queries,
    // the backward through everything.
    let step = |m: &MvmpHmr, d: &Device| {
        let batch = FrameBatcher::with_vertices(body.clone()).batch(vec![sample.clone()], d);
        let l = stage2_loss(
            m,
            &batch,
            &Stage2::at_true_roots(&mvmp::losses::LossWeights::default()),
            d,
        );
        let terms: Vec<f32> = l
            .terms
            .iter()
            .map(|(_, v)| v.clone().into_scalar::<f32>())
            .collect();
        let g = l.total.backward();
        (terms, grad_norms(m, &g))
    };
    let ad_other = other.clone().autodiff();
    let (ta, ga) = step(&model, &flex.autodiff());
    let (tb, gb) = step(&model.fork(&ad_other), &ad_other);
    r.check("training step: loss terms", &ta, &tb);
    assert!(ga.iter().filter(|&&n| n > 0.0).count() > 100);
    r.check("training step: gradient norm per tensor", &ga, &gb);
}

/// Run every check of the suite with `other` against flex.
fn suite(other: &Device, backend: &'static str, tol: f32) {
    let mut r = Report::new(backend, tol);
    rotations(other, &mut r);
    reductions(other, &mut r);
    smplx(other, &mut r);
    backbones(other, &mut r);
    fusion(other, &mut r);
    rootnet(other, &mut r);
    transformer_block(other, &mut r);
    tiled_attention(other, &mut r);
    recomputed_block(other, &mut r);
    model_and_training_step(other, &mut r);
    r.finish();
}

#[test]
#[allow(deprecated)]
fn ndarray_matches_flex() {
    suite(&Device::ndarray(), "ndarray", 1e-4);
}

#[cfg(feature = "wgpu")]
#[test]
fn wgpu_matches_flex() {
    suite(
        &Device::wgpu(burn::tensor::DeviceKind::DefaultDevice),
        "wgpu",
        1e-4,
    );
}
