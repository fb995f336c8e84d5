//! The Human Transformer Block and the decoder heads (paper, Sec. 4.3; docs/architecture.md, Pipeline).
//!
//! Queries `[B, K, D]` (one per detected root), the fused volume as tokens `[B, P, D]` with a 3D sinusoidal
//! positional encoding of each voxel centre. Each block: pre-norm self-attention among the people (padded
//! people masked), pre-norm cross-attention to the volume tokens, pre-norm FFN, each residual. Heads: 53
//! rotations (6D), betas, expression, each a residual on the mean parameters, and a 3D offset from the root.
use burn::config::Config;
use burn::module::{Module, Param};
use burn::nn::attention::{MhaInput, MultiHeadAttention, MultiHeadAttentionConfig};
use burn::nn::{LayerNorm, LayerNormConfig, Linear, LinearConfig};
use burn::tensor::activation::gelu;
use burn::tensor::{Bool, Device, Tensor, TensorData};
use serde::{Deserialize, Serialize};

use crate::queries::{PARAM_DIM, mean_params, trilinear_sample};
use mvmp_geom::VoxelGrid;
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_REGRESSED};

/// The decoder's knobs: what a model config's `[decoder]` table sets (each written once, here, with its
/// default). [`DecoderConfig`] adds what the model derives from the rest of its config.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct DecoderOptions {
    /// Model width D.
    pub dim: usize,
    /// Number of Human Transformer Blocks (paper: 2).
    pub depth: usize,
    pub heads: usize,
    /// Hidden width of each block's FFN, in multiples of D.
    pub ffn_ratio: usize,
    /// Average-pool the volume by this factor along every axis whose voxel count it divides (an axis it
    /// does not divide stays unpooled) before cross-attention; 1 keeps every voxel.
    pub pool: usize,
    /// Without blocks: the VoxelSMPLX baseline (an MLP on the sampled queries).
    pub use_htb: bool,
    /// Layer-normalise the volume's sample at each root before it joins the query. It is C channels beside
    /// the 338 constant mean parameters and the root's position encoding, and unnormalised it stays too
    /// small to steer the heads: trained from such queries the decoder gave every person one pose (the
    /// decoder's learning test). false (the paper) keeps the raw sample.
    pub query_norm: bool,
    /// Points per axis (x, y, z) of a lattice centred on each root where the volume is sampled for its
    /// query; `[1, 1, 1]` (the paper) samples the root alone. A person's own column of features reaches
    /// the heads directly, instead of only through cross-attention that starts uniform over the volume.
    pub query_lattice: [usize; 3],
    /// Metres from the lattice's first point to its last along each axis (ignored where it has one).
    pub query_span: [f64; 3],
    /// Turn the query lattice about the vertical with each person's heading (the facing head's
    /// reading), so that its x axis points where the person faces and its y axis to their left: a
    /// raised left hand then falls on the same lattice points whichever way its owner faces. false (a
    /// lattice along the world's axes) makes the map from the samples to the body pose depend on the
    /// heading. The box of `query_joints` turns alike (its samples, or its centroids, which are then
    /// in the heading frame). Needs a heading (`facing = true`) and more than one lattice point or
    /// `query_joints`.
    pub heading_lattice: bool,
    /// The query's (normalised) volume sample also reaches the heads directly: projected by
    /// `sample_proj` and added after the final norm, as the height features are. Through the query
    /// path it shares the residual stream with everything the blocks add for every person alike, and
    /// the trained decoder read none of it (docs/architecture.md, The image features go unread).
    /// false (the paper) has the query path alone.
    pub sample_skip: bool,
    /// Standardise each channel of the volume over its voxels (per scene: zero mean, unit variance)
    /// before the queries sample it and the tokens are made. What sets one person's features apart
    /// can be a small part of a channel whose level is the same everywhere; a small input moves the
    /// weights that read it slowly under Adam (docs/architecture.md, What the decoder is given).
    /// false (the paper) reads the volume as fused.
    pub volume_norm: bool,
    /// Each heatmap joint's centroid near the root, from the joint heatmap volume (the RootNet's input),
    /// joins the query ([`QueryInputs::joints`]; the model sets [`DecoderConfig::joint_channels`] to its
    /// heatmap joints). false (the paper) reads the feature volume alone.
    pub query_joints: bool,
    /// Points per axis of the lattice centred on each root over which each joint's centroid is taken.
    pub joint_lattice: [usize; 3],
    /// Metres from that lattice's first point to its last per axis: the box around the root where a
    /// person's joints are looked for.
    pub joint_span: [f64; 3],
    /// With `query_joints`: the joint heatmap volume joins the query as its samples on the joint lattice
    /// (turned with the heading under `heading_lattice`, layer-normalised) instead of as each joint's
    /// centroid. A centroid keeps one number per joint and axis; a linear read of the samples told the
    /// demo's body poses 0.18 R^2 better than of the centroids (docs/architecture.md, The image features
    /// go unread). With `sample_skip` they also reach the heads directly.
    pub joint_samples: bool,
    /// With `joint_samples`: the joint heatmap samples also reach the 21 body-pose rotations through
    /// one linear map (`pose_read`) that starts at zero, added to what the heads give. Through the
    /// query path the samples share the residual stream with what the blocks add for everyone alike,
    /// and the heads learned to give one pose (docs/architecture.md, The image features go unread); a
    /// linear read of the same samples tells the pose far better than the decoder does. Started at
    /// zero, the map changes nothing at first and grows only along what lowers the loss. false (the
    /// paper) has the heads alone.
    pub pose_read: bool,
    /// With `joint_samples`: a head and a zero-started linear read of the joint samples give a
    /// correction to the 21 body joints' offsets from the pelvis in the body's own frame (its global
    /// rotation's, metres), which the model adds to the offsets its own posed joints have
    /// ([`DecoderOutput::joint_offsets`]). A linear read of the samples places the joints better than
    /// the rotations the decoder regresses do (docs/architecture.md, Joints, then rotations). false
    /// (the paper) regresses rotations alone.
    pub joint_offsets: bool,
    /// Only the body-pose head trains the shared query path (projection, blocks, final norm): the
    /// global orientation, the hands and face, betas, expression and the root offset get heads of
    /// their own that read it detached. Residuals the queries cannot explain (the heading's error,
    /// shapes and expressions a few pixels tall) otherwise flood the shared path, and the decoder
    /// gives everyone one pose: in the decoder's learning test, with the loss on all 53 rotations
    /// and on random betas and expression, the bend error stayed at 1.00 of predicting none
    /// shared, and fell to 0.42 this way. false (the paper) shares one rotation head.
    pub pose_trunk: bool,
    /// Radial basis features of each root's height above the floor (world z = 0), added to the
    /// normalised query the heads read through `height_proj`; 0 (the paper) reads none. A person's
    /// pelvis height tells crouching and sitting from standing, but inside the root's position
    /// encoding, beside its x and y and the heading, the heads did not find it: on the demo the 15%
    /// of held-out people who crouch (pelvis 0.61 m high against 0.92) got everyone's knee bend (0.198
    /// rad against their true 1.9).
    pub height_features: usize,
}

