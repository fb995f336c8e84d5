//! The DINOv2-layout ViT: shapes, parameter counts, position-embedding interpolation, and one block
//! against an independent numpy computation (scripts/vit_block_fixture.py).
use burn::module::{Module, Param};
use burn::tensor::{Device, Tensor, TensorData};
use mvmp_backbone::vit::{ViTConfig, bicubic_matrix};

fn vals<const D: usize>(t: Tensor<D>) -> Vec<f32> {
    t.into_data().try_into_vec().unwrap()
}

#[test]
fn shapes_of_the_feature_maps() {
    let d = Device::flex();
    let vit = ViTConfig::tiny().init(&d);
    let x = Tensor::<4>::zeros([2, 3, 224, 224], &d);
    assert_eq!(vit.forward(x).dims(), [2, 192, 16, 16]);
    // Any size: the patch grid follows the input (pos-embeds interpolated).
    let x = Tensor::<4>::zeros([1, 3, 126, 280], &d);
    assert_eq!(vit.forward(x).dims(), [1, 192, 9, 20]);
}

/// The matmul patch embedding is the stride-14 convolution: the same tokens and the same weight gradient,
/// on a size that is not a multiple of 14 (the last rows and columns fall outside every patch).
#[test]
fn patch_embedding_is_the_strided_convolution() {
    let d = Device::flex().autodiff();
    let vit = ViTConfig::tiny().init(&d);
    let n = 2 * 3 * 45 * 33;
    let img: Vec<f32> = (0..n)
        .map(|i| ((i * 7919) % 1000) as f32 / 500.0 - 1.0)
        .collect();
    let x = || Tensor::<4>::from_data(TensorData::new(img.clone(), [2, 3, 45, 33]), &d);
    let (tokens, hw) = vit.patch_embed.forward(x());
    assert_eq!(hw, [3, 2]);
    let conv = vit.patch_embed.proj.forward(x()); // [2, C, 3, 2]
    let conv_tokens = conv.clone().reshape([2, 192, 6]).swap_dims(1, 2);
    let (a, b) = (vals(tokens.clone()), vals(conv_tokens));
    let diff = a
        .iter()
        .zip(&b)
        .map(|(p, q)| (p - q).abs())
        .fold(0f32, f32::max);
    assert!(diff < 1e-5, "tokens differ by {diff}");

    // Gradients of the same weighted sum through either path.
    let w = Tensor::<3>::from_data(
        TensorData::new(
            (0..2 * 6 * 192)
                .map(|i| (i % 13) as f32 - 6.0)
                .collect::<Vec<_>>(),
            [2, 6, 192],
        ),
        &d,
    );
    let weight = vit.patch_embed.proj.weight.val();
    let g1 = weight.grad(&(tokens * w.clone()).sum().backward()).unwrap();
    let w_conv = w.swap_dims(1, 2).reshape([2, 192, 3, 2]);
    let g2 = weight.grad(&(conv * w_conv).sum().backward()).unwrap();
    let (g1, g2) = (vals(g1), vals(g2));
    let scale = g2.iter().fold(0f32, |m, v| m.max(v.abs()));
    let diff = g1
        .iter()
        .zip(&g2)
        .map(|(p, q)| (p - q).abs())
        .fold(0f32, f32::max);
    assert!(
        diff <= 1e-5 * scale,
        "weight gradients differ by {diff} (scale {scale})"
    );
}

#[test]
fn parameter_counts_follow_the_architecture() {
    let d = Device::flex();
    // Per block: 12 C^2 + 15 C; patch embed 588 C + C; cls, mask, final norm 4 C; pos (1 + M^2) C.
    let count = |c: usize, depth: usize, m: usize| {
        depth * (12 * c * c + 15 * c) + 589 * c + 4 * c + (1 + m * m) * c
    };
    let tiny = ViTConfig::tiny().init(&d);
    assert_eq!(tiny.num_params(), count(192, 4, 16));
    let small = ViTConfig::vit_small_14().init(&d);
    assert_eq!(small.num_params(), count(384, 12, 37));
    assert_eq!(small.num_params(), 22_056_576);
    // Every variant a model config can name parses from that name and back, and builds its config.
    for n in ["tiny", "vit_small_14", "vit_base_14", "vit_large_14"] {
        let v: mvmp_backbone::VitVariant = n.parse().unwrap();
        assert_eq!(v.name(), n);
    }
    assert_eq!(
        mvmp_backbone::VitVariant::Large14.config(),
        ViTConfig::vit_large_14()
    );
    assert!("vit_huge".parse::<mvmp_backbone::VitVariant>().is_err());
}

