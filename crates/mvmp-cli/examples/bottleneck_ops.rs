//! The tiny HRNet's layer1 op by op: each of its first bottleneck's operations (the convolutions, the
//! norms, the residual join) forward and backward alone on 4 views' 56 x 56 maps, then the whole
//! bottleneck. `hrnet_parts` says which part of HRNet the time is in; this says which operation of
//! the part that takes most: the norm and the residual join over the 64-channel maps, each a few
//! passes over 3 MB, cost more than half as much as the three products together.
//!
//! `cargo run --release -p mvmp-cli --example bottleneck_ops` (median and fastest of 25 runs).
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

#[path = "parts/timing.rs"]
mod timing;

use burn::tensor::{Device, Tensor, TensorData};
use mvmp_backbone::hrnet::HRNetConfig;
use mvmp_kernels::conv::conv2d;
use mvmp_kernels::norm::{batch_norm, batch_norm_relu};
use mvmp_kernels::residual::add_relu;

/// 4 views of `c` channels at 56 x 56, varied values, tracked for its gradient.
fn maps(d: &Device, c: usize) -> Tensor<4> {
    let n = 4 * c * 56 * 56;
    let v: Vec<f32> = (0..n)
        .map(|i| ((i * 7919) % 255) as f32 / 255.0 - 0.5)
        .collect();
    Tensor::<4>::from_data(TensorData::new(v, [4, c, 56, 56]), d).require_grad()
}

fn main() {
    timing::finish("bottleneck_ops", run());
}

fn run() -> std::io::Result<()> {
    let d = Device::flex().autodiff();
    let net = HRNetConfig::tiny(17).init(&d);
    let b = &net.layer1[0];
    let (x16, x64) = (maps(&d, 16), maps(&d, 64));
    let rows: [(&str, &dyn Fn() -> Tensor<4>); 7] = [
        ("conv1 1x1 16 -> 16", &|| conv2d(&b.conv1, x16.clone())),
        ("norm and ReLU, 16", &|| {
            batch_norm_relu(&b.bn1, x16.clone())
        }),
        ("conv2 3x3 16 -> 16", &|| conv2d(&b.conv2, x16.clone())),
        ("conv3 1x1 16 -> 64", &|| conv2d(&b.conv3, x16.clone())),
        ("norm, 64", &|| batch_norm(&b.bn3, x64.clone())),
        ("residual join, 64", &|| {
            add_relu(x64.clone(), x64.clone() * 0.5)
        }),
        ("the whole bottleneck", &|| b.forward(x16.clone())),
    ];
    timing::print(format_args!(
        "tiny HRNet's first bottleneck, 4 views at 56 x 56: forward and backward per operation"
    ))?;
    for (name, f) in rows {
        let (median, fastest) = timing::median_and_fastest(25, || drop(f().sum().backward()));
        timing::print(format_args!(
            "{name:22} {median:6.2} ms (fastest {fastest:6.2})"
        ))?;
    }
    Ok(())
}
