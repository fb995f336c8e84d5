//! The tiled attention against burn's plain attention: values and the gradients of q, k and v.

use crate::{attention, plain_attention};
use burn::tensor::{Device, Distribution, Tensor, TensorData};
use std::cell::Cell;

const TOL: f32 = 1e-5;

thread_local! {
    /// Each test's own random stream: burn's generator is one per device, shared by the tests running
    /// in parallel, so a test's draws (and its worst rounding difference) would depend on the others.
    static STREAM: Cell<u64> = const { Cell::new(1) };
}

/// Restart this thread's random stream.
fn seed(s: u64) {
    STREAM.with(|c| c.set(s));
}

/// Normal values of standard deviation `spread` from this thread's stream (splitmix64, Box-Muller).
fn normal<const D: usize>(dims: [usize; D], spread: f64, device: &Device) -> Tensor<D> {
    let next = || {
        STREAM.with(|c| {
            let mut z = c.get().wrapping_add(0x9e37_79b9_7f4a_7c15);
            c.set(z);
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        })
    };
    let n: usize = dims.iter().product();
    let values: Vec<f32> = (0..n)
        .map(|_| {
            let (u, v) = (1.0 - next(), next());
            (spread * (-2.0 * u.ln()).sqrt() * (std::f64::consts::TAU * v).cos()) as f32
        })
        .collect();
    Tensor::from_data(TensorData::new(values, dims), device)
}

fn random(dims: [usize; 4], spread: f64, device: &Device) -> Tensor<4> {
    normal(dims, spread, device)
}

fn max_abs_diff(a: Tensor<4>, b: Tensor<4>) -> f32 {
    (a - b).abs().max().into_scalar::<f32>()
}

/// Values and gradients of both paths on one autodiff device; returns the worst difference of each.
fn compare(device: &Device, nq: usize, nk: usize, block: usize, spread: f64) -> [f32; 4] {
    let (b, h, d, dv) = (2, 3, 8, 5);
    let q0 = random([b, h, nq, d], spread, device);
    let k0 = random([b, h, nk, d], spread, device);
    let v0 = random([b, h, nk, dv], 1.0, device);
    // A random weighting of the output makes every output element's gradient different.
    let w = random([b, h, nq, dv], 1.0, device);
    let scale = 1.0 / (d as f64).sqrt();
    let run = |tiled: bool| {
        let (q, k, v) = (
            q0.clone().require_grad(),
            k0.clone().require_grad(),
            v0.clone().require_grad(),
        );
        let out = if tiled {
            attention(q.clone(), k.clone(), v.clone(), scale, block)
        } else {
            plain_attention(q.clone(), k.clone(), v.clone(), scale)
        };
        let grads = (out.clone() * w.clone()).sum().backward();
        let g = |t: &Tensor<4>| t.grad(&grads).expect("a gradient");
        [out.detach(), g(&q), g(&k), g(&v)]
    };
    let (tiled, plain) = (run(true), run(false));
    let mut worst = [0.0; 4];
    for (i, (a, b)) in tiled.into_iter().zip(plain).enumerate() {
        worst[i] = max_abs_diff(a, b);
    }
    worst
}

fn assert_matches(device: Device) {
    seed(7);
    // One tile, tiles that divide the tokens, tiles that do not, cross-attention (Nq != Nk), and
    // peaked scores where the running maximum changes from tile to tile.
    for (nq, nk, block, spread) in [
        (9, 9, 64, 1.0),
        (32, 32, 8, 1.0),
        (37, 29, 8, 1.0),
        (5, 41, 7, 1.0),
        (23, 23, 4, 2.0),
        (150, 70, 512, 1.0),
    ] {
        let worst = compare(&device, nq, nk, block, spread);
        for (name, w) in ["output", "dq", "dk", "dv"].iter().zip(worst) {
            assert!(
                w < TOL,
                "{name} differs by {w} (nq {nq}, nk {nk}, block {block}, spread {spread})"
            );
        }
    }
}

#[test]
fn tiled_attention_equals_plain_attention_on_flex() {
    assert_matches(Device::flex().autodiff());
}

#[test]
#[allow(deprecated)]
fn tiled_attention_equals_plain_attention_on_ndarray() {
    assert_matches(Device::ndarray().autodiff());
}

#[test]
fn tiled_attention_runs_without_autodiff() {
    let device = Device::flex();
    let (q, k, v) = (
        random([1, 2, 13, 4], 1.0, &device),
        random([1, 2, 11, 4], 1.0, &device),
        random([1, 2, 11, 3], 1.0, &device),
    );
    let diff = max_abs_diff(
        attention(q.clone(), k.clone(), v.clone(), 0.5, 4),
        plain_attention(q, k, v, 0.5),
    );
    assert!(diff < TOL, "forward differs by {diff}");
}

#[test]
fn zero_queries_give_an_empty_output() {
    let device = Device::flex();
    let out = attention(
        random([1, 2, 0, 4], 1.0, &device),
        random([1, 2, 3, 4], 1.0, &device),
        random([1, 2, 3, 5], 1.0, &device),
        0.5,
        4,
    );
    assert_eq!(out.dims(), [1, 2, 0, 5]);
}

/// q, k and v as the ViT makes them: views (narrowed, permuted, reshaped) of one projection, whose
/// gradient gathers all three.
#[test]
fn views_of_one_projection_get_their_gradients() {
    let device = Device::flex().autodiff();
    seed(3);
    let (b, n, h, d) = (1, 26, 3, 64);
    let x = normal([b, n, 3 * h * d], 1.0, &device).require_grad();
    let w = random([b, h, n, d], 1.0, &device);
    let run = |tile: Option<usize>| {
        let qkv = x.clone().reshape([b, n, 3, h, d]).permute([2, 0, 3, 1, 4]);
        let q = qkv.clone().narrow(0, 0, 1).reshape([b, h, n, d]);
        let k = qkv.clone().narrow(0, 1, 1).reshape([b, h, n, d]);
        let v = qkv.narrow(0, 2, 1).reshape([b, h, n, d]);
        let out = match tile {
            Some(t) => attention(q, k, v, 0.125, t),
            None => plain_attention(q, k, v, 0.125),
        };
        let g = (out * w.clone()).sum().backward();
        x.grad(&g).unwrap()
    };
    let (a, b2) = (run(Some(8)), run(None));
    let diff = (a.clone() - b2).abs().max().into_scalar::<f32>();
    let scale = a.abs().max().into_scalar::<f32>();
    assert!(
        diff / scale < TOL,
        "input gradient differs by {diff} (largest {scale})"
    );
}

mod recompute {
    use super::{TOL, normal, random, seed};
    use crate::recompute::{BlockParams, BlockShape, block, param};
    use burn::tensor::activation::gelu;
    use burn::tensor::module::{layer_norm, linear};
    use burn::tensor::{Device, Tensor};

    const C: usize = 12;
    const HIDDEN: usize = 20;
    const HEADS: usize = 3;
    const EPS: f64 = 1e-6;

    /// The 14 parameters in `BlockParams`' order, with their shapes.
    fn params(device: &Device) -> Vec<Tensor<2>> {
        let shapes = [
            [1, C],
            [1, C],
            [C, 3 * C],
            [1, 3 * C],
            [C, C],
            [1, C],
            [1, C],
            [1, C],
            [1, C],
            [C, HIDDEN],
            [1, HIDDEN],
            [HIDDEN, C],
            [1, C],
            [1, C],
        ];
        shapes
            .iter()
            .map(|&s| normal(s, 0.5, device).require_grad())
            .collect()
    }

    fn row(t: &Tensor<2>) -> Tensor<1> {
        t.clone().squeeze_dim(0)
    }

