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
use super::grid::{slot_offset, Leaf, SparseGrid, TileLevel, LEAF_VOXELS};
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

/// A leaf or an 8³ tile of the density: the blocks V is kept voxel by voxel in.
enum Block<'g> {
    Leaf(&'g Leaf),
    Tile(IVec3, f32),
}

impl Block<'_> {
    fn origin(&self) -> IVec3 {
        match self {
            Block::Leaf(l) => l.origin,
            Block::Tile(o, _) => *o,
        }
    }

    fn mask(&self) -> [u64; 8] {
        match self {
            Block::Leaf(l) => l.mask,
            Block::Tile(..) => [u64::MAX; 8],
        }
    }

    /// The density of voxel `slot`, 0 where it is inactive or not positive.
    fn active_density(&self, slot: usize) -> f32 {
        match self {
            Block::Leaf(l) if l.is_active(slot) => l.values.get(slot).max(0.0),
            Block::Leaf(_) => 0.0,
            Block::Tile(_, v) => v.max(0.0),
        }
    }
}

impl Visibility {
    /// Sweeps V through `field` at extinction `sigma_t` per unit density.
    pub fn build(field: &DensityField, sigma_t: f32) -> Visibility {
        let grid = &field.grid;
        // Leaves and 8³ tiles alike, voxel by voxel: an 8³ tile often lies under a surface, where
        // V changes across it. Larger tiles take the value at their centre.
        let blocks: Vec<Block> = grid
            .leaves()
            .iter()
            .map(Block::Leaf)
            .chain(grid.tiles(TileLevel::Block).map(|(o, v)| Block::Tile(o, v)))
            .collect();
        let tiles: Vec<(TileLevel, IVec3, f32, IVec3)> = [TileLevel::Node, TileLevel::Root]
            .into_iter()
            .flat_map(|level| {
                let half = IVec3::splat((level.dim() / 2) as i32);
                grid.tiles(level).map(move |(o, v)| (level, o, v, o + half))
            })
            .collect();
        // ρ·V accumulates in place, a direction at a time: the result and one shadow volume are
        // all the build holds.
        let share = 1.0 / DIRECTIONS as f32;
        let mut block_values = vec![[0.0f32; LEAF_VOXELS]; blocks.len()];
        let mut tile_values = vec![0.0f32; tiles.len()];
        for d in fibonacci(DIRECTIONS) {
            let volume = ShadowVolume::build(field, sigma_t, d);
            block_values
                .par_iter_mut()
                .zip(&blocks)
                .for_each(|(values, block)| {
                    let mut cursor = ShadowCursor::default();
                    for (slot, value) in values.iter_mut().enumerate() {
                        let rho = block.active_density(slot);
                        if rho > 0.0 {
                            let tau = volume
                                .core_value(block.origin() + slot_offset(slot), &mut cursor)
                                .unwrap_or(0.0);
                            *value += rho * share * (-tau).exp();
                        }
                    }
                });
            tile_values
                .par_iter_mut()
                .zip(&tiles)
                .for_each(|(value, (_, _, rho, centre))| {
                    let mut cursor = ShadowCursor::default();
                    let tau = volume.core_value(*centre, &mut cursor).unwrap_or(0.0);
                    *value += rho.max(0.0) * share * (-tau).exp();
                });
        }
        let mut weighted = SparseGrid::new(grid.transform, 0.0);
        for (block, values) in blocks.iter().zip(block_values) {
            weighted.insert_leaf(block.origin(), block.mask(), values);
        }
        for ((level, origin, _, _), value) in tiles.iter().zip(tile_values) {
            weighted.insert_tile(*level, *origin, value);
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::grid::{Transform, LEAF_DIM};
    use glam::Vec3;

    /// V at `p` in the cube of density 1 over voxels [0, n)³, whose trilinear density ends half a
    /// voxel beyond its outer voxels: the mean of e^{−σt·d} over the same directions, d the exact
    /// distance to that boundary.
    fn cube_visibility(p: Vec3, n: f32, sigma_t: f32) -> f32 {
        let lo = Vec3::splat(-0.5) - p;
        let hi = Vec3::splat(n - 0.5) - p;
        let mean: f32 = fibonacci(DIRECTIONS)
            .iter()
            .map(|d| {
                let exit = |a: usize| match d[a] {
                    x if x > 0.0 => hi[a] / x,
                    x if x < 0.0 => lo[a] / x,
                    _ => f32::INFINITY,
                };
                (-sigma_t * exit(0).min(exit(1)).min(exit(2))).exp()
            })
            .sum();
        mean / DIRECTIONS as f32
    }

    #[test]
    fn a_uniform_cube_sees_the_environment_through_its_exact_depths() {
        // 4³ leaves of density 1: 32³ voxels.
        let mut grid = SparseGrid::new(Transform::default(), 0.0);
        for l in 0..64 {
            let origin = IVec3::new(l / 16, (l / 4) % 4, l % 4) * LEAF_DIM;
            grid.insert_leaf(origin, [u64::MAX; 8], [1.0; LEAF_VOXELS]);
        }
        let field = DensityField::new(grid);
        let sigma_t = 0.1;
        let v = Visibility::build(&field, sigma_t);
        for p in [
            IVec3::splat(16),
            IVec3::new(0, 16, 16),
            IVec3::new(3, 28, 9),
            IVec3::splat(31),
        ] {
            let want = cube_visibility(p.as_vec3(), 32.0, sigma_t);
            // ρ = 1, so the stored ρ·V is V.
            let got = v.weighted.value(p);
            assert!((got - want).abs() < 0.02 * want, "{p}: {got} vs {want}");
        }
        // Outside the medium nothing is stored: ρ·V is 0 there.
        assert_eq!(v.weighted.value(IVec3::splat(40)), 0.0);
    }

    /// The visibility of one tile at the origin.
    fn of_tile(level: TileLevel, value: f32, sigma_t: f32) -> Visibility {
        let mut grid = SparseGrid::new(Transform::default(), 0.0);
        grid.insert_tile(level, IVec3::ZERO, value);
        Visibility::build(&DensityField::new(grid), sigma_t)
    }

    #[test]
    fn an_8_cubed_tile_is_resolved_voxel_by_voxel() {
        let v = of_tile(TileLevel::Block, 1.0, 0.3);
        // At a corner the sweep resamples its depths bilinearly across the cube's edges, where
        // the depth has a kink: 3.5 % there, under 2 % inside.
        for (p, tolerance) in [
            (IVec3::ZERO, 0.05),
            (IVec3::new(3, 4, 3), 0.02),
            (IVec3::new(7, 2, 5), 0.02),
        ] {
            let want = cube_visibility(p.as_vec3(), 8.0, 0.3);
            let got = v.weighted.value(p);
            assert!(
                (got - want).abs() < tolerance * want,
                "{p}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn a_large_tile_takes_the_visibility_of_its_centre() {
        let v = of_tile(TileLevel::Node, 0.5, 0.04);
        // Density 0.5 at σt 0.04 is the unit cube of 128 at σt 0.02; the tile stores ρ·V.
        let want = 0.5 * cube_visibility(Vec3::splat(64.0), 128.0, 0.02);
        let got = v.weighted.value(IVec3::new(5, 100, 17));
        assert!((got - want).abs() < 0.02 * want, "{got} vs {want}");
    }
}
