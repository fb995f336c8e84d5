//! The voxel grid in the voxel-centre convention: `x_i = c_x - L_x/2 + (i + 0.5) L_x / X`.
//! Tensors over the grid are `[B, C, X, Y, Z]` and a flat index is `(ix * Y + iy) * Z + iz`.
use serde::{Deserialize, Serialize};

use crate::GeomError;

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VoxelGrid {
    /// Centre of the grid in the world (metres).
    pub center: [f64; 3],
    /// Extent along x, y, z (metres).
    pub size: [f64; 3],
    /// Number of voxels along x, y, z.
    pub shape: [usize; 3],
}

/// Most voxels along one axis (the paper's grid has 300).
pub const MAX_GRID_SIDE: usize = 4096;
/// Most voxels in a grid: 2^25, 18 times the paper's 300 x 300 x 20; a 32-channel f32 volume over it is
/// already 4 GiB.
pub const MAX_VOXELS: usize = 1 << 25;

/// Most metres a grid's centre lies from the origin, and most metres a side spans: the network computes
/// positions in float32, where 1e300 is infinite and a kilometre-wide grid already loses millimetres.
pub const MAX_EXTENT: f64 = 10_000.0;

impl VoxelGrid {
    pub fn new(center: [f64; 3], size: [f64; 3], shape: [usize; 3]) -> Result<Self, GeomError> {
        let g = VoxelGrid {
            center,
            size,
            shape,
        };
        g.validate()?;
        Ok(g)
    }

    pub fn validate(&self) -> Result<(), GeomError> {
        for a in 0..3 {
            if !(self.center[a].is_finite() && self.center[a].abs() <= MAX_EXTENT) {
                return Err(GeomError::InvalidGrid(format!(
                    "center[{a}] = {}: expected a finite coordinate within {MAX_EXTENT} m",
                    self.center[a]
                )));
            }
            if !(self.size[a].is_finite() && self.size[a] > 0.0 && self.size[a] <= MAX_EXTENT) {
                return Err(GeomError::InvalidGrid(format!(
                    "size[{a}] = {}: expected a positive size up to {MAX_EXTENT} m",
                    self.size[a]
                )));
            }
            if self.shape[a] == 0 || self.shape[a] > MAX_GRID_SIDE {
                return Err(GeomError::InvalidGrid(format!(
                    "shape[{a}] = {}: expected 1 to {MAX_GRID_SIDE} voxels",
                    self.shape[a]
                )));
            }
        }
        // Each side is at most 2^12, so the product cannot overflow.
        let n: usize = self.shape.iter().product();
        if n > MAX_VOXELS {
            return Err(GeomError::InvalidGrid(format!(
                "shape = {:?}: {n} voxels, more than the {MAX_VOXELS} allowed",
                self.shape
            )));
        }
        Ok(())
    }

    /// Edge length of one voxel along each axis.
    pub fn voxel_size(&self) -> [f64; 3] {
        std::array::from_fn(|a| self.size[a] / self.shape[a] as f64)
    }

    pub fn num_voxels(&self) -> usize {
        self.shape.iter().product()
    }

    /// The lower corner of the grid.
    pub fn min_corner(&self) -> [f64; 3] {
        std::array::from_fn(|a| self.center[a] - self.size[a] / 2.0)
    }

    /// World position of a (possibly fractional) voxel index; integers give voxel centres.
    pub fn index_to_world(&self, idx: [f64; 3]) -> [f64; 3] {
        let lo = self.min_corner();
        let vs = self.voxel_size();
        std::array::from_fn(|a| lo[a] + (idx[a] + 0.5) * vs[a])
    }

    /// Continuous voxel index of a world point (inverse of [`VoxelGrid::index_to_world`]).
    pub fn world_to_index(&self, p: [f64; 3]) -> [f64; 3] {
        let lo = self.min_corner();
        let vs = self.voxel_size();
        std::array::from_fn(|a| (p[a] - lo[a]) / vs[a] - 0.5)
    }

    /// The voxel that contains a world point, or `None` outside the grid.
    pub fn containing_voxel(&self, p: [f64; 3]) -> Option<[usize; 3]> {
        let f = self.world_to_index(p);
        let mut out = [0usize; 3];
        for a in 0..3 {
            let i = (f[a] + 0.5).floor();
            if i < 0.0 || i >= self.shape[a] as f64 {
                return None;
            }
            out[a] = i as usize;
        }
        Some(out)
    }

    pub fn flat_index(&self, idx: [usize; 3]) -> usize {
        (idx[0] * self.shape[1] + idx[1]) * self.shape[2] + idx[2]
    }

    pub fn unflatten(&self, flat: usize) -> [usize; 3] {
        let [_, y, z] = self.shape;
        [flat / (y * z), (flat / z) % y, flat % z]
    }

    /// All voxel centres in flat-index order, as `[x, y, z]` triples.
    pub fn centers(&self) -> Vec<[f64; 3]> {
        let [nx, ny, nz] = self.shape;
        let mut out = Vec::with_capacity(self.num_voxels());
        for ix in 0..nx {
            for iy in 0..ny {
                for iz in 0..nz {
                    out.push(self.index_to_world([ix as f64, iy as f64, iz as f64]));
                }
            }
        }
        out
    }
}
