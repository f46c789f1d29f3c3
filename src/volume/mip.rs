//! Coarser copies of a density for marching far from a ray's origin: level ℓ holds the mean of
//! each 2^ℓ-voxel cube of the fine grid (the box filter keeps ∫ρ, so a line integral through a
//! level is the mean of the fine integrals over its footprint). Each level is a sparse grid with
//! its own accelerators, built from the one below in time ∝ its active voxels; a constant tile
//! stays a tile at every level.
//!
//! Index spaces: fine voxel i covers [i − ½, i + ½], so coarse voxel I of a level twice as coarse
//! covers fine voxels 2I and 2I + 1 and its centre sits at fine 2I + ½: p_coarse = (p_fine − ½)/2.

use glam::{DVec3, IVec3, Vec3};
use hashbrown::HashMap;
use rayon::prelude::*;

use super::field::DensityField;
use super::grid::{corner, Leaf, SparseGrid, TileLevel, LEAF_LOG2, LEAF_VOXELS};

/// The coarser levels of a density; `level(1)` is twice as coarse as the density itself.
pub struct DensityMip {
    levels: Vec<DensityField>,
}

impl DensityMip {
    /// `count` levels above `fine` (fewer if the grid shrinks to a single voxel first).
    pub fn build(fine: &SparseGrid, count: usize) -> DensityMip {
        let mut levels: Vec<DensityField> = Vec::with_capacity(count);
        for _ in 0..count {
            let below = levels.last().map(|f| &f.grid).unwrap_or(fine);
            let single_voxel = below
                .active_bbox()
                .is_none_or(|(lo, hi)| (hi - lo).max_element() == 0);
            if single_voxel {
                break;
            }
            levels.push(DensityField::new(coarsen(below)));
        }
        DensityMip { levels }
    }

    /// The number of coarse levels.
    pub fn len(&self) -> usize {
        self.levels.len()
    }

    /// Level `l` ≥ 1: voxels 2^l fine voxels wide.
    pub fn level(&self, l: usize) -> &DensityField {
        &self.levels[l - 1]
    }

    /// Bytes held by every level's grid and accelerators.
    pub fn memory_bytes(&self) -> usize {
        self.levels
            .iter()
            .map(|f| f.grid.memory_bytes() + f.brick_bytes())
            .sum()
    }
}

/// Fine index point `p` in the index space of level `l`.
pub fn to_level(p: Vec3, l: usize) -> Vec3 {
    let s = (1u32 << l) as f32;
    (p + 0.5) / s - 0.5
}

/// What covers one coarse leaf: fine leaves, and 8³ tiles as (origin, value).
type Parts<'a> = (Vec<&'a Leaf>, Vec<(IVec3, f32)>);

