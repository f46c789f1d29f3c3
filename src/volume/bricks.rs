//! Apron bricks for the camera march and the bake's T_ri rays: the trilinear density as plain array
//! indexing.
//!
//! A trilinear sample whose lower corner `floor(p)` lies in block B (key = voxel >> 3) reads the
//! voxels `floor(p) + {0,1}³`, all inside `8B + [0, 8]³`. A *brick* stores exactly those 9³ values
//! (the block's own 8³ plus a one-voxel apron from its upper neighbours, as NanoVDB-style renderers
//! do), so a sample costs one hash lookup per block crossed and then eight loads at fixed offsets,
//! with no per-corner block test. Values come from [`SparseGrid::value`] and blend with
//! `trilinear`, so a sample is bit-identical to [`SparseGrid::sample_index`].
//!
//! **Which blocks.** The blocks within one block of a leaf or an 8³ tile get an entry — the same
//! 3×3×3 dilation the DDA's spans cover (`volume::dda`), so nearly every sample the march takes
//! finds one, and their number follows the active leaves. An entry whose eight corner blocks are
//! one constant (a tile interior, the empty shell above a leaf) keeps just that value — trilinear
//! of eight equal values is that value exactly — and only the others hold a brick. Every other
//! block (empty space, the inside or rim of a 128³ tile) goes to the cached [`BlockSampler`].

use glam::{IVec3, Vec3};
use hashbrown::HashMap;
use rayon::prelude::*;

use crate::math::floor::floor_split;
use crate::volume::dense_box::DenseBox;
use crate::volume::grid::{
    corner, corner_offsets, trilinear, Block, SparseGrid, TileLevel, LEAF_DIM, LEAF_LOG2,
};
use crate::volume::keys::KeyIndex;
use crate::volume::sampler::BlockSampler;

/// Voxels along a brick edge: a leaf plus the apron it shares with its upper neighbours.
const BRICK_DIM: usize = LEAF_DIM as usize + 1;
/// Values in one brick.
const BRICK_VOXELS: usize = BRICK_DIM * BRICK_DIM * BRICK_DIM;
/// One brick's values, x-major like a leaf's slots.
type Brick = [f32; BRICK_VOXELS];
/// Offset of corner `n` (bits x, y, z as [`corner`]) from a cell's lower corner in a brick.
const CORNER_OFFSETS: [usize; 8] = corner_offsets(BRICK_DIM);

/// Values from a cell's lower corner to its upper one in a brick (the last corner offset + 1).
const CELL_REACH: usize = BRICK_DIM * BRICK_DIM + BRICK_DIM + 2;

/// Per cell of a brick (the 8³ whose lower corners lie in its block), whether any of its eight
/// corners is above 0: bit `y·8 + z` of word `x`. A sample in a cell without one is ≤ 0, which
/// the march treats as empty ([`BrickSampler::sample_positive`]); most of the steps the march
/// takes inside the DDA's spans are such samples (measured on the bench cloud, 1920×1080: 11.6 M
/// of 21.4 M), and the bit spares them the eight loads and the blend.
type Positive = [u64; LEAF_DIM as usize];

/// Bytes of one brick: its values and its cells' mask.
const BRICK_BYTES: usize = std::mem::size_of::<Brick>() + std::mem::size_of::<Positive>();

/// What a block's entry holds.
#[derive(Debug, Clone, Copy, PartialEq)]
enum Entry {
    /// Index into [`Bricks::values`].
    Brick(u32),
    /// Every sample with its lower corner in this block is this value.
    Uniform(f32),
}

