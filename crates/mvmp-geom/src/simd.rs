//! Where the fused CPU inference passes (SMPL-X, fusion) run, and the vector instruction set their kernels
//! use.
use burn::tensor::Device;

/// Whether `device` takes the fused SMPL-X pass: burn's flex backend without autodiff. (`Device` equality
/// does not tell autodiff flex from plain flex, hence both checks.) Fusion's fused pass runs on flex
/// under autodiff too, with its own backward (mvmp-fusion).
pub fn runs_fused(device: &Device) -> bool {
    !device.is_autodiff() && *device == Device::flex()
}

/// Detected at run time, so one binary runs everywhere and uses the widest registers it finds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Isa {
    /// AVX-512F: 16 float32 lanes.
    #[cfg(target_arch = "x86_64")]
    Avx512,
    /// AVX2 with FMA: 8 lanes.
    #[cfg(target_arch = "x86_64")]
    Avx2,
    /// Plain Rust, vectorised by the compiler for the build target.
    Portable,
}

impl Isa {
    pub fn detect() -> Isa {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f") {
                return Isa::Avx512;
            }
            if std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
            {
                return Isa::Avx2;
            }
        }
        Isa::Portable
    }
}