    /// The block in burn's tensor ops: the reference.
    fn reference(x: Tensor<3>, p: &[Tensor<2>]) -> Tensor<3> {
        let [b, n, _] = x.dims();
        let d = C / HEADS;
        let h = layer_norm(x.clone(), row(&p[0]), Some(row(&p[1])), EPS);
        let qkv = linear(h, p[2].clone(), Some(row(&p[3])))
            .reshape([b, n, 3, HEADS, d])
            .permute([2, 0, 3, 1, 4]);
        let part = |i| qkv.clone().narrow(0, i, 1).reshape([b, HEADS, n, d]);
        let att = crate::plain_attention(part(0), part(1), part(2), 1.0 / (d as f64).sqrt());
        let att = att.swap_dims(1, 2).reshape([b, n, C]);
        let x = x + linear(att, p[4].clone(), Some(row(&p[5]))) * p[6].clone().unsqueeze::<3>();
        let h = layer_norm(x.clone(), row(&p[7]), Some(row(&p[8])), EPS);
        let m = linear(
            gelu(linear(h, p[9].clone(), Some(row(&p[10])))),
            p[11].clone(),
            Some(row(&p[12])),
        );
        x + m * p[13].clone().unsqueeze::<3>()
    }

    fn recomputed(x: Tensor<3>, p: &[Tensor<2>], tile: usize) -> Tensor<3> {
        let r = |i: usize| param(row(&p[i]));
        let params = BlockParams {
            norm1_gamma: r(0),
            norm1_beta: r(1),
            qkv_weight: param(p[2].clone()),
            qkv_bias: r(3),
            proj_weight: param(p[4].clone()),
            proj_bias: r(5),
            ls1: r(6),
            norm2_gamma: r(7),
            norm2_beta: r(8),
            fc1_weight: param(p[9].clone()),
            fc1_bias: r(10),
            fc2_weight: param(p[11].clone()),
            fc2_bias: r(12),
            ls2: r(13),
        };
        block(
            x,
            params,
            BlockShape {
                heads: HEADS,
                tile,
                eps: EPS,
            },
        )
    }

    fn largest_difference(device: Device) -> f32 {
        seed(11);
        let x = random([2, 19, C, 1], 1.0, &device)
            .squeeze_dim::<3>(3)
            .require_grad();
        let p = params(&device);
        let w = random([2, 19, C, 1], 1.0, &device).squeeze_dim::<3>(3);
        let run = |recompute: bool| {
            let out = if recompute {
                recomputed(x.clone(), &p, 8)
            } else {
                reference(x.clone(), &p)
            };
            let grads = (out.clone() * w.clone()).sum().backward();
            let mut all = vec![out.detach().flatten::<1>(0, 2)];
            all.push(x.grad(&grads).expect("d/dx").flatten::<1>(0, 2));
            all.extend(
                p.iter()
                    .map(|t| t.grad(&grads).expect("d/dparam").flatten::<1>(0, 1)),
            );
            all
        };
        let (a, b) = (run(true), run(false));
        a.into_iter()
            .zip(b)
            .map(|(a, b)| (a - b).abs().max().into_scalar::<f32>())
            .fold(0.0, f32::max)
    }

    /// The recomputed block equals the block in burn's ops: output, and the gradients of the input and of
    /// all 14 parameters.
    #[test]
    fn a_recomputed_block_has_the_gradients_of_the_stored_one_on_flex() {
        let worst = largest_difference(Device::flex().autodiff());
        assert!(worst < TOL, "differs by {worst}");
    }

    #[test]
    #[allow(deprecated)]
    fn a_recomputed_block_has_the_gradients_of_the_stored_one_on_ndarray() {
        let worst = largest_difference(Device::ndarray().autodiff());
        assert!(worst < TOL, "differs by {worst}");
    }
}

/// The largest relative difference of each pair: values and gradients from two ways of computing one thing.
fn assert_close(a: Vec<Tensor<1>>, b: Vec<Tensor<1>>, what: &str) {
    assert_eq!(a.len(), b.len());
    for (i, (a, b)) in a.into_iter().zip(b).enumerate() {
        let scale = b.clone().abs().max().into_scalar::<f32>().max(1e-6);
        let diff = (a - b).abs().max().into_scalar::<f32>() / scale;
        assert!(
            diff < 1e-5,
            "{what}: output/d input/d weight/d bias [{i}] differs by {diff}"
        );
    }
}

/// 2D convolutions as products equal burn's: values and the gradients of input, weight and bias, for
/// HRNet's 1x1s (pointwise products, with and without a bias; a stride-2 1x1 is a columns product), 3x3s and stride-2 3x3s, an uneven padding and a kernel that does not fit the input a
/// whole number of times; on flex (the im2col operation) and on ndarray (the columns as tensor ops).
#[test]
fn convolutions_as_products_are_the_convolutions_2d() {
    #[allow(deprecated)]
    for d in [Device::flex().autodiff(), Device::ndarray().autodiff()] {
        products_are_convolutions(&d);
    }
}

fn products_are_convolutions(d: &Device) {
    use burn::nn::PaddingConfig2d;
    use burn::nn::conv::Conv2dConfig;
    seed(3);
    for (k, stride, pad, bias) in [
        (1, 1, (0, 0, 0, 0), true),
        (1, 1, (0, 0, 0, 0), false),
        (1, 2, (0, 0, 0, 0), true),
        (3, 1, (1, 1, 1, 1), false),
        (3, 2, (1, 1, 1, 1), true),
        (3, 2, (0, 2, 1, 0), false),
        (2, 3, (0, 0, 0, 0), true),
    ] {
        let conv = Conv2dConfig::new([5, 7], [k, k])
            .with_stride([stride, stride])
            .with_padding(PaddingConfig2d::Explicit(pad.0, pad.1, pad.2, pad.3))
            .with_bias(bias)
            .init(d);
        let x = normal([2, 5, 6, 9], 1.0, d).require_grad();
        let w = normal(conv.forward(x.clone()).dims(), 1.0, d);
        let run = |product: bool| {
            let y = match product {
                true => crate::conv::conv2d(&conv, x.clone()),
                false => conv.forward(x.clone()),
            };
            let grads = (y.clone() * w.clone()).sum().backward();
            let mut out = vec![
                y.detach().flatten::<1>(0, 3),
                x.grad(&grads).unwrap().flatten::<1>(0, 3),
                conv.weight.val().grad(&grads).unwrap().flatten::<1>(0, 3),
            ];
            out.extend(conv.bias.as_ref().map(|b| b.val().grad(&grads).unwrap()));
            out
        };
        assert_close(
            run(true),
            run(false),
            &format!("{d:?}: kernel {k} stride {stride} pad {pad:?}"),
        );
    }
}

/// A convolution's output `y` of `x` and the gradients of `x`, `weight` and `bias` under a fixed random
/// weighting of the output (drawn with `probe_seed`), each flattened.
fn outputs_and_gradients<const D: usize>(
    y: Tensor<D>,
    x: &Tensor<D>,
    weight: &Tensor<D>,
    bias: Option<&Tensor<1>>,
    probe_seed: u64,
) -> Vec<Tensor<1>> {
    seed(probe_seed);
    let probe = normal(y.dims(), 1.0, &x.device());
    let grads = (y.clone() * probe).sum().backward();
    let mut out = vec![
        y.detach().flatten::<1>(0, D - 1),
        x.grad(&grads).unwrap().flatten::<1>(0, D - 1),
        weight.grad(&grads).unwrap().flatten::<1>(0, D - 1),
    ];
    out.extend(bias.map(|b| b.grad(&grads).unwrap()));
    out
}

/// A 3D convolution's output and its gradients in the input, weight and bias under a fixed random
/// weighting of the output (seeded), computed by `f`.
fn conv3d_outputs(
    conv: &burn::nn::conv::Conv3d,
    x: &Tensor<5>,
    f: impl Fn(&burn::nn::conv::Conv3d, Tensor<5>) -> Tensor<5>,
) -> Vec<Tensor<1>> {
    let x = x.clone().require_grad();
    let y = f(conv, x.clone());
    let bias = conv.bias.as_ref().map(|b| b.val());
    outputs_and_gradients(y, &x, &conv.weight.val(), bias.as_ref(), 99)
}

