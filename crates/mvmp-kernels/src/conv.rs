//! 2D convolutions in training as the matrix products they are (im2col): each kernel tap is a strided
//! slice of the zero-padded input, channels last, and the taps side by side multiply the weight. The
//! backward is then two matrix products and the slices' scatter, where flex's own convolution backward is
//! far slower when channels are few (4 views, forward / backward: a 3x3 over 16 channels at 56 x 56 3.9 /
//! 34 ms; a 1x1 0.24 / 13 ms, the same 1x1 as a product 0.68 / 0.57 ms). The tiny HRNet's forward and
//! backward went from 393-417 to 253-316 ms with it (`mvmp bench model --backward`).
//!
//! The taps are kept for the backward, `k^2` times the input, so convolutions over
//! [`PRODUCT_MAX_ELEMENTS`] tap values (the paper-size HRNet's highest branch) and every convolution
//! without autodiff take burn's own. 3D convolutions keep burn's: the same form made the tiny RootNet's
//! forward and backward slower (264-308 against 218-255 ms).
use burn::nn::PaddingConfig2d;
use burn::nn::conv::Conv2d;
use burn::tensor::ops::PadMode;
use burn::tensor::{Slice, Tensor};

/// Most tap values (output positions x kernel taps x input channels) of a convolution computed as a
/// product: 64 MiB of f32.
pub const PRODUCT_MAX_ELEMENTS: usize = 1 << 24;

/// `conv.forward(x)`, as a product when training and small enough (see the module's notes).
pub fn conv2d(conv: &Conv2d, x: Tensor<4>) -> Tensor<4> {
    let pad = match conv.padding {
        PaddingConfig2d::Valid => Some([(0, 0); 2]),
        PaddingConfig2d::Explicit(top, left, bottom, right) => Some([(top, bottom), (left, right)]),
        PaddingConfig2d::Same => None,
    };
    let plain = conv.dilation == [1; 2] && conv.groups == 1;
    match pad {
        Some(pad) if plain && x.is_autodiff() => {
            let [b, ci, h, w] = x.dims();
            let y = product::<4, 2>(
                x.clone().permute([0, 2, 3, 1]),
                [b, h, w, ci],
                conv.weight.val().permute([0, 2, 3, 1]),
                conv.bias.as_ref().map(|p| p.val()),
                conv.stride,
                pad,
            );
            y.map_or_else(|| conv.forward(x), |y| y.permute([0, 3, 1, 2]))
        }
        _ => conv.forward(x),
    }
}

/// The convolution of channels-last `x` (`dims` = [B, spatial.., C]) with channels-last `weight`
/// `[Co, k.., C]`: `[B, out spatial.., Co]`, or `None` when its taps would exceed the cap.
fn product<const D: usize, const S: usize>(
    x: Tensor<D>,
    dims: [usize; D],
    weight: Tensor<D>,
    bias: Option<Tensor<1>>,
    stride: [usize; S],
    pad: [(usize, usize); S],
) -> Option<Tensor<D>> {
    let wd = weight.dims();
    let (b, ci, co) = (dims[0], dims[D - 1], wd[0]);
    let k: [usize; S] = std::array::from_fn(|a| wd[a + 1]);
    // A kernel wider than the padded input has no output position: burn's convolution says so.
    let span: [Option<usize>; S] =
        std::array::from_fn(|a| (dims[a + 1] + pad[a].0 + pad[a].1).checked_sub(k[a]));
    if span.contains(&None) {
        return None;
    }
    let out: [usize; S] = std::array::from_fn(|a| span[a].unwrap_or(0) / stride[a] + 1);
    let (positions, taps) = (out.iter().product::<usize>(), k.iter().product::<usize>());
    if b * positions * taps * ci > PRODUCT_MAX_ELEMENTS {
        return None;
    }
    let mut x = x;
    if pad.iter().any(|&(l, r)| l + r > 0) {
        let mut pairs = pad.to_vec();
        pairs.push((0, 0));
        x = x.pad(pairs, PadMode::Constant(0.0));
    }
    let slices: Vec<Tensor<D>> = (0..taps)
        .map(|t| {
            let mut rest = t;
            let mut ranges = vec![Slice::full(); D];
            for a in (0..S).rev() {
                let at = rest % k[a];
                rest /= k[a];
                let end = at + stride[a] * (out[a] - 1) + 1;
                ranges[a + 1] = Slice::new(at as isize, Some(end as isize), stride[a] as isize);
            }
            x.clone().slice(ranges.as_slice())
        })
        .collect();
    let cols = Tensor::cat(slices, D - 1).reshape([b * positions, taps * ci]);
    let mut y = cols.matmul(weight.reshape([co, taps * ci]).transpose());
    if let Some(bias) = bias {
        y = y + bias.reshape([1, co]);
    }
    let mut shape = [b; D];
    shape[1..=S].copy_from_slice(&out);
    shape[D - 1] = co;
    Some(y.reshape(shape))
}