/// The bricks of one grid, built once per render (or per bake's T_ri) and shared by every ray.
pub struct Bricks {
    entries: KeyIndex<Entry>,
    values: Vec<Brick>,
    /// Per brick, its cells that can sample above 0.
    positive: Vec<Positive>,
    /// 128³ tiles (key = voxel >> 7) and their values. A block whose 2×2×2 window lies inside one
    /// is uniform without an entry of its own: a node tile holds 4096 blocks, and sending their
    /// samples to the fallback sampler doubled the T_ri phase of a tiled 300³ block.
    node_tiles: HashMap<IVec3, f32>,
    /// The value of every block without an entry, when that is known: a block within one of a
    /// leaf or a block tile has an entry, so the window of one without lies in node tiles, root
    /// tiles or the background; with no node or root tile it is the background alone, and empty
    /// space costs a sample no lookup (`None`: the grid has such tiles, or there are no bricks).
    outside: Option<f32>,
}

impl Bricks {
    /// No bricks: every sample goes to the fallback sampler, which reads the same values.
    pub fn empty() -> Bricks {
        Bricks {
            entries: KeyIndex::new(Vec::new()),
            values: Vec::new(),
            positive: Vec::new(),
            node_tiles: HashMap::new(),
            outside: None,
        }
    }

    pub fn build(grid: &SparseGrid) -> Bricks {
        // Which entries are uniform is decided in parallel; the bricks are then numbered in key
        // order (deterministic) and filled in parallel in place, so the build holds the bricks
        // once, never a copy of them.
        let (keys, uniform) = plan(grid);
        let mut entries = Vec::with_capacity(keys.len());
        let mut brick_keys = Vec::new();
        for (&key, u) in keys.iter().zip(&uniform) {
            let entry = match u {
                Some(v) => Entry::Uniform(*v),
                None => {
                    brick_keys.push(key);
                    Entry::Brick(brick_keys.len() as u32 - 1)
                }
            };
            entries.push((key, entry));
        }
        let entries = KeyIndex::new(entries);
        let mut values = vec![[0.0; BRICK_VOXELS]; brick_keys.len()];
        let mut positive = vec![[0; LEAF_DIM as usize]; brick_keys.len()];
        values
            .par_iter_mut()
            .zip(&mut positive)
            .zip(&brick_keys)
            .for_each(|((brick, positive), &key)| {
                fill(&window(grid, key), brick);
                *positive = positive_cells(brick);
            });
        let node_tiles = grid
            .tiles(TileLevel::Node)
            .map(|(origin, v)| (origin >> TileLevel::Node.log2() as i32, v))
            .collect();
        let large_tiles = [TileLevel::Node, TileLevel::Root]
            .iter()
            .any(|&level| grid.tiles(level).next().is_some());
        Bricks {
            entries,
            values,
            positive,
            node_tiles,
            outside: (!large_tiles).then_some(grid.background),
        }
    }

    /// The uniform entry of block `key` when its window lies inside a node tile.
    fn in_node_tile(&self, key: IVec3) -> Option<Entry> {
        // The window key + {0,1}³ stays in the node unless the block is on its upper faces.
        const LAST: i32 = (1 << (TileLevel::Node.log2() - LEAF_LOG2)) - 1;
        let node = key >> (TileLevel::Node.log2() - LEAF_LOG2) as i32;
        if self.node_tiles.is_empty() || (key & LAST).cmpeq(IVec3::splat(LAST)).any() {
            return None;
        }
        self.node_tiles.get(&node).map(|&v| Entry::Uniform(v))
    }

    /// Bytes held: the brick values and cell masks, and the entries' index.
    pub fn memory_bytes(&self) -> usize {
        self.values.capacity() * BRICK_BYTES + self.entries.memory_bytes()
    }

    /// What [`Bricks::build`] will hold for `grid`, from its plan alone (no brick filled).
    pub fn estimate_bytes(grid: &SparseGrid) -> usize {
        let (keys, uniform) = plan(grid);
        uniform.iter().filter(|u| u.is_none()).count() * BRICK_BYTES
            + KeyIndex::<Entry>::bytes_for(&keys)
    }
}

