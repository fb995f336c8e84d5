//! The tiny RootNet's forward and backward on the autodiff flex device, and each kind of block it is
//! made of at the sizes it runs them (the tiny config: 17 heatmap joints, `rootnet_width = 0.5`, group
//! norm, a 32 x 32 x 8 grid): the 7^3 front, the residual blocks at each resolution, the upsampling
//! blocks and the pooling. `mvmp bench model --backward` times the RootNet whole; this says which of its
//! blocks the time is in (a row is one call of a block; its name says how often the V2V calls it).
//!
//! `cargo run --release -p mvmp-cli --example rootnet_parts` (median and fastest of 9 runs). The whole
//! RootNet is timed with burn's norms and the front as a 3D product, with the fused norms
//! (`mvmp_kernels::norm`) and the front's depth folded into its channels (`mvmp_kernels::conv`), and
//! with the 3x3x3 blocks computed directly besides (`mvmp_kernels::direct`), in turn. The residual
//! blocks' rows take the direct path where it applies (full and half resolution).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[path = "parts/timing.rs"]
mod timing;

use burn::tensor::{Device, Distribution, Tensor};
use mvmp_fusion::pool::max_pool3d_2;
use mvmp_fusion::v2v::{Basic3DBlock, Res3DBlock, RootNetConfig, Upsample3DBlock, VolumeNorm};

/// Times `f` (9 runs) and prints the row.
fn time(name: &str, f: impl Fn()) -> std::io::Result<()> {
    let (median, fastest) = timing::median_and_fastest(9, f);
    timing::print(format_args!(
        "{name:44} {median:7.1} ms (fastest {fastest:7.1})"
    ))
}

/// A random tracked volume `[1, c, x, y, z]`.
fn volume(c: usize, [x, y, z]: [usize; 3], d: &Device) -> Tensor<5> {
    Tensor::<5>::random([1, c, x, y, z], Distribution::Default, d).require_grad()
}

fn main() {
    timing::finish("rootnet_parts", run());
}

fn run() -> std::io::Result<()> {
    let d = Device::flex().autodiff();
    let n = VolumeNorm::Group;
    let full = [32, 32, 8];
    let half = full.map(|a| a / 2);
    let quarter = full.map(|a| a / 4);
    let heatmaps = volume(17, full, &d);
    let rootnet = RootNetConfig::new(17).with_width(0.5).with_norm(n).init(&d);
    timing::print(format_args!(
        "tiny RootNet on a [1, 17, 32, 32, 8] heatmap volume: forward and backward"
    ))?;
    // Burn's norms, the front and the 3x3x3 blocks as 3D products; the fused norms and the folded
    // front; and the 3x3x3 blocks direct besides, in turn, so that the rows share the machine's state.
    for _ in 0..3 {
        for (fused, direct) in [(false, false), (true, false), (true, true)] {
            mvmp_kernels::norm::set_fused_norm(fused);
            mvmp_kernels::conv::set_fold_depth(fused);
            mvmp_kernels::direct::set_direct_conv3d(direct);
            let how = match (fused, direct) {
                (false, _) => "burn's norms, 3D front",
                (true, false) => "fused norms, folded front",
                (true, true) => "the same, direct 3x3x3",
            };
            time(&format!("the whole RootNet, {how}"), || {
                let (likelihood, offset) = rootnet.forward(heatmaps.clone());
                drop((likelihood.sum() + offset.sum()).backward());
            })?;
        }
    }
    mvmp_kernels::direct::set_direct_conv3d(true);
    let front = Basic3DBlock::new(17, 8, 7, n, &d);
    // Its depth folded into the channels and not, in turn.
    for fold in [false, true, false, true] {
        mvmp_kernels::conv::set_fold_depth(fold);
        let how = if fold { "folded" } else { "as 3D" };
        time(
            &format!("front: 7^3, 17 -> 8 channels, full, {how}"),
            || drop(front.forward(heatmaps.clone()).sum().backward()),
        )?;
    }
    // Widths 8, 16, 32, 64 (the reference's 16 to 128 at `rootnet_width = 0.5`).
    for (name, c, co, size) in [
        ("residual 8 -> 16, full (once)", 8, 16, full),
        ("residual 16 -> 16, full (once)", 16, 16, full),
        ("residual 16 -> 32, half (once)", 16, 32, half),
        ("residual 32 -> 32, half (twice)", 32, 32, half),
        ("residual 32 -> 64, quarter (once)", 32, 64, quarter),
        ("residual 64 -> 64, quarter (twice)", 64, 64, quarter),
    ] {
        let block = Res3DBlock::new(c, co, n, &d);
        let x = volume(c, size, &d);
        time(name, || drop(block.forward(x.clone()).sum().backward()))?;
    }
    for (name, c, co, size) in [
        ("upsampling 64 -> 32, quarter to half", 64, 32, quarter),
        ("upsampling 32 -> 16, half to full", 32, 16, half),
    ] {
        let block = Upsample3DBlock::new(c, co, n, &d);
        let x = volume(c, size, &d);
        time(name, || drop(block.forward(x.clone()).sum().backward()))?;
    }
    let x = volume(16, full, &d);
    time("max pooling by 2, 16 channels, full", || {
        drop(max_pool3d_2(x.clone()).sum().backward())
    })
}
