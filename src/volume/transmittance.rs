//! Optical depth along world-space rays through a sparse grid: fixed steps on a lattice of
//! positions measured from the ray origin, evaluated only inside the spans of occupied blocks that
//! the hierarchical DDA ([`Occupancy`]) yields — the same empty-space skipping as the renderer's.
//! Samples outside spans have zero density, so skipping changes no result.

use glam::{IVec3, Vec3};
use rayon::prelude::*;

use std::ops::ControlFlow;

use crate::math::floor::ceil;
use crate::math::ray::Ray;

use super::field::DensityField;
use super::grid::{Block, SparseGrid, LEAF_LOG2, LEAF_VOXELS};
use super::keys::KeyIndex;
use super::mip::DensityMip;

/// Step length in voxels: the midpoint rule on a piecewise-trilinear density is accurate to well
/// under 1 % of the optical depth at one sample per voxel. T_ri marches hundreds of millions of
/// samples per bake, so one per voxel (not the renderer's two) halves the bake at no visible cost.
pub const STEP_VOXELS: f32 = 1.0;
/// Rays stop once transmittance falls below this: what is left cannot change a transfer value by
/// more than 1e-4 of full visibility.
pub const MIN_TRANSMITTANCE: f32 = 1e-4;

/// How many times the depth that cuts a ray off a test asks of the density at its maximum
/// ([`OpticalDepth::all_cut_off`]): one that allows for a lower density reaches further. On
/// cloud_large, whose interior is near its maximum, margins 1.1 / 1.25 / 1.5 / 2 found 4 591 /
/// 4 369 / 3 946 / 0 of its 16 806 nodes dark at σt 1 (2 the reach past [`MAX_DARK_REACH`]),
/// 5 865 / 5 657 / 5 440 / 4 665 at σt 1.6.
const DARK_MARGIN: f32 = 1.1;
/// The farthest, in voxels, the test reads around a ray's origin: a thinner medium needs rays too
/// long for the test to pay (and marches coarser levels past its first steps, which it does not
/// bound). Measured on cloud_large (T_ri, three alternating runs), raising it from 16 to 24:
/// σt 0.7 (a reach of 17) 6.36–7.31 → 5.75–5.86 s, σt 0.55 (21) 6.2–7.8 against 6.6–7.0 s.
const MAX_DARK_REACH: f32 = 24.0;

/// Where every ray is cut off close to its origin ([`OpticalDepth::all_cut_off`]).
struct DarkTest {
    /// Voxels within this distance of an origin hold what a ray's first n samples read.
    radius: f32,
    /// The least density that cuts a ray off within n samples, n = [`DARK_MARGIN`] times what
    /// the density's maximum needs.
    needed: f32,
    /// Per leaf key (voxel >> 3), its least value, 0 for a leaf with an inactive voxel: a block
    /// with a floor above the needed density is wholly inside the medium and passes at once.
    floors: KeyIndex<f32>,
}

impl DarkTest {
    /// The least density of block `key` (0 outside the medium).
    fn floor(&self, grid: &SparseGrid, key: IVec3) -> f32 {
        if let Some(m) = self.floors.get(key) {
            return m;
        }
        match grid.tile_level(key << LEAF_LOG2) {
            Some(_) => grid.value(key << LEAF_LOG2),
            None => 0.0,
        }
    }
}

/// Integrates σt·ρ along rays.
pub struct OpticalDepth<'a> {
    field: &'a DensityField,
    /// Coarser levels for the far part of each ray, and how many fine steps precede them.
    far: Option<FarField<'a>>,
    sigma_t: f32,
    /// World length of one step.
    step: f32,
    inv_scale: Vec3,
    /// Index-space box outside which the density is zero (active bbox grown by one voxel).
    lo: Vec3,
    hi: Vec3,
    /// March only the occupied spans (`false`: the whole box, to prove skipping is exact).
    skip_empty: bool,
    /// World distance from a ray's origin before which the occupied spans are not walked.
    walk_from: f64,
    /// What tells that a box's rays are all cut off (`None`: nothing is told).
    dark: Option<DarkTest>,
}

/// The far field of a ray: `near` steps at the fine level, then `near` steps at each coarser level
/// in turn (steps 2^ℓ voxels long through level ℓ), the last level to the end of the ray.
#[derive(Clone, Copy)]
pub struct FarField<'a> {
    pub mip: &'a DensityMip,
    pub near: u32,
}

