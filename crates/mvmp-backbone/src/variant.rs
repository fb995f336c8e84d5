//! The backbone variants a model config names (`backbone = "vit_large_14"`, `hrnet = "hrnet_w32"`).
use serde::{Deserialize, Serialize};

use crate::{HRNetConfig, ViTConfig};

/// The ViT variants: the tiny CPU model and DINOv2's S/14, B/14 and L/14.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum VitVariant {
    #[serde(rename = "tiny")]
    Tiny,
    #[serde(rename = "vit_small_14")]
    Small14,
    #[serde(rename = "vit_base_14")]
    Base14,
    #[serde(rename = "vit_large_14")]
    Large14,
}

impl VitVariant {
    pub const ALL: [VitVariant; 4] = [
        VitVariant::Tiny,
        VitVariant::Small14,
        VitVariant::Base14,
        VitVariant::Large14,
    ];

    pub fn name(self) -> &'static str {
        match self {
            VitVariant::Tiny => "tiny",
            VitVariant::Small14 => "vit_small_14",
            VitVariant::Base14 => "vit_base_14",
            VitVariant::Large14 => "vit_large_14",
        }
    }

    pub fn config(self) -> ViTConfig {
        match self {
            VitVariant::Tiny => ViTConfig::tiny(),
            VitVariant::Small14 => ViTConfig::vit_small_14(),
            VitVariant::Base14 => ViTConfig::vit_base_14(),
            VitVariant::Large14 => ViTConfig::vit_large_14(),
        }
    }
}

impl std::str::FromStr for VitVariant {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        VitVariant::ALL
            .into_iter()
            .find(|v| v.name() == s)
            .ok_or_else(|| {
                format!("{s:?}: expected tiny, vit_small_14, vit_base_14 or vit_large_14")
            })
    }
}

impl std::fmt::Display for VitVariant {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// The HRNet variants: the tiny and small CPU models and the reference W32 and W48.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum HrnetVariant {
    #[serde(rename = "tiny")]
    Tiny,
    #[serde(rename = "small")]
    Small,
    #[serde(rename = "hrnet_w32")]
    W32,
    #[serde(rename = "hrnet_w48")]
    W48,
}

impl HrnetVariant {
    pub const ALL: [HrnetVariant; 4] = [
        HrnetVariant::Tiny,
        HrnetVariant::Small,
        HrnetVariant::W32,
        HrnetVariant::W48,
    ];

    pub fn name(self) -> &'static str {
        match self {
            HrnetVariant::Tiny => "tiny",
            HrnetVariant::Small => "small",
            HrnetVariant::W32 => "hrnet_w32",
            HrnetVariant::W48 => "hrnet_w48",
        }
    }

    /// The network for `joints` heatmaps.
    pub fn config(self, joints: usize) -> HRNetConfig {
        match self {
            HrnetVariant::Tiny => HRNetConfig::tiny(joints),
            HrnetVariant::Small => HRNetConfig::small(joints),
            HrnetVariant::W32 => HRNetConfig::hrnet_w32(joints),
            HrnetVariant::W48 => HRNetConfig::hrnet_w48(joints),
        }
    }
}

impl std::str::FromStr for HrnetVariant {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        HrnetVariant::ALL
            .into_iter()
            .find(|v| v.name() == s)
            .ok_or_else(|| format!("{s:?}: expected tiny, small, hrnet_w32 or hrnet_w48"))
    }
}

impl std::fmt::Display for HrnetVariant {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}
