//! The density as the renderers and the bake read it: the sparse grid with its two accelerators —
//! the occupancy that lets rays skip empty space, built with the field, and the apron bricks that
//! make a trilinear sample a hash lookup per block and eight loads, built when the work ahead will
//! repay them. Every density sample anywhere goes through [`DensityField::sampler`].

use std::sync::{LazyLock, OnceLock};
use std::time::Instant;

use super::bricks::{BrickSampler, Bricks};
use super::dda::Occupancy;
use super::grid::SparseGrid;

/// What a sampler reads when a field has no bricks: every sample goes to the grid itself.
static NO_BRICKS: LazyLock<Bricks> = LazyLock::new(Bricks::empty);

/// A density grid and its accelerators.
pub struct DensityField {
    pub grid: SparseGrid,
    pub occupancy: Occupancy,
    /// The bricks hold about twice the leaves' memory and repay it only over many samples per
    /// leaf: built by [`DensityField::build_bricks`] where that holds (a bake, a path trace, a
    /// sun's shadow, a march with many rays per leaf), released by a bake while its lattice,
    /// which samples no density, transports light. Without them samples read the grid: slower,
    /// the same values.
    bricks: OnceLock<Bricks>,
    /// The bricks' bytes, held or not: counted when first asked.
    brick_bytes: OnceLock<usize>,
}

impl DensityField {
    /// The field with its bricks built.
    pub fn new(grid: SparseGrid) -> DensityField {
        // Side by side: each has serial parts (hash maps filled in key order) the other's
        // parallel work fills in around.
        let (occupancy, bricks) = rayon::join(|| Occupancy::build(&grid), || Bricks::build(&grid));
        DensityField {
            grid,
            occupancy,
            brick_bytes: OnceLock::from(bricks.memory_bytes()),
            bricks: OnceLock::from(bricks),
        }
    }

    /// The field with its occupancy only; [`DensityField::build_bricks`] adds the bricks.
    pub fn without_bricks(grid: SparseGrid) -> DensityField {
        DensityField {
            occupancy: Occupancy::build(&grid),
            grid,
            bricks: OnceLock::new(),
            brick_bytes: OnceLock::new(),
        }
    }

    /// A sampler for one ray (one thread): the trilinear density at index-space points.
    pub fn sampler(&self) -> BrickSampler<'_> {
        BrickSampler::new(self.bricks.get().unwrap_or(&NO_BRICKS), &self.grid)
    }

    /// Builds the bricks unless they are built; returns the seconds it took (0 when they were).
    pub fn build_bricks(&self) -> f64 {
        let clock = Instant::now();
        let mut built = false;
        let bricks = self.bricks.get_or_init(|| {
            built = true;
            Bricks::build(&self.grid)
        });
        self.brick_bytes.get_or_init(|| bricks.memory_bytes());
        if built {
            clock.elapsed().as_secs_f64()
        } else {
            0.0
        }
    }

    /// Frees the bricks until [`DensityField::build_bricks`].
    pub fn release_bricks(&mut self) {
        self.bricks.take();
    }

    /// Whether the bricks are built.
    pub fn has_bricks(&self) -> bool {
        self.bricks.get().is_some()
    }

    /// Bytes of the bricks once built, built or not.
    pub fn brick_bytes(&self) -> usize {
        *self.brick_bytes.get_or_init(|| match self.bricks.get() {
            Some(bricks) => bricks.memory_bytes(),
            None => Bricks::estimate_bytes(&self.grid),
        })
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
        assert!(field.has_bricks());
        field.release_bricks();
        assert!(!field.has_bricks());
        assert_eq!(samples(&field), with);
        field.build_bricks();
        assert!(field.has_bricks());
        assert_eq!(samples(&field), with);
        let built = field.bricks.get().map(|b| b.memory_bytes());
        assert_eq!(Some(field.brick_bytes()), built);
        // Never built, the same samples, and the bricks' bytes counted from their plan alone.
        let unbuilt = DensityField::without_bricks(field.grid.clone());
        assert_eq!(samples(&unbuilt), with);
        assert_eq!(Some(unbuilt.brick_bytes()), built);
        assert!(!unbuilt.has_bricks());
    }
}
