//! `mvmp model summary`: parameters per module, the main activations and the multiply-accumulates of one
//! forward, computed from the configuration (the formulas follow each module's structure).
use burn::module::{Module, ModuleVisitor, Param};
use burn::tensor::{Device, Tensor};

use crate::ModelConfig;
use mvmp_backbone::vit::PATCH;
use mvmp_smplx::names::{NUM_JOINTS, NUM_VERTICES};

/// One row of the summary.
#[derive(Debug, Clone)]
pub struct Row {
    pub name: &'static str,
    /// Trainable parameters.
    pub params: usize,
    /// Everything stored in a checkpoint (parameters and running statistics), float32 bytes.
    pub stored_bytes: usize,
    /// Multiply-accumulates of one forward (batch 1, `views` views).
    pub macs: f64,
}

#[derive(Debug, Clone)]
pub struct Summary {
    pub rows: Vec<Row>,
    /// (tensor, float32 bytes) of the largest activations of one forward.
    pub activations: Vec<(String, usize)>,
}

struct Count {
    trainable: usize,
    all: usize,
}

impl ModuleVisitor for Count {
    fn visit_float<const D: usize>(&mut self, p: &Param<Tensor<D>>) {
        let n = p.lazy_shape().num_elements();
        self.all += n;
        if p.is_require_grad() {
            self.trainable += n;
        }
    }
}

fn count<M: Module>(m: &M) -> (usize, usize) {
    let mut c = Count {
        trainable: 0,
        all: 0,
    };
    m.visit(&mut c);
    (c.trainable, c.all * 4)
}

fn conv_macs(ci: usize, co: usize, k: usize, out_pixels: f64) -> f64 {
    (ci * co * k * k) as f64 * out_pixels
}

/// The facing head per view: two stride-2 3 x 3 convolutions on the image, then two 3 x 3 and a 1 x 1
/// at stride 4 (see `FacingHead`).
fn facing_macs(cfg: &ModelConfig) -> f64 {
    let hidden = crate::facing::HIDDEN;
    let s = cfg.hrnet_input() as f64;
    let (half, quarter) = ((s / 2.0).powi(2), (s / 4.0).powi(2));
    let width = cfg.hrnet_config().width;
    conv_macs(3, hidden / 2, 3, half)
        + conv_macs(hidden / 2, hidden, 3, quarter)
        + conv_macs(hidden + width, hidden, 3, quarter)
        + conv_macs(hidden, hidden, 3, quarter)
        + conv_macs(hidden, 2, 1, quarter)
}

/// HRNet multiply-accumulates for an `s x s` input, following [`mvmp_backbone::HRNetConfig`]'s structure.
fn hrnet_macs(cfg: &ModelConfig) -> f64 {
    let h = cfg.hrnet_config();
    let s = cfg.hrnet_input() as f64;
    let px = |stride: f64| (s / stride).ceil().powi(2);
    let mut m = conv_macs(3, h.stem, 3, px(2.0)) + conv_macs(h.stem, h.stem, 3, px(4.0));
    let l1 = h.planes * 4;
    for i in 0..4 {
        let ci = if i == 0 { h.stem } else { l1 };
        m += conv_macs(ci, h.planes, 1, px(4.0)) + conv_macs(h.planes, h.planes, 3, px(4.0));
        m += conv_macs(h.planes, l1, 1, px(4.0));
        if ci != l1 {
            m += conv_macs(ci, l1, 1, px(4.0));
        }
    }
    let w = [h.width, 2 * h.width, 4 * h.width, 8 * h.width];
    let stride = |b: usize| 4.0 * (1 << b) as f64;
    // Transitions.
    m += conv_macs(l1, w[0], 3, px(4.0)) + conv_macs(l1, w[1], 3, px(8.0));
    m += conv_macs(w[1], w[2], 3, px(16.0)) + conv_macs(w[2], w[3], 3, px(32.0));
    for (st, &modules) in h.modules.iter().enumerate() {
        let nb = st + 2;
        for md in 0..modules {
            for (b, &wb) in w.iter().enumerate().take(nb) {
                m += (h.blocks * 2) as f64 * conv_macs(wb, wb, 3, px(stride(b)));
            }
            let outputs = if st == 2 && md == modules - 1 { 1 } else { nb };
            for i in 0..outputs {
                for j in 0..nb {
                    if j > i {
                        m += conv_macs(w[j], w[i], 1, px(stride(j)));
                    } else if j < i {
                        for k in 0..i - j {
                            let co = if k == i - j - 1 { w[i] } else { w[j] };
                            m += conv_macs(w[j], co, 3, px(stride(j + k + 1)));
                        }
                    }
                }
            }
        }
    }
    m + conv_macs(w[0], cfg.heatmap_joints.len(), 1, px(4.0))
}

