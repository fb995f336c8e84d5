//! `mvmp bench train`: seconds per training step of a config, per stage, and where they go (the phases
//! every step logs in `metrics.jsonl`: load, forward, backward, gradient norms, optimizer, the weight
//! average's update). Each stage trains on its own in a temporary run (the other stage set to 0
//! epochs), stopped after the warm-up and the timed steps; nothing is left behind. The last column is the peak of host memory allocated while
//! the stage ran (model, optimizer state, data, steps and the one-frame validation), for CPU devices.
use std::path::Path;

use anyhow::{Context, Result};
use burn::tensor::Device;
use mvmp_train::{RunDir, Stage, TrainConfig, TrainOptions};
use serde_json::Value;

use crate::run::write_demo_configs;

/// Steps of each stage run before the timed ones (allocations, caches, autotuning).
const WARM_UP: usize = 2;
/// The phases of a step, as `metrics.jsonl` names them; `volumes` (what the step computes for a stage
/// that keeps it, `cache_volumes`) and `average` (the weight average's update) only where the stage
/// has them.
const PHASES: [&str; 7] = [
    "load",
    "volumes",
    "forward",
    "backward",
    "grad_norm",
    "optimizer",
    "average",
];

pub struct BenchTrainArgs<'a> {
    /// A training config (default: the demo's on a synthetic set made for the run).
    pub config: Option<&'a Path>,
    /// The dataset (default: the config's own).
    pub data: Option<&'a Path>,
    /// Timed steps per stage.
    pub steps: usize,
    /// One-frame scenes of the synthetic set made when no config is given.
    pub scenes: usize,
    /// Whether the device computes in host memory, where the allocator sees it (the peak column).
    pub host: bool,
    /// Also time each stage with the fused backward passes off (the tensor-op paths), side by side.
    pub baseline: bool,
}

pub fn bench_train(args: &BenchTrainArgs, device: &Device) -> Result<()> {
    let tmp = tempfile::tempdir().context("creating a temporary directory")?;
    let (config, data) = match args.config {
        Some(c) => (c.to_path_buf(), args.data.map(Path::to_path_buf)),
        None => demo_setup(tmp.path(), args)?,
    };
    let (mut cfg, model) = TrainConfig::read(&config)?;
    if let Some(d) = &data {
        cfg.data = Some(d.to_string_lossy().into_owned());
    }
    anyhow::ensure!(
        cfg.data.is_some() || !cfg.sources.is_empty(),
        "training config {}: no training data: set `data` or add [[sources]], or pass --data DIR",
        config.display()
    );
    // Every source opened (files, splits, cameras) before anything is printed.
    mvmp_train::open_training_set(&cfg, &model, &config)?;
    let name = match args.config {
        Some(c) => c.display().to_string(),
        None => "the demo's configs".into(),
    };
    println!(
        "{name}: median seconds per step over {} steps after {WARM_UP} warm-up steps, batch {}, {} views",
        args.steps, cfg.batch_size, cfg.train_views
    );
    let header: Vec<String> = PHASES.iter().map(|p| format!("{p:>5}")).collect();
    println!(
        "stage  path       steps  s/step  {}  peak MiB",
        header.join("  ")
    );
    let paths: &[bool] = if args.baseline {
        &[true, false]
    } else {
        &[true]
    };
    for stage in Stage::ALL {
        let mut times = Vec::new();
        for &fused in paths {
            set_fused_passes(fused);
            let timed = time_stage(stage, &cfg, &model, tmp.path(), args.steps, device);
            set_fused_passes(true);
            let (mut line, s_per_step, peak, kept) = timed?;
            line += &match args.host {
                true => format!("  {:>8.0}", peak as f64 / (1 << 20) as f64),
                false => format!("  {:>8}", "-"),
            };
            let path = if fused { "fused" } else { "tensor-ops" };
            println!("{:>5}  {path:<10} {line}", stage.number());
            if cfg.stage(stage).cache_volumes {
                println!(
                    "{:>5}  each timed step computed the volumes the stage keeps; a step that reads \
                     them takes about {kept:.3} s (s/step less `volumes`)",
                    stage.number()
                );
            }
            times.push(s_per_step);
        }
        if let [fused, ops] = times[..] {
            println!(
                "{:>5}  tensor-ops / fused: {:.2}x",
                stage.number(),
                ops / fused
            );
        }
    }
    Ok(())
}

/// The training passes with their own backward on flex (fusion, SMPL-X, convolution columns and
/// products, batch, group and layer norm, linear layers, attention, residual joins, GELU) and the
/// one-pass weight updates (Adam's step, the weight average's), on or off.
fn set_fused_passes(on: bool) {
    mvmp_fusion::set_fused_backward(on);
    mvmp_smplx::set_fused_backward(on);
    mvmp_kernels::im2col::set_fused_im2col(on);
    mvmp_kernels::product::set_fused_product(on);
    mvmp_kernels::norm::set_fused_norm(on);
    mvmp_kernels::residual::set_fused_residual(on);
    mvmp_kernels::linear::set_fused_linear(on);
    mvmp_kernels::layer_norm::set_fused_layer_norm(on);
    mvmp_kernels::attention::set_host_attention(on);
    mvmp_kernels::gelu::set_parallel_gelu(on);
    mvmp_train::adam::set_fused_adam(on);
    mvmp_kernels::blend::set_host_blend(on);
    mvmp_losses::set_fused_mesh_2d(on);
}

