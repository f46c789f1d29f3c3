//! The visibility V(p) = (1/4π)∫ e^{−τ(p, ω)} dω of the density: the share of the environment a
//! point sees through the medium, whatever the light. It falls by orders of magnitude within one
//! transfer voxel under a thick lit surface, which is what a transfer interpolated between nodes K
//! voxels apart cannot follow; the renderer takes the shape of that fall from V
//! ([`crate::render::march::TransferRadiance`]).
//!
//! V is the mean of e^{−τ} over equal-area directions, each τ swept once through the occupied
//! region by a [`ShadowVolume`], so the cost follows the active voxels, and the result is
//! deterministic (no Monte Carlo noise to become texture). It is swept and kept at a
//! [`Resolution`]: the density itself, or its 2× box mean ([`crate::volume::mip`]).
//!
//! It is kept as D = −ln V on the topology of the density it was swept through, and read as
//! V = e^{−D} with D interpolated trilinearly over the corners where the density is above 0: empty
//! voxels beside a surface, where V was not swept, take no part. Under a lit surface V falls by a
//! near-constant factor per voxel, a straight line in D; a corner's weight is its trilinear
//! weight alone: read as ρ·V over ρ, V would lean toward the denser corner between two layers
//! and bulge above the exponential fall, once per voxel layer, which draws stripes one voxel
//! apart across a cloud's lit lobes. The grid holds 1 + D where the density is above 0 and 0 elsewhere
//! ([`stored`]), so which corners hold a value comes from the same eight loads
//! ([`BrickSampler::sample_covered`]). Its values, V one per active voxel in
//! [`Visibility::values`]' order, are what a cache stores.

use std::borrow::Cow;

use glam::{IVec3, Vec3};
use half::f16;
use rayon::prelude::*;

use super::bricks::{BrickSampler, Bricks};
use super::grid::{slot_offset, Block, Leaf, SparseGrid, TileLevel, LEAF_LOG2, LEAF_VOXELS};
use super::mip::{coarsen, to_level};
use super::shadow::{ShadowCursor, ShadowVolume};
use super::DensityField;
use crate::math::sphere::fibonacci;

/// The coarsest level V is kept at: a 4096³ tile is 16³ voxels there.
pub const MAX_LEVEL: usize = 8;

/// How finely V is swept and kept: the density level (0: the density itself, 1: its 2× box
/// mean) and the directions its mean takes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Resolution {
    pub level: usize,
    pub directions: usize,
}

impl Resolution {
    /// What a single-scattering transfer is shaped by. Measured at 256×144 against the path
    /// tracer (studio map, torus at 1.92 / cloud at 5.4 optical depths per transfer voxel, single
    /// scattering): the density and 16 directions 9.0 / 14.8 %, 8 directions 9.6 / 15.9 %, the 2×
    /// mean and 16 directions 11.0 / 19.9 %.
    pub const FINE: Resolution = Resolution {
        level: 0,
        directions: 16,
    };
}

/// V of the density as a renderer reads it, with what a cache stores of it.
pub struct Visibility {
    pub resolution: Resolution,
    /// V at every active voxel (and every large tile's centre) of the level's density, in the
    /// order of [`units`]: what a cache stores.
    values: Vec<f16>,
    /// The kept grid ([`stored`]) on the level's topology, and its bricks.
    kept: SparseGrid,
    bricks: Bricks,
    /// The level's density (`None` at level 0, where a ray's own density divides).
    coarse: Option<DensityField>,
}

/// Samples V for one ray.
pub struct VisibilitySampler<'a> {
    level: usize,
    kept: BrickSampler<'a>,
    density: Option<BrickSampler<'a>>,
}

