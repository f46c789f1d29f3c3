//! The sparse density grid: 8³ leaves and constant tiles kept at their own tree level (never
//! expanded voxel by voxel), keyed in `hashbrown` maps, with the index↔world transform, trilinear
//! sampling, the active bounding box, per-block maxima and a coarse occupancy level for skipping.
//!
//! Conventions (docs/model.md): voxel (i,j,k) holds its value at index point (i,j,k); between centres the
//! density is trilinear; inactive voxels and everything outside the tree take the background value.

use std::sync::OnceLock;

use glam::{DVec3, IVec3, Vec3};
use half::f16;
use half::slice::HalfFloatSliceExt;
use hashbrown::HashMap;
use rayon::prelude::*;

use crate::math::ray::Ray;

/// log2 of the leaf edge: 8³ voxels per leaf, as in OpenVDB's `Tree_*_5_4_3`.
pub const LEAF_LOG2: u32 = 3;
/// Voxels along a leaf edge.
pub const LEAF_DIM: i32 = 1 << LEAF_LOG2;
/// Voxels in a leaf.
pub const LEAF_VOXELS: usize = 1 << (3 * LEAF_LOG2);

/// The tree levels a constant tile can live at, by the log2 of its edge in voxels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TileLevel {
    /// A slot of an internal-4 node: 8³ voxels.
    Block = 3,
    /// A slot of an internal-5 node: 128³ voxels.
    Node = 7,
    /// A root tile: 4096³ voxels.
    Root = 12,
}

impl TileLevel {
    pub const ALL: [TileLevel; 3] = [TileLevel::Block, TileLevel::Node, TileLevel::Root];

    pub const fn log2(self) -> u32 {
        self as u32
    }

    /// Voxels along one edge of a tile at this level.
    pub fn dim(self) -> i64 {
        1i64 << self.log2()
    }

    /// Voxels in one tile at this level.
    pub fn voxel_count(self) -> u64 {
        1u64 << (3 * self.log2())
    }

    fn index(self) -> usize {
        match self {
            TileLevel::Block => 0,
            TileLevel::Node => 1,
            TileLevel::Root => 2,
        }
    }
}

/// Index → world: `world = ijk · scale + translation`, per axis (the scale may be negative).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Transform {
    pub scale: DVec3,
    pub translation: DVec3,
}

impl Default for Transform {
    fn default() -> Self {
        Transform {
            scale: DVec3::ONE,
            translation: DVec3::ZERO,
        }
    }
}

impl Transform {
    pub fn index_to_world(&self, ijk: DVec3) -> DVec3 {
        ijk * self.scale + self.translation
    }

    pub fn world_to_index(&self, world: DVec3) -> DVec3 {
        (world - self.translation) / self.scale
    }

    /// The world ray from `origin` along unit `dir`, in index space with its direction per world
    /// unit: points move to index space, and `t` stays a world distance.
    pub fn ray_to_index(&self, origin: Vec3, dir: Vec3) -> Ray {
        Ray::new(
            self.world_to_index(origin.as_dvec3()),
            dir.as_dvec3() / self.scale,
        )
    }

    /// The edge lengths of one voxel in world units.
    pub fn voxel_size(&self) -> DVec3 {
        self.scale.abs()
    }
}

/// One 8³ leaf: values in OpenVDB's slot order (x major, z fastest) with inactive voxels already
/// set to the background, and the active mask.
#[derive(Clone)]
pub struct Leaf {
    pub origin: IVec3,
    pub mask: [u64; 8],
    pub values: LeafValues,
    /// Largest value of the leaf (active voxels; the background where none is active).
    pub max: f32,
}

/// A leaf's values: f32, or f16 where that is all the source holds (a cache that stores its
/// density as f16), so a render of a big cloud holds its density in half the memory, every value
/// the same f32 it decodes to.
#[derive(Clone)]
pub enum LeafValues {
    F32(Box<[f32; LEAF_VOXELS]>),
    F16(Box<[f16; LEAF_VOXELS]>),
}

