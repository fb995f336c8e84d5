//! HRNet import from checkpoints written here with the key names and shapes of the reference
//! `pose_hrnet.py` (deep-high-resolution-net.pytorch).
use burn::tensor::Device;
use mvmp_backbone::HRNetConfig;
use mvmp_backbone::import::import_hrnet;

/// The reference state dict of an HRNet: (key, shape).
fn reference_keys(cfg: &HRNetConfig) -> Vec<(String, Vec<usize>)> {
    let mut k = Vec::new();
    let conv =
        |k: &mut Vec<(String, Vec<usize>)>, name: String, ci: usize, co: usize, ks: usize| {
            k.push((format!("{name}.weight"), vec![co, ci, ks, ks]));
        };
    let bn = |k: &mut Vec<(String, Vec<usize>)>, name: String, c: usize| {
        for f in ["weight", "bias", "running_mean", "running_var"] {
            k.push((format!("{name}.{f}"), vec![c]));
        }
        k.push((format!("{name}.num_batches_tracked"), vec![]));
    };
    conv(&mut k, "conv1".into(), 3, cfg.stem, 3);
    bn(&mut k, "bn1".into(), cfg.stem);
    conv(&mut k, "conv2".into(), cfg.stem, cfg.stem, 3);
    bn(&mut k, "bn2".into(), cfg.stem);
    let l1 = cfg.planes * 4;
    for i in 0..4 {
        let ci = if i == 0 { cfg.stem } else { l1 };
        conv(&mut k, format!("layer1.{i}.conv1"), ci, cfg.planes, 1);
        bn(&mut k, format!("layer1.{i}.bn1"), cfg.planes);
        conv(
            &mut k,
            format!("layer1.{i}.conv2"),
            cfg.planes,
            cfg.planes,
            3,
        );
        bn(&mut k, format!("layer1.{i}.bn2"), cfg.planes);
        conv(&mut k, format!("layer1.{i}.conv3"), cfg.planes, l1, 1);
        bn(&mut k, format!("layer1.{i}.bn3"), l1);
        if ci != l1 {
            conv(&mut k, format!("layer1.{i}.downsample.0"), ci, l1, 1);
            bn(&mut k, format!("layer1.{i}.downsample.1"), l1);
        }
    }
    let w: Vec<usize> = (0..4).map(|b| cfg.width << b).collect();
    conv(&mut k, "transition1.0.0".into(), l1, w[0], 3);
    bn(&mut k, "transition1.0.1".into(), w[0]);
    conv(&mut k, "transition1.1.0.0".into(), l1, w[1], 3);
    bn(&mut k, "transition1.1.0.1".into(), w[1]);
    for (t, nb) in [(2usize, 3usize), (3, 4)] {
        conv(
            &mut k,
            format!("transition{t}.{}.0.0", nb - 1),
            w[nb - 2],
            w[nb - 1],
            3,
        );
        bn(&mut k, format!("transition{t}.{}.0.1", nb - 1), w[nb - 1]);
    }
    for (si, &modules) in cfg.modules.iter().enumerate() {
        let (s, nb) = (si + 2, si + 2);
        for m in 0..modules {
            for (b, &wb) in w.iter().enumerate().take(nb) {
                for blk in 0..cfg.blocks {
                    let p = format!("stage{s}.{m}.branches.{b}.{blk}");
                    conv(&mut k, format!("{p}.conv1"), wb, wb, 3);
                    bn(&mut k, format!("{p}.bn1"), wb);
                    conv(&mut k, format!("{p}.conv2"), wb, wb, 3);
                    bn(&mut k, format!("{p}.bn2"), wb);
                }
            }
            let outputs = if s == 4 && m == modules - 1 { 1 } else { nb };
            for i in 0..outputs {
                for j in 0..nb {
                    let p = format!("stage{s}.{m}.fuse_layers.{i}.{j}");
                    if j > i {
                        conv(&mut k, format!("{p}.0"), w[j], w[i], 1);
                        bn(&mut k, format!("{p}.1"), w[i]);
                    } else if j < i {
                        for c in 0..i - j {
                            let co = if c == i - j - 1 { w[i] } else { w[j] };
                            conv(&mut k, format!("{p}.{c}.0"), w[j], co, 3);
                            bn(&mut k, format!("{p}.{c}.1"), co);
                        }
                    }
                }
            }
        }
    }
    k.push(("final_layer.weight".into(), vec![cfg.joints, w[0], 1, 1]));
    k.push(("final_layer.bias".into(), vec![cfg.joints]));
    k
}

