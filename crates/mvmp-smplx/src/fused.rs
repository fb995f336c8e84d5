//! The SMPL-X forward as one fused pass over the mesh, for CPU inference (no gradient).
//!
//! The tensor layer (`layer.rs`) runs every step as a separate op over `[N, V, 3]` planes and a dense
//! `[55, V]` skinning GEMM. Here the mesh is cut into blocks of [`BLOCK`] vertices and each block is
//! finished while it is in cache:
//! 1. one GEMM gives the unposed vertices of every body: the block's packed rows
//!    `[template | shape and expression directions | pose correctives]` (`K = 1 + 20 + 486` columns)
//!    times the bodies' features `[1, betas, expression, (R_j - I)_{j=1..54}]`;
//! 2. skinning over only the joints that weigh on the block (a handful, not 55);
//! 3. the translation, written straight into `[N, V, 3]`.
//!
//! The model's arrays are read once per forward whatever the batch (the pose correctives alone are 61 MB
//! in float32), on every core. The kinematic chain and the joints are small and run per body.
use std::sync::Arc;

use mvmp_kernels::cpu::{Isa, SendPtr};
use mvmp_kernels::panel::gemm_panel;
use rayon::prelude::*;

use crate::BodyModel;
use crate::names::{NUM_BETAS, NUM_EXPRESSION, NUM_JOINTS, NUM_POSE_JOINTS};
use crate::params::Translation;

mod backward;

/// Vertices per block: two AVX-512 registers of float32 per coordinate.
pub(crate) const BLOCK: usize = mvmp_kernels::panel::PANEL;

/// The model's arrays laid out for the fused pass.
pub(crate) struct FusedLbs {
    num_vertices: usize,
    num_blocks: usize,
    /// Columns of the per-vertex linear map: 1 + components + 486.
    k: usize,
    num_components: usize,
    /// `[block][axis][K][BLOCK]`: for each block and coordinate, the K columns of its rows, with the block's
    /// vertices innermost (vertices past the end are zero).
    packed: Vec<f32>,
    /// Per block: the range of its active joints in `active` and `active_weights`.
    block_active: Vec<(u32, u32)>,
    /// Joint index of each active entry.
    active: Vec<u8>,
    /// `[entry][BLOCK]` skinning weight of the entry's joint for each vertex of its block.
    active_weights: Vec<f32>,
    /// `[55 * 3]` joints of the template and `[components][55 * 3]` their shape displacements.
    j_template: Vec<f32>,
    j_shapedirs: Vec<f32>,
    parents: Vec<usize>,
    /// Joints in an order where each parent comes before its children.
    chain_order: Vec<usize>,
    /// Extra joints as weighted sums of three vertices.
    extra: Vec<[(usize, f32); 3]>,
    /// `packed` as one row-major `[K, 3 * blocks * BLOCK]` matrix (columns: axis, then vertex), made by
    /// the first backward: the backward's product runs on it as one GEMM.
    rows: std::sync::OnceLock<Vec<f32>>,
}

impl std::fmt::Debug for FusedLbs {
    // The arrays are tens of megabytes: show their sizes only.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FusedLbs")
            .field("num_vertices", &self.num_vertices)
            .field("num_blocks", &self.num_blocks)
            .field("k", &self.k)
            .field("active_joints", &self.active.len())
            .finish_non_exhaustive()
    }
}

/// Where one body's kinematic chain writes: its skinning transforms `[55][12]`, its shift `[3]` and its
/// 55 posed joints `[55][3]`.
struct Posed<'a> {
    transforms: &'a mut [f32],
    shift: &'a mut [f32],
    joints: &'a mut [f32],
}

/// Float32 arrays of a fused forward: `vertices [N, V, 3]`, `joints [N, J, 3]` and, when asked for (the
/// backward's input), the unposed vertices `[blocks][3][N][BLOCK]`.
pub(crate) struct FusedOutput {
    pub vertices: Vec<f32>,
    pub joints: Vec<f32>,
    pub unposed: Vec<f32>,
}

