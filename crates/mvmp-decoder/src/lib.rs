//! The MVMP-HMR decoder: person queries sampled from the fused volume at each root, the Human Transformer
//! Block (self-attention among people, cross-attention to the volume, FFN) and the SMPL-X heads.
pub mod htb;
pub mod queries;

pub use htb::{
    Decoder, DecoderConfig, DecoderOptions, DecoderOutput, HumanTransformerBlock, QueryInputs,
    height_features, lattice_offsets, point_encoding, sample_turned, scaled_read,
    standardise_channels,
};
pub use queries::{mean_params, params_vector, trilinear_sample};
