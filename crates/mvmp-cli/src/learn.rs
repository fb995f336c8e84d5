//! `mvmp bench learn`: the full model and the paper's comparisons (the VoxelSMPLX baseline, max and
//! deformable fusion, without the orientation loss, without the density loss, the head and spine root
//! variants) trained on one synthetic set with one schedule, sized so that the full model takes about the
//! wall time given, and scored on its held-out scenes.
//! Writes a table and the validation curves of every variant (`learning.md`, `curves.png`) and says
//! whether each of the paper's directions reproduces. A benchmark, not a test: its figures depend on the
//! machine and the time given.
use std::path::Path;

use anyhow::{Context, Result, bail};
use burn::tensor::Device;

use mvmp_data::loader::Split;
use mvmp_eval::Metrics;
use mvmp_fusion::FusionMode;
use mvmp_io::write_atomic;
use mvmp_model::ModelConfig;
use mvmp_model::config::PrimaryJoint;
use mvmp_train::TrainConfig;
use mvmp_train::curves::{Curves, write_png};

use crate::run::{EvalArgs, Source, eval, table, write_demo_configs};

/// One configuration of the comparison: a name and its change to the demo's tiny configs.
struct Variant {
    name: &'static str,
    edit: fn(&mut TrainConfig, &mut ModelConfig),
}

const VARIANTS: [Variant; 8] = [
    Variant {
        name: "full",
        edit: |_, _| {},
    },
    Variant {
        name: "voxelsmplx",
        edit: |_, m| m.decoder.use_htb = false,
    },
    Variant {
        name: "fusion_max",
        edit: |_, m| m.fusion = FusionMode::Max,
    },
    Variant {
        name: "fusion_deformable",
        edit: |_, m| m.fusion = FusionMode::Deformable,
    },
    Variant {
        name: "no_orientation",
        edit: |t, _| t.loss.orientation = 0.0,
    },
    Variant {
        name: "no_density",
        edit: |t, _| t.loss.density = 0.0,
    },
    Variant {
        name: "root_head",
        edit: |_, m| m.primary_joint = PrimaryJoint::Head,
    },
    Variant {
        name: "root_spine",
        edit: |_, m| m.primary_joint = PrimaryJoint::Spine,
    },
];

/// Timed steps per stage when the benchmark measures this machine's step times before it sizes the
/// schedule (after `bench_train`'s warm-up steps).
const CALIBRATION_STEPS: usize = 6;
/// The part of the training time that is not steps (validation after every epoch).
const VALIDATION_SHARE: f64 = 0.15;
/// Stage 1's part of the steps' time. HRNet and the facing head learn only slowly, and a stage-1 step
/// costs about half a stage-2 one: on the demo's data, 4 stage-1 and 3 stage-2 epochs (about 40% of the
/// steps' time in stage 1) gave a lower held-out MPJPE than 1 and 4 (14%) in about the same time, through
/// the body's heading (docs/architecture.md, Stage 1's share of the schedule).
const STAGE1_SHARE: f64 = 0.4;
/// Every variant trains the same schedule, so that a variant slower per step (deformable fusion) or a
/// machine busy with something else does not cut one variant's schedule short and not another's. This
/// many times the time given stops a variant that is far slower (or starved by other work: the guard
/// counts wall time); the report marks it and leaves it out of the paper's directions.
const TIME_GUARD: f64 = 2.0;

pub struct LearnArgs<'a> {
    pub out: &'a Path,
    pub minutes: f64,
    pub scenes: usize,
    /// Comma-separated variant names (default: all).
    pub variants: Option<&'a str>,
    /// The training seeds every variant runs with (each a run of its own).
    pub seeds: &'a [u64],
    /// Epochs of stage 1 and 2, fixed instead of sized from `minutes`: benchmarks on machines of other
    /// speeds then train the same steps and compare.
    pub epochs: Option<&'a [usize]>,
    /// HRNet weights every variant starts from (`[init] hrnet`), as the paper's comparisons all start
    /// from one pretrained backbone.
    pub init_hrnet: Option<&'a Path>,
    /// Every variant trains by [`kept_volumes_recipe`].
    pub kept_volumes: bool,
    /// Pretrain the HRNet every variant starts from: the pretraining set's scenes and stage 1's epochs
    /// (`crate::pretrain`).
    pub pretrain: Option<&'a [usize]>,
}

/// What a benchmark trains, fixed once it has measured its step times (`OUT/plan.json`): a stopped
/// benchmark goes on from it ([`resume_learn`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Plan {
    minutes: f64,
    scenes: usize,
    variants: Vec<String>,
    seeds: Vec<u64>,
    /// Frames of the training split.
    train_frames: usize,
    /// Epochs of stage 1 and 2 every variant trains.
    epochs: [usize; 2],
    /// The full model's seconds per step of each stage, measured before the plan was made.
    step_seconds: [f64; 2],
    /// Whether `epochs` were given (`--epochs`) rather than sized to `minutes`, which is then the time
    /// they take at `step_seconds` (absent in plans of earlier versions: sized).
    #[serde(default)]
    fixed_epochs: bool,
    /// The HRNet weights every variant starts from (absolute; absent: from scratch).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    init_hrnet: Option<String>,
    /// Whether every variant trains by [`kept_volumes_recipe`] (absent in plans of earlier versions:
    /// not).
    #[serde(default)]
    kept_volumes: bool,
    /// The pretraining set's scenes and stage 1's epochs when the benchmark pretrains the HRNet that
    /// `init_hrnet` names (absent: given, or none).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pretrain: Option<[usize; 2]>,
}

const PLAN: &str = "plan.json";
/// A run's figures once it is trained and scored (`runs/RUN/bench.json`).
const SCORED: &str = "bench.json";
/// Minutes a run trained before the benchmark was stopped (`runs/RUN/bench-minutes.json`).
const PARTIAL: &str = "bench-minutes.json";
/// The run whose stage 1 a run went on from (`runs/RUN/bench-stage1.json`).
const SHARED: &str = "bench-stage1.json";