impl FusedLbs {
    /// `j_template`, `j_shapedirs` (`[components][55*3]`) and `extra` come from the layer, which derives
    /// them once for both paths.
    pub(crate) fn new(
        model: &BodyModel,
        j_template: Vec<f32>,
        j_shapedirs: Vec<f32>,
        extra: Vec<[(usize, f32); 3]>,
    ) -> Arc<Self> {
        let v = model.num_vertices();
        let l = model.num_shape_components;
        let e0 = model.expression_offset();
        let comps: Vec<usize> = (0..NUM_BETAS).chain(e0..e0 + NUM_EXPRESSION).collect();
        let nc = comps.len();
        let p = NUM_POSE_JOINTS * 9;
        let k = 1 + nc + p;
        let num_blocks = v.div_ceil(BLOCK);
        let mut packed = vec![0f32; num_blocks * 3 * k * BLOCK];
        for vi in 0..v {
            let (blk, i) = (vi / BLOCK, vi % BLOCK);
            for a in 0..3 {
                let panel = &mut packed[(blk * 3 + a) * k * BLOCK..(blk * 3 + a + 1) * k * BLOCK];
                let row = vi * 3 + a;
                panel[i] = model.v_template[row];
                for (ci, &c) in comps.iter().enumerate() {
                    panel[(1 + ci) * BLOCK + i] = model.shapedirs[row * l + c];
                }
                for q in 0..p {
                    panel[(1 + nc + q) * BLOCK + i] = model.posedirs[row * p + q];
                }
            }
        }
        let mut block_active = Vec::with_capacity(num_blocks);
        let mut active = Vec::new();
        let mut active_weights = Vec::new();
        for blk in 0..num_blocks {
            let start = active.len() as u32;
            let verts = blk * BLOCK..((blk + 1) * BLOCK).min(v);
            for j in 0..NUM_JOINTS {
                if verts
                    .clone()
                    .any(|vi| model.weights[vi * NUM_JOINTS + j] != 0.0)
                {
                    active.push(j as u8);
                    let mut w = [0f32; BLOCK];
                    for vi in verts.clone() {
                        w[vi - blk * BLOCK] = model.weights[vi * NUM_JOINTS + j];
                    }
                    active_weights.extend_from_slice(&w);
                }
            }
            block_active.push((start, active.len() as u32 - start));
        }
        let parents: Vec<usize> = (0..NUM_JOINTS)
            .map(|j| model.parents[j].max(0) as usize)
            .collect();
        let mut depth = vec![0usize; NUM_JOINTS];
        // Depths by relaxation, so any parent order in a file works (SMPL-X's parents precede children).
        for _ in 0..NUM_JOINTS {
            for j in 1..NUM_JOINTS {
                depth[j] = depth[parents[j]] + 1;
            }
        }
        let mut chain_order: Vec<usize> = (0..NUM_JOINTS).collect();
        chain_order.sort_by_key(|&j| depth[j]);
        Arc::new(FusedLbs {
            num_vertices: v,
            num_blocks,
            k,
            num_components: nc,
            packed,
            block_active,
            active,
            active_weights,
            j_template,
            j_shapedirs,
            parents,
            chain_order,
            extra,
            rows: std::sync::OnceLock::new(),
        })
    }

    pub(crate) fn num_components(&self) -> usize {
        self.num_components
    }

    pub(crate) fn num_vertices(&self) -> usize {
        self.num_vertices
    }

    /// Output joints: the 55 of the skeleton and the vertex joints.
    pub(crate) fn num_joints(&self) -> usize {
        NUM_JOINTS + self.extra.len()
    }

    /// [`FusedLbs::rows`]'s matrix, made on first use.
    fn rows(&self) -> &[f32] {
        self.rows.get_or_init(|| {
            let (k, vp) = (self.k, self.num_blocks * BLOCK);
            let mut rows = vec![0f32; k * 3 * vp];
            for blk in 0..self.num_blocks {
                for a in 0..3 {
                    let panel = &self.packed[(blk * 3 + a) * k * BLOCK..][..k * BLOCK];
                    for (q, src) in panel.chunks_exact(BLOCK).enumerate() {
                        rows[q * 3 * vp + a * vp + blk * BLOCK..][..BLOCK].copy_from_slice(src);
                    }
                }
            }
            rows
        })
    }

    /// The forward for `n` bodies: `rot [N, 55, 9]` row-major matrices, `coeffs [N, 20]` (betas then
    /// expression), `transl [N, 3]`.
    pub(crate) fn forward(
        &self,
        n: usize,
        rot: &[f32],
        coeffs: &[f32],
        transl: &[f32],
        mode: Translation,
        keep_unposed: bool,
    ) -> FusedOutput {
        let nc = self.num_components;
        debug_assert_eq!(rot.len(), n * NUM_JOINTS * 9);
        debug_assert_eq!(coeffs.len(), n * nc);
        debug_assert_eq!(transl.len(), n * 3);
        let feat = self.features(n, rot, coeffs);
        let (transforms, shift, mut joints) = self.pose_bodies(n, rot, coeffs, transl, mode);
        let mut unposed = match keep_unposed {
            true => vec![0f32; self.num_blocks * 3 * n * BLOCK],
            false => Vec::new(),
        };
        let vertices = self.skin(n, &feat, &transforms, &shift, &mut unposed);
        self.vertex_joints(n, &vertices, &mut joints);
        FusedOutput {
            vertices,
            joints,
            unposed,
        }
    }

