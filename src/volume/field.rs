//! The density as the renderers and the bake read it: the sparse grid with its two accelerators,
//! built once — the occupancy that lets rays skip empty space, and the apron bricks that make a
//! trilinear sample a hash lookup per block and eight loads. Every density sample anywhere goes
//! through [`DensityField::sampler`].

use std::sync::OnceLock;

use super::bricks::{BrickSampler, Bricks};
use super::dda::Occupancy;
use super::grid::SparseGrid;

/// A density grid and its accelerators.
pub struct DensityField {
    pub grid: SparseGrid,
    pub occupancy: Occupancy,
    /// Built with the field; a bake releases them for its lattice phase (they are the largest
    /// accelerator and the lattice samples no density), and the next sampler builds them again.
    bricks: OnceLock<Bricks>,
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
            bricks: OnceLock::from(bricks),
        }
    }

    /// A sampler for one ray (one thread): the trilinear density at index-space points.
    pub fn sampler(&self) -> BrickSampler<'_> {
        let bricks = self.bricks.get_or_init(|| Bricks::build(&self.grid));
        BrickSampler::new(bricks, &self.grid)
    }

    /// Frees the bricks until the next [`DensityField::sampler`] builds them again.
    pub fn release_bricks(&mut self) {
        self.bricks.take();
    }

    /// Bytes of the accelerators once built, released or not (the grid counts its own).
    pub fn accelerator_bytes(&self) -> usize {
        self.brick_bytes
    }
}
