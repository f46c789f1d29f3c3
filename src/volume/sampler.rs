//! A trilinear sampler for marching: [`SparseGrid::sample_index`] with a memory of the 2×2×2
//! blocks around the last sample. Consecutive steps of a ray mostly stay in one block, so the hash
//! lookups (one for the leaf map plus up to three for tiles, per block) are paid once per block
//! crossed instead of once — or eight times at a block edge — per sample. Results are bit-identical
//! to `sample_index`: same corner values, same blend. It needs no setup: [`crate::volume::bricks`] falls back to
//! it outside the bricks.

use glam::{IVec3, Vec3};

use crate::math::floor::floor_split;

use crate::volume::grid::{
    corner, corner_offsets, trilinear, Block, Leaf, SparseGrid, LEAF_DIM, LEAF_LOG2,
};

/// Offset of corner `n` (bits x, y, z as [`corner`]) from a cell's lower corner in a leaf.
const LEAF_CORNERS: [usize; 8] = corner_offsets(LEAF_DIM as usize);

/// One ray's sampler; cheap to create, not shared between threads.
pub struct BlockSampler<'a> {
    grid: &'a SparseGrid,
    /// Key of the block holding the lower corner of the last sample; the cache covers
    /// `base + {0,1}³`.
    base: IVec3,
    blocks: [Option<Block<'a>>; 8],
}

impl<'a> BlockSampler<'a> {
    pub fn new(grid: &'a SparseGrid) -> Self {
        BlockSampler {
            grid,
            // No real block key is this far out (keys are voxel >> 3), so the first sample refills.
            base: IVec3::MIN,
            blocks: [None; 8],
        }
    }

    /// The block `base + d`, `d ∈ {0,1}³`, looked up once.
    #[inline]
    fn block(&mut self, d: IVec3) -> Block<'a> {
        let i = (d.x * 4 + d.y * 2 + d.z) as usize;
        let grid = self.grid;
        let key = self.base + d;
        *self.blocks[i].get_or_insert_with(|| grid.block(key))
    }

    /// Trilinear density at an index-space point, exactly as [`SparseGrid::sample_index`].
    #[inline]
    pub fn sample(&mut self, p: Vec3) -> f32 {
        let (c, f) = self.corners(p);
        trilinear(c, f)
    }

    /// The eight values a trilinear sample at `p` blends ([`corner`] order) and its fractions.
    #[inline]
    pub fn corners(&mut self, p: Vec3) -> ([f32; 8], Vec3) {
        let (i0, f) = floor_split(p);
        let key = i0 >> LEAF_LOG2;
        if key != self.base {
            self.base = key;
            self.blocks = [None; 8];
        }
        let mut c = [0.0f32; 8];
        let local = i0 & (LEAF_DIM - 1);
        if local.max_element() < LEAF_DIM - 1 {
            match self.block(IVec3::ZERO) {
                Block::Leaf(leaf) => c = leaf.values.gather(Leaf::slot(i0), &LEAF_CORNERS),
                // Trilinear of eight equal values is that value exactly.
                Block::Constant(v) => c = [v; 8],
            }
        } else {
            for (n, v) in c.iter_mut().enumerate() {
                let ijk = i0 + corner(n);
                *v = match self.block((ijk >> LEAF_LOG2) - key) {
                    Block::Leaf(leaf) => leaf.values.get(Leaf::slot(ijk)),
                    Block::Constant(value) => value,
                };
            }
        }
        (c, f)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::grid::{TileLevel, LEAF_VOXELS};
    use crate::volume::Transform;

    #[test]
    fn f16_leaves_sample_as_their_f32_values_in_half_the_memory() {
        // Values f16 holds exactly (quarters) become f16 leaves; a value it cannot hold (0.1)
        // keeps its leaf f32. Every sample is the f32 grid's, bit for bit.
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        let values = std::array::from_fn(|s| (s % 13) as f32 * 0.25);
        g.insert_leaf(IVec3::ZERO, [u64::MAX; 8], values);
        g.insert_leaf(IVec3::new(8, 0, 0), [0xf0f0_f0f0_f0f0_f0f0; 8], values);
        let mut inexact = values;
        inexact[7] = 0.1;
        g.insert_leaf(IVec3::new(0, 8, 0), [u64::MAX; 8], inexact);
        let mut h = g.clone();
        for leaf in h.leaves_mut() {
            *leaf = leaf.clone().into_f16();
        }
        let held: Vec<usize> = h.leaves().iter().map(|l| l.values.memory_bytes()).collect();
        assert_eq!(held, [1024, 1024, 2048]);
        assert!(h.memory_bytes() < g.memory_bytes());
        let (mut a, mut b) = (BlockSampler::new(&g), BlockSampler::new(&h));
        for n in 0..20_000 {
            let t = n as f32 * 0.011;
            let p = Vec3::new(
                8.0 + 9.0 * t.sin(),
                8.0 + 9.0 * (1.3 * t).cos(),
                4.0 + 5.0 * t.cos(),
            );
            assert_eq!(a.sample(p).to_bits(), b.sample(p).to_bits(), "{p}");
        }
    }

    #[test]
    fn bit_identical_to_sample_index() {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Node, IVec3::new(-128, 0, 0), 0.5);
        g.insert_tile(TileLevel::Block, IVec3::new(8, 0, 0), 2.0);
        let mut values = [0.0; LEAF_VOXELS];
        for (s, v) in values.iter_mut().enumerate() {
            *v = (s % 13) as f32 * 0.25;
        }
        g.insert_leaf(IVec3::ZERO, [u64::MAX; 8], values);
        g.insert_leaf(IVec3::new(0, 8, 0), [0xf0f0_f0f0_f0f0_f0f0; 8], values);
        let mut sampler = BlockSampler::new(&g);
        // A wandering walk that crosses block faces, edges and corners, forwards and backwards.
        let mut p = Vec3::new(-3.0, -1.5, -2.0);
        for n in 0..20_000 {
            let a = n as f32 * 0.013;
            p += Vec3::new(a.sin(), (1.7 * a).cos(), (0.6 * a).sin()) * 0.37;
            p = p.clamp(Vec3::splat(-10.0), Vec3::splat(20.0));
            assert_eq!(
                sampler.sample(p).to_bits(),
                g.sample_index(p).to_bits(),
                "{p}"
            );
        }
    }
}