/// A trained and scored run, as `runs/RUN/bench.json` keeps it.
#[derive(serde::Serialize, serde::Deserialize)]
struct Scored {
    steps: u64,
    minutes: f64,
    metrics: Metrics,
    /// Whether the run trained its whole schedule (absent in runs scored by earlier versions).
    #[serde(default)]
    finished: Option<bool>,
    /// The run whose stage 1 it went on from (absent: its own).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    stage1_from: Option<String>,
}

/// The name of one variant's run with one seed: the variant's own when the benchmark runs one seed.
fn label(name: &str, seed: u64, seeds: &[u64]) -> String {
    match seeds {
        [_] => name.to_string(),
        _ => format!("{name}-s{seed}"),
    }
}

/// The decoder-alone recipe (`--kept-volumes`): the decoder's `pose_trunk`, and a stage 2 that keeps
/// the ViT and detection fixed and each training frame's volumes from its first decoding
/// (`freeze_backbone`, `freeze_detection`, `cache_volumes`; no `detection_lr`, which would train
/// nothing). A kept-volumes step costs about a fifth of a whole-model one, so the same minutes buy the
/// decoder four times the steps (docs/learning.md, The decoder alone on kept volumes).
fn kept_volumes_recipe(t: &mut TrainConfig, m: &mut ModelConfig) {
    m.decoder.pose_trunk = true;
    t.stage2.freeze_backbone = true;
    t.stage2.freeze_detection = true;
    t.stage2.cache_volumes = true;
    t.stage2.detection_lr = None;
}

/// The benchmark's base configs (`OUT/configs`), with the plan's recipe.
fn base_configs(out: &Path, kept_volumes: bool) -> Result<(TrainConfig, ModelConfig)> {
    let (mut t, mut m) = TrainConfig::read(&out.join("configs").join("train.toml"))?;
    if kept_volumes {
        kept_volumes_recipe(&mut t, &mut m);
    }
    Ok((t, m))
}

fn select(list: Option<&str>) -> Result<Vec<&'static Variant>> {
    let Some(list) = list else {
        return Ok(VARIANTS.iter().collect());
    };
    list.split(',')
        .map(|name| {
            VARIANTS
                .iter()
                .find(|v| v.name == name.trim())
                .with_context(|| {
                    let names: Vec<&str> = VARIANTS.iter().map(|v| v.name).collect();
                    format!(
                        "--variants: unknown variant {name:?}; expected some of {}",
                        names.join(", ")
                    )
                })
        })
        .collect()
}

/// Epochs of each stage that fill `minutes` at `step_s` seconds per step of stage 1 and 2: stage 1
/// [`STAGE1_SHARE`] of the steps' time (at least one epoch), stage 2 what is left (at least one).
fn epochs(minutes: f64, train_frames: usize, step_s: [f64; 2]) -> (usize, usize) {
    let seconds = minutes * 60.0 * (1.0 - VALIDATION_SHARE);
    let epoch_s = step_s.map(|s| s * train_frames as f64);
    let e1 = (seconds * STAGE1_SHARE / epoch_s[0]).round().max(1.0);
    let e2 = ((seconds - e1 * epoch_s[0]) / epoch_s[1]).round().max(1.0);
    (e1 as usize, e2 as usize)
}

/// Minutes the full model takes for `epochs` of each stage at `step_s` seconds per step, validation
/// included: the time a fixed schedule is given (and its guard counted from).
fn schedule_minutes(epochs: [usize; 2], train_frames: usize, step_s: [f64; 2]) -> f64 {
    let steps_s: f64 = (0..2)
        .map(|i| epochs[i] as f64 * train_frames as f64 * step_s[i])
        .sum();
    steps_s / (1.0 - VALIDATION_SHARE) / 60.0
}

/// The `--epochs` given: two counts, stage 1 and stage 2, each at least 1.
fn fixed_epochs(given: &[usize]) -> Result<[usize; 2]> {
    match given {
        &[e1, e2] if e1 > 0 && e2 > 0 => Ok([e1, e2]),
        _ => bail!(
            "--epochs: give the epochs of stage 1 and stage 2, each at least 1, as `S1,S2` (e.g. 3,3); \
             got {given:?}"
        ),
    }
}

/// The figures of one trained variant with one seed.
struct Row {
    name: &'static str,
    seed: u64,
    /// The run's name ([`label`]).
    run: String,
    metrics: Metrics,
    steps: u64,
    minutes: f64,
    /// Whether the run trained its whole schedule; `Some(false)`: the time guard stopped it.
    finished: Option<bool>,
    /// The run whose stage 1 it went on from.
    stage1_from: Option<String>,
}

pub fn bench_learn(args: &LearnArgs, device: &Device) -> Result<()> {
    let out = args.out;
    let existed = out.exists();
    if existed && std::fs::read_dir(out)?.next().is_some() {
        bail!(
            "{} exists and is not empty: pass --out to a new directory (or --resume to go on with a \
             stopped benchmark there)",
            out.display()
        );
    }
    // The benchmark writes in place (its runs can be watched as they train). Until its plan is made, a
    // failure or an interrupt removes what it wrote; from then on it keeps what is done, to go on from.
    crate::interrupt::unfinished_output(out, existed);
    let result = plan_and_run(args, device);
    crate::interrupt::finished(out);
    result.map_err(|err| {
        if out.join(PLAN).exists() {
            return kept(out, err);
        }
        match crate::interrupt::clear(out, existed) {
            Ok(()) => anyhow::anyhow!(
                "{} (what was written under {} was removed)",
                crate::report::message(&err),
                out.display()
            ),
            Err(e) => anyhow::anyhow!(
                "{} (removing what was written under {} failed too: {e})",
                crate::report::message(&err),
                out.display()
            ),
        }
    })
}