/// The blocks that get an entry: every block within one of a leaf or a block tile, sorted
/// (x-major, as leaves are stored) so neighbouring bricks sit near each other: marked in a
/// [`DenseBox`] when the blocks are compact (its cells come out sorted), else sorted here.
fn keys(grid: &SparseGrid) -> Vec<IVec3> {
    let sources: Vec<IVec3> = grid
        .leaves()
        .iter()
        .map(|l| l.origin)
        .chain(grid.tiles(TileLevel::Block).map(|(o, _)| o))
        .map(|o| o >> LEAF_LOG2 as i32)
        .collect();
    let neighbours =
        |key: IVec3| (0..27).map(move |n| key + IVec3::new(n / 9 - 1, (n / 3) % 3 - 1, n % 3 - 1));
    let (lo, hi) = sources
        .iter()
        .fold((IVec3::MAX, IVec3::MIN), |(a, b), k| (a.min(*k), b.max(*k)));
    let touches = 27 * sources.len() as u64;
    if let Some(mut dense) = DenseBox::new(lo - 1, hi + 1, false, touches) {
        for &key in &sources {
            neighbours(key).for_each(|k| *dense.cell(k) = true);
        }
        return dense.into_cells().filter(|c| c.1).map(|c| c.0).collect();
    }
    let mut keys: Vec<IVec3> = sources.into_iter().flat_map(neighbours).collect();
    keys.par_sort_unstable_by_key(|k| (k.x, k.y, k.z));
    keys.dedup();
    keys
}

/// The blocks that get an entry ([`keys`]) and, for each, its value when it is uniform (`None`:
/// it needs a brick).
fn plan(grid: &SparseGrid) -> (Vec<IVec3>, Vec<Option<f32>>) {
    let keys = keys(grid);
    let uniform = keys
        .par_iter()
        .map(|&key| uniform(&window(grid, key)))
        .collect();
    (keys, uniform)
}

/// The eight blocks a brick at `key` reads: `key + {0,1}³`, ordered as [`corner`].
fn window(grid: &SparseGrid, key: IVec3) -> [Block<'_>; 8] {
    std::array::from_fn(|n| grid.block(key + corner(n)))
}

/// The value of eight blocks that are all the same constant, if they are.
fn uniform(blocks: &[Block; 8]) -> Option<f32> {
    let first = match blocks[0] {
        Block::Constant(v) => v,
        Block::Leaf(_) => return None,
    };
    let same = |b: &Block| matches!(b, Block::Constant(v) if v.to_bits() == first.to_bits());
    blocks.iter().all(same).then_some(first)
}

/// Writes to `out` the 9³ values `8B + [0, 8]³` from block B and its upper neighbours (`blocks`
/// in [`corner`] order), a row along z at a time: the block's eight values, then the apron's one.
fn fill(blocks: &[Block; 8], out: &mut Brick) {
    let dim = LEAF_DIM as usize;
    for (row, out) in out.chunks_exact_mut(BRICK_DIM).enumerate() {
        // The apron (coordinate 8) is coordinate 0 of the next block along that axis.
        let (x, y) = (row / BRICK_DIM, row % BRICK_DIM);
        let n = ((x / dim) << 2) | ((y / dim) << 1);
        let start = ((x % dim) * dim + y % dim) * dim;
        match blocks[n] {
            Block::Leaf(leaf) => leaf.values.copy_to(start, &mut out[..dim]),
            Block::Constant(c) => out[..dim].fill(c),
        }
        out[dim] = match blocks[n | 1] {
            Block::Leaf(leaf) => leaf.values.get(start),
            Block::Constant(c) => c,
        };
    }
}

