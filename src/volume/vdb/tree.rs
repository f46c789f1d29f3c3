//! The tree of one grid (docs/vdb-format.md, "Tree topology"): root tiles and children, internal-5 and internal-4 nodes
//! with their tiles, then the leaf buffers — read straight into a [`SparseGrid`]. Node counts are
//! checked against the bytes that remain before anything is allocated for them; leaf values are
//! decoded in parallel once the buffer section's layout is known.

use glam::IVec3;
use hashbrown::HashSet;
use rayon::prelude::*;

use super::codec::{decode_block, parse_block, ValueBlock, ValueFormat};
use super::cursor::Cursor;
use super::VdbError;
use crate::volume::grid::{Leaf, SparseGrid, TileLevel, Transform, LEAF_VOXELS};

/// Bytes of a leaf's value mask.
const LEAF_MASK_BYTES: usize = LEAF_VOXELS / 8;
/// Least bytes a leaf occupies in the buffer section: its mask copy and a meta byte.
const LEAF_MIN_BUFFER: usize = LEAF_MASK_BYTES + 1;
/// Root tiles and children sit on a 4096³ lattice; the largest origin keeps the tile in i32 space.
const ROOT_DIM: i32 = 4096;
const MAX_ROOT_ORIGIN: i64 = (1i64 << 31) - ROOT_DIM as i64;
/// Leaves decoded per parallel batch: bounds the transient memory to one batch of values.
const DECODE_BATCH: usize = 8192;

/// Where topology and buffers must end, when the file has grid offsets.
pub struct Bounds {
    pub block_pos: Option<usize>,
    pub end_pos: Option<usize>,
}

struct PendingLeaf {
    origin: IVec3,
    mask: [u64; 8],
}

fn read_mask(cur: &mut Cursor, words: usize, what: &str) -> Result<Vec<u64>, VdbError> {
    let bytes = cur.bytes(words * 8, what)?;
    Ok(bytes
        .chunks_exact(8)
        .map(|c| u64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]))
        .collect())
}

fn popcount(mask: &[u64]) -> usize {
    mask.iter().map(|w| w.count_ones() as usize).sum()
}

fn bit(mask: &[u64], n: usize) -> bool {
    mask[n >> 6] >> (n & 63) & 1 == 1
}

/// Assigns an array of `count` decoded values to the active slots of a node with `mask`.
fn scatter_active(mask: &[u64], values: &[f32], slots: usize, mut put: impl FnMut(usize, f32)) {
    if values.len() == slots {
        (0..slots)
            .filter(|&n| bit(mask, n))
            .for_each(|n| put(n, values[n]));
    } else {
        (0..slots)
            .filter(|&n| bit(mask, n))
            .zip(values)
            .for_each(|(n, &v)| put(n, v));
    }
}

struct TreeReader<'a, 'c> {
    cur: &'c mut Cursor<'a>,
    fmt: ValueFormat,
    grid: SparseGrid,
    leaves: Vec<PendingLeaf>,
    scratch: Vec<u8>,
    values: Vec<f32>,
}

impl TreeReader<'_, '_> {
    /// The root's tiles and children (each child an internal-5 node, read recursively): origins
    /// aligned, in range, unique, and the children sorted, as OpenVDB writes them.
    fn root(&mut self, num_tiles: usize, num_children: usize) -> Result<(), VdbError> {
        let mut origins = HashSet::new();
        let check_origin = |o: IVec3, origins: &mut HashSet<IVec3>| -> Result<(), VdbError> {
            let aligned = (o.x | o.y | o.z) & (ROOT_DIM - 1) == 0;
            let in_range = o.to_array().iter().all(|&c| (c as i64) <= MAX_ROOT_ORIGIN);
            if !aligned || !in_range {
                return Err(VdbError::new(format!(
                    "root node origin {o} is not a valid 4096³ origin"
                )));
            }
            if !origins.insert(o) {
                return Err(VdbError::new(format!("root node origin {o} appears twice")));
            }
            Ok(())
        };
        for _ in 0..num_tiles {
            let origin = self.cur.coord("root tile origin")?;
            check_origin(origin, &mut origins)?;
            let value = self.fmt.read_full(self.cur, "root tile value")?;
            if self.cur.bool("root tile active flag")? {
                self.grid.insert_tile(TileLevel::Root, origin, value);
            }
        }
        let mut previous: Option<IVec3> = None;
        for _ in 0..num_children {
            let origin = self.cur.coord("root child origin")?;
            check_origin(origin, &mut origins)?;
            if previous.is_some_and(|p| p.to_array() >= origin.to_array()) {
                return Err(VdbError::new(format!(
                    "root children are not sorted by origin (at {origin})"
                )));
            }
            previous = Some(origin);
            self.internal(origin, 5)?;
        }
        Ok(())
    }

