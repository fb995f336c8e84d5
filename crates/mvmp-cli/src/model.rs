//! `mvmp model summary`, `mvmp model extract`, `mvmp bench model` and `mvmp bench fusion`.
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_REGRESSED};

use crate::probe::{ring_rig, ring_roots};
use std::path::Path;
use std::time::Instant;

use anyhow::{Result, bail};
use burn::tensor::module::avg_pool2d;
use burn::tensor::ops::AvgPoolOptions;
use burn::tensor::{Bool, Device, Tensor, TensorData};

use mvmp_decoder::QueryInputs;
use mvmp_fusion::{FusionMode, Subvoxel, extract_roots, fuse_views};
use mvmp_model::summary::summarize;
use mvmp_model::{ModelConfig, MvmpHmr, RigGrids};
use mvmp_smplx::{SmplxLayer, Translation, regressed_to_full_pose};

/// flex's float32 GEMM speed on this machine (GFLOP/s), the speed the stages' shares are of: the median
/// of 7 products of two 1024 x 1024 matrices after one, the product summed to a scalar so that it has
/// finished (a pass over 4 MB, under 1% of the product). Measured, not a constant: the GEMM's kernels
/// are chosen at run time (AVX-512, AVX2 + FMA), so machines of one core count differ by 2x.
fn flex_gemm_gflops() -> f64 {
    let d = Device::flex();
    let n = 1024;
    let m = |seed: usize| {
        let v: Vec<f32> = (0..n * n)
            .map(|i| ((i * 7 + seed) % 251) as f32 / 251.0)
            .collect();
        Tensor::<2>::from_data(TensorData::new(v, [n, n]), &d)
    };
    let (a, b) = (m(0), m(1));
    let (_, t) = time(7, || a.clone().matmul(b.clone()));
    2.0 * (n * n * n) as f64 / t / 1e9
}

/// `mvmp model extract`: the run's HRNet (`hrnet`) or ViT weights alone, as `[init]` reads them.
pub fn extract(run: &Path, hrnet: bool, out: &Path) -> Result<()> {
    // The config first: it says when `run` is not a run directory at all.
    let cfg = mvmp_infer::run_files::model_config(run)?;
    let weights = mvmp_infer::run_files::weights(run)?;
    crate::paths::not_over_input("--out", out, run)?;
    let mut model = cfg.init(&Device::flex());
    mvmp_infer::load_weights(&mut model, &weights)?;
    let what = match hrnet {
        true => {
            mvmp_io::checkpoint::save(&model.hrnet, out)?;
            format!(
                "HRNet `{}`, {} heatmap joints",
                cfg.hrnet,
                cfg.heatmap_joints.len()
            )
        }
        false => {
            mvmp_io::checkpoint::save(&model.vit, out)?;
            format!("ViT `{}`", cfg.backbone)
        }
    };
    println!(
        "wrote {} (burnpack, {what}, from {})",
        out.display(),
        weights.display()
    );
    Ok(())
}

pub fn summary(config: &Path, views: usize) -> Result<()> {
    let cfg = ModelConfig::read(config)?;
    if views == 0 {
        bail!("--views must be at least 1");
    }
    // An autodiff device tells trainable parameters from running statistics.
    let s = summarize(&cfg, views, &Device::flex().autodiff());
    println!(
        "model {} ({} views, batch 1, {} x {} input)",
        config.display(),
        views,
        cfg.image_size,
        cfg.image_size
    );
    println!(
        "{:<10} {:>14} {:>12} {:>14}",
        "module", "parameters", "stored MB", "GMAC/forward"
    );
    let (mut tp, mut tb, mut tm) = (0, 0, 0.0);
    for r in &s.rows {
        println!(
            "{:<10} {:>14} {:>12.1} {:>14.2}",
            r.name,
            r.params,
            r.stored_bytes as f64 / 1e6,
            r.macs / 1e9
        );
        tp += r.params;
        tb += r.stored_bytes;
        tm += r.macs;
    }
    println!(
        "{:<10} {:>14} {:>12.1} {:>14.2}",
        "total",
        tp,
        tb as f64 / 1e6,
        tm / 1e9
    );
    println!("largest activations (float32):");
    for (name, bytes) in &s.activations {
        println!("  {:<52} {:>10.1} MB", name, *bytes as f64 / 1e6);
    }
    Ok(())
}