/// Which cells of `brick` have a corner above 0 ([`Positive`]).
fn positive_cells(brick: &Brick) -> Positive {
    // Per row along z, its values above 0 as bits; a cell's corners are bits z and z + 1 of
    // the rows at (x, y), (x + 1, y), (x, y + 1) and (x + 1, y + 1).
    let mut rows = [0u16; BRICK_DIM * BRICK_DIM];
    for (bits, row) in rows.iter_mut().zip(brick.chunks_exact(BRICK_DIM)) {
        *bits = row
            .iter()
            .enumerate()
            .fold(0, |b, (z, &v)| b | (((v > 0.0) as u16) << z));
    }
    let dim = LEAF_DIM as usize;
    std::array::from_fn(|x| {
        (0..dim).fold(0u64, |word, y| {
            let at = |x: usize, y: usize| rows[x * BRICK_DIM + y];
            let any = at(x, y) | at(x + 1, y) | at(x, y + 1) | at(x + 1, y + 1);
            word | ((((any | (any >> 1)) & 0xFF) as u64) << (y * dim))
        })
    })
}

/// One ray's sampler over [`Bricks`]: the entry of the last block sampled is kept, so the hash
/// lookup is paid once per block crossed.
pub struct BrickSampler<'a> {
    bricks: &'a Bricks,
    fallback: BlockSampler<'a>,
    key: IVec3,
    entry: Option<Entry>,
}

impl<'a> BrickSampler<'a> {
    pub fn new(bricks: &'a Bricks, grid: &'a SparseGrid) -> Self {
        BrickSampler {
            bricks,
            fallback: BlockSampler::new(grid),
            // No real block key is this far out (keys are voxel >> 3), so the first sample looks up.
            key: IVec3::MIN,
            entry: None,
        }
    }

    /// Trilinear density at an index-space point, exactly as [`SparseGrid::sample_index`].
    /// Always inlined into the march's step loop: as a call it spent a quarter of its
    /// instructions saving and restoring registers.
    #[inline(always)]
    pub fn sample(&mut self, p: Vec3) -> f32 {
        self.sample_in::<false>(p)
    }

    /// The density at `p` where it can be above 0, and 0 where it cannot: equal to
    /// [`BrickSampler::sample`] wherever that is above 0, and ≤ 0 wherever that is, read
    /// without a load of the density in a brick's cells whose corners are all ≤ 0
    /// ([`Positive`]). For the march, to which a density ≤ 0 is empty.
    #[inline(always)]
    pub fn sample_positive(&mut self, p: Vec3) -> f32 {
        self.sample_in::<true>(p)
    }

    /// [`BrickSampler::sample`], or with `POSITIVE` [`BrickSampler::sample_positive`].
    #[inline(always)]
    fn sample_in<const POSITIVE: bool>(&mut self, p: Vec3) -> f32 {
        let (i0, f) = floor_split(p);
        self.look_up(i0);
        match self.entry {
            Some(Entry::Brick(b)) => {
                if POSITIVE {
                    let l = (i0 & (LEAF_DIM - 1)).as_uvec3();
                    let word = self.bricks.positive[b as usize][l.x as usize];
                    if word >> (l.y * LEAF_DIM as u32 + l.z) & 1 == 0 {
                        return 0.0;
                    }
                }
                trilinear(self.brick_corners(b, i0), f)
            }
            Some(Entry::Uniform(v)) => v,
            None => self.sample_fallback(p),
        }
    }

    /// The trilinear blends at `p` of the values and of which of them are above 0:
    /// (Σ w·v, Σ w·[v > 0]). A grid that holds a quantity as a value above 0 where it is defined,
    /// and 0 elsewhere, is interpolated over the corners that hold it alone as the first over the
    /// second, read from the same eight loads.
    #[inline]
    pub fn sample_covered(&mut self, p: Vec3) -> (f32, f32) {
        let (i0, f) = floor_split(p);
        self.look_up(i0);
        let c = match self.entry {
            Some(Entry::Brick(b)) => self.brick_corners(b, i0),
            Some(Entry::Uniform(v)) => [v; 8],
            None => {
                let (c, _) = self.fallback.corners(p);
                c
            }
        };
        (
            trilinear(c, f),
            trilinear(c.map(|v| (v > 0.0) as u8 as f32), f),
        )
    }