impl LeafValues {
    /// The value in `slot`. A single f16 converts in software, inlined: the CPU's conversion,
    /// chosen at run time, costs a call per value.
    #[inline]
    pub fn get(&self, slot: usize) -> f32 {
        match self {
            LeafValues::F32(v) => v[slot],
            LeafValues::F16(v) => v[slot].to_f32_const(),
        }
    }

    /// Every value, in slot order.
    pub fn to_array(&self) -> [f32; LEAF_VOXELS] {
        let mut out = [0.0; LEAF_VOXELS];
        self.copy_to(0, &mut out);
        out
    }

    /// The values of slots `start..start + out.len()`, written to `out`.
    #[inline]
    pub fn copy_to(&self, start: usize, out: &mut [f32]) {
        match self {
            LeafValues::F32(v) => out.copy_from_slice(&v[start..start + out.len()]),
            LeafValues::F16(v) => v[start..start + out.len()].convert_to_f32_slice(out),
        }
    }

    /// The values at `base + offsets[n]`.
    #[inline]
    pub fn gather<const N: usize>(&self, base: usize, offsets: &[usize; N]) -> [f32; N] {
        match self {
            LeafValues::F32(v) => std::array::from_fn(|n| v[base + offsets[n]]),
            LeafValues::F16(v) => std::array::from_fn(|n| v[base + offsets[n]].to_f32_const()),
        }
    }

    /// The f32 values, to change in place (`None`: held as f16).
    pub fn f32_mut(&mut self) -> Option<&mut [f32; LEAF_VOXELS]> {
        match self {
            LeafValues::F32(v) => Some(v),
            LeafValues::F16(_) => None,
        }
    }

    /// Bytes held.
    pub fn memory_bytes(&self) -> usize {
        match self {
            LeafValues::F32(_) => std::mem::size_of::<[f32; LEAF_VOXELS]>(),
            LeafValues::F16(_) => std::mem::size_of::<[f16; LEAF_VOXELS]>(),
        }
    }
}

impl Leaf {
    /// A leaf of `values` in slot order. Inactive voxels take `background`, so sampling never
    /// sees the arbitrary values a writer may leave in them.
    pub fn new(
        origin: IVec3,
        mask: [u64; 8],
        mut values: [f32; LEAF_VOXELS],
        background: f32,
    ) -> Leaf {
        let mut max = f32::NEG_INFINITY;
        for (slot, v) in values.iter_mut().enumerate() {
            if mask[slot >> 6] >> (slot & 63) & 1 == 1 {
                max = max.max(*v);
            } else {
                *v = background;
            }
        }
        if max == f32::NEG_INFINITY {
            max = background;
        }
        Leaf {
            origin,
            mask,
            values: LeafValues::F32(Box::new(values)),
            max,
        }
    }

    /// This leaf with its values held as f16 when each is one exactly (else as it is): the same
    /// values in half the memory.
    pub fn into_f16(self) -> Leaf {
        let LeafValues::F32(v) = &self.values else {
            return self;
        };
        let mut half = [f16::ZERO; LEAF_VOXELS];
        half.convert_from_f32_slice(&v[..]);
        let mut back = [0.0f32; LEAF_VOXELS];
        half.convert_to_f32_slice(&mut back);
        if back
            .iter()
            .zip(v.iter())
            .any(|(b, f)| b.to_bits() != f.to_bits())
        {
            return self;
        }
        Leaf {
            values: LeafValues::F16(Box::new(half)),
            ..self
        }
    }

    /// The slot of voxel `ijk` (which must lie in this leaf).
    #[inline]
    pub fn slot(ijk: IVec3) -> usize {
        let l = ijk & (LEAF_DIM - 1);
        ((l.x << (2 * LEAF_LOG2)) | (l.y << LEAF_LOG2) | l.z) as usize
    }