    /// Every body's kinematic chain: the skinning transforms `[N][55][12]`, the shifts `[N][3]` and the
    /// joints `[N, 55 + extra, 3]` with the 55 posed skeleton joints filled in.
    fn pose_bodies(
        &self,
        n: usize,
        rot: &[f32],
        coeffs: &[f32],
        transl: &[f32],
        mode: Translation,
    ) -> (Vec<f32>, Vec<f32>, Vec<f32>) {
        let (nc, nj) = (self.num_components, NUM_JOINTS + self.extra.len());
        let mut transforms = vec![0f32; n * NUM_JOINTS * 12];
        let mut shift = vec![0f32; n * 3];
        let mut joints = vec![0f32; n * nj * 3];
        for b in 0..n {
            self.pose_body(
                &coeffs[b * nc..(b + 1) * nc],
                &rot[b * NUM_JOINTS * 9..(b + 1) * NUM_JOINTS * 9],
                [transl[b * 3], transl[b * 3 + 1], transl[b * 3 + 2]],
                mode,
                Posed {
                    transforms: &mut transforms[b * NUM_JOINTS * 12..(b + 1) * NUM_JOINTS * 12],
                    shift: &mut shift[b * 3..b * 3 + 3],
                    joints: &mut joints[b * nj * 3..(b * nj + NUM_JOINTS) * 3],
                },
            );
        }
        (transforms, shift, joints)
    }

    /// `feat [K, N]`: column b holds body b's GEMM features, 1, its coefficients, and its 54 non-root
    /// rotations minus the identity (the pose correctives' input).
    fn features(&self, n: usize, rot: &[f32], coeffs: &[f32]) -> Vec<f32> {
        let nc = self.num_components;
        let mut feat = vec![0f32; self.k * n];
        for b in 0..n {
            let c = &coeffs[b * nc..(b + 1) * nc];
            let r = &rot[b * NUM_JOINTS * 9..(b + 1) * NUM_JOINTS * 9];
            feat[b] = 1.0;
            for (ci, &cv) in c.iter().enumerate() {
                feat[(1 + ci) * n + b] = cv;
            }
            for j in 1..NUM_JOINTS {
                for e in 0..9 {
                    let eye = if e % 4 == 0 { 1.0 } else { 0.0 };
                    feat[(1 + nc + (j - 1) * 9 + e) * n + b] = r[j * 9 + e] - eye;
                }
            }
        }
        feat
    }

    /// One body's rest joints from its shape coefficients `c`, and every joint's world rotation and
    /// position from its rotations `r` (`[55][9]`).
    fn chain(&self, c: &[f32], r: &[f32]) -> Chain {
        let mut rest = self.j_template.clone();
        for (ci, &cv) in c.iter().enumerate() {
            let dir = &self.j_shapedirs[ci * NUM_JOINTS * 3..(ci + 1) * NUM_JOINTS * 3];
            for (x, d) in rest.iter_mut().zip(dir) {
                *x += cv * d;
            }
        }
        let mut g_rot = [[0f32; 9]; NUM_JOINTS];
        let mut g_t = [[0f32; 3]; NUM_JOINTS];
        for &j in &self.chain_order {
            let rj = rotation(r, j);
            let jr = point(&rest, j);
            if j == 0 {
                g_rot[0] = rj;
                g_t[0] = jr;
                continue;
            }
            let p = self.parents[j];
            let gp = g_rot[p];
            g_t[j] = add3(mat_vec(&gp, &sub3(jr, point(&rest, p))), g_t[p]);
            g_rot[j] = mat_mul(&gp, &rj);
        }
        Chain { rest, g_rot, g_t }
    }

    /// One body's kinematic chain: the skinning transforms, the shift and the posed joints.
    fn pose_body(&self, c: &[f32], r: &[f32], tr: [f32; 3], mode: Translation, out: Posed) {
        let Chain { rest, g_rot, g_t } = self.chain(c, r);
        let s = match mode {
            Translation::Standard => tr,
            Translation::Pelvis => sub3(tr, point(&rest, 0)),
        };
        out.shift.copy_from_slice(&s);
        for j in 0..NUM_JOINTS {
            let t = sub3(g_t[j], mat_vec(&g_rot[j], &point(&rest, j)));
            let a = &mut out.transforms[j * 12..(j + 1) * 12];
            for row in 0..3 {
                a[row * 4..row * 4 + 3].copy_from_slice(&g_rot[j][row * 3..row * 3 + 3]);
                a[row * 4 + 3] = t[row];
            }
            for ax in 0..3 {
                out.joints[j * 3 + ax] = g_t[j][ax] + s[ax];
            }
        }
    }