/// A stage's input: cut from the stage before it, and tracked when the backward is timed.
fn leaf<const D: usize>(t: Tensor<D>, backward: bool) -> Tensor<D> {
    match backward {
        true => t.detach().require_grad(),
        false => t,
    }
}

/// `y`, after the backward of its sum when `backward` is set (waited for on the device).
fn with_backward<const D: usize>(y: Tensor<D>, backward: bool, device: &Device) -> Tensor<D> {
    if backward {
        let grads = y.clone().sum().backward();
        // An asynchronous backend has only queued the backward's kernels.
        let _ = device.sync();
        drop(grads);
    }
    y
}

fn sync<const D: usize>(t: &Tensor<D>) {
    let _ = t.clone().sum().into_scalar::<f32>();
}

fn time<const D: usize>(iters: usize, mut f: impl FnMut() -> Tensor<D>) -> (Tensor<D>, f64) {
    let mut out = f();
    sync(&out);
    let mut times = Vec::with_capacity(iters);
    for _ in 0..iters {
        let t0 = Instant::now();
        out = f();
        sync(&out);
        times.push(t0.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    (out, times[times.len() / 2])
}

/// The training-memory estimate of `mvmp model summary --training`, printed.
pub fn training_summary(
    config: &Path,
    views: usize,
    batch: usize,
    people: Option<usize>,
) -> Result<()> {
    let cfg = ModelConfig::read(config)?;
    let shape = crate::training_memory::Shape {
        batch,
        views,
        people: people.unwrap_or(cfg.max_people),
    };
    let e = crate::training_memory::estimate(&cfg, shape)?;
    let mb = |b: f64| b / 1e6;
    println!(
        "training step on flex, batch {batch}, {views} views, {} people per sample (estimate):",
        shape.people
    );
    let line = |what: &str, bytes: f64| println!("  {what:<58} {:>10.1} MB", mb(bytes));
    line("weights", e.weights);
    line("body model, its layer, one batch", e.fixed);
    for s in &e.stages {
        let n = s.stage.number();
        line(
            &format!("stage {n}: Adam's two moments of what it trains"),
            s.adam,
        );
        line(
            &format!("stage {n}: activations, gradients, backward working memory"),
            s.step,
        );
        line(&format!("stage {n}: peak"), e.total(s));
    }
    for s in &e.stages {
        for (side, g, bytes) in &s.probes {
            println!(
                "  stage {} probe: {side} x {side} input, {} x {} x {} grid: {:.1} MB",
                s.stage.number(),
                g[0],
                g[1],
                g[2],
                mb(*bytes)
            );
        }
    }
    Ok(())
}

/// Projection and fusion alone at a config's scale: the sampling grids of a ring rig, then the fusion of
/// the feature maps (the config's channels and fusion mode) and of the heatmaps (mean), from the cached
/// grids, with maps of the sizes the backbones would give.
pub fn bench_fusion(config: &Path, views: usize, iters: usize, device: &Device) -> Result<()> {
    let cfg = ModelConfig::read(config)?;
    if views == 0 || iters == 0 {
        bail!("--views and --iters must be at least 1");
    }
    let mode = match cfg.fusion {
        // Its offsets and weights are parameters of the model: `bench model` times it.
        FusionMode::Deformable => bail!(
            "{}: fusion = \"deformable\" has learned parameters; `mvmp bench model --config` times it",
            config.display()
        ),
        m => m,
    };
    let (cams, lbs) = ring_rig(&cfg, views)?;
    let t0 = Instant::now();
    let grids = RigGrids::new(&cfg, &cams, &lbs, device);
    sync(&grids.features.grid);
    sync(&grids.heatmaps.grid);
    let t_grids = t0.elapsed().as_secs_f64();
    let maps = |c: usize, side: usize| {
        let n = views * c * side * side;
        let v: Vec<f32> = (0..n).map(|i| ((i * 7919) % 997) as f32 / 997.0).collect();
        Tensor::<5>::from_data(TensorData::new(v, [1, views, c, side, side]), device)
    };
    let [fh, _] = grids.features.map_hw;
    let [hh, _] = grids.heatmaps.map_hw;
    let feats = maps(cfg.feature_channels, fh);
    let hm = maps(cfg.heatmap_joints.len(), hh);
    let fg = std::slice::from_ref(&grids.features);
    let hg = std::slice::from_ref(&grids.heatmaps);
    let (_, t_feat) = time(iters, || fuse_views(feats.clone(), fg, mode));
    let (_, t_hm) = time(iters, || fuse_views(hm.clone(), hg, FusionMode::Mean));
    let [x, y, z] = cfg.grid.shape;
    let p = x * y * z;
    let path = if grids.features.is_fused() {
        "the fused CPU pass"
    } else {
        "tensor ops"
    };
    println!(
        "fusion for {} on {:?} ({path}): {} views, {} x {} x {} voxels, median of {} runs",
        config.display(),
        device,
        views,
        x,
        y,
        z,
        iters
    );
    println!("sampling grids (once per rig): {:.1} ms", t_grids * 1e3);
    let mb = |c: usize| (c * p * 4) as f64 / 1e6;
    println!(
        "{mode:?} fusion of {} channels from {fh} x {fh} maps: {:.1} ms ({:.1} MB volume)",
        cfg.feature_channels,
        t_feat * 1e3,
        mb(cfg.feature_channels)
    );
    println!(
        "Mean fusion of {} heatmaps from {hh} x {hh} maps: {:.1} ms ({:.1} MB volume)",
        cfg.heatmap_joints.len(),
        t_hm * 1e3,
        mb(cfg.heatmap_joints.len())
    );
    Ok(())
}

/// With `backward`, every stage runs on the autodiff device, and each timing is its forward and the
/// backward of the sum of its output: into its parameters and, from fusion on, into its input (which is
/// what training back-propagates into), with each stage's input a leaf of its own.
pub fn bench(
    config: &Path,
    views: usize,
    iters: usize,
    backward: bool,
    device: &Device,
) -> Result<()> {
    let cfg = ModelConfig::read(config)?;
    if views == 0 || iters == 0 {
        bail!("--views and --iters must be at least 1");
    }
    let device = &match backward {
        true => device.clone().autodiff(),
        false => device.clone(),
    };
    let net = cfg.init(device);
    let s = cfg.image_size;
    let (cams, lbs) = ring_rig(&cfg, views)?;
    let (grids, t_grids) = time_grids(&cfg, &cams, &lbs, iters, device);
    let n = views * 3 * (s * s) as usize;
    let img: Vec<f32> = (0..n)
        .map(|i| ((i * 7919) % 255) as f32 / 255.0 - 0.5)
        .collect();
    let x = Tensor::<4>::from_data(
        TensorData::new(img, [views, 3, s as usize, s as usize]),
        device,
    );
    let mut b = StageBench {
        iters,
        backward,
        device,
        summary: summarize(&cfg, views, &Device::flex().autodiff()),
        rows: Vec::new(),
    };
    let (feats, hm) = b.backbones(&net, &cfg, x);
    let (vol, hvol) = b.fusion(&cfg, &grids, feats, hm);
    let rot = b.heads(&net, &cfg, vol, hvol);
    b.smplx(rot);
    let header = format!(
        "model {} on {:?}: {views} views, {s} x {s} input, {} people, median of {iters} runs",
        config.display(),
        device,
        cfg.max_people
    );
    print_stage_times(&header, t_grids, backward, &b.rows);
    Ok(())
}

/// The stages of `mvmp bench model`, each timed on its own input; the rows are (stage, seconds, MACs).
struct StageBench<'a> {
    iters: usize,
    backward: bool,
    device: &'a Device,
    summary: mvmp_model::summary::Summary,
    rows: Vec<(&'static str, f64, f64)>,
}

impl StageBench<'_> {
    fn macs(&self, name: &str) -> f64 {
        self.summary
            .rows
            .iter()
            .find(|r| r.name == name)
            .map_or(0.0, |r| r.macs)
    }

    /// Time `f` (with its backward when timed) and record it.
    fn run<const D: usize>(
        &mut self,
        stage: &'static str,
        macs: f64,
        f: impl Fn() -> Tensor<D>,
    ) -> Tensor<D> {
        let (backward, device) = (self.backward, self.device);
        let (y, t) = time(self.iters, || with_backward(f(), backward, device));
        self.rows.push((stage, t, macs));
        y
    }

    /// The ViT with its reduction and HRNet (on the input pooled by `hrnet_downsample`, as in the model):
    /// features and heatmaps `[1, V, C, h, w]`, cut from the graph.
    fn backbones(
        &mut self,
        net: &MvmpHmr,
        cfg: &ModelConfig,
        x: Tensor<4>,
    ) -> (Tensor<5>, Tensor<5>) {
        let macs = self.macs("vit") + self.macs("reduce");
        let feats = self.run("vit+reduce", macs, || net.view_features(x.clone()));
        let xh = match cfg.hrnet_downsample.max(1) as usize {
            1 => x,
            k => avg_pool2d(x, AvgPoolOptions::new([k, k])),
        };
        let hm = self.run("hrnet", self.macs("hrnet"), || {
            net.hrnet.forward(xh.clone())
        });
        let [v, cf, h, w] = feats.dims();
        let [_, j, hh, hw] = hm.dims();
        (
            leaf(feats.reshape([1, v, cf, h, w]), self.backward),
            leaf(hm.reshape([1, v, j, hh, hw]), self.backward),
        )
    }

    /// Both fusions, timed as one row: the feature volume and the heatmap volume, cut from the graph.
    fn fusion(
        &mut self,
        cfg: &ModelConfig,
        grids: &RigGrids,
        feats: Tensor<5>,
        hm: Tensor<5>,
    ) -> (Tensor<5>, Tensor<5>) {
        let fg = vec![grids.features.clone()];
        let hg = vec![grids.heatmaps.clone()];
        let vol = self.run("fusion", 0.0, || fuse_views(feats.clone(), &fg, cfg.fusion));
        let t1 = self.rows.pop().map_or(0.0, |r| r.1);
        let hvol = self.run("fusion", self.macs("fusion"), || {
            fuse_views(hm.clone(), &hg, FusionMode::Mean)
        });
        if let Some(r) = self.rows.last_mut() {
            r.1 += t1;
        }
        (leaf(vol, self.backward), leaf(hvol, self.backward))
    }

    /// The RootNet, root extraction and the decoder at `max_people` roots on a ring: the rotations
    /// `[K, 53, 3, 3]`, cut from the graph.
    fn heads(
        &mut self,
        net: &MvmpHmr,
        cfg: &ModelConfig,
        vol: Tensor<5>,
        hvol: Tensor<5>,
    ) -> Tensor<4> {
        let (g, k, device) = (&cfg.grid, cfg.max_people, self.device);
        let lik = self.run("rootnet", self.macs("rootnet"), || {
            net.rootnet.forward(hvol.clone()).0
        });
        let t0 = Instant::now();
        let _ = extract_roots(lik, Subvoxel::Centre, g, k, f32::MIN);
        self.rows.push(("roots", t0.elapsed().as_secs_f64(), 0.0));
        let roots = Tensor::<3>::from_data(TensorData::new(ring_roots(g, k), [1, k, 3]), device);
        let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true; k], [1, k]), device);
        // What the config has the decoder read beside the volume: everyone facing +x, the joint volume.
        let facing = [1f32, 0.0].repeat(k);
        let heading = Tensor::<3>::from_data(TensorData::new(facing, [1, k, 2]), device);
        let rot = self.run("decoder", self.macs("decoder"), || {
            let inputs = QueryInputs {
                heading: cfg.facing.then(|| heading.clone()),
                joints: cfg.decoder.query_joints.then(|| hvol.clone().detach()),
            };
            let decoded =
                (net.decoder).forward_with(vol.clone(), inputs, g, roots.clone(), present.clone());
            decoded.rot6d
        });
        let rot = rot.detach().reshape([k * NUM_REGRESSED, 6]);
        let rotm = mvmp_geom::rotation::rot6d_to_matrix(rot).reshape([k, NUM_REGRESSED, 3, 3]);
        leaf(rotm, self.backward)
    }

    /// The stand-in body layer posing `K` bodies.
    fn smplx(&mut self, rotm: Tensor<4>) {
        let device = self.device;
        let layer = SmplxLayer::new(&mvmp_smplx::standin_model(0), device);
        let k = rotm.dims()[0];
        self.run("smplx", self.macs("smplx"), || {
            layer
                .forward(
                    regressed_to_full_pose(rotm.clone()),
                    Tensor::zeros([k, NUM_BETAS], device),
                    Tensor::zeros([k, NUM_EXPRESSION], device),
                    Tensor::zeros([k, 3], device),
                    Translation::Pelvis,
                )
                .vertices
        });
    }
}

