//! What the fused CPU passes (SMPL-X, fusion) share: the vector instruction set their kernels use, and
//! the pointer their parallel workers write through.

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

/// A pointer that parallel workers write through, each to its own disjoint part of one output (the
/// callers say which part is whose).
#[derive(Clone, Copy)]
pub struct SendPtr(pub *mut f32);
// SAFETY: every user writes through it to ranges no other worker touches (see each call site).
unsafe impl Send for SendPtr {}
unsafe impl Sync for SendPtr {}

impl SendPtr {
    /// A method, so that closures capture the whole (Send) wrapper rather than its raw field.
    pub fn get(self) -> *mut f32 {
        self.0
    }
}