/// The heights (metres) spanned by the centres of [`DecoderOptions::height_features`].
const HEIGHT_RANGE: [f32; 2] = [0.2, 1.4];

impl Default for DecoderOptions {
    fn default() -> Self {
        DecoderOptions {
            dim: 256,
            depth: 2,
            heads: 8,
            ffn_ratio: 4,
            pool: 1,
            use_htb: true,
            query_norm: false,
            query_lattice: [1, 1, 1],
            query_span: [0.0; 3],
            heading_lattice: false,
            sample_skip: false,
            volume_norm: false,
            query_joints: false,
            joint_lattice: [5, 5, 8],
            joint_span: [1.0, 1.0, 1.75],
            joint_samples: false,
            pose_read: false,
            joint_offsets: false,
            pose_trunk: false,
            height_features: 0,
        }
    }
}

/// The decoder as the model builds it: its [`DecoderOptions`] and what the rest of the model fixes.
#[derive(Config, Debug, PartialEq)]
pub struct DecoderConfig {
    /// Channels of the fused feature volume (C_f).
    pub volume_channels: usize,
    #[config(default = "DecoderOptions::default()")]
    pub options: DecoderOptions,
    /// Add each person's estimated heading (a horizontal unit-length direction in the world, `[B, K, 2]`)
    /// to its query through `heading_proj`; false (the paper) reads none.
    #[config(default = false)]
    pub heading: bool,
    /// Joints of a joint heatmap volume whose centroids near each root join its query (see
    /// [`QueryInputs::joints`]); 0 (the paper) reads none.
    #[config(default = 0)]
    pub joint_channels: usize,
    /// Side of the score tiles of cross-attention (`mvmp_kernels::attention`); 0 computes the whole score
    /// matrix with burn's ops.
    #[config(default = "mvmp_kernels::DEFAULT_BLOCK")]
    pub attention_tile: usize,
}

#[derive(Module, Debug)]
pub struct HumanTransformerBlock {
    pub norm_sa: LayerNorm,
    pub self_attn: MultiHeadAttention,
    pub norm_ca: LayerNorm,
    pub cross_attn: MultiHeadAttention,
    pub norm_ffn: LayerNorm,
    pub fc1: Linear,
    pub fc2: Linear,
    /// See [`DecoderConfig::attention_tile`].
    pub tile: usize,
}

/// burn's multi-head attention of `query [B, K, D]` to `context [B, P, D]` through `mha`'s projections,
/// with the scores computed in tiles of side `tile` (0: burn's own forward). No mask: every token counts.
fn cross_attend(
    mha: &MultiHeadAttention,
    query: Tensor<3>,
    context: Tensor<3>,
    tile: usize,
) -> Tensor<3> {
    if tile == 0 {
        return mha
            .forward(MhaInput::new(query, context.clone(), context))
            .context;
    }
    let [b, k, d] = query.dims();
    let (h, dk) = (mha.n_heads, mha.d_k);
    let heads = |x: Tensor<3>, lin: &burn::nn::Linear| {
        let n = x.dims()[1];
        lin.forward(x).reshape([b, n, h, dk]).swap_dims(1, 2)
    };
    let (q, kk, v) = (
        heads(query, &mha.query),
        heads(context.clone(), &mha.key),
        heads(context, &mha.value),
    );
    let out = mvmp_kernels::attention(q, kk, v, 1.0 / (dk as f64).sqrt(), tile);
    mha.output.forward(out.swap_dims(1, 2).reshape([b, k, d]))
}

