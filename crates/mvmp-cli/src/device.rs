//! `--device` parsing. The device decides the backend at run time (burn 0.22); a backend that was not
//! compiled in gets an error that says how to get it.
use anyhow::{Result, bail};
use burn::tensor::Device;

/// Whether `--device s` computes in host memory (flex, ndarray), where the binary's allocator counts it.
pub fn is_host(s: &str) -> bool {
    matches!(s.split(':').next(), Some("cpu" | "flex" | "ndarray"))
}

pub fn parse(s: &str) -> Result<Device> {
    let (name, index) = match s.split_once(':') {
        Some((n, i)) => (n, Some(i)),
        None => (s, None),
    };
    match name {
        "cpu" | "flex" => {
            if index.is_some() {
                bail!("--device {s}: the CPU device takes no index");
            }
            Ok(Device::flex())
        }
        #[allow(deprecated)]
        "ndarray" => Ok(Device::ndarray()),
        "wgpu" => wgpu(index, s),
        "cuda" => bail!(
            "--device {s}: this mvmp binary was built without CUDA support; use --device wgpu on a \
             GPU (build with `cargo build --release --features wgpu`)"
        ),
        other => {
            bail!("--device {other:?} is not a device; expected cpu, ndarray, wgpu or cuda[:N]")
        }
    }
}

#[cfg(feature = "wgpu")]
fn wgpu(index: Option<&str>, s: &str) -> Result<Device> {
    use burn::tensor::DeviceKind;
    let kind = match index {
        None => DeviceKind::DefaultDevice,
        Some(i) => DeviceKind::DiscreteGpu(
            i.parse()
                .map_err(|_| anyhow::anyhow!("--device {s}: {i:?} is not a GPU index"))?,
        ),
    };
    let device = Device::wgpu(kind);
    probe(&device, s)?;
    Ok(device)
}

/// wgpu picks its adapter on first use and panics when there is none, and an adapter without the atomics
/// burn's reductions need (wgpu's OpenGL fallback when no Vulkan driver is installed) fails inside the
/// first large reduction: run one now, so that either is an error naming the cause instead of a panic in
/// the middle of a command.
#[cfg(feature = "wgpu")]
fn probe(device: &Device, s: &str) -> Result<()> {
    use burn::tensor::Tensor;
    // Large enough for the atomic reduction kernels, below the size where burn 0.22's one-pass sum
    // runs out of workgroups on some adapters (mvmp_losses::sum_all).
    const N: usize = 1 << 17;
    let previous = std::panic::take_hook();
    // Silence the panic messages of wgpu's worker threads while probing; the error below says it all.
    std::panic::set_hook(Box::new(|_| {}));
    let d = device.clone();
    let result = std::panic::catch_unwind(move || {
        Tensor::<1>::ones([N], &d)
            .sum()
            .try_into_scalar::<f32>()
            .map_err(|e| format!("{e:?}"))
    });
    std::panic::set_hook(previous);
    let cause = match result {
        Ok(Ok(v)) if v == N as f32 => return Ok(()),
        Ok(Ok(v)) => format!("a test sum of {N} ones gave {v}"),
        Ok(Err(e)) => e,
        Err(e) => e
            .downcast_ref::<String>()
            .cloned()
            .or_else(|| e.downcast_ref::<&str>().map(|m| m.to_string()))
            .unwrap_or_else(|| "the backend panicked".into()),
    };
    bail!(
        "--device {s}: no usable GPU adapter ({}). Install the GPU's Vulkan driver (Metal on macOS, \
         DX12 on Windows); on Linux without a GPU, Debian's software Vulkan driver works: \
         `apt-get install mesa-vulkan-drivers libvulkan1`",
        cause.lines().map(str::trim).collect::<Vec<_>>().join(" ")
    )
}

#[cfg(not(feature = "wgpu"))]
fn wgpu(_index: Option<&str>, s: &str) -> Result<Device> {
    bail!(
        "--device {s}: this mvmp binary was built without the wgpu backend; rebuild with \
         `cargo build --release -p mvmp-cli --features wgpu` (on Linux without a GPU, install \
         mesa-vulkan-drivers and libvulkan1 for a software Vulkan driver)"
    )
}