/// Go on with the benchmark stopped in `out`: its runs scored stay, a run stopped resumes from its
/// checkpoint, and the rest train as planned. `more` adds variants to the plan (comma-separated), trained
/// on its schedule: a benchmark of the full model alone can take its comparisons later.
pub fn resume_learn(out: &Path, more: Option<&str>, device: &Device) -> Result<()> {
    let path = out.join(PLAN);
    let text = std::fs::read_to_string(&path).with_context(|| {
        format!(
            "{}: cannot read the plan of a stopped benchmark (start one with --out instead)",
            path.display()
        )
    })?;
    let mut plan: Plan =
        serde_json::from_str(&text).with_context(|| format!("{}: not a plan", path.display()))?;
    let mut variants = select(Some(&plan.variants.join(",")))
        .with_context(|| format!("{}: key `variants`", path.display()))?;
    if plan.seeds.is_empty() || plan.epochs.contains(&0) {
        bail!(
            "{}: key `seeds` is empty or `epochs` holds 0 ({:?}, {:?})",
            path.display(),
            plan.seeds,
            plan.epochs
        );
    }
    // Only a usable plan takes more variants.
    if let Some(more) = more {
        variants = with_added(&variants, &select(Some(more))?);
        plan.variants = variants.iter().map(|v| v.name.to_string()).collect();
        write_atomic(&path, serde_json::to_string_pretty(&plan)?.as_bytes())?;
    }
    eprintln!("resuming the benchmark in {}", out.display());
    run_plan(out, &plan, &variants, device).map_err(|e| kept(out, e))
}

/// The variants of `planned` and of `more`, each once, in the benchmark's own order.
fn with_added(planned: &[&'static Variant], more: &[&'static Variant]) -> Vec<&'static Variant> {
    let named = |v: &Variant| planned.iter().chain(more).any(|p| p.name == v.name);
    VARIANTS.iter().filter(|v| named(v)).collect()
}

/// `err` of a benchmark whose plan is made: what is done stays to go on from.
fn kept(out: &Path, err: anyhow::Error) -> anyhow::Error {
    anyhow::anyhow!(
        "{} (the runs done and the checkpoints of the one stopped stay under {}; `mvmp bench \
         learn --resume --out {}` goes on)",
        crate::report::message(&err),
        out.display(),
        out.display()
    )
}

fn plan_and_run(args: &LearnArgs, device: &Device) -> Result<()> {
    let out = args.out;
    let variants = select(args.variants)?;
    let fixed = args.epochs.map(fixed_epochs).transpose()?;
    let pretrain = args.pretrain.map(crate::pretrain::parse).transpose()?;
    for (i, seed) in args.seeds.iter().enumerate() {
        if args.seeds[..i].contains(seed) {
            bail!("--seeds: seed {seed} is given twice");
        }
    }
    let cfg_dir = out.join("configs");
    std::fs::create_dir_all(&cfg_dir).with_context(|| format!("creating {}", cfg_dir.display()))?;
    write_demo_configs(&cfg_dir, args.scenes)?;
    let (base_train, base_model) = base_configs(out, args.kept_volumes)?;
    let init_hrnet = match pretrain {
        Some(_) => Some(
            crate::pretrain::hrnet_file(out)?
                .to_string_lossy()
                .into_owned(),
        ),
        None => args
            .init_hrnet
            .map(|f| checked_hrnet(f, &base_model))
            .transpose()?,
    };
    let data = out.join("data");
    eprintln!(
        "synthetic dataset ({} scenes) -> {}",
        args.scenes,
        data.display()
    );
    crate::data::synth(&cfg_dir.join("synth.toml"), &data)?;
    let layout = mvmp_data::DatasetLayout::open(&data)?;
    let train_frames = mvmp_data::loader::split_scenes(&layout, Split::Train)?
        .iter()
        .map(|&s| layout.scenes[s].index.frames.len())
        .sum::<usize>();
    let step_s = calibrate(&base_train, &base_model, &data, device)?;
    let ([e1, e2], minutes) = match fixed {
        Some(e) => (e, schedule_minutes(e, train_frames, step_s)),
        None => (
            epochs(args.minutes, train_frames, step_s).into(),
            args.minutes,
        ),
    };
    let plan = Plan {
        minutes,
        scenes: args.scenes,
        variants: variants.iter().map(|v| v.name.to_string()).collect(),
        seeds: args.seeds.to_vec(),
        train_frames,
        epochs: [e1, e2],
        step_seconds: step_s,
        fixed_epochs: fixed.is_some(),
        init_hrnet,
        kept_volumes: args.kept_volumes,
        pretrain,
    };
    write_atomic(
        &out.join(PLAN),
        serde_json::to_string_pretty(&plan)?.as_bytes(),
    )?;
    // From here on, what is done is kept to go on from: an interrupt no longer removes it.
    crate::interrupt::finished(out);
    run_plan(out, &plan, &variants, device)
}