impl HumanTransformerBlock {
    fn new(dim: usize, heads: usize, ffn: usize, tile: usize, device: &Device) -> Self {
        let mha = || {
            MultiHeadAttentionConfig::new(dim, heads)
                .with_dropout(0.0)
                .init(device)
        };
        HumanTransformerBlock {
            norm_sa: LayerNormConfig::new(dim).init(device),
            self_attn: mha(),
            norm_ca: LayerNormConfig::new(dim).init(device),
            cross_attn: mha(),
            norm_ffn: LayerNormConfig::new(dim).init(device),
            fc1: LinearConfig::new(dim, dim * ffn).init(device),
            fc2: LinearConfig::new(dim * ffn, dim).init(device),
            tile,
        }
    }

    /// `queries [B, K, D]`, `padding [B, K]` (true = no person), `tokens [B, P, D]` -> `[B, K, D]`.
    pub fn forward(&self, q: Tensor<3>, padding: Tensor<2, Bool>, tokens: Tensor<3>) -> Tensor<3> {
        let q = self.self_attention(q, padding);
        let q = self.cross_attention(q, tokens);
        self.feed_forward(q)
    }

    /// The block's first residual: pre-norm self-attention among the people (padded ones masked).
    pub fn self_attention(&self, q: Tensor<3>, padding: Tensor<2, Bool>) -> Tensor<3> {
        let h = self.norm_sa.forward(q.clone());
        q + self
            .self_attn
            .forward(MhaInput::new(h.clone(), h.clone(), h).mask_pad(padding))
            .context
    }

    /// The block's second residual: pre-norm cross-attention of the queries to the volume's tokens.
    pub fn cross_attention(&self, q: Tensor<3>, tokens: Tensor<3>) -> Tensor<3> {
        let h = self.norm_ca.forward(q.clone());
        q + cross_attend(&self.cross_attn, h, tokens, self.tile)
    }

    /// The block's third residual: the pre-norm feed-forward layers.
    pub fn feed_forward(&self, q: Tensor<3>) -> Tensor<3> {
        let h = self.norm_ffn.forward(q.clone());
        q + self.fc2.forward(gelu(self.fc1.forward(h)))
    }
}

/// A two-layer MLP head with a GELU between the layers. With a ReLU there, Adam at 3e-4 or more silenced
/// every hidden unit of the rotation head within a few hundred steps of the decoder's learning test, so
/// that the head gave every person the same output (the test's error stayed at 1.00 of predicting no
/// bend); the GELU keeps a gradient for negative inputs.
#[derive(Module, Debug)]
pub struct Head {
    pub fc1: Linear,
    pub fc2: Linear,
}

impl Head {
    fn new(dim: usize, out: usize, device: &Device) -> Self {
        Head {
            fc1: LinearConfig::new(dim, dim).init(device),
            // Start at the mean: the residual heads begin near zero.
            fc2: LinearConfig::new(dim, out)
                .with_initializer(burn::nn::Initializer::Normal {
                    mean: 0.0,
                    std: 1e-3,
                })
                .init(device),
        }
    }
    fn forward(&self, x: Tensor<3>) -> Tensor<3> {
        self.fc2.forward(gelu(self.fc1.forward(x)))
    }
}

#[derive(Module, Debug)]
pub struct Decoder {
    pub query_proj: Linear,
    pub token_proj: Linear,
    pub pos_proj: Linear,
    pub blocks: Vec<HumanTransformerBlock>,
    pub baseline: Option<Head>,
    pub norm: LayerNorm,
    /// The 53 rotations (6D); with [`DecoderOptions::pose_trunk`] the 21 body joints alone.
    pub rot_head: Head,
    /// With [`DecoderOptions::pose_trunk`]: the global orientation (6D) and the 31 jaw, eye and hand
    /// rotations, each from the detached query.
    pub global_head: Option<Head>,
    pub hands_head: Option<Head>,
    pub betas_head: Head,
    pub expr_head: Head,
    pub offset_head: Head,
    /// See [`DecoderOptions::pose_trunk`].
    pub pose_trunk: bool,
    /// Present when the decoder reads a heading per person (see [`Decoder::forward_with`]).
    pub heading_proj: Option<Linear>,
    /// Present with [`DecoderOptions::height_features`].
    pub height_proj: Option<Linear>,
    /// Present with [`DecoderOptions::sample_skip`].
    pub sample_proj: Option<Linear>,
    /// Present with [`DecoderOptions::pose_read`]: joint samples -> the body's 21 rotations (6D).
    pub pose_read: Option<Linear>,
    /// Present with [`DecoderOptions::joint_offsets`]: the query -> the joint offsets' correction, and
    /// the joint samples -> the same, started at zero.
    pub offsets_head: Option<Head>,
    pub offsets_read: Option<Linear>,
    /// See [`DecoderOptions::volume_norm`].
    #[module(skip)]
    pub volume_norm: bool,
    /// Present with [`DecoderOptions::query_norm`].
    pub query_norm: Option<LayerNorm>,
    /// Present with joint centroids or samples ([`DecoderConfig::joint_channels`] > 0): they are
    /// layer-normalised before they join the query.
    pub joint_norm: Option<LayerNorm>,
    /// See [`DecoderOptions::joint_samples`].
    #[module(skip)]
    pub joint_samples: bool,
    /// Offsets from the root of the query's sample points (see [`DecoderOptions::query_lattice`]).
    #[module(skip)]
    pub lattice: Vec<[f32; 3]>,
    /// See [`DecoderOptions::heading_lattice`].
    #[module(skip)]
    pub heading_lattice: bool,
    /// Offsets from the root over which joint centroids are taken (see [`DecoderOptions::joint_lattice`]).
    #[module(skip)]
    pub joint_lattice: Vec<[f32; 3]>,
    /// Half the joint box per axis (metres): centroids are given as fractions of it.
    #[module(skip)]
    pub joint_half: [f32; 3],
    /// Where the residual heads start: the mean parameters `[PARAM_DIM]` (set from the training data,
    /// kept in checkpoints, never trained).
    pub mean: Param<Tensor<1>>,
    pub pool: usize,
}

