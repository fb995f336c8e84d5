//! `mvmp model fit-decoder`: the run's decoder alone, fitted to a joint volume at the true roots and
//! headings (`mvmp_train::decoder_fit`).
use std::path::Path;

use anyhow::{Result, bail};
use burn::tensor::Device;

use mvmp_data::loader::Split;
use mvmp_infer::Predictor;
use mvmp_model::ModelConfig;
use mvmp_train::RunDir;
use mvmp_train::decoder_fit::{FitLoss, FitOptions, FitPoint, JointMaps, fit, frames};

pub struct FitArgs<'a> {
    pub run: &'a Path,
    pub data: &'a Path,
    pub maps: JointMaps,
    pub loss: FitLoss,
    pub steps: usize,
    pub lr: Option<f64>,
    pub test_frames: usize,
    pub every: usize,
    pub decoder: Option<&'a Path>,
    pub out: Option<&'a Path>,
}

pub fn fit_decoder(args: &FitArgs, device: &Device) -> Result<()> {
    crate::paths::out_dir_exists(args.out)?;
    let (_, tcfg, mcfg) = RunDir::open(args.run)?;
    let (pred, _) = Predictor::from_run(args.run, device)?;
    let mcfg = match args.decoder {
        Some(path) => decoder_from(path, &mcfg)?,
        None => mcfg,
    };
    let opts = FitOptions {
        maps: args.maps,
        loss: args.loss,
        steps: args.steps,
        lr: args.lr.unwrap_or(tcfg.stage2.lr),
        views: tcfg.test_views,
        test_frames: args.test_frames,
        sigma: tcfg.loss.heatmap_sigma,
        seed: tcfg.seed,
        every: args.every,
    };
    let train = frames(&pred.model, args.data, Split::Train, 0, &opts, device)?;
    let test = frames(
        &pred.model,
        args.data,
        Split::Test,
        opts.test_frames,
        &opts,
        device,
    )?;
    if train.is_empty() || test.is_empty() {
        bail!(
            "{}: the train and test splits need people whose heading the annotation gives ({} and {} frames have)",
            args.data.display(),
            train.len(),
            test.len()
        );
    }
    println!(
        "{} training and {} held-out frames; {:?} maps, {:?} loss, {} steps at {}",
        train.len(),
        test.len(),
        opts.maps,
        opts.loss,
        opts.steps,
        opts.lr
    );
    if let Some(path) = args.decoder {
        println!("the decoder of {}", path.display());
    }
    let points = fit(&mcfg, &train, &test, &opts, |p: FitPoint| {
        println!(
            "step {:>7}: body rotations {:.2} deg from the truth held out, {:.2} on training frames",
            p.step, p.held_out_deg, p.train_deg
        );
    })?;
    if let Some(out) = args.out {
        let report = serde_json::json!({
            "run": args.run, "data": args.data, "maps": format!("{:?}", opts.maps).to_lowercase(),
            "loss": format!("{:?}", opts.loss).to_lowercase(), "steps": opts.steps, "lr": opts.lr,
            "decoder": args.decoder, "train_frames": train.len(), "test_frames": test.len(), "points": points,
        });
        mvmp_io::write_atomic_with(out, |w| {
            serde_json::to_writer_pretty(&mut *w, &report).map_err(std::io::Error::other)
        })?;
    }
    Ok(())
}

/// The model config at `path`, whose decoder is fitted to volumes made as `run`'s model makes them: it
/// must have `run`'s grid and heatmap joints.
fn decoder_from(path: &Path, run: &ModelConfig) -> Result<ModelConfig> {
    let cfg = ModelConfig::read(path)?;
    if cfg.grid != run.grid {
        bail!(
            "{}: `grid` {:?} is not the run's {:?} (--decoder reads the run's volumes)",
            path.display(),
            cfg.grid,
            run.grid
        );
    }
    if cfg.heatmap_joints != run.heatmap_joints {
        bail!(
            "{}: `heatmap_joints` {:?} are not the run's {:?} (--decoder reads the run's volumes)",
            path.display(),
            cfg.heatmap_joints,
            run.heatmap_joints
        );
    }
    Ok(cfg)
}
