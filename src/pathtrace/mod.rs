//! Ground truth: an unbiased Monte Carlo volumetric path tracer of exactly the model of
//! [docs/model.md](../../docs/model.md) (σt = sigma_t·ρ, σs = albedo·σt, isotropic phase, the environment at infinity), against which
//! the transfer method's error is measured rather than guessed.
//!
//! **Estimator.** From the camera, delta tracking finds the first real collision; escaping rays
//! return transmittance 1 (an unbiased 0/1 estimate of Tr), so the film adds the background behind
//! them. At every collision the throughput β is multiplied by the albedo (σs/σt) and light is
//! gathered two ways, combined by multiple importance sampling with the power heuristic:
//! - **next-event estimation**: a direction drawn from the environment's importance distribution,
//!   its transmittance by ratio tracking, weight β·(1/4π)·Tr·E·w_light/p_light;
//! - **phase sampling**: a uniform direction (the isotropic phase, so f/p = 1); if delta tracking
//!   lets it escape, it sees E with weight β·w_phase; if it collides, the path goes on from there.
//!
//! Each sun is gathered by next-event estimation alone — a direction uniform over its disc (pdf
//! 1/Ω against radiance E/Ω), or its direction for a point — weight β·(1/4π)·Tr·E. Suns are not
//! in the map, so an escaping phase-sampled ray never sees one and nothing is counted twice.
//!
//! Light scattered once (found at the first collision) is the `direct` layer, the rest `indirect`,
//! matching the transfer's T_ri and F_ms. After [`ROULETTE_AFTER`] scatterings Russian roulette
//! survives with probability q = β, so a surviving path's weight β/q is exactly 1 and never
//! grows past it (high albedo makes fireflies otherwise). Every path's random numbers come from a
//! PCG seeded by (`--seed`, pixel, sample index): the image is the same on any thread count.

pub mod tracking;

use std::f64::consts::PI;

use glam::Vec3;
use rand::{Rng, SeedableRng};

pub use crate::light::envlight::EnvLight;
pub use tracking::{Medium3d, TrackStats};

use crate::light::sun::Sun;
use crate::render::film::{CameraSample, RayResult};
use crate::volume::bricks::BrickSampler;

/// Scatterings before Russian roulette starts: the first few bounces carry most of the light of
/// a typical cloud and stay noise-free of roulette.
pub const ROULETTE_AFTER: u32 = 3;
/// Longest path followed. At albedo 1 roulette never ends a path (q = β = 1) and it ends only by
/// escaping, after ~τ² scatterings in a medium τ thick; this bounds the time of absurd inputs
/// (τ ≈ 300) at a bias far below the noise of any practical render.
pub const MAX_PATH_SCATTERINGS: u32 = 100_000;
/// The phase function ([`crate::transfer::PHASE`], isotropic), also the density of uniform
/// direction sampling.
const PHASE: f64 = crate::transfer::PHASE as f64;

/// What `--method pathtrace` needs besides the camera.
pub struct PathTracer<'a> {
    pub medium: Medium3d<'a>,
    pub albedo: f32,
    pub light: &'a EnvLight<'a>,
    pub suns: &'a [Sun],
    /// Most scattering events per path (`--max-bounces`; 1 = single scattering).
    pub max_bounces: u32,
    pub seed: u64,
}

/// Counts for `--stats`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct PathStats {
    pub paths: u64,
    /// Real collisions at which light was gathered.
    pub scatterings: u64,
    pub lookups: u64,
}

impl std::ops::AddAssign for PathStats {
    fn add_assign(&mut self, o: PathStats) {
        self.paths += o.paths;
        self.scatterings += o.scatterings;
        self.lookups += o.lookups;
    }
}

/// The power heuristic (exponent 2) weight of a strategy with density `a` against one with `b`.
fn power_heuristic(a: f64, b: f64) -> f64 {
    let (a2, b2) = (a * a, b * b);
    if a2 + b2 > 0.0 {
        a2 / (a2 + b2)
    } else {
        0.0
    }
}

/// A direction uniform over the sphere.
fn uniform_sphere(rng: &mut impl Rng) -> Vec3 {
    let z = 1.0 - 2.0 * rng.random::<f64>();
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = 2.0 * PI * rng.random::<f64>();
    Vec3::new((r * phi.cos()) as f32, (r * phi.sin()) as f32, z as f32)
}