/// A parameter that is saved and loaded but not trained.
fn constant(t: Tensor<1>) -> Param<Tensor<1>> {
    Param::from_tensor(t).set_require_grad(false)
}

/// What a query reads beside the feature volume.
#[derive(Debug, Clone, Default)]
pub struct QueryInputs {
    /// Each person's heading (a horizontal unit direction in the world) `[B, K, 2]`, which
    /// `heading_proj` adds to the query (a decoder without `heading_proj` ignores it).
    pub heading: Option<Tensor<3>>,
    /// A joint heatmap volume `[B, E, X, Y, Z]` on the features' grid (`E` the config's
    /// `joint_channels`). Each joint's centroid in the box around a root (its likelihood squared as the
    /// weight) joins the query as an offset from the root: where a person's knees or hands are, a few
    /// numbers a head reads directly, rather than a pattern spread over many voxels' features.
    pub joints: Option<Tensor<5>>,
}

/// Decoder output for `K` query slots.
#[derive(Debug, Clone)]
pub struct DecoderOutput {
    /// `[B, K, 53, 6]`
    pub rot6d: Tensor<4>,
    /// `[B, K, 10]`
    pub betas: Tensor<3>,
    /// `[B, K, 10]`
    pub expression: Tensor<3>,
    /// `[B, K, 3]` root + offset: the pelvis in the world (T_wld).
    pub transl: Tensor<3>,
    /// `[B, K, W]` the joint samples the linear pose read took, when the decoder has one
    /// ([`DecoderOptions::pose_read`]).
    pub pose_inputs: Option<Tensor<3>>,
    /// `[B, K, 21 * 3]` with [`DecoderOptions::joint_offsets`]: the correction to the body joints'
    /// offsets from the pelvis in each body's own frame (metres).
    pub joint_offsets: Option<Tensor<3>>,
}

/// Body joints among the regressed rotations (slots 1..=21, after the global orientation).
const BODY_SLOTS: usize = 21;

/// Frequencies of the 3D sinusoidal positional encoding (per axis, sin and cos).
const POS_FREQS: usize = 8;

/// Sinusoidal encoding of voxel centres `[P, 3 * 2 * POS_FREQS]`, coordinates normalised to the grid.
fn voxel_encoding(grid: &VoxelGrid, pool: [usize; 3], device: &Device) -> Tensor<2> {
    let shape = [
        grid.shape[0] / pool[0],
        grid.shape[1] / pool[1],
        grid.shape[2] / pool[2],
    ];
    let coarse = VoxelGrid::new(grid.center, grid.size, shape).expect("valid pooled grid");
    let lo = coarse.min_corner();
    let mut v = Vec::with_capacity(coarse.num_voxels() * 6 * POS_FREQS);
    for c in coarse.centers() {
        for a in 0..3 {
            let x = (c[a] - lo[a]) / coarse.size[a]; // 0..1
            for f in 0..POS_FREQS {
                let w = std::f64::consts::PI * (1 << f) as f64 * x;
                v.push(w.sin() as f32);
                v.push(w.cos() as f32);
            }
        }
    }
    Tensor::from_data(
        TensorData::new(v, [coarse.num_voxels(), 6 * POS_FREQS]),
        device,
    )
}

/// The same encoding as [`voxel_encoding`] for arbitrary world points `[B, K, 3]` -> `[B, K, 6 * POS_FREQS]`.
/// Each person query gets its root's encoding: without it a query's cross-attention starts uniform over
/// the whole volume and can find the tokens around its own person only through their content.
pub fn point_encoding(points: Tensor<3>, grid: &VoxelGrid) -> Tensor<3> {
    let [b, k, _] = points.dims();
    let device = points.device();
    let lo = grid.min_corner();
    let to_vec = |v: [f64; 3]| v.iter().map(|&x| x as f32).collect::<Vec<_>>();
    let lo = Tensor::<1>::from_data(TensorData::new(to_vec(lo), [3]), &device);
    let size = Tensor::<1>::from_data(TensorData::new(to_vec(grid.size), [3]), &device);
    let x = (points - lo.reshape([1, 1, 3])) / size.reshape([1, 1, 3]); // 0..1 inside the grid
    let freqs: Vec<f32> = (0..POS_FREQS)
        .map(|f| (std::f64::consts::PI * (1u64 << f) as f64) as f32)
        .collect();
    let freqs = Tensor::<1>::from_data(TensorData::new(freqs, [POS_FREQS]), &device);
    let w = x.reshape([b, k, 3, 1]) * freqs.reshape([1, 1, 1, POS_FREQS]); // [B, K, 3, F]
    // Per axis and frequency: (sin, cos), the order of `voxel_encoding`.
    Tensor::stack::<5>(vec![w.clone().sin(), w.cos()], 4).reshape([b, k, 6 * POS_FREQS])
}

