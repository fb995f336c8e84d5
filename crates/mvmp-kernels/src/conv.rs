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
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

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
        Some(pad) if plain && x.is_autodiff() => direct2d(conv, x.clone(), pad)
            .or_else(|| product(conv, x.clone(), pad))
            .unwrap_or_else(|| conv.forward(x)),
        _ => conv.forward(x),
    }
}

/// A stride-1 "same" 2D convolution (HRNet's 3 x 3s) as a 3D one of depth one, directly where
/// [`crate::direct::conv3d`] takes it: the image is the volume's last two axes, so that a slab is the
/// whole image and its run wastes only the padding columns. With it the tiny HRNet's forward and
/// backward took 51-54 ms against 65 as products of columns (`mvmp bench model --backward`, 2 cores).
pub(crate) fn direct2d(
    conv: &Conv2d,
    x: Tensor<4>,
    [top, left, bottom, right]: [usize; 4],
) -> Option<Tensor<4>> {
    if conv.stride != [1; 2] || top != bottom || left != right {
        return None;
    }
    let weight = conv.weight.val().unsqueeze_dim::<5>(2);
    let bias = conv.bias.as_ref().map(|b| b.val());
    let y = crate::direct::conv3d(x.unsqueeze_dim::<5>(2), weight, bias, [0, top, left])?;
    Some(y.squeeze_dim::<4>(2))
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
    let y = crate::product::weight_product(weight.clone().reshape([co, x.dims()[1]]), x);
    match bias {
        Some(b) => y + b.val().reshape([1, co, 1]),
        None => y,
    }
}

/// `conv.forward(x)` for a 3D convolution: in training on flex, directly where [`crate::direct`]
/// takes it (a "same" kernel over a volume most of whose run is output), else folded
/// ([`folded_conv3d`]) or as a product of the columns ([`crate::im2col`]) and the weight when small
/// enough; otherwise burn's own.
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
    if conv.stride == [1; 3] {
        let bias = conv.bias.as_ref().map(|b| b.val());
        if let Some(y) = crate::direct::conv3d(x.clone(), conv.weight.val(), bias, pad) {
            return y;
        }
    }
    if let Some(y) = folded_conv3d(conv, x.clone()) {
        return y;
    }
    product3d(conv, x.clone(), pad).unwrap_or_else(|| conv.forward(x))
}

static FOLD_DEPTH: AtomicBool = AtomicBool::new(true);

/// Whether training on flex folds a shallow last axis into the channels ([`folded_conv3d`]; the
/// default) or not; process-wide, so that a benchmark can time both.
pub fn set_fold_depth(on: bool) {
    FOLD_DEPTH.store(on, Ordering::Relaxed);
}

/// Most multiply-adds of the folded form per useful one (taps that fall inside the input).
const FOLD_MAX_WASTE: f64 = 1.5;
/// Fewest kernel taps along the folded axis: the tiny RootNet's 3^3 blocks at a quarter of its
/// resolution (8 x 8 x 2) wasted nothing folded but took 3.7-4.8 ms forward and backward against
/// 2.3-2.6 as 3D products (`--example rootnet_parts`).
const FOLD_MIN_TAPS: usize = 5;

/// Multiply-adds along the last axis of the folded form (every output row against every input row)
/// per useful one, for an input `depth` deep, a kernel `k` deep and padding `pad`; `None` if the
/// kernel is wider than the padded input.
pub fn fold_waste(depth: usize, k: usize, pad: usize) -> Option<f64> {
    let out = (depth + 2 * pad).checked_sub(k)? + 1;
    let useful: usize = (0..out)
        .map(|o| {
            (0..k)
                .filter(|&t| (pad..pad + depth).contains(&(o + t)))
                .count()
        })
        .sum();
    Some((out * depth) as f64 / useful.max(1) as f64)
}