impl FarField<'_> {
    /// Levels a ray of `length` voxels reaches: level ℓ ends (2^(ℓ+1) − 1)·near voxels out.
    pub fn levels_for(length: f32, near: u32) -> usize {
        let mut level = 0;
        while ((1u64 << (level + 1)) - 1) as f32 * (near as f32) < length && level < 30 {
            level += 1;
        }
        level
    }
}

impl<'a> OpticalDepth<'a> {
    pub fn new(field: &'a DensityField, sigma_t: f32, skip_empty: bool) -> Self {
        let grid = &field.grid;
        let scale = grid.transform.scale.as_vec3();
        let (lo, hi) = grid
            .active_bbox()
            .map(|(lo, hi)| (lo.as_vec3() - 1.0, hi.as_vec3() + 1.0))
            .unwrap_or((Vec3::ONE, Vec3::ZERO));
        OpticalDepth {
            field,
            far: None,
            sigma_t,
            step: STEP_VOXELS * scale.abs().min_element(),
            inv_scale: scale.recip(),
            lo,
            hi,
            skip_empty,
            walk_from: 0.0,
            dark: None,
        }
    }

    /// Readies [`Self::all_cut_off`] where it can pay: the density is marched at its own
    /// resolution (no coarser levels), and a ray is cut off within [`MAX_DARK_REACH`] voxels at
    /// the density's maximum over [`DARK_MARGIN`]. Each leaf's least value is gathered.
    pub fn with_dark_test(self) -> Self {
        let grid = &self.field.grid;
        let max = grid.value_stats().map_or(0.0, |s| s.max);
        let levels = self.far.is_some_and(|f| f.mip.len() > 0);
        let depth_per_step = self.sigma_t * max * self.step;
        if levels || depth_per_step <= 0.0 {
            return self;
        }
        let cutoff = -MIN_TRANSMITTANCE.ln();
        let samples = (DARK_MARGIN * cutoff / depth_per_step).ceil();
        // Sample k lies within (k + ½)·STEP_VOXELS voxels of its origin (a world step is one
        // smallest voxel edge), and its trilinear corners within √3 of it.
        let radius = (samples - 0.5) * STEP_VOXELS + 3f32.sqrt();
        if radius > MAX_DARK_REACH {
            return self;
        }
        let floors = grid
            .leaves()
            .par_iter()
            .map(|leaf| {
                let full = leaf.mask.iter().all(|&m| m == u64::MAX);
                let least = (0..LEAF_VOXELS)
                    .map(|slot| leaf.values.get(slot))
                    .fold(f32::INFINITY, f32::min);
                (leaf.origin >> LEAF_LOG2, if full { least } else { 0.0 })
            })
            .collect();
        let needed = cutoff / (samples * self.sigma_t * self.step);
        OpticalDepth {
            dark: Some(DarkTest {
                radius,
                needed,
                floors: KeyIndex::new(floors),
            }),
            ..self
        }
    }

    /// Whether every ray from every index point of the box `[lo, hi]` is cut off
    /// ([`MIN_TRANSMITTANCE`]) within its first n samples: where every voxel within the test's
    /// radius of the box is active and denser than σt·n·Δ needs, those samples alone cut it
    /// off. `false` where it cannot tell.
    pub fn all_cut_off(&self, (lo, hi): (Vec3, Vec3)) -> bool {
        let Some(dark) = &self.dark else {
            return false;
        };
        let grid = &self.field.grid;
        let r2 = dark.radius * dark.radius;
        // Squared distance from the voxel box [a, b] to the origins' box.
        let gap2 = |a: Vec3, b: Vec3| {
            let gap = (lo - b).max(a - hi).max(Vec3::ZERO);
            gap.length_squared()
        };
        let reach = dark.radius.ceil() as i32;
        let from = (lo.floor().as_ivec3() - reach) >> LEAF_LOG2;
        let to = (hi.ceil().as_ivec3() + reach) >> LEAF_LOG2;
        let edge = (1 << LEAF_LOG2) - 1;
        for x in from.x..=to.x {
            for y in from.y..=to.y {
                for z in from.z..=to.z {
                    let key = IVec3::new(x, y, z);
                    let origin = key << LEAF_LOG2;
                    let (a, b) = (origin.as_vec3(), (origin + edge).as_vec3());
                    if gap2(a, b) > r2 || dark.floor(grid, key) > dark.needed {
                        continue;
                    }
                    // Part of the block is within reach and not all of it dense enough: each
                    // voxel within reach must be. A constant block (a tile or the background)
                    // whose floor failed has no voxel that is.
                    let block = grid.block(key);
                    for slot in 0..LEAF_VOXELS {
                        let v = origin + super::grid::slot_offset(slot);
                        if gap2(v.as_vec3(), v.as_vec3()) > r2 {
                            continue;
                        }
                        let dense = match block {
                            Block::Leaf(leaf) => {
                                leaf.is_active(slot) && leaf.values.get(slot) > dark.needed
                            }
                            Block::Constant(_) => false,
                        };
                        if !dense {
                            return false;
                        }
                    }
                }
            }
        }
        true
    }

