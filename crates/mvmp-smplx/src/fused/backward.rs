//! The backward of the fused SMPL-X pass: from the gradients of the vertices and joints to those of the
//! rotations, the shape and expression coefficients and the translation.
//!
//! It takes the unposed vertices the forward kept, recomputes the kinematic chain (small), and runs the
//! forward's steps in reverse:
//! 1. the vertex joints hand their gradient to their three vertices, and the shift gets the sum of every
//!    output point's;
//! 2. per block of vertices, skinning's backward gives each unposed vertex's gradient and each active
//!    joint's transform gradient (summed over blocks afterwards, in block order);
//! 3. the packed rows, as one matrix, times the unposed vertices' gradients gives the features'
//!    gradient (one GEMM);
//! 4. the kinematic chain in reverse, per body.
//!
//! Every sum runs in one order whatever the number of threads, so a run repeats on one machine.
use mvmp_kernels::cpu::SendPtr;
use rayon::prelude::*;

use super::{BLOCK, Chain, FusedLbs, point, rotation, sub3};
use crate::names::NUM_JOINTS;
use crate::params::Translation;

/// Gradients of a fused forward's inputs: `rot [N, 55, 9]`, `coeffs [N, 20]`, `transl [N, 3]`.
pub(crate) struct FusedGrads {
    pub rot: Vec<f32>,
    pub coeffs: Vec<f32>,
    pub transl: Vec<f32>,
}

impl FusedLbs {
    /// The backward of [`FusedLbs::forward`] with the same inputs and the unposed vertices it kept,
    /// given `grad_v [N, V, 3]` and `grad_j [N, J, 3]`.
    #[allow(clippy::too_many_arguments)]
    pub(crate) fn backward(
        &self,
        n: usize,
        rot: &[f32],
        coeffs: &[f32],
        transl: &[f32],
        mode: Translation,
        unposed: &[f32],
        grad_v: &[f32],
        grad_j: &[f32],
    ) -> FusedGrads {
        let nc = self.num_components;
        let nj = NUM_JOINTS + self.extra.len();
        assert_eq!(unposed.len(), self.num_blocks * 3 * n * BLOCK);
        let (transforms, _, _) = self.pose_bodies(n, rot, coeffs, transl, mode);
        let gv = self.vertex_gradient(n, grad_v, grad_j);
        let d_shift = self.shift_gradient(n, &gv, grad_j);
        let (d_unposed, d_transforms) = self.skin_backward(n, unposed, &transforms, &gv);
        let d_feat = self.feature_gradient(n, &d_unposed);
        let mut out = FusedGrads {
            rot: vec![0f32; n * NUM_JOINTS * 9],
            coeffs: vec![0f32; n * nc],
            transl: d_shift.clone(),
        };
        for b in 0..n {
            let c = &coeffs[b * nc..(b + 1) * nc];
            let r = &rot[b * NUM_JOINTS * 9..(b + 1) * NUM_JOINTS * 9];
            let ds = point(&d_shift, b);
            let d_a = &d_transforms[b * NUM_JOINTS * 12..(b + 1) * NUM_JOINTS * 12];
            let d_joints = &grad_j[b * nj * 3..(b * nj + NUM_JOINTS) * 3];
            let (d_rot, d_rest) = self.chain_backward(c, r, d_a, d_joints, ds, mode);
            out.rot[b * NUM_JOINTS * 9..(b + 1) * NUM_JOINTS * 9].copy_from_slice(&d_rot);
            self.coefficient_gradient(
                b,
                n,
                &d_feat,
                &d_rest,
                &mut out.coeffs[b * nc..(b + 1) * nc],
            );
            for j in 1..NUM_JOINTS {
                for e in 0..9 {
                    out.rot[(b * NUM_JOINTS + j) * 9 + e] +=
                        d_feat[(1 + nc + (j - 1) * 9 + e) * n + b];
                }
            }
        }
        out
    }

