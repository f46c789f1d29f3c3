//! The density as the renderers and the bake read it: the sparse grid with its two accelerators,
//! built once — the occupancy that lets rays skip empty space, and the apron bricks that make a
//! trilinear sample a hash lookup per block and eight loads. Every density sample anywhere goes
//! through [`DensityField::sampler`].

use super::bricks::{BrickSampler, Bricks};
use super::dda::Occupancy;
use super::grid::SparseGrid;

/// A density grid and its accelerators.
pub struct DensityField {
    pub grid: SparseGrid,
    pub occupancy: Occupancy,
    /// Built with the field; a bake releases them while its lattice transports light (they are
    /// the largest accelerator, and the transport samples no density) and builds them again
    /// after. Released, they are empty and samples read the grid itself: slower, the same values.
    bricks: Bricks,
    /// The bricks' bytes, held or not: what a sampler will hold.
    brick_bytes: usize,
}

impl DensityField {
    pub fn new(grid: SparseGrid) -> DensityField {
        // Side by side: each has serial parts (hash maps filled in key order) the other's
        // parallel work fills in around.
        let (occupancy, bricks) = rayon::join(|| Occupancy::build(&grid), || Bricks::build(&grid));
        DensityField {
            grid,
            occupancy,
            brick_bytes: bricks.memory_bytes(),
            bricks,
        }
    }

    /// A sampler for one ray (one thread): the trilinear density at index-space points.
    pub fn sampler(&self) -> BrickSampler<'_> {
        BrickSampler::new(&self.bricks, &self.grid)
    }

    /// Frees the bricks until [`DensityField::restore_bricks`].
    pub fn release_bricks(&mut self) {
        self.bricks = Bricks::empty();
    }

    /// Builds the bricks again after [`DensityField::release_bricks`].
    pub fn restore_bricks(&mut self) {
        self.bricks = Bricks::build(&self.grid);
    }

    /// Bytes of the accelerators once built, released or not (the grid counts its own).
    pub fn accelerator_bytes(&self) -> usize {
        self.brick_bytes
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::grid::{TileLevel, Transform};
    use glam::{IVec3, Vec3};

    #[test]
    fn released_bricks_change_no_sample() {
        // A leaf of varied values beside a tile: released, the samples come from the grid itself
        // and must be the bricks' values bit for bit; restored, the bricks are back.
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Block, IVec3::new(8, 0, 0), 0.5);
        let values = std::array::from_fn(|i| (i % 11) as f32 * 0.1);
        g.insert_leaf(IVec3::ZERO, [u64::MAX; 8], values);
        let mut field = DensityField::new(g);
        let points: Vec<Vec3> = (0..500)
            .map(|i| {
                let f = |k: u32| ((i * k) % 97) as f32 / 97.0;
                Vec3::new(f(13) * 18.0 - 1.0, f(29) * 10.0 - 1.0, f(41) * 10.0 - 1.0)
            })
            .collect();
        let samples = |field: &DensityField| -> Vec<u32> {
            let mut s = field.sampler();
            points.iter().map(|p| s.sample(*p).to_bits()).collect()
        };
        let with = samples(&field);
        assert!(field.bricks.memory_bytes() > 0);
        field.release_bricks();
        assert_eq!(field.bricks.memory_bytes(), 0);
        assert_eq!(samples(&field), with);
        field.restore_bricks();
        assert!(field.bricks.memory_bytes() > 0);
        assert_eq!(samples(&field), with);
        assert_eq!(field.accelerator_bytes(), field.bricks.memory_bytes());
    }
}