/// 3D convolutions as products of columns equal burn's: values and the gradients of input, weight and
/// bias, for the RootNet's 3x3x3 and 1x1x1, a stride-2 kernel and an axis the kernel does not fit a whole
/// number of times.
#[test]
fn convolutions_as_products_are_the_convolutions_3d() {
    use burn::nn::PaddingConfig3d;
    use burn::nn::conv::Conv3dConfig;
    let d = Device::flex().autodiff();
    seed(5);
    for (k, stride, pad, bias) in [
        (3, 1, 1, true),
        (1, 1, 0, true),
        (1, 1, 0, false),
        (3, 2, 1, false),
        (2, 1, 0, true),
    ] {
        let conv = Conv3dConfig::new([3, 4], [k; 3])
            .with_stride([stride; 3])
            .with_padding(PaddingConfig3d::Explicit(pad, pad, pad))
            .with_bias(bias)
            .init(&d);
        let x = normal([2, 3, 5, 6, 7], 1.0, &d);
        assert_close(
            conv3d_outputs(&conv, &x, crate::conv::conv3d),
            conv3d_outputs(&conv, &x, |c, x| c.forward(x)),
            &format!("kernel {k} stride {stride} pad {pad}"),
        );
    }
}

/// A shallow last axis folded into the channels gives burn's 3D convolution: values and the gradients
/// of input, weight and bias, for the RootNet's front (7^3 over 8 deep, padding 3), a kernel as deep
/// as the input without padding, uneven kernel sides, and a batch of two. Each case must take the
/// folded path.
#[test]
fn folded_depth_convolutions_are_the_convolutions() {
    use burn::nn::PaddingConfig3d;
    use burn::nn::conv::{Conv3d, Conv3dConfig};
    let d = Device::flex().autodiff();
    seed(8);
    for (ci, co, kernel, pad, dims, bias) in [
        (3, 2, [7, 7, 7], [3, 3, 3], [1, 9, 8, 8], true),
        (2, 3, [3, 5, 6], [1, 2, 0], [2, 5, 7, 6], false),
        (4, 2, [5, 5, 5], [2, 2, 2], [1, 6, 6, 6], true),
    ] {
        let conv = Conv3dConfig::new([ci, co], kernel)
            .with_padding(PaddingConfig3d::Explicit(pad[0], pad[1], pad[2]))
            .with_bias(bias)
            .init(&d);
        let [b, nx, ny, nz] = dims;
        let x = normal([b, ci, nx, ny, nz], 1.0, &d);
        let folded = |c: &Conv3d, x| crate::conv::folded_conv3d(c, x).expect("the folded path");
        assert_close(
            conv3d_outputs(&conv, &x, folded),
            conv3d_outputs(&conv, &x, |c, x| c.forward(x)),
            &format!("kernel {kernel:?} pad {pad:?}"),
        );
    }
}

/// The folded form's extra work along the axis, counted by hand: 8 deep, kernel 7, padding 3 has
/// 4 + 5 + 6 + 7 + 7 + 6 + 5 + 4 = 44 useful taps against 8 x 8; without padding a kernel as deep as
/// the input wastes nothing; a kernel wider than the padded input has no form.
#[test]
fn the_fold_waste_is_counted_per_tap() {
    use crate::conv::fold_waste;
    assert_eq!(fold_waste(8, 7, 3), Some(64.0 / 44.0));
    assert_eq!(fold_waste(6, 6, 0), Some(1.0));
    assert_eq!(fold_waste(2, 7, 1), None);
}

/// Without autodiff, or over the size cap, the convolution is burn's own (the same values).
#[test]
fn convolutions_without_autodiff_or_too_large_are_burns() {
    use burn::nn::conv::Conv2dConfig;
    let d = Device::flex();
    let conv = Conv2dConfig::new([2, 3], [3, 3]).init(&d);
    let x = Tensor::<4>::random([1, 2, 5, 5], Distribution::Default, &d);
    let diff = (crate::conv::conv2d(&conv, x.clone()) - conv.forward(x))
        .abs()
        .max();
    assert_eq!(diff.into_scalar::<f32>(), 0.0);
    // 9 taps x 1 channel x 2^21 positions is over the cap: burn's convolution, bit for bit.
    let a = Device::flex().autodiff();
    let conv = Conv2dConfig::new([1, 1], [3, 3]).init(&a);
    let x = Tensor::<4>::random([1, 1, 1 << 11, 1 << 10], Distribution::Default, &a);
    const { assert!(9 * (1usize << 21) > crate::conv::PRODUCT_MAX_ELEMENTS) };
    let diff = (crate::conv::conv2d(&conv, x.clone()) - conv.forward(x))
        .abs()
        .max();
    assert_eq!(diff.into_scalar::<f32>(), 0.0);
}

/// The fused batch norm against burn's: output, running statistics and the gradients of input, gamma
/// and beta under a random weighting of the output; 4D (HRNet) and 5D (the RootNet's volumes) inputs,
/// a permuted input as the convolutions hand over, and channels whose values sit far from zero.
mod batch_norm {
    use super::{normal, seed};
    use crate::norm::{batch_norm, batch_norm_relu};
    use burn::module::Param;
    use burn::nn::{BatchNorm, BatchNormConfig};
    use burn::tensor::{Device, Tensor};

    fn layer(c: usize, d: &Device) -> BatchNorm {
        let mut bn = BatchNormConfig::new(c).init(d);
        bn.gamma = Param::from_tensor(normal([c], 1.0, d) + 1.0);
        bn.beta = Param::from_tensor(normal([c], 1.0, d));
        bn
    }

    /// Largest difference relative to the reference's largest magnitude.
    fn rel<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> f32 {
        let scale = b.clone().abs().max().into_scalar::<f32>().max(1e-6);
        (a - b).abs().max().into_scalar::<f32>() / scale
    }

    /// The fused norm against burn's, without and with the ReLU that follows it.
    fn compare<const D: usize>(x0: Tensor<D>, w: Tensor<D>) {
        compare_with(x0.clone(), w.clone(), false);
        compare_with(x0, w, true);
    }

    fn compare_with<const D: usize>(x0: Tensor<D>, w: Tensor<D>, relu: bool) {
        let d = x0.device();
        let c = x0.dims()[1];
        let (fused, plain) = (layer(c, &d), layer(c, &d));
        let run = |bn: &BatchNorm, fused: bool| {
            let x = x0.clone().require_grad();
            let y = match (fused, relu) {
                (true, false) => batch_norm(bn, x.clone()),
                (true, true) => batch_norm_relu(bn, x.clone()),
                (false, false) => bn.forward(x.clone()),
                (false, true) => burn::tensor::activation::relu(bn.forward(x.clone())),
            };
            let g = (y.clone() * w.clone()).sum().backward();
            let grad = |t: Tensor<1>| t.grad(&g).expect("a gradient");
            let dx = x.grad(&g).expect("an input gradient");
            (y.inner(), dx, grad(bn.gamma.val()), grad(bn.beta.val()))
        };
        // Same parameters on both paths.
        let plain = BatchNorm {
            gamma: Param::from_tensor(fused.gamma.val()),
            beta: Param::from_tensor(fused.beta.val()),
            ..plain
        };
        let (ya, dxa, dga, dba) = run(&fused, true);
        let (yb, dxb, dgb, dbb) = run(&plain, false);
        for (what, diff) in [
            ("output", rel(ya, yb)),
            ("d input", rel(dxa, dxb)),
            ("d gamma", rel(dga, dgb)),
            ("d beta", rel(dba, dbb)),
            (
                "running mean",
                rel(fused.running_mean.value(), plain.running_mean.value()),
            ),
            (
                "running var",
                rel(fused.running_var.value(), plain.running_var.value()),
            ),
        ] {
            assert!(
                diff < 1e-5,
                "{what} differs by {diff} (shape {:?}, relu {relu})",
                x0.dims()
            );
        }
    }