    /// The vertices' gradient `[N, V, 3]` with each vertex joint's handed to its three vertices.
    fn vertex_gradient(&self, n: usize, grad_v: &[f32], grad_j: &[f32]) -> Vec<f32> {
        let (v, nj) = (self.num_vertices, NUM_JOINTS + self.extra.len());
        let mut gv = grad_v.to_vec();
        for b in 0..n {
            for (xi, taps) in self.extra.iter().enumerate() {
                let g = point(grad_j, b * nj + NUM_JOINTS + xi);
                for &(vi, w) in taps {
                    for ax in 0..3 {
                        gv[(b * v + vi) * 3 + ax] += w * g[ax];
                    }
                }
            }
        }
        gv
    }

    /// Each body's shift gradient `[N, 3]`: every vertex and skeleton joint carries the shift.
    fn shift_gradient(&self, n: usize, gv: &[f32], grad_j: &[f32]) -> Vec<f32> {
        let (v, nj) = (self.num_vertices, NUM_JOINTS + self.extra.len());
        let mut ds = vec![0f32; n * 3];
        for b in 0..n {
            let vertices = gv[b * v * 3..(b + 1) * v * 3].chunks_exact(3);
            let skeleton = grad_j[b * nj * 3..(b * nj + NUM_JOINTS) * 3].chunks_exact(3);
            for g in vertices.chain(skeleton) {
                for ax in 0..3 {
                    ds[b * 3 + ax] += g[ax];
                }
            }
        }
        ds
    }

    /// Skinning's backward, block by block: the unposed vertices' gradient `[3][blocks * BLOCK][N]`
    /// (zero past the mesh) and every body's transform gradient `[N][55][12]`.
    fn skin_backward(
        &self,
        n: usize,
        unposed: &[f32],
        transforms: &[f32],
        gv: &[f32],
    ) -> (Vec<f32>, Vec<f32>) {
        let vp = self.num_blocks * BLOCK;
        let mut d_unposed = vec![0f32; 3 * n * vp];
        // One transform gradient per active entry and body, written by the entry's block.
        let mut partial = vec![0f32; self.active.len() * n * 12];
        let (du, dp) = (
            SendPtr(d_unposed.as_mut_ptr()),
            SendPtr(partial.as_mut_ptr()),
        );
        let per_block = 3 * n * BLOCK;
        (0..self.num_blocks).into_par_iter().for_each(|blk| {
            let unposed = &unposed[blk * per_block..(blk + 1) * per_block];
            // SAFETY: block `blk` writes only its own vertices of `d_unposed` and its own active
            // entries of `partial`, which no other block touches; both outlive the loop.
            unsafe { self.skin_block_backward(blk, n, unposed, transforms, gv, du, dp) };
        });
        let mut d_transforms = vec![0f32; n * NUM_JOINTS * 12];
        for (e, &j) in self.active.iter().enumerate() {
            for b in 0..n {
                let src = &partial[(e * n + b) * 12..(e * n + b + 1) * 12];
                let dst = &mut d_transforms[(b * NUM_JOINTS + j as usize) * 12..][..12];
                for (d, s) in dst.iter_mut().zip(src) {
                    *d += s;
                }
            }
        }
        (d_unposed, d_transforms)
    }

