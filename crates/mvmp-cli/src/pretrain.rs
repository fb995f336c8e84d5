//! `mvmp bench learn --pretrain-hrnet SCENES,EPOCHS`: the HRNet every variant starts from, pretrained by
//! the benchmark itself. The paper's comparisons all start from one backbone pretrained on 2D pose; the
//! reference weights are not at hand, so the benchmark pretrains on a synthetic set of its own recipe
//! with the next seed (no scene repeats the benchmark's): stage 1 alone, HRNet taken out of the run
//! (docs/learning.md, The full model from a pretrained HRNet).
use std::path::{Path, PathBuf};

use anyhow::{Context, Result, bail};
use burn::tensor::Device;

use mvmp_io::write_atomic;
use mvmp_train::TrainConfig;

use crate::run::write_demo_configs;

/// Where the benchmark pretrains (`OUT/pretrain`): its configs, set, run and the HRNet it gives.
const DIR: &str = "pretrain";

/// The `--pretrain-hrnet` given: the pretraining set's scenes (at least 3: one is held out) and stage
/// 1's epochs (at least 1).
pub fn parse(given: &[usize]) -> Result<[usize; 2]> {
    match given {
        &[scenes, epochs] if scenes >= 3 && epochs > 0 => Ok([scenes, epochs]),
        _ => bail!(
            "--pretrain-hrnet: give the pretraining set's scenes (at least 3) and stage 1's epochs (at \
             least 1) as `SCENES,EPOCHS` (e.g. 1152,12); got {given:?}"
        ),
    }
}

/// The HRNet weights a benchmark in `out` pretrains (absolute, so that the variants' configs find it).
pub fn hrnet_file(out: &Path) -> Result<PathBuf> {
    let file = out.join(DIR).join("hrnet.bpk");
    std::path::absolute(&file).with_context(|| format!("resolving {}", file.display()))
}

/// Pretrain HRNet for the benchmark in `out`, unless it is done: the set (made once), stage 1 alone
/// for `epochs` (a stopped pretraining resumes from its checkpoint), then HRNet written to
/// [`hrnet_file`].
pub fn pretrain_hrnet(out: &Path, [scenes, epochs]: [usize; 2], device: &Device) -> Result<()> {
    let file = hrnet_file(out)?;
    if file.exists() {
        return Ok(());
    }
    let dir = out.join(DIR);
    let (cfg_dir, data, run) = (dir.join("configs"), dir.join("data"), dir.join("run"));
    std::fs::create_dir_all(&cfg_dir).with_context(|| format!("creating {}", cfg_dir.display()))?;
    write_demo_configs(&cfg_dir, scenes)?;
    // The set is staged and renamed whole: one that exists is complete.
    if !data.exists() {
        let mut synth = mvmp_data::synth::SynthConfig::read(&cfg_dir.join("synth.toml"))?;
        synth.seed += 1;
        eprintln!(
            "pretraining set ({scenes} scenes, seed {}) -> {}",
            synth.seed,
            data.display()
        );
        mvmp_data::synth::generate(&synth, &data, &cfg_dir, &|| {})?;
    }
    let config = cfg_dir.join("pretrain.toml");
    let (mut train, _) = TrainConfig::read(&cfg_dir.join("train.toml"))?;
    train.stage1.epochs = epochs;
    train.stage2.epochs = 0;
    write_atomic(&config, toml::to_string(&train)?.as_bytes())?;
    train_stage1(&run, &config, &data, device)?;
    eprintln!("[pretrain] HRNet -> {}", file.display());
    crate::model::extract(&run, true, &file)
}

/// Train the pretraining run to its end: new, or on from its checkpoint (a directory without one
/// starts again).
fn train_stage1(run: &Path, config: &Path, data: &Path, device: &Device) -> Result<()> {
    let state = match run.join("state.json").exists() {
        true => mvmp_train::RunDir::open(run)?.0.state()?,
        false => None,
    };
    if state.as_ref().is_some_and(|s| s.finished) {
        return Ok(());
    }
    if run.exists() && state.is_none() {
        std::fs::remove_dir_all(run)
            .with_context(|| format!("removing {} (no checkpoint)", run.display()))?;
    }
    let resumed = state.is_some();
    eprintln!("[pretrain] stage 1 -> {}", run.display());
    crate::train::train(
        crate::train::TrainArgs {
            config: (!resumed).then_some(config),
            data: (!resumed).then_some(data),
            out: Some(run),
            resume: resumed.then_some(run),
            from_stage1: None,
            stop_after_steps: None,
            stop_after_minutes: None,
            resumable: false,
        },
        device,
        &mut crate::train::BarMonitor::new(true),
    )?;
    if let Some(signal) = crate::interrupt::received() {
        bail!("[pretrain] stopped by signal {signal}");
    }
    Ok(())
}