fn v2v_macs(cfg: &ModelConfig) -> f64 {
    let p = cfg.grid.num_voxels() as f64;
    let w = [16.0, 32.0, 64.0, 128.0].map(|c: f64| (c * cfg.rootnet_width).round().max(2.0));
    let j = cfg.heatmap_joints.len() as f64;
    let res = |ci: f64, co: f64, vox: f64| {
        (ci * co * 27.0 + co * co * 27.0 + if ci != co { ci * co } else { 0.0 }) * vox
    };
    j * w[0] * 343.0 * p
        + res(w[0], w[1], p)
        + res(w[1], w[1], p)
        + res(w[1], w[2], p / 8.0)
        + res(w[2], w[2], p / 8.0)
        + res(w[2], w[3], p / 64.0)
        + 2.0 * res(w[3], w[3], p / 64.0)
        + w[3] * w[2] * 8.0 * p / 8.0
        + res(w[2], w[2], p / 8.0)
        + w[2] * w[1] * 8.0 * p
        + w[1] * 4.0 * p
}

/// Summarise a configuration with `views` views (batch 1). Builds the model on `device`.
/// The ViT attention's largest tensor: the whole score matrix of one block, or one tile of it when
/// attention runs in tiles (`attention_tile`).
fn vit_attention(cfg: &ModelConfig, v: f64, heads: f64, n: f64) -> (String, usize) {
    match cfg.attention_tile {
        0 => (
            "ViT attention of one block [V, heads, N, N]".into(),
            (v * heads * n * n * 4.0) as usize,
        ),
        t => {
            let side = (t as f64).min(n);
            (
                format!("ViT attention score tile [V, heads, {t}, {t}]"),
                (v * heads * side * side * 4.0) as usize,
            )
        }
    }
}

/// The sizes a summary's counts are made of.
struct Sizes {
    /// Views, tokens per view (with the class token), ViT width, the ViT's MLP width.
    v: f64,
    n: f64,
    c: f64,
    hidden: f64,
    /// Voxels, feature channels, heatmap joints, people, decoder width, cross-attention tokens.
    p: f64,
    cf: f64,
    j: f64,
    k: f64,
    d: f64,
    tokens: f64,
}

impl Sizes {
    fn of(cfg: &ModelConfig, views: usize) -> Self {
        let vit = cfg.vit();
        let s = cfg.image_size as usize;
        let c = vit.embed_dim as f64;
        let p = cfg.grid.num_voxels() as f64;
        let pool = cfg.decoder.pool as f64;
        let z_pool = if cfg.grid.shape[2].is_multiple_of(cfg.decoder.pool) {
            pool
        } else {
            1.0
        };
        Sizes {
            v: views as f64,
            n: ((s / PATCH) * (s / PATCH)) as f64 + 1.0,
            c,
            hidden: c * vit.mlp_ratio,
            p,
            cf: cfg.feature_channels as f64,
            j: cfg.heatmap_joints.len() as f64,
            k: cfg.max_people as f64,
            d: cfg.decoder.dim as f64,
            tokens: p / (pool * pool * z_pool),
        }
    }
}

/// The decoder's MACs: token projection, query projection, blocks (or the baseline's MLP).
fn decoder_macs(cfg: &ModelConfig, z: &Sizes) -> f64 {
    let (k, d, tokens) = (z.k, z.d, z.tokens);
    // The query projection reads every lattice point of the features (and the joints' centroids or
    // samples); with `sample_skip` the features' samples (and the joints' samples) are projected a
    // second time, onto the heads' input.
    let dc = cfg.decoder_config();
    let skip = match cfg.decoder.sample_skip {
        true => dc.skip_width(),
        false => 0,
    };
    let inputs = skip + dc.sample_width() + dc.joint_width() + mvmp_decoder::queries::PARAM_DIM;
    let pose_read = match cfg.decoder.pose_read {
        true => dc.joint_width() as f64 * 21.0 * 6.0,
        false => 0.0,
    };
    // The offsets' head (two layers) and their read of the samples.
    let joint_offsets = match cfg.decoder.joint_offsets {
        true => d * d + d * 63.0 + dc.joint_width() as f64 * 63.0,
        false => 0.0,
    };
    let query_macs = k * (inputs as f64 * d + pose_read + joint_offsets);
    tokens * z.cf * d
        + query_macs
        + if cfg.decoder.use_htb {
            cfg.decoder.depth as f64
                * (8.0 * k * d * d + 2.0 * tokens * d * d + 2.0 * k * tokens * d + 8.0 * k * d * d)
        } else {
            k * d * d * 2.0
        }
}

