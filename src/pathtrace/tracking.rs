//! Free-flight sampling through the sparse density, unbiased whatever the density: **delta
//! tracking** (where does a ray first really collide?) and **ratio tracking** (how much light gets
//! through?), both against piecewise-constant majorants taken from the hierarchical DDA's spans —
//! each span's bound on the trilinear density, from the per-leaf and per-tile maxima — so empty
//! space costs nothing and thin regions get long tentative steps.
//!
//! Within a span of majorant σ̄ = σt·ρ̄, tentative collisions are exponential steps of rate σ̄; at
//! each, the real density ρ decides: delta tracking accepts with probability ρ/ρ̄, ratio tracking
//! multiplies its estimate by 1 − ρ/ρ̄. The exponential's memorylessness lets a step that overshoots
//! a span's end restart at the next span with the next majorant.

use std::ops::ControlFlow;

use glam::Vec3;
use rand::Rng;

use crate::volume::bricks::BrickSampler;
use crate::volume::DensityField;

/// Ratio tracking plays Russian roulette once its estimate falls below this: the shadow ray stops
/// with probability ½ or continues with twice the weight (so at most 2·this), unbiased, and a long
/// thick path costs a bounded number of lookups.
const SHADOW_ROULETTE_BELOW: f64 = 0.1;

/// The density a tracker walks through, and the medium's extinction per unit density.
pub struct Medium3d<'a> {
    pub field: &'a DensityField,
    pub sigma_t: f32,
}

/// Counts for `--stats`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct TrackStats {
    /// Density lookups (tentative collisions).
    pub lookups: u64,
}

impl<'a> Medium3d<'a> {
    /// Walks tentative collisions along the ray; `at` gets each one's world distance and the ratio
    /// ρ/ρ̄ there, and stops the walk by returning `Break`.
    fn walk<R: Rng>(
        &self,
        origin: Vec3,
        dir: Vec3,
        rng: &mut R,
        sampler: &mut BrickSampler,
        stats: &mut TrackStats,
        mut at: impl FnMut(f64, f64, &mut R) -> ControlFlow<()>,
    ) {
        if self.sigma_t <= 0.0 {
            return;
        }
        let ray = self.field.grid.transform.ray_to_index(origin, dir);
        self.field
            .occupancy
            .visit_majorants(&ray, 0.0, f64::INFINITY, |span| {
                if span.max_density <= 0.0 {
                    return ControlFlow::Continue(());
                }
                let bound = span.max_density as f64;
                let rate = self.sigma_t as f64 * bound;
                let mut t = span.t0;
                loop {
                    // 1 − u ∈ (0, 1]: the logarithm is finite.
                    t -= (1.0 - rng.random::<f64>()).ln() / rate;
                    if t >= span.t1 {
                        return ControlFlow::Continue(());
                    }
                    stats.lookups += 1;
                    let rho = sampler.sample(ray.at(t).as_vec3()) as f64;
                    at(t, (rho / bound).clamp(0.0, 1.0), rng)?;
                }
            });
    }

    /// Delta tracking: the world distance of the first real collision, `None` if the ray escapes.
    pub fn collide(
        &self,
        origin: Vec3,
        dir: Vec3,
        rng: &mut impl Rng,
        sampler: &mut BrickSampler,
        stats: &mut TrackStats,
    ) -> Option<f64> {
        let mut hit = None;
        self.walk(origin, dir, rng, sampler, stats, |t, ratio, rng| {
            if rng.random::<f64>() < ratio {
                hit = Some(t);
                ControlFlow::Break(())
            } else {
                ControlFlow::Continue(())
            }
        });
        hit
    }

