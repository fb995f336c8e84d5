//! Convolutions in training as the matrix products they are: the zero-padded input's taps of every
//! output position side by side (the columns) multiply the weight. On flex the columns are one
//! operation ([`crate::im2col`], channels first, with its own col2im backward) and the product a
//! batched matmul whose output is already channels first; elsewhere each kernel tap is a strided slice
//! of the padded input, channels last. Flex's own convolution backward is far slower when channels are
//! few (4 views, forward / backward: a 3x3 over 16 channels at 56 x 56 3.9 / 34 ms; a 1x1 0.24 / 13
//! ms, the same 1x1 as a product 0.68 / 0.57 ms). The tiny HRNet's forward and backward went from
//! 393-417 to 253-316 ms with the slices, to 205-230 ms with a columns operation and to 72-89 ms with
//! the channels-first columns and the pointwise products below (`mvmp bench model --backward`).
//!
//! A 1 x 1 (x 1) convolution of stride 1 needs no columns: it is the weight times each batch item's
//! channels-first input as it lies, one batched product whose gradients autodiff derives, with no
//! transposes either way.
//!
//! The columns are kept for the backward, `k^2` (`k^3`) times the input, so convolutions over
//! [`PRODUCT_MAX_ELEMENTS`] tap values (the paper-size HRNet's highest branch) and every convolution
//! without autodiff take burn's own. 3D convolutions are products only on flex: as slices (27 of them)
//! they made the tiny RootNet's forward and backward slower (264-308 against 218-255 ms); with the
//! operation they are faster (211-217 against 240-246 ms).
use burn::nn::PaddingConfig2d;
use burn::nn::PaddingConfig3d;
use burn::nn::conv::{Conv2d, Conv3d};
use burn::tensor::ops::PadMode;
use burn::tensor::{Device, Tensor, s};

use crate::im2col::Columns;
use std::sync::atomic::{AtomicUsize, Ordering};

/// Most tap values (output positions x kernel taps x input channels) of a convolution computed as a
/// product: 64 MiB of f32.
pub const PRODUCT_MAX_ELEMENTS: usize = 1 << 24;

static PRODUCT_CAP: AtomicUsize = AtomicUsize::new(PRODUCT_MAX_ELEMENTS);

/// Set the cap on a product's tap values for the whole process ([`PRODUCT_MAX_ELEMENTS`] unless set);
/// returns the previous one. The training-memory estimate measures a model at a reduced scale with the
/// cap reduced alike, so that each convolution takes the path it takes at full scale.
pub fn set_product_cap(elements: usize) -> usize {
    PRODUCT_CAP.swap(elements, Ordering::Relaxed)
}

/// `conv.forward(x)`, as a product when training and small enough (see the module's notes).
pub fn conv2d(conv: &Conv2d, x: Tensor<4>) -> Tensor<4> {
    let pad = match conv.padding {
        PaddingConfig2d::Valid => Some([0; 4]),
        PaddingConfig2d::Explicit(top, left, bottom, right) => Some([top, left, bottom, right]),
        PaddingConfig2d::Same => None,
    };
    let plain = conv.dilation == [1; 2] && conv.groups == 1;
    match pad {
        Some([0, 0, 0, 0])
            if plain && x.is_autodiff() && pointwise(&conv.kernel_size, &conv.stride) =>
        {
            pointwise_conv(&conv.weight.val(), conv.bias.as_ref(), x)
        }
        Some(pad) if plain && x.is_autodiff() => {
            product(conv, x.clone(), pad).unwrap_or_else(|| conv.forward(x))
        }
        _ => conv.forward(x),
    }
}

/// Whether a kernel is 1 x 1 (x 1) with stride 1: a per-position product of the channels.
fn pointwise(kernel: &[usize], stride: &[usize]) -> bool {
    kernel.iter().chain(stride).all(|&n| n == 1)
}

/// A pointwise convolution in the channels-first layout it is given: `weight [Co, Ci, 1, ...]` times
/// each batch item's `x [B, Ci, ...]`, its positions flattened -> `[B, Co, ...]`. No columns and no
/// transposes: as a columns product the same 1x1 (4 views of 64 channels at 56 x 56, HRNet's first
/// layer) took 2.6-4.7 ms forward and backward, as this product 1.0-1.4 ms.
fn pointwise_conv<const D: usize, const K: usize>(
    weight: &Tensor<K>,
    bias: Option<&burn::module::Param<Tensor<1>>>,
    x: Tensor<D>,
) -> Tensor<D> {
    let mut dims = x.dims();
    let y = pointwise_product(weight, bias, x.flatten::<3>(2, D - 1));
    dims[1] = y.dims()[1];
    y.reshape(dims)
}

/// [`pointwise_conv`] on `x [B, Ci, P]` (P positions) -> `[B, Co, P]`.
fn pointwise_product<const K: usize>(
    weight: &Tensor<K>,
    bias: Option<&burn::module::Param<Tensor<1>>>,
    x: Tensor<3>,
) -> Tensor<3> {
    let co = weight.dims()[0];
    let y = weight.clone().reshape([1, co, x.dims()[1]]).matmul(x);
    match bias {
        Some(b) => y + b.val().reshape([1, co, 1]),
        None => y,
    }
}