impl VisibilitySampler<'_> {
    /// V at the density's index point `p`, where the density is `rho` (`None` where the level's
    /// density is 0: V is not defined there).
    // Out of line: inlined into the march's step loop, which runs without it in every render
    // with multiple scattering, it cost those renders 1 % more instructions (callgrind, the
    // cloud at 480×270).
    #[inline(never)]
    pub fn at(&mut self, p: Vec3, rho: f32) -> Option<f32> {
        let (q, rho) = match &mut self.density {
            Some(density) => {
                let q = to_level(p, self.level);
                (q, density.sample(q))
            }
            None => (p, rho),
        };
        let (sum, cover) = self.kept.sample_covered(q);
        (rho > 0.0 && cover > 0.0).then(|| from_stored(sum, cover))
    }
}

/// The largest D = −ln V kept: a cache holds V as f16, whose smallest value above 0 is
/// 6·10⁻⁸ = e^{−16.6}; V = 0 (no direction sees out) is kept as e^{−16}, far below anything the
/// shaping reads ([`crate::render::march`] ignores a fitted V under 10⁻⁴).
const MAX_DEPTH: f32 = 16.0;

/// What the kept grid holds at a voxel of density `rho` whose visibility is `v`: 1 + D, D = −ln V
/// bounded by [`MAX_DEPTH`], where the density is above 0, else 0 (module doc).
pub(crate) fn stored(rho: f32, v: f32) -> f32 {
    if rho <= 0.0 {
        return 0.0;
    }
    1.0 + match v > 0.0 {
        true => (-v.ln()).clamp(0.0, MAX_DEPTH),
        false => MAX_DEPTH,
    }
}

/// V from the blends of a kept grid at a point ([`BrickSampler::sample_covered`]): the mean of
/// 1 + D over the corners that hold it, `cover` > 0.
pub(crate) fn from_stored(sum: f32, cover: f32) -> f32 {
    (1.0 - sum / cover).exp()
}

/// Where V is kept: the voxels of a leaf or of an 8³ tile (an 8³ tile often lies under a surface,
/// where V changes across it), or one value for a larger tile, taken at its centre.
#[derive(Debug, Clone, Copy)]
enum Unit {
    Voxels { origin: IVec3, mask: [u64; 8] },
    Tile { level: TileLevel, origin: IVec3 },
}

impl Unit {
    fn count(&self) -> usize {
        match self {
            Unit::Voxels { mask, .. } => mask.iter().map(|m| m.count_ones() as usize).sum(),
            Unit::Tile { .. } => 1,
        }
    }

    /// The voxels V is taken at, in value order.
    fn points(&self) -> impl Iterator<Item = IVec3> + '_ {
        let (voxels, tile) = match *self {
            Unit::Voxels { origin, mask } => (Some((origin, mask)), None),
            Unit::Tile { level, origin } => {
                (None, Some(origin + IVec3::splat((level.dim() / 2) as i32)))
            }
        };
        voxels
            .into_iter()
            .flat_map(|(origin, mask)| {
                (0..LEAF_VOXELS)
                    .filter(move |&s| Leaf::is_set(&mask, s))
                    .map(move |s| origin + slot_offset(s))
            })
            .chain(tile)
    }
}

/// The units of `grid`, a level of `fine`, in the order values are kept: blocks by origin (x, y,
/// z), then the larger tiles by level and origin. An 8³ tile of a coarse level that halves a larger
/// tile of `fine` stays a tile: it lies inside a uniform region, and a huge tile kept voxel by
/// voxel would cost memory in proportion to its volume.
fn units(grid: &SparseGrid, fine: &SparseGrid, level: usize) -> Vec<Unit> {
    let inside_large_tile = |origin: IVec3| {
        level > 0
            && matches!(
                fine.tile_level(origin << level as i32),
                Some(TileLevel::Node | TileLevel::Root)
            )
    };
    let (large, blocks): (Vec<IVec3>, Vec<IVec3>) = grid
        .tiles(TileLevel::Block)
        .map(|(o, _)| o)
        .partition(|&o| inside_large_tile(o));
    let mut voxels: Vec<(IVec3, [u64; 8])> = grid
        .leaves()
        .iter()
        .map(|l| (l.origin, l.mask))
        .chain(blocks.into_iter().map(|o| (o, [u64::MAX; 8])))
        .collect();
    voxels.sort_unstable_by_key(|(o, _)| o.to_array());
    let mut tiles: Vec<(TileLevel, IVec3)> = large
        .into_iter()
        .map(|o| (TileLevel::Block, o))
        .chain(
            [TileLevel::Node, TileLevel::Root]
                .into_iter()
                .flat_map(|level| grid.tiles(level).map(move |(o, _)| (level, o))),
        )
        .collect();
    tiles.sort_unstable_by_key(|(level, o)| (level.log2(), o.to_array()));
    voxels
        .into_iter()
        .map(|(origin, mask)| Unit::Voxels { origin, mask })
        .chain(
            tiles
                .into_iter()
                .map(|(level, origin)| Unit::Tile { level, origin }),
        )
        .collect()
}