/// `n` Gaussian bumps of each root's height `[B, K, 3]` -> `[B, K, n]`, centred evenly over
/// [`HEIGHT_RANGE`], each as wide as their spacing: a height becomes a few features near 1 that a head
/// reads linearly.
pub fn height_features(roots: Tensor<3>, n: usize) -> Tensor<3> {
    let [b, k, _] = roots.dims();
    let [lo, hi] = HEIGHT_RANGE;
    let step = (hi - lo) / (n.max(2) - 1) as f32;
    let centres: Vec<f32> = (0..n).map(|i| lo + step * i as f32).collect();
    let centres = Tensor::<1>::from_data(TensorData::new(centres, [n]), &roots.device());
    let z = roots.narrow(2, 2, 1); // [B, K, 1]
    let d = (z - centres.reshape([1, 1, n])) / step;
    (d.powi_scalar(2) * -0.5).exp().reshape([b, k, n])
}

impl DecoderConfig {
    pub fn init(&self, device: &Device) -> Decoder {
        let o = &self.options;
        let d = o.dim;
        Decoder {
            query_proj: LinearConfig::new(self.sample_width() + self.joint_width() + PARAM_DIM, d)
                .init(device),
            token_proj: LinearConfig::new(self.volume_channels, d).init(device),
            pos_proj: LinearConfig::new(6 * POS_FREQS, d).init(device),
            blocks: if o.use_htb {
                (0..o.depth)
                    .map(|_| {
                        let tile = self.attention_tile;
                        HumanTransformerBlock::new(d, o.heads, o.ffn_ratio, tile, device)
                    })
                    .collect()
            } else {
                Vec::new()
            },
            baseline: (!o.use_htb).then(|| Head::new(d, d, device)),
            norm: LayerNormConfig::new(d).init(device),
            rot_head: Head::new(
                d,
                if o.pose_trunk {
                    BODY_SLOTS
                } else {
                    NUM_REGRESSED
                } * 6,
                device,
            ),
            global_head: o.pose_trunk.then(|| Head::new(d, 6, device)),
            hands_head: (o.pose_trunk)
                .then(|| Head::new(d, (NUM_REGRESSED - 1 - BODY_SLOTS) * 6, device)),
            pose_trunk: o.pose_trunk,
            betas_head: Head::new(d, NUM_BETAS, device),
            expr_head: Head::new(d, NUM_EXPRESSION, device),
            offset_head: Head::new(d, 3, device),
            heading_proj: self.heading.then(|| LinearConfig::new(2, d).init(device)),
            sample_proj: o
                .sample_skip
                .then(|| LinearConfig::new(self.skip_width(), d).init(device)),
            pose_read: (o.pose_read && o.joint_samples).then(|| {
                LinearConfig::new(self.joint_width(), BODY_SLOTS * 6)
                    .with_initializer(burn::nn::Initializer::Zeros)
                    .init(device)
            }),
            offsets_head: o
                .joint_offsets
                .then(|| Head::new(d, BODY_SLOTS * 3, device)),
            offsets_read: (o.joint_offsets && o.joint_samples).then(|| {
                LinearConfig::new(self.joint_width(), BODY_SLOTS * 3)
                    .with_initializer(burn::nn::Initializer::Zeros)
                    .init(device)
            }),
            height_proj: (o.height_features > 0)
                .then(|| LinearConfig::new(o.height_features, d).init(device)),
            query_norm: o
                .query_norm
                .then(|| LayerNormConfig::new(self.sample_width()).init(device)),
            joint_norm: (self.joint_channels > 0)
                .then(|| LayerNormConfig::new(self.joint_width()).init(device)),
            joint_samples: o.joint_samples,
            lattice: lattice_offsets(o.query_lattice, o.query_span),
            heading_lattice: o.heading_lattice,
            volume_norm: o.volume_norm,
            joint_lattice: lattice_offsets(o.joint_lattice, o.joint_span),
            joint_half: o.joint_span.map(|s| (s / 2.0).max(1e-3) as f32),
            mean: constant(mean_params(device)),
            pool: o.pool.max(1),
        }
    }
}

impl DecoderConfig {
    /// Channels of a query's volume sample: every lattice point's.
    pub fn sample_width(&self) -> usize {
        self.volume_channels * self.options.query_lattice.iter().product::<usize>()
    }

    /// Numbers a query reads from the joint heatmap volume: three per joint, or with
    /// [`DecoderOptions::joint_samples`] one per joint and joint-lattice point.
    pub fn joint_width(&self) -> usize {
        let o = &self.options;
        match o.joint_samples {
            true => self.joint_channels * o.joint_lattice.iter().product::<usize>(),
            false => 3 * self.joint_channels,
        }
    }

    /// What `sample_proj` reads: the feature sample, and the joints' samples where they are read.
    pub fn skip_width(&self) -> usize {
        match self.options.joint_samples {
            true => self.sample_width() + self.joint_width(),
            false => self.sample_width(),
        }
    }
}

