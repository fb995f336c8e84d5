//! Importing pretrained DINOv2 weights into [`ViT`].
//!
//! Accepted sources: the torch-hub checkpoint (`dinov2_vit*14_pretrain.pth`, or the same state dict saved
//! as `.safetensors`) and the Hugging Face `facebook/dinov2-*` `model.safetensors`. Keys may carry a
//! `module.`, `backbone.` or `encoder.` prefix (wrappers such as Multi-HMR's), which is removed.
//! PyTorch layouts are adapted on the way in (Linear weights transposed; LayerNorm `weight`/`bias` become
//! `gamma`/`beta`).
//!
//! | torch-hub key                      | Hugging Face key                                              | mvmp key |
//! |------------------------------------|---------------------------------------------------------------|----------|
//! | `cls_token`                        | `embeddings.cls_token`                                        | same as torch-hub |
//! | `pos_embed`                        | `embeddings.position_embeddings`                              | |
//! | `mask_token`                       | `embeddings.mask_token`                                       | |
//! | `patch_embed.proj.{weight,bias}`   | `embeddings.patch_embeddings.projection.*`                    | |
//! | `blocks.N.norm1.*`                 | `encoder.layer.N.norm1.*`                                     | `blocks.N.norm1.{gamma,beta}` |
//! | `blocks.N.attn.qkv.*`              | `encoder.layer.N.attention.attention.{query,key,value}.*` (concatenated q, k, v) | |
//! | `blocks.N.attn.proj.*`             | `encoder.layer.N.attention.output.dense.*`                    | |
//! | `blocks.N.ls1.gamma`               | `encoder.layer.N.layer_scale1.lambda1`                        | |
//! | `blocks.N.norm2.*`                 | `encoder.layer.N.norm2.*`                                     | |
//! | `blocks.N.mlp.fc1.*`, `mlp.fc2.*`  | `encoder.layer.N.mlp.fc1.*`, `mlp.fc2.*`                      | |
//! | `blocks.N.ls2.gamma`               | `encoder.layer.N.layer_scale2.lambda1`                        | |
//! | `norm.*`                           | `layernorm.*`                                                 | `norm.{gamma,beta}` |
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use burn::store::{ModuleSnapshot, PyTorchToBurnAdapter, PytorchStore, SafetensorsStore};

use crate::ViT;

#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    #[error("{path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("{path}: {what}")]
    Format { path: PathBuf, what: String },
    #[error(transparent)]
    Output(#[from] mvmp_io::IoError),
}

use mvmp_io::checkpoint::{LoadReport, check_finite};

/// A tensor read from a file: dtype, shape, little-endian bytes.
type Raw = (safetensors::Dtype, Vec<usize>, Vec<u8>);

const PREFIXES: &str = r"^(module\.)?(backbone\.)?(encoder\.)?";