pub fn summarize(cfg: &ModelConfig, views: usize, device: &Device) -> Summary {
    let net = cfg.init(device);
    let z = Sizes::of(cfg, views);
    let (v, n, c, p) = (z.v, z.n, z.c, z.p);
    let vit_macs = v
        * ((3 * PATCH * PATCH) as f64 * c * (n - 1.0)
            + cfg.vit().depth as f64 * (n * (4.0 * c * c + 2.0 * c * z.hidden) + 2.0 * n * n * c));
    // Bilinear sampling: 4 taps per channel, voxel and view.
    let points = net.deformable.as_ref().map_or(1.0, |d| d.points as f64);
    let fusion_macs = v * p * 4.0 * (z.cf * points + z.j);
    let (nj, nv) = (NUM_JOINTS as f64, NUM_VERTICES as f64);
    let smplx_macs = z.k * (486.0 * 3.0 * nv + 12.0 * nj * nv + 20.0 * 3.0 * nv);
    let mut rows = vec![
        ("vit", count(&net.vit), vit_macs),
        ("reduce", count(&net.reduce), v * (c * z.cf) * (n - 1.0)),
        ("hrnet", count(&net.hrnet), v * hrnet_macs(cfg)),
        (
            "fusion",
            net.deformable.as_ref().map_or((0, 0), count),
            fusion_macs,
        ),
        ("rootnet", count(&net.rootnet), v2v_macs(cfg)),
        ("decoder", count(&net.decoder), decoder_macs(cfg, &z)),
        ("smplx", (0, 0), smplx_macs),
    ];
    if let Some(f) = &net.facing {
        rows.insert(3, ("facing", count(f), v * facing_macs(cfg)));
    }
    // Trained in stage 2 and stored with the weights; inference does not run it.
    if let Some(h) = &net.vit_joints {
        rows.insert(2, ("vit_joints", count(h), 0.0));
    }
    let rows = rows
        .into_iter()
        .map(|(name, (params, stored_bytes), macs)| Row {
            name,
            params,
            stored_bytes,
            macs,
        })
        .collect();
    Summary {
        rows,
        activations: activations(cfg, &z),
    }
}

/// The largest activations of one forward (name, bytes).
fn activations(cfg: &ModelConfig, z: &Sizes) -> Vec<(String, usize)> {
    let (v, n, c, p, cf, j, k, tokens) = (z.v, z.n, z.c, z.p, z.cf, z.j, z.k, z.tokens);
    let s = cfg.image_size as f64;
    let b = |x: f64| (x * 4.0) as usize;
    let hs = (cfg.hrnet_input() / 4) as f64;
    let v2v_w0 = (16.0 * cfg.rootnet_width).round().max(2.0);
    vec![
        ("images [V, 3, S, S]".to_string(), b(v * 3.0 * s * s)),
        ("ViT tokens of one block [V, N, C]".into(), b(v * n * c)),
        vit_attention(cfg, v, cfg.vit().heads as f64, n),
        ("features [V, Cf, S/14, S/14]".into(), b(v * cf * (n - 1.0))),
        (format!("heatmaps [V, J, {hs}, {hs}]"), b(v * j * hs * hs)),
        ("fused volume [Cf, X, Y, Z]".into(), b(cf * p)),
        ("heatmap volume [J, X, Y, Z]".into(), b(j * p)),
        ("V2V first activation [16w, X, Y, Z]".into(), b(v2v_w0 * p)),
        (
            "V2V 7^3 input patches (im2col, if the conv unfolds)".into(),
            b(j * 343.0 * p),
        ),
        ("decoder tokens [P/pool^3, D]".into(), b(tokens * z.d)),
        match cfg.attention_tile {
            0 => (
                "cross-attention weights [heads, K, P/pool^3]".into(),
                b(cfg.decoder.heads as f64 * k * tokens),
            ),
            t => (
                format!("cross-attention score tile [heads, K, {t}]"),
                b(cfg.decoder.heads as f64 * k.min(t as f64) * tokens.min(t as f64)),
            ),
        },
        (
            format!("meshes [K, {NUM_VERTICES}, 3]"),
            b(k * NUM_VERTICES as f64 * 3.0),
        ),
    ]
}
