//! DINOv2 import from checkpoints written here in the exact torch-hub and Hugging Face key layouts and shapes
//! (`dinov2_vit*14_pretrain.pth`, `facebook/dinov2-*`), with deterministic pseudo-random values.
use std::path::Path;

use burn::tensor::Device;
use mvmp_backbone::ViTConfig;
use mvmp_backbone::import::import_dinov2;

fn value(name: &str, i: usize) -> f32 {
    let mut h: u64 = 1469598103934665603;
    for b in name.bytes() {
        h = (h ^ b as u64).wrapping_mul(1099511628211);
    }
    let mut z = h ^ (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
    z = (z ^ (z >> 31)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z ^= z >> 29;
    (z >> 40) as f32 / (1u64 << 24) as f32 - 0.5
}

/// The torch-hub DINOv2 state dict of a ViT of width `c`, `depth` blocks, a `m x m` position grid.
fn hub_keys(c: usize, depth: usize, m: usize) -> Vec<(String, Vec<usize>)> {
    let mut k: Vec<(String, Vec<usize>)> = vec![
        ("cls_token".into(), vec![1, 1, c]),
        ("pos_embed".into(), vec![1, 1 + m * m, c]),
        ("mask_token".into(), vec![1, c]),
        ("patch_embed.proj.weight".into(), vec![c, 3, 14, 14]),
        ("patch_embed.proj.bias".into(), vec![c]),
        ("norm.weight".into(), vec![c]),
        ("norm.bias".into(), vec![c]),
    ];
    for i in 0..depth {
        let b = |s: &str| format!("blocks.{i}.{s}");
        for (n, s) in [
            ("norm1.weight", vec![c]),
            ("norm1.bias", vec![c]),
            ("attn.qkv.weight", vec![3 * c, c]),
            ("attn.qkv.bias", vec![3 * c]),
            ("attn.proj.weight", vec![c, c]),
            ("attn.proj.bias", vec![c]),
            ("ls1.gamma", vec![c]),
            ("norm2.weight", vec![c]),
            ("norm2.bias", vec![c]),
            ("mlp.fc1.weight", vec![4 * c, c]),
            ("mlp.fc1.bias", vec![4 * c]),
            ("mlp.fc2.weight", vec![c, 4 * c]),
            ("mlp.fc2.bias", vec![c]),
            ("ls2.gamma", vec![c]),
        ] {
            k.push((b(n), s));
        }
    }
    k
}

fn data(name: &str, shape: &[usize]) -> Vec<u8> {
    let n: usize = shape.iter().product();
    (0..n).flat_map(|i| value(name, i).to_le_bytes()).collect()
}

fn write(path: &Path, tensors: Vec<(String, Vec<usize>, Vec<u8>)>) {
    let views: Vec<(String, safetensors::tensor::TensorView)> = tensors
        .iter()
        .map(|(n, s, d)| {
            (
                n.clone(),
                safetensors::tensor::TensorView::new(safetensors::Dtype::F32, s.clone(), d)
                    .unwrap(),
            )
        })
        .collect();
    std::fs::write(path, safetensors::serialize(views, None).unwrap()).unwrap();
}

fn check_variant(cfg: ViTConfig, prefix: &str, with_hf: bool) {
    let d = Device::flex();
    let (c, depth, m) = (cfg.embed_dim, cfg.depth, cfg.pos_grid());
    let dir = tempfile::tempdir().unwrap();
    let keys = hub_keys(c, depth, m);
    let hub = dir.path().join("hub.safetensors");
    write(
        &hub,
        keys.iter()
            .map(|(n, s)| (format!("{prefix}{n}"), s.clone(), data(n, s)))
            .collect(),
    );
    let mut vit = cfg.init(&d);
    let rep = import_dinov2(&mut vit, &hub).unwrap();
    assert!(
        rep.missing.is_empty() && rep.unused.is_empty() && rep.errors.is_empty(),
        "{:?} {:?} {:?}",
        rep.missing,
        rep.unused,
        rep.errors
    );
    assert_eq!(rep.loaded.len(), keys.len());
    // Values land in place: Linear weights transposed, LayerNorm weight -> gamma.
    let qkv: Vec<f32> = vit.blocks[depth - 1]
        .attn
        .qkv
        .weight
        .val()
        .into_data()
        .try_into_vec()
        .unwrap();
    let name = format!("blocks.{}.attn.qkv.weight", depth - 1);
    for (row, col) in [(0usize, 0usize), (3 * c - 1, 5), (c + 7, c - 1)] {
        assert_eq!(
            qkv[col * 3 * c + row],
            value(&name, row * c + col),
            "qkv[{row}][{col}]"
        );
    }
    let g: Vec<f32> = vit.norm.gamma.val().into_data().try_into_vec().unwrap();
    assert_eq!(g[3], value("norm.weight", 3));
    let pe: Vec<f32> = vit.pos_embed.val().into_data().try_into_vec().unwrap();
    assert_eq!(pe[c + 1], value("pos_embed", c + 1));
    // Saved in burn's native format and loaded back, unchanged.
    let native = dir.path().join("vit.bpk");
    mvmp_io::checkpoint::save(&vit, &native).unwrap();
    let mut back = cfg.init(&d);
    let rep = mvmp_io::checkpoint::load(&mut back, &native).unwrap();
    assert!(rep.missing.is_empty() && rep.errors.is_empty());
    let qkv_back: Vec<f32> = back.blocks[depth - 1]
        .attn
        .qkv
        .weight
        .val()
        .into_data()
        .try_into_vec()
        .unwrap();
    assert_eq!(qkv_back, qkv);

    if !with_hf {
        return;
    }
    // The same weights under the Hugging Face names (q, k and v separate) import to the same model.
    let mut hf = Vec::new();
    for (n, s) in &keys {
        let v = data(n, s);
        let new = if let Some(rest) = n.strip_prefix("blocks.") {
            let (i, tail) = rest.split_once('.').unwrap();
            if let Some(field) = tail.strip_prefix("attn.qkv.") {
                let part = v.len() / 3;
                for (j, w) in ["query", "key", "value"].iter().enumerate() {
                    let mut sh = s.clone();
                    sh[0] /= 3;
                    hf.push((
                        format!("encoder.layer.{i}.attention.attention.{w}.{field}"),
                        sh,
                        v[j * part..(j + 1) * part].to_vec(),
                    ));
                }
                continue;
            }
            let t = tail
                .replace("attn.proj.", "attention.output.dense.")
                .replace("ls1.gamma", "layer_scale1.lambda1")
                .replace("ls2.gamma", "layer_scale2.lambda1");
            format!("encoder.layer.{i}.{t}")
        } else {
            match n.as_str() {
                "cls_token" | "mask_token" => format!("embeddings.{n}"),
                "pos_embed" => "embeddings.position_embeddings".into(),
                _ if n.starts_with("patch_embed.proj.") => n.replace(
                    "patch_embed.proj.",
                    "embeddings.patch_embeddings.projection.",
                ),
                _ => n.replace("norm.", "layernorm."),
            }
        };
        hf.push((new, s.clone(), v));
    }
    let hfp = dir.path().join("model.safetensors");
    write(&hfp, hf);
    let mut vit2 = cfg.init(&d);
    let rep = import_dinov2(&mut vit2, &hfp).unwrap();
    assert!(
        rep.missing.is_empty() && rep.unused.is_empty(),
        "{:?} {:?}",
        rep.missing,
        rep.unused
    );
    let qkv2: Vec<f32> = vit2.blocks[depth - 1]
        .attn
        .qkv
        .weight
        .val()
        .into_data()
        .try_into_vec()
        .unwrap();
    assert_eq!(qkv, qkv2);
}

#[test]
fn hub_and_hugging_face_layouts_import_tiny_and_small() {
    check_variant(ViTConfig::tiny(), "", true);
    check_variant(ViTConfig::vit_small_14(), "backbone.", true);
}

#[test]
fn hub_layout_imports_base_and_large() {
    check_variant(ViTConfig::vit_base_14(), "module.", false);
    check_variant(ViTConfig::vit_large_14(), "", false);
}

#[test]
fn bad_files_are_errors() {
    let d = Device::flex();
    let mut vit = ViTConfig::tiny().init(&d);
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("junk.safetensors");
    std::fs::write(&p, b"not a checkpoint").unwrap();
    assert!(
        import_dinov2(&mut vit, &p)
            .unwrap_err()
            .to_string()
            .contains("junk.safetensors")
    );
    assert!(
        import_dinov2(&mut vit, &dir.path().join("w.onnx"))
            .unwrap_err()
            .to_string()
            .contains(".safetensors or .pth")
    );
    assert!(import_dinov2(&mut vit, &dir.path().join("absent.pth")).is_err());
}

#[test]
fn hugging_face_attention_of_mismatched_shapes_and_non_finite_weights_are_refused() {
    let d = Device::flex();
    let dir = tempfile::tempdir().unwrap();
    let layer = "encoder.layer.0.attention.attention";
    let patch = (
        "embeddings.patch_embeddings.projection.weight".to_string(),
        vec![192, 3, 16, 16],
        data("patch", &[192, 3, 16, 16]),
    );
    // Scalars (once an index panic) and three different shapes (once concatenated silently).
    for (i, shapes) in [
        [vec![], vec![], vec![]],
        [vec![192, 192], vec![96, 384], vec![384, 96]],
    ]
    .into_iter()
    .enumerate()
    {
        let mut t = vec![patch.clone()];
        for (name, shape) in ["query", "key", "value"].into_iter().zip(shapes) {
            let bytes = data(name, &shape);
            t.push((format!("{layer}.{name}.weight"), shape, bytes));
        }
        let p = dir.path().join(format!("qkv{i}.safetensors"));
        write(&p, t);
        let mut vit = ViTConfig::tiny().init(&d);
        let e = import_dinov2(&mut vit, &p).unwrap_err().to_string();
        assert!(
            e.contains(&format!("qkv{i}.safetensors")) && e.contains("block 0"),
            "{e}"
        );
    }
    // A NaN in the class token.
    let mut cls = data("cls", &[1, 1, 192]);
    cls[..4].copy_from_slice(&f32::NAN.to_le_bytes());
    let p = dir.path().join("nan.safetensors");
    write(&p, vec![("cls_token".into(), vec![1, 1, 192], cls)]);
    let mut vit = ViTConfig::tiny().init(&d);
    let e = import_dinov2(&mut vit, &p).unwrap_err().to_string();
    assert!(
        e.contains("nan.safetensors") && e.contains("cls_token"),
        "{e}"
    );
}