    pub fn is_active(&self, slot: usize) -> bool {
        Leaf::is_set(&self.mask, slot)
    }

    /// Whether `slot`'s bit is set in an active-voxel mask (before a leaf is built from it).
    pub fn is_set(mask: &[u64; 8], slot: usize) -> bool {
        mask[slot >> 6] >> (slot & 63) & 1 == 1
    }

    pub fn active_count(&self) -> u32 {
        self.mask.iter().map(|w| w.count_ones()).sum()
    }
}

/// What covers one 8³ block of index space.
#[derive(Clone, Copy)]
pub enum Block<'a> {
    Leaf(&'a Leaf),
    /// A constant region (a tile at any level, or the background).
    Constant(f32),
}

/// Summary statistics over the active values, for `info` and for tests against OpenVDB.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ValueStats {
    pub min: f32,
    pub max: f32,
    /// Σ over active voxels, a tile counting value × its voxel count.
    pub sum: f64,
}

/// A sparse scalar grid: the project's own structure for a VDB grid.
#[derive(Clone)]
pub struct SparseGrid {
    pub transform: Transform,
    pub background: f32,
    leaves: Vec<Leaf>,
    /// Leaf index by leaf key (`origin >> 3`).
    leaf_index: HashMap<IVec3, u32>,
    /// Active tiles per level, value by key (`origin >> level`).
    tiles: [HashMap<IVec3, f32>; 3],
    /// Coarse occupancy: the largest value inside each 128³ node (key `origin >> 7`), leaves and
    /// tiles alike, so a ray can skip a whole empty node in one step.
    node_max: HashMap<IVec3, f32>,
    /// [`SparseGrid::value_stats`] and [`SparseGrid::active_bbox`] once asked, until the grid
    /// changes: each is a pass over every active voxel, and a render from a cache asked for them
    /// five times before its first ray (framing, warnings, the march's support).
    stats: OnceLock<Option<ValueStats>>,
    bbox: OnceLock<Option<(IVec3, IVec3)>>,
}

impl SparseGrid {
    pub fn new(transform: Transform, background: f32) -> Self {
        SparseGrid {
            transform,
            background,
            leaves: Vec::new(),
            leaf_index: HashMap::new(),
            tiles: Default::default(),
            node_max: HashMap::new(),
            stats: OnceLock::new(),
            bbox: OnceLock::new(),
        }
    }

    /// Forgets the summaries of the grid as it was ([`SparseGrid::value_stats`]): every change
    /// goes through here.
    fn changed(&mut self) {
        self.stats = OnceLock::new();
        self.bbox = OnceLock::new();
    }

    /// Room for `n` more leaves, so adding a known number of them moves none.
    pub fn reserve_leaves(&mut self, n: usize) {
        self.leaves.reserve_exact(n);
        self.leaf_index.reserve(n);
    }

    /// Adds a leaf; `values` in slot order ([`Leaf::new`]).
    pub fn insert_leaf(&mut self, origin: IVec3, mask: [u64; 8], values: [f32; LEAF_VOXELS]) {
        let leaf = Leaf::new(origin, mask, values, self.background);
        self.push_leaf(leaf);
    }

    /// Adds a leaf made by [`Leaf::new`] with this grid's background (a reader makes them in
    /// parallel, then adds them in order).
    pub fn push_leaf(&mut self, leaf: Leaf) {
        self.changed();
        let key = leaf.origin >> LEAF_LOG2;
        self.leaf_index.insert(key, self.leaves.len() as u32);
        self.raise_node_max(leaf.origin >> 7, leaf.max);
        self.leaves.push(leaf);
    }

    /// Adds an active constant tile at its own level (inactive tiles are background and not kept).
    pub fn insert_tile(&mut self, level: TileLevel, origin: IVec3, value: f32) {
        self.changed();
        self.tiles[level.index()].insert(origin >> level.log2() as i32, value);
        if level != TileLevel::Root {
            self.raise_node_max(origin >> 7, value);
        }
    }