/// A linear read of many inputs (`pose_read`, `offsets_read`) scaled by 1 / sqrt(inputs): Adam moves
/// every weight by about the learning rate whatever its gradient, so thousands of unit inputs would
/// otherwise move the outputs by whole units per step.
pub fn scaled_read(layer: &Linear, x: Tensor<3>) -> Tensor<3> {
    layer.forward(x) / (layer.weight.dims()[0] as f64).sqrt()
}

/// Each channel of `volume` `[B, C, X, Y, Z]` less its mean over the voxels, divided by their standard
/// deviation (at least 1e-3 of it, so that a constant channel stays finite).
pub fn standardise_channels(volume: Tensor<5>) -> Tensor<5> {
    let [b, c, nx, ny, nz] = volume.dims();
    let flat = volume.reshape([b, c, nx * ny * nz]);
    let centred = flat.clone() - flat.mean_dim(2);
    let std = centred
        .clone()
        .powi_scalar(2)
        .mean_dim(2)
        .sqrt()
        .clamp_min(1e-3);
    (centred / std).reshape([b, c, nx, ny, nz])
}

/// The volume `[B, C, X, Y, Z]` at the `lattice` offsets round each root `[B, K, 3]`, the lattice turned
/// about the vertical so that its x axis points along each heading `[B, K, 2]` (a horizontal unit
/// vector) and its y axis to the left -> `[B, K, L * C]`.
pub fn sample_turned(
    volume: Tensor<5>,
    roots: Tensor<3>,
    heading: Tensor<3>,
    lattice: &[[f32; 3]],
    grid: &VoxelGrid,
) -> Tensor<3> {
    let [b, k, _] = roots.dims();
    let (l, c) = (lattice.len(), volume.dims()[1]);
    let device = roots.device();
    let axis = |a: usize| {
        let v: Vec<f32> = lattice.iter().map(|o| o[a]).collect();
        Tensor::<1>::from_data(TensorData::new(v, [l]), &device).reshape([1, 1, l])
    };
    let (ox, oy, oz) = (axis(0), axis(1), axis(2));
    let hx = heading.clone().narrow(2, 0, 1); // [B, K, 1]
    let hy = heading.narrow(2, 1, 1);
    // Forward (hx, hy), left (-hy, hx).
    let wx = ox.clone() * hx.clone() - oy.clone() * hy.clone();
    let wy = ox * hy + oy * hx;
    let wz = oz.repeat_dim(0, b).repeat_dim(1, k);
    let offsets = Tensor::stack::<4>(vec![wx, wy, wz], 3); // [B, K, L, 3]
    let points = roots.reshape([b, k, 1, 3]) + offsets;
    trilinear_sample(volume, points.reshape([b, k * l, 3]), grid).reshape([b, k, l * c])
}

/// The offsets from a root of a lattice of `shape` points spanning `span` metres per axis, centred on
/// it, x slowest and z fastest.
pub fn lattice_offsets(shape: [usize; 3], span: [f64; 3]) -> Vec<[f32; 3]> {
    let axis = |a: usize| -> Vec<f32> {
        let n = shape[a].max(1);
        if n == 1 {
            return vec![0.0];
        }
        (0..n)
            .map(|i| (span[a] * (i as f64 / (n - 1) as f64 - 0.5)) as f32)
            .collect()
    };
    let (xs, ys, zs) = (axis(0), axis(1), axis(2));
    let mut out = Vec::with_capacity(xs.len() * ys.len() * zs.len());
    for &x in &xs {
        for &y in &ys {
            out.extend(zs.iter().map(|&z| [x, y, z]));
        }
    }
    out
}

/// `volume [B, C, X, Y, Z]` at `offsets` around each root `[B, K, 3]` -> `[B, K, L, C]`.
fn sample_at(
    volume: Tensor<5>,
    roots: Tensor<3>,
    offsets: &[[f32; 3]],
    grid: &VoxelGrid,
) -> Tensor<4> {
    let [b, k, _] = roots.dims();
    let c = volume.dims()[1];
    let l = offsets.len();
    let flat: Vec<f32> = offsets.iter().flatten().copied().collect();
    let offsets = Tensor::<1>::from_data(TensorData::new(flat, [l * 3]), &roots.device());
    let points = roots.reshape([b, k, 1, 3]) + offsets.reshape([1, 1, l, 3]);
    trilinear_sample(volume, points.reshape([b, k * l, 3]), grid).reshape([b, k, l, c])
}

/// [`sample_at`] with each root's samples side by side -> `[B, K, L * C]`.
fn sample_flat(
    volume: Tensor<5>,
    roots: Tensor<3>,
    offsets: &[[f32; 3]],
    grid: &VoxelGrid,
) -> Tensor<3> {
    let [b, k, _] = roots.dims();
    let s = sample_at(volume, roots, offsets, grid);
    let [_, _, l, c] = s.dims();
    s.reshape([b, k, l * c])
}

impl Decoder {
    /// The volume `[B, C, X, Y, Z]` at every lattice point around each root `[B, K, 3]` -> `[B, K, L * C]`.
    pub fn sample_lattice(
        &self,
        volume: Tensor<5>,
        roots: Tensor<3>,
        grid: &VoxelGrid,
    ) -> Tensor<3> {
        if self.lattice.len() <= 1 {
            return trilinear_sample(volume, roots, grid);
        }
        sample_flat(volume, roots, &self.lattice, grid)
    }

