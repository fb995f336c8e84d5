//! Root extraction from the likelihood volume and the Gaussian targets of the detection loss, in the
//! voxel-centre convention of [`VoxelGrid`].
use burn::tensor::{Device, Tensor, TensorData};

use crate::pool::nms3d;
use mvmp_geom::VoxelGrid;

/// A detected root.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Root {
    /// World position (metres), voxel centre plus the predicted sub-voxel offset.
    pub position: [f64; 3],
    pub score: f32,
    /// The voxel of the peak.
    pub voxel: [usize; 3],
}

/// How a root is placed within its peak voxel.
#[derive(Debug, Clone)]
pub enum Subvoxel {
    /// At the voxel centre.
    Centre,
    /// Voxel centre plus the offset head's output `[B, 3, X, Y, Z]` (voxel units, clamped to half a
    /// voxel): the paper's refinement.
    Offset(Box<Tensor<5>>),
    /// At the vertex of the Gaussian through the peak and its two neighbours on each axis
    /// ([`gaussian_peak`]).
    Peak,
}

/// Which [`Subvoxel`] refinement a model uses (`root_refine` in model configs).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum RootRefine {
    /// The offset head (paper).
    #[default]
    Offset,
    /// The likelihood's own peak shape; the offset head is still trained but not read.
    Peak,
}

impl RootRefine {
    /// The refinement with the offset volume a forward produced.
    pub fn with_offset(self, offset: Tensor<5>) -> Subvoxel {
        match self {
            RootRefine::Offset => Subvoxel::Offset(Box::new(offset)),
            RootRefine::Peak => Subvoxel::Peak,
        }
    }
}

/// NMS (3 x 3 x 3), top-K, threshold, sub-voxel refinement. `likelihood`: `[B, 1, X, Y, Z]`. Returns, per
/// batch item, the roots with score above `threshold`, best first.
pub fn extract_roots(
    likelihood: Tensor<5>,
    refine: Subvoxel,
    grid: &VoxelGrid,
    k: usize,
    threshold: f32,
) -> Vec<Vec<Root>> {
    let [b, _, x, y, z] = likelihood.dims();
    let p = x * y * z;
    let k = k.min(p);
    let raw: Option<Vec<f32>> = matches!(refine, Subvoxel::Peak).then(|| {
        likelihood
            .clone()
            .into_data()
            .try_into_vec()
            .expect("f32 likelihood")
    });
    let kept = nms3d(likelihood).reshape([b, p]);
    let (vals, idx) = kept.topk_with_indices(k, 1);
    let vals: Vec<f32> = vals.into_data().try_into_vec().expect("f32 scores");
    let idx: Vec<i64> = idx
        .into_data()
        .convert::<i64>()
        .try_into_vec()
        .expect("integer indices");
    let offs: Option<Vec<f32>> = match refine {
        Subvoxel::Offset(o) => Some(
            o.reshape([b, 3, p])
                .into_data()
                .try_into_vec()
                .expect("f32 offsets"),
        ),
        _ => None,
    };
    let vs = grid.voxel_size();
    (0..b)
        .map(|bi| {
            (0..k)
                .filter(|&j| vals[bi * k + j] > threshold)
                .map(|j| {
                    let flat = idx[bi * k + j] as usize;
                    let voxel = grid.unflatten(flat);
                    let d: [f64; 3] = match (&offs, &raw) {
                        (Some(o), _) => std::array::from_fn(|a| {
                            (o[(bi * 3 + a) * p + flat] as f64).clamp(-0.5, 0.5)
                        }),
                        (_, Some(l)) => gaussian_peak(&l[bi * p..(bi + 1) * p], grid, voxel),
                        _ => [0.0; 3],
                    };
                    let c = grid.index_to_world(voxel.map(|i| i as f64));
                    Root {
                        position: std::array::from_fn(|a| c[a] + d[a] * vs[a]),
                        score: vals[bi * k + j],
                        voxel,
                    }
                })
                .collect()
        })
        .collect()
}

/// The sub-voxel position (voxel units, each axis within [-0.5, 0.5]) of the peak of `volume` (one item,
/// flat) at `voxel`: per axis the vertex of the parabola through the log-values at the voxel and its two
/// neighbours, which is exact for a sampled Gaussian. 0 on an axis where the voxel is at the grid's edge
/// or a value is not positive.
pub fn gaussian_peak(volume: &[f32], grid: &VoxelGrid, voxel: [usize; 3]) -> [f64; 3] {
    let at = |v: [usize; 3]| volume[grid.flat_index(v)] as f64;
    let f0 = at(voxel);
    std::array::from_fn(|a| {
        if voxel[a] == 0 || voxel[a] + 1 >= grid.shape[a] {
            return 0.0;
        }
        let (mut lo, mut hi) = (voxel, voxel);
        lo[a] -= 1;
        hi[a] += 1;
        let (fm, fp) = (at(lo), at(hi));
        if fm <= 0.0 || fp <= 0.0 || f0 <= 0.0 {
            return 0.0;
        }
        let (lm, l0, lp) = (fm.ln(), f0.ln(), fp.ln());
        let curvature = lm - 2.0 * l0 + lp;
        // Not a peak on this axis (flat, a valley, or a NaN from a broken likelihood).
        if curvature.is_nan() || curvature >= 0.0 {
            return 0.0;
        }
        (0.5 * (lm - lp) / curvature).clamp(-0.5, 0.5)
    })
}