    /// Every body's vertices `[N, V, 3]`: per block, the GEMM of the packed rows and the features gives
    /// the unposed vertices (copied to `keep [blocks][3][N][BLOCK]` unless it is empty), then the block
    /// is skinned and shifted.
    fn skin(
        &self,
        n: usize,
        feat: &[f32],
        transforms: &[f32],
        shift: &[f32],
        keep: &mut [f32],
    ) -> Vec<f32> {
        let k = self.k;
        let mut vertices = vec![0f32; n * self.num_vertices * 3];
        let out = SendPtr(vertices.as_mut_ptr());
        let kept = (!keep.is_empty()).then_some(SendPtr(keep.as_mut_ptr()));
        let isa = Isa::detect();
        (0..self.num_blocks).into_par_iter().for_each_init(
            || vec![0f32; 3 * n * BLOCK],
            |unposed, blk| {
                for a in 0..3 {
                    let panel =
                        &self.packed[(blk * 3 + a) * k * BLOCK..(blk * 3 + a + 1) * k * BLOCK];
                    let dst = &mut unposed[a * n * BLOCK..(a + 1) * n * BLOCK];
                    gemm_panel(isa, panel, feat, k, n, dst);
                }
                if let Some(kept) = kept {
                    let len = 3 * n * BLOCK;
                    // SAFETY: block `blk` writes only its own `len` values of `keep`, which outlives the
                    // parallel loop.
                    unsafe { std::slice::from_raw_parts_mut(kept.get().add(blk * len), len) }
                        .copy_from_slice(unposed);
                }
                // SAFETY: block `blk` writes only vertices blk*BLOCK.. of each body, which no other
                // block touches, and `vertices` outlives the parallel loop.
                unsafe { self.skin_block(isa, blk, n, unposed, transforms, shift, out) };
            },
        );
        vertices
    }

    /// The vertex joints from the finished mesh (the shift is already in the vertices), added after
    /// each body's 55 skeleton joints in `joints [N, 55 + extra, 3]`.
    fn vertex_joints(&self, n: usize, vertices: &[f32], joints: &mut [f32]) {
        let (v, nj) = (self.num_vertices, NUM_JOINTS + self.extra.len());
        for b in 0..n {
            for (xi, taps) in self.extra.iter().enumerate() {
                let o = (b * nj + NUM_JOINTS + xi) * 3;
                for &(vi, w) in taps {
                    for ax in 0..3 {
                        joints[o + ax] += w * vertices[(b * v + vi) * 3 + ax];
                    }
                }
            }
        }
    }

