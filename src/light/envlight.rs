//! The environment as a light the path tracer can aim at: radiance by direction (rotated and
//! scaled as `render` shows it) and importance sampling of directions in proportion to the latlong
//! image's brightness times each pixel's solid angle (the sin θ term), with the exact solid-angle
//! density of what it samples, so multiple importance sampling can weigh it against phase sampling.
//!
//! A pixel is chosen with probability P = w/Σw, w = mean(RGB) · Ω_pixel, then a point uniform in
//! its (u, v) rectangle; since dω = 2π² sin θ du dv, the density over directions is
//! p(ω) = P · W·H / (2π² sin θ(ω)).

use std::f64::consts::PI;

use glam::Vec3;
use rand::distr::weighted::WeightedIndex;
use rand::distr::Distribution;
use rand::Rng;

use crate::light::env::dir_to_uv;
use crate::light::sh;
use crate::light::Lighting;

/// An environment ready for next-event estimation.
pub struct EnvLight<'a> {
    lighting: &'a Lighting,
    /// Pixel choice, `None` when the map is black everywhere (phase sampling alone then finds
    /// nothing, which is right).
    pixels: Option<WeightedIndex<f64>>,
    /// Per pixel, P · W·H / (2π²): divided by sin θ it is the density over directions.
    density: Vec<f64>,
}