    fn raise_node_max(&mut self, key: IVec3, value: f32) {
        let m = self.node_max.entry(key).or_insert(value);
        *m = m.max(value);
    }

    pub fn leaves(&self) -> &[Leaf] {
        &self.leaves
    }

    /// A copy of this grid with each leaf made anew by `f` (same origin and mask, in the same
    /// order), and the node maxima of what it makes.
    pub fn map_leaves(&self, f: impl Fn(&Leaf) -> Leaf + Sync + Send) -> SparseGrid {
        let leaves: Vec<Leaf> = self.leaves.par_iter().map(f).collect();
        let mut grid = SparseGrid::new(self.transform, self.background);
        grid.reserve_leaves(leaves.len());
        for level in TileLevel::ALL {
            for (origin, value) in self.tiles(level) {
                grid.insert_tile(level, origin, value);
            }
        }
        for leaf in leaves {
            grid.push_leaf(leaf);
        }
        grid
    }

    /// Clamps negative tile values to zero (a density cannot be negative).
    pub fn clamp_negative_tiles(&mut self) {
        self.changed();
        for map in self.tiles.iter_mut() {
            map.values_mut().for_each(|v| *v = v.max(0.0));
        }
        self.node_max.values_mut().for_each(|v| *v = v.max(0.0));
    }

    pub fn leaves_mut(&mut self) -> &mut [Leaf] {
        self.changed();
        &mut self.leaves
    }