/// The voxels of `units`, in value order.
fn points(units: &[Unit]) -> Vec<IVec3> {
    units.iter().flat_map(Unit::points).collect()
}

/// The kept grid ([`stored`]) on `grid`'s topology from V in the order of `units`.
fn assemble(grid: &SparseGrid, units: &[Unit], values: &[f32]) -> SparseGrid {
    let starts: Vec<usize> = units
        .iter()
        .scan(0, |next, u| {
            let start = *next;
            *next += u.count();
            Some(start)
        })
        .collect();
    let leaves: Vec<(IVec3, [u64; 8], [f32; LEAF_VOXELS])> = units
        .par_iter()
        .zip(&starts)
        .filter_map(|(unit, &start)| match *unit {
            Unit::Voxels { origin, mask } => {
                let block = grid.block(origin >> LEAF_LOG2 as i32);
                let mut kept = [0.0; LEAF_VOXELS];
                let mut next = values[start..].iter();
                for slot in (0..LEAF_VOXELS).filter(|&s| Leaf::is_set(&mask, s)) {
                    let rho = match block {
                        Block::Leaf(leaf) => leaf.values.get(slot),
                        Block::Constant(v) => v,
                    };
                    kept[slot] = stored(rho, next.next().copied().unwrap_or(0.0));
                }
                Some((origin, mask, kept))
            }
            Unit::Tile { .. } => None,
        })
        .collect();
    let mut out = SparseGrid::new(grid.transform, 0.0);
    out.reserve_leaves(leaves.len());
    for (origin, mask, values) in leaves {
        out.insert_leaf(origin, mask, values);
    }
    for (unit, &start) in units.iter().zip(&starts) {
        if let Unit::Tile { level, origin } = *unit {
            out.insert_tile(level, origin, stored(grid.value(origin), values[start]));
        }
    }
    out
}

/// `fine` coarsened to `level`.
fn coarsened(fine: &SparseGrid, level: usize) -> SparseGrid {
    (1..level).fold(coarsen(fine), |g, _| coarsen(&g))
}

impl Visibility {
    /// Sweeps V through `field` (or its coarser level) at extinction `sigma_t` per unit density,
    /// one direction at a time: the values and one shadow volume are all the sweep holds.
    pub fn build(field: &DensityField, sigma_t: f32, resolution: Resolution) -> Visibility {
        let coarse = (resolution.level > 0)
            .then(|| DensityField::new(coarsened(&field.grid, resolution.level)));
        let level = coarse.as_ref().unwrap_or(field);
        let units = units(&level.grid, &field.grid, resolution.level);
        let points = points(&units);
        let share = 1.0 / resolution.directions as f32;
        let mut mean = vec![0.0f32; points.len()];
        for d in fibonacci(resolution.directions) {
            let volume = ShadowVolume::build(level, sigma_t, d);
            mean.par_iter_mut().zip(&points).for_each_init(
                ShadowCursor::default,
                |cursor, (v, p)| {
                    let tau = volume.core_value(*p, cursor).unwrap_or(0.0);
                    *v += share * (-tau).exp();
                },
            );
        }
        drop(points);
        let values = mean.into_iter().map(f16::from_f32).collect();
        Visibility::from_parts(&field.grid, resolution, &units, values, coarse)
    }