    /// Ratio tracking: an unbiased estimate of the transmittance from `origin` to infinity.
    pub fn transmittance(
        &self,
        origin: Vec3,
        dir: Vec3,
        rng: &mut impl Rng,
        sampler: &mut BrickSampler,
        stats: &mut TrackStats,
    ) -> f64 {
        let mut tr = 1.0f64;
        self.walk(origin, dir, rng, sampler, stats, |_, ratio, rng| {
            tr *= 1.0 - ratio;
            if tr < SHADOW_ROULETTE_BELOW {
                if rng.random::<f64>() < 0.5 {
                    tr = 0.0;
                    return ControlFlow::Break(());
                }
                tr *= 2.0;
            }
            ControlFlow::Continue(())
        });
        tr
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::grid::{SparseGrid, TileLevel, Transform};
    use glam::DVec3;
    use glam::IVec3;
    use rand::SeedableRng;

    /// A 128³ node tile of density `value`, voxel size 0.5 (so 63.5 world units across the support
    /// of voxel centres 0..127).
    fn slab(value: f32) -> SparseGrid {
        let mut g = SparseGrid::new(
            Transform {
                scale: DVec3::splat(0.5),
                translation: DVec3::ZERO,
            },
            0.0,
        );
        g.insert_tile(TileLevel::Node, IVec3::ZERO, value);
        g
    }

    #[test]
    fn both_trackers_estimate_the_analytic_transmittance() {
        // Along +X through the middle of the tile, from inside it at voxel 27.5 (world 13.75):
        // density 1 up to voxel 127, then linear to 0 at 128 (trilinear), so the optical depth
        // to infinity is σt·0.5·(127 − 27.5 + 0.5) world units.
        let g = slab(1.0);
        let field = DensityField::new(g);
        let sigma_t = 0.04f32;
        let medium = Medium3d {
            field: &field,
            sigma_t,
        };
        let origin = Vec3::new(13.75, 32.0, 32.0);
        let want = (-(sigma_t as f64) * 0.5 * 100.0).exp();
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(3);
        let mut sampler = field.sampler();
        let mut stats = TrackStats::default();
        let n = 40_000;
        let (mut escaped, mut ratio) = (0usize, 0.0f64);
        for _ in 0..n {
            let hit = medium.collide(origin, Vec3::X, &mut rng, &mut sampler, &mut stats);
            escaped += hit.is_none() as usize;
            ratio += medium.transmittance(origin, Vec3::X, &mut rng, &mut sampler, &mut stats);
        }
        let p = escaped as f64 / n as f64;
        // Binomial standard error: 4σ ≈ 0.01 at p ≈ 0.135.
        assert!((p - want).abs() < 4.0 * (want * (1.0 - want) / n as f64).sqrt());
        assert!(
            (ratio / n as f64 - want).abs() < 0.005,
            "{}",
            ratio / n as f64
        );
        assert!(stats.lookups > 0);
    }

    #[test]
    fn collisions_are_exponential_in_a_uniform_medium() {
        // Mean free path 1/σt inside a uniform medium: the mean of collision distances short of
        // the far side, for a medium much thicker than a free path, is ≈ 1/σt.
        let g = slab(2.0);
        let field = DensityField::new(g.clone());
        let medium = Medium3d {
            field: &field,
            sigma_t: 1.0,
        };
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(9);
        let mut sampler = field.sampler();
        let mut stats = TrackStats::default();
        let origin = Vec3::new(2.0, 32.0, 32.0);
        let n = 20_000;
        let mean: f64 = (0..n)
            .map(|_| {
                medium
                    .collide(origin, Vec3::X, &mut rng, &mut sampler, &mut stats)
                    .unwrap()
            })
            .sum::<f64>()
            / n as f64;
        assert!((mean - 0.5).abs() < 0.02, "{mean}");
    }

    #[test]
    fn empty_space_and_zero_extinction_are_free() {
        let empty = DensityField::new(SparseGrid::new(Transform::default(), 0.0));
        let dense = DensityField::new(slab(1.0));
        let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(1);
        let mut stats = TrackStats::default();
        for (field, sigma_t) in [(&empty, 1.0), (&dense, 0.0)] {
            let medium = Medium3d { field, sigma_t };
            let mut sampler = field.sampler();
            let o = Vec3::new(-10.0, 30.0, 30.0);
            assert_eq!(
                medium.collide(o, Vec3::X, &mut rng, &mut sampler, &mut stats),
                None
            );
            assert_eq!(
                medium.transmittance(o, Vec3::X, &mut rng, &mut sampler, &mut stats),
                1.0
            );
        }
        assert_eq!(stats.lookups, 0);
    }
}