    /// Reads an internal node with log2 dimension `log2` (5 or 4) at `origin`.
    fn internal(&mut self, origin: IVec3, log2: u32) -> Result<(), VdbError> {
        let slots = 1usize << (3 * log2);
        let child_log2 = if log2 == 5 { 7 } else { 3 };
        let child_mask = read_mask(self.cur, slots / 64, "internal node child mask")?;
        let value_mask = read_mask(self.cur, slots / 64, "internal node value mask")?;
        if child_mask.iter().zip(&value_mask).any(|(c, v)| c & v != 0) {
            return Err(VdbError::new(format!(
                "internal node at {origin}: a slot is both a child and an active tile"
            )));
        }
        let children = popcount(&child_mask);
        let min_child = if log2 == 5 {
            2 * 512 + 1
        } else {
            LEAF_MASK_BYTES
        };
        if children.saturating_mul(min_child) > self.cur.remaining() {
            return Err(VdbError::new(format!(
                "internal node at {origin} claims {children} children, more than the file can hold"
            )));
        }
        let block = parse_block(self.cur, slots, popcount(&value_mask), &self.fmt)?;
        decode_block(&block, &self.fmt, &mut self.scratch, &mut self.values)?;
        let level = if log2 == 5 {
            TileLevel::Node
        } else {
            TileLevel::Block
        };
        let local = |n: usize| {
            let n = n as i32;
            let m = (1 << log2) - 1;
            IVec3::new(n >> (2 * log2), (n >> log2) & m, n & m) << child_log2
        };
        let grid = &mut self.grid;
        scatter_active(&value_mask, &self.values, slots, |n, v| {
            grid.insert_tile(level, origin + local(n), v)
        });
        for n in (0..slots).filter(|&n| bit(&child_mask, n)) {
            let child = origin + local(n);
            if log2 == 5 {
                self.internal(child, 4)?;
            } else {
                let m = read_mask(self.cur, 8, "leaf value mask")?;
                let mut mask = [0u64; 8];
                mask.copy_from_slice(&m);
                self.leaves.push(PendingLeaf {
                    origin: child,
                    mask,
                });
            }
        }
        Ok(())
    }
}

/// Reads one grid's topology and buffers from `cur` into a sparse grid.
pub fn read_tree(
    cur: &mut Cursor,
    fmt: ValueFormat,
    transform: Transform,
    bounds: &Bounds,
) -> Result<SparseGrid, VdbError> {
    let buffer_count = cur.i32("buffer count")?;
    if buffer_count != 1 {
        return Err(VdbError::new(format!(
            "buffer count is {buffer_count}, expected 1"
        )));
    }
    let background = fmt.read_full(cur, "background value")?;
    let num_tiles = cur.u32("root tile count")? as usize;
    let num_children = cur.u32("root child count")? as usize;
    let tile_bytes = 12 + fmt.full_size() + 1;
    let child_bytes = 12 + 2 * 4096 + 1;
    let need = (num_tiles as u64) * tile_bytes as u64 + (num_children as u64) * child_bytes as u64;
    if need > cur.remaining() as u64 {
        return Err(VdbError::new(format!(
            "root claims {num_tiles} tiles and {num_children} children, more than the file holds"
        )));
    }
    let mut reader = TreeReader {
        cur,
        fmt,
        grid: SparseGrid::new(transform, background),
        leaves: Vec::new(),
        scratch: Vec::new(),
        values: Vec::new(),
    };
    reader.root(num_tiles, num_children)?;
    if let Some(b) = bounds.block_pos {
        if reader.cur.pos() != b {
            return Err(VdbError::new(format!(
                "topology ends at offset {}, but the grid says its buffers start at {b}",
                reader.cur.pos()
            )));
        }
    }
    // Every leaf needs at least a mask copy and a meta byte in the buffers: check that before the
    // 2 KiB of values per leaf are allocated.
    if reader.leaves.len().saturating_mul(LEAF_MIN_BUFFER) > reader.cur.remaining() {
        return Err(VdbError::new(format!(
            "{} leaves cannot fit in the {} bytes left for their buffers",
            reader.leaves.len(),
            reader.cur.remaining()
        )));
    }
    let TreeReader {
        cur,
        mut grid,
        leaves,
        ..
    } = reader;
    read_leaf_buffers(cur, &mut grid, &leaves, &fmt, bounds)?;
    Ok(grid)
}

/// The leaves' value buffers, after the topology: each buffer's mask must repeat the topology's,
/// and the buffers must end where the grid says; then decoded in parallel batches.
fn read_leaf_buffers(
    cur: &mut Cursor,
    grid: &mut SparseGrid,
    leaves: &[PendingLeaf],
    fmt: &ValueFormat,
    bounds: &Bounds,
) -> Result<(), VdbError> {
    let background = grid.background;
    let mut blocks: Vec<ValueBlock> = Vec::with_capacity(leaves.len());
    for leaf in leaves {
        let m = read_mask(cur, 8, "leaf buffer mask")?;
        if m[..] != leaf.mask[..] {
            return Err(VdbError::new(format!(
                "leaf at {}: buffer mask differs from the topology mask",
                leaf.origin
            )));
        }
        blocks.push(parse_block(cur, LEAF_VOXELS, popcount(&leaf.mask), fmt)?);
    }
    if let Some(e) = bounds.end_pos {
        if cur.pos() != e {
            return Err(VdbError::new(format!(
                "leaf buffers end at offset {}, but the grid says it ends at {e}",
                cur.pos()
            )));
        }
    }
    for (leaf_batch, block_batch) in leaves.chunks(DECODE_BATCH).zip(blocks.chunks(DECODE_BATCH)) {
        // Decoded, masked and measured in parallel; added to the grid in file order.
        let decoded: Vec<Box<Leaf>> = leaf_batch
            .par_iter()
            .zip(block_batch)
            .map_init(
                || (Vec::new(), Vec::new()),
                |(scratch, values), (leaf, block)| {
                    decode_block(block, fmt, scratch, values)?;
                    let mut out = [background; LEAF_VOXELS];
                    scatter_active(&leaf.mask, values, LEAF_VOXELS, |n, v| out[n] = v);
                    Ok(Box::new(Leaf::new(leaf.origin, leaf.mask, out, background)))
                },
            )
            .collect::<Result<_, VdbError>>()?;
        for leaf in decoded {
            grid.push_leaf(*leaf);
        }
    }
    Ok(())
}