    #[test]
    fn fused_batch_norm_is_burns() {
        let d = Device::flex().autodiff();
        seed(21);
        compare(
            normal([3, 4, 5, 6], 2.0, &d) + 3.0,
            normal([3, 4, 5, 6], 1.0, &d),
        );
        compare(
            normal([2, 3, 4, 3, 5], 1.0, &d),
            normal([2, 3, 4, 3, 5], 1.0, &d),
        );
        // Channels last, permuted to channels first: a strided view, as a product convolution returns.
        let x = normal([2, 5, 7, 3], 1.0, &d).permute([0, 3, 1, 2]);
        compare(x, normal([2, 3, 5, 7], 1.0, &d));
        // One value per channel and item: the variance is over the batch alone.
        compare(normal([4, 3, 1, 1], 1.0, &d), normal([4, 3, 1, 1], 1.0, &d));
    }

    /// The sum of the output is `N * beta` whatever the input: its gradient is zero in the input and in
    /// gamma (the normalised values sum to zero) and `N` in beta.
    #[test]
    fn the_sum_of_a_batch_norm_moves_with_beta_alone() {
        let d = Device::flex().autodiff();
        seed(5);
        let bn = layer(3, &d);
        let x = (normal([2, 3, 4, 5], 3.0, &d) + 1.0).require_grad();
        let g = batch_norm(&bn, x.clone()).sum().backward();
        let dx = x.grad(&g).unwrap().abs().max().into_scalar::<f32>();
        let dgamma = bn
            .gamma
            .val()
            .grad(&g)
            .unwrap()
            .abs()
            .max()
            .into_scalar::<f32>();
        let dbeta = bn.beta.val().grad(&g).unwrap();
        assert!(dx < 1e-5, "d input {dx}");
        assert!(dgamma < 1e-4, "d gamma {dgamma}");
        let err = (dbeta - 40.0).abs().max().into_scalar::<f32>();
        assert!(err < 1e-4, "d beta off 40 by {err}");
    }

    /// Without autodiff the layer normalises with its running statistics: burn's path, bit for bit.
    #[test]
    fn inference_batch_norm_is_burns() {
        let d = Device::flex();
        seed(9);
        let bn = layer(3, &d);
        let x = normal([2, 3, 4, 4], 1.0, &d);
        let diff = (batch_norm(&bn, x.clone()) - bn.forward(x)).abs().max();
        assert_eq!(diff.into_scalar::<f32>(), 0.0);
    }
}

/// The parallel GELU against burn's: values and input gradients under a random weighting, on a
/// contiguous input larger than one chunk and on a permuted one; without autodiff (the parallel pass
/// too) within 2e-6 of burn's (values up to about 13).
mod gelu {
    use super::{normal, seed};
    use crate::gelu::gelu;
    use burn::tensor::{Device, Tensor};

    fn compare<const D: usize>(x0: Tensor<D>, w: Tensor<D>) {
        let run = |parallel: bool| {
            let x = x0.clone().require_grad();
            let y = if parallel {
                gelu(x.clone())
            } else {
                burn::tensor::activation::gelu(x.clone())
            };
            let g = (y.clone() * w.clone()).sum().backward();
            (y.inner(), x.grad(&g).expect("an input gradient"))
        };
        let ((ya, ga), (yb, gb)) = (run(true), run(false));
        let dy = (ya - yb).abs().max().into_scalar::<f32>();
        let dg = (ga - gb).abs().max().into_scalar::<f32>();
        assert!(
            dy < 1e-6 && dg < 1e-6,
            "values differ by {dy}, gradients by {dg}"
        );
    }

    #[test]
    fn parallel_gelu_is_burns() {
        let d = Device::flex().autodiff();
        seed(3);
        compare(
            normal([3, 130, 257], 3.0, &d),
            normal([3, 130, 257], 1.0, &d),
        );
        let x = normal([4, 6, 5], 2.0, &d).permute([2, 0, 1]);
        compare(x, normal([5, 4, 6], 1.0, &d));
        let plain = Device::flex();
        let x = normal([3, 130, 257], 3.0, &plain);
        let diff = (gelu(x.clone()) - burn::tensor::activation::gelu(x))
            .abs()
            .max();
        let diff = diff.into_scalar::<f32>();
        assert!(diff < 2e-6, "values differ by {diff}");
    }
}

/// The vectorised `exp` and GELU against double-precision references: `exp` within 3e-7 relative over
/// [-86.5, 88.72] (and 0, infinity and NaN outside it), GELU within 1e-5 relative and its slope
/// within 1e-6 over [-10, 10] (libm's `erf` in f64); the slice forms, vectorised for this machine's
/// widest instruction set, give the scalar form's bits.
mod vmath {
    use crate::vmath::{exp, exp_shifted, gelu, gelu_backward_into, gelu_into, gelu_slope};

    fn sweep(lo: f32, hi: f32, n: usize) -> Vec<f32> {
        (0..=n)
            .map(|i| lo + (hi - lo) * i as f32 / n as f32)
            .collect()
    }

    #[test]
    fn exp_is_exp() {
        for x in sweep(-86.5, 88.72, 200_003) {
            let want = (x as f64).exp();
            let rel = ((exp(x) as f64 - want) / want).abs();
            assert!(rel < 3e-7, "exp({x}) = {} against {want}", exp(x));
        }
        assert_eq!(exp(0.0), 1.0);
        assert_eq!(exp(-86.6), 0.0);
        assert_eq!(exp(f32::NEG_INFINITY), 0.0);
        assert_eq!(exp(89.0), f32::INFINITY);
        assert!(exp(f32::NAN).is_nan());
    }

    #[test]
    fn gelu_and_its_slope_are_the_erf_forms() {
        // 1 + erf(x / sqrt 2) as erfc(-x / sqrt 2), exact where 1 + erf would cancel.
        let twice_cdf = |x: f64| libm::erfc(-x / std::f64::consts::SQRT_2);
        for x in sweep(-10.0, 10.0, 100_001) {
            let xd = x as f64;
            let value = 0.5 * xd * twice_cdf(xd);
            let pdf = (-0.5 * xd * xd).exp() / (2.0 * std::f64::consts::PI).sqrt();
            let slope = 0.5 * twice_cdf(xd) + xd * pdf;
            let rel = ((gelu(x) as f64 - value) / value.abs().max(1e-30)).abs();
            assert!(rel < 1e-5, "gelu({x}) = {} against {value}", gelu(x));
            let abs = (gelu_slope(x) as f64 - slope).abs();
            assert!(abs < 1e-6, "gelu'({x}) = {} against {slope}", gelu_slope(x));
        }
        assert_eq!(gelu(0.0), 0.0);
        assert_eq!(gelu(f32::INFINITY), f32::INFINITY);
        assert!(gelu(f32::NAN).is_nan());
    }

    #[test]
    fn the_slice_forms_give_the_scalar_bits() {
        let x = sweep(-12.0, 12.0, 4099);
        let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
        let mut e = x.clone();
        exp_shifted(&mut e, 1.5);
        let want: Vec<f32> = x.iter().map(|&x| exp(x - 1.5)).collect();
        assert_eq!(bits(&e), bits(&want));
        let mut y = vec![0.0; x.len()];
        gelu_into(&x, &mut y);
        assert_eq!(
            bits(&y),
            bits(&x.iter().map(|&x| gelu(x)).collect::<Vec<_>>())
        );
        let g = sweep(-1.0, 2.0, 4099);
        gelu_backward_into(&g, &x, &mut y);
        let want: Vec<f32> = g.iter().zip(&x).map(|(&g, &x)| g * gelu_slope(x)).collect();
        assert_eq!(bits(&y), bits(&want));
    }
}