impl PathTracer<'_> {
    /// The random stream of one camera sample.
    fn rng(&self, s: &CameraSample) -> rand_pcg::Pcg64Mcg {
        let mut key = [0u8; 12];
        key[..4].copy_from_slice(&s.x.to_le_bytes());
        key[4..8].copy_from_slice(&s.y.to_le_bytes());
        key[8..].copy_from_slice(&s.index.to_le_bytes());
        rand_pcg::Pcg64Mcg::seed_from_u64(xxhash_rust::xxh3::xxh3_64_with_seed(&key, self.seed))
    }

    /// One camera path's estimate of the volume's radiance and transmittance.
    pub fn trace(&self, sample: CameraSample, stats: &mut PathStats) -> RayResult {
        let mut rng = self.rng(&sample);
        let mut sampler = self.medium.field.sampler();
        let mut track = TrackStats::default();
        stats.paths += 1;
        let mut out = RayResult::CLEAR;
        let first = self.medium.collide(
            sample.origin,
            sample.dir,
            &mut rng,
            &mut sampler,
            &mut track,
        );
        if let Some(t) = first {
            out.transmittance = 0.0;
            out.depth = t as f32;
            let x = sample.origin + sample.dir * t as f32;
            self.scatter_from(x, &mut out, &mut rng, &mut sampler, &mut track, stats);
        }
        stats.lookups += track.lookups;
        out
    }

    /// Follows the path from its first collision at `x`, adding light to `out`.
    fn scatter_from(
        &self,
        mut x: Vec3,
        out: &mut RayResult,
        rng: &mut impl Rng,
        sampler: &mut BrickSampler,
        track: &mut TrackStats,
        stats: &mut PathStats,
    ) {
        let mut beta = 1.0f64;
        let mut bounce = 1u32;
        let max_bounces = self.max_bounces.min(MAX_PATH_SCATTERINGS);
        loop {
            stats.scatterings += 1;
            beta *= self.albedo as f64;
            if beta <= 0.0 {
                return;
            }
            let layer = if bounce == 1 {
                &mut out.direct
            } else {
                &mut out.indirect
            };
            let mut add = |weight: f64, le: [f32; 3]| {
                for (o, l) in layer.iter_mut().zip(le) {
                    *o += (weight * l as f64) as f32;
                }
            };
            // Next-event estimation towards the environment.
            if let Some((wl, pdf_light)) = self.light.sample(rng) {
                let tr = self.medium.transmittance(x, wl, rng, sampler, track);
                if tr > 0.0 {
                    let mis = power_heuristic(pdf_light, PHASE);
                    add(beta * PHASE * tr * mis / pdf_light, self.light.radiance(wl));
                }
            }
            // Next-event estimation towards each sun: a delta (or a small disc) no phase sample hits.
            for sun in self.suns {
                let wl = sun.sample(rng.random(), rng.random());
                let tr = self.medium.transmittance(x, wl, rng, sampler, track);
                if tr > 0.0 {
                    add(beta * PHASE * tr, sun.irradiance);
                }
            }
            // Phase sampling: escape sees the environment, a collision continues the path.
            let w = uniform_sphere(rng);
            match self.medium.collide(x, w, rng, sampler, track) {
                None => {
                    let mis = power_heuristic(PHASE, self.light.pdf(w));
                    add(beta * mis, self.light.radiance(w));
                    return;
                }
                Some(t) => {
                    if bounce >= max_bounces {
                        return;
                    }
                    x += w * t as f32;
                    bounce += 1;
                    if bounce > ROULETTE_AFTER {
                        let q = beta.min(1.0);
                        if rng.random::<f64>() >= q {
                            return;
                        }
                        beta /= q;
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::light::env::Environment;
    use crate::light::sh::Window;
    use crate::light::Lighting;
    use crate::render::camera::Camera;
    use crate::render::film::{render_rows, Background};
    use crate::volume::grid::{add_hashed_leaves, SparseGrid, TileLevel, Transform};
    use crate::volume::DensityField;
    use glam::IVec3;

    /// A thin 128³ node tile beside 40 leaves of random density up to 3: varied density, empty
    /// gaps, thick in places (σt 0.1: a leaf is up to 2.4 optical depths across).
    fn lumpy() -> SparseGrid {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Node, IVec3::new(128, 0, 0), 0.3);
        add_hashed_leaves(&mut g, 40);
        g
    }

    fn camera() -> Camera {
        Camera::framing(Vec3::ZERO, Vec3::new(255.0, 127.0, 127.0), 12, 8, 45.0).unwrap()
    }

    fn constant_env(c: f32) -> Environment {
        Environment::from_pixels(32, 16, vec![[c; 3]; 32 * 16])
            .unwrap()
            .0
    }

    /// Renders `grid` at `w`×`h` with `spp` samples, the camera framing its box from +Z.
    fn render(
        grid: &SparseGrid,
        env: &Environment,
        sigma_t: f32,
        albedo: f32,
        max_bounces: u32,
        spp: u32,
        background: bool,
    ) -> crate::render::Frame {
        let field = DensityField::new(grid.clone());
        let lighting = Lighting {
            env: env.clone(),
            rotation: 0.0,
            scale: 1.0,
            window: Window::None,
            suns: Vec::new(),
            sun_search: None,
            projections: Default::default(),
        };
        let light = lighting.sampler();
        let tracer = PathTracer {
            medium: Medium3d {
                field: &field,
                sigma_t,
            },
            albedo,
            light: &light,
            suns: &[],
            max_bounces,
            seed: 5,
        };
        let cam = camera();
        let bg = crate::render::film::each_direction(|d| light.radiance(d));
        let background: Option<Background> = if background { Some(&bg) } else { None };
        let (frame, stats) = render_rows(
            &cam,
            spp,
            background,
            &indicatif::ProgressBar::hidden(),
            0..cam.height,
            true,
            || (),
            |s, st: &mut PathStats, _| tracer.trace(s, st),
        );
        assert_eq!(stats.paths, 12 * 8 * spp as u64);
        frame
    }

    #[test]
    fn white_furnace_every_pixel_is_the_environment() {
        // Albedo 1 under a constant environment c: every path's expected radiance is c. Pixels
        // are independent estimates of the same value, so their spread gives the standard error
        // of their mean.
        let g = lumpy();
        let frame = render(&g, &constant_env(2.0), 0.1, 1.0, u32::MAX, 256, true);
        let values: Vec<f64> = frame.rgba.iter().map(|p| p[0] as f64 / 2.0).collect();
        let n = values.len() as f64;
        let mean = values.iter().sum::<f64>() / n;
        let var = values.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1.0);
        let std_error = (var / n).sqrt();
        assert!(std_error < 0.01, "{std_error}");
        assert!((mean - 1.0).abs() < 4.0 * std_error, "{mean} ± {std_error}");
        // The volume covers most of the frame: the test is not about the background.
        let covered = frame.direct.iter().filter(|p| p[0] > 0.0).count();
        assert!(covered > values.len() / 2, "{covered}");
    }

    /// `n` paths, seeded by `seed`, along −Z through the middle of a 128³ tile of density 1
    /// (σt `sigma_t`, `albedo`), under a constant environment `c` and `suns`.
    fn through_tile(
        c: f32,
        sigma_t: f32,
        albedo: f32,
        suns: &[Sun],
        max_bounces: u32,
        seed: u64,
        n: u32,
    ) -> Vec<RayResult> {
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        g.insert_tile(TileLevel::Node, IVec3::ZERO, 1.0);
        let field = DensityField::new(g);
        let lighting = Lighting {
            env: constant_env(c),
            rotation: 0.0,
            scale: 1.0,
            window: Window::None,
            suns: Vec::new(),
            sun_search: None,
            projections: Default::default(),
        };
        let light = lighting.sampler();
        let tracer = PathTracer {
            medium: Medium3d {
                field: &field,
                sigma_t,
            },
            albedo,
            light: &light,
            suns,
            max_bounces,
            seed,
        };
        let mut stats = PathStats::default();
        (0..n)
            .map(|index| {
                let s = CameraSample {
                    x: 0,
                    y: 0,
                    index,
                    origin: Vec3::new(63.3, 64.2, 300.0),
                    dir: -Vec3::Z,
                };
                tracer.trace(s, &mut stats)
            })
            .collect()
    }

    #[test]
    fn pure_absorber_gives_the_analytic_transmittance() {
        // Albedo 0 ⇒ L = Tr·E (docs/model.md). A 128³ tile of density 1 seen along −Z through
        // its middle: the trilinear density ramps from 0 to 1 over the outer voxel on each side,
        // so ∫ρ = the chord of [−0.5, 127.5], 128 voxels. The tracer's 0/1 transmittance averages
        // to e^{−σt·128}.
        let sigma_t = 0.01f32;
        let n = 20_000u32;
        let mut sum = 0.0f64;
        for r in through_tile(1.0, sigma_t, 0.0, &[], u32::MAX, 1, n) {
            assert_eq!((r.direct, r.indirect), ([0.0; 3], [0.0; 3]));
            sum += r.transmittance as f64;
        }
        let want = (-(sigma_t as f64) * 128.0).exp();
        let got = sum / n as f64;
        let sigma = (want * (1.0 - want) / n as f64).sqrt();
        assert!((got - want).abs() < 4.0 * sigma, "{got} vs {want}");
    }

    #[test]
    fn a_sun_behind_the_camera_gives_the_analytic_single_scattering() {
        // Camera ray and shadow ray run along one line through a 128³ tile of density 1: with
        // T(s) the optical depth to depth s, L = ∫ σs·(1/4π)·E·e^{−2T(s)} ds = albedo·E/(4π) ·
        // (1 − e^{−2τ})/2, τ = σt·128, whatever the trilinear ramps at the faces.
        let (sigma_t, albedo, e) = (0.01f32, 0.8f32, 3.0f32);
        let suns = [Sun::new(Vec3::Z, [e; 3], 0.0).unwrap()];
        let n = 40_000u32;
        let (mut sum, mut sum2) = (0.0f64, 0.0f64);
        for r in through_tile(0.0, sigma_t, albedo, &suns, 1, 3, n) {
            let v = r.direct[0] as f64;
            sum += v;
            sum2 += v * v;
        }
        let tau = sigma_t as f64 * 128.0;
        let want = (albedo * e) as f64 * PHASE * (1.0 - (-2.0 * tau).exp()) / 2.0;
        let mean = sum / n as f64;
        let std_error = ((sum2 / n as f64 - mean * mean) / n as f64).sqrt();
        assert!(std_error < 0.02 * want, "{std_error}");
        assert!((mean - want).abs() < 4.0 * std_error, "{mean} vs {want}");
    }

    #[test]
    fn zero_density_is_the_environment_exactly() {
        let g = SparseGrid::new(Transform::default(), 0.0);
        let env = constant_env(0.7);
        let frame = render(&g, &env, 1.0, 0.9, u32::MAX, 2, true);
        // Bilinear lookup of a constant map: exact but for rounding.
        for p in &frame.rgba {
            assert!(
                p[..3].iter().all(|c| (c - 0.7).abs() < 1e-6) && p[3] == 1.0,
                "{p:?}"
            );
        }
        let alpha = render(&g, &env, 1.0, 0.9, u32::MAX, 2, false);
        assert!(alpha.rgba.iter().all(|p| *p == [0.0; 4]));
    }

    #[test]
    fn single_scattering_is_the_direct_layer_and_deterministic() {
        let g = lumpy();
        let env = constant_env(1.0);
        let one = render(&g, &env, 0.1, 0.9, 1, 8, false);
        assert!(one.indirect.iter().all(|p| *p == [0.0; 3]));
        assert!(one.direct.iter().any(|p| p[0] > 0.0));
        assert_eq!(one, render(&g, &env, 0.1, 0.9, 1, 8, false));
        let all = render(&g, &env, 0.1, 0.9, u32::MAX, 8, false);
        assert!(all.indirect.iter().any(|p| p[0] > 0.0));
    }

    #[test]
    fn power_heuristic_weights_sum_to_one() {
        for (a, b) in [(1.0, 3.0), (0.2, 0.0), (5.0, 5.0)] {
            assert!((power_heuristic(a, b) + power_heuristic(b, a) - 1.0).abs() < 1e-12);
        }
        assert_eq!(power_heuristic(0.0, 0.0), 0.0);
    }
}