#[test]
fn pos_embed_interpolation_is_the_identity_at_native_size_and_matches_direct_bicubic() {
    let d = Device::flex();
    let vit = ViTConfig::tiny().init(&d);
    let pe = vals(vit.pos_embed.val());
    assert_eq!(vals(vit.interpolate_pos_embed(16, 16)), pe);
    // Direct evaluation of PyTorch's bicubic (A = -0.75) with the scale-factor mapping, per output pixel.
    let (m, c, h0, w0) = (16usize, 192usize, 9usize, 20usize);
    let out = vals(vit.interpolate_pos_embed(h0, w0));
    assert_eq!(out.len(), (1 + h0 * w0) * c);
    assert_eq!(out[..c], pe[..c], "class token untouched");
    let cubic = |x: f64| {
        let a = -0.75;
        let x = x.abs();
        if x <= 1.0 {
            (a + 2.0) * x.powi(3) - (a + 3.0) * x * x + 1.0
        } else if x < 2.0 {
            a * x.powi(3) - 5.0 * a * x * x + 8.0 * a * x - 4.0 * a
        } else {
            0.0
        }
    };
    let src = |o: usize, out_n: usize| (o as f64 + 0.5) * m as f64 / (out_n as f64 + 0.1) - 0.5;
    for (i, j, ch) in [(0, 0, 0), (4, 7, 5), (8, 19, 191), (3, 11, 77)] {
        let (sy, sx) = (src(i, h0), src(j, w0));
        let mut acc = 0.0;
        for ky in (sy.floor() as i64 - 1)..=(sy.floor() as i64 + 2) {
            for kx in (sx.floor() as i64 - 1)..=(sx.floor() as i64 + 2) {
                let (cy, cx) = (
                    ky.clamp(0, m as i64 - 1) as usize,
                    kx.clamp(0, m as i64 - 1) as usize,
                );
                let v = pe[(1 + cy * m + cx) * c + ch] as f64;
                acc += cubic(sy - ky as f64) * cubic(sx - kx as f64) * v;
            }
        }
        let got = out[(1 + i * w0 + j) * c + ch] as f64;
        assert!((got - acc).abs() < 1e-6, "({i}, {j}, {ch}): {got} vs {acc}");
    }
    // Rows of the interpolation matrices sum to 1 (a constant field stays constant).
    let mat = bicubic_matrix(37, 92, 92.1 / 37.0);
    for r in mat.chunks(37) {
        assert!((r.iter().sum::<f64>() - 1.0).abs() < 1e-12);
    }
}

fn formula(n: usize, a: f64, b: f64, scale: f64) -> Vec<f32> {
    (0..n)
        .map(|i| ((i as f64 * a + b).sin() * scale) as f32)
        .collect()
}

fn param1(v: Vec<f32>, d: &Device) -> Param<Tensor<1>> {
    let n = v.len();
    Param::from_tensor(Tensor::from_data(TensorData::new(v, [n]), d))
}

/// A PyTorch `[out, in]` weight into burn's `[in, out]` layout.
fn linear_weight(v: Vec<f32>, out: usize, inp: usize, d: &Device) -> Param<Tensor<2>> {
    let t: Vec<f32> = (0..inp * out)
        .map(|k| v[(k % out) * inp + k / out])
        .collect();
    Param::from_tensor(Tensor::from_data(TensorData::new(t, [inp, out]), d))
}

#[test]
fn one_block_matches_the_numpy_reference() {
    let fx: serde_json::Value =
        serde_json::from_str(include_str!("fixtures/vit_block.json")).unwrap();
    let (c, heads, n, hidden) = (8usize, 2usize, 5usize, 32usize);
    assert_eq!(fx["C"], c);
    let d = Device::flex();
    let mut vit = ViTConfig::new(c, 1, heads)
        .with_img_size(28)
        .with_mlp_ratio(4.0)
        .init(&d);
    let b = &mut vit.blocks[0];
    b.norm1.gamma = param1(
        formula(c, 0.5, 0.2, 0.1).iter().map(|x| x + 1.0).collect(),
        &d,
    );
    b.norm1.beta = Some(param1(formula(c, 0.7, 0.3, 0.1), &d));
    b.attn.qkv.weight = linear_weight(formula(3 * c * c, 0.11, 0.4, 0.3), 3 * c, c, &d);
    b.attn.qkv.bias = Some(param1(formula(3 * c, 0.13, 0.5, 0.1), &d));
    b.attn.proj.weight = linear_weight(formula(c * c, 0.17, 0.6, 0.3), c, c, &d);
    b.attn.proj.bias = Some(param1(formula(c, 0.19, 0.7, 0.1), &d));
    b.ls1.gamma = param1(
        formula(c, 0.23, 0.8, 0.2).iter().map(|x| x + 0.5).collect(),
        &d,
    );
    b.norm2.gamma = param1(
        formula(c, 0.29, 0.9, 0.1).iter().map(|x| x + 1.0).collect(),
        &d,
    );
    b.norm2.beta = Some(param1(formula(c, 0.31, 1.0, 0.1), &d));
    b.mlp.fc1.weight = linear_weight(formula(hidden * c, 0.41, 1.1, 0.3), hidden, c, &d);
    b.mlp.fc1.bias = Some(param1(formula(hidden, 0.43, 1.2, 0.1), &d));
    b.mlp.fc2.weight = linear_weight(formula(c * hidden, 0.47, 1.3, 0.2), c, hidden, &d);
    b.mlp.fc2.bias = Some(param1(formula(c, 0.53, 1.4, 0.1), &d));
    b.ls2.gamma = param1(
        formula(c, 0.59, 1.5, 0.2).iter().map(|x| x + 0.5).collect(),
        &d,
    );
    let x: Vec<f32> = fx["x"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|r| {
            r.as_array()
                .unwrap()
                .iter()
                .map(|v| v.as_f64().unwrap() as f32)
        })
        .collect();
    let want: Vec<f64> = fx["y"]
        .as_array()
        .unwrap()
        .iter()
        .flat_map(|r| r.as_array().unwrap().iter().map(|v| v.as_f64().unwrap()))
        .collect();
    let y = vals(vit.blocks[0].forward(Tensor::from_data(TensorData::new(x, [1, n, c]), &d)));
    let worst = y
        .iter()
        .zip(&want)
        .map(|(a, b)| (*a as f64 - b).abs())
        .fold(0.0, f64::max);
    // float32 against float64.
    assert!(worst < 2e-5, "max abs difference {worst}");
}