fn run_plan(out: &Path, plan: &Plan, variants: &[&'static Variant], device: &Device) -> Result<()> {
    if let Some(pretrain) = plan.pretrain {
        crate::pretrain::pretrain_hrnet(out, pretrain, device)?;
    }
    let cfg_dir = out.join("configs");
    let (base_train, base_model) = base_configs(out, plan.kept_volumes)?;
    let [e1, e2] = plan.epochs;
    eprintln!(
        "each variant: {e1} + {e2} epochs of {} frames (about {:.1} min for the full model at {:.3} and \
         {:.3} s per step, measured here), stopped at {:.1} min",
        plan.train_frames,
        plan.minutes,
        plan.step_seconds[0],
        plan.step_seconds[1],
        plan.minutes * TIME_GUARD
    );
    let mut planned: Vec<Planned> = Vec::new();
    for v in variants {
        for &seed in &plan.seeds {
            let (mut t, mut m) = (base_train.clone(), base_model.clone());
            t.stage1.epochs = e1;
            t.stage2.epochs = e2;
            t.seed = seed;
            t.init.hrnet = plan.init_hrnet.clone();
            (v.edit)(&mut t, &mut m);
            let run = label(v.name, seed, &plan.seeds);
            let dir = cfg_dir.join(&run);
            std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
            write_atomic(&dir.join("model.toml"), toml::to_string(&m)?.as_bytes())?;
            t.model = "model.toml".into();
            write_atomic(&dir.join("train.toml"), toml::to_string(&t)?.as_bytes())?;
            // The first run planned is the one of its group that trains stage 1.
            let donor = planned
                .iter()
                .position(|p| p.model == m && t.same_stage1(&p.train));
            planned.push(Planned {
                name: v.name,
                seed,
                run,
                train: t,
                model: m,
                donor,
            });
        }
    }
    let mut rows = Vec::new();
    let mut curves = Vec::new();
    for (i, p) in planned.iter().enumerate() {
        let share = match p.donor {
            Some(d) => Share::Takes(&planned[d].run),
            None if planned.iter().any(|q| q.donor == Some(i)) => Share::Gives,
            None => Share::Alone,
        };
        rows.push(train_and_score(
            p.name, p.seed, &p.run, out, plan, share, device,
        )?);
        let log = std::fs::read_to_string(out.join("runs").join(&p.run).join("metrics.jsonl"))?;
        curves.push((p.run.clone(), Curves::from_log(&log)));
    }
    let picture = Curves::compare(
        &curves,
        "stage 2 total",
        "stage 2 mpjpe_mm",
        "stage 2 recall_500",
    );
    write_png(&picture, &out.join("curves.png"))?;
    let report = report(&rows, plan);
    write_atomic(&out.join("learning.md"), report.as_bytes())?;
    print!("{report}");
    eprintln!(
        "written: {}, {}",
        out.join("learning.md").display(),
        out.join("curves.png").display()
    );
    Ok(())
}

/// `--init-hrnet FILE` made absolute, once it has loaded into the benchmark's model: a file that does
/// not fit is named before the set is made and the step times are measured.
fn checked_hrnet(file: &Path, model: &ModelConfig) -> Result<String> {
    let abs = std::path::absolute(file)
        .with_context(|| format!("--init-hrnet {}", file.display()))?
        .to_string_lossy()
        .into_owned();
    let init = mvmp_train::config::InitWeights {
        hrnet: Some(abs.clone()),
        vit: None,
    };
    mvmp_train::init::load_init(&mut model.init(&Device::flex()), &init)
        .with_context(|| format!("--init-hrnet {}", file.display()))?;
    Ok(abs)
}

/// This machine's seconds per step of each stage of the full model on the benchmark's set: the
/// schedule is sized from them, so that `--minutes` holds on fast and slow machines alike.
fn calibrate(
    train: &TrainConfig,
    model: &ModelConfig,
    data: &Path,
    device: &Device,
) -> Result<[f64; 2]> {
    let mut cfg = train.clone();
    let data =
        std::fs::canonicalize(data).with_context(|| format!("resolving {}", data.display()))?;
    cfg.data = Some(data.to_string_lossy().into_owned());
    let tmp = tempfile::tempdir().context("creating a temporary directory")?;
    eprintln!("measuring this machine's step times ({CALIBRATION_STEPS} steps per stage)");
    crate::bench_train::step_seconds(&cfg, model, tmp.path(), CALIBRATION_STEPS, device)
}

/// Read a JSON file the benchmark wrote, naming it in the error.
fn read_json<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
    serde_json::from_str(&text).with_context(|| format!("{}: malformed", path.display()))
}

/// One run the benchmark trains: its variant, seed, name and configs, and the earlier run whose stage 1
/// it shares (its configs train stage 1 alike: [`TrainConfig::same_stage1`]).
struct Planned {
    name: &'static str,
    seed: u64,
    run: String,
    train: TrainConfig,
    model: ModelConfig,
    donor: Option<usize>,
}

/// A run's part in sharing stage 1: it trains its own and none take it, it trains its own and others
/// take it (`OUT/stage1/RUN` keeps it at its end), or it takes another run's.
#[derive(Debug, Clone, Copy)]
enum Share<'a> {
    Alone,
    Gives,
    Takes(&'a str),
}

/// Runs at the end of stage 1 (`OUT/stage1/RUN`), for the runs that share it to branch from.
const STAGE1: &str = "stage1";

/// Train one variant on the benchmark's schedule (at most [`TIME_GUARD`] times the time given), then
/// score it on the held-out scenes. A run scored before is read back; a run stopped before resumes
/// from its checkpoint (a run directory without one starts again). Its configs are `OUT/configs/RUN`.
/// A run that takes another's stage 1 starts from that run's copy at the end of it, its minutes
/// counted in; one whose stage 1 others take makes that copy on the way.
fn train_and_score(
    name: &'static str,
    seed: u64,
    run: &str,
    out: &Path,
    plan: &Plan,
    share: Share,
    device: &Device,
) -> Result<Row> {
    let run_dir = out.join("runs").join(run);
    let row = |s: Scored| Row {
        name,
        seed,
        run: run.to_string(),
        metrics: s.metrics,
        steps: s.steps,
        minutes: s.minutes,
        finished: s.finished,
        stage1_from: s.stage1_from,
    };
    if run_dir.join(SCORED).exists() {
        eprintln!("[{run}] trained and scored before");
        return Ok(row(read_json(&run_dir.join(SCORED))?));
    }
    if run_dir.exists() && !run_dir.join("state.json").exists() {
        std::fs::remove_dir_all(&run_dir)
            .with_context(|| format!("removing {} (no checkpoint)", run_dir.display()))?;
    }
    let stage1_from = match share {
        Share::Takes(donor) => take_stage1(out, donor, run)?,
        _ => None,
    };
    if let Share::Gives = share {
        give_stage1(out, run, plan, device)?;
    }
    let minutes = train_for(out, run, plan, None, device)?;
    let (opened, _, _) = mvmp_train::RunDir::open(&run_dir)?;
    let state = opened.state()?;
    let steps = state.as_ref().map_or(0, |s| s.global_step);
    let finished = state.is_some_and(|s| s.finished);
    if !finished {
        eprintln!(
            "[{run}] stopped by the time guard after {steps} steps, short of its schedule: it is scored, \
             and the report leaves it out of the comparisons"
        );
    }
    let report = run_dir.join("eval-test.json");
    let data = out.join("data");
    let eval_args = EvalArgs::held_out(Source::Run(&run_dir), &data, &report);
    let (metrics, _) = eval(&eval_args, device, true)?;
    let scored = Scored {
        steps,
        minutes,
        metrics,
        finished: Some(finished),
        stage1_from,
    };
    write_atomic(
        &run_dir.join(SCORED),
        serde_json::to_string_pretty(&scored)?.as_bytes(),
    )?;
    Ok(row(scored))
}