/// The convolution with the tiled gradients equals burn's: values and the gradients of input, weight
/// and bias, for the RootNet's 7x7x7 front over a volume whose last axis is shorter than the
/// kernel, uneven kernels and paddings, paddings wider than the volume, more positions than one tile,
/// and two batch items.
#[test]
fn tiled_weight_gradients_are_the_convolutions() {
    use burn::tensor::ops::ConvOptions;
    let d = Device::flex().autodiff();
    seed(11);
    for (x_dims, co, kernel, pad, bias) in [
        ([1, 5, 8, 8, 6], 3, [7, 7, 7], [3, 3, 3], true),
        ([2, 3, 5, 6, 7], 4, [3, 5, 3], [1, 2, 1], false),
        ([2, 2, 4, 9, 11], 2, [1, 3, 5], [0, 1, 2], true),
        ([1, 2, 3, 3, 3], 2, [3, 3, 3], [0, 0, 0], false),
        ([1, 2, 4, 2, 1], 2, [3, 5, 7], [1, 2, 3], true),
        // Paddings wider than the kernel less one: the input's gradient is burn's there.
        ([1, 2, 3, 4, 5], 2, [1, 3, 3], [1, 1, 3], true),
    ] {
        let x = normal(x_dims, 1.0, &d).require_grad();
        let weight =
            normal([co, x_dims[1], kernel[0], kernel[1], kernel[2]], 0.5, &d).require_grad();
        let b = bias.then(|| normal([co], 1.0, &d).require_grad());
        let options = ConvOptions::new([1; 3], pad, [1; 3], 1);
        let run = |tiled: bool| {
            let (xi, wi, bi) = (x.clone(), weight.clone(), b.clone());
            let y = match tiled {
                true => crate::wgrad::conv3d(xi, wi, bi, options.clone()),
                false => burn::tensor::module::conv3d(xi, wi, bi, options.clone()),
            };
            let probe = normal(y.dims(), 1.0, &d);
            let grads = (y.clone() * probe).sum().backward();
            let mut out = vec![
                y.detach().flatten::<1>(0, 4),
                x.grad(&grads).unwrap().flatten::<1>(0, 4),
                weight.grad(&grads).unwrap().flatten::<1>(0, 4),
            ];
            out.extend(b.as_ref().map(|b| b.grad(&grads).unwrap()));
            out
        };
        seed(12);
        let tiled = run(true);
        seed(12);
        let plain = run(false);
        assert_close(
            tiled,
            plain,
            &format!("input {x_dims:?} kernel {kernel:?} pad {pad:?}"),
        );
    }
}

/// Output and the gradients of input, weight and bias of a stride-1 3D convolution of `x` padded by
/// `pad`, under a fixed random weighting of the output: directly (whatever share of its work is output)
/// or burn's.
fn direct_outputs(
    x: &Tensor<5>,
    weight: &Tensor<5>,
    bias: Option<&Tensor<1>>,
    pad: [usize; 3],
    direct: bool,
) -> Vec<Tensor<1>> {
    use burn::tensor::ops::ConvOptions;
    let (xi, wi, bi) = (x.clone(), weight.clone(), bias.cloned());
    let y = match direct {
        true => crate::direct::convolution(xi, wi, bi),
        false => burn::tensor::module::conv3d(xi, wi, bi, ConvOptions::new([1; 3], pad, [1; 3], 1)),
    };
    outputs_and_gradients(y, x, weight, bias, 12)
}

/// The direct convolution equals burn's: values and the gradients of input, weight and bias, for the
/// RootNet's 3x3x3 blocks (8 -> 16, 16 -> 16 and 64 -> 64 channels at its three resolutions, the
/// last two axes 4 and 2 deep), channels that fill neither a tile nor a register (3 -> 5, 9 -> 20),
/// uneven odd kernels with a side of 1, volumes thinner than the kernel, a row of one voxel, and two
/// batch items.
#[test]
fn direct_convolutions_are_the_convolutions() {
    let d = Device::flex().autodiff();
    seed(21);
    for (x_dims, co, kernel, bias) in [
        ([1, 8, 6, 5, 8], 16, [3, 3, 3], true),
        ([1, 16, 4, 4, 4], 16, [3, 3, 3], false),
        ([1, 64, 3, 3, 2], 64, [3, 3, 3], true),
        ([2, 3, 5, 6, 7], 5, [3, 3, 3], true),
        ([1, 9, 4, 7, 3], 20, [1, 3, 5], false),
        ([2, 4, 2, 1, 5], 3, [5, 3, 1], true),
        ([1, 2, 1, 1, 1], 17, [3, 3, 3], true),
    ] {
        let x = normal(x_dims, 1.0, &d).require_grad();
        let w = normal([co, x_dims[1], kernel[0], kernel[1], kernel[2]], 0.5, &d).require_grad();
        let b = bias.then(|| normal([co], 1.0, &d).require_grad());
        let pad = kernel.map(|k| k / 2);
        assert_close(
            direct_outputs(&x, &w, b.as_ref(), pad, true),
            direct_outputs(&x, &w, b.as_ref(), pad, false),
            &format!("input {x_dims:?} kernel {kernel:?} -> {co}"),
        );
    }
}

/// The direct convolution gives the same bits on one thread as on four, and takes only "same"
/// paddings of odd kernels: other paddings, even kernels and a single tap are left to the caller.
#[test]
fn the_direct_convolution_does_not_depend_on_the_thread_count() {
    use crate::direct::takes;
    let d = Device::flex().autodiff();
    seed(22);
    let x = normal([2, 16, 9, 8, 8], 1.0, &d).require_grad();
    let w = normal([16, 16, 3, 3, 3], 0.5, &d).require_grad();
    let run = || bits_of(direct_outputs(&x, &w, None, [1; 3], true));
    assert_eq!(in_pool(1, run), in_pool(4, run));
    assert!(takes([3, 3, 3], [1, 1, 1]) && takes([1, 3, 5], [0, 1, 2]));
    assert!(!takes([3, 3, 3], [0, 1, 1]) && !takes([2, 3, 3], [1, 1, 1]) && !takes([1; 3], [0; 3]));
}

/// The direct path is taken where most of what it computes is output: the tiny RootNet's full and
/// half resolutions (256 of 324 and 64 of 96 positions, counted by hand), not its quarter one (16 of
/// 36), and not without autodiff.
#[test]
fn the_direct_convolution_is_taken_where_it_pays() {
    use crate::direct::{conv3d, useful};
    assert_eq!(useful([32, 32, 8], [3; 3]), 256.0 / 324.0);
    assert_eq!(useful([16, 16, 4], [3; 3]), 64.0 / 96.0);
    assert_eq!(useful([8, 8, 2], [3; 3]), 16.0 / 36.0);
    let d = Device::flex().autodiff();
    let w = normal([4, 4, 3, 3, 3], 0.5, &d);
    let taken = |n: [usize; 3], d: &Device| {
        let x = normal([1, 4, n[0], n[1], n[2]], 1.0, d);
        conv3d(x, w.clone().to_device(d), None, [1; 3]).is_some()
    };
    assert!(taken([16, 16, 4], &d) && !taken([8, 8, 2], &d));
    assert!(!taken([16, 16, 4], &Device::flex()));
}

