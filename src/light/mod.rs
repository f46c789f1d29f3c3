//! Light: environment maps and the built-in sky, their spherical-harmonic projection, importance
//! sampling for the path tracer, suns, and [`Lighting`], everything a render needs to know about
//! its light.

pub mod env;
pub(crate) mod envlight;
pub mod extract;
pub mod sh;
pub mod sun;

use glam::Vec3;

use crate::error::{Error, Result};
use env::Environment;
use envlight::EnvLight;
use sh::Window;
use sun::{Sun, MAX_SUNS};

/// Everything about the light of a render: the environment map (or the built-in sky), how it is
/// turned and scaled, how its SH projection is windowed, and the suns beside it. Both renderers
/// and the background take their light from here, so they see the same world.
pub struct Lighting {
    pub env: Environment,
    /// Turn about +Y, radians, counter-clockwise seen from above (as [`sh::Sh::rotate_y`]).
    pub rotation: f64,
    /// Multiplies the map's radiance.
    pub scale: f32,
    /// Windowing of the SH coefficients against ringing.
    pub window: Window,
    /// Directional lights, world space, final irradiance (the map's own sun turned and scaled
    /// with the map). They are not in `env`: the SH part never sees them.
    pub suns: Vec<Sun>,
    /// What the search for a sun in the map found, one line: `Ok` a sun taken out of the map,
    /// `Err` why none was (`None`: no search was made).
    pub sun_search: Option<std::result::Result<String, String>>,
    /// The map's SH projection by band count, made once: a sequence renders every frame under
    /// the same map without projecting it again.
    pub projections: std::sync::Mutex<Vec<(usize, Vec<[f32; 3]>)>>,
}

/// How to light a render besides the map itself.
#[derive(Debug, Clone, PartialEq)]
pub struct LightOptions {
    /// Turn of the map (and of its own sun) about +Y, degrees.
    pub rotation_deg: f64,
    /// Multiplies the map's radiance (and its own sun's).
    pub scale: f32,
    pub window: Window,
    /// Suns given by the user, world space, not scaled. With the built-in sky they replace its sun.
    pub suns: Vec<Sun>,
    /// Look for a sun in a map file and turn it into a light ([`extract`]); `false` leaves the
    /// built-in sky's sun as pixels of its map too.
    pub extract_sun: bool,
}

impl Lighting {
    /// Loads `spec` (a latlong .exr or .hdr, or `sky`: a soft sky and its sun) lit as `options`
    /// says.
    pub fn load(spec: &str, options: &LightOptions) -> Result<Lighting> {
        let sky = spec == env::SKY_SPEC;
        let sun_in_map = sky && !options.extract_sun && options.suns.is_empty();
        let mut lighting = Lighting {
            env: match sun_in_map {
                true => Environment::sky_with_sun_in_map(),
                false => Environment::load(spec)?,
            },
            rotation: options.rotation_deg.to_radians(),
            scale: options.scale,
            window: options.window,
            suns: Vec::new(),
            sun_search: None,
            projections: Default::default(),
        };
        if sky && options.suns.is_empty() && !sun_in_map {
            lighting.add_map_sun(env::sky_sun());
        }
        if !sky && options.extract_sun {
            let search = extract::find_sun(&lighting.env);
            let line = search.describe();
            lighting.sun_search = Some(match search {
                extract::SunSearch::Found { sun, residual, .. } => {
                    lighting.env = residual;
                    lighting.add_map_sun(sun);
                    Ok(line)
                }
                extract::SunSearch::None(_) => Err(line),
            });
        }
        lighting.suns.extend_from_slice(&options.suns);
        if lighting.suns.len() > MAX_SUNS {
            return Err(Error::usage(format!(
                "{} suns: at most {MAX_SUNS} are supported",
                lighting.suns.len()
            )));
        }
        Ok(lighting)
    }

    /// Adds a sun given in the map's own frame: turned and scaled with the map.
    fn add_map_sun(&mut self, sun: Sun) {
        let mut s = sun.rotated_y(self.rotation);
        s.irradiance = s.irradiance.map(|e| e * self.scale);
        self.suns.push(s);
    }

    /// The RGB SH coefficients of the light for `bands` bands, windowed, turned and scaled: what
    /// relighting multiplies the transfer with.
    pub fn sh_coefficients(&self, bands: usize) -> Vec<[f32; 3]> {
        let mut kept = self.projections.lock().unwrap_or_else(|e| e.into_inner());
        if let Some((_, c)) = kept.iter().find(|(b, _)| *b == bands) {
            return c.clone();
        }
        let mut sh = self.env.project(bands);
        sh.apply_window(self.window);
        sh.rotate_y(self.rotation);
        let c: Vec<[f32; 3]> = sh
            .coeffs
            .iter()
            .map(|c| c.map(|v| v * self.scale))
            .collect();
        kept.push((bands, c.clone()));
        c
    }

    /// Radiance arriving from the world direction `dir` (unit): what a path escaping along `dir`
    /// sees of the map.
    pub fn radiance(&self, dir: Vec3) -> [f32; 3] {
        let mut out = [[0.0; 3]];
        self.env.lookup_batch(&[dir], self.rotation, &mut out);
        out[0].map(|v| v * self.scale)
    }