    /// [`Decoder::sample_lattice`] with the lattice turned about the vertical so that its x axis points
    /// along each person's heading `[B, K, 2]` (a horizontal unit vector) and its y axis to their left.
    pub fn sample_lattice_turned(
        &self,
        volume: Tensor<5>,
        roots: Tensor<3>,
        heading: Tensor<3>,
        grid: &VoxelGrid,
    ) -> Tensor<3> {
        sample_turned(volume, roots, heading, &self.lattice, grid)
    }

    /// Each joint's centroid in the box around each root, from a joint heatmap volume `[B, E, X, Y, Z]`:
    /// the lattice's offsets weighted by the squared (non-negative) likelihood there, as fractions of
    /// the box's half sides -> `[B, K, E * 3]` (0 for a joint with no likelihood in the box). Given a
    /// `heading` `[B, K, 2]`, the box turns with it and the centroid is in the person's heading frame.
    pub fn joint_centroids(
        &self,
        joints: Tensor<5>,
        roots: Tensor<3>,
        heading: Option<Tensor<3>>,
        grid: &VoxelGrid,
    ) -> Tensor<3> {
        let [b, k, _] = roots.dims();
        let device = roots.device();
        let e = joints.dims()[1];
        let l = self.joint_lattice.len();
        let s = match heading {
            Some(h) => {
                sample_turned(joints, roots, h, &self.joint_lattice, grid).reshape([b, k, l, e])
            }
            None => sample_at(joints, roots, &self.joint_lattice, grid),
        }; // [B, K, L, E]
        let w = s.clamp_min(0.0).powi_scalar(2).swap_dims(2, 3); // [B, K, E, L]
        let total = w.clone().sum_dim(3).clamp_min(1e-6); // [B, K, E, 1]
        let scaled: Vec<f32> = (self.joint_lattice.iter())
            .flat_map(|o| std::array::from_fn::<f32, 3, _>(|a| o[a] / self.joint_half[a]))
            .collect();
        let offsets = Tensor::<2>::from_data(TensorData::new(scaled, [l, 3]), &device);
        let centroid = w.reshape([b * k, e, l]).matmul(offsets.unsqueeze::<3>()); // [B*K, E, 3]
        (centroid.reshape([b, k, e, 3]) / total).reshape([b, k, e * 3])
    }

    /// What a query reads of the joint heatmap volume `[B, E, X, Y, Z]`, layer-normalised: each joint's
    /// centroid, or with [`DecoderOptions::joint_samples`] its samples on the joint lattice (turned with
    /// `heading` under `heading_lattice`) -> `[B, K, W]`.
    pub fn joint_inputs(
        &self,
        joints: Tensor<5>,
        roots: Tensor<3>,
        heading: Option<Tensor<3>>,
        grid: &VoxelGrid,
    ) -> Tensor<3> {
        let part = match (self.joint_samples, heading) {
            (true, Some(h)) if self.heading_lattice => {
                sample_turned(joints, roots, h, &self.joint_lattice, grid)
            }
            (true, _) => sample_flat(joints, roots, &self.joint_lattice, grid),
            (false, h) => {
                let h = h.filter(|_| self.heading_lattice);
                self.joint_centroids(joints, roots, h, grid) // [B, K, E * 3]
            }
        };
        // Raw, the centroids (a few tenths of the box) never steered the heads: in the learning test's
        // frames, with each person's bends given only as joint offsets, the bend error stayed at 1.00 of
        // predicting none; scaled by 20 it fell to 0.24.
        match &self.joint_norm {
            Some(norm) => norm.forward(part),
            None => part,
        }
    }

    /// The same decoder starting its regression from `mean` `[PARAM_DIM]` (see [`params_vector`]).
    ///
    /// [`params_vector`]: crate::queries::params_vector
    pub fn with_mean(mut self, mean: Tensor<1>) -> Self {
        assert_eq!(mean.dims(), [PARAM_DIM], "a full parameter vector");
        self.mean = constant(mean);
        self
    }

    fn pool_factors(&self, grid: &VoxelGrid) -> [usize; 3] {
        std::array::from_fn(|a| {
            if grid.shape[a].is_multiple_of(self.pool) {
                self.pool
            } else {
                1
            }
        })
    }

    /// The residual 6D rotations `[B, K, 53 * 6]`: one head on `q`, or with `pose_trunk` the body's
    /// head on `q` between the global and the hands-and-face heads on `side`.
    fn rotations(&self, q: Tensor<3>, side: Tensor<3>) -> Tensor<3> {
        match (&self.global_head, &self.hands_head) {
            (Some(g), Some(h)) => Tensor::cat(
                vec![
                    g.forward(side.clone()),
                    self.rot_head.forward(q),
                    h.forward(side),
                ],
                2,
            ),
            _ => self.rot_head.forward(q),
        }
    }

    /// `volume [B, C, X, Y, Z]`, `roots [B, K, 3]` (world), `present [B, K]` -> parameters per slot.
    pub fn forward(
        &self,
        volume: Tensor<5>,
        grid: &VoxelGrid,
        roots: Tensor<3>,
        present: Tensor<2, Bool>,
    ) -> DecoderOutput {
        let extra = QueryInputs::default();
        self.forward_with(volume, extra, grid, roots, present)
    }