/// HRNet's stride-1 "same" 2D convolutions go the direct way in training on flex (as 3D ones of depth
/// one) and equal burn's there: values and the gradients of input, weight and bias for the tiny HRNet's
/// 3x3s (8 -> 8 channels at 56 x 56 and 64 -> 64 on its lowest branch's 7 x 7, four views; 16 -> 16 at
/// 28 x 28), a 5x5 over a
/// rectangle with a bias, channels that fill neither a tile nor a register (3 -> 5). A stride-2 3x3, a
/// padding other than half the kernel, a 1x1 (a pointwise product) and an even kernel are not taken.
#[test]
fn same_2d_convolutions_are_taken_directly() {
    use burn::nn::PaddingConfig2d;
    use burn::nn::conv::{Conv2d, Conv2dConfig};
    let d = Device::flex().autodiff();
    seed(23);
    let conv = |[ci, co]: [usize; 2], k: usize, stride: usize, pad: [usize; 4], bias: bool| {
        Conv2dConfig::new([ci, co], [k, k])
            .with_stride([stride, stride])
            .with_padding(PaddingConfig2d::Explicit(pad[0], pad[1], pad[2], pad[3]))
            .with_bias(bias)
            .init(&d)
    };
    let outputs = |c: &Conv2d, x: &Tensor<4>, direct: bool| {
        let y = match direct {
            true => crate::conv::direct2d(c, x.clone(), [c.kernel_size[0] / 2; 4]).unwrap(),
            false => c.forward(x.clone()),
        };
        let bias = c.bias.as_ref().map(|b| b.val());
        outputs_and_gradients(y, x, &c.weight.val(), bias.as_ref(), 24)
    };
    for (x_dims, co, k, bias) in [
        ([4, 8, 56, 56], 8, 3, false),
        ([1, 16, 28, 28], 16, 3, false),
        ([4, 64, 7, 7], 64, 3, false),
        ([2, 6, 9, 13], 8, 5, true),
        ([2, 3, 5, 6], 5, 3, true),
    ] {
        let c = conv([x_dims[1], co], k, 1, [k / 2; 4], bias);
        let x = normal(x_dims, 1.0, &d).require_grad();
        assert_close(
            outputs(&c, &x, true),
            outputs(&c, &x, false),
            &format!("input {x_dims:?} kernel {k} -> {co}"),
        );
    }
    let x = normal([1, 4, 8, 8], 1.0, &d);
    let taken = |c: Conv2d, pad: [usize; 4]| crate::conv::direct2d(&c, x.clone(), pad).is_some();
    assert!(taken(conv([4, 4], 3, 1, [1; 4], false), [1; 4]));
    assert!(!taken(conv([4, 4], 3, 2, [1; 4], false), [1; 4]));
    assert!(!taken(
        conv([4, 4], 3, 1, [0, 2, 1, 0], false),
        [0, 2, 1, 0]
    ));
    assert!(!taken(conv([4, 4], 3, 1, [0; 4], false), [0; 4]));
    assert!(!taken(conv([4, 4], 1, 1, [0; 4], false), [0; 4]));
    assert!(!taken(conv([4, 4], 2, 1, [1; 4], false), [1; 4]));
    let inference = conv([4, 4], 3, 1, [1; 4], false);
    let plain = normal([1, 4, 8, 8], 1.0, &Device::flex());
    assert!(crate::conv::direct2d(&inference, plain, [1; 4]).is_none());
}

/// The fused group norm against burn's: output and the gradients of input, gamma and beta under a
/// random weighting of the output, for groups of one channel, of several and of all channels, 4D (the
/// facing head) and 5D (the RootNet), a permuted input, and a batch whose count of item-groups equals
/// the channels' (so that the two kinds of statistics could be confused).
mod group_norm {
    use super::{normal, seed};
    use crate::norm::{group_norm, group_norm_relu};
    use burn::module::Param;
    use burn::nn::{GroupNorm, GroupNormConfig};
    use burn::tensor::{Device, Tensor};

    fn layer(groups: usize, c: usize, d: &Device) -> GroupNorm {
        let mut gn = GroupNormConfig::new(groups, c).init(d);
        gn.gamma = Some(Param::from_tensor(normal([c], 1.0, d) + 1.0));
        gn.beta = Some(Param::from_tensor(normal([c], 1.0, d)));
        gn
    }

    fn rel<const D: usize>(a: Tensor<D>, b: Tensor<D>) -> f32 {
        let scale = b.clone().abs().max().into_scalar::<f32>().max(1e-6);
        (a - b).abs().max().into_scalar::<f32>() / scale
    }

    /// The fused norm against burn's, without and with the ReLU that follows it.
    fn compare<const D: usize>(groups: usize, x0: Tensor<D>, w: Tensor<D>) {
        compare_with(groups, x0.clone(), w.clone(), false);
        compare_with(groups, x0, w, true);
    }

    fn compare_with<const D: usize>(groups: usize, x0: Tensor<D>, w: Tensor<D>, relu: bool) {
        let gn = layer(groups, x0.dims()[1], &x0.device());
        let run = |fused: bool| {
            let x = x0.clone().require_grad();
            let y = match (fused, relu) {
                (true, false) => group_norm(&gn, x.clone()),
                (true, true) => group_norm_relu(&gn, x.clone()),
                (false, false) => gn.forward(x.clone()),
                (false, true) => burn::tensor::activation::relu(gn.forward(x.clone())),
            };
            let g = (y.clone() * w.clone()).sum().backward();
            let grad = |p: &Option<Param<Tensor<1>>>| {
                let t = p.as_ref().expect("affine").val();
                t.grad(&g).expect("a gradient")
            };
            let dx = x.grad(&g).expect("an input gradient");
            (y.inner(), dx, grad(&gn.gamma), grad(&gn.beta))
        };
        let (ya, dxa, dga, dba) = run(true);
        let (yb, dxb, dgb, dbb) = run(false);
        for (what, diff) in [
            ("output", rel(ya, yb)),
            ("d input", rel(dxa, dxb)),
            ("d gamma", rel(dga, dgb)),
            ("d beta", rel(dba, dbb)),
        ] {
            assert!(
                diff < 1e-5,
                "{what} differs by {diff} (groups {groups}, shape {:?}, relu {relu})",
                x0.dims()
            );
        }
    }

    #[test]
    fn fused_group_norm_is_burns() {
        let d = Device::flex().autodiff();
        seed(23);
        for groups in [1, 2, 8] {
            compare(
                groups,
                normal([3, 8, 5, 6], 2.0, &d) + 3.0,
                normal([3, 8, 5, 6], 1.0, &d),
            );
        }
        compare(
            4,
            normal([3, 8, 4, 3, 5], 1.0, &d),
            normal([3, 8, 4, 3, 5], 1.0, &d),
        );
        // 2 items x 4 groups: as many item-groups as channels.
        compare(
            4,
            normal([2, 8, 3, 3], 1.0, &d),
            normal([2, 8, 3, 3], 1.0, &d),
        );
        let x = normal([2, 5, 7, 4], 1.0, &d).permute([0, 3, 1, 2]);
        compare(2, x, normal([2, 4, 5, 7], 1.0, &d));
    }

    /// Each item-group's normalised values sum to zero, so with one gamma for every channel the
    /// output's sum moves with beta alone: zero gradient in the input, gamma's gradient summing to zero
    /// over each group's channels, and `B * S` per channel in beta.
    #[test]
    fn the_sum_of_a_group_norm_moves_with_beta_alone() {
        let d = Device::flex().autodiff();
        seed(6);
        let mut gn = layer(2, 4, &d);
        gn.gamma = Some(Param::from_tensor(Tensor::<1>::ones([4], &d) * 1.7));
        let x = (normal([3, 4, 2, 5], 3.0, &d) + 1.0).require_grad();
        let g = group_norm(&gn, x.clone()).sum().backward();
        let abs_max = |t: Tensor<1>| t.abs().max().into_scalar::<f32>();
        let dx = x.grad(&g).unwrap().abs().max().into_scalar::<f32>();
        let dgamma = gn.gamma.as_ref().unwrap().val().grad(&g).unwrap();
        let per_group = abs_max(dgamma.reshape([2, 2]).sum_dim(1).flatten::<1>(0, 1));
        let dbeta = gn.beta.as_ref().unwrap().val().grad(&g).unwrap();
        assert!(dx < 1e-5, "d input {dx}");
        assert!(per_group < 1e-4, "d gamma sums to {per_group} over a group");
        assert!(abs_max(dbeta - 30.0) < 1e-4, "d beta is not 30");
    }