/// The default width of the Gaussian root target (metres), as VoxelPose and the paper use.
pub const DEFAULT_SIGMA: f64 = 0.2;

/// The Gaussian target volume `[X, Y, Z]` (flat, in flat-index order) for roots in the world:
/// `exp(-|c - mu|^2 / (2 sigma^2))` at every voxel centre `c` within 3 sigma, people merged by maximum.
pub fn gaussian_target_values(grid: &VoxelGrid, roots: &[[f64; 3]], sigma: f64) -> Vec<f32> {
    let mut out = vec![0f32; grid.num_voxels()];
    let vs = grid.voxel_size();
    for r in roots {
        let c = grid.world_to_index(*r);
        let lo: [i64; 3] =
            std::array::from_fn(|a| ((c[a] - 3.0 * sigma / vs[a]).floor() as i64).max(0));
        let hi: [i64; 3] = std::array::from_fn(|a| {
            ((c[a] + 3.0 * sigma / vs[a]).ceil() as i64).min(grid.shape[a] as i64 - 1)
        });
        for ix in lo[0]..=hi[0] {
            for iy in lo[1]..=hi[1] {
                for iz in lo[2]..=hi[2] {
                    let w = grid.index_to_world([ix as f64, iy as f64, iz as f64]);
                    let d2: f64 = (0..3).map(|a| (w[a] - r[a]).powi(2)).sum();
                    let g = (-d2 / (2.0 * sigma * sigma)).exp() as f32;
                    let k = grid.flat_index([ix as usize, iy as usize, iz as usize]);
                    out[k] = out[k].max(g);
                }
            }
        }
    }
    out
}

/// [`gaussian_target_values`] for a batch, as a tensor `[B, 1, X, Y, Z]`.
pub fn gaussian_target(
    grid: &VoxelGrid,
    roots: &[Vec<[f64; 3]>],
    sigma: f64,
    device: &Device,
) -> Tensor<5> {
    let [x, y, z] = grid.shape;
    let data: Vec<f32> = roots
        .iter()
        .flat_map(|r| gaussian_target_values(grid, r, sigma))
        .collect();
    Tensor::from_data(TensorData::new(data, [roots.len(), 1, x, y, z]), device)
}

/// The voxel that holds a root and the root's sub-voxel offset from that voxel's centre (voxel units, in
/// [-0.5, 0.5)), or `None` outside the grid: the target of the offset head.
pub fn root_voxel_and_offset(grid: &VoxelGrid, root: [f64; 3]) -> Option<([usize; 3], [f64; 3])> {
    let v = grid.containing_voxel(root)?;
    let c = grid.world_to_index(root);
    Some((v, std::array::from_fn(|a| c[a] - v[a] as f64)))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 5 x 5 x 5 volume holding a Gaussian of width 1 voxel centred at `mu` (voxel units).
    fn gaussian_volume(grid: &VoxelGrid, mu: [f64; 3]) -> Vec<f32> {
        (0..grid.num_voxels())
            .map(|i| {
                let v = grid.unflatten(i);
                let d2: f64 = (0..3).map(|a| (v[a] as f64 - mu[a]).powi(2)).sum();
                (-d2 / 2.0).exp() as f32
            })
            .collect()
    }

    #[test]
    fn the_peak_of_a_sampled_gaussian_is_found_exactly_and_nan_gives_no_shift() {
        let grid = VoxelGrid::new([0.0; 3], [5.0; 3], [5, 5, 5]).unwrap();
        // By hand: the log of a Gaussian is a parabola, so the vertex through three samples is exact.
        let vol = gaussian_volume(&grid, [2.3, 1.8, 2.0]);
        let d = gaussian_peak(&vol, &grid, [2, 2, 2]);
        for (got, want) in d.iter().zip([0.3, -0.2, 0.0]) {
            assert!((got - want).abs() < 1e-4, "{d:?}");
        }
        // At the grid's edge there is no neighbour on one side: no shift along that axis.
        assert_eq!(gaussian_peak(&vol, &grid, [0, 2, 2])[0], 0.0);
        let mut broken = vol.clone();
        broken[grid.flat_index([3, 2, 2])] = f32::NAN;
        assert_eq!(gaussian_peak(&broken, &grid, [2, 2, 2])[0], 0.0);
    }
}