/// Train `run` (a new run from its configs, or on from its checkpoint) until its schedule ends, the
/// time guard stops it (the minutes it trained before count: `runs/RUN/bench-minutes.json`) or it has
/// trained `steps` steps in all. Returns the minutes it has trained in all.
fn train_for(
    out: &Path,
    run: &str,
    plan: &Plan,
    steps: Option<u64>,
    device: &Device,
) -> Result<f64> {
    let (run_dir, data) = (out.join("runs").join(run), out.join("data"));
    let resumed = run_dir.join("state.json").exists();
    let before: f64 = match run_dir.join(PARTIAL).exists() {
        true => read_json(&run_dir.join(PARTIAL))?,
        false => 0.0,
    };
    eprintln!("[{run}] training -> {}", run_dir.display());
    let t0 = std::time::Instant::now();
    let config = out.join("configs").join(run).join("train.toml");
    crate::train::train(
        crate::train::TrainArgs {
            config: (!resumed).then_some(config.as_path()),
            data: (!resumed).then_some(data.as_path()),
            out: Some(&run_dir),
            resume: resumed.then_some(run_dir.as_path()),
            from_stage1: None,
            stop_after_steps: steps,
            stop_after_minutes: Some((plan.minutes * TIME_GUARD - before).max(0.0)),
            resumable: false,
        },
        device,
        &mut crate::train::BarMonitor::new(true),
    )?;
    let minutes = before + t0.elapsed().as_secs_f64() / 60.0;
    // Kept for a resume, should the benchmark stop before the run is scored.
    write_atomic(&run_dir.join(PARTIAL), minutes.to_string().as_bytes())?;
    if let Some(signal) = crate::interrupt::received() {
        bail!("[{run}] stopped by signal {signal} after {minutes:.1} minutes of training");
    }
    Ok(minutes)
}

/// Train `run` to the end of stage 1 and keep a copy of it there (`OUT/stage1/RUN`, with the minutes
/// it took) for the runs that share its stage 1; nothing when the copy exists or the run is past it.
fn give_stage1(out: &Path, run: &str, plan: &Plan, device: &Device) -> Result<()> {
    let (run_dir, kept) = (out.join("runs").join(run), out.join(STAGE1).join(run));
    // The minutes are written last: a copy without them is unfinished.
    if kept.join(PARTIAL).exists() {
        return Ok(());
    }
    let (train, model) = TrainConfig::read(&out.join("configs").join(run).join("train.toml"))?;
    let steps = (plan.epochs[0] * plan.train_frames.div_ceil(train.batch_size)) as u64;
    let at = |dir: &Path| -> Result<Option<mvmp_train::RunState>> {
        match dir.join("state.json").exists() {
            true => Ok(mvmp_train::RunDir::open(dir)?.0.state()?),
            false => Ok(None),
        }
    };
    if at(&run_dir)?
        .is_some_and(|s| s.global_step > steps || s.stage != mvmp_train::Stage::Detection)
    {
        return Ok(());
    }
    let minutes = train_for(out, run, plan, Some(steps), device)?;
    if !at(&run_dir)?.is_some_and(|s| s.stage == mvmp_train::Stage::Detection && !s.finished) {
        return Ok(());
    }
    if kept.exists() {
        std::fs::remove_dir_all(&kept)
            .with_context(|| format!("removing {} (unfinished)", kept.display()))?;
    }
    let from = mvmp_train::RunDir { root: run_dir };
    let copy = mvmp_train::RunDir::branch(&from, &kept, &train, &model)?;
    write_atomic(&copy.root.join(PARTIAL), minutes.to_string().as_bytes())?;
    eprintln!(
        "[{run}] stage 1 kept for the runs that share it -> {}",
        kept.display()
    );
    Ok(())
}

/// Start the new run `run` from `donor`'s copy at the end of its stage 1, with the minutes that took;
/// returns the donor's name. Nothing (the run trains its own stage 1) when the run has begun or the
/// donor kept no copy (its time guard stopped it first).
fn take_stage1(out: &Path, donor: &str, run: &str) -> Result<Option<String>> {
    let (run_dir, kept) = (out.join("runs").join(run), out.join(STAGE1).join(donor));
    if run_dir.exists() {
        return Ok(read_json::<Option<String>>(&run_dir.join(SHARED))
            .ok()
            .flatten());
    }
    if !kept.join(PARTIAL).exists() {
        eprintln!("[{run}] {donor} kept no stage 1 to share: training its own");
        return Ok(None);
    }
    let (train, model) = TrainConfig::read(&out.join("configs").join(run).join("train.toml"))?;
    let from = mvmp_train::RunDir { root: kept.clone() };
    mvmp_train::RunDir::branch(&from, &run_dir, &train, &model)?;
    std::fs::copy(kept.join(PARTIAL), run_dir.join(PARTIAL))
        .with_context(|| format!("copying {}", kept.join(PARTIAL).display()))?;
    write_atomic(
        &run_dir.join(SHARED),
        serde_json::to_string(&Some(donor))?.as_bytes(),
    )?;
    eprintln!("[{run}] stage 1 from {donor} (its configs train stage 1 alike)");
    Ok(Some(donor.to_string()))
}