    /// Marches the far part of every ray through `far`'s coarser levels. A coarse level's
    /// trilinear density reaches up to one of its voxels past the fine box, so the box grows by
    /// the coarsest voxel: rays keep the tails that carry their share of ∫ρ.
    /// Without coarser levels it is the fine march as it was.
    pub fn with_far_field(self, far: FarField<'a>) -> Self {
        if far.mip.len() == 0 {
            let walk_from = (self.step * far.near as f32) as f64;
            return OpticalDepth { walk_from, ..self };
        }
        let grow = (1u32 << far.mip.len()) as f32;
        OpticalDepth {
            far: Some(far),
            lo: self.lo - grow,
            hi: self.hi + grow,
            ..self
        }
    }

    /// World distance along `dir` from index point `origin` to the far side of the density's box,
    /// and the index-space velocity per world unit. In f32, unlike [`Ray::clip`]: the bake's
    /// caches are defined by this f32 exit distance (the f64 clip moves the last bit of a few
    /// T_ri rays' step counts, and with them a cache's bytes).
    fn clip(&self, origin: Vec3, dir: Vec3) -> (f32, Vec3) {
        let v = dir * self.inv_scale;
        let mut exit = f32::INFINITY;
        for a in 0..3 {
            if v[a] > 0.0 {
                exit = exit.min((self.hi[a] - origin[a]) / v[a]);
            } else if v[a] < 0.0 {
                exit = exit.min((self.lo[a] - origin[a]) / v[a]);
            }
        }
        (exit.max(0.0), v)
    }

    /// Transmittance from index point `origin` toward world direction `dir` (unit) to infinity.
    pub fn transmittance(&self, origin: Vec3, dir: Vec3) -> f32 {
        self.transmittance_beyond(origin, dir, 0.0)
    }

    /// [`Self::transmittance`] for the rest of a ray that started `travelled` world units before
    /// `origin`: the far field's coarser levels begin where they would have on the whole ray.
    fn transmittance_beyond(&self, origin: Vec3, dir: Vec3, travelled: f32) -> f32 {
        let (exit, v) = self.clip(origin, dir);
        (-self.integrate(origin, v, exit, -MIN_TRANSMITTANCE.ln(), travelled)).exp()
    }

