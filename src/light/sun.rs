//! Suns: directional lights at infinity, the high-frequency part of the light that ten SH bands
//! cannot hold (thesis 6.5.2, 7.1). A sun shines *from* a direction with an RGB irradiance on a
//! surface facing it; with an angular radius it is a disc of uniform radiance E/Ω seen in the
//! background and sampled by the path tracer, else a point at infinity.

use std::f64::consts::PI;

use glam::{DVec3, Vec3};

use crate::error::{Error, Result};

/// Most suns one render takes: each costs a transmittance volume and a lattice solve, and a dozen
/// suns is a sky, better left in the environment map.
pub const MAX_SUNS: usize = 8;
/// Largest angular radius of a disc, degrees: wider than this a light is soft, and belongs in the
/// environment's SH.
pub const MAX_RADIUS_DEG: f32 = 20.0;
/// `vdb_render -light`'s colour C scatters L = C·albedo·Tr per unit opacity, with no phase
/// function; an isotropic phase gives L = E/(4π)·albedo·Tr, so the same picture needs E = 4π·C.
pub const VDB_RENDER_LIGHT_TO_IRRADIANCE: f32 = 4.0 * std::f32::consts::PI;

/// A directional light.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sun {
    /// Unit vector pointing *toward* the light, world space.
    pub direction: Vec3,
    /// RGB irradiance on a surface facing the light (radiance × solid angle, the environment's
    /// radiance unit times steradians).
    pub irradiance: [f32; 3],
    /// Angular radius in radians; 0 is a point at infinity.
    pub radius: f32,
}

impl Sun {
    /// A sun toward `direction` (any length but zero) with `irradiance` and angular radius
    /// `radius_deg`, checked.
    pub fn new(direction: Vec3, irradiance: [f32; 3], radius_deg: f32) -> Result<Sun> {
        let len = direction.length();
        if !(len.is_finite() && len > 0.0) {
            return Err(Error::usage(format!(
                "sun direction {direction}: must be a finite, non-zero vector"
            )));
        }
        if irradiance.iter().any(|c| !(c.is_finite() && *c >= 0.0)) {
            return Err(Error::usage(format!(
                "sun colour {irradiance:?}: every channel must be a finite number ≥ 0"
            )));
        }
        if !(0.0..=MAX_RADIUS_DEG).contains(&radius_deg) {
            return Err(Error::usage(format!(
                "sun radius {radius_deg}°: must lie in 0..={MAX_RADIUS_DEG} degrees"
            )));
        }
        Ok(Sun {
            direction: direction / len,
            irradiance,
            radius: radius_deg.to_radians(),
        })
    }

    /// `--sun X,Y,Z[,R,G,B[,RADIUS_DEG]]`: the direction toward the light, its irradiance
    /// (default `default_irradiance`) and its angular radius in degrees (default 0).
    pub fn parse(spec: &str, default_irradiance: [f32; 3]) -> Result<Sun> {
        let v = numbers(spec, "--sun", "X,Y,Z[,R,G,B[,RADIUS_DEG]]", &[3, 6, 7])?;
        let irradiance = match v.len() {
            3 => default_irradiance,
            _ => [v[3], v[4], v[5]],
        };
        Sun::new(
            Vec3::new(v[0], v[1], v[2]),
            irradiance,
            v.get(6).copied().unwrap_or(0.0),
        )
        .map_err(|e| Error::usage(format!("--sun {spec}: {e}")))
    }

    /// `--light X,Y,Z[,R,G,B]` as `vdb_render` reads it: the direction toward the light and a
    /// colour that scatters C·albedo (default 0.7 grey, `vdb_render`'s).
    pub fn parse_vdb_render(spec: &str) -> Result<Sun> {
        const DEFAULT_COLOUR: f32 = 0.7;
        let v = numbers(spec, "--light", "X,Y,Z[,R,G,B]", &[3, 6])?;
        let colour: [f32; 3] = match v.len() {
            3 => [DEFAULT_COLOUR; 3],
            _ => [v[3], v[4], v[5]],
        };
        Sun::new(
            Vec3::new(v[0], v[1], v[2]),
            colour.map(|c| c * VDB_RENDER_LIGHT_TO_IRRADIANCE),
            0.0,
        )
        .map_err(|e| Error::usage(format!("--light {spec}: {e}")))
    }

    /// Solid angle of the disc, steradians (0 for a point).
    pub fn solid_angle(&self) -> f64 {
        cap_solid_angle(self.radius as f64)
    }

    /// Radiance seen looking along `dir` (unit, toward the sky): E/Ω inside the disc, else 0. A
    /// point sun is never seen.
    pub fn radiance(&self, dir: Vec3) -> [f32; 3] {
        let omega = self.solid_angle();
        if omega <= 0.0 || (dir.dot(self.direction) as f64) < (self.radius as f64).cos() {
            return [0.0; 3];
        }
        self.irradiance.map(|e| (e as f64 / omega) as f32)
    }

