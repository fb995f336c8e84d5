//! `mvmp`: the command-line front end. It parses arguments and calls into the library crates.
use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

mod body;
mod data;
mod device;
mod import;
mod model;

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
    /// The MVMP-HMR model: summaries.
    #[command(subcommand)]
    Model(ModelCommand),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(BenchCommand),
}

#[derive(Subcommand)]
enum ImportCommand {
    /// DINOv2 ViT weights (torch-hub .pth/.safetensors or Hugging Face model.safetensors).
    Dinov2 {
        /// tiny, vit_small_14, vit_base_14 or vit_large_14.
        #[arg(long, default_value = "vit_large_14")]
        variant: String,
        #[arg(long)]
        from: PathBuf,
        /// Output weights (burnpack, mvmp key names).
        #[arg(long)]
        out: PathBuf,
    },
    /// HRNet pose weights in the reference pose_hrnet layout (.pth or .safetensors).
    Hrnet {
        /// tiny, hrnet_w32 or hrnet_w48.
        #[arg(long, default_value = "hrnet_w32")]
        variant: String,
        /// Heatmap joints of the checkpoint's head (17 for COCO).
        #[arg(long, default_value_t = 17)]
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
        #[arg(long, default_value_t = 5)]
        views: usize,
    },
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
        /// Layout of the dataset.
        #[arg(long, default_value = "mvmp")]
        format: String,
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
        #[arg(long, default_value_t = 0)]
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
        #[arg(long, default_value_t = 512)]
        size: u32,
    },
}

#[derive(Subcommand)]
enum BenchCommand {
    /// Median wall time of the SMPL-X forward.
    Smplx {
        #[arg(long, default_value_t = 30)]
        batch: usize,
        #[arg(long)]
        model: Option<PathBuf>,
        /// Timed repetitions after the warm-up.
        #[arg(long, default_value_t = 20)]
        iters: usize,
    },
    /// Per-stage forward times of a model config (batch 1) and the fraction of GEMM speed each reaches.
    Model {
        #[arg(long)]
        config: PathBuf,
        #[arg(long, default_value_t = 4)]
        views: usize,
        #[arg(long, default_value_t = 3)]
        iters: usize,
    },
}

fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("MVMP_LOG")
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn")),
        )
        .with_writer(std::io::stderr)
        .init();
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            // Library errors often spell out their cause already; print each cause once.
            let mut msg = e.to_string();
            for cause in e.chain().skip(1) {
                let c = cause.to_string();
                if !msg.contains(&c) {
                    msg = format!("{msg}: {c}");
                }
            }
            eprintln!("error: {msg}");
            ExitCode::FAILURE
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
        Command::Data(DataCommand::Check { format, dir }) => data::check(&format, &dir),
        Command::Model(ModelCommand::Summary { config, views }) => model::summary(&config, views),
        Command::Import(ImportCommand::Dinov2 { variant, from, out }) => {
            import::dinov2(&variant, &from, &out)
        }
        Command::Import(ImportCommand::Hrnet {
            variant,
            joints,
            from,
            out,
        }) => import::hrnet(&variant, joints, &from, &out),
        Command::Bench(BenchCommand::Model {
            config,
            views,
            iters,
        }) => model::bench(&config, views, iters, &device),
        Command::Bench(BenchCommand::Smplx {
            batch,
            model,
            iters,
        }) => body::bench(model.as_deref(), batch, iters, &device),
    }
}
