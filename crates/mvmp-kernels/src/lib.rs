//! Tensor operations that carry their own backward pass, registered with burn as a backend extension:
//! each backend runs the forward in its own ops, and under autodiff the backward is the one written
//! here rather than the one burn would derive from the forward's ops: tiled attention, a transformer
//! block recomputed in its backward, a convolution's columns (im2col, with col2im as its backward),
//! a 3D convolution whose gradients are tiled products (`wgrad`), a "same" 3D convolution
//! of few channels computed directly, forward and backward (`direct`), the weight's product that ends every
//! product convolution (`product`), batch and group norm (with the ReLU that follows them), the
//! residual join `relu(a + b)` and GELU on flex (with `vmath`'s vectorised `exp` and error
//! function). `blend` is the weight average's update on flex in one pass (no backward: it runs
//! outside autodiff).
//! `conv` holds convolutions written as matrix products for training. `cpu` and `panel` hold what the fused CPU passes
//! share: instruction-set dispatch, the pointer of their parallel writes, and the SMPL-X panel products.

pub mod attention;
mod attention_host;
pub mod blend;
pub mod conv;
pub mod cpu;
pub mod direct;
pub mod gelu;
pub mod host;
pub mod im2col;
pub mod layer_norm;
pub mod linear;
pub mod norm;
pub mod panel;
pub mod product;
pub mod recompute;
pub mod residual;
pub mod vmath;
pub mod wgrad;

pub use attention::{DEFAULT_BLOCK, attention, packed_self_attention, plain_attention};

#[cfg(test)]
mod tests;
