//! `mvmp`: the command-line front end. It parses arguments and calls into the library crates.
use std::path::PathBuf;
use std::process::ExitCode;

use burn::tensor::Device;
use clap::{Parser, Subcommand, ValueEnum};
use mvmp_data::sources::SourceFormat;

/// mimalloc keeps freed pages: burn allocates a fresh buffer for every op's output, and with the system
/// allocator each large one page-faults anew (measured: the SMPL-X skinning GEMM took 12.1 ms with the
/// system allocator, 4.1 ms with mimalloc). Counted, for the memory figures of `bench attention`.
#[global_allocator]
static GLOBAL: alloc::Counting<mimalloc::MiMalloc> = alloc::Counting::new(mimalloc::MiMalloc);

mod alloc;
mod bench_attention;
mod bench_train;
mod body;
mod compare;
mod data;
mod decoder_fit;
mod device;
mod import;
mod interrupt;
mod learn;
mod model;
mod paths;
mod pretrain;
mod probe;
mod progress;
mod report;
mod run;
mod train;
mod training_memory;
mod volume_probe;

/// A flag that must be a positive, finite number of `unit` (metres, minutes).
fn positive(
    unit: &'static str,
) -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static {
    move |s| match s.parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        Ok(v) => Err(format!("{v}: expected a positive, finite number of {unit}")),
        Err(e) => Err(format!("{e}")),
    }
}

/// A count flag that must be at least 1 (0 views would project into no camera at all).
fn at_least_one() -> clap::builder::RangedU64ValueParser<usize> {
    clap::builder::RangedU64ValueParser::<usize>::new().range(1..)
}

/// A count flag from 1 to `max`: where a count sizes an allocation, the cap keeps a typo from aborting
/// on memory.
fn up_to(max: usize) -> clap::builder::RangedU64ValueParser<usize> {
    clap::builder::RangedU64ValueParser::<usize>::new().range(1..=max as u64)
}

/// A body-model reference flag: `standin:SEED` or a path.
fn body_reference(s: &str) -> Result<String, String> {
    mvmp_smplx::check_reference(s).map(|()| s.to_string())
}

/// Most timed repetitions a benchmark takes (`--iters`): each run's time is kept for the median.
const MAX_ITERS: usize = 1_000_000;

/// Most minutes a time flag takes (a year and more): a larger one would overflow the duration it sets.
const MAX_MINUTES: f64 = 1e6;

/// A positive number of minutes, at most [`MAX_MINUTES`].
fn minutes() -> impl Fn(&str) -> Result<f64, String> + Clone + Send + Sync + 'static {
    let positive = positive("minutes");
    move |s| match positive(s)? {
        v if v <= MAX_MINUTES => Ok(v),
        v => Err(format!("{v}: expected at most {MAX_MINUTES} minutes")),
    }
}

#[derive(Parser)]
#[command(
    name = "mvmp",
    version,
    about = "Multiview multi-person whole-body human mesh recovery"
)]
struct Cli {
    /// Compute device: cpu (burn flex), ndarray, wgpu, cuda[:N].
    #[arg(long, global = true, default_value = "cpu")]
    device: String,
    #[command(subcommand)]
    command: Command,
}

/// `mvmp eval --baseline`: a reference to score instead of a model.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Baseline {
    /// The training split's mean pose placed upright at each ground-truth pelvis.
    MeanPose,
}

