//! The sparse transfer grid: transfer voxels at 1/K of the density resolution, allocated only where
//! the density is active within a voxel's footprint plus a one-voxel apron, grouped in 4³ tiles
//! found through a [`KeyIndex`]. Per-voxel data (SH coefficients, radiance) lives in flat arrays
//! indexed by the voxel's slot; slots are numbered tile by tile, so each tile's coefficients are
//! contiguous.
//!
//! Transfer voxel `a` sits at density index point `K·a` and its footprint is the density voxels
//! nearest to it, `round(i / K) = a`. Radiance at a density index point `p` is read from the
//! transfer voxels around `p / K` with the transfer's [`super::Basis`]: the eight around it
//! trilinearly, which the apron makes exist wherever density is active, or the 27 around its
//! nearest as quadratic B-splines.

use glam::{IVec3, Vec3};

use super::basis::{window_index, WINDOW};
use crate::volume::grid::{slot_offset, SparseGrid, TileLevel, LEAF_VOXELS};
use crate::volume::keys::KeyIndex;

/// log2 of a tile's edge in transfer voxels: 4³ = 64 voxels, one 64-bit occupancy word.
pub const TILE_LOG2: i32 = 2;
const TILE_DIM: i32 = 1 << TILE_LOG2;
const TILE_VOXELS: usize = 1 << (3 * TILE_LOG2);
/// Marks a tile position with no transfer voxel.
const EMPTY: u32 = u32::MAX;
/// Which transfer voxels exist and where their data lives.
#[derive(Clone)]
pub struct TransferLayout {
    /// Density voxels per transfer voxel along each axis.
    pub k: i32,
    /// Per tile key (`voxel >> TILE_LOG2`), its index in `tile_slots`.
    tiles: KeyIndex<u32>,
    /// Per tile, the slot of each of its 64 voxels or `EMPTY`.
    tile_slots: Vec<[u32; TILE_VOXELS]>,
    /// The transfer-voxel coordinate of every slot, tile by tile.
    voxels: Vec<IVec3>,
}

fn tile_local(v: IVec3) -> usize {
    let l = v & (TILE_DIM - 1);
    ((l.x << (2 * TILE_LOG2)) | (l.y << TILE_LOG2) | l.z) as usize
}

/// The sort key of slots: tile first, then position within the tile.
fn slot_order(v: IVec3) -> ([i32; 3], usize) {
    ((v >> TILE_LOG2).to_array(), tile_local(v))
}

impl TransferLayout {
    /// The transfer voxels for `density` at 1/`k` resolution: every footprint holding an active
    /// density voxel or tile, dilated by one voxel in all 26 directions.
    pub fn build(density: &SparseGrid, k: i32) -> TransferLayout {
        let to_transfer = |i: i32| (i + k / 2).div_euclid(k);
        let mut core: hashbrown::HashSet<IVec3> = hashbrown::HashSet::new();
        for leaf in density.leaves() {
            for slot in 0..LEAF_VOXELS {
                if leaf.is_active(slot) && leaf.values.get(slot) > 0.0 {
                    let p = leaf.origin + slot_offset(slot);
                    core.insert(IVec3::new(
                        to_transfer(p.x),
                        to_transfer(p.y),
                        to_transfer(p.z),
                    ));
                }
            }
        }
        for level in TileLevel::ALL {
            for (origin, value) in density.tiles(level) {
                if value <= 0.0 {
                    continue;
                }
                // A tile covers a box of transfer voxels: visit the box, not the tile's voxels.
                let far = origin.as_i64vec3() + glam::I64Vec3::splat(level.dim() - 1);
                let far = far
                    .min(glam::I64Vec3::splat(i32::MAX as i64 - k as i64))
                    .as_ivec3();
                let (lo, hi) = (origin.map(to_transfer), far.map(to_transfer));
                for x in lo.x..=hi.x {
                    for y in lo.y..=hi.y {
                        for z in lo.z..=hi.z {
                            core.insert(IVec3::new(x, y, z));
                        }
                    }
                }
            }
        }
        let mut all: hashbrown::HashSet<IVec3> = hashbrown::HashSet::with_capacity(core.len() * 2);
        for v in &core {
            for n in 0..27 {
                all.insert(*v + IVec3::new(n / 9 - 1, (n / 3) % 3 - 1, n % 3 - 1));
            }
        }
        // Slots tile by tile, in a fixed order, so a bake is deterministic and tiles contiguous.
        let mut voxels: Vec<IVec3> = all.into_iter().collect();
        voxels.sort_unstable_by_key(|v| slot_order(*v));
        Self::index(k, voxels)
    }