/// A 3D convolution (stride 1, one group) over a volume shallow along its last axis, as a 2D one
/// over the first two with that axis folded into the channels: input channel `(ci, zi)`, output
/// channel `(co, zo)`, and the kernel's taps along the axis placed where `zi - zo` selects them (zero
/// elsewhere). The tiny RootNet's 7^3 front (17 channels to 8 over 32 x 32 x 8) is then a product of
/// 64 rows by 6664 over 1024 positions instead of 8 rows by 5831 over 8192, at 1.45 times the
/// multiply-adds but in a shape the GEMM runs near its speed, and its columns are 27 MB instead of
/// 191 (`--example rootnet_parts`: its forward and backward 27-30 ms against 64). In training on flex
/// where the kernel is at least [`FOLD_MIN_TAPS`] deep, the folded form wastes at most
/// [`FOLD_MAX_WASTE`] times the useful work and its columns fit the product cap; `None` otherwise.
pub fn folded_conv3d(conv: &Conv3d, x: Tensor<5>) -> Option<Tensor<5>> {
    let PaddingConfig3d::Explicit(px, py, pz) = conv.padding else {
        return None;
    };
    let plain = conv.dilation == [1; 3] && conv.groups == 1 && conv.stride == [1; 3];
    let on = FOLD_DEPTH.load(Ordering::Relaxed) && crate::im2col::fused_im2col();
    if !(plain && on && x.is_autodiff() && x.device() == Device::flex()) {
        return None;
    }
    let [b, ci, nx, ny, nz] = x.dims();
    let [kx, ky, kz] = conv.kernel_size;
    if kz < FOLD_MIN_TAPS || fold_waste(nz, kz, pz)? > FOLD_MAX_WASTE {
        return None;
    }
    let oz = nz + 2 * pz - kz + 1;
    let ox = (nx + 2 * px).checked_sub(kx)? + 1;
    let oy = (ny + 2 * py).checked_sub(ky)? + 1;
    if b * ox * oy * kx * ky * ci * nz > PRODUCT_CAP.load(Ordering::Relaxed) {
        return None;
    }
    let co = conv.weight.dims()[0];
    let weight = folded_weight(conv.weight.val(), nz, pz);
    let x2 = x.permute([0, 1, 4, 2, 3]).reshape([b, ci * nz, 1, nx, ny]);
    let geometry = Columns {
        kernel: [1, kx, ky],
        stride: [1; 3],
        pad: [0, px, py],
        out: [1, ox, oy],
    };
    let y = planar_product(&weight, None, x2, geometry); // [B, Co * Zo, Xo * Yo]
    let y = y.reshape([b, co, oz, ox, oy]).permute([0, 1, 3, 4, 2]);
    Some(match &conv.bias {
        Some(bias) => y + bias.val().reshape([1, co, 1, 1, 1]),
        None => y,
    })
}

/// `weight [Co, Ci, kx, ky, kz]` -> `[Co * Zo, Ci * Zi, 1, kx, ky]` for an input `depth` deep padded
/// by `pad`: entry `(co, zo), (ci, zi)` holds tap `zi + pad - zo` where that is a tap, else zero. A
/// product with a constant selection, so that the kernel's gradient is gathered back by autodiff.
fn folded_weight(weight: Tensor<5>, depth: usize, pad: usize) -> Tensor<5> {
    let [co, ci, kx, ky, kz] = weight.dims();
    let out = depth + 2 * pad - kz + 1;
    let mut select = vec![0f32; kz * out * depth];
    for t in 0..kz {
        for o in 0..out {
            if let Some(i) = (o + t).checked_sub(pad).filter(|&i| i < depth) {
                select[(t * out + o) * depth + i] = 1.0;
            }
        }
    }
    let select = Tensor::<2>::from_data(
        burn::tensor::TensorData::new(select, [kz, out * depth]),
        &weight.device(),
    );
    weight
        .reshape([co * ci * kx * ky, kz])
        .matmul(select)
        .reshape([co, ci, kx, ky, out, depth])
        .permute([0, 4, 1, 5, 2, 3])
        .reshape([co * out, ci * depth, 1, kx, ky])
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