    /// Active tiles at one level: (origin, value).
    pub fn tiles(&self, level: TileLevel) -> impl Iterator<Item = (IVec3, f32)> + '_ {
        let shift = level.log2() as i32;
        self.tiles[level.index()]
            .iter()
            .map(move |(k, v)| (*k << shift, *v))
    }

    pub fn tile_count(&self) -> u64 {
        self.tiles.iter().map(|t| t.len() as u64).sum()
    }

    pub fn leaf_count(&self) -> usize {
        self.leaves.len()
    }

    pub fn active_voxels(&self) -> u64 {
        let leaf: u64 = self.leaves.iter().map(|l| l.active_count() as u64).sum();
        let tile: u64 = TileLevel::ALL
            .iter()
            .map(|lvl| self.tiles[lvl.index()].len() as u64 * lvl.voxel_count())
            .sum();
        leaf + tile
    }

    pub fn is_empty(&self) -> bool {
        self.active_voxels() == 0
    }

    /// Inclusive index bounding box of the active voxels and tiles; `None` when nothing is active.
    pub fn active_bbox(&self) -> Option<(IVec3, IVec3)> {
        *self.bbox.get_or_init(|| self.bbox_where(|_| true))
    }

    /// Inclusive index bounding box of the active voxels and tiles whose value is at least
    /// `threshold`; `None` when there are none.
    pub fn bbox_above(&self, threshold: f32) -> Option<(IVec3, IVec3)> {
        self.bbox_where(|v| v >= threshold)
    }

    fn bbox_where(&self, keep: impl Fn(f32) -> bool + Sync) -> Option<(IVec3, IVec3)> {
        use rayon::prelude::*;
        // Leaves in parallel: min and max give the same box in any order.
        let (mut lo, mut hi) = self
            .leaves
            .par_iter()
            .map(|leaf| {
                let (mut lo, mut hi) = (IVec3::MAX, IVec3::MIN);
                for slot in 0..LEAF_VOXELS {
                    if leaf.is_active(slot) && keep(leaf.values.get(slot)) {
                        let p = leaf.origin + slot_offset(slot);
                        lo = lo.min(p);
                        hi = hi.max(p);
                    }
                }
                (lo, hi)
            })
            .reduce(
                || (IVec3::MAX, IVec3::MIN),
                |(a, b), (c, d)| (a.min(c), b.max(d)),
            );
        for level in TileLevel::ALL {
            for (origin, _) in self.tiles(level).filter(|(_, v)| keep(*v)) {
                lo = lo.min(origin);
                // Root tiles reach 4095 past their origin; saturate at the edge of i32 space.
                let far = (origin.as_i64vec3() + glam::I64Vec3::splat(level.dim() - 1))
                    .min(glam::I64Vec3::splat(i32::MAX as i64));
                hi = hi.max(far.as_ivec3());
            }
        }
        (lo.x <= hi.x).then_some((lo, hi))
    }

    /// Min, max and sum over the active values; `None` when nothing is active.
    pub fn value_stats(&self) -> Option<ValueStats> {
        *self.stats.get_or_init(|| self.compute_value_stats())
    }

    fn compute_value_stats(&self) -> Option<ValueStats> {
        let mut s = ValueStats {
            min: f32::INFINITY,
            max: f32::NEG_INFINITY,
            sum: 0.0,
        };
        use rayon::prelude::*;
        // Each leaf's stats in parallel, then added up in leaf order: the same sum on any thread
        // count.
        let per_leaf: Vec<(f32, f32, f64, bool)> = self
            .leaves
            .par_iter()
            .map(|leaf| {
                let (mut min, mut max, mut sum, mut any) =
                    (f32::INFINITY, f32::NEG_INFINITY, 0.0f64, false);
                for slot in 0..LEAF_VOXELS {
                    if leaf.is_active(slot) {
                        let v = leaf.values.get(slot);
                        min = min.min(v);
                        max = max.max(v);
                        sum += v as f64;
                        any = true;
                    }
                }
                (min, max, sum, any)
            })
            .collect();
        let mut any = false;
        for (min, max, sum, a) in per_leaf {
            s.min = s.min.min(min);
            s.max = s.max.max(max);
            s.sum += sum;
            any |= a;
        }
        for level in TileLevel::ALL {
            for (_, v) in self.tiles(level) {
                s.min = s.min.min(v);
                s.max = s.max.max(v);
                s.sum += v as f64 * level.voxel_count() as f64;
                any = true;
            }
        }
        any.then_some(s)
    }

    /// Bytes held by this structure (leaves, tiles, maps), for `info` and memory estimates.
    pub fn memory_bytes(&self) -> usize {
        // A hashbrown entry costs its key and value plus one control byte, at ~87.5 % load.
        fn map_bytes<V>(m: &HashMap<IVec3, V>) -> usize {
            m.capacity() * (std::mem::size_of::<(IVec3, V)>() + 1)
        }
        self.leaves.capacity() * std::mem::size_of::<Leaf>()
            + self
                .leaves
                .iter()
                .map(|l| l.values.memory_bytes())
                .sum::<usize>()
            + map_bytes(&self.leaf_index)
            + self.tiles.iter().map(map_bytes).sum::<usize>()
            + map_bytes(&self.node_max)
    }

    /// What covers the 8³ block with key `key` (= any voxel of it `>> 3`).
    #[inline]
    pub fn block(&self, key: IVec3) -> Block<'_> {
        if let Some(&i) = self.leaf_index.get(&key) {
            return Block::Leaf(&self.leaves[i as usize]);
        }
        Block::Constant(self.tile_value(key << LEAF_LOG2).unwrap_or(self.background))
    }

    /// The active tile covering voxel `ijk`, if any (deepest level first): its level and value.
    fn tile(&self, ijk: IVec3) -> Option<(TileLevel, f32)> {
        TileLevel::ALL.into_iter().find_map(|lvl| {
            self.tiles[lvl.index()]
                .get(&(ijk >> lvl.log2() as i32))
                .map(|&v| (lvl, v))
        })
    }

    /// The value of the active tile covering voxel `ijk`, if any.
    fn tile_value(&self, ijk: IVec3) -> Option<f32> {
        self.tile(ijk).map(|(_, v)| v)
    }

    /// The level of the active tile covering voxel `ijk`, if any.
    pub fn tile_level(&self, ijk: IVec3) -> Option<TileLevel> {
        self.tile(ijk).map(|(lvl, _)| lvl)
    }

    /// The value at voxel `ijk` (background where nothing active is).
    pub fn value(&self, ijk: IVec3) -> f32 {
        match self.block(ijk >> LEAF_LOG2) {
            Block::Leaf(leaf) => leaf.values.get(Leaf::slot(ijk)),
            Block::Constant(v) => v,
        }
    }

    /// Largest value inside the 128³ node `key` (= voxel `>> 7`), the coarse occupancy level.
    pub fn node_max(&self, key: IVec3) -> f32 {
        let root = self.tiles[TileLevel::Root.index()]
            .get(&(key >> 5))
            .copied();
        match (self.node_max.get(&key).copied(), root) {
            (Some(a), Some(b)) => a.max(b),
            (a, b) => a.or(b).unwrap_or(self.background),
        }
    }

    /// Trilinear density at an index-space point: the reference the tests hold the samplers to
    /// (eight plain lookups); every ray samples through
    /// [`DensityField::sampler`](crate::volume::DensityField::sampler), bit for bit the same.
    #[cfg(test)]
    pub(crate) fn sample_index(&self, p: Vec3) -> f32 {
        let base = p.floor();
        let i0 = base.as_ivec3();
        let c = std::array::from_fn(|n| self.value(i0 + corner(n)));
        trilinear(c, p - base)
    }
}