    /// Without autodiff the layer is burn's, bit for bit.
    #[test]
    fn inference_group_norm_is_burns() {
        let d = Device::flex();
        seed(10);
        let gn = layer(2, 4, &d);
        let x = normal([2, 4, 3, 3], 1.0, &d);
        let diff = (group_norm(&gn, x.clone()) - gn.forward(x)).abs().max();
        assert_eq!(diff.into_scalar::<f32>(), 0.0);
    }
}

/// The product operation and its gradients in the weight and the input, against burn's matmul with the
/// weight broadcast, and the same bits whatever the number of threads.
mod product {
    use super::*;
    use crate::product::weight_product;

    /// Output, weight gradient and input gradient of `w . x[b]` weighted by a fixed random `r`.
    fn run(w: &Tensor<2>, x: &Tensor<3>, r: &Tensor<3>, fused: bool) -> Vec<Tensor<1>> {
        let (w, x) = (w.clone().require_grad(), x.clone().require_grad());
        let y = match fused {
            true => weight_product(w.clone(), x.clone()),
            false => {
                let [co, k] = w.dims();
                w.clone().reshape([1, co, k]).matmul(x.clone())
            }
        };
        let grads = (y.clone() * r.clone()).sum().backward();
        vec![
            y.detach().flatten::<1>(0, 2),
            w.grad(&grads).unwrap().flatten::<1>(0, 1),
            x.grad(&grads).unwrap().flatten::<1>(0, 2),
        ]
    }

    /// Shapes with one tile, a tile and a remainder, several items (more tiles than chunks) and an
    /// output of one channel.
    const SHAPES: [[usize; 4]; 4] = [
        [1, 7, 5, 40],
        [2, 16, 64, 1300],
        [3, 9, 144, 2500],
        [2, 1, 3, 600],
    ];

    #[test]
    fn the_product_and_its_gradients_are_burns() {
        let d = Device::flex().autodiff();
        seed(11);
        for [b, co, k, p] in SHAPES {
            let w = normal([co, k], 1.0, &d);
            let x = normal([b, k, p], 1.0, &d);
            let r = normal([b, co, p], 1.0, &d);
            assert_close(
                run(&w, &x, &r, true),
                run(&w, &x, &r, false),
                &format!("product [{b}, {co}, {k}, {p}]"),
            );
        }
    }

    #[test]
    fn the_product_does_not_depend_on_the_thread_count() {
        let d = Device::flex().autodiff();
        seed(12);
        let [b, co, k, p] = SHAPES[2];
        let (w, x, r) = (
            normal([co, k], 1.0, &d),
            normal([b, k, p], 1.0, &d),
            normal([b, co, p], 1.0, &d),
        );
        let bits = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            pool.install(|| run(&w, &x, &r, true))
                .into_iter()
                .map(|t| t.into_data().try_into_vec::<f32>().unwrap())
                .collect::<Vec<_>>()
        };
        assert_eq!(bits(1), bits(3));
    }

    #[test]
    fn the_product_without_autodiff_is_the_matmul() {
        let d = Device::flex();
        seed(13);
        let w = normal([4, 6], 1.0, &d);
        let x = normal([2, 6, 9], 1.0, &d);
        let want = w.clone().reshape([1, 4, 6]).matmul(x.clone());
        let got = weight_product(w, x);
        assert_eq!(got.into_data(), want.into_data());
    }
}

/// `relu(a + b)` in one pass against burn's addition and ReLU: values and both inputs' gradients,
/// with one input constant and with one tensor on both sides.
mod residual {
    use super::*;
    use crate::residual::add_relu;
    use burn::tensor::activation::relu;

    #[test]
    fn the_fused_residual_join_is_burns() {
        let d = Device::flex().autodiff();
        seed(31);
        let (a0, b0) = (normal([2, 3, 5, 7], 1.0, &d), normal([2, 3, 5, 7], 1.0, &d));
        let r = normal([2, 3, 5, 7], 1.0, &d);
        for (grad_a, grad_b) in [(true, true), (true, false), (false, true)] {
            let run = |fused: bool| {
                let a = if grad_a {
                    a0.clone().require_grad()
                } else {
                    a0.clone()
                };
                let b = if grad_b {
                    b0.clone().require_grad()
                } else {
                    b0.clone()
                };
                let y = match fused {
                    true => add_relu(a.clone(), b.clone()),
                    false => relu(a.clone() + b.clone()),
                };
                let g = (y.clone() * r.clone()).sum().backward();
                let mut out = vec![y.detach().flatten::<1>(0, 3)];
                out.extend(grad_a.then(|| a.grad(&g).unwrap().flatten::<1>(0, 3)));
                out.extend(grad_b.then(|| b.grad(&g).unwrap().flatten::<1>(0, 3)));
                out
            };
            assert_close(run(true), run(false), &format!("grads {grad_a} {grad_b}"));
        }
        let x = a0.require_grad();
        let g = (add_relu(x.clone(), x.clone()) * r.clone())
            .sum()
            .backward();
        let got = x.grad(&g).unwrap();
        let x_ref = x.detach().require_grad();
        let g_ref = (relu(x_ref.clone() * 2.0) * r).sum().backward();
        let want = x_ref.grad(&g_ref).unwrap();
        assert_close(
            vec![got.flatten(0, 3)],
            vec![want.flatten(0, 3)],
            "one tensor twice",
        );
    }
}

/// The values of each tensor, as bits to compare.
fn bits_of(ts: Vec<Tensor<1>>) -> Vec<Vec<f32>> {
    ts.into_iter()
        .map(|t| t.into_data().try_into_vec::<f32>().unwrap())
        .collect()
}

/// `run` in a pool of `threads` threads.
fn in_pool<T: Send>(threads: usize, run: impl FnOnce() -> T + Send) -> T {
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .unwrap();
    pool.install(run)
}

mod linear {
    use super::*;
    use crate::linear::linear;

    /// Output and the gradients of input, weight and bias (when there is one) of `x . w + b`, weighted
    /// by a fixed random `r`: the operation, or burn's broadcast matmul and sum.
    fn run(
        x: &Tensor<3>,
        w: &Tensor<2>,
        b: Option<&Tensor<1>>,
        r: &Tensor<3>,
        fused: bool,
    ) -> Vec<Tensor<1>> {
        let (x, w) = (x.clone().require_grad(), w.clone().require_grad());
        let b = b.map(|b| b.clone().require_grad());
        let y = match fused {
            true => linear(x.clone(), w.clone(), b.clone()),
            false => {
                let y = x.clone().matmul(w.clone().unsqueeze_dim::<3>(0));
                match &b {
                    Some(b) => y + b.clone().unsqueeze_dims::<3>(&[0, 1]),
                    None => y,
                }
            }
        };
        let grads = (y.clone() * r.clone()).sum().backward();
        let mut out = vec![
            y.detach().flatten::<1>(0, 2),
            x.grad(&grads).unwrap().flatten::<1>(0, 2),
            w.grad(&grads).unwrap().flatten::<1>(0, 1),
        ];
        out.extend(b.map(|b| b.grad(&grads).unwrap()));
        out
    }

    /// `[items, rows, in, out]`: one tile, several tiles and more rows than chunks, fewer rows than
    /// chunks, a single output.
    const SHAPES: [[usize; 4]; 4] = [
        [2, 7, 5, 3],
        [3, 300, 64, 48],
        [1, 3, 9, 11],
        [2, 130, 17, 1],
    ];

    #[test]
    fn the_linear_layer_and_its_gradients_are_burns() {
        let d = Device::flex().autodiff();
        seed(41);
        for (i, [items, rows, k, n]) in SHAPES.into_iter().enumerate() {
            let x = normal([items, rows, k], 1.0, &d);
            let w = normal([k, n], 1.0, &d);
            let b = normal([n], 1.0, &d);
            let r = normal([items, rows, n], 1.0, &d);
            let b = (i != 2).then_some(&b);
            assert_close(
                run(&x, &w, b, &r, true),
                run(&x, &w, b, &r, false),
                &format!("linear [{items}, {rows}, {k}, {n}], bias {}", b.is_some()),
            );
        }
    }