/// Median seconds per step of each stage of `cfg` on `device`, from `steps` timed steps after the
/// warm-up (runs in a temporary directory under `tmp`); of a stage that keeps volumes, a step that
/// reads them (the first epoch's steps, which compute them, cost more).
pub fn step_seconds(
    cfg: &TrainConfig,
    model: &mvmp_model::ModelConfig,
    tmp: &Path,
    steps: usize,
    device: &Device,
) -> Result<[f64; 2]> {
    let mut out = [0.0; 2];
    for (i, stage) in Stage::ALL.into_iter().enumerate() {
        let (_, s_per_step, _, kept) = time_stage(stage, cfg, model, tmp, steps, device)?;
        // A stage that keeps volumes computes them in its first epoch alone.
        out[i] = match cfg.stage(stage).cache_volumes {
            true => kept,
            false => s_per_step,
        };
    }
    Ok(out)
}

/// One stage trained alone for the warm-up and `steps` timed steps: its table line (without the stage,
/// the path and the peak), its median seconds per step, the peak of host memory allocated, bytes, and
/// the median of a step's seconds less its `volumes` phase.
fn time_stage(
    stage: Stage,
    cfg: &TrainConfig,
    model: &mvmp_model::ModelConfig,
    tmp: &Path,
    steps: usize,
    device: &Device,
) -> Result<(String, f64, usize, f64)> {
    let mut c = cfg.clone();
    // Only this stage trains, one epoch of exactly the steps timed whatever the set's size (frames
    // repeat when the set is smaller), and validation at its end reads one frame.
    let (this, other) = if stage == Stage::Detection {
        (&mut c.stage1, &mut c.stage2)
    } else {
        (&mut c.stage2, &mut c.stage1)
    };
    this.epochs = 1;
    other.epochs = 0;
    c.epoch_frames = (WARM_UP + steps) * c.batch_size;
    c.val_frames = 1;
    let run_dir = tempfile::tempdir_in(tmp).context("creating a temporary run directory")?;
    let run = RunDir::create(&run_dir.path().join("run"), &c, model, None)?;
    let (run, c, m) = RunDir::open(&run.root)?;
    let opts = TrainOptions {
        device: device.clone(),
        stop: Default::default(),
        stop_after_steps: Some((WARM_UP + steps) as u64),
        stop_after_time: None,
    };
    eprintln!("stage {}: {} steps", stage.number(), WARM_UP + steps);
    let base = crate::GLOBAL.reset_peak();
    mvmp_train::train(&run, &c, &m, &opts, &mut mvmp_train::Quiet)?;
    let peak = crate::GLOBAL.peak().saturating_sub(base);
    let (line, s_per_step, kept) = row(&run.metrics_path())?;
    Ok((line, s_per_step, peak, kept))
}

/// The demo's configs and synthetic set (with `scenes` scenes) under `dir`: (training config, dataset).
fn demo_setup(
    dir: &Path,
    args: &BenchTrainArgs,
) -> Result<(std::path::PathBuf, Option<std::path::PathBuf>)> {
    write_demo_configs(dir, args.scenes)?;
    let data = match args.data {
        Some(d) => d.to_path_buf(),
        None => {
            // Standard output carries the table alone.
            let d = dir.join("data");
            let cfg = mvmp_data::synth::SynthConfig::read(&dir.join("synth.toml"))?;
            eprintln!("synthesising {} scenes", cfg.scenes);
            mvmp_data::synth::generate(&cfg, &d, dir, &|| {})?;
            d
        }
    };
    Ok((dir.join("train.toml"), Some(data)))
}

/// One stage's line of the table (from the steps column on), its median seconds per step and the median
/// of a step's seconds less its `volumes` phase: the medians of the steps after the warm-up in its log.
fn row(log: &Path) -> Result<(String, f64, f64)> {
    let text =
        std::fs::read_to_string(log).with_context(|| format!("reading {}", log.display()))?;
    let steps: Vec<Value> = text
        .lines()
        .filter_map(|l| serde_json::from_str::<Value>(l).ok())
        .filter(|v| v["kind"] == "step")
        .skip(WARM_UP)
        .collect();
    anyhow::ensure!(
        !steps.is_empty(),
        "no step after the warm-up in {} (too few training frames?)",
        log.display()
    );
    let med = |f: &dyn Fn(&Value) -> Option<f64>| median(steps.iter().filter_map(f).collect());
    let seconds = med(&|v| v["seconds"].as_f64());
    let mut line = format!("{:>5}  {seconds:>6.3}", steps.len());
    for p in PHASES {
        let width = p.len().max(5);
        let m = med(&|v| v["phase_seconds"][p].as_f64());
        line += &match m.is_nan() {
            true => format!("  {:>width$}", "-"),
            false => format!("  {m:>width$.3}"),
        };
    }
    let kept = med(&|v| {
        let volumes = v["phase_seconds"]["volumes"].as_f64().unwrap_or(0.0);
        Some(v["seconds"].as_f64()? - volumes)
    });
    Ok((line, seconds, kept))
}

fn median(mut x: Vec<f64>) -> f64 {
    if x.is_empty() {
        return f64::NAN;
    }
    x.sort_by(f64::total_cmp);
    let n = x.len();
    if n % 2 == 1 {
        x[n / 2]
    } else {
        0.5 * (x[n / 2 - 1] + x[n / 2])
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn median_of_odd_and_even_counts() {
        assert_eq!(super::median(vec![3.0, 1.0, 2.0]), 2.0);
        assert_eq!(super::median(vec![4.0, 1.0, 2.0, 3.0]), 2.5);
        assert!(super::median(vec![]).is_nan());
    }
}