/// MPJPE differences smaller than this are called noise: one run per variant, and on the demo three
/// seeds spanned 5.7 and 16.4 mm (two code versions) while summing the same functions in another order
/// moved one seed by 17.6 mm (README, The two commands).
const NOISE_MM: f64 = 20.0;

/// The rows of one variant, one per seed.
fn seeds_of<'r>(rows: &'r [Row], name: &str) -> Vec<&'r Row> {
    rows.iter().filter(|r| r.name == name).collect()
}

/// The mean of one figure over `rows`; `None` when there are none or one of them lacks it (a seed
/// that found no one leaves the variant unscored, not scored on the others).
fn mean_of(rows: &[&Row], figure: impl Fn(&Metrics) -> Option<f64>) -> Option<f64> {
    let each: Option<Vec<f64>> = rows.iter().map(|r| figure(&r.metrics)).collect();
    let each = each.filter(|e| !e.is_empty())?;
    Some(each.iter().sum::<f64>() / each.len() as f64)
}

/// A variant's MPJPE averaged over its seeds.
fn mean_mpjpe(rows: &[Row], name: &str) -> Option<f64> {
    mean_of(&seeds_of(rows, name), |m| m.mpjpe_mm)
}

/// How `a`'s MPJPE (the mean over seeds) compares with `b`'s: lower by more than [`NOISE_MM`]
/// (`Some(Some(true))`), higher by more (`Some(Some(false))`), within it (`Some(None)`); `None` when
/// either is missing or unscored.
fn lower(rows: &[Row], a: &str, b: &str) -> Option<Option<bool>> {
    let d = mean_mpjpe(rows, b)? - mean_mpjpe(rows, a)?;
    Some((d.abs() > NOISE_MM).then_some(d > 0.0))
}

/// Each variant over its seeds: mean MPJPE, PVE, PA-PVE and recall, and the seeds' MPJPE range.
fn seed_summary(rows: &[Row]) -> String {
    let mut s = format!(
        "{:<20} {:>6} {:>9} {:>15} {:>9} {:>9} {:>8}\n",
        "", "seeds", "MPJPE", "MPJPE range", "PVE", "PA-PVE", "recall"
    );
    let mut names: Vec<&str> = rows.iter().map(|r| r.name).collect();
    names.dedup();
    for name in names {
        let mine = seeds_of(rows, name);
        let mean = |figure: fn(&Metrics) -> Option<f64>, digits: usize| {
            mean_of(&mine, figure).map_or("-".into(), |v| format!("{v:.digits$}"))
        };
        let mpjpe: Option<Vec<f64>> = mine.iter().map(|r| r.metrics.mpjpe_mm).collect();
        let range = mpjpe.map_or("-".into(), |v| {
            let lo = v.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = v.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            format!("{lo:.1}-{hi:.1}")
        });
        s += &format!(
            "{name:<20} {:>6} {:>9} {range:>15} {:>9} {:>9} {:>8}\n",
            mine.len(),
            mean(|m| m.mpjpe_mm, 1),
            mean(|m| m.pve_mm, 1),
            mean(|m| m.pa_pve_mm, 1),
            mean(|m| m.recall_500, 3),
        );
    }
    s
}

/// Whether a run of the variant was stopped by the time guard before its schedule's end.
fn stopped(rows: &[Row], name: &str) -> bool {
    seeds_of(rows, name)
        .iter()
        .any(|r| r.finished == Some(false))
}

/// One line of the report's directions: the verdict over `pairs` (`a` should beat `b`), unless a
/// variant was stopped short of the schedule, which would compare fewer steps with more.
fn direction(rows: &[Row], what: &str, pairs: &[(&str, &str)]) -> String {
    let mut short: Vec<&str> = pairs.iter().flat_map(|&(a, b)| [a, b]).collect();
    short.retain(|n| stopped(rows, n));
    short.dedup();
    if !short.is_empty() {
        return format!(
            "- {what}: not compared ({} stopped by the time guard short of the schedule)\n",
            short.join(", ")
        );
    }
    let each: Vec<_> = pairs.iter().map(|(a, b)| lower(rows, a, b)).collect();
    format!("- {what}: {}\n", verdict(&each))
}

/// One direction's verdict over its pairs: every pair must go the paper's way by more than the noise.
fn verdict(each: &[Option<Option<bool>>]) -> &'static str {
    if each.iter().any(Option::is_none) {
        return "not measured (a variant missing or unscored)";
    }
    let each: Vec<Option<bool>> = each.iter().map(|v| v.flatten()).collect();
    if each.iter().all(|v| *v == Some(true)) {
        "reproduces"
    } else if each.contains(&Some(false)) {
        "does not reproduce (the opposite, beyond the noise)"
    } else {
        "not distinguished (within the noise)"
    }
}