    /// What camera rays that leave the volume along `dirs` see, into `out`: the map and the discs
    /// of the suns ([`crate::render::film::Background`]).
    pub fn backgrounds(&self, dirs: &[Vec3], out: &mut [[f32; 3]]) {
        self.env.lookup_batch(dirs, self.rotation, out);
        for (c, &dir) in out.iter_mut().zip(dirs) {
            *c = c.map(|v| v * self.scale);
            for s in &self.suns {
                for (c, l) in c.iter_mut().zip(s.radiance(dir)) {
                    *c += l;
                }
            }
        }
    }

    /// The light prepared for importance sampling (the path tracer's next-event estimation).
    pub fn sampler(&self) -> EnvLight<'_> {
        EnvLight::new(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A map whose radiance varies along both axes, so a turn or a flip would show.
    fn lumpy() -> Environment {
        let (w, h) = (16, 8);
        let pixels = (0..w * h)
            .map(|i| {
                let (c, r) = ((i % w) as f32, (i / w) as f32);
                [1.0 + c, 2.0 + r * r, 0.5 + c * r]
            })
            .collect();
        Environment::from_pixels(w, h, pixels).unwrap().0
    }

    #[test]
    fn a_turned_light_shows_the_map_where_the_turn_takes_it() {
        let angle = 0.7f64;
        let lighting = Lighting {
            env: lumpy(),
            rotation: angle,
            scale: 3.0,
            window: Window::None,
            suns: Vec::new(),
            sun_search: None,
            projections: Default::default(),
        };
        for d in [
            Vec3::new(0.3, 0.5, -0.8),
            Vec3::new(-0.9, 0.1, 0.2),
            Vec3::new(0.0, -0.6, 0.7),
        ] {
            let d = d.normalize();
            let map_dir = [d.x as f64, d.y as f64, d.z as f64];
            // Counter-clockwise seen from above: the map's feature at `d` now lies at R_y(angle)·d.
            let (s, c) = angle.sin_cos();
            let world = Vec3::new(
                (c * map_dir[0] + s * map_dir[2]) as f32,
                map_dir[1] as f32,
                (-s * map_dir[0] + c * map_dir[2]) as f32,
            );
            let want = lighting.env.lookup(map_dir).map(|v| v * 3.0);
            let got = lighting.radiance(world);
            for k in 0..3 {
                assert!(
                    (got[k] - want[k]).abs() < 1e-3 * want[k],
                    "{d}: {got:?} vs {want:?}"
                );
            }
        }
    }

    #[test]
    fn a_constant_light_projects_to_its_scaled_dc_term_only() {
        let env = Environment::from_pixels(64, 32, vec![[0.5, 1.0, 2.0]; 2048])
            .unwrap()
            .0;
        let lighting = Lighting {
            env,
            rotation: 1.1,
            scale: 2.0,
            window: Window::Hamming,
            suns: Vec::new(),
            sun_search: None,
            projections: Default::default(),
        };
        let coeffs = lighting.sh_coefficients(3);
        // L = c: c_00 = ∫ c·Y00 dω = c·√(4π), times the scale; the turn and window keep band 0.
        let y00 = (4.0 * std::f64::consts::PI).sqrt() as f32;
        for (k, c) in [0.5f32, 1.0, 2.0].iter().enumerate() {
            assert!(
                (coeffs[0][k] - 2.0 * c * y00).abs() < 1e-3 * c * y00,
                "{coeffs:?}"
            );
        }
        // Projected once per band count: a second call is the kept copy.
        assert_eq!(lighting.sh_coefficients(3), coeffs);
        lighting.sh_coefficients(2);
        assert_eq!(lighting.projections.lock().unwrap().len(), 2);
        // Higher bands: only the pixel quadrature's error, well under 1e-3 of the DC term.
        let dc = coeffs[0][2];
        assert!(
            coeffs[1..].iter().flatten().all(|v| v.abs() < 1e-3 * dc),
            "{coeffs:?}"
        );
    }

    fn options(suns: Vec<Sun>, extract_sun: bool) -> LightOptions {
        LightOptions {
            rotation_deg: 90.0,
            scale: 2.0,
            window: Window::None,
            suns,
            extract_sun,
        }
    }

    #[test]
    fn the_sky_brings_its_sun_as_a_light_unless_replaced_or_kept_in_the_map() {
        let sky = env::sky_sun();
        let lit = Lighting::load(env::SKY_SPEC, &options(vec![], true)).unwrap();
        assert_eq!(lit.suns.len(), 1);
        // Turned and scaled with the map.
        let want = sky.rotated_y(90f64.to_radians());
        assert!((lit.suns[0].direction - want.direction).length() < 1e-6);
        assert_eq!(lit.suns[0].irradiance, sky.irradiance.map(|e| e * 2.0));
        // The background shows the disc; the map the path tracer escapes to does not.
        let d = lit.suns[0].direction;
        let mut seen = [[0.0; 3]];
        lit.backgrounds(&[d], &mut seen);
        assert!(seen[0][0] > 1000.0 * lit.radiance(d)[0]);
        // A sun of the user's replaces it, unscaled and unturned.
        let mine = Sun::new(Vec3::Y, [1.0, 2.0, 3.0], 0.0).unwrap();
        let replaced = Lighting::load(env::SKY_SPEC, &options(vec![mine], true)).unwrap();
        assert_eq!(replaced.suns, vec![mine]);
        // Kept in the map: no light, and the map's pixels hold its power.
        let kept = Lighting::load(env::SKY_SPEC, &options(vec![], false)).unwrap();
        assert!(kept.suns.is_empty());
        assert!(kept.radiance(d)[0] > 1000.0);
    }
}