#[derive(Subcommand)]
enum Command {
    /// Body-model tools: the stand-in model, the SMPL-X forward, previews.
    #[command(subcommand)]
    Body(BodyCommand),
    /// Datasets: synthesis, statistics, validation.
    #[command(subcommand)]
    Data(DataCommand),
    /// Import pretrained weights into mvmp's format.
    #[command(subcommand)]
    Import(ImportCommand),
    /// The MVMP-HMR model: summaries and a probe of a run's volumes.
    #[command(subcommand)]
    Model(ModelCommand),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(BenchCommand),
    /// Score a run (or stored predictions, or the mean-pose reference) on a dataset split.
    Eval(EvalCli),
    /// Runs side by side: the figures their evaluations stored (`RUN/eval-<split>.json`, from
    /// `mvmp eval --run`) as one table, and their validation curves in one picture.
    Compare {
        /// Run directory made by `mvmp train` (repeat for each run).
        #[arg(long = "run", required = true)]
        runs: Vec<PathBuf>,
        /// A name per run, comma-separated, in --run order (default: each directory's name).
        #[arg(long, value_delimiter = ',')]
        names: Option<Vec<String>>,
        /// The split whose stored evaluation is read.
        #[arg(long, default_value = "test")]
        split: String,
        /// The stage whose curves are drawn: 1 (detection: root error and recall) or 2 (the whole
        /// model: MPJPE and recall@500).
        #[arg(long, default_value_t = 2)]
        stage: u8,
        /// The validation error drawn: a `*_mm` key of the runs' `metrics.jsonl`, e.g. pa_pve_mm
        /// (default: root_mm in stage 1, mpjpe_mm in stage 2).
        #[arg(long, requires = "plot")]
        error: Option<String>,
        /// Draw the runs' loss totals and validation curves into this PNG.
        #[arg(long)]
        plot: Option<PathBuf>,
    },
    /// Recover every person's SMPL-X mesh from calibrated views of a frame (or a sequence of frames).
    Infer {
        /// Run directory made by `mvmp train`.
        #[arg(long)]
        run: PathBuf,
        /// Camera rig (mvmp-rig JSON).
        #[arg(long)]
        rig: PathBuf,
        /// One image per camera, in rig order.
        #[arg(long, num_args = 1..)]
        images: Vec<PathBuf>,
        /// A sequence: one sub-directory per frame, each with one image per camera.
        #[arg(long)]
        frames: Option<PathBuf>,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
    },
    /// The end-to-end demo: synthesise the tiny dataset, train both stages on the CPU, evaluate, infer.
    Demo {
        /// Output directory (must not exist or be empty).
        #[arg(long, default_value = "out/demo")]
        out: PathBuf,
        /// Training seed (initial weights, frame order, view draws); the dataset stays the same.
        #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
        seed: u64,
    },
    /// Train MVMP-HMR (stage 1: detection; stage 2: the whole model), or resume a run.
    Train {
        /// Training config (TOML), e.g. configs/train/tiny.toml.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Dataset root (overrides the config's `data`).
        #[arg(long)]
        data: Option<PathBuf>,
        /// Run directory to create (default: out/runs/<config name>).
        #[arg(long)]
        out: Option<PathBuf>,
        /// Continue the run in this directory from its last checkpoint.
        #[arg(long)]
        resume: Option<PathBuf>,
        /// With --config: a new run that goes on from this run's stage-1 checkpoint instead of
        /// training stage 1 again; the two configs must train stage 1 alike (they may differ in
        /// [stage2] and in the loss terms stage 1 does not read), with the same model.
        #[arg(long, requires = "config", conflicts_with = "resume")]
        from_stage1: Option<PathBuf>,
        /// Stop with a checkpoint once the run has made this many optimizer steps.
        #[arg(long, allow_negative_numbers = true, value_parser = clap::builder::RangedU64ValueParser::<u64>::new().range(1..))]
        stop_after_steps: Option<u64>,
        /// Stop with a checkpoint once this call has trained this many minutes (wall time; the step in
        /// flight finishes first). `--resume` continues such a run.
        #[arg(long, value_parser = minutes(), allow_negative_numbers = true)]
        stop_after_minutes: Option<f64>,
    },
}

#[derive(Subcommand)]
enum ImportCommand {
    /// DINOv2 ViT weights (torch-hub .pth/.safetensors or Hugging Face model.safetensors).
    Dinov2 {
        /// tiny, vit_small_14, vit_base_14 or vit_large_14.
        #[arg(long, default_value = "vit_large_14")]
        variant: mvmp_backbone::VitVariant,
        #[arg(long)]
        from: PathBuf,
        /// Output weights (burnpack, mvmp key names).
        #[arg(long)]
        out: PathBuf,
    },
    /// HRNet pose weights in the reference pose_hrnet layout (.pth or .safetensors).
    Hrnet {
        /// tiny, small, hrnet_w32 or hrnet_w48.
        #[arg(long, default_value = "hrnet_w32")]
        variant: mvmp_backbone::HrnetVariant,
        /// Heatmap joints of the checkpoint's head (17 for COCO).
        #[arg(long, allow_negative_numbers = true, default_value_t = 17, value_parser = up_to(1024))]
        joints: usize,
        #[arg(long)]
        from: PathBuf,
        #[arg(long)]
        out: PathBuf,
    },
}