/// Rename Hugging Face DINOv2 tensors to the torch-hub names, concatenating query, key and value.
fn hf_to_hub(st: &safetensors::SafeTensors, path: &Path) -> Result<Vec<u8>, ImportError> {
    let fmt = |what: String| ImportError::Format {
        path: path.into(),
        what,
    };
    let mut out: BTreeMap<String, Raw> = BTreeMap::new();
    // (block, weight|bias) -> query, key, value.
    let mut qkv: BTreeMap<(usize, String), [Option<Raw>; 3]> = BTreeMap::new();
    for (name, view) in st.tensors() {
        let key = name.trim_start_matches("dinov2.");
        let entry = (view.dtype(), view.shape().to_vec(), view.data().to_vec());
        let renamed = if let Some(rest) = key.strip_prefix("embeddings.") {
            match rest {
                "cls_token" => "cls_token".to_string(),
                "mask_token" => "mask_token".to_string(),
                "position_embeddings" => "pos_embed".to_string(),
                r => match r.strip_prefix("patch_embeddings.projection.") {
                    Some(p) => format!("patch_embed.proj.{p}"),
                    None => key.to_string(),
                },
            }
        } else if let Some(rest) = key.strip_prefix("encoder.layer.") {
            let (n, tail) = rest
                .split_once('.')
                .ok_or_else(|| fmt(format!("unexpected key {name}")))?;
            let n: usize = n
                .parse()
                .map_err(|_| fmt(format!("unexpected key {name}")))?;
            if let Some(p) = tail.strip_prefix("attention.attention.") {
                let (which, field) = p.split_once('.').unwrap_or((p, ""));
                let slot = match which {
                    "query" => 0,
                    "key" => 1,
                    "value" => 2,
                    _ => return Err(fmt(format!("unexpected key {name}"))),
                };
                qkv.entry((n, field.to_string())).or_default()[slot] = Some(entry);
                continue;
            }
            let t = tail
                .replace("attention.output.dense.", "attn.proj.")
                .replace("layer_scale1.lambda1", "ls1.gamma")
                .replace("layer_scale2.lambda1", "ls2.gamma");
            format!("blocks.{n}.{t}")
        } else if let Some(p) = key.strip_prefix("layernorm.") {
            format!("norm.{p}")
        } else {
            key.to_string()
        };
        out.insert(renamed, entry);
    }
    for ((n, field), parts) in qkv {
        let [Some(q), Some(k), Some(v)] = parts else {
            return Err(fmt(format!(
                "block {n}: query, key and value {field} are not all present"
            )));
        };
        if q.1.is_empty() || (q.0, &q.1) != (k.0, &k.1) || (q.0, &q.1) != (v.0, &v.1) {
            return Err(fmt(format!(
                "block {n}: query, key and value {field} must be arrays of one shape and dtype; they are {:?} {:?}, {:?} {:?} and {:?} {:?}",
                q.0, q.1, k.0, k.1, v.0, v.1
            )));
        }
        // Stacked along the output dimension (rows): [q; k; v].
        let mut shape = q.1.clone();
        shape[0] *= 3;
        let data = [q.2, k.2, v.2].concat();
        out.insert(format!("blocks.{n}.attn.qkv.{field}"), (q.0, shape, data));
    }
    let views: Vec<(String, safetensors::tensor::TensorView)> = out
        .iter()
        .map(|(k, (dt, shape, data))| {
            safetensors::tensor::TensorView::new(*dt, shape.clone(), data)
                .map(|v| (k.clone(), v))
                .map_err(|e| fmt(format!("{k}: {e}")))
        })
        .collect::<Result<_, _>>()?;
    safetensors::serialize(views, None).map_err(|e| fmt(e.to_string()))
}

/// Load DINOv2 weights from `path` into `vit`.
pub fn import_dinov2(vit: &mut ViT, path: &Path) -> Result<LoadReport, ImportError> {
    let io = |source| ImportError::Io {
        path: path.into(),
        source,
    };
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
    let result = match ext {
        "safetensors" => {
            let bytes = std::fs::read(path).map_err(io)?;
            let st =
                safetensors::SafeTensors::deserialize(&bytes).map_err(|e| ImportError::Format {
                    path: path.into(),
                    what: format!("not a safetensors file: {e}"),
                })?;
            let is_hf = st
                .names()
                .iter()
                .any(|n| n.contains("embeddings.patch_embeddings"));
            let bytes = if is_hf {
                hf_to_hub(&st, path)?
            } else {
                bytes.clone()
            };
            let mut store = SafetensorsStore::from_bytes(Some(bytes))
                .with_key_remapping(PREFIXES, "")
                .with_from_adapter(PyTorchToBurnAdapter)
                .allow_partial(true)
                .validate(false);
            vit.load_from(&mut store).map_err(|e| ImportError::Format {
                path: path.into(),
                what: e.to_string(),
            })?
        }
        "pth" | "pt" | "bin" => {
            if !path.exists() {
                return Err(io(std::io::Error::new(
                    std::io::ErrorKind::NotFound,
                    "no such file",
                )));
            }
            let mut store = PytorchStore::from_file(path)
                .with_key_remapping(PREFIXES, "")
                .allow_partial(true)
                .validate(false);
            vit.load_from(&mut store).map_err(|e| ImportError::Format {
                path: path.into(),
                what: e.to_string(),
            })?
        }
        _ => {
            return Err(ImportError::Format {
                path: path.into(),
                what: "expected a .safetensors or .pth checkpoint".into(),
            });
        }
    };
    check_finite(vit, path)?;
    Ok(result.into())
}

