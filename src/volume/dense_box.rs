//! A dense box of cells over a range of block keys, x-major: what the field's builders mark
//! into when the blocks they touch are compact. Neighbouring leaves then touch neighbouring
//! cells, where a hash map scatters every touch over a table of megabytes (a cache miss each),
//! and the cells come out in key order, sorted for free.

use glam::IVec3;

/// How many more cells than touches a box may have and still be used: past it the box is mostly
/// empty space (a thin helix across a large volume, tiles far apart) and the caller keeps its
/// sparse path.
const MAX_SPREAD: u64 = 4;

pub(crate) struct DenseBox<T> {
    lo: IVec3,
    dim: IVec3,
    cells: Vec<T>,
}

impl<T: Clone> DenseBox<T> {
    /// Cells of `fill` for the keys `lo..=hi`, or `None` when the box is empty or holds more than
    /// [`MAX_SPREAD`] cells per one of the `touches` the caller will make.
    pub fn new(lo: IVec3, hi: IVec3, fill: T, touches: u64) -> Option<DenseBox<T>> {
        if hi.cmplt(lo).any() {
            return None;
        }
        // In i64 and u128: keys far apart (a damaged file's leaf origins) must not wrap around.
        let dim = (hi.as_i64vec3() - lo.as_i64vec3() + 1).as_u64vec3();
        let n = dim.x as u128 * dim.y as u128 * dim.z as u128;
        if n > MAX_SPREAD as u128 * touches as u128 {
            return None;
        }
        Some(DenseBox {
            lo,
            dim: dim.as_ivec3(),
            cells: vec![fill; n as usize],
        })
    }

    /// The cell of `key`, which lies in the box.
    pub fn cell(&mut self, key: IVec3) -> &mut T {
        let (l, d) = ((key - self.lo).as_uvec3(), self.dim.as_uvec3());
        &mut self.cells[(l.x as usize * d.y as usize + l.y as usize) * d.z as usize + l.z as usize]
    }

    /// Every cell with its key, in ascending (x, y, z).
    pub fn into_cells(self) -> impl Iterator<Item = (IVec3, T)> {
        let (lo, dim) = (self.lo, self.dim);
        let (dy, dz) = (dim.y as usize, dim.z as usize);
        self.cells.into_iter().enumerate().map(move |(i, c)| {
            let l = [i / (dy * dz), i / dz % dy, i % dz].map(|v| v as i32);
            (lo + IVec3::from_array(l), c)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cells_come_out_in_key_order_and_sparse_boxes_are_refused() {
        let mut b = DenseBox::new(IVec3::new(-1, 0, 2), IVec3::new(0, 1, 3), 0, 2).unwrap();
        *b.cell(IVec3::new(0, 0, 3)) = 5;
        *b.cell(IVec3::new(-1, 1, 2)) = 7;
        let cells: Vec<(IVec3, i32)> = b.into_cells().collect();
        let keys: Vec<IVec3> = cells.iter().map(|c| c.0).collect();
        let mut sorted = keys.clone();
        sorted.sort_by_key(|k| (k.x, k.y, k.z));
        assert_eq!(keys, sorted);
        assert_eq!(cells.len(), 8);
        assert!(cells.contains(&(IVec3::new(0, 0, 3), 5)));
        assert!(cells.contains(&(IVec3::new(-1, 1, 2), 7)));
        // Eight cells for one touch is past the spread; an inverted box is empty; keys at the ends
        // of i32 do not wrap into a small box.
        assert!(DenseBox::new(IVec3::ZERO, IVec3::ONE, 0, 1).is_none());
        assert!(DenseBox::new(IVec3::ONE, IVec3::ZERO, 0, 100).is_none());
        assert!(DenseBox::new(IVec3::MIN, IVec3::MAX, 0, u64::MAX).is_none());
    }
}
