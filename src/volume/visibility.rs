//! The visibility V(p) = (1/4π)∫ e^{−τ(p, ω)} dω of every density voxel: the share of the
//! environment a voxel sees through the medium, whatever the light. It falls by orders of
//! magnitude within one transfer voxel under a thick lit surface, which is what a transfer
//! interpolated between nodes K voxels apart cannot follow; the renderer takes the shape of that
//! fall from V at the density's resolution ([`crate::render::march::TransferRadiance`]).
//!
//! V is the mean of e^{−τ} over [`DIRECTIONS`] equal-area directions, each τ swept once through
//! the occupied region by a [`ShadowVolume`], so the cost follows the active voxels, and the
//! result is deterministic (no Monte Carlo noise to become texture).
//!
//! It is kept as ρ·V on the density's own topology: sampled trilinearly and divided by the
//! trilinear ρ, it is V interpolated with density weights, so empty voxels beside a surface (where
//! V is not defined) take no part.

use glam::IVec3;
use rayon::prelude::*;

use super::bricks::{BrickSampler, Bricks};
use super::grid::{slot_offset, SparseGrid, TileLevel, LEAF_VOXELS};
use super::shadow::{ShadowCursor, ShadowVolume};
use super::DensityField;
use crate::math::sphere::fibonacci;

/// Directions V averages over. V only shapes the light between transfer nodes (its ratio to its
/// own interpolation), so its quadrature error largely cancels.
pub const DIRECTIONS: usize = 16;

/// ρ·V on the density's topology, with the accelerator that samples it.
pub struct Visibility {
    pub weighted: SparseGrid,
    bricks: Bricks,
}

impl Visibility {
    /// Sweeps V through `field` at extinction `sigma_t` per unit density.
    pub fn build(field: &DensityField, sigma_t: f32) -> Visibility {
        let grid = &field.grid;
        let leaves = grid.leaves();
        let tiles: Vec<(TileLevel, IVec3, f32, IVec3)> =
            [TileLevel::Block, TileLevel::Node, TileLevel::Root]
                .into_iter()
                .flat_map(|level| {
                    let half = IVec3::splat((level.dim() / 2) as i32);
                    grid.tiles(level).map(move |(o, v)| (level, o, v, o + half))
                })
                .collect();
        let mut leaf_sums = vec![[0.0f32; LEAF_VOXELS]; leaves.len()];
        let mut tile_sums = vec![0.0f32; tiles.len()];
        let dirs = fibonacci(DIRECTIONS);
        for d in dirs {
            let volume = ShadowVolume::build(field, sigma_t, d);
            leaf_sums
                .par_iter_mut()
                .zip(leaves)
                .for_each(|(sums, leaf)| {
                    let mut cursor = ShadowCursor::default();
                    for (slot, s) in sums.iter_mut().enumerate() {
                        if leaf.is_active(slot) {
                            let tau = volume
                                .core_value(leaf.origin + slot_offset(slot), &mut cursor)
                                .unwrap_or(0.0);
                            *s += (-tau).exp();
                        }
                    }
                });
            tile_sums
                .par_iter_mut()
                .zip(&tiles)
                .for_each(|(s, (_, _, _, centre))| {
                    let mut cursor = ShadowCursor::default();
                    *s += (-volume.core_value(*centre, &mut cursor).unwrap_or(0.0)).exp();
                });
        }
        let mean = 1.0 / DIRECTIONS as f32;
        let mut weighted = SparseGrid::new(grid.transform.clone(), 0.0);
        for (leaf, sums) in leaves.iter().zip(&leaf_sums) {
            let values = std::array::from_fn(|s| leaf.values[s].max(0.0) * sums[s] * mean);
            weighted.insert_leaf(leaf.origin, leaf.mask, values);
        }
        for ((level, origin, rho, _), s) in tiles.iter().zip(&tile_sums) {
            weighted.insert_tile(*level, *origin, rho.max(0.0) * s * mean);
        }
        let bricks = Bricks::build(&weighted);
        Visibility { weighted, bricks }
    }

    /// A sampler of ρ·V for one ray.
    pub fn sampler(&self) -> BrickSampler<'_> {
        BrickSampler::new(&self.bricks, &self.weighted)
    }

    /// Bytes held (the grid and its bricks).
    pub fn memory_bytes(&self) -> usize {
        self.weighted.memory_bytes() + self.bricks.memory_bytes()
    }
}