fn write(path: &std::path::Path, keys: &[(String, Vec<usize>)]) {
    let data: Vec<(String, Vec<usize>, Vec<u8>, safetensors::Dtype)> = keys
        .iter()
        .map(|(n, s)| {
            let count: usize = s.iter().product();
            if n.ends_with("num_batches_tracked") {
                (
                    n.clone(),
                    s.clone(),
                    7i64.to_le_bytes().to_vec(),
                    safetensors::Dtype::I64,
                )
            } else {
                let v: Vec<u8> = (0..count)
                    .flat_map(|i| ((i % 13) as f32 * 0.01 + 0.5).to_le_bytes())
                    .collect();
                (n.clone(), s.clone(), v, safetensors::Dtype::F32)
            }
        })
        .collect();
    let views: Vec<(String, safetensors::tensor::TensorView)> = data
        .iter()
        .map(|(n, s, d, t)| {
            (
                n.clone(),
                safetensors::tensor::TensorView::new(*t, s.clone(), d).unwrap(),
            )
        })
        .collect();
    std::fs::write(path, safetensors::serialize(views, None).unwrap()).unwrap();
}

#[test]
fn reference_layout_loads_completely() {
    let d = Device::flex();
    for cfg in [
        HRNetConfig::tiny(17),
        HRNetConfig::hrnet_w32(17),
        HRNetConfig::hrnet_w48(17),
    ] {
        let keys = reference_keys(&cfg);
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("pose_hrnet.safetensors");
        write(&p, &keys);
        let mut net = cfg.init(&d);
        let rep = import_hrnet(&mut net, &p).unwrap();
        assert!(rep.missing.is_empty(), "missing: {:?}", rep.missing);
        assert!(rep.errors.is_empty(), "errors: {:?}", rep.errors);
        // Only the batch-norm counters go unused.
        assert!(
            rep.unused
                .iter()
                .all(|k| k.ends_with("num_batches_tracked")),
            "{:?}",
            rep.unused
        );
        let n_tracked = keys
            .iter()
            .filter(|(n, _)| n.ends_with("num_batches_tracked"))
            .count();
        assert_eq!(rep.loaded.len(), keys.len() - n_tracked);
    }
}

/// A batch norm's running variance below zero (its square root is NaN in every forward) is refused,
/// naming the file and the module; so is a non-finite weight.
#[test]
fn negative_running_variances_and_non_finite_weights_are_refused() {
    let d = Device::flex();
    let cfg = HRNetConfig::tiny(17);
    let dir = tempfile::tempdir().unwrap();
    for (key, value, needle) in [
        ("bn1.running_var", -0.5f32, "negative variance"),
        ("conv1.weight", f32::INFINITY, "NaN or infinite"),
    ] {
        let shape = reference_keys(&cfg)
            .into_iter()
            .find(|(n, _)| n == key)
            .unwrap()
            .1;
        let count: usize = shape.iter().product();
        let bytes: Vec<u8> = (0..count)
            .flat_map(|i| if i == 3 { value } else { 0.5 }.to_le_bytes())
            .collect();
        let view =
            safetensors::tensor::TensorView::new(safetensors::Dtype::F32, shape, &bytes).unwrap();
        let p = dir.path().join("bad_hrnet.safetensors");
        std::fs::write(&p, safetensors::serialize([(key, view)], None).unwrap()).unwrap();
        let mut net = cfg.init(&d);
        let e = import_hrnet(&mut net, &p).unwrap_err().to_string();
        let module = key.rsplit_once('.').unwrap().0;
        assert!(
            e.contains("bad_hrnet.safetensors") && e.contains(module) && e.contains(needle),
            "{e}"
        );
    }
}
