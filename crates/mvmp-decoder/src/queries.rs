//! Person queries: a trilinear sample of the fused volume at each root, plus the mean SMPL-X parameters.
use burn::tensor::{Device, Int, Tensor, TensorData};

use mvmp_geom::VoxelGrid;
use mvmp_geom::rotation::{matrix_to_rot6d, y_up_to_z_up};
use mvmp_smplx::names::{NUM_BETAS, NUM_EXPRESSION, NUM_REGRESSED};

/// Width of the parameter vector: 53 rotations in 6D, betas, expression.
pub const PARAM_DIM: usize = NUM_REGRESSED * 6 + NUM_BETAS + NUM_EXPRESSION;

/// The default mean parameter vector `[PARAM_DIM]`: the global orientation of an upright person in the
/// z-up world (the y-up to z-up turn), identity for every other rotation, zero betas and expression.
/// Training replaces it with its data's mean ([`params_vector`]); this is where an untrained model starts.
pub fn mean_params(device: &Device) -> Tensor<1> {
    let g = y_up_to_z_up();
    let mut rotations = vec![[1f32, 0., 0., 0., 1., 0., 0., 0., 1.]; NUM_REGRESSED];
    rotations[0] = std::array::from_fn(|k| g[(k / 3, k % 3)] as f32);
    params_vector(
        &rotations,
        &[0.0; NUM_BETAS],
        &[0.0; NUM_EXPRESSION],
        device,
    )
}

/// A parameter vector `[PARAM_DIM]` from 53 rotation matrices in the regressed order (row-major), betas
/// and expression.
pub fn params_vector(
    rotations: &[[f32; 9]],
    betas: &[f32; NUM_BETAS],
    expression: &[f32; NUM_EXPRESSION],
    device: &Device,
) -> Tensor<1> {
    assert_eq!(
        rotations.len(),
        NUM_REGRESSED,
        "one rotation per regressed joint"
    );
    let flat: Vec<f32> = rotations.iter().flatten().copied().collect();
    let r6 = matrix_to_rot6d(Tensor::<3>::from_data(
        TensorData::new(flat, [NUM_REGRESSED, 3, 3]),
        device,
    ))
    .reshape([NUM_REGRESSED * 6]);
    let coeffs: Vec<f32> = betas.iter().chain(expression).copied().collect();
    let coeffs = Tensor::from_data(
        TensorData::new(coeffs, [NUM_BETAS + NUM_EXPRESSION]),
        device,
    );
    Tensor::cat(vec![r6, coeffs], 0)
}

/// Trilinear sample of `volume` `[B, C, X, Y, Z]` at world points `[B, K, 3]` (voxel-centre convention,
/// clamped to the grid), giving `[B, K, C]`. Differentiable in the volume and the points.
pub fn trilinear_sample(volume: Tensor<5>, points: Tensor<3>, grid: &VoxelGrid) -> Tensor<3> {
    let [b, c, nx, ny, nz] = volume.dims();
    let k = points.dims()[1];
    let lo = grid.min_corner();
    let vs = grid.voxel_size();
    let shape = [nx, ny, nz];
    let flat = volume.reshape([b, c, nx * ny * nz]);
    // Continuous voxel index per axis, clamped so that both corners exist.
    let axis = |a: usize| -> (Tensor<2, Int>, Tensor<2>) {
        let p = points.clone().narrow(2, a, 1).reshape([b, k]);
        let f = ((p - lo[a]) / vs[a] - 0.5).clamp(0.0, (shape[a] - 1) as f32);
        let i0 = f.clone().floor().clamp_max((shape[a].max(2) - 2) as f32);
        let i0 = if shape[a] == 1 { i0.zeros_like() } else { i0 };
        let t = f - i0.clone();
        (i0.int(), t)
    };
    let (ix, tx) = axis(0);
    let (iy, ty) = axis(1);
    let (iz, tz) = axis(2);
    let step = |n: usize| if n > 1 { 1 } else { 0 };
    let mut out: Option<Tensor<3>> = None;
    for corner in 0..8 {
        let (dx, dy, dz) = ((corner >> 2) & 1, (corner >> 1) & 1, corner & 1);
        let idx = ((ix.clone() + (dx * step(nx)) as i64) * (ny * nz) as i64
            + (iy.clone() + (dy * step(ny)) as i64) * nz as i64)
            + (iz.clone() + (dz * step(nz)) as i64); // [B, K]
        let w = |t: &Tensor<2>, d: usize| if d == 1 { t.clone() } else { -t.clone() + 1.0 };
        let wt = w(&tx, dx) * w(&ty, dy) * w(&tz, dz); // [B, K]
        let g = flat
            .clone()
            .gather(2, idx.unsqueeze_dim::<3>(1).repeat_dim(1, c)); // [B, C, K]
        let term = g * wt.unsqueeze_dim::<3>(1);
        out = Some(match out {
            Some(o) => o + term,
            None => term,
        });
    }
    out.expect("eight corners").swap_dims(1, 2)
}