/// Offset of leaf slot `slot` from the leaf origin.
#[inline]
pub fn slot_offset(slot: usize) -> IVec3 {
    let s = slot as i32;
    IVec3::new(
        s >> (2 * LEAF_LOG2),
        (s >> LEAF_LOG2) & (LEAF_DIM - 1),
        s & (LEAF_DIM - 1),
    )
}

/// Corner `n` of a unit cell, bits (x, y, z) = (n>>2, n>>1, n) & 1.
#[inline]
pub(crate) fn corner(n: usize) -> IVec3 {
    IVec3::new((n >> 2) as i32 & 1, (n >> 1) as i32 & 1, n as i32 & 1)
}

/// Offset of corner `n` (bits x, y, z as [`corner`]) from a cell's lower corner in an x-major
/// box of values whose rows (along z) and columns (along y) are `row` long: a leaf's slots, a
/// brick's values.
pub(crate) const fn corner_offsets(row: usize) -> [usize; 8] {
    let mut o = [0; 8];
    let mut n = 0;
    while n < 8 {
        o[n] = (n >> 2) * row * row + ((n >> 1) & 1) * row + (n & 1);
        n += 1;
    }
    o
}

/// Trilinear blend of corner values `c` (ordered as [`corner`]) at fractions `f`.
#[inline]
pub(crate) fn trilinear(c: [f32; 8], f: Vec3) -> f32 {
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(c[0], c[4], f.x);
    let x01 = lerp(c[1], c[5], f.x);
    let x10 = lerp(c[2], c[6], f.x);
    let x11 = lerp(c[3], c[7], f.x);
    lerp(lerp(x00, x10, f.y), lerp(x01, x11, f.y), f.z)
}

/// A box of 8³ block tiles of density 1 over voxels [0, `size`) (multiples of 8), unit voxels: a
/// uniform slab or cube whose faces lie on block boundaries.
#[cfg(test)]
pub fn block_box(size: IVec3) -> SparseGrid {
    let mut g = SparseGrid::new(Transform::default(), 0.0);
    for x in (0..size.x).step_by(LEAF_DIM as usize) {
        for y in (0..size.y).step_by(LEAF_DIM as usize) {
            for z in (0..size.z).step_by(LEAF_DIM as usize) {
                g.insert_tile(TileLevel::Block, IVec3::new(x, y, z), 1.0);
            }
        }
    }
    g
}