#[derive(Subcommand)]
enum ModelCommand {
    /// Parameters per module (count and MB), the largest activations and the MACs of one forward.
    Summary {
        /// Model config (TOML), e.g. configs/model/paper.toml.
        #[arg(long)]
        config: PathBuf,
        /// Views per sample.
        #[arg(long, allow_negative_numbers = true, default_value_t = 5, value_parser = up_to(mvmp_train::config::MAX_VIEWS))]
        views: usize,
        /// Also estimate a training step's peak memory per stage on flex (weights, Adam's moments,
        /// activations, gradients, the backward's working memory, the body model) from measured steps
        /// at reduced scale.
        #[arg(long)]
        training: bool,
        /// Samples per training step, for --training.
        #[arg(long, allow_negative_numbers = true, default_value_t = 1, value_parser = up_to(mvmp_train::config::MAX_BATCH))]
        batch: usize,
        /// People per sample, for --training (default: the config's max_people).
        #[arg(long, allow_negative_numbers = true, value_parser = up_to(mvmp_model::config::MAX_PEOPLE))]
        people: Option<usize>,
    },
    /// A linear probe of a run's volumes: how well a ridge regression reads each person's body pose
    /// from the image-feature volume (and the joint heatmap volume, and the root height) sampled round
    /// their true root, fitted on the training split and scored on the held-out one, beside the same
    /// model at its initial weights.
    Probe {
        /// Run directory made by `mvmp train`.
        #[arg(long)]
        run: PathBuf,
        /// Dataset root (mvmp layout) with train and test splits.
        #[arg(long)]
        data: PathBuf,
        /// Lattice points per axis (ahead, left, up), e.g. 3,3,8.
        #[arg(long, default_value = "3,3,8", value_parser = lattice_shape)]
        lattice: LatticeShape,
        /// Metres from the lattice's first point to its last per axis.
        #[arg(long, default_value = "1,1,1.75", value_parser = lattice_span)]
        span: LatticeSpan,
        /// Views per frame (the first N cameras; default: the run's test_views).
        #[arg(long, allow_negative_numbers = true, value_parser = up_to(mvmp_train::config::MAX_VIEWS))]
        views: Option<usize>,
        /// Read at most N frames per split, spread over it (0 = all).
        #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
        frames: usize,
        /// Also write the scores as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// The run's decoder alone, from fresh weights, trained on a joint heatmap volume with every
    /// person at their true root and heading (a zero image-feature volume), and the mean angle of its
    /// 21 body rotations from the truth on held-out people: how much of the pose a volume lets the
    /// decoder learn, in seconds.
    FitDecoder {
        /// Run directory made by `mvmp train` (its model config; its HRNet with --maps model).
        #[arg(long)]
        run: PathBuf,
        /// Dataset root (mvmp layout) with train and test splits.
        #[arg(long)]
        data: PathBuf,
        /// The joint volume: the truth's heatmap targets fused (a perfect HRNet), the run's HRNet maps, or
        /// zeros (the root's height and the heading alone).
        #[arg(long, value_enum, default_value = "truth")]
        maps: FitMaps,
        /// The training loss: the body rotations' L1 alone, or the parameter loss as training has it.
        #[arg(long, value_enum, default_value = "parameters")]
        loss: FitLossArg,
        /// One-frame steps.
        #[arg(long, allow_negative_numbers = true, default_value_t = 864, value_parser = up_to(10_000_000))]
        steps: usize,
        /// Adam's rate (default: the run's stage-2 rate).
        #[arg(long, allow_negative_numbers = true, value_parser = positive_rate)]
        lr: Option<f64>,
        /// Held-out frames scored, spread over the split.
        #[arg(long, allow_negative_numbers = true, default_value_t = 48, value_parser = up_to(1_000_000))]
        test_frames: usize,
        /// Score every N steps.
        #[arg(long, allow_negative_numbers = true, default_value_t = 288, value_parser = up_to(10_000_000))]
        every: usize,
        /// Take the decoder from this model config instead of the run's (the same grid and heatmap
        /// joints): how a decoder change reads the same maps.
        #[arg(long)]
        decoder: Option<PathBuf>,
        /// Also write the scores as JSON here.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// One backbone's weights from a run (its final weights, else its newest checkpoint), for another
    /// run's `[init]`: a network pretrained on one dataset starts the training on another.
    Extract {
        /// Run directory made by `mvmp train`.
        #[arg(long)]
        run: PathBuf,
        /// Which backbone.
        #[arg(long, value_enum)]
        module: Backbone,
        /// The weights file to write (burnpack).
        #[arg(long)]
        out: PathBuf,
    },
}

/// `mvmp model extract --module`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum Backbone {
    Hrnet,
    Vit,
}

/// `mvmp model fit-decoder --maps`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum FitMaps {
    Truth,
    Model,
    Zero,
}

/// `mvmp model fit-decoder --loss`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, ValueEnum)]
enum FitLossArg {
    Body,
    Parameters,
}

/// A learning rate: finite and above zero.
fn positive_rate(s: &str) -> Result<f64, String> {
    match s.parse::<f64>() {
        Ok(x) if x.is_finite() && x > 0.0 => Ok(x),
        _ => Err(format!("{s}: not a positive learning rate")),
    }
}

/// `--lattice`: three positive counts.
#[derive(Clone, Copy, Debug)]
struct LatticeShape([usize; 3]);

/// `--span`: three non-negative lengths in metres.
#[derive(Clone, Copy, Debug)]
struct LatticeSpan([f64; 3]);

fn three<T: std::str::FromStr>(s: &str) -> Result<[T; 3], String> {
    let v: Vec<T> = (s.split(','))
        .map(|x| {
            x.trim()
                .parse::<T>()
                .map_err(|_| format!("{x:?} is not a number"))
        })
        .collect::<Result<_, _>>()?;
    <[T; 3]>::try_from(v)
        .map_err(|v| format!("expected three comma-separated values, got {}", v.len()))
}

/// Most points of a probe's lattice: each person's features are points times channels.
const MAX_PROBE_POINTS: usize = 4096;

