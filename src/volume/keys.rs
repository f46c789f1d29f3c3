//! A map from block keys (integer 3-vectors: a voxel's block, a shadow brick, a transfer tile) to
//! small values, read once per block a ray crosses: a dense table over the keys' bounding box
//! where that box is compact, as the keys of a cloud's blocks are, so a lookup is a bounds test
//! and one load; a hash map where it is not (blocks scattered over a huge domain).

use glam::IVec3;
use hashbrown::HashMap;

/// A dense table may hold up to this many cells per key: at 4 bytes a cell, plus the value, no
/// more than a hash map's slot per key. A cloud's blocks fill a third to a half of their box.
const DENSE_CELLS_PER_KEY: u64 = 4;
/// A dense cell without a key.
const ABSENT: u32 = u32::MAX;
/// Boxes up to this many cells are always dense (a table this small costs nothing).
const DENSE_MIN_CELLS: u64 = 1 << 12;

/// Key → value, read-only once built.
#[derive(Clone)]
pub struct KeyIndex<V: Copy> {
    table: Table<V>,
}

#[derive(Clone)]
enum Table<V> {
    /// Row-major over [lo, lo + dims) (z fastest), each cell the index of its key's value.
    Dense {
        lo: IVec3,
        dims: [u32; 3],
        cells: Vec<u32>,
        values: Vec<V>,
    },
    Sparse(HashMap<IVec3, V>),
}

impl<V: Copy> KeyIndex<V> {
    /// Indexes `pairs`; a key given twice keeps its last value.
    pub fn new(pairs: Vec<(IVec3, V)>) -> KeyIndex<V> {
        let Some(cells) = dense_cells(pairs.iter().map(|p| p.0), pairs.len()) else {
            return KeyIndex {
                table: Table::Sparse(pairs.into_iter().collect()),
            };
        };
        let (lo, dims) = cells;
        let mut table = vec![ABSENT; dims.iter().map(|&d| d as usize).product()];
        let mut values = Vec::with_capacity(pairs.len());
        for (key, value) in pairs {
            // Every key lies in the box made of them.
            let cell = &mut table[dense_at(key - lo, dims).unwrap_or_default()];
            match *cell {
                ABSENT => {
                    *cell = values.len() as u32;
                    values.push(value);
                }
                at => values[at as usize] = value,
            }
        }
        KeyIndex {
            table: Table::Dense {
                lo,
                dims,
                cells: table,
                values,
            },
        }
    }

    /// The value of `key`, if it has one.
    #[inline(always)]
    pub fn get(&self, key: IVec3) -> Option<V> {
        match &self.table {
            Table::Dense {
                lo,
                dims,
                cells,
                values,
            } => match cells[dense_at(key - *lo, *dims)?] {
                ABSENT => None,
                at => Some(values[at as usize]),
            },
            Table::Sparse(map) => map.get(&key).copied(),
        }
    }

    /// The number of keys.
    #[cfg(test)]
    pub fn len(&self) -> usize {
        match &self.table {
            Table::Dense { values, .. } => values.len(),
            Table::Sparse(map) => map.len(),
        }
    }

    /// Bytes held.
    pub fn memory_bytes(&self) -> usize {
        match &self.table {
            Table::Dense { cells, values, .. } => {
                cells.capacity() * 4 + values.capacity() * std::mem::size_of::<V>()
            }
            Table::Sparse(map) => map_bytes::<V>(map.capacity()),
        }
    }

    /// The bytes [`KeyIndex::new`] will hold for `keys` (each once).
    pub fn bytes_for(keys: &[IVec3]) -> usize {
        match dense_cells(keys.iter().copied(), keys.len()) {
            Some((_, dims)) => {
                dims.iter().map(|&d| d as usize).product::<usize>() * 4
                    + keys.len() * std::mem::size_of::<V>()
            }
            None => map_bytes::<V>(HashMap::<IVec3, V>::with_capacity(keys.len()).capacity()),
        }
    }
}

/// A hash map's bytes at `capacity`: key, value and a control byte per slot.
fn map_bytes<V>(capacity: usize) -> usize {
    capacity * (std::mem::size_of::<(IVec3, V)>() + 1)
}