fn report(rows: &[Row], plan: &Plan) -> String {
    let (frames, [e1, e2], step_s) = (plan.train_frames, plan.epochs, plan.step_seconds);
    let (mut command, sized) = if plan.fixed_epochs {
        (
            format!("--epochs {e1},{e2}"),
            "given; the full model takes about",
        )
    } else {
        (
            format!("--minutes {}", plan.minutes),
            "sized so that the full model takes about",
        )
    };
    let start = match (&plan.init_hrnet, plan.pretrain) {
        (_, Some([scenes, epochs])) => {
            command += &format!(" --pretrain-hrnet {scenes},{epochs}");
            format!(
                "starts from the HRNet the benchmark pretrained ({epochs} stage-1 epochs on {scenes} \
                 scenes of the next seed; `pretrain/hrnet.bpk`) and "
            )
        }
        (Some(f), None) => {
            command += &format!(" --init-hrnet {f}");
            format!("starts from the HRNet weights of {f} and ")
        }
        (None, None) => String::new(),
    };
    let recipe = match plan.kept_volumes {
        true => {
            command += " --kept-volumes";
            " (the decoder's `pose_trunk`; stage 2 trains the decoder alone, on kept volumes)"
        }
        false => "",
    };
    let mut s = format!(
        "# Learning benchmark\n\n`mvmp bench learn {command} --scenes {}`: the tiny model on a synthetic set of {} \
         one-frame scenes ({frames} for training, the rest held out). Every variant {start}trains the same schedule{recipe}, \
         {e1} + {e2} epochs ({sized} {:.1} minutes at the {:.3} and {:.3} s \
         per step of stage 1 and 2 measured on this machine; a variant is stopped at {:.1} minutes), then is \
         scored on the held-out scenes. Errors in mm.\n\n```text\n",
        plan.scenes,
        plan.scenes,
        plan.minutes,
        step_s[0],
        step_s[1],
        plan.minutes * TIME_GUARD
    );
    let named: Vec<(String, Metrics)> = rows
        .iter()
        .map(|r| (r.run.clone(), r.metrics.clone()))
        .collect();
    s += &table(&named);
    if plan.seeds.len() > 1 {
        s += &format!(
            "```\n\nOver the seeds {:?} (means; the range is the seeds' lowest and highest MPJPE):\n\n```text\n",
            plan.seeds
        );
        s += &seed_summary(rows);
    }
    s += "```\n\n| variant | seed | steps | minutes | schedule | stage 1 |\n|---|---|---|---|---|---|\n";
    for r in rows {
        let schedule = match r.finished {
            Some(true) => "trained",
            Some(false) => "stopped by the time guard",
            None => "not recorded",
        };
        let stage1 = match &r.stage1_from {
            Some(run) => format!("{run}'s"),
            None => "its own".into(),
        };
        s += &format!(
            "| {} | {} | {} | {:.1} | {schedule} | {stage1} |\n",
            r.name, r.seed, r.steps, r.minutes
        );
    }
    if rows.iter().any(|r| r.stage1_from.is_some()) {
        s += "\nA run whose configs train stage 1 as an earlier run's do (the loss terms it leaves out are \
              stage 2's) goes on from that run's weights at the end of stage 1 instead of training it \
              again; its minutes count that run's stage 1.\n";
    }
    s += &format!(
        "\nThe paper's directions (MPJPE, the mean over seeds; differences within {NOISE_MM} mm are noise):\n\n"
    );
    for (what, pairs) in [
        (
            "mean fusion beats max and deformable",
            vec![("full", "fusion_max"), ("full", "fusion_deformable")],
        ),
        (
            "the orientation loss lowers MPJPE",
            vec![("full", "no_orientation")],
        ),
        (
            "the density loss lowers MPJPE",
            vec![("full", "no_density")],
        ),
        (
            "the full model beats VoxelSMPLX",
            vec![("full", "voxelsmplx")],
        ),
        (
            "(root joint, the ablation configs) the pelvis beats the head and the spine",
            vec![("full", "root_head"), ("full", "root_spine")],
        ),
    ] {
        s += &direction(rows, what, &pairs);
    }
    s += "\n![validation curves of every variant](curves.png)\n";
    s
}

#[cfg(test)]
mod tests {
    use super::{
        Plan, Row, direction, epochs, fixed_epochs, lower, report, schedule_minutes, seed_summary,
        verdict,
    };
    use mvmp_eval::Metrics;

    fn row(name: &'static str, seed: u64, mpjpe: Option<f64>) -> Row {
        let metrics = Metrics {
            mpjpe_mm: mpjpe,
            pve_mm: mpjpe.map(|m| m - 30.0),
            pa_pve_mm: Some(70.0),
            root_mm: None,
            rr_mpjpe_mm: None,
            pa_mpjpe_mm: None,
            recall_500: Some(0.9 + seed as f64 * 0.02),
            ap: Default::default(),
            matched: 1,
            ground_truth: 1,
            predictions: 1,
        };
        Row {
            name,
            seed,
            run: format!("{name}-s{seed}"),
            metrics,
            steps: 10,
            minutes: 1.0,
            finished: Some(true),
            stage1_from: None,
        }
    }

    #[test]
    fn a_variant_stopped_by_the_time_guard_is_not_compared() {
        let mut rows = vec![
            row("full", 0, Some(150.0)),
            row("fusion_max", 0, Some(185.0)),
            row("fusion_deformable", 0, Some(190.0)),
        ];
        let pairs = [("full", "fusion_max"), ("full", "fusion_deformable")];
        let line = direction(&rows, "mean fusion", &pairs);
        assert_eq!(line, "- mean fusion: reproduces\n");
        rows[2].finished = Some(false);
        let line = direction(&rows, "mean fusion", &pairs);
        assert!(
            line.contains("not compared (fusion_deformable stopped by the time guard"),
            "{line}"
        );
    }

    #[test]
    fn directions_compare_the_means_over_seeds() {
        let rows = [
            row("full", 0, Some(150.0)),
            row("full", 1, Some(170.0)),
            row("fusion_max", 0, Some(185.0)),
            row("fusion_max", 1, Some(195.0)),
            row("voxelsmplx", 0, Some(140.0)),
            row("voxelsmplx", 1, Some(190.0)),
            row("no_density", 0, Some(100.0)),
            row("no_density", 1, None),
        ];
        // Means 160 against 190: 30 mm, beyond the 20 mm noise.
        assert_eq!(lower(&rows, "full", "fusion_max"), Some(Some(true)));
        // Means 160 and 165: within it, although seed 0 alone goes the other way by 10.
        assert_eq!(lower(&rows, "full", "voxelsmplx"), Some(None));
        // A seed that found no one leaves the variant unscored, not scored on the other seed.
        assert_eq!(lower(&rows, "full", "no_density"), None);
        assert_eq!(lower(&rows, "full", "root_head"), None);
        let summary = seed_summary(&rows);
        let full = summary.lines().find(|l| l.starts_with("full")).unwrap();
        for cell in ["2", "160.0", "150.0-170.0", "130.0", "70.0", "0.910"] {
            assert!(
                full.split_whitespace().any(|c| c == cell),
                "{cell} not in {full}"
            );
        }
        let nd = summary
            .lines()
            .find(|l| l.starts_with("no_density"))
            .unwrap();
        assert_eq!(nd.split_whitespace().nth(2), Some("-"), "{nd}");
    }