    /// A direction toward the light for next-event estimation, from two uniform numbers in
    /// [0, 1): uniform over the disc's cone (pdf 1/Ω, so the estimate is E·Tr·f exactly as for a
    /// point), or the direction itself for a point.
    pub fn sample(&self, u1: f64, u2: f64) -> Vec3 {
        if self.radius <= 0.0 {
            return self.direction;
        }
        let cos_max = (self.radius as f64).cos();
        let cos = 1.0 - u1 * (1.0 - cos_max);
        let sin = (1.0 - cos * cos).max(0.0).sqrt();
        let phi = 2.0 * PI * u2;
        let w = self.direction.as_dvec3();
        let (t, b) = orthonormal_basis(w);
        (w * cos + (t * phi.cos() + b * phi.sin()) * sin)
            .normalize()
            .as_vec3()
    }

    /// The sun turned about +Y by `angle` radians (as the environment's `--env-rotate`).
    pub fn rotated_y(&self, angle: f64) -> Sun {
        let (s, c) = angle.sin_cos();
        let d = self.direction.as_dvec3();
        Sun {
            direction: DVec3::new(c * d.x + s * d.z, d.y, -s * d.x + c * d.z)
                .normalize()
                .as_vec3(),
            ..*self
        }
    }
}

/// Solid angle of a disc on the sphere (a spherical cap) of angular radius `radius` radians.
pub fn cap_solid_angle(radius: f64) -> f64 {
    2.0 * PI * (1.0 - radius.cos())
}

/// Two unit vectors completing `w` (unit) to an orthonormal basis.
fn orthonormal_basis(w: DVec3) -> (DVec3, DVec3) {
    let a = if w.x.abs() > 0.9 { DVec3::Y } else { DVec3::X };
    let t = w.cross(a).normalize();
    (t, w.cross(t))
}

/// The comma-separated numbers of a flag's value, as many as one of `counts`.
fn numbers(spec: &str, flag: &str, form: &str, counts: &[usize]) -> Result<Vec<f32>> {
    let bad = || Error::usage(format!("{flag} {spec}: expected {form}"));
    let v: Vec<f32> = spec
        .split(',')
        .map(|p| p.trim().parse::<f32>().map_err(|_| bad()))
        .collect::<Result<_>>()?;
    if !counts.contains(&v.len()) {
        return Err(bad());
    }
    Ok(v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_direction_colour_and_radius() {
        let s = Sun::parse("0,2,0", [1.0, 2.0, 3.0]).unwrap();
        assert_eq!(
            (s.direction, s.irradiance, s.radius),
            (Vec3::Y, [1.0, 2.0, 3.0], 0.0)
        );
        let s = Sun::parse("1,0,0,4,5,6,2", [0.0; 3]).unwrap();
        assert_eq!(s.irradiance, [4.0, 5.0, 6.0]);
        assert!((s.radius - 2f32.to_radians()).abs() < 1e-7);
        let l = Sun::parse_vdb_render("0.3,0.3,0.0").unwrap();
        assert!((l.irradiance[0] - 0.7 * 4.0 * std::f32::consts::PI).abs() < 1e-5);
        assert!((l.direction - Vec3::new(1.0, 1.0, 0.0).normalize()).length() < 1e-6);
    }

    #[test]
    fn bad_suns_are_one_line_errors() {
        for spec in [
            "0,0,0",
            "nan,1,0",
            "1,0",
            "1,0,0,1,1",
            "1,0,0,-1,1,1",
            "1,0,0,1,inf,1",
            "1,0,0,1,1,1,45",
            "a,b,c",
        ] {
            let e = Sun::parse(spec, [1.0; 3]).unwrap_err().to_string();
            assert!(e.contains("--sun") && !e.contains('\n'), "{spec}: {e}");
        }
    }

    #[test]
    fn disc_samples_stay_in_the_cone_and_its_radiance_integrates_to_the_irradiance() {
        let s = Sun::new(Vec3::new(0.2, 0.9, -0.3), [2.0, 1.0, 0.5], 3.0).unwrap();
        let cos_max = s.radius.cos();
        let mut mean = Vec3::ZERO;
        let n = 64;
        for i in 0..n {
            for j in 0..n {
                let d = s.sample((i as f64 + 0.5) / n as f64, (j as f64 + 0.5) / n as f64);
                assert!(d.dot(s.direction) >= cos_max - 1e-6);
                assert!((d.length() - 1.0).abs() < 1e-5);
                mean += d;
            }
        }
        // Uniform over the cone: the mean points along the axis.
        assert!(mean.normalize().dot(s.direction) > 1.0 - 1e-6);
        // Radiance E/Ω over Ω is E.
        let inside = s.radiance(s.direction);
        assert!((inside[0] as f64 * s.solid_angle() - 2.0).abs() < 1e-5);
        assert_eq!(s.radiance(-s.direction), [0.0; 3]);
    }

    #[test]
    fn rotation_matches_the_environment_turn() {
        // −Z turns toward −X for a positive angle (docs/model.md, "Rotation").
        let s = Sun::new(-Vec3::Z, [1.0; 3], 0.0).unwrap();
        let r = s.rotated_y(std::f64::consts::FRAC_PI_2);
        assert!((r.direction - -Vec3::X).length() < 1e-6, "{}", r.direction);
    }
}