    /// The visibility of `fine` whose values a cache holds (`values`, in [`Visibility::values`]'
    /// order); `None` when their number is not the one the density has at `resolution`.
    pub fn from_values(
        fine: &SparseGrid,
        resolution: Resolution,
        values: Vec<f16>,
    ) -> Option<Visibility> {
        let coarse =
            (resolution.level > 0).then(|| DensityField::new(coarsened(fine, resolution.level)));
        let grid = coarse.as_ref().map_or(fine, |c| &c.grid);
        let units = units(grid, fine, resolution.level);
        let count: usize = units.iter().map(Unit::count).sum();
        (count == values.len())
            .then(|| Visibility::from_parts(fine, resolution, &units, values, coarse))
    }

    /// The visibility whose values `values` are kept at `units` of the level's density.
    fn from_parts(
        fine: &SparseGrid,
        resolution: Resolution,
        units: &[Unit],
        values: Vec<f16>,
        coarse: Option<DensityField>,
    ) -> Visibility {
        let grid = coarse.as_ref().map_or(fine, |c| &c.grid);
        let v: Vec<f32> = values.iter().map(|v| v.to_f32()).collect();
        let kept = assemble(grid, units, &v);
        let bricks = Bricks::build(&kept);
        Visibility {
            resolution,
            values,
            kept,
            bricks,
            coarse,
        }
    }

    /// V per active voxel of the level's density (and per large tile), as a cache stores it.
    pub fn values(&self) -> &[f16] {
        &self.values
    }