/// The 2×2×2 box mean of `fine`: a coarse voxel is active when any of its eight is, and an
/// inactive fine voxel counts as the background.
pub fn coarsen(fine: &SparseGrid) -> SparseGrid {
    let t = fine.transform;
    let transform = super::Transform {
        scale: t.scale * 2.0,
        translation: t.index_to_world(DVec3::splat(0.5)),
    };
    let mut coarse = SparseGrid::new(transform, fine.background);
    // What lands in each coarse leaf (key: coarse leaf origin >> 3, i.e. fine origin >> 4): fine
    // leaves, and 8³ tiles, which halve to 4³ and so no longer fill a block of their own.
    let mut parts: HashMap<IVec3, Parts> = HashMap::new();
    for leaf in fine.leaves() {
        parts.entry(leaf.origin >> 4).or_default().0.push(leaf);
    }
    for (origin, value) in fine.tiles(TileLevel::Block) {
        parts
            .entry(origin >> 4)
            .or_default()
            .1
            .push((origin, value));
    }
    let parts: Vec<_> = parts.into_iter().collect();
    let leaves: Vec<Leaf> = parts
        .par_iter()
        .map(|(key, (leaves, tiles))| {
            let origin = *key << LEAF_LOG2;
            let mut values = [fine.background; LEAF_VOXELS];
            let mut mask = [0u64; 8];
            // Each fine block present fills the 4³ coarse voxels it covers: all eight children of
            // a coarse voxel lie in one fine block, and a leaf's inactive voxels hold the background.
            let mut fill = |block: IVec3, child: &dyn Fn(IVec3) -> (f32, bool)| {
                for slot in 0..LEAF_VOXELS / 8 {
                    let c = IVec3::new(slot as i32 >> 4, (slot as i32 >> 2) & 3, slot as i32 & 3);
                    let (mut sum, mut active) = (0.0, false);
                    for n in 0..8 {
                        let (v, a) = child(c * 2 + corner(n));
                        sum += v;
                        active |= a;
                    }
                    let at = Leaf::slot((block >> 1) + c - origin);
                    values[at] = sum / 8.0;
                    if active {
                        mask[at >> 6] |= 1 << (at & 63);
                    }
                }
            };
            for leaf in leaves {
                fill(leaf.origin, &|o| {
                    let s = Leaf::slot(o);
                    (leaf.values.get(s), leaf.is_active(s))
                });
            }
            for &(tile, value) in tiles {
                fill(tile, &|_| (value, true));
            }
            Leaf::new(origin, mask, values, fine.background)
        })
        .collect();
    let mut leaves = leaves;
    leaves.sort_unstable_by_key(|l| (l.origin.x, l.origin.y, l.origin.z));
    for leaf in leaves {
        // A block wholly active at one value (the inside of a uniform region) stays a tile, so a
        // tiled volume keeps its tiles at every level.
        let first = leaf.values.get(0);
        let uniform = leaf.mask.iter().all(|&m| m == u64::MAX)
            && leaf.values.to_array().iter().all(|&v| v == first);
        match uniform {
            true => coarse.insert_tile(TileLevel::Block, leaf.origin, first),
            false => coarse.push_leaf(leaf),
        }
    }
    // Larger tiles halve into whole tiles: 128³ into 64³ (512 blocks), 4096³ into 2048³ (4096
    // nodes of 128³).
    for (level, into) in [
        (TileLevel::Node, TileLevel::Block),
        (TileLevel::Root, TileLevel::Node),
    ] {
        let (half, step) = ((level.dim() / 2) as i32, into.dim() as i32);
        for (origin, value) in fine.tiles(level) {
            let base = origin >> 1;
            for x in (0..half).step_by(step as usize) {
                for y in (0..half).step_by(step as usize) {
                    for z in (0..half).step_by(step as usize) {
                        coarse.insert_tile(into, base + IVec3::new(x, y, z), value);
                    }
                }
            }
        }
    }
    coarse
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_level_is_the_box_mean_and_keeps_the_integral() {
        let mut g = SparseGrid::new(Default::default(), 0.0);
        let mut values = [0f32; LEAF_VOXELS];
        for (i, v) in values.iter_mut().enumerate() {
            *v = (i % 5) as f32 * 0.25;
        }
        let mut mask = [u64::MAX; 8];
        mask[2] = 0x00ff_00ff_00ff_00ff;
        g.insert_leaf(IVec3::new(8, 0, -8), mask, values);
        g.insert_tile(TileLevel::Block, IVec3::new(16, 0, -8), 2.0);
        let c = coarsen(&g);
        let sum = |g: &SparseGrid| g.value_stats().map_or(0.0, |s| s.sum);
        assert!(
            (sum(&c) * 8.0 - sum(&g)).abs() < 1e-3,
            "{} {}",
            sum(&c),
            sum(&g)
        );
        for ijk in [
            IVec3::new(4, 0, -4),
            IVec3::new(5, 2, -1),
            IVec3::new(9, 3, -3),
        ] {
            let mut mean = 0.0;
            for o in 0..8 {
                mean += g.value(ijk * 2 + corner(o)) / 8.0;
            }
            assert!(
                (c.value(ijk) - mean).abs() < 1e-6,
                "{ijk}: {} {mean}",
                c.value(ijk)
            );
        }
    }

    #[test]
    fn tiles_halve_into_tiles() {
        let mut g = SparseGrid::new(Default::default(), 0.0);
        g.insert_tile(TileLevel::Node, IVec3::new(128, 0, 0), 0.5);
        g.insert_tile(TileLevel::Root, IVec3::new(4096, 0, 0), 1.0);
        let c = coarsen(&g);
        assert_eq!(c.active_voxels(), g.active_voxels() / 8);
        assert_eq!(c.value(IVec3::new(64, 63, 0)), 0.5);
        assert_eq!(c.value(IVec3::new(2048 + 2047, 0, 100)), 1.0);
        assert_eq!(c.value(IVec3::new(128, 0, 0)), 0.0);
    }

    #[test]
    fn level_coordinates_map_centres() {
        // Fine voxels 2 and 3 average into coarse voxel 1, whose centre is fine 2.5.
        assert_eq!(to_level(Vec3::splat(2.5), 1), Vec3::ONE);
        assert_eq!(to_level(Vec3::splat(5.5), 2), Vec3::ONE);
    }
}