    /// Makes `entry` that of the block holding voxel `i0`, looked up only when the block changes.
    #[inline(always)]
    fn look_up(&mut self, i0: IVec3) {
        let key = i0 >> LEAF_LOG2;
        if key != self.key {
            self.key = key;
            self.entry = self.bricks.entries.get(key);
        }
    }

    /// The eight values of brick `b` a sample with lower corner `i0` blends ([`corner`] order).
    #[inline(always)]
    fn brick_corners(&self, b: u32, i0: IVec3) -> [f32; 8] {
        let brick = &self.bricks.values[b as usize];
        let l = (i0 & (LEAF_DIM - 1)).as_uvec3();
        let base = (l.x as usize * BRICK_DIM + l.y as usize) * BRICK_DIM + l.z as usize;
        // One bounds check for the cell's whole reach instead of one per corner.
        let cell = &brick[base..base + CELL_REACH];
        std::array::from_fn(|n| cell[CORNER_OFFSETS[n]])
    }

    /// The density at the voxels `lo + [0, dim)` into `out`, x-major (z fastest): a sample at a
    /// voxel is its value, so a brick gives whole rows at once, where sampling each voxel costs a
    /// floor, a block test and a blend.
    pub fn gather(&mut self, lo: IVec3, dim: IVec3, out: &mut [f32]) {
        let hi = lo + dim;
        let (klo, khi) = (lo >> LEAF_LOG2, (hi - 1) >> LEAF_LOG2);
        let at = |v: IVec3| {
            let l = (v - lo).as_uvec3();
            (l.x as usize * dim.y as usize + l.y as usize) * dim.z as usize + l.z as usize
        };
        for kx in klo.x..=khi.x {
            for ky in klo.y..=khi.y {
                for kz in klo.z..=khi.z {
                    let key = IVec3::new(kx, ky, kz);
                    let (blo, bhi) = ((key << LEAF_LOG2).max(lo), ((key + 1) << LEAF_LOG2).min(hi));
                    if key != self.key {
                        self.key = key;
                        self.entry = self.bricks.entries.get(key);
                    }
                    let run = (bhi.z - blo.z) as usize;
                    for x in blo.x..bhi.x {
                        for y in blo.y..bhi.y {
                            let row = IVec3::new(x, y, blo.z);
                            let o = at(row);
                            match self.entry {
                                Some(Entry::Brick(b)) => {
                                    let l = (row & (LEAF_DIM - 1)).as_uvec3();
                                    let s = (l.x as usize * BRICK_DIM + l.y as usize) * BRICK_DIM
                                        + l.z as usize;
                                    out[o..o + run].copy_from_slice(
                                        &self.bricks.values[b as usize][s..s + run],
                                    );
                                }
                                Some(Entry::Uniform(v)) => out[o..o + run].fill(v),
                                None => {
                                    for (z, value) in out[o..o + run].iter_mut().enumerate() {
                                        *value = self.sample((row + IVec3::Z * z as i32).as_vec3());
                                    }
                                }
                            }
                        }
                    }
                }
            }
        }
    }