fn lattice_shape(s: &str) -> Result<LatticeShape, String> {
    let n: [usize; 3] = three(s)?;
    if !n.iter().all(|&k| (1..=64).contains(&k)) {
        return Err(format!("{s}: each count must be 1 to 64"));
    }
    match n.iter().product::<usize>() <= MAX_PROBE_POINTS {
        true => Ok(LatticeShape(n)),
        false => Err(format!("{s}: at most {MAX_PROBE_POINTS} points in all")),
    }
}

fn lattice_span(s: &str) -> Result<LatticeSpan, String> {
    let m: [f64; 3] = three(s)?;
    match m
        .iter()
        .all(|&x| x.is_finite() && (0.0..=100.0).contains(&x))
    {
        true => Ok(LatticeSpan(m)),
        false => Err(format!("{s}: each length must be 0 to 100 metres")),
    }
}

/// `mvmp eval`'s arguments.
#[derive(clap::Args)]
struct EvalCli {
    /// Run directory made by `mvmp train`.
    #[arg(long, conflicts_with_all = ["predictions", "baseline"])]
    run: Option<PathBuf>,
    /// Predictions in infer's layout: PRED_DIR/<scene>/<frame>/people.npz.
    #[arg(long, conflicts_with = "baseline")]
    predictions: Option<PathBuf>,
    /// A reference instead of a model: `mean-pose` (the training split's mean pose at each ground-truth pelvis).
    #[arg(long, value_enum)]
    baseline: Option<Baseline>,
    /// Dataset root (mvmp layout).
    #[arg(long)]
    data: PathBuf,
    /// train, test or all.
    #[arg(long, default_value = "test")]
    split: String,
    /// Views per frame (the first N cameras; default: the run's test_views).
    #[arg(long, allow_negative_numbers = true, value_parser = up_to(mvmp_train::config::MAX_VIEWS))]
    views: Option<usize>,
    /// Score only the first N frames (0 = all).
    #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
    frames: usize,
    /// Matching gate on pelvis distance (metres).
    #[arg(long, default_value_t = mvmp_eval::DEFAULT_GATE, value_parser = positive("metres"), allow_negative_numbers = true)]
    gate: f64,
    /// Write the JSON report here (default: RUN_DIR/eval-<split>.json for a run).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Also write each frame's predictions (infer's layout) under this directory.
    #[arg(long)]
    save_predictions: Option<PathBuf>,
    /// Body model for --predictions (`standin:SEED` or an SMPLX npz; default: the dataset's) and for
    /// --pseudo-gt (default: the run's).
    #[arg(long, value_parser = body_reference)]
    body_model: Option<String>,
    /// Joints MPJPE is taken on: smplx127, panoptic15 or h36m17 (mapped from SMPL-X joints).
    #[arg(long, default_value = "smplx127")]
    joints: mvmp_eval::joint_sets::JointSet,
    /// Dataset layout: mvmp; panoptic (CMU Panoptic read in place; --split test = voxelpose-val,
    /// train = voxelpose-train, or comma-separated sequence names); h36m (Human3.6M read in place;
    /// --split test = S9,S11, train = S1,S5,S6,S7,S8, or comma-separated subjects).
    #[arg(long, default_value = "mvmp")]
    format: SourceFormat,
    /// Keep every N-th frame (panoptic: default the split's stride; h36m: default 5, i.e. 10 Hz).
    #[arg(long, allow_negative_numbers = true, value_parser = up_to(1_000_000))]
    stride: Option<usize>,
    /// Panoptic and h36m: SMPL-X pseudo-ground-truth fits, DIR/<sequence>/<frame>/people.npz (infer's
    /// layout; <sequence> is S9/<action> for h36m, <frame> the 8-digit Panoptic index or the 6-digit
    /// image number); PVE and PA-PVE are computed against them, posed with --body-model (default:
    /// the run's).
    #[arg(long)]
    pseudo_gt: Option<PathBuf>,
    /// Diagnostic: replace the fused image-feature volume with zeros before the decoder, to measure
    /// what the predictions owe to the images' features beyond detection, the heading and the root's
    /// height (with --run; the report records it).
    #[arg(long)]
    zero_volume: bool,
    /// Diagnostic (an error budget): take these SMPL-X parameter groups (comma-separated: orient, body,
    /// hands, face, shape) from the annotated person nearest each prediction's pelvis, keeping the
    /// predicted pelvis, before scoring (with --run or --predictions on an mvmp dataset; the report records it).
    #[arg(long, value_parser = mvmp_eval::truth_parts::parse_truth_parts)]
    truth: Option<mvmp_eval::truth_parts::TruthParts>,
}