/// `conv.forward(x)` for a 3D convolution: in training on flex, as a product of the columns
/// ([`crate::im2col`]) and the weight when small enough; otherwise burn's own.
pub fn conv3d(conv: &Conv3d, x: Tensor<5>) -> Tensor<5> {
    let pad = match conv.padding {
        PaddingConfig3d::Valid => [0; 3],
        PaddingConfig3d::Explicit(a, b, c) => [a, b, c],
        PaddingConfig3d::Same => return conv.forward(x),
    };
    let plain = conv.dilation == [1; 3] && conv.groups == 1;
    let fused = x.is_autodiff() && x.device() == Device::flex() && crate::im2col::fused_im2col();
    if !(plain && fused) {
        return conv.forward(x);
    }
    if pad == [0; 3] && pointwise(&conv.kernel_size, &conv.stride) {
        return pointwise_conv(&conv.weight.val(), conv.bias.as_ref(), x);
    }
    product3d(conv, x.clone(), pad).unwrap_or_else(|| conv.forward(x))
}

/// The 3D convolution as a product with symmetric padding `pad`; `None` when the kernel is wider than
/// the padded input or its taps would exceed the cap.
fn product3d(conv: &Conv3d, x: Tensor<5>, pad: [usize; 3]) -> Option<Tensor<5>> {
    let [b, ci, d, h, w] = x.dims();
    let co = conv.weight.dims()[0];
    let mut out = [0; 3];
    for (a, n) in [d, h, w].into_iter().enumerate() {
        out[a] = (n + 2 * pad[a]).checked_sub(conv.kernel_size[a])? / conv.stride[a] + 1;
    }
    let taps: usize = conv.kernel_size.iter().product();
    let outputs: usize = out.iter().product();
    if b * outputs * taps * ci > PRODUCT_CAP.load(Ordering::Relaxed) {
        return None;
    }
    let geometry = Columns {
        kernel: conv.kernel_size,
        stride: conv.stride,
        pad,
        out,
    };
    let y = planar_product(&conv.weight.val(), conv.bias.as_ref(), x, geometry);
    let [od, oh, ow] = out;
    Some(y.reshape([b, co, od, oh, ow]))
}

/// `weight [Co, Ci, k...]` times each batch item's planar columns of `x [B, Ci, D, H, W]`
/// ([`crate::im2col`]), plus the bias -> `[B, Co, Do * Ho * Wo]`, channels first as the input was.
fn planar_product<const K: usize>(
    weight: &Tensor<K>,
    bias: Option<&burn::module::Param<Tensor<1>>>,
    x: Tensor<5>,
    geometry: Columns,
) -> Tensor<3> {
    pointwise_product(weight, bias, crate::im2col::columns(x, geometry))
}

/// The convolution as a product, `pad` = (top, left, bottom, right); `None` when the kernel is wider
/// than the padded input (burn's convolution says so) or its taps would exceed the cap.
fn product(conv: &Conv2d, x: Tensor<4>, pad: [usize; 4]) -> Option<Tensor<4>> {
    let [b, ci, h, w] = x.dims();
    let [top, left, bottom, right] = pad;
    let ([kh, kw], [sh, sw]) = (conv.kernel_size, conv.stride);
    let co = conv.weight.dims()[0];
    let ho = (h + top + bottom).checked_sub(kh)? / sh + 1;
    let wo = (w + left + right).checked_sub(kw)? / sw + 1;
    if b * ho * wo * kh * kw * ci > PRODUCT_CAP.load(Ordering::Relaxed) {
        return None;
    }
    if x.device() == Device::flex() && crate::im2col::fused_im2col() {
        let geometry = Columns {
            kernel: [1, kh, kw],
            stride: [1, sh, sw],
            pad: [0, top, left],
            out: [1, ho, wo],
        };
        let y = planar_product(
            &conv.weight.val(),
            conv.bias.as_ref(),
            x.unsqueeze_dim(2),
            geometry,
        );
        return Some(y.reshape([b, co, ho, wo]));
    }
    // The weight's taps in the columns' order: [Co, kh, kw, Ci].
    let weight = conv
        .weight
        .val()
        .permute([0, 2, 3, 1])
        .reshape([co, kh * kw * ci]);
    let mut y = tensor_columns(x, [kh, kw], [sh, sw], pad, [ho, wo]).matmul(weight.transpose());
    if let Some(bias) = &conv.bias {
        y = y + bias.val().reshape([1, co]);
    }
    Some(y.reshape([b, ho, wo, co]).permute([0, 3, 1, 2]))
}

/// [`crate::im2col::columns`] as tensor ops on any backend: the zero-padded input channels last, one
/// strided slice per kernel tap, side by side.
fn tensor_columns(
    x: Tensor<4>,
    [kh, kw]: [usize; 2],
    [sh, sw]: [usize; 2],
    pad: [usize; 4],
    [ho, wo]: [usize; 2],
) -> Tensor<2> {
    let [b, ci, _, _] = x.dims();
    let [top, left, bottom, right] = pad;
    let mut x = x.permute([0, 2, 3, 1]); // [B, H, W, C]
    if pad != [0; 4] {
        x = x.pad(
            [(top, bottom), (left, right), (0, 0)],
            PadMode::Constant(0.0),
        );
    }
    let (si, sj) = (sh as isize, sw as isize);
    let taps: Vec<Tensor<4>> = (0..kh * kw)
        .map(|t| {
            let (i, j) = (t / kw, t % kw);
            x.clone()
                .slice(s![.., i..i + sh * (ho - 1) + 1; si, j..j + sw * (wo - 1) + 1; sj, ..])
        })
        .collect();
    Tensor::cat(taps, 3).reshape([b * ho * wo, kh * kw * ci])
}