/// Source-key rewrites from the reference HRNet (`pose_hrnet.py`) names to mvmp's, applied in order:
///
/// | reference key                                   | mvmp key                                          |
/// |-------------------------------------------------|---------------------------------------------------|
/// | `layer1.N.downsample.{0,1}.*`                   | `layer1.N.downsample.{conv,bn}.*`                 |
/// | `transitionT.B.0.{0,1}.*` (new branch, stride 2) | `transitionT.layers.B.{conv,bn}.*`               |
/// | `transitionT.B.{0,1}.*` (width change)          | `transitionT.layers.B.{conv,bn}.*`                |
/// | `stageS.M.fuse_layers.I.J.K.{0,1}.*` (J < I)    | `stageS.M.fuse_layers.I.J.down.K.cb.{conv,bn}.*`  |
/// | `stageS.M.fuse_layers.I.J.{0,1}.*` (J > I)      | `stageS.M.fuse_layers.I.J.up.{conv,bn}.*`         |
/// | everything else (`conv1`, `bn1`, `layerN`, `stageS.M.branches.B.K.*`, `final_layer`) | unchanged |
///
/// Batch norms: `weight`/`bias` become `gamma`/`beta`; `running_mean`/`running_var` load;
/// `num_batches_tracked` is reported unused.
const HRNET_RULES: [(&str, &str); 10] = [
    (r"\.downsample\.0\.", ".downsample.conv."),
    (r"\.downsample\.1\.", ".downsample.bn."),
    (
        r"^transition(\d)\.(\d)\.0\.0\.",
        "transition${1}.layers.${2}.conv.",
    ),
    (
        r"^transition(\d)\.(\d)\.0\.1\.",
        "transition${1}.layers.${2}.bn.",
    ),
    (
        r"^transition(\d)\.(\d)\.0\.",
        "transition${1}.layers.${2}.conv.",
    ),
    (
        r"^transition(\d)\.(\d)\.1\.",
        "transition${1}.layers.${2}.bn.",
    ),
    (
        r"fuse_layers\.(\d)\.(\d)\.(\d)\.0\.",
        "fuse_layers.${1}.${2}.down.${3}.cb.conv.",
    ),
    (
        r"fuse_layers\.(\d)\.(\d)\.(\d)\.1\.",
        "fuse_layers.${1}.${2}.down.${3}.cb.bn.",
    ),
    (
        r"fuse_layers\.(\d)\.(\d)\.0\.",
        "fuse_layers.${1}.${2}.up.conv.",
    ),
    (
        r"fuse_layers\.(\d)\.(\d)\.1\.",
        "fuse_layers.${1}.${2}.up.bn.",
    ),
];

/// Load reference HRNet weights (`.pth` or `.safetensors`) into `net`.
pub fn import_hrnet(net: &mut crate::HRNet, path: &Path) -> Result<LoadReport, ImportError> {
    let fmt = |what: String| ImportError::Format {
        path: path.into(),
        what,
    };
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("");
    let result = match ext {
        "safetensors" => {
            let bytes = std::fs::read(path).map_err(|source| ImportError::Io {
                path: path.into(),
                source,
            })?;
            safetensors::SafeTensors::deserialize(&bytes)
                .map_err(|e| fmt(format!("not a safetensors file: {e}")))?;
            let mut store = SafetensorsStore::from_bytes(Some(bytes))
                .with_key_remapping(PREFIXES, "")
                .with_from_adapter(PyTorchToBurnAdapter)
                .allow_partial(true)
                .validate(false);
            for (from, to) in HRNET_RULES {
                store = store.with_key_remapping(from, to);
            }
            net.load_from(&mut store).map_err(|e| fmt(e.to_string()))?
        }
        "pth" | "pt" => {
            if !path.exists() {
                return Err(ImportError::Io {
                    path: path.into(),
                    source: std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
                });
            }
            let mut store = PytorchStore::from_file(path)
                .with_key_remapping(PREFIXES, "")
                .allow_partial(true)
                .validate(false);
            for (from, to) in HRNET_RULES {
                store = store.with_key_remapping(from, to);
            }
            net.load_from(&mut store).map_err(|e| fmt(e.to_string()))?
        }
        _ => return Err(fmt("expected a .safetensors or .pth checkpoint".into())),
    };
    check_finite(net, path)?;
    Ok(result.into())
}