    /// # Safety
    /// `du` points to `3 * blocks * BLOCK * n` floats and `dp` to `active * n * 12`; only block `blk`'s
    /// vertices and active entries are written.
    #[allow(clippy::too_many_arguments)]
    unsafe fn skin_block_backward(
        &self,
        blk: usize,
        n: usize,
        unposed: &[f32],
        transforms: &[f32],
        gv: &[f32],
        du: SendPtr,
        dp: SendPtr,
    ) {
        let (start, count) = self.block_active[blk];
        let entries = start as usize..(start + count) as usize;
        let joints = &self.active[entries.clone()];
        let weights = &self.active_weights[entries.start * BLOCK..entries.end * BLOCK];
        let v0 = blk * BLOCK;
        let len = BLOCK.min(self.num_vertices - v0);
        let vp = self.num_blocks * BLOCK;
        for b in 0..n {
            let p: [&[f32]; 3] = std::array::from_fn(|a| &unposed[(a * n + b) * BLOCK..][..BLOCK]);
            let mut g = [[0f32; BLOCK]; 3];
            for i in 0..len {
                for (ax, row) in g.iter_mut().enumerate() {
                    row[i] = gv[(b * self.num_vertices + v0 + i) * 3 + ax];
                }
            }
            // d unposed[c] = sum over output axes of the blended transform's entry (ax, c) times the
            // output gradient.
            let mut d = [[0f32; BLOCK]; 3];
            for (ax, g_ax) in g.iter().enumerate() {
                for (e, &j) in joints.iter().enumerate() {
                    let w = &weights[e * BLOCK..][..BLOCK];
                    let a = &transforms[(b * NUM_JOINTS + j as usize) * 12 + ax * 4..][..3];
                    for (c, d_c) in d.iter_mut().enumerate() {
                        for i in 0..BLOCK {
                            d_c[i] += w[i] * a[c] * g_ax[i];
                        }
                    }
                }
            }
            for (c, d_c) in d.iter().enumerate() {
                for (i, &x) in d_c.iter().enumerate() {
                    // SAFETY: the function's contract; vertex v0 + i of body b is block `blk`'s.
                    unsafe { *du.get().add((c * vp + v0 + i) * n + b) = x };
                }
            }
            // d transform (ax, c) of an active joint = sum over the block of its weight times the
            // output gradient times the homogeneous unposed vertex.
            for (e, _) in joints.iter().enumerate() {
                let w = &weights[e * BLOCK..][..BLOCK];
                // SAFETY: the function's contract; entry `start + e` belongs to block `blk`.
                let dst = unsafe {
                    std::slice::from_raw_parts_mut(
                        dp.get().add(((entries.start + e) * n + b) * 12),
                        12,
                    )
                };
                for (ax, g_ax) in g.iter().enumerate() {
                    let wg: [f32; BLOCK] = std::array::from_fn(|i| w[i] * g_ax[i]);
                    for (c, p_c) in p.iter().enumerate() {
                        dst[ax * 4 + c] = wg.iter().zip(p_c.iter()).map(|(x, y)| x * y).sum();
                    }
                    dst[ax * 4 + 3] = wg.iter().sum();
                }
            }
        }
    }

    /// The features' gradient `[K, N]`: the packed rows as one `[K, 3 * blocks * BLOCK]` matrix
    /// ([`FusedLbs::rows`]) times the unposed vertices' gradient `[3 * blocks * BLOCK, N]`.
    fn feature_gradient(&self, n: usize, d_unposed: &[f32]) -> Vec<f32> {
        let (k, cols) = (self.k, 3 * self.num_blocks * BLOCK);
        let rows = self.rows();
        assert!(rows.len() == k * cols && d_unposed.len() == cols * n);
        let mut d_feat = vec![0f32; k * n];
        let parallelism = if k * n * cols >= 192 * 192 * 192 {
            gemm::Parallelism::Rayon(0)
        } else {
            gemm::Parallelism::None
        };
        // SAFETY: all three buffers are contiguous row-major matrices of the sizes asserted above, and
        // the output is not read (`read_dst` false).
        unsafe {
            gemm::gemm(
                k,
                n,
                cols,
                d_feat.as_mut_ptr(),
                1,
                n as isize,
                false,
                rows.as_ptr(),
                1,
                cols as isize,
                d_unposed.as_ptr(),
                1,
                n as isize,
                0.0,
                1.0,
                false,
                false,
                false,
                parallelism,
            );
        }
        d_feat
    }