    #[test]
    fn the_schedule_fills_the_time_at_the_measured_step_times() {
        // 11 minutes less validation: 561 s. Stage 1: 40% is 224.4 s, 0.78 of one 288 s epoch of 576
        // frames at 0.5 s, so one epoch; stage 2: (561 - 288) / (576 x 0.25) = 1.9, so 2.
        assert_eq!(epochs(11.0, 576, [0.5, 0.25]), (1, 2));
        // 40 minutes, 100 frames at 0.1 and 0.2 s: stage 1 816 / 10 = 81.6 -> 82 epochs, stage 2
        // (2040 - 820) / 20 = 61.
        assert_eq!(epochs(40.0, 100, [0.1, 0.2]), (82, 61));
        // 3 minutes, 100 frames at 0.25 and 0.5 s: stage 1 61.2 / 25 = 2.45 -> 2, stage 2
        // (153 - 50) / 50 = 2.06 -> 2.
        assert_eq!(epochs(3.0, 100, [0.25, 0.5]), (2, 2));
        // Far too little time still trains one epoch of each.
        assert_eq!(epochs(0.1, 1000, [1.0, 1.0]), (1, 1));
    }

    #[test]
    fn a_fixed_schedule_is_given_the_time_it_takes() {
        // 3 + 3 epochs of 576 frames at 0.3 and 0.55 s: 518.4 + 950.4 s of steps, over 0.85 for
        // validation, 1728 s: 28.8 minutes.
        let m = schedule_minutes([3, 3], 576, [0.3, 0.55]);
        assert!((m - 28.8).abs() < 1e-9, "{m}");
        // Sizing the schedule to that time gives the same epochs back.
        assert_eq!(epochs(m, 576, [0.3, 0.55]), (3, 3));
        assert_eq!(fixed_epochs(&[3, 4]).unwrap(), [3, 4]);
        for bad in [&[3][..], &[3, 0], &[1, 2, 3], &[]] {
            let err = fixed_epochs(bad).unwrap_err().to_string();
            assert!(
                err.contains("--epochs") && err.contains(&format!("{bad:?}")),
                "{err}"
            );
        }
    }

    #[test]
    fn the_report_judges_the_root_joint_and_names_a_fixed_schedule() {
        let plan = Plan {
            minutes: 28.8,
            scenes: 864,
            variants: vec!["full".into(), "root_head".into(), "root_spine".into()],
            seeds: vec![0],
            train_frames: 576,
            epochs: [3, 3],
            step_seconds: [0.3, 0.55],
            fixed_epochs: true,
            init_hrnet: None,
            kept_volumes: false,
            pretrain: None,
        };
        let far = [
            row("full", 0, Some(150.0)),
            row("root_head", 0, Some(200.0)),
            row("root_spine", 0, Some(175.0)),
        ];
        let text = report(&far, &plan);
        assert!(
            text.starts_with(
                "# Learning benchmark\n\n`mvmp bench learn --epochs 3,3 --scenes 864`"
            )
        );
        assert!(text.contains("3 + 3 epochs (given; the full model takes about 28.8 minutes"));
        assert!(
            text.contains("the pelvis beats the head and the spine: reproduces"),
            "{text}"
        );
        // The spine within the noise: the direction does not hold for both.
        let rows = [
            row("full", 0, Some(150.0)),
            row("root_head", 0, Some(200.0)),
            row("root_spine", 0, Some(160.0)),
        ];
        let text = report(&rows, &plan);
        assert!(
            text.contains("the pelvis beats the head and the spine: not distinguished"),
            "{text}"
        );
        // A benchmark from pretrained HRNet weights names them in its command and its schedule.
        let plan = Plan {
            init_hrnet: Some("/w/hrnet.bpk".into()),
            ..plan
        };
        let text = report(&rows, &plan);
        assert!(
            text.contains("`mvmp bench learn --epochs 3,3 --init-hrnet /w/hrnet.bpk --scenes 864`"),
            "{text}"
        );
        assert!(
            text.contains("Every variant starts from the HRNet weights of /w/hrnet.bpk and trains"),
            "{text}"
        );
        // One that pretrains its HRNet names the pretraining in its command, not the file.
        let plan = Plan {
            pretrain: Some([1152, 12]),
            ..plan
        };
        let text = report(&rows, &plan);
        assert!(
            text.contains("`mvmp bench learn --epochs 3,3 --pretrain-hrnet 1152,12 --scenes 864`"),
            "{text}"
        );
        assert!(
            text.contains(
                "starts from the HRNet the benchmark pretrained (12 stage-1 epochs on 1152"
            ),
            "{text}"
        );
        let plan = Plan {
            kept_volumes: true,
            ..plan
        };
        let text = report(&rows, &plan);
        assert!(
            text.contains("--pretrain-hrnet 1152,12 --kept-volumes --scenes 864`"),
            "{text}"
        );
        assert!(
            text.contains("trains the same schedule (the decoder's `pose_trunk`; stage 2 trains"),
            "{text}"
        );
    }

    #[test]
    fn a_direction_reproduces_only_beyond_the_noise() {
        assert_eq!(verdict(&[Some(Some(true)), Some(Some(true))]), "reproduces");
        assert!(verdict(&[Some(Some(true)), Some(None)]).starts_with("not distinguished"));
        assert!(verdict(&[Some(Some(true)), Some(Some(false))]).starts_with("does not reproduce"));
        assert!(verdict(&[Some(Some(true)), None]).starts_with("not measured"));
    }
}
