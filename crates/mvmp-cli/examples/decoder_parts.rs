//! The tiny decoder's forward and backward on the autodiff flex device, and its parts at the sizes it
//! runs them (configs/model/tiny.toml: 10 queries, a 32-channel feature volume and a 17-joint heatmap
//! volume on the 32 x 32 x 8 grid, pooled by 2 into 1024 tokens of width 128, two blocks): the joint
//! samples round each root, the tokens, one block and each of its three parts. `mvmp bench model
//! --backward` times the decoder whole; this says which part the time is in.
//!
//! `cargo run --release -p mvmp-cli --example decoder_parts` (median and fastest of 15 runs).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[path = "parts/timing.rs"]
mod timing;

use burn::tensor::{Bool, Device, Distribution, Tensor, TensorData};
use mvmp_decoder::QueryInputs;
use mvmp_model::config::ModelConfig;

/// Times `f` (15 runs) and prints the row.
fn time(name: &str, f: impl Fn()) -> std::io::Result<()> {
    let (median, fastest) = timing::median_and_fastest(15, f);
    timing::print(format_args!(
        "{name:40} {median:7.2} ms (fastest {fastest:7.2})"
    ))
}

/// A random tracked tensor.
fn random<const D: usize>(shape: [usize; D], d: &Device) -> Tensor<D> {
    Tensor::<D>::random(shape, Distribution::Default, d).require_grad()
}

fn main() {
    timing::finish("decoder_parts", run());
}

fn run() -> std::io::Result<()> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../../configs/model/tiny.toml");
    let cfg = ModelConfig::read(std::path::Path::new(path)).map_err(std::io::Error::other)?;
    let d = Device::flex().autodiff();
    let dec = cfg.decoder_config().init(&d);
    let (g, k) = (&cfg.grid, cfg.max_people);
    let [nx, ny, nz] = g.shape;
    let volume = random([1, cfg.feature_channels, nx, ny, nz], &d);
    let joints = random([1, cfg.heatmap_joints.len(), nx, ny, nz], &d);
    let ring: Vec<f32> = (0..k)
        .flat_map(|i| {
            let a = i as f64 * 2.4;
            [
                (g.center[0] + a.cos()) as f32,
                (g.center[1] + a.sin()) as f32,
                0.9,
            ]
        })
        .collect();
    let roots = Tensor::<3>::from_data(TensorData::new(ring, [1, k, 3]), &d);
    let present = Tensor::<2, Bool>::from_data(TensorData::new(vec![true; k], [1, k]), &d);
    let heading = Tensor::<3>::from_data(TensorData::new([1f32, 0.0].repeat(k), [1, k, 2]), &d);
    let width = dec.query_proj.weight.dims()[1];
    let q = random([1, k, width], &d);
    let tokens = random([1, 1024, width], &d);
    let padding = present.clone().bool_not();
    let blk = &dec.blocks[0];
    timing::print(format_args!(
        "tiny decoder, {k} queries, {} tokens of {width}: forward and backward",
        tokens.dims()[1]
    ))?;
    time("the whole decoder", || {
        let inputs = QueryInputs {
            heading: Some(heading.clone()),
            joints: Some(joints.clone()),
        };
        let out = dec.forward_with(volume.clone(), inputs, g, roots.clone(), present.clone());
        drop((out.rot6d.sum() + out.betas.sum() + out.transl.sum()).backward());
    })?;
    time("joint samples (turned lattice)", || {
        let s = dec.joint_inputs(joints.clone(), roots.clone(), Some(heading.clone()), g);
        drop(s.sum().backward());
    })?;
    time("feature samples (turned lattice)", || {
        let s = dec.sample_lattice_turned(volume.clone(), roots.clone(), heading.clone(), g);
        drop(s.sum().backward());
    })?;
    time("one block", || {
        drop(
            blk.forward(q.clone(), padding.clone(), tokens.clone())
                .sum()
                .backward(),
        );
    })?;
    time("one block's self-attention", || {
        drop(
            blk.self_attention(q.clone(), padding.clone())
                .sum()
                .backward(),
        );
    })?;
    time("one block's cross-attention", || {
        drop(
            blk.cross_attention(q.clone(), tokens.clone())
                .sum()
                .backward(),
        );
    })?;
    time("one block's feed-forward", || {
        drop(blk.feed_forward(q.clone()).sum().backward());
    })?;
    Ok(())
}