/// Adds `count` leaves of hashed density (0 to 3) at hashed block positions in [0, 112)³, skipping
/// repeats: a sparse, cloud-like test grid with gaps between leaves.
#[cfg(test)]
pub fn add_hashed_leaves(g: &mut SparseGrid, count: u32) {
    use crate::math::hash::hash_unit;
    for n in 0..count {
        let key = IVec3::new(
            (hash_unit(n, 1, 0, 9) * 14.0) as i32,
            (hash_unit(n, 2, 0, 9) * 14.0) as i32,
            (hash_unit(n, 3, 0, 9) * 14.0) as i32,
        );
        if g.leaves().iter().any(|l| l.origin == key * 8) {
            continue;
        }
        let mut values = [0.0; LEAF_VOXELS];
        for (i, v) in values.iter_mut().enumerate() {
            *v = hash_unit(n, i as u32, 4, 9) * 3.0;
        }
        g.insert_leaf(key * 8, [u64::MAX; 8], values);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn leaf_with(grid: &mut SparseGrid, origin: IVec3, voxels: &[(IVec3, f32)]) {
        let mut mask = [0u64; 8];
        let mut values = [0.0; LEAF_VOXELS];
        for &(p, v) in voxels {
            let s = Leaf::slot(p);
            mask[s >> 6] |= 1 << (s & 63);
            values[s] = v;
        }
        grid.insert_leaf(origin, mask, values);
    }

    /// A 2×2×2 grid with value i + 2j + 4k at voxel (i,j,k).
    fn cube() -> SparseGrid {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        let mut vox = Vec::new();
        for n in 0..8 {
            let p = corner(n);
            vox.push((p, (p.x + 2 * p.y + 4 * p.z) as f32));
        }
        leaf_with(&mut g, IVec3::ZERO, &vox);
        g
    }

    #[test]
    fn summaries_follow_every_change_of_the_grid() {
        let mut g = cube();
        let stats = |g: &SparseGrid| g.value_stats().map(|s| (s.min, s.max, s.sum));
        assert_eq!(stats(&g), Some((0.0, 7.0, 28.0)));
        assert_eq!(g.active_bbox(), Some((IVec3::ZERO, IVec3::ONE)));
        g.insert_tile(TileLevel::Block, IVec3::splat(8), 9.0);
        assert_eq!(stats(&g), Some((0.0, 9.0, 28.0 + 9.0 * 512.0)));
        assert_eq!(g.active_bbox(), Some((IVec3::ZERO, IVec3::splat(15))));
        if let Some(v) = g.leaves_mut()[0].values.f32_mut() {
            v.fill(-1.0);
        }
        assert_eq!(stats(&g), Some((-1.0, 9.0, -8.0 + 9.0 * 512.0)));
        g.insert_tile(TileLevel::Block, IVec3::splat(8), -2.0);
        g.clamp_negative_tiles();
        assert_eq!(stats(&g), Some((-1.0, 0.0, -8.0)));
    }

    #[test]
    fn trilinear_on_a_2x2x2_grid() {
        let g = cube();
        // The field is linear (x + 2y + 4z) inside the cube, so trilinear reproduces it exactly.
        assert_eq!(g.sample_index(Vec3::new(0.5, 0.5, 0.5)), 3.5);
        assert_eq!(g.sample_index(Vec3::new(0.25, 0.0, 0.0)), 0.25);
        assert_eq!(g.sample_index(Vec3::new(1.0, 0.5, 0.75)), 1.0 + 1.0 + 3.0);
        // Exactly on a voxel centre: that voxel's value.
        assert_eq!(g.sample_index(Vec3::new(1.0, 1.0, 1.0)), 7.0);
        // Half a voxel outside: blends with the background 0 — (1,1,1)=7 fades to 3.5.
        assert_eq!(g.sample_index(Vec3::new(1.5, 1.0, 1.0)), 3.5);
        assert_eq!(g.active_voxels(), 8);
        assert_eq!(g.active_bbox(), Some((IVec3::ZERO, IVec3::ONE)));
        let s = g.value_stats().unwrap();
        assert_eq!((s.min, s.max, s.sum), (0.0, 7.0, 28.0));
    }

    #[test]
    fn tile_next_to_a_leaf() {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        // An 8³ tile of 2.0 at x∈[0,7], a leaf at x∈[8,15] whose x=8 face holds 1.0.
        g.insert_tile(TileLevel::Block, IVec3::ZERO, 2.0);
        let face: Vec<_> = (0..64)
            .map(|n| (IVec3::new(8, n / 8, n % 8), 1.0))
            .collect();
        leaf_with(&mut g, IVec3::new(8, 0, 0), &face);
        // Between x=7 (tile, 2.0) and x=8 (leaf, 1.0): a quarter of the way → 1.75.
        assert_eq!(g.sample_index(Vec3::new(7.25, 3.0, 3.0)), 1.75);
        // Inside the tile, far from the leaf: the tile value, from one lookup.
        assert_eq!(g.sample_index(Vec3::new(2.3, 4.1, 5.9)), 2.0);
        assert_eq!(g.value(IVec3::new(7, 7, 7)), 2.0);
        assert_eq!(g.value(IVec3::new(9, 0, 0)), 0.0);
        assert_eq!(g.active_voxels(), 512 + 64);
        assert_eq!(g.tile_count(), 1);
        assert_eq!(g.node_max(IVec3::ZERO), 2.0);
        assert_eq!(g.node_max(IVec3::new(1, 0, 0)), 0.0);
        assert_eq!(g.active_bbox(), Some((IVec3::ZERO, IVec3::new(8, 7, 7))));
    }

    #[test]
    fn big_tiles_sample_at_their_own_level() {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Node, IVec3::new(-128, 0, 0), 0.5);
        g.insert_tile(TileLevel::Root, IVec3::new(4096, 0, 0), 0.25);
        assert_eq!(g.value(IVec3::new(-1, 127, 64)), 0.5);
        assert_eq!(g.value(IVec3::new(-129, 0, 0)), 0.0);
        assert_eq!(g.value(IVec3::new(5000, 4095, 0)), 0.25);
        // At x = -0.5, halfway between the tile (x=-1) and empty space (x=0).
        assert_eq!(g.sample_index(Vec3::new(-0.5, 5.0, 5.0)), 0.25);
        assert_eq!(g.node_max(IVec3::new(33, 0, 0)), 0.25);
        assert_eq!(g.active_voxels(), (1u64 << 21) + (1u64 << 36));
        assert_eq!(
            g.active_bbox(),
            Some((IVec3::new(-128, 0, 0), IVec3::new(8191, 4095, 4095)))
        );
    }

    #[test]
    fn transform_round_trip_with_negative_scale() {
        let t = Transform {
            scale: DVec3::new(0.05, -0.1, 0.05),
            translation: DVec3::new(1.0, -0.5, 2.0),
        };
        let w = t.index_to_world(DVec3::new(10.0, 20.0, -4.0));
        assert!((w - DVec3::new(1.5, -2.5, 1.8)).length() < 1e-12);
        assert!((t.world_to_index(w) - DVec3::new(10.0, 20.0, -4.0)).length() < 1e-9);
        assert_eq!(t.voxel_size(), DVec3::new(0.05, 0.1, 0.05));
    }

    #[test]
    fn inactive_voxels_read_as_background() {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        let mut values = [9.0; LEAF_VOXELS];
        values[0] = 1.0;
        let mut mask = [0u64; 8];
        mask[0] = 1;
        g.insert_leaf(IVec3::ZERO, mask, values);
        assert_eq!(g.value(IVec3::ZERO), 1.0);
        assert_eq!(g.value(IVec3::new(0, 0, 1)), 0.0);
        assert_eq!(g.leaves()[0].max, 1.0);
    }
}