/// Features and every parameter's gradient of `vit` on `[2, 3, 56, 70]` images (20 patches each), the
/// output weighted by fixed values: the sum of squares of layer-normalised features is nearly constant,
/// and its gradients would be rounding noise.
fn features_and_gradients(vit: &mvmp_backbone::vit::ViT, d: &Device) -> (Vec<f32>, Vec<Vec<f32>>) {
    use burn::module::ModuleVisitor;
    struct Collect<'a>(&'a burn::tensor::Gradients, Vec<Vec<f32>>);
    impl ModuleVisitor for Collect<'_> {
        fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
            if let Some(g) = p.val().grad(self.0) {
                self.1.push(vals(g));
            }
        }
    }
    let pattern = |n: usize, k: usize, m: usize| -> Vec<f32> {
        (0..n)
            .map(|i| ((i * k) % m) as f32 / m as f32 - 0.5)
            .collect()
    };
    let x = Tensor::<4>::from_data(
        TensorData::new(pattern(2 * 3 * 56 * 70, 31, 89), [2, 3, 56, 70]),
        d,
    );
    let w = Tensor::<4>::from_data(
        TensorData::new(pattern(2 * 192 * 20, 17, 37), [2, 192, 4, 5]),
        d,
    );
    let f = vit.forward(x);
    let grads = (f.clone() * w).sum().backward();
    let mut c = Collect(&grads, Vec::new());
    vit.visit(&mut c);
    (vals(f.detach()), c.1)
}

/// `a` and `b` give the same features and gradients, within 1e-5 of each tensor's largest magnitude.
fn assert_same_features_and_gradients(
    a: &mvmp_backbone::vit::ViT,
    b: &mvmp_backbone::vit::ViT,
    d: &Device,
) {
    let ((fa, ga), (fb, gb)) = (features_and_gradients(a, d), features_and_gradients(b, d));
    let worst = |a: &[f32], b: &[f32]| {
        let scale = a.iter().fold(1e-6f32, |m, x| m.max(x.abs()));
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f32::max)
            / scale
    };
    assert!(
        worst(&fa, &fb) < 1e-5,
        "features differ by {}",
        worst(&fa, &fb)
    );
    assert_eq!(ga.len(), gb.len());
    assert!(ga.len() > 40, "{} gradients", ga.len());
    for (i, (a, b)) in ga.iter().zip(&gb).enumerate() {
        assert!(
            worst(a, b) < 1e-5,
            "parameter {i}: gradient differs by {}",
            worst(a, b)
        );
    }
}

/// Attention in tiles (`mvmp_kernels::attention`, 3 tiles of 8 over 21 tokens) gives the whole score
/// matrix's result: the same features and the same gradient of every parameter.
#[test]
fn tiled_attention_gives_the_same_features_and_gradients() {
    let d = Device::flex().autodiff();
    let whole = ViTConfig::tiny().with_attention_tile(0).init(&d);
    let mut tiled = whole.clone();
    for b in &mut tiled.blocks {
        b.attn.tile = 8;
    }
    assert_same_features_and_gradients(&whole, &tiled, &d);
}

/// Blocks recomputed in the backward (`mvmp_kernels::recompute`) give the stored blocks' features and
/// the same gradient of every parameter.
#[test]
fn recomputed_blocks_give_the_same_features_and_gradients() {
    let d = Device::flex().autodiff();
    let stored = ViTConfig::tiny().with_attention_tile(8).init(&d);
    let mut recomputed = stored.clone();
    for b in &mut recomputed.blocks {
        b.recompute = true;
    }
    assert_same_features_and_gradients(&stored, &recomputed, &d);
}