    /// About how many transfer voxels [`TransferLayout::build`] makes for `density` at 1/`k`
    /// resolution, without making them: in time ∝ leaves + tiles, so a volume of billions of voxels
    /// in tiles is answered at once. Each leaf counts the transfer voxels its 8³ box touches, with
    /// the one-voxel apron; each tile the box it covers (its apron is its neighbours' voxels, or a
    /// thin shell). Shared voxels count once per leaf, so this is at most a few times the truth on
    /// scattered leaves, within a few percent on volumes of tiles.
    pub fn estimate_len(density: &SparseGrid, k: i32) -> u64 {
        let to_transfer = |i: i64| (i + k as i64 / 2).div_euclid(k as i64);
        let cells = |origin: IVec3, dim: i64, apron: i64| -> u64 {
            (0..3)
                .map(|a| {
                    let o = origin[a] as i64;
                    (to_transfer(o + dim - 1) - to_transfer(o) + 1 + 2 * apron) as u64
                })
                .product()
        };
        let leaves: u64 = density.leaves().iter().map(|l| cells(l.origin, 8, 1)).sum();
        TileLevel::ALL
            .iter()
            .flat_map(|&level| {
                density
                    .tiles(level)
                    .filter(|(_, v)| *v > 0.0)
                    .map(move |(o, _)| cells(o, level.dim(), 0))
            })
            .fold(leaves, u64::saturating_add)
    }

    /// A layout from voxels already in slot order (as a cache stores them); `None` when they are
    /// not strictly in that order, which also rules out repeats.
    pub fn from_voxels(k: i32, voxels: Vec<IVec3>) -> Option<TransferLayout> {
        let ordered = voxels
            .windows(2)
            .all(|w| slot_order(w[0]) < slot_order(w[1]));
        ordered.then(|| Self::index(k, voxels))
    }

    /// Indexes `voxels`, which are in slot order: each tile's voxels one after another.
    fn index(k: i32, voxels: Vec<IVec3>) -> TransferLayout {
        let mut keys: Vec<(IVec3, u32)> = Vec::new();
        let mut tile_slots: Vec<[u32; TILE_VOXELS]> = Vec::new();
        for (slot, v) in voxels.iter().enumerate() {
            let key = *v >> TILE_LOG2;
            if keys.last().is_none_or(|&(last, _)| last != key) {
                keys.push((key, tile_slots.len() as u32));
                tile_slots.push([EMPTY; TILE_VOXELS]);
            }
            if let Some(tile) = tile_slots.last_mut() {
                tile[tile_local(*v)] = slot as u32;
            }
        }
        TransferLayout {
            k,
            tiles: KeyIndex::new(keys),
            tile_slots,
            voxels,
        }
    }

    /// Number of transfer voxels.
    pub fn len(&self) -> usize {
        self.voxels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.voxels.is_empty()
    }

    pub fn tile_count(&self) -> usize {
        self.tile_slots.len()
    }

    /// Transfer-voxel coordinates, by slot.
    pub fn voxels(&self) -> &[IVec3] {
        &self.voxels
    }

    /// The slot of transfer voxel `v`, if it exists.
    #[inline]
    pub fn slot(&self, v: IVec3) -> Option<usize> {
        let s = self.tile_slots[self.tiles.get(v >> TILE_LOG2)? as usize][tile_local(v)];
        (s != EMPTY).then_some(s as usize)
    }