impl<'a> EnvLight<'a> {
    pub fn new(lighting: &'a Lighting) -> Self {
        let env = &lighting.env;
        let (w, h) = (env.width(), env.height());
        let weights: Vec<f64> = env
            .pixels()
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let solid_angle = sh::latlong_pixel_solid_angle(i / w, w, h);
                (p[0] as f64 + p[1] as f64 + p[2] as f64) / 3.0 * solid_angle
            })
            .collect();
        let total: f64 = weights.iter().sum();
        let to_density = (w * h) as f64 / (2.0 * PI * PI * total);
        let density = if total > 0.0 {
            weights.iter().map(|x| x * to_density).collect()
        } else {
            Vec::new()
        };
        EnvLight {
            lighting,
            // Fails only when every weight is zero (a black map): nothing to aim at.
            pixels: WeightedIndex::new(&weights).ok(),
            density,
        }
    }

    /// Radiance arriving from the world direction `dir` (unit).
    pub fn radiance(&self, dir: Vec3) -> [f32; 3] {
        self.lighting.radiance(dir)
    }

    /// A direction drawn in proportion to the map's brightness, with its density over the sphere;
    /// `None` for a black map.
    pub fn sample(&self, rng: &mut impl Rng) -> Option<(Vec3, f64)> {
        let index = self.pixels.as_ref()?.sample(rng);
        let (w, h) = (self.lighting.env.width(), self.lighting.env.height());
        let (col, row) = (index % w, index / w);
        let u = (col as f64 + rng.random::<f64>()) / w as f64;
        let v = (row as f64 + rng.random::<f64>()) / h as f64;
        let theta = PI * v;
        let map_dir = sh::direction(theta, 2.0 * PI * u);
        let [x, y, z] = sh::rotate_dir_y(map_dir, self.lighting.rotation);
        let dir = Vec3::new(x as f32, y as f32, z as f32).normalize();
        // The density of the f32 direction as `pdf` evaluates it (not of the exact (u, v)): near a
        // pole f32 moves θ by a relative 1e-3, and MIS needs both strategies to weigh a direction
        // with the same densities.
        let pdf = self.pdf(dir);
        (pdf > 0.0).then_some((dir, pdf))
    }

    /// The density over the sphere with which [`EnvLight::sample`] draws the world direction `dir`.
    pub fn pdf(&self, dir: Vec3) -> f64 {
        if self.density.is_empty() {
            return 0.0;
        }
        let world = [dir.x as f64, dir.y as f64, dir.z as f64];
        let (u, v) = dir_to_uv(sh::rotate_dir_y(world, -self.lighting.rotation));
        let (w, h) = (self.lighting.env.width(), self.lighting.env.height());
        let col = ((u * w as f64) as usize).min(w - 1);
        let row = ((v * h as f64) as usize).min(h - 1);
        let sin_theta = (PI * v).sin();
        if sin_theta <= 0.0 {
            return 0.0;
        }
        self.density[row * w + col] / sin_theta
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::light::env::Environment;
    use crate::light::sh::Window;
    use rand::SeedableRng;

    fn lighting(env: Environment, rotation: f64, scale: f32) -> Lighting {
        Lighting {
            env,
            rotation,
            scale,
            window: Window::None,
            suns: Vec::new(),
            sun_search: None,
            projections: Default::default(),
        }
    }

    fn rng() -> rand_pcg::Pcg64Mcg {
        rand_pcg::Pcg64Mcg::seed_from_u64(17)
    }

    /// Bright upper-left quadrant, dim elsewhere, black in the last column band: a map whose
    /// sampling density varies strongly and vanishes somewhere.
    fn lumpy_env() -> Environment {
        let (w, h) = (16, 8);
        let pixels = (0..w * h)
            .map(|i| {
                let (c, r) = (i % w, i / w);
                let v = if c >= 12 {
                    0.0
                } else if c < 6 && r < 4 {
                    5.0
                } else {
                    0.5
                };
                [v, v * 0.5, v * 2.0]
            })
            .collect();
        Environment::from_pixels(w, h, pixels).unwrap().0
    }

    #[test]
    fn one_over_pdf_integrates_the_lit_solid_angle() {
        // E[1/p(ω)] = ∫_{p>0} dω: 4π for a map lit everywhere, less where it is black.
        let constant = Environment::from_pixels(8, 4, vec![[1.0; 3]; 32])
            .unwrap()
            .0;
        for (env, expected) in [(constant, 4.0 * PI), (lumpy_env(), 4.0 * PI * 12.0 / 16.0)] {
            let lit = lighting(env, 0.7, 2.0);
            let light = EnvLight::new(&lit);
            let mut rng = rng();
            let n = 200_000;
            let mut sum = 0.0;
            for _ in 0..n {
                // `None` (a direction rounded onto a pole or into a black pixel) adds 0.
                if let Some((_, pdf)) = light.sample(&mut rng) {
                    sum += 1.0 / pdf;
                }
            }
            let mean = sum / n as f64;
            assert!((mean / expected - 1.0).abs() < 0.01, "{mean} vs {expected}");
        }
    }

    #[test]
    fn samples_follow_brightness_chi_square() {
        // Histogram of sampled pixels (in map space, undoing the rotation) against the expected
        // probabilities P = w/Σw: χ² over the lit pixels with 12·8 − 1 = 95 degrees of freedom.
        let lit = lighting(lumpy_env(), 1.3, 1.0);
        let env = &lit.env;
        let light = EnvLight::new(&lit);
        let (w, h) = (16usize, 8usize);
        let n = 400_000usize;
        let mut counts = vec![0usize; w * h];
        let mut rng = rng();
        for _ in 0..n {
            let Some((dir, _)) = light.sample(&mut rng) else {
                continue;
            };
            let d = sh::rotate_dir_y([dir.x as f64, dir.y as f64, dir.z as f64], -1.3);
            let (u, v) = dir_to_uv(d);
            let (c, r) = (
                ((u * w as f64) as usize).min(w - 1),
                ((v * h as f64) as usize).min(h - 1),
            );
            counts[r * w + c] += 1;
        }
        let weights: Vec<f64> = env
            .pixels()
            .iter()
            .enumerate()
            .map(|(i, p)| {
                (p[0] + p[1] + p[2]) as f64 / 3.0 * sh::latlong_pixel_solid_angle(i / w, w, h)
            })
            .collect();
        let total: f64 = weights.iter().sum();
        let mut chi2 = 0.0;
        for (i, &c) in counts.iter().enumerate() {
            let expected = n as f64 * weights[i] / total;
            if expected == 0.0 {
                assert_eq!(c, 0, "a black pixel was sampled");
            } else {
                chi2 += (c as f64 - expected).powi(2) / expected;
            }
        }
        // 95 degrees of freedom: the 99.9 % quantile is about 145.
        assert!(chi2 < 145.0, "chi² = {chi2}");
    }

    #[test]
    fn a_black_map_offers_no_samples() {
        let env = Environment::from_pixels(4, 2, vec![[0.0; 3]; 8]).unwrap().0;
        let lit = lighting(env, 0.0, 1.0);
        let light = EnvLight::new(&lit);
        assert!(light.sample(&mut rng()).is_none());
        assert_eq!(light.pdf(Vec3::Y), 0.0);
    }
}