#[derive(Subcommand)]
enum DataCommand {
    /// Make a synthetic multiview multi-person dataset in the MVMP-HMR layout.
    Synth {
        /// Synthesis config (TOML), e.g. configs/synth/tiny.toml.
        #[arg(long)]
        config: PathBuf,
        /// Output dataset directory (must not exist, or be empty).
        #[arg(long)]
        out: PathBuf,
    },
    /// The dataset-table numbers of a dataset: scenes, frames, views, area, people, occlusion.
    Stats {
        /// Dataset root.
        dir: PathBuf,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
        /// Write a PNG contact sheet of the first frame's views.
        #[arg(long)]
        sheet: Option<PathBuf>,
    },
    /// Validate a whole dataset tree and list every problem with its file.
    Check {
        /// Layout of the dataset: mvmp, panoptic or h36m.
        #[arg(long, default_value = "mvmp")]
        format: SourceFormat,
        /// Decode every image whole (a plain check reads image headers only).
        #[arg(long)]
        deep: bool,
        /// Dataset root.
        dir: PathBuf,
    },
}

#[derive(Subcommand)]
enum BodyCommand {
    /// Write the procedural stand-in body model in the official SMPLX npz layout.
    MakeStandin {
        /// Output .npz path.
        #[arg(long)]
        out: PathBuf,
        /// Generator seed.
        #[arg(long, allow_negative_numbers = true, default_value_t = 0)]
        seed: u64,
    },
    /// Pose bodies: write output.npz / output.json (vertices, joints) and one OBJ and PLY per body.
    Forward {
        /// SMPLX_*.npz model file (default: the stand-in).
        #[arg(long)]
        model: Option<PathBuf>,
        /// JSON with one body or a list of bodies (standard smplx keys, axis-angle, metres).
        #[arg(long)]
        params: PathBuf,
        /// Output directory.
        #[arg(long)]
        out: PathBuf,
    },
    /// Render posed bodies to a PNG (software rasterizer), seen from the front.
    Render {
        #[arg(long)]
        model: Option<PathBuf>,
        /// JSON parameters; without it, the rest pose.
        #[arg(long)]
        params: Option<PathBuf>,
        /// Output PNG.
        #[arg(long)]
        out: PathBuf,
        /// Image width and height in pixels.
        #[arg(long, allow_negative_numbers = true, default_value_t = 512, value_parser = clap::builder::RangedU64ValueParser::<u32>::new().range(1..=8192))]
        size: u32,
    },
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Seconds and peak extra memory of one attention forward and backward: the tiled operation training
    /// uses beside burn's plain ops (whose backward keeps every head's N x N probabilities), over token
    /// counts. The default is one ViT-L/14 block's attention at the paper's 1288 x 1288 (8465 tokens).
    Attention {
        /// Comma-separated token counts.
        #[arg(long, allow_negative_numbers = true, value_delimiter = ',', default_values_t = [1024, 2048, 4096, 8465], value_parser = at_least_one())]
        tokens: Vec<usize>,
        #[arg(long, allow_negative_numbers = true, default_value_t = 16, value_parser = at_least_one())]
        heads: usize,
        #[arg(long, allow_negative_numbers = true, default_value_t = 64, value_parser = at_least_one())]
        head_dim: usize,
        /// Side of the score tiles.
        #[arg(long, allow_negative_numbers = true, default_value_t = mvmp_kernels::DEFAULT_BLOCK, value_parser = at_least_one())]
        tile: usize,
        /// Run the plain path only up to this many tokens (16 heads at 8465 tokens hold 4.6 GB of
        /// probabilities, several times over in the backward).
        #[arg(long, allow_negative_numbers = true, default_value_t = 4096)]
        plain_up_to: usize,
    },
    /// Median wall time of the SMPL-X forward; with --backward, of forward and backward as training runs
    /// them (on the CPU the fused operation beside the tensor ops).
    Smplx {
        /// Bodies per forward (at most 4096: each holds 10475 posed vertices and the packed features).
        #[arg(long, allow_negative_numbers = true, default_value_t = 30, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=4096))]
        batch: usize,
        #[arg(long)]
        model: Option<PathBuf>,
        /// Timed repetitions after the warm-up.
        #[arg(long, allow_negative_numbers = true, default_value_t = 20, value_parser = up_to(MAX_ITERS))]
        iters: usize,
        /// Time forward and backward (gradients of every input) instead of the forward alone.
        #[arg(long)]
        backward: bool,
    },
    /// Projection and fusion at a model config's scale (its grid, input size, channels): the sampling
    /// grids of a ring rig and the median fusion times from them.
    Fusion {
        #[arg(long)]
        config: PathBuf,
        #[arg(long, allow_negative_numbers = true, default_value_t = 5, value_parser = up_to(mvmp_train::config::MAX_VIEWS))]
        views: usize,
        /// Timed repetitions after the warm-up.
        #[arg(long, allow_negative_numbers = true, default_value_t = 5, value_parser = up_to(MAX_ITERS))]
        iters: usize,
    },
    /// The learning benchmark: the full tiny model and the paper's comparisons (VoxelSMPLX, max and
    /// deformable fusion, without the orientation or density loss, head and spine roots), each trained on
    /// one synthetic set on one schedule and scored on its held-out scenes; writes OUT/learning.md
    /// (table, the paper's directions) and OUT/curves.png.
    Learn {
        /// The full model's training time, minutes: the schedule every variant trains is sized to it.
        #[arg(long, allow_negative_numbers = true, default_value_t = 40.0, value_parser = minutes())]
        minutes: f64,
        /// One-frame scenes of the synthetic set (two thirds train, one third held out). Twice the demo's:
        /// with the steps fixed, distinct scenes teach more than passes over the same ones (README).
        #[arg(long, allow_negative_numbers = true, default_value_t = 864, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(3..=10000))]
        scenes: usize,
        /// Comma-separated variants (default: all): full, voxelsmplx, fusion_max, fusion_deformable,
        /// no_orientation, no_density, root_head, root_spine.
        #[arg(long)]
        variants: Option<String>,
        /// Comma-separated training seeds: every variant trains once with each (one run per variant and
        /// seed), and the report adds each variant's mean and spread over them.
        #[arg(long, value_delimiter = ',', default_value = "0")]
        seeds: Vec<u64>,
        /// Epochs of stage 1 and stage 2 (`S1,S2`), fixed instead of sized from --minutes, so that
        /// benchmarks on machines of other speeds train the same steps; the time guard then counts from
        /// the time they take at the step times measured here.
        #[arg(long, value_delimiter = ',', conflicts_with = "minutes")]
        epochs: Option<Vec<usize>>,
        /// HRNet weights every variant starts from (`[init] hrnet` of its training config): the
        /// model's `tiny` HRNet with 17 joints, as `mvmp model extract` or `mvmp import hrnet` write it.
        #[arg(long)]
        init_hrnet: Option<PathBuf>,
        /// Every variant trains by the decoder-alone recipe: the decoder's `pose_trunk`, and a stage 2
        /// that keeps the ViT and detection fixed and each frame's volumes from its first decoding
        /// (`[stage2] freeze_backbone`, `freeze_detection`, `cache_volumes`), so that its steps cost
        /// about a fifth. Meant with --init-hrnet: maps trained from scratch give the decoder little
        /// to read (docs/learning.md).
        #[arg(long)]
        kept_volumes: bool,
        /// Pretrain the HRNet every variant starts from, as `SCENES,EPOCHS` (e.g. 1152,12): stage 1
        /// alone for EPOCHS epochs on a synthetic set of the benchmark's recipe with SCENES scenes and
        /// the next seed, before the variants (OUT/pretrain; a stopped benchmark goes on from it).
        #[arg(long, value_delimiter = ',', conflicts_with = "init_hrnet")]
        pretrain_hrnet: Option<Vec<usize>>,
        #[arg(long, default_value = "out/learn")]
        out: PathBuf,
        /// Go on with the benchmark stopped in --out (by Ctrl-C or an error once its schedule was
        /// planned), or add to one that finished: runs scored stay, a stopped run resumes from its
        /// checkpoint, the rest train as planned; its minutes, scenes and seeds are the plan's. With
        /// --variants, those variants join the plan and train on its schedule.
        #[arg(long, conflicts_with_all = ["minutes", "scenes", "seeds", "epochs", "init_hrnet", "kept_volumes", "pretrain_hrnet"])]
        resume: bool,
    },
    /// Seconds per training step of each stage and their split (load, forward, backward, gradient
    /// norms, optimizer), from short runs in a temporary directory.
    Train {
        /// Training config (default: the demo's, on a synthetic set made for the benchmark).
        #[arg(long)]
        config: Option<PathBuf>,
        /// Dataset root (overrides the config's `data`).
        #[arg(long)]
        data: Option<PathBuf>,
        /// Timed steps per stage (after 2 warm-up steps).
        #[arg(long, allow_negative_numbers = true, default_value_t = 10, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(1..=100000))]
        steps: usize,
        /// One-frame scenes of the synthetic set made without --config and --data.
        #[arg(long, allow_negative_numbers = true, default_value_t = 48, value_parser = clap::builder::RangedU64ValueParser::<usize>::new().range(3..=10000))]
        scenes: usize,
        /// Also time every stage with the fused training passes off (fusion and convolution columns as
        /// tensor ops), and print the ratio.
        #[arg(long)]
        baseline: bool,
    },
    /// Per-stage forward times of a model config (batch 1) and the fraction of GEMM speed each reaches;
    /// with --backward, forward and backward.
    Model {
        #[arg(long)]
        config: PathBuf,
        #[arg(long, allow_negative_numbers = true, default_value_t = 4, value_parser = up_to(mvmp_train::config::MAX_VIEWS))]
        views: usize,
        #[arg(long, allow_negative_numbers = true, default_value_t = 3, value_parser = up_to(MAX_ITERS))]
        iters: usize,
        /// Time each stage's forward and backward (on the autodiff device; what a training step runs).
        #[arg(long)]
        backward: bool,
    },
}

