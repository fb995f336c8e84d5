//! An HRNet's forward and backward on the autodiff flex device (the tiny one unless named), timed part by part: each row
//! runs the network up to the end of one part (stem, layer1, the transitions and stages, the final
//! layer) and back-propagates the sum of what it has so far, so a part's cost is its row less the row
//! before. `mvmp bench model --backward` times HRNet whole; this says which of its parts the time is in.
//!
//! `cargo run --release -p mvmp-cli --example hrnet_parts [-- VIEWS SIZE [VARIANT]]` (4 views of 224 x
//! 224 unless given; VARIANT tiny, small, hrnet_w32 or hrnet_w48; median and fastest of 7 runs).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[path = "parts/timing.rs"]
mod timing;

use burn::tensor::{Device, Tensor, TensorData};
use mvmp_backbone::HrnetVariant;
use mvmp_backbone::hrnet::HRNet;
use mvmp_kernels::conv::conv2d;
use mvmp_kernels::norm::batch_norm_relu;

const PARTS: [&str; 9] = [
    "stem",
    "layer1",
    "transition1",
    "stage2",
    "transition2",
    "stage3",
    "transition3",
    "stage4",
    "final layer",
];

fn total(xs: &[Tensor<4>]) -> Tensor<1> {
    let sums = xs.iter().map(|t| t.clone().sum());
    sums.reduce(|a, b| a + b).expect("a branch")
}

/// The network run through part `upto` (an index into [`PARTS`]), summed.
fn through(net: &HRNet, x: Tensor<4>, upto: usize) -> Tensor<1> {
    let x = batch_norm_relu(&net.bn1, conv2d(&net.conv1, x));
    let x = batch_norm_relu(&net.bn2, conv2d(&net.conv2, x));
    if upto == 0 {
        return x.sum();
    }
    let x = net.layer1.iter().fold(x, |x, b| b.forward(x));
    if upto == 1 {
        return x.sum();
    }
    let mut xs = net.transition1.forward(&[x]);
    let stages = [
        (&net.stage2, Some(&net.transition2)),
        (&net.stage3, Some(&net.transition3)),
        (&net.stage4, None),
    ];
    let mut part = 2;
    for (modules, transition) in stages {
        if upto == part {
            return total(&xs);
        }
        xs = modules.iter().fold(xs, |xs, m| m.forward(xs));
        part += 1;
        if upto == part {
            return total(&xs);
        }
        if let Some(t) = transition {
            xs = t.forward(&xs);
            part += 1;
        }
    }
    conv2d(&net.final_layer, xs.swap_remove(0)).sum()
}

/// Positional argument `i`, `default` when absent; refused, naming `what` it must be, unless `ok` holds.
fn argument(i: usize, what: &str, default: usize, ok: fn(usize) -> bool) -> std::io::Result<usize> {
    let Some(text) = std::env::args().nth(i) else {
        return Ok(default);
    };
    match text.parse::<usize>() {
        Ok(n) if ok(n) => Ok(n),
        _ => Err(std::io::Error::new(
            std::io::ErrorKind::InvalidInput,
            format!("argument {i}: {text:?} is not {what}"),
        )),
    }
}

fn main() {
    timing::finish("hrnet_parts", run());
}

fn run() -> std::io::Result<()> {
    let views = argument(1, "VIEWS, a count of at least 1", 4, |n| n >= 1)?;
    let side = "SIZE, a multiple of 4 of at least 32 pixels";
    let size = argument(2, side, 224, |n| n >= 32 && n.is_multiple_of(4))?;
    let variant: HrnetVariant = match std::env::args().nth(3) {
        Some(name) => name.parse().map_err(|e: String| {
            std::io::Error::new(std::io::ErrorKind::InvalidInput, format!("argument 3: {e}"))
        })?,
        None => HrnetVariant::Tiny,
    };
    let d = Device::flex().autodiff();
    let net = variant.config(17).init(&d);
    let n = views * 3 * size * size;
    let img: Vec<f32> = (0..n)
        .map(|i| ((i * 7919) % 255) as f32 / 255.0 - 0.5)
        .collect();
    let x = Tensor::<4>::from_data(TensorData::new(img, [views, 3, size, size]), &d);
    timing::print(format_args!(
        "HRNet {variant}, {views} views of {size} x {size}: forward and backward through each part"
    ))?;
    let mut before = 0.0;
    for (upto, name) in PARTS.iter().enumerate() {
        let (median, fastest) =
            timing::median_and_fastest(7, || drop(through(&net, x.clone(), upto).backward()));
        timing::print(format_args!(
            "through {name:12} {median:7.1} ms (fastest {fastest:7.1}); the part {:6.1} ms",
            median - before
        ))?;
        before = median;
    }
    Ok(())
}