    /// Skin the unposed block `[3][N][BLOCK]` of every body and write it, shifted, to `out [N, V, 3]`.
    ///
    /// # Safety
    /// `out` points to `n * num_vertices * 3` floats; only this block's vertices are written.
    #[allow(clippy::too_many_arguments)]
    unsafe fn skin_block(
        &self,
        isa: Isa,
        blk: usize,
        n: usize,
        unposed: &[f32],
        transforms: &[f32],
        shift: &[f32],
        out: SendPtr,
    ) {
        // The same loop compiled for each instruction set: the default x86-64 target has only SSE2
        // (4 lanes), and this loop runs on 16-lane registers where the machine has them.
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx512f")]
            unsafe fn avx512(l: &FusedLbs, a: (usize, usize, &[f32], &[f32], &[f32], SendPtr)) {
                // SAFETY: forwarded from the caller's contract.
                unsafe { l.skin_block_body(a.0, a.1, a.2, a.3, a.4, a.5) }
            }
            #[target_feature(enable = "avx2,fma")]
            unsafe fn avx2(l: &FusedLbs, a: (usize, usize, &[f32], &[f32], &[f32], SendPtr)) {
                // SAFETY: forwarded from the caller's contract.
                unsafe { l.skin_block_body(a.0, a.1, a.2, a.3, a.4, a.5) }
            }
            let args = (blk, n, unposed, transforms, shift, out);
            match isa {
                // SAFETY: the features were detected; the rest is the caller's contract.
                Isa::Avx512 => return unsafe { avx512(self, args) },
                Isa::Avx2 => return unsafe { avx2(self, args) },
                Isa::Portable => {}
            }
        }
        let _ = isa;
        // SAFETY: the caller's contract.
        unsafe { self.skin_block_body(blk, n, unposed, transforms, shift, out) }
    }

    /// # Safety
    /// As [`FusedLbs::skin_block`].
    #[inline(always)]
    unsafe fn skin_block_body(
        &self,
        blk: usize,
        n: usize,
        unposed: &[f32],
        transforms: &[f32],
        shift: &[f32],
        out: SendPtr,
    ) {
        let (start, count) = self.block_active[blk];
        let range = start as usize..(start + count) as usize;
        let joints = &self.active[range.clone()];
        let weights = &self.active_weights[range.start * BLOCK..range.end * BLOCK];
        let v0 = blk * BLOCK;
        let len = BLOCK.min(self.num_vertices - v0);
        for b in 0..n {
            let px: &[f32; BLOCK] = unposed[b * BLOCK..][..BLOCK].try_into().expect("BLOCK");
            let py: &[f32; BLOCK] = unposed[(n + b) * BLOCK..][..BLOCK]
                .try_into()
                .expect("BLOCK");
            let pz: &[f32; BLOCK] = unposed[(2 * n + b) * BLOCK..][..BLOCK]
                .try_into()
                .expect("BLOCK");
            let mut res = [[0f32; BLOCK]; 3];
            for (ax, r) in res.iter_mut().enumerate() {
                // One output axis at a time: its four blended coefficient rows, as plain indexed loops
                // that the compiler turns into full-width vector code.
                let (mut t0, mut t1, mut t2, mut t3) =
                    ([0f32; BLOCK], [0f32; BLOCK], [0f32; BLOCK], [0f32; BLOCK]);
                for (e, &j) in joints.iter().enumerate() {
                    let w: &[f32; BLOCK] = weights[e * BLOCK..][..BLOCK].try_into().expect("BLOCK");
                    let a: &[f32; 4] = transforms[(b * NUM_JOINTS + j as usize) * 12 + ax * 4..]
                        [..4]
                        .try_into()
                        .expect("4");
                    for i in 0..BLOCK {
                        t0[i] += w[i] * a[0];
                        t1[i] += w[i] * a[1];
                        t2[i] += w[i] * a[2];
                        t3[i] += w[i] * a[3];
                    }
                }
                let s = shift[b * 3 + ax];
                for i in 0..BLOCK {
                    r[i] = t0[i] * px[i] + t1[i] * py[i] + t2[i] * pz[i] + t3[i] + s;
                }
            }
            // SAFETY: see the function's contract; rows v0..v0+len of body b are this block's.
            let dst = unsafe {
                std::slice::from_raw_parts_mut(out.0.add((b * self.num_vertices + v0) * 3), len * 3)
            };
            for i in 0..len {
                dst[i * 3] = res[0][i];
                dst[i * 3 + 1] = res[1][i];
                dst[i * 3 + 2] = res[2][i];
            }
        }
    }
}

/// One body's rest joints `[55 * 3]` and its joints' world rotations (row-major) and positions.
struct Chain {
    rest: Vec<f32>,
    g_rot: [[f32; 9]; NUM_JOINTS],
    g_t: [[f32; 3]; NUM_JOINTS],
}

/// Joint `j`'s rotation from `[55][9]`.
fn rotation(r: &[f32], j: usize) -> [f32; 9] {
    r[j * 9..j * 9 + 9].try_into().expect("9 entries")
}

/// Joint `j`'s point from `[55][3]`.
fn point(p: &[f32], j: usize) -> [f32; 3] {
    [p[j * 3], p[j * 3 + 1], p[j * 3 + 2]]
}

fn mat_mul(a: &[f32; 9], b: &[f32; 9]) -> [f32; 9] {
    let mut c = [0f32; 9];
    for i in 0..3 {
        for j in 0..3 {
            c[i * 3 + j] = a[i * 3] * b[j] + a[i * 3 + 1] * b[3 + j] + a[i * 3 + 2] * b[6 + j];
        }
    }
    c
}

fn mat_vec(a: &[f32; 9], x: &[f32; 3]) -> [f32; 3] {
    [
        a[0] * x[0] + a[1] * x[1] + a[2] * x[2],
        a[3] * x[0] + a[4] * x[1] + a[5] * x[2],
        a[6] * x[0] + a[7] * x[1] + a[8] * x[2],
    ]
}

fn add3(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}

fn sub3(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
