//! `--device` parsing. The device decides the backend at run time (burn 0.22); a backend that was not
//! compiled in gets an error that says how to get it.
use anyhow::{Result, bail};
use burn::tensor::Device;

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
    Ok(Device::wgpu(kind))
}

#[cfg(not(feature = "wgpu"))]
fn wgpu(_index: Option<&str>, s: &str) -> Result<Device> {
    bail!(
        "--device {s}: this mvmp binary was built without the wgpu backend; rebuild with \
         `cargo build --release -p mvmp-cli --features wgpu` (on Linux without a GPU, install \
         mesa-vulkan-drivers and libvulkan1 for a software Vulkan driver)"
    )
}