    /// The slots of the nodes `b + [0, edge)³` a point reads ([`super::Basis::window`]; `edge` ≤
    /// [`super::basis::MAX_EDGE`]), node `b + (x, y, z)` at [`window_index`], `missing` where a
    /// node has no transfer voxel and in the entries past `edge`³; `None` when no node has.
    #[inline]
    pub fn window(&self, b: IVec3, edge: usize, missing: u32) -> Option<[u32; WINDOW]> {
        let mut slots = [missing; WINDOW];
        let mut any = false;
        for x in 0..edge {
            for y in 0..edge {
                for z in 0..edge {
                    if let Some(s) = self.slot(b + IVec3::new(x as i32, y as i32, z as i32)) {
                        slots[window_index(edge, x, y, z)] = s as u32;
                        any = true;
                    }
                }
            }
        }
        any.then_some(slots)
    }

    /// Density index-space position of transfer voxel `v`.
    pub fn position(&self, v: IVec3) -> Vec3 {
        (v * self.k).as_vec3()
    }

    /// Bytes of the layout itself (not of the per-voxel data).
    pub fn memory_bytes(&self) -> usize {
        self.tiles.memory_bytes()
            + self.tile_slots.capacity() * TILE_VOXELS * 4
            + self.voxels.capacity() * std::mem::size_of::<IVec3>()
    }

    /// The eight transfer voxels around density index point `p` with their trilinear weights;
    /// a missing voxel gets slot `None` (its data reads as zero).
    #[inline]
    pub fn corners(&self, p: Vec3) -> [(Option<usize>, f32); 8] {
        let q = p / self.k as f32;
        let base = q.floor();
        let f = q - base;
        let b = base.as_ivec3();
        std::array::from_fn(|n| {
            let c = IVec3::new((n >> 2) as i32 & 1, (n >> 1) as i32 & 1, n as i32 & 1);
            let w = |bit: i32, t: f32| if bit == 1 { t } else { 1.0 - t };
            (self.slot(b + c), w(c.x, f.x) * w(c.y, f.y) * w(c.z, f.z))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::Transform;

    #[test]
    fn footprint_and_apron() {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        let mut values = [0.0; LEAF_VOXELS];
        let mut mask = [0u64; 8];
        // One active voxel at index (3, 0, 0): nearest transfer voxel at K=6 is round(3/6) = 1
        // (3 + 3).div_euclid(6) = 1, so the core is (1,0,0) and the apron 3×3×3 around it.
        let s = crate::volume::grid::Leaf::slot(IVec3::new(3, 0, 0));
        mask[s >> 6] |= 1 << (s & 63);
        values[s] = 1.0;
        g.insert_leaf(IVec3::ZERO, mask, values);
        let layout = TransferLayout::build(&g, 6);
        assert_eq!(layout.len(), 27);
        assert!(layout.slot(IVec3::new(1, 0, 0)).is_some());
        assert!(layout.slot(IVec3::new(0, -1, 1)).is_some());
        assert!(layout.slot(IVec3::new(3, 0, 0)).is_none());
        // Every point near the active voxel finds all eight interpolation corners.
        for p in [Vec3::new(2.5, 0.4, -0.5), Vec3::new(3.5, 0.0, 0.0)] {
            assert!(layout.corners(p).iter().all(|(s, _)| s.is_some()));
        }
        let w: f32 = layout
            .corners(Vec3::new(4.0, 1.0, 2.0))
            .iter()
            .map(|c| c.1)
            .sum();
        assert!((w - 1.0).abs() < 1e-6);
    }

    #[test]
    fn tiles_are_not_expanded_voxel_by_voxel() {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Node, IVec3::ZERO, 1.0);
        let layout = TransferLayout::build(&g, 8);
        // Index 0..127 maps to transfer voxels 0..16 (round(127/8) = 16), plus the apron.
        assert_eq!(layout.len(), 19usize.pow(3));
        let slots: Vec<usize> = layout
            .voxels()
            .iter()
            .map(|v| layout.slot(*v).unwrap())
            .collect();
        assert!(slots.iter().enumerate().all(|(i, s)| i == *s));
    }
}