    /// [`Decoder::forward`] with what a query may read beside the volume (see [`QueryInputs`]).
    pub fn forward_with(
        &self,
        volume: Tensor<5>,
        inputs: QueryInputs,
        grid: &VoxelGrid,
        roots: Tensor<3>,
        present: Tensor<2, Bool>,
    ) -> DecoderOutput {
        let [b, c, nx, ny, nz] = volume.dims();
        let k = roots.dims()[1];
        let device = volume.device();
        let volume = match self.volume_norm {
            true => standardise_channels(volume),
            false => volume,
        };
        let QueryInputs { heading, joints } = inputs;
        let mut sampled = match &heading {
            Some(h) if self.heading_lattice && self.lattice.len() > 1 => {
                self.sample_lattice_turned(volume.clone(), roots.clone(), h.clone(), grid)
            }
            _ => self.sample_lattice(volume.clone(), roots.clone(), grid),
        }; // [B, K, L * C]
        if let Some(norm) = &self.query_norm {
            sampled = norm.forward(sampled);
        }
        let joint_part = joints.map(|j| self.joint_inputs(j, roots.clone(), heading.clone(), grid));
        let offsets_read = (self.offsets_read.as_ref())
            .zip(joint_part.clone())
            .map(|(p, j)| scaled_read(p, j));
        let pose_inputs = joint_part.clone().filter(|_| self.pose_read.is_some());
        let pose_read = (self.pose_read.as_ref())
            .zip(pose_inputs.clone())
            .map(|(p, j)| scaled_read(p, j));
        let mut skip_in = sampled.clone();
        if let Some(j) = joint_part {
            if self.joint_samples {
                skip_in = Tensor::cat(vec![skip_in, j.clone()], 2);
            }
            sampled = Tensor::cat(vec![sampled, j], 2);
        }
        let skip = self.sample_proj.as_ref().map(|p| p.forward(skip_in));
        let mean = self.mean.val().detach().reshape([1, 1, PARAM_DIM]);
        let q_in = Tensor::cat(
            vec![sampled, mean.clone().repeat_dim(0, b).repeat_dim(1, k)],
            2,
        );
        let mut q = self.query_proj.forward(q_in); // [B, K, D]
        if let (Some(proj), Some(h)) = (&self.heading_proj, heading) {
            q = q + proj.forward(h);
        }
        if self.blocks.is_empty() {
            if let Some(mlp) = &self.baseline {
                q = q.clone() + mlp.forward(q);
            }
        } else {
            let [px, py, pz] = self.pool_factors(grid);
            // Batch and channels folded into one axis: burn-ndarray takes at most 6 dimensions.
            let pooled = volume
                .reshape([b * c, nx / px, px, ny / py, py, nz])
                .mean_dim(2)
                .mean_dim(4)
                .reshape([b * c, nx / px, ny / py, nz / pz, pz])
                .mean_dim(4);
            let p = (nx / px) * (ny / py) * (nz / pz);
            let tokens = self
                .token_proj
                .forward(pooled.reshape([b, c, p]).swap_dims(1, 2)); // [B, P, D]
            let pos = self
                .pos_proj
                .forward(voxel_encoding(grid, [px, py, pz], &device)); // [P, D]
            let tokens = tokens + pos.unsqueeze_dim::<3>(0);
            // The queries carry their root's position in the tokens' own encoding.
            q = q + self.pos_proj.forward(point_encoding(roots.clone(), grid));
            let padding = present.bool_not();
            for blk in &self.blocks {
                q = blk.forward(q, padding.clone(), tokens.clone());
            }
        }
        let mut q = self.norm.forward(q);
        if let Some(skip) = skip {
            q = q + skip;
        }
        if let Some(proj) = &self.height_proj {
            q = q + proj.forward(height_features(roots.clone(), proj.weight.dims()[0]));
        }
        // What every head but the body pose's reads (see `DecoderOptions::pose_trunk`).
        let side = if self.pose_trunk {
            q.clone().detach()
        } else {
            q.clone()
        };
        let joint_offsets = self.offsets_head.as_ref().map(|h| match offsets_read {
            Some(read) => h.forward(q.clone()) + read,
            None => h.forward(q.clone()),
        });
        let mean = mean.reshape([1, 1, PARAM_DIM]);
        let mut rot =
            mean.clone().narrow(2, 0, NUM_REGRESSED * 6) + self.rotations(q, side.clone());
        if let Some(read) = pose_read {
            // The body's rotations follow the global orientation's in the 53.
            let rest = (NUM_REGRESSED - 1 - BODY_SLOTS) * 6;
            let padded = Tensor::cat(
                vec![
                    Tensor::zeros([b, k, 6], &device),
                    read,
                    Tensor::zeros([b, k, rest], &device),
                ],
                2,
            );
            rot = rot + padded;
        }
        let betas = mean.clone().narrow(2, NUM_REGRESSED * 6, NUM_BETAS)
            + self.betas_head.forward(side.clone());
        let expr = mean.narrow(2, NUM_REGRESSED * 6 + NUM_BETAS, NUM_EXPRESSION)
            + self.expr_head.forward(side.clone());
        let offset = self.offset_head.forward(side);
        DecoderOutput {
            rot6d: rot.reshape([b, k, NUM_REGRESSED, 6]),
            betas,
            expression: expr,
            transl: roots + offset,
            pose_inputs,
            joint_offsets,
        }
    }
}