    /// Samples outside every brick's block (empty space, node tiles): rare along a march, so kept
    /// out of line.
    #[cold]
    #[inline(never)]
    fn sample_fallback(&mut self, p: Vec3) -> f32 {
        // A block of the background, or inside a node tile, becomes a uniform entry for the rest
        // of its samples.
        let uniform = self
            .bricks
            .outside
            .map(Entry::Uniform)
            .or_else(|| self.bricks.in_node_tile(self.key));
        if let Some(entry @ Entry::Uniform(v)) = uniform {
            self.entry = Some(entry);
            return v;
        }
        self.fallback.sample(p)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::grid::LEAF_VOXELS;
    use crate::volume::Transform;

    /// The brick sample at `p` is bit for bit the reference sampler's.
    fn assert_same(sampler: &mut BrickSampler, g: &SparseGrid, p: Vec3) {
        assert_eq!(
            sampler.sample(p).to_bits(),
            g.sample_index(p).to_bits(),
            "{p}"
        );
    }

    #[test]
    fn bit_identical_to_sample_index() {
        // Leaves next to each other, to an 8³ tile, to a 128³ tile and to empty space; a leaf with
        // inactive voxels; a tile with a different value beside another tile. Without the 128³
        // tile, empty space is the background (not 0 here) with no lookup.
        for node_tile in [true, false] {
            let background = if node_tile { 0.0 } else { 0.125 };
            let g = grid_for_identity(node_tile, background);
            let bricks = Bricks::build(&g);
            assert_eq!(bricks.outside, (!node_tile).then_some(background));
            assert!(bricks.memory_bytes() > bricks.values.len() * BRICK_VOXELS * 4);
            assert!(!bricks.values.is_empty());
            let mut sampler = BrickSampler::new(&bricks, &g);
            // A wandering walk that crosses block faces, edges and corners, forwards and backwards.
            let mut p = Vec3::new(-3.0, -1.5, -2.0);
            for n in 0..40_000 {
                let a = n as f32 * 0.013;
                p += Vec3::new(a.sin(), (1.7 * a).cos(), (0.6 * a).sin()) * 0.37;
                p = p.clamp(Vec3::splat(-20.0), Vec3::splat(30.0));
                assert_same(&mut sampler, &g, p);
            }
        }
    }

    #[test]
    fn a_positive_sample_is_the_sample_wherever_that_is_above_0() {
        // Two leaves side by side, mostly 0, with a few voxels above 0 (one on the face the
        // upper brick's apron reads) and a few below, placed with no symmetry between the axes.
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        for (origin, marks) in [
            (
                IVec3::ZERO,
                [(1, 2, 7, 1.0), (7, 0, 3, 0.5), (4, 6, 0, -1.0)],
            ),
            (
                IVec3::new(8, 0, 0),
                [(0, 5, 1, 2.0), (3, 3, 6, -0.5), (6, 7, 2, 0.25)],
            ),
        ] {
            let mut values = [0.0; LEAF_VOXELS];
            for (x, y, z, v) in marks {
                values[(x * 8 + y) * 8 + z] = v;
            }
            g.insert_leaf(origin, [u64::MAX; 8], values);
        }
        let bricks = Bricks::build(&g);
        let mut sampler = BrickSampler::new(&bricks, &g);
        let (mut zero, mut positive) = (0, 0);
        // Every cell of the leaves and one block around them, at a point inside it off its
        // centre.
        for x in -8..24 {
            for y in -8..16 {
                for z in -8..16 {
                    let p = IVec3::new(x, y, z).as_vec3() + Vec3::new(0.3, 0.6, 0.8);
                    let (full, masked) = (sampler.sample(p), sampler.sample_positive(p));
                    match full > 0.0 {
                        true => assert_eq!(masked.to_bits(), full.to_bits(), "{p}"),
                        false => assert!(masked <= 0.0, "{p}: {masked}"),
                    }
                    zero += (masked == 0.0) as u32;
                    positive += (full > 0.0) as u32;
                }
            }
        }
        // Eight cells around each voxel above 0 (no two share one): the rest read 0 or less.
        assert_eq!(positive, 8 * 4);
        assert!(zero > 15_000, "{zero}");
    }

    #[test]
    fn a_gathered_box_holds_the_samples_at_its_voxels() {
        // A box across leaves, 8³ tiles, a 128³ tile and empty space, with corners off the block
        // grid, against one sample per voxel.
        let g = grid_for_identity(true, 0.0);
        let bricks = Bricks::build(&g);
        let mut sampler = BrickSampler::new(&bricks, &g);
        let (lo, dim) = (IVec3::new(-11, -3, -5), IVec3::new(37, 21, 14));
        let mut out = vec![f32::NAN; (dim.x * dim.y * dim.z) as usize];
        sampler.gather(lo, dim, &mut out);
        let mut i = 0;
        for x in 0..dim.x {
            for y in 0..dim.y {
                for z in 0..dim.z {
                    let p = (lo + IVec3::new(x, y, z)).as_vec3();
                    assert_eq!(out[i].to_bits(), g.sample_index(p).to_bits(), "{p}");
                    i += 1;
                }
            }
        }
    }

    fn grid_for_identity(node_tile: bool, background: f32) -> SparseGrid {
        let mut g = SparseGrid::new(Transform::default(), background);
        if node_tile {
            g.insert_tile(TileLevel::Node, IVec3::new(-128, 0, 0), 0.5);
        }
        g.insert_tile(TileLevel::Block, IVec3::new(8, 0, 0), 2.0);
        g.insert_tile(TileLevel::Block, IVec3::new(8, 8, 0), 2.0);
        g.insert_tile(TileLevel::Block, IVec3::new(16, 8, 0), 3.0);
        let mut values = [0.0; LEAF_VOXELS];
        for (s, v) in values.iter_mut().enumerate() {
            *v = (s % 13) as f32 * 0.25;
        }
        g.insert_leaf(IVec3::ZERO, [u64::MAX; 8], values);
        g.insert_leaf(IVec3::new(0, 8, 0), [0xf0f0_f0f0_f0f0_f0f0; 8], values);
        g.insert_leaf(IVec3::new(-8, 0, 0), [u64::MAX; 8], values);
        g
    }

    #[test]
    fn node_tile_interiors_are_uniform_without_entries() {
        // A 128³ tile beside a leaf: its blocks away from the leaf have no entry, yet sample as
        // the tile's value without the fallback, except on the node's upper faces (their window
        // reaches the next node), which the fallback still samples exactly.
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Node, IVec3::ZERO, 0.75);
        g.insert_leaf(IVec3::new(128, 0, 0), [u64::MAX; 8], [2.0; LEAF_VOXELS]);
        let bricks = Bricks::build(&g);
        let inside = IVec3::new(5, 7, 3);
        assert_eq!(bricks.entries.get(inside), None);
        assert_eq!(bricks.in_node_tile(inside), Some(Entry::Uniform(0.75)));
        assert_eq!(bricks.in_node_tile(IVec3::new(15, 7, 3)), None);
        assert_eq!(bricks.in_node_tile(IVec3::new(16, 7, 3)), None);
        let mut sampler = BrickSampler::new(&bricks, &g);
        for p in [
            Vec3::new(44.3, 60.1, 25.9),
            Vec3::new(127.5, 60.1, 25.9),
            Vec3::new(-0.5, 3.0, 3.0),
            Vec3::new(131.2, 3.5, 3.5),
        ] {
            assert_same(&mut sampler, &g, p);
        }
    }

    #[test]
    fn tile_interiors_take_no_brick() {
        // 3×3×3 tiles of 1: entries for them and a one-block shell (5³ = 125). The 2³ blocks whose
        // corner blocks are all tiles keep the value 1, the 61 whose corner blocks are all empty
        // keep 0, and the other 56 a brick.
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        for n in 0..27 {
            let b = IVec3::new(n / 9, (n / 3) % 3, n % 3);
            g.insert_tile(TileLevel::Block, b * LEAF_DIM, 1.0);
        }
        let bricks = Bricks::build(&g);
        assert_eq!((bricks.entries.len(), bricks.values.len()), (125, 56));
        assert_eq!(bricks.entries.get(IVec3::ONE), Some(Entry::Uniform(1.0)));
        assert!(matches!(
            bricks.entries.get(IVec3::splat(2)),
            Some(Entry::Brick(_))
        ));
        assert_eq!(
            bricks.entries.get(IVec3::new(3, 0, -1)),
            Some(Entry::Uniform(0.0))
        );
    }
}