/// The rig's sampling grids and the median time to make them over `iters` runs after one: the first
/// call also pays for the thread pool and the allocator's first pages (80 ms against 10 on a 2-core
/// machine), which a training step, making them every step, does not.
fn time_grids(
    cfg: &ModelConfig,
    cams: &[mvmp_geom::Camera],
    lbs: &[mvmp_geom::Letterbox],
    iters: usize,
    device: &Device,
) -> (RigGrids, f64) {
    let make = || {
        let grids = RigGrids::new(cfg, cams, lbs, device);
        sync(&grids.features.grid);
        grids
    };
    let mut grids = make();
    let mut times = Vec::with_capacity(iters);
    for _ in 0..iters {
        let t0 = Instant::now();
        grids = make();
        times.push(t0.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    (grids, times[times.len() / 2])
}

/// The table of `bench model`: per stage its time, GFLOP/s and share of flex's GEMM speed.
fn print_stage_times(header: &str, t_grids: f64, backward: bool, rows: &[(&str, f64, f64)]) {
    println!("{header}");
    println!("sampling grids (per rig, median): {:.1} ms", t_grids * 1e3);
    // A backward computes the gradients of the input and of the weights: twice the forward's work.
    let (what, work) = match backward {
        true => ("forward + backward, at 3x the forward's MACs", 3.0),
        false => ("forward", 1.0),
    };
    let gemm = flex_gemm_gflops();
    println!("{what}; flex's 1024^3 GEMM here: {gemm:.0} GFLOP/s:");
    println!(
        "{:<11} {:>10} {:>10} {:>12}",
        "stage", "ms", "GFLOP/s", "% of GEMM"
    );
    let mut total = 0.0;
    for (name, t, m) in rows {
        let gflops = 2.0 * work * m / t / 1e9;
        let pct = if *m > 0.0 {
            format!("{:.0}%", 100.0 * gflops / gemm)
        } else {
            "-".into()
        };
        let gf = if *m > 0.0 {
            format!("{gflops:.1}")
        } else {
            "-".into()
        };
        println!("{:<11} {:>10.1} {:>10} {:>12}", name, t * 1e3, gf, pct);
        total += t;
    }
    println!("{:<11} {:>10.1}", "total", total * 1e3);
}