/// `println!` panics when standard output is closed (`mvmp ... | head`) or full: that is an I/O error of
/// the command's output, reported as one (non-zero exit, no panic trace), not a bug. A damaged CDF file's
/// panic inside its decoder is caught and reported as that file's error, so it prints nothing here.
fn output_errors_are_errors() {
    let default = std::panic::take_hook();
    std::panic::set_hook(Box::new(move |info| {
        if mvmp_data::cdf_pose::decoding_on_this_thread() {
            return;
        }
        let payload = info.payload();
        let msg = payload
            .downcast_ref::<String>()
            .map(String::as_str)
            .or_else(|| payload.downcast_ref::<&str>().copied())
            .unwrap_or("");
        if let Some(cause) = msg.strip_prefix("failed printing to stdout: ") {
            use std::io::Write;
            let _ = writeln!(
                std::io::stderr(),
                "error: writing to standard output: {cause}"
            );
            std::process::exit(1);
        }
        default(info)
    }));
}

fn main() -> ExitCode {
    alloc::keep_freed_memory();
    output_errors_are_errors();
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("MVMP_LOG")
                // wgpu reports every graphics API it fails to open while it looks for an adapter (GL
                // under a Vulkan-only driver, for one); a missing adapter is an error of its own.
                .unwrap_or_else(|_| {
                    tracing_subscriber::EnvFilter::new("warn,wgpu_hal=off,wgpu_core=off")
                }),
        )
        .with_writer(std::io::stderr)
        // Colour codes only for a person at a terminal, not in logs and pipes.
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .init();
    let cli = Cli::parse();
    interrupt::install();
    match run(cli) {
        // A run stopped by a signal wrote its checkpoint, but did not finish: the status says which
        // signal stopped it, as a scheduler or `timeout` expects.
        Ok(()) => match interrupt::received() {
            Some(signal) => ExitCode::from(128 + signal),
            None => ExitCode::SUCCESS,
        },
        Err(e) => {
            eprintln!("error: {}", report::message(&e));
            // The demo stops with an error when a signal stopped its training.
            interrupt::received().map_or(ExitCode::FAILURE, |s| ExitCode::from(128 + s))
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<()> {
    let device = device::parse(&cli.device)?;
    match cli.command {
        Command::Body(BodyCommand::MakeStandin { out, seed }) => body::make_standin(&out, seed),
        Command::Body(BodyCommand::Forward { model, params, out }) => {
            body::forward(model.as_deref(), &params, &out, &device)
        }
        Command::Body(BodyCommand::Render {
            model,
            params,
            out,
            size,
        }) => body::render(model.as_deref(), params.as_deref(), &out, size, &device),
        Command::Data(DataCommand::Synth { config, out }) => data::synth(&config, &out),
        Command::Data(DataCommand::Stats { dir, json, sheet }) => {
            data::stats(&dir, json, sheet.as_deref())
        }
        Command::Data(DataCommand::Check { format, dir, deep }) => data::check(format, &dir, deep),
        Command::Model(ModelCommand::Summary {
            config,
            views,
            training,
            batch,
            people,
        }) => {
            model::summary(&config, views)?;
            match training {
                true => model::training_summary(&config, views, batch, people),
                false => Ok(()),
            }
        }
        Command::Model(ModelCommand::Probe {
            run,
            data,
            lattice,
            span,
            views,
            frames,
            out,
        }) => volume_probe::probe(
            &volume_probe::ProbeArgs {
                run: &run,
                data: &data,
                lattice: lattice.0,
                span: span.0,
                views,
                frames,
                out: out.as_deref(),
            },
            &device,
        ),
        Command::Model(ModelCommand::FitDecoder {
            run,
            data,
            maps,
            loss,
            steps,
            lr,
            test_frames,
            every,
            decoder,
            out,
        }) => decoder_fit::fit_decoder(
            &decoder_fit::FitArgs {
                run: &run,
                data: &data,
                maps: match maps {
                    FitMaps::Truth => mvmp_train::decoder_fit::JointMaps::Truth,
                    FitMaps::Model => mvmp_train::decoder_fit::JointMaps::Model,
                    FitMaps::Zero => mvmp_train::decoder_fit::JointMaps::Zero,
                },
                loss: match loss {
                    FitLossArg::Body => mvmp_train::decoder_fit::FitLoss::Body,
                    FitLossArg::Parameters => mvmp_train::decoder_fit::FitLoss::Parameters,
                },
                steps,
                lr,
                test_frames,
                every,
                decoder: decoder.as_deref(),
                out: out.as_deref(),
            },
            &device,
        ),
        Command::Model(ModelCommand::Extract { run, module, out }) => {
            model::extract(&run, module == Backbone::Hrnet, &out)
        }
        Command::Import(ImportCommand::Dinov2 { variant, from, out }) => {
            import::dinov2(variant, &from, &out)
        }
        Command::Import(ImportCommand::Hrnet {
            variant,
            joints,
            from,
            out,
        }) => import::hrnet(variant, joints, &from, &out),
        Command::Eval(e) => eval_command(e, &device),
        Command::Compare {
            runs,
            names,
            split,
            stage,
            error,
            plot,
        } => compare::compare(&compare::CompareArgs {
            runs: &runs,
            names: names.as_deref(),
            split: &split,
            stage,
            error: error.as_deref(),
            plot: plot.as_deref(),
        })
        .map(|_| ()),
        Command::Infer {
            run,
            rig,
            images,
            frames,
            out,
        } => run::infer(
            &run::InferArgs {
                run: &run,
                rig: &rig,
                images: &images,
                frames: frames.as_deref(),
                out: &out,
            },
            &device,
            false,
        ),
        Command::Demo { out, seed } => run::demo(&out, seed, &device),
        Command::Train {
            config,
            data,
            out,
            resume,
            from_stage1,
            stop_after_steps,
            stop_after_minutes,
        } => train::train(
            train::TrainArgs {
                config: config.as_deref(),
                data: data.as_deref(),
                out: out.as_deref(),
                resume: resume.as_deref(),
                from_stage1: from_stage1.as_deref(),
                stop_after_steps,
                stop_after_minutes,
                resumable: true,
            },
            &device,
            &mut train::BarMonitor::new(false),
        )
        .map(|_| ()),
        Command::Bench(b) => bench_command(b, &device, device::is_host(&cli.device)),
    }
}

/// `mvmp eval`: score, print the table and where the report went.
fn eval_command(e: EvalCli, device: &Device) -> anyhow::Result<()> {
    let source = match (&e.run, &e.predictions, e.baseline) {
        (Some(r), None, None) => run::Source::Run(r),
        (None, Some(p), None) => run::Source::Predictions(p),
        (None, None, Some(Baseline::MeanPose)) => run::Source::MeanPose,
        _ => anyhow::bail!("pass one of --run RUN_DIR, --predictions DIR, --baseline mean-pose"),
    };
    let split = if e.format != SourceFormat::Mvmp {
        mvmp_data::loader::Split::Test
    } else {
        run::parse_split(&e.split)?
    };
    let out = e.out.clone().or_else(|| {
        e.run
            .as_ref()
            .map(|r| r.join(format!("eval-{}.json", e.split)))
    });
    let args = run::EvalArgs {
        source,
        data: &e.data,
        split,
        views: e.views,
        frames: e.frames,
        gate: e.gate,
        out: out.as_deref(),
        save_predictions: e.save_predictions.as_deref(),
        body_model: e.body_model.as_deref(),
        joints: e.joints,
        format: e.format,
        split_name: &e.split,
        stride: e.stride,
        pseudo_gt: e.pseudo_gt.as_deref(),
        zero_volume: e.zero_volume,
        truth: e.truth.clone().map(|t| t.0).unwrap_or_default(),
    };
    let (m, _) = run::eval(&args, device, false)?;
    print!(
        "{}",
        run::table(&[(format!("{} split", e.split), m.clone())])
    );
    println!(
        "matched {} of {} ground-truth people, {} predictions",
        m.matched, m.ground_truth, m.predictions
    );
    if let Some(parts) = run::error_parts(&m) {
        println!("{parts}");
    }
    if let Some(o) = &out {
        println!("report {}", o.display());
    }
    Ok(())
}

/// `mvmp bench ...`: `host` says whether the device computes in host memory (the peak columns).
fn bench_command(cmd: BenchCommand, device: &Device, host: bool) -> anyhow::Result<()> {
    match cmd {
        BenchCommand::Model {
            config,
            views,
            iters,
            backward,
        } => model::bench(&config, views, iters, backward, device),
        BenchCommand::Attention {
            tokens,
            heads,
            head_dim,
            tile,
            plain_up_to,
        } => bench_attention::bench_attention(
            &bench_attention::AttentionArgs {
                tokens: &tokens,
                heads,
                head_dim,
                tile,
                plain_up_to,
                host,
            },
            device,
        ),
        BenchCommand::Train {
            config,
            data,
            steps,
            scenes,
            baseline,
        } => bench_train::bench_train(
            &bench_train::BenchTrainArgs {
                config: config.as_deref(),
                data: data.as_deref(),
                steps,
                scenes,
                host,
                baseline,
            },
            device,
        ),
        BenchCommand::Learn {
            out,
            resume: true,
            variants,
            ..
        } => learn::resume_learn(&out, variants.as_deref(), device),
        BenchCommand::Learn {
            minutes,
            scenes,
            variants,
            seeds,
            epochs,
            init_hrnet,
            kept_volumes,
            pretrain_hrnet,
            out,
            resume: false,
        } => learn::bench_learn(
            &learn::LearnArgs {
                out: &out,
                minutes,
                scenes,
                variants: variants.as_deref(),
                seeds: &seeds,
                epochs: epochs.as_deref(),
                init_hrnet: init_hrnet.as_deref(),
                kept_volumes,
                pretrain: pretrain_hrnet.as_deref(),
            },
            device,
        ),
        BenchCommand::Fusion {
            config,
            views,
            iters,
        } => model::bench_fusion(&config, views, iters, device),
        BenchCommand::Smplx {
            batch,
            model,
            iters,
            backward,
        } => body::bench(model.as_deref(), batch, iters, backward, device),
    }
}
