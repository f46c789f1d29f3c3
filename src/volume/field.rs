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
    pub bricks: Bricks,
}

impl DensityField {
    pub fn new(grid: SparseGrid) -> DensityField {
        // Side by side: each has serial parts (hash maps filled in key order) the other's
        // parallel work fills in around.
        let (occupancy, bricks) = rayon::join(|| Occupancy::build(&grid), || Bricks::build(&grid));
        DensityField {
            grid,
            occupancy,
            bricks,
        }
    }

    /// A sampler for one ray (one thread): the trilinear density at index-space points.
    pub fn sampler(&self) -> BrickSampler<'_> {
        BrickSampler::new(&self.bricks, &self.grid)
    }

    /// Bytes held by the accelerators (the grid counts its own).
    pub fn accelerator_bytes(&self) -> usize {
        self.bricks.memory_bytes()
    }
}