    /// The mean transmittance toward world direction `dir` (unit) along the chord of the index box
    /// `[lo, hi]` through index point `origin`, weighted by ρ·w: ∫ ρ·w·T ds / ∫ ρ·w·g ds over the
    /// chord, where `weight` gives w at a point and `importance` g at a point of density ρ — g ≡ 1
    /// for the plain mean (`None`), or the density that drew the chord's start over ρ·w (an
    /// importance estimate); `None` where the chord holds no weight.
    ///
    /// One ray from where the chord leaves the box toward `dir` gives the transmittance of
    /// everything beyond it; the chord is then walked back from there, one midpoint sample per
    /// step of at most `step_voxels`, the optical depth growing as it goes. The chord's depth is
    /// integrated, not drawn: inside a thick footprint T runs from 1 to nothing along the light,
    /// and a single point per direction leaves that to chance (docs/model.md, "The transfer").
    ///
    /// A plain mean lies between 0 and the transmittance beyond the chord, so where that ray was
    /// cut off ([`MIN_TRANSMITTANCE`]) the chord is not walked and the mean is that transmittance,
    /// as a ray cut off reads: deep in a thick medium most chords are dark, and their walks were a
    /// quarter of the footprint means' time at 1.6 optical depths per voxel (docs/benchmarks.md).
    pub fn chord_mean<G: FnMut(Vec3, f32) -> f32>(
        &self,
        origin: Vec3,
        dir: Vec3,
        (lo, hi): (Vec3, Vec3),
        step_voxels: f32,
        mut weight: impl FnMut(Vec3) -> f32,
        mut importance: Option<G>,
    ) -> Option<f32> {
        let v = dir * self.inv_scale;
        let (mut enter, mut exit) = (f32::NEG_INFINITY, f32::INFINITY);
        for a in 0..3 {
            if v[a] != 0.0 {
                let (s0, s1) = ((lo[a] - origin[a]) / v[a], (hi[a] - origin[a]) / v[a]);
                enter = enter.max(s0.min(s1));
                exit = exit.min(s0.max(s1));
            } else if origin[a] < lo[a] || origin[a] > hi[a] {
                return None;
            }
        }
        if exit <= enter {
            return None;
        }
        // The levels are as wide as a direction's cone from the chord's own start allows.
        let beyond = self.transmittance_beyond(origin + v * exit, dir, exit.max(0.0));
        if importance.is_none() && beyond <= MIN_TRANSMITTANCE {
            return Some(beyond);
        }
        let steps = ((exit - enter) / (step_voxels * self.step)).ceil().max(1.0);
        let step = (exit - enter) / steps;
        let mut sampler = self.field.sampler();
        // `t` is the transmittance from the start of the current step to where the chord leaves.
        let (mut t, mut weighted, mut total) = (1.0f32, 0.0f32, 0.0f32);
        for k in 0..steps as u32 {
            let p = origin + v * (exit - (k as f32 + 0.5) * step);
            let rho = sampler.sample(p);
            if rho <= 0.0 {
                continue;
            }
            let w = rho * weight(p);
            let g = importance.as_mut().map_or(1.0, |g| g(p, rho));
            // T averaged over the step exactly for the density of its midpoint: at an optical
            // depth per step near one, T at the midpoint alone is 1–2 % low.
            let (across, mean) = through_and_leaving(self.sigma_t * rho * step);
            weighted += w * t * mean;
            total += w * g;
            t *= across;
        }
        (total > 0.0).then(|| beyond * weighted / total)
    }

    /// ∫ σt·ρ over [0, end] (world units), stopping past `cutoff`: at the fine level, or with a
    /// far field, through ever coarser levels as the ray goes on — as a ray that started
    /// `travelled` before `origin` would.
    fn integrate(&self, origin: Vec3, v: Vec3, end: f32, cutoff: f32, travelled: f32) -> f32 {
        let Some(far) = self.far else {
            return self.march(self.field, origin, v, (0.0, end), self.step, cutoff, 0.0);
        };
        let (mut tau, mut t0, mut level_end) = (0.0, 0.0, -travelled);
        for level in 0..=far.mip.len() {
            level_end += self.step * (far.near << level) as f32;
            let t1 = if level == far.mip.len() {
                end
            } else {
                end.min(level_end)
            };
            if t1 <= t0 {
                continue;
            }
            tau = match level {
                0 => self.march(self.field, origin, v, (t0, t1), self.step, cutoff, tau),
                _ => {
                    let scale = (1u32 << level) as f32;
                    let o = super::mip::to_level(origin, level);
                    let field = far.mip.level(level);
                    self.march(
                        field,
                        o,
                        v / scale,
                        (t0, t1),
                        self.step * scale,
                        cutoff,
                        tau,
                    )
                }
            };
            if t1 >= end || tau > cutoff {
                break;
            }
            t0 = t1;
        }
        tau
    }