    /// One body's kinematic chain in reverse: from its transform gradients `d_a [55][12]`, its skeleton
    /// joints' gradients `[55][3]` and its shift's, the gradients of its rotations `[55][9]` and of its
    /// rest joints `[55 * 3]`.
    fn chain_backward(
        &self,
        c: &[f32],
        r: &[f32],
        d_a: &[f32],
        d_joints: &[f32],
        ds: [f32; 3],
        mode: Translation,
    ) -> (Vec<f32>, Vec<f32>) {
        let Chain {
            rest,
            g_rot,
            g_t: _,
        } = self.chain(c, r);
        let mut d_g = [[0f32; 9]; NUM_JOINTS];
        let mut d_t = [[0f32; 3]; NUM_JOINTS];
        let mut d_rest = vec![0f32; NUM_JOINTS * 3];
        // A_j = [G_j | g_t_j - G_j rest_j], posed joint j = g_t_j + shift.
        for j in 0..NUM_JOINTS {
            let a = &d_a[j * 12..(j + 1) * 12];
            let dt = [a[3], a[7], a[11]];
            let rj = point(&rest, j);
            for row in 0..3 {
                for col in 0..3 {
                    d_g[j][row * 3 + col] = a[row * 4 + col] - dt[row] * rj[col];
                }
                d_t[j][row] = dt[row] + d_joints[j * 3 + row];
            }
            let back = mat_t_vec(&g_rot[j], &dt);
            for ax in 0..3 {
                d_rest[j * 3 + ax] -= back[ax];
            }
        }
        if mode == Translation::Pelvis {
            for ax in 0..3 {
                d_rest[ax] -= ds[ax];
            }
        }
        let mut d_rot = vec![0f32; NUM_JOINTS * 9];
        for &j in self.chain_order.iter().rev() {
            if j == 0 {
                d_rot[..9].copy_from_slice(&d_g[0]);
                for ax in 0..3 {
                    d_rest[ax] += d_t[0][ax];
                }
                continue;
            }
            let p = self.parents[j];
            let (gp, rj) = (g_rot[p], rotation(r, j));
            // g_t_j = G_p (rest_j - rest_p) + g_t_p
            let rel = sub3(point(&rest, j), point(&rest, p));
            let dtj = d_t[j];
            let d_rel = mat_t_vec(&gp, &dtj);
            for ax in 0..3 {
                d_rest[j * 3 + ax] += d_rel[ax];
                d_rest[p * 3 + ax] -= d_rel[ax];
                d_t[p][ax] += dtj[ax];
            }
            // G_j = G_p R_j
            let dgj = d_g[j];
            let to_parent = mat_mul_bt(&dgj, &rj);
            for row in 0..3 {
                for col in 0..3 {
                    d_g[p][row * 3 + col] += dtj[row] * rel[col] + to_parent[row * 3 + col];
                }
            }
            d_rot[j * 9..j * 9 + 9].copy_from_slice(&mat_at_mul(&gp, &dgj));
        }
        (d_rot, d_rest)
    }

    /// Body `b`'s coefficient gradient: through its rest joints and through the GEMM features.
    fn coefficient_gradient(
        &self,
        b: usize,
        n: usize,
        d_feat: &[f32],
        d_rest: &[f32],
        out: &mut [f32],
    ) {
        for (ci, o) in out.iter_mut().enumerate() {
            let dir = &self.j_shapedirs[ci * NUM_JOINTS * 3..(ci + 1) * NUM_JOINTS * 3];
            let through_rest: f32 = dir.iter().zip(d_rest).map(|(x, y)| x * y).sum();
            *o = through_rest + d_feat[(1 + ci) * n + b];
        }
    }
}

/// `A^T x` for a row-major 3 x 3 `A`.
fn mat_t_vec(a: &[f32; 9], x: &[f32; 3]) -> [f32; 3] {
    [
        a[0] * x[0] + a[3] * x[1] + a[6] * x[2],
        a[1] * x[0] + a[4] * x[1] + a[7] * x[2],
        a[2] * x[0] + a[5] * x[1] + a[8] * x[2],
    ]
}

/// `A B^T`.
fn mat_mul_bt(a: &[f32; 9], b: &[f32; 9]) -> [f32; 9] {
    std::array::from_fn(|e| {
        let (i, j) = (e / 3, e % 3);
        a[i * 3] * b[j * 3] + a[i * 3 + 1] * b[j * 3 + 1] + a[i * 3 + 2] * b[j * 3 + 2]
    })
}

/// `A^T B`.
fn mat_at_mul(a: &[f32; 9], b: &[f32; 9]) -> [f32; 9] {
    std::array::from_fn(|e| {
        let (i, j) = (e / 3, e % 3);
        a[i] * b[j] + a[3 + i] * b[3 + j] + a[6 + i] * b[6 + j]
    })
}