/// The box of `keys` and its dimensions, when a dense table over it is small enough for `len`
/// keys.
fn dense_cells(keys: impl Iterator<Item = IVec3>, len: usize) -> Option<(IVec3, [u32; 3])> {
    let (lo, hi) = keys.fold((IVec3::MAX, IVec3::MIN), |(lo, hi), k| {
        (lo.min(k), hi.max(k))
    });
    if len == 0 {
        return Some((IVec3::ZERO, [0; 3]));
    }
    // In i64: a box of keys spread over the whole i32 range overflows i32 and u32.
    let dims = (hi.as_i64vec3() - lo.as_i64vec3() + 1).to_array();
    let cells = dims
        .iter()
        .try_fold(1u64, |n, &d| n.checked_mul(d as u64))?;
    (cells <= DENSE_MIN_CELLS.max(DENSE_CELLS_PER_KEY * len as u64))
        .then(|| (lo, dims.map(|d| d as u32)))
}

/// The row-major index of offset `d` in a box of `dims`, if `d` lies inside it.
#[inline(always)]
fn dense_at(d: IVec3, dims: [u32; 3]) -> Option<usize> {
    // A negative offset wraps to a huge u32, outside like one past the end.
    let [x, y, z] = d.to_array().map(|c| c as u32);
    (x < dims[0] && y < dims[1] && z < dims[2])
        .then(|| (x as usize * dims[1] as usize + y as usize) * dims[2] as usize + z as usize)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn is_dense<V: Copy>(index: &KeyIndex<V>) -> bool {
        matches!(index.table, Table::Dense { .. })
    }

    #[test]
    fn a_compact_box_is_dense_and_answers_every_key_and_only_those() {
        let keys: Vec<IVec3> = (0..200)
            .map(|i| IVec3::new(i % 7 - 3, (i / 7) % 5 - 20, i / 35 + 9))
            .filter(|k| (k.x + k.y + k.z) % 3 != 0)
            .collect();
        let index = KeyIndex::new(
            keys.iter()
                .enumerate()
                .map(|(i, &k)| (k, i as u32))
                .collect(),
        );
        assert!(is_dense(&index));
        assert_eq!(index.len(), keys.len());
        for (i, &k) in keys.iter().enumerate() {
            assert_eq!(index.get(k), Some(i as u32));
        }
        // Around and inside the box, keys never given have no value.
        for x in -6..6 {
            for y in -23..-13 {
                for z in 6..18 {
                    let k = IVec3::new(x, y, z);
                    if !keys.contains(&k) {
                        assert_eq!(index.get(k), None, "{k}");
                    }
                }
            }
        }
    }

    #[test]
    fn scattered_keys_are_hashed_and_the_extremes_of_i32_are_keys_too() {
        let keys = [
            IVec3::MIN,
            IVec3::MAX,
            IVec3::ZERO,
            IVec3::new(1 << 28, -5, 3),
        ];
        let index = KeyIndex::new(keys.iter().map(|&k| (k, k.x)).collect());
        assert!(!is_dense(&index));
        for k in keys {
            assert_eq!(index.get(k), Some(k.x));
        }
        assert_eq!(index.get(IVec3::ONE), None);
        // Two keys at the ends of one axis: a box 2³² long, not a table.
        let far = KeyIndex::new(vec![
            (IVec3::new(i32::MIN, 0, 0), 1),
            (IVec3::new(i32::MAX, 0, 0), 2),
        ]);
        assert!(!is_dense(&far));
        assert_eq!(far.get(IVec3::new(i32::MAX, 0, 0)), Some(2));
    }

    #[test]
    fn nothing_indexed_answers_nothing_and_a_repeated_key_keeps_its_last_value() {
        let empty: KeyIndex<u32> = KeyIndex::new(Vec::new());
        assert_eq!((empty.len(), empty.get(IVec3::ZERO)), (0, None));
        let twice = KeyIndex::new(vec![(IVec3::ONE, 1u32), (IVec3::ONE, 2)]);
        assert_eq!((twice.len(), twice.get(IVec3::ONE)), (1, Some(2)));
        let keys = [IVec3::ONE, IVec3::new(3, 1, 2), IVec3::new(2, 2, 2)];
        let three = KeyIndex::new(keys.iter().map(|&k| (k, 0u32)).collect());
        assert_eq!(KeyIndex::<u32>::bytes_for(&keys), three.memory_bytes());
    }
}