    #[test]
    fn the_linear_layer_does_not_depend_on_the_thread_count() {
        let d = Device::flex().autodiff();
        seed(42);
        let [items, rows, k, n] = SHAPES[1];
        let (x, w, b, r) = (
            normal([items, rows, k], 1.0, &d),
            normal([k, n], 1.0, &d),
            normal([n], 1.0, &d),
            normal([items, rows, n], 1.0, &d),
        );
        let bits = |threads| bits_of(in_pool(threads, || run(&x, &w, Some(&b), &r, true)));
        assert_eq!(bits(1), bits(3));
    }
}

mod layer_norm {
    use super::*;
    use crate::layer_norm::layer_norm;
    use burn::nn::LayerNormConfig;

    /// Output and the gradients of input, scale and shift (when there is one), weighted by `r`: the
    /// operation, or burn's layer norm as autodiff runs it.
    fn run(
        x: &Tensor<3>,
        norm: &burn::nn::LayerNorm,
        r: &Tensor<3>,
        fused: bool,
    ) -> Vec<Tensor<1>> {
        let x = x.clone().require_grad();
        let y = match fused {
            true => layer_norm(norm, x.clone(), 1e-6),
            false => burn::tensor::module::layer_norm(
                x.clone(),
                norm.gamma.val(),
                norm.beta.as_ref().map(|b| b.val()),
                1e-6,
            ),
        };
        let grads = (y.clone() * r.clone()).sum().backward();
        let mut out = vec![
            y.detach().flatten::<1>(0, 2),
            x.grad(&grads).unwrap().flatten::<1>(0, 2),
            norm.gamma.val().grad(&grads).unwrap(),
        ];
        out.extend(norm.beta.as_ref().map(|b| b.val().grad(&grads).unwrap()));
        out
    }

    /// A norm of `c` features with random scale and shift (or none).
    fn norm(c: usize, shift: bool, d: &Device) -> burn::nn::LayerNorm {
        let mut n = LayerNormConfig::new(c).with_bias(shift).init(d);
        n.gamma = burn::module::Param::from_tensor(normal([c], 1.0, d));
        n.beta = n
            .beta
            .map(|_| burn::module::Param::from_tensor(normal([c], 1.0, d)));
        n
    }

    #[test]
    fn the_fused_layer_norm_and_its_gradients_are_burns() {
        let d = Device::flex().autodiff();
        seed(51);
        // Rows in one task and in several (more than the chunks), no shift, rows far from zero.
        for (i, [items, rows, c]) in [[2, 5, 7], [3, 70, 48], [1, 9, 16], [2, 33, 24]]
            .into_iter()
            .enumerate()
        {
            let offset = if i == 3 { 50.0 } else { 0.0 };
            let x = normal([items, rows, c], 2.0, &d) + offset;
            let r = normal([items, rows, c], 1.0, &d);
            let n = norm(c, i != 2, &d);
            assert_close(
                run(&x, &n, &r, true),
                run(&x, &n, &r, false),
                &format!("layer norm [{items}, {rows}, {c}], shift {}", i != 2),
            );
        }
    }

    #[test]
    fn the_fused_layer_norm_does_not_depend_on_the_thread_count() {
        let d = Device::flex().autodiff();
        seed(52);
        let x = normal([3, 70, 48], 1.0, &d);
        let r = normal([3, 70, 48], 1.0, &d);
        let n = norm(48, true, &d);
        let bits = |threads| bits_of(in_pool(threads, || run(&x, &n, &r, true)));
        assert_eq!(bits(1), bits(3));
    }
}

/// The attention's host passes sum each head's key and value gradients in one order.
#[test]
fn attention_does_not_depend_on_the_thread_count() {
    let d = Device::flex().autodiff();
    seed(61);
    let (q0, k0, v0) = (
        random([2, 3, 150, 8], 1.0, &d),
        random([2, 3, 90, 8], 1.0, &d),
        random([2, 3, 90, 5], 1.0, &d),
    );
    let w = random([2, 3, 150, 5], 1.0, &d);
    let run = || {
        let (q, k, v) = (
            q0.clone().require_grad(),
            k0.clone().require_grad(),
            v0.clone().require_grad(),
        );
        let out = attention(q.clone(), k.clone(), v.clone(), 0.3, 512);
        let grads = (out.clone() * w.clone()).sum().backward();
        let flat = |t: Tensor<4>| t.flatten::<1>(0, 3);
        vec![
            flat(out.detach()),
            flat(q.grad(&grads).unwrap()),
            flat(k.grad(&grads).unwrap()),
            flat(v.grad(&grads).unwrap()),
        ]
    };
    assert_eq!(bits_of(in_pool(1, run)), bits_of(in_pool(3, run)));
}

mod packed_attention {
    use super::*;
    use crate::packed_self_attention;

    /// The heads split out of `qkv [B, N, 3 C]` and attended by burn's ops, joined again.
    fn reference(qkv: Tensor<3>, heads: usize, scale: f64) -> Tensor<3> {
        let [b, n, c3] = qkv.dims();
        let d = c3 / 3 / heads;
        let qkv = qkv.reshape([b, n, 3, heads, d]).permute([2, 0, 3, 1, 4]);
        let part = |i| qkv.clone().narrow(0, i, 1).reshape([b, heads, n, d]);
        let out = plain_attention(part(0), part(1), part(2), scale);
        out.swap_dims(1, 2).reshape([b, n, c3 / 3])
    }

    /// Output and the projection's gradient, weighted by `w`: the operation or the reference.
    fn run(
        qkv: &Tensor<3>,
        w: &Tensor<3>,
        heads: usize,
        block: usize,
        packed: bool,
    ) -> Vec<Tensor<1>> {
        let x = qkv.clone().require_grad();
        let scale = 0.4;
        let y = match packed {
            true => packed_self_attention(x.clone(), heads, scale, block),
            false => reference(x.clone(), heads, scale),
        };
        let grads = (y.clone() * w.clone()).sum().backward();
        vec![
            y.detach().flatten::<1>(0, 2),
            x.grad(&grads).unwrap().flatten::<1>(0, 2),
        ]
    }

    #[test]
    fn packed_self_attention_and_its_gradient_are_burns() {
        let d = Device::flex().autodiff();
        seed(71);
        // One tile, several tiles with a remainder, one head, heads of one channel.
        for [b, n, heads, width, block] in [
            [2, 9, 3, 4, 64],
            [1, 150, 2, 8, 64],
            [2, 37, 1, 5, 8],
            [1, 20, 6, 1, 7],
        ] {
            let c = heads * width;
            let qkv = normal([b, n, 3 * c], 1.0, &d);
            let w = normal([b, n, c], 1.0, &d);
            assert_close(
                run(&qkv, &w, heads, block, true),
                run(&qkv, &w, heads, block, false),
                &format!("packed attention [{b}, {n}, {heads} x {width}], block {block}"),
            );
        }
    }

    #[test]
    fn packed_self_attention_does_not_depend_on_the_thread_count() {
        let d = Device::flex().autodiff();
        seed(72);
        let qkv = normal([2, 150, 3 * 12], 1.0, &d);
        let w = normal([2, 150, 12], 1.0, &d);
        let bits = |threads| bits_of(in_pool(threads, || run(&qkv, &w, 3, 64, true)));
        assert_eq!(bits(1), bits(3));
    }

    #[test]
    fn packed_self_attention_without_autodiff_is_burns() {
        let d = Device::flex();
        seed(73);
        let qkv = normal([2, 30, 3 * 8], 1.0, &d);
        let got = packed_self_attention(qkv.clone(), 2, 0.5, 16);
        let want = reference(qkv, 2, 0.5);
        let diff = (got - want).abs().max().into_scalar::<f32>();
        assert!(diff < TOL, "forward differs by {diff}");
    }
}