    /// Midpoint-rule ∫ σt·ρ of `field` over `range` (world units) added to `tau`, stopping past
    /// `cutoff`. Samples sit at t0 + (k + ½)·step; the last partial step is weighted by its length.
    #[allow(clippy::too_many_arguments)]
    fn march(
        &self,
        field: &DensityField,
        origin: Vec3,
        v: Vec3,
        (t0, end): (f32, f32),
        step: f32,
        cutoff: f32,
        mut tau: f32,
    ) -> f32 {
        if end <= t0 {
            return tau;
        }
        let steps = ceil(((end - t0) / step) as f64).max(0) as u32;
        let mut sampler = field.sampler();
        // Samples whose positions fall in [a, b): spans are half-open, so none is taken twice.
        let mut run = |a: f64, b: f64| {
            let first = ceil((a - t0 as f64) / step as f64 - 0.5).max(0) as u32;
            let last = (ceil((b - t0 as f64) / step as f64 - 0.5).max(0) as u32).min(steps);
            for k in first..last {
                let p = origin + v * (t0 + (k as f32 + 0.5) * step);
                let len = if k + 1 == steps {
                    end - t0 - k as f32 * step
                } else {
                    step
                };
                tau += self.sigma_t * sampler.sample(p) * len;
                if tau > cutoff {
                    return ControlFlow::Break(());
                }
            }
            ControlFlow::Continue(())
        };
        // The last, partial step's sample lies past `end`: walk to the end of that whole step.
        let reach = t0 as f64 + steps as f64 * step as f64;
        // With a far field every range is a few dozen steps at most, and walking the occupied
        // spans cost more than the empty samples it saves (torus300 and cloud_large: T_ri 8 % and
        // 16 % slower with the walk); samples outside spans are zero either way.
        if self.skip_empty && self.far.is_none() {
            // The first steps are taken without the walk, whose set-up costs more than the few
            // empty samples it could skip there; in a thick medium most rays end within them.
            let walk = self.walk_from.clamp(t0 as f64, reach);
            if run(t0 as f64, walk).is_continue() && walk < reach {
                let ray = Ray::new(origin.as_dvec3(), v.as_dvec3());
                field
                    .occupancy
                    .visit_spans(&ray, walk, reach, |span| run(span.t0, span.t1));
            }
        } else {
            let _ = run(t0 as f64, reach);
        }
        tau
    }
}