    /// A sampler of V for one ray.
    pub fn sampler(&self) -> VisibilitySampler<'_> {
        VisibilitySampler {
            level: self.resolution.level,
            kept: BrickSampler::new(&self.bricks, &self.kept),
            density: self.coarse.as_ref().map(DensityField::sampler),
        }
    }

    /// The kept grid ([`stored`]) on the topology of the density `fine`, V sampled at each of its
    /// voxels as a ray samples it: what the fit of V reads.
    pub fn fine_kept(&self, fine: &SparseGrid) -> Cow<'_, SparseGrid> {
        if self.coarse.is_none() {
            return Cow::Borrowed(&self.kept);
        }
        let units = units(fine, fine, 0);
        let values: Vec<f32> = points(&units)
            .par_iter()
            .map_init(
                || self.sampler(),
                |sampler, p| sampler.at(p.as_vec3(), 0.0).unwrap_or(0.0),
            )
            .collect();
        Cow::Owned(assemble(fine, &units, &values))
    }

    /// Bytes held: the values, the kept grid and the level's density, with their bricks.
    pub fn memory_bytes(&self) -> u64 {
        (self.values.len() * 2
            + self.kept.memory_bytes()
            + self.bricks.memory_bytes()
            + self
                .coarse
                .as_ref()
                .map_or(0, |c| c.grid.memory_bytes() + c.brick_bytes())) as u64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::grid::{Transform, LEAF_DIM};
    use glam::Vec3;

    /// V at `p` in the cube of density 1 over voxels [0, n)³, whose trilinear density ends half a
    /// voxel beyond its outer voxels: the mean of e^{−σt·d} over the same directions, d the exact
    /// distance to that boundary.
    fn cube_visibility(p: Vec3, n: f32, sigma_t: f32) -> f32 {
        cube_visibility_over(p, n, sigma_t, Resolution::FINE.directions)
    }

    /// [`cube_visibility`] over the first `directions` Fibonacci directions.
    fn cube_visibility_over(p: Vec3, n: f32, sigma_t: f32, directions: usize) -> f32 {
        let lo = Vec3::splat(-0.5) - p;
        let hi = Vec3::splat(n - 0.5) - p;
        let mean: f32 = fibonacci(directions)
            .iter()
            .map(|d| {
                let exit = |a: usize| match d[a] {
                    x if x > 0.0 => hi[a] / x,
                    x if x < 0.0 => lo[a] / x,
                    _ => f32::INFINITY,
                };
                (-sigma_t * exit(0).min(exit(1)).min(exit(2))).exp()
            })
            .sum();
        mean / directions as f32
    }

    /// V on the density's 2× mean over 8 directions.
    const COARSE: Resolution = Resolution {
        level: 1,
        directions: 8,
    };

    /// 4³ leaves of density 1: 32³ voxels.
    fn cube() -> DensityField {
        let mut grid = SparseGrid::new(Transform::default(), 0.0);
        for l in 0..64 {
            let origin = IVec3::new(l / 16, (l / 4) % 4, l % 4) * LEAF_DIM;
            grid.insert_leaf(origin, [u64::MAX; 8], [1.0; LEAF_VOXELS]);
        }
        DensityField::new(grid)
    }

    #[test]
    fn a_uniform_cube_sees_the_environment_through_its_exact_depths() {
        let field = cube();
        let sigma_t = 0.1;
        let v = Visibility::build(&field, sigma_t, Resolution::FINE);
        for p in [
            IVec3::splat(16),
            IVec3::new(0, 16, 16),
            IVec3::new(3, 28, 9),
            IVec3::splat(31),
        ] {
            let want = cube_visibility(p.as_vec3(), 32.0, sigma_t);
            let got = v.sampler().at(p.as_vec3(), 1.0).unwrap();
            assert!((got - want).abs() < 0.02 * want, "{p}: {got} vs {want}");
        }
        // Outside the medium nothing is stored.
        assert_eq!(v.kept.value(IVec3::splat(40)), 0.0);
    }

    #[test]
    fn between_voxel_layers_under_a_lit_face_v_follows_its_fall() {
        // A slab 4 voxels thick (x) whose outer layer is thin, ramping up to full density, as a
        // cloud's surface does, at one optical depth per voxel: V falls by a near-constant factor
        // per layer, and halfway between two layers it is the geometric mean of theirs, where a
        // blend weighted by density would lean toward the denser, darker layer.
        let mut grid = SparseGrid::new(Transform::default(), 0.0);
        let mut values = [0.0; LEAF_VOXELS];
        for (slot, v) in values.iter_mut().enumerate() {
            let x = slot_offset(slot).x;
            *v = [0.1, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0][x as usize];
        }
        for (y, z) in [(0, 0), (0, 8), (8, 0), (8, 8)] {
            grid.insert_leaf(IVec3::new(0, y, z), [u64::MAX; 8], values);
        }
        let v = Visibility::build(&DensityField::new(grid), 1.0, Resolution::FINE);
        let mut sampler = v.sampler();
        let at = |sampler: &mut VisibilitySampler, x: f32, rho: f32| {
            sampler.at(Vec3::new(x, 8.0, 8.0), rho).unwrap()
        };
        let (v0, v1) = (at(&mut sampler, 0.0, 0.1), at(&mut sampler, 1.0, 1.0));
        let half = at(&mut sampler, 0.5, 0.55);
        let geometric = (v0 * v1).sqrt();
        assert!(v1 < 0.8 * v0, "{v0} {v1}");
        assert!(
            (half - geometric).abs() < 1e-3 * geometric,
            "{half} vs {geometric}"
        );
    }

    /// The visibility of one tile at the origin.
    fn of_tile(level: TileLevel, value: f32, sigma_t: f32) -> Visibility {
        let mut grid = SparseGrid::new(Transform::default(), 0.0);
        grid.insert_tile(level, IVec3::ZERO, value);
        Visibility::build(&DensityField::new(grid), sigma_t, Resolution::FINE)
    }

    #[test]
    fn an_8_cubed_tile_is_resolved_voxel_by_voxel() {
        let v = of_tile(TileLevel::Block, 1.0, 0.3);
        // At a corner the sweep resamples its depths bilinearly across the cube's edges, where
        // the depth has a kink: 3.5 % there, under 2 % inside.
        for (p, tolerance) in [
            (IVec3::ZERO, 0.05),
            (IVec3::new(3, 4, 3), 0.02),
            (IVec3::new(7, 2, 5), 0.02),
        ] {
            let want = cube_visibility(p.as_vec3(), 8.0, 0.3);
            let got = v.sampler().at(p.as_vec3(), 1.0).unwrap();
            assert!(
                (got - want).abs() < tolerance * want,
                "{p}: {got} vs {want}"
            );
        }
    }

    #[test]
    fn a_large_tile_takes_the_visibility_of_its_centre() {
        let v = of_tile(TileLevel::Node, 0.5, 0.04);
        // Density 0.5 at σt 0.04 is the unit cube of 128 at σt 0.02; the tile holds one V.
        let want = cube_visibility(Vec3::splat(64.0), 128.0, 0.02);
        let got = v.sampler().at(Vec3::new(5.0, 100.0, 17.0), 0.5).unwrap();
        assert!((got - want).abs() < 0.02 * want, "{got} vs {want}");
    }

    #[test]
    fn the_coarse_level_sees_the_same_cube() {
        // The 2× mean of the cube is 16³ coarse voxels whose trilinear density ends where the
        // cube's does, so V at a coarse voxel's centre is the cube's there; between centres it
        // is interpolated.
        let field = cube();
        let sigma_t = 0.1;
        let v = Visibility::build(&field, sigma_t, COARSE);
        assert_eq!(v.values().len(), 16 * 16 * 16);
        let mut sampler = v.sampler();
        for (p, tolerance) in [
            (Vec3::splat(16.5), 0.02),
            (Vec3::new(0.5, 16.5, 16.5), 0.02),
            (Vec3::new(2.0, 29.0, 9.0), 0.04),
            (Vec3::new(17.2, 3.9, 25.0), 0.04),
        ] {
            let want = cube_visibility_over(p, 32.0, sigma_t, COARSE.directions);
            let got = sampler.at(p, 1.0).unwrap();
            assert!(
                (got - want).abs() < tolerance * want,
                "{p}: {got} vs {want}"
            );
        }
        // Outside the medium V is not defined.
        assert_eq!(sampler.at(Vec3::splat(40.0), 0.0), None);
    }

    #[test]
    fn stored_values_rebuild_the_same_visibility() {
        let field = cube();
        for resolution in [Resolution::FINE, COARSE] {
            let v = Visibility::build(&field, 0.2, resolution);
            let back = Visibility::from_values(&field.grid, resolution, v.values().to_vec())
                .expect("the values fit the density");
            let p = Vec3::new(3.3, 17.0, 30.1);
            assert_eq!(back.sampler().at(p, 1.0), v.sampler().at(p, 1.0));
            let mut short = v.values().to_vec();
            short.pop();
            assert!(Visibility::from_values(&field.grid, resolution, short).is_none());
        }
    }

    #[test]
    fn a_large_tile_stays_a_tile_at_the_coarse_level() {
        // A 128³ tile halves into 512 tiles of 8³ coarse voxels: 512 values, not 512².
        let mut grid = SparseGrid::new(Transform::default(), 0.0);
        grid.insert_tile(TileLevel::Node, IVec3::ZERO, 0.5);
        let v = Visibility::build(&DensityField::new(grid), 0.04, COARSE);
        assert_eq!(v.values().len(), 512);
        // The coarse tile at the cube's centre sees it as the fine tile's centre does, to the
        // directions' quadrature.
        let want = cube_visibility_over(Vec3::splat(64.0), 128.0, 0.02, 8);
        let got = v.sampler().at(Vec3::splat(64.0), 0.5).unwrap();
        assert!((got - want).abs() < 0.05 * want, "{got} vs {want}");
    }
}