/// e^(−t) and (1 − e^(−t))/t over a step of optical depth t: what crosses it, and what of the
/// light emitted uniformly along it leaves it — T's mean over the step. From one `exp`, a third
/// of the time of `exp_m1`: the lattice's link build spends most of its time here.
pub(crate) fn through_and_leaving(t: f32) -> (f32, f32) {
    // Below this the quotient would lose digits to 1 − e^(−t), and the series to t⁴ is within
    // t⁵/720 < 2·10⁻⁸ of it; above, 1 − e^(−t) is within 10⁻⁶ relative.
    const SERIES_BELOW: f32 = 0.1;
    let through = (-t).exp();
    let leaving = match t < SERIES_BELOW {
        true => 1.0 - t * (0.5 - t * (1.0 / 6.0 - t * (1.0 / 24.0 - t / 120.0))),
        false => (1.0 - through) / t,
    };
    (through, leaving)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::{SparseGrid, TileLevel, Transform};
    use glam::{DVec3, IVec3};

    /// −ln of the transmittance to infinity: the optical depth, while it stays below the cutoff.
    fn depth_to_infinity(d: &OpticalDepth, origin: Vec3, dir: Vec3) -> f32 {
        -d.transmittance(origin, dir).ln()
    }

    fn slab() -> SparseGrid {
        // A 128³ tile of density 1 at x ∈ [128, 255], a few empty leaves' worth of space before it.
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Node, IVec3::new(128, 0, 0), 1.0);
        g
    }

    #[test]
    fn uniform_tile_has_analytic_depth() {
        let field = DensityField::new(slab());
        let d = OpticalDepth::new(&field, 0.01, true);
        // From x = 60 toward +x: density ramps 0→1 over [127, 128], is 1 to 255, ramps to 0 at 256.
        // The ramps integrate to ½ each, so ∫ρ = 128 voxels exactly.
        let tau = depth_to_infinity(&d, Vec3::new(60.0, 64.0, 64.0), Vec3::X);
        assert!((tau - 1.28).abs() < 1e-4, "{tau}");
    }

    #[test]
    fn skipping_changes_nothing() {
        let mut g = slab();
        let mut mask = [0u64; 8];
        mask[3] = 0xff00_ff00_0000_00ff;
        let mut values = [0.0; 512];
        for (i, v) in values.iter_mut().enumerate() {
            *v = (i % 7) as f32 * 0.1;
        }
        g.insert_leaf(IVec3::new(16, 56, 64), mask, values);
        let field = DensityField::new(g);
        let skip = OpticalDepth::new(&field, 0.3, true);
        let plain = OpticalDepth::new(&field, 0.3, false);
        for i in 0..200 {
            let a = i as f32 * 0.37;
            let dir = Vec3::new(a.cos(), (a * 1.3).sin() * 0.3, a.sin()).normalize();
            let o = Vec3::new(20.0 + (i % 5) as f32, 60.0, 66.0);
            let (x, y) = (skip.transmittance(o, dir), plain.transmittance(o, dir));
            assert_eq!(x, y, "ray {i}");
        }
    }

    #[test]
    fn the_far_field_keeps_the_depth_of_a_uniform_slab() {
        // The slab seen from 68 voxels away: the ray crosses it at levels 3 and 4 (near = 4:
        // levels end 4, 12, 28, 60, 124, 252 voxels out), whose box means keep ∫ρ = 128.
        let field = DensityField::new(slab());
        let mip = DensityMip::build(&field.grid, FarField::levels_for(300.0, 4));
        assert_eq!(mip.len(), 6);
        let far = FarField { mip: &mip, near: 4 };
        let d = OpticalDepth::new(&field, 0.01, true).with_far_field(far);
        let tau = depth_to_infinity(&d, Vec3::new(60.0, 64.0, 64.0), Vec3::X);
        assert!((tau - 1.28).abs() < 0.01, "{tau}");
    }

    #[test]
    fn the_far_field_starts_after_near_steps() {
        // Within `near` steps of its origin a ray is marched at the fine level, bit for bit.
        let field = DensityField::new(slab());
        let mip = DensityMip::build(&field.grid, 3);
        let fine = OpticalDepth::new(&field, 0.01, true);
        let far = fine.with_far_field(FarField {
            mip: &mip,
            near: 40,
        });
        let fine = OpticalDepth::new(&field, 0.01, true);
        let (o, dir) = (Vec3::new(200.0, 64.0, 64.0), Vec3::new(0.0, 0.6, 0.8));
        let (exit, v) = fine.clip(o, dir);
        assert!(exit > 40.0);
        assert_eq!(
            fine.integrate(o, v, 39.5, f32::INFINITY, 0.0),
            far.integrate(o, v, 39.5, f32::INFINITY, 0.0)
        );
        assert_ne!(
            fine.integrate(o, v, exit, f32::INFINITY, 0.0),
            far.integrate(o, v, exit, f32::INFINITY, 0.0)
        );
    }

    #[test]
    fn a_far_field_without_levels_is_the_fine_march() {
        // A medium too thick for any level (a bake at σt 1) must bake exactly as without one.
        let field = DensityField::new(slab());
        let mip = DensityMip::build(&field.grid, 0);
        let plain = OpticalDepth::new(&field, 0.003, true);
        let far = OpticalDepth::new(&field, 0.003, true).with_far_field(FarField {
            mip: &mip,
            near: 12,
        });
        for i in 0..100 {
            let a = i as f32 * 0.61;
            let dir = Vec3::new(a.cos(), (a * 1.7).sin() * 0.5, a.sin()).normalize();
            let o = Vec3::new(130.0 + i as f32, 60.0, 66.0);
            let (x, y) = (plain.transmittance(o, dir), far.transmittance(o, dir));
            assert_eq!(x.to_bits(), y.to_bits(), "ray {i}");
        }
    }

    #[test]
    fn a_chord_in_a_uniform_slab_has_the_analytic_mean() {
        // Inside the slab (ρ = 1 on [128, 255], ramping to 0 by 256) toward +x from the chord
        // x ∈ [150, 170]: T(x) = e^(−σ(255.5 − x)), whose mean over the chord is
        // e^(−σ·85.5)·(1 − e^(−20σ))/(20σ).
        let field = DensityField::new(slab());
        let sigma = 0.05;
        let d = OpticalDepth::new(&field, sigma, true);
        let box_ = (Vec3::new(150.0, 50.0, 50.0), Vec3::new(170.0, 80.0, 80.0));
        let mean = d
            .chord_mean(
                Vec3::new(163.2, 64.0, 64.0),
                Vec3::X,
                box_,
                1.0,
                |_| 1.0,
                PLAIN,
            )
            .unwrap();
        let want = (-sigma * 85.5).exp() * (1.0 - (-20.0 * sigma).exp()) / (20.0 * sigma);
        assert!((mean / want - 1.0).abs() < 1e-3, "{mean} vs {want}");
        // A chord that misses the box holds nothing.
        let outside = Vec3::new(163.2, 90.0, 64.0);
        assert_eq!(
            d.chord_mean(outside, Vec3::X, box_, 1.0, |_| 1.0, PLAIN),
            None
        );
    }

    /// No importance: a plain mean.
    const PLAIN: Option<fn(Vec3, f32) -> f32> = None;

    #[test]
    fn a_dark_chord_reads_as_a_ray_cut_off() {
        // Deep in the slab toward +x the light beyond the chord x ∈ [140, 160] has crossed 95
        // optical depths: the ray is cut off, and a plain mean, which lies between 0 and what
        // comes from beyond, is what comes from beyond, the chord not walked. An importance
        // estimate is not bounded so and walks it, darker by the chord's own fall.
        let field = DensityField::new(slab());
        let d = OpticalDepth::new(&field, 1.0, true);
        let box_ = (Vec3::new(140.0, 50.0, 50.0), Vec3::new(160.0, 80.0, 80.0));
        let origin = Vec3::new(151.3, 64.0, 64.0);
        let beyond = d.transmittance(Vec3::new(160.0, 64.0, 64.0), Vec3::X);
        assert!(beyond > 0.0 && beyond <= MIN_TRANSMITTANCE, "{beyond}");
        let plain = d.chord_mean(origin, Vec3::X, box_, 1.0, |_| 1.0, PLAIN);
        assert_eq!(plain, Some(beyond));
        let walked = d
            .chord_mean(origin, Vec3::X, box_, 1.0, |_| 1.0, Some(|_, _| 1.0))
            .unwrap();
        assert!(walked > 0.0 && walked < 0.2 * beyond, "{walked} {beyond}");
    }

    #[test]
    fn the_dark_test_tells_only_where_every_ray_is_cut_off() {
        // Inside the slab at one optical depth per voxel a ray is cut off within ten voxels: far
        // from the faces every ray from a point, or from a box of points, is; seven voxels from
        // the face at x = 128 the ray toward it is not (e^(−7.5) > 10⁻⁴), and the test says so.
        let field = DensityField::new(slab());
        let d = OpticalDepth::new(&field, 1.0, true).with_dark_test();
        let inside = Vec3::new(190.0, 64.0, 64.0);
        assert!(d.all_cut_off((inside, inside)));
        assert!(d.all_cut_off((inside - 6.0, inside + 6.0)));
        for i in 0..300 {
            let a = i as f32 * 0.41;
            let dir = Vec3::new(a.cos(), (a * 1.9).sin(), a.sin()).normalize();
            for o in [inside, inside - 6.0, inside + Vec3::new(6.0, -6.0, 6.0)] {
                assert!(
                    d.transmittance(o, dir) <= MIN_TRANSMITTANCE,
                    "ray {i} from {o}"
                );
            }
        }
        // The point nearest the face that the test calls dark: its rays toward the face, the
        // brightest there are, are cut off too.
        let first = (129..190)
            .map(|x| Vec3::new(x as f32, 64.0, 64.0))
            .find(|&p| d.all_cut_off((p, p)))
            .unwrap();
        for dir in [-Vec3::X, Vec3::new(-1.0, 0.3, 0.2).normalize()] {
            assert!(d.transmittance(first, dir) <= MIN_TRANSMITTANCE, "{first}");
        }
        let near_face = Vec3::new(135.0, 64.0, 64.0);
        assert!(d.transmittance(near_face, -Vec3::X) > MIN_TRANSMITTANCE);
        assert!(!d.all_cut_off((near_face, near_face)));
        assert!(!d.all_cut_off((inside - 6.0, inside + Vec3::new(60.0, 6.0, 6.0))));
        // Where a ray is cut off only past the test's reach (a thinner medium), or marches coarser
        // levels, nothing is told.
        let thin = OpticalDepth::new(&field, 0.05, true).with_dark_test();
        assert!(!thin.all_cut_off((inside, inside)));
        let mip = DensityMip::build(&field.grid, 2);
        let far = FarField {
            mip: &mip,
            near: 12,
        };
        let coarse = OpticalDepth::new(&field, 1.0, true)
            .with_far_field(far)
            .with_dark_test();
        assert!(!coarse.all_cut_off((inside, inside)));
    }

    #[test]
    fn a_chord_across_a_lit_face_has_the_analytic_mean() {
        // Across the slab's lit face at half an optical depth per voxel, toward the light (−x)
        // and slanted: T runs from 1 to e^(−6) along the chord, weighted by ρ·w with a tent w.
        // The density depends on x alone, ρ = clamp(x − 127, 0, 1), so the depth from x toward
        // −x is σ·F(x)/|d_x| with F its integral; the reference integrates the chord in f64 at
        // 10⁻³ voxel. (The exact mean per step is 0.15 % off it here; T at the steps' midpoints 1 %.)
        let field = DensityField::new(slab());
        let sigma = 0.5;
        let d = OpticalDepth::new(&field, sigma, true);
        let (lo, hi) = (Vec3::new(118.0, 54.0, 54.0), Vec3::new(140.0, 74.0, 74.0));
        let centre = 0.5 * (lo + hi);
        let tent = |q: DVec3| {
            let o = ((q - centre.as_dvec3()) / (0.5 * (hi - lo).as_dvec3())).abs();
            (1.0 - o.x) * (1.0 - o.y) * (1.0 - o.z)
        };
        let dir = Vec3::new(-0.9, 0.3, -0.2).normalize();
        let origin = Vec3::new(131.0, 63.0, 65.0);
        let mean = d
            .chord_mean(
                origin,
                dir,
                (lo, hi),
                1.0,
                |q| tent(q.as_dvec3()) as f32,
                PLAIN,
            )
            .unwrap();
        let rho = |x: f64| (x - 127.0).clamp(0.0, 1.0);
        let integral = |x: f64| match x {
            x if x < 127.0 => 0.0,
            x if x < 128.0 => 0.5 * (x - 127.0).powi(2),
            x => 0.5 + (x - 128.0),
        };
        let (mut sum, mut total) = (0.0, 0.0);
        for i in -40_000..40_000 {
            let p = origin.as_dvec3() + dir.as_dvec3() * (i as f64 * 1e-3);
            if (p.cmpge(lo.as_dvec3()) & p.cmple(hi.as_dvec3())).all() {
                let w = rho(p.x) * tent(p);
                sum += w * (-sigma as f64 * integral(p.x) / dir.x.abs() as f64).exp();
                total += w;
            }
        }
        let want = (sum / total) as f32;
        assert!(
            want > 0.2 && want < 0.8,
            "{want}: the chord must cross the face"
        );
        assert!((mean / want - 1.0).abs() < 0.005, "{mean} vs {want}");
    }

    #[test]
    fn far_field_levels_cover_the_ray() {
        assert_eq!(FarField::levels_for(4.0, 4), 0);
        assert_eq!(FarField::levels_for(12.0, 4), 1);
        assert_eq!(FarField::levels_for(12.5, 4), 2);
    }

    #[test]
    fn world_units_follow_the_voxel_size() {
        let mut g = slab();
        g.transform.scale = glam::DVec3::splat(0.5);
        let field = DensityField::new(g);
        let d = OpticalDepth::new(&field, 0.01, true);
        // 128 voxels of density 1 are 64 world units: τ = 0.64.
        let tau = depth_to_infinity(&d, Vec3::new(60.0, 64.0, 64.0), Vec3::X);
        assert!((tau - 0.64).abs() < 1e-4, "{tau}");
    }

    #[test]
    fn a_steps_through_and_leaving_shares_are_exact_on_both_sides_of_the_series() {
        for t in [
            0.0f64, 1e-6, 1e-3, 0.05, 0.0999, 0.1, 0.1001, 0.5, 2.0, 9.0, 40.0,
        ] {
            let (through, leaving) = through_and_leaving(t as f32);
            let exact_leaving = if t == 0.0 { 1.0 } else { -(-t).exp_m1() / t };
            assert!(((through as f64) / (-t).exp() - 1.0).abs() < 1e-6, "{t}");
            assert!(
                ((leaving as f64) / exact_leaving - 1.0).abs() < 1e-6,
                "{t}: {leaving}"
            );
        }
    }
}
