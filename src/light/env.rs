//! Environment maps (docs/model.md, "Environment maps"): latitude–longitude radiance images read from OpenEXR
//! or Radiance `.hdr`, or the built-in procedural sky; bilinear lookup by direction; projection onto
//! SH by the deterministic pixel quadrature of [`crate::light::sh`].

use std::f32::consts::{FRAC_1_PI, TAU};
use std::f64::consts::PI;
use std::fs::File;
use std::io::{BufRead, BufReader, Read};
use std::path::Path;

use glam::Vec3;

use crate::error::{Error, Result};
use crate::light::sh::{self, ShRgb};
use crate::light::sun::{cap_solid_angle, Sun};
use crate::math::arc;
use crate::math::floor::floor;

/// The `--env` value that selects the built-in sky instead of a file.
pub const SKY_SPEC: &str = "sky";

/// The largest map accepted: 16384×8192 RGB f32 is 1.6 GB, already beyond any production HDRI
/// (16k maps are the largest in common use); a forged header asking for more is refused before
/// any allocation.
pub const MAX_ENV_PIXELS: usize = 16384 * 8192;

/// Finite stand-in for +Inf radiance. Large enough to dominate any real map, small enough that
/// sums over a whole map (≤ 2²⁷ pixels, weights ≤ 4π, |Yᵢ| < 2 up to 20 bands) stay finite in f32.
pub const RADIANCE_CAP: f32 = 1.0e30;

/// Built-in sky resolution: 0.7° per pixel resolves the sun disc and far exceeds what 20 SH bands
/// (≈ 9° features) can carry.
const SKY_WIDTH: usize = 512;
const SKY_HEIGHT: usize = 256;

/// A latitude–longitude radiance map, linear RGB, row 0 at the zenith (+Y).
#[derive(Debug, Clone, PartialEq)]
pub struct Environment {
    width: usize,
    height: usize,
    pixels: Vec<[f32; 3]>,
}

/// How many pixel values [`Environment::from_pixels`] had to repair.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Repairs {
    pub nan: usize,
    pub infinite: usize,
    pub negative: usize,
}

impl Repairs {
    pub fn total(&self) -> usize {
        self.nan + self.infinite + self.negative
    }
}

impl Environment {
    /// `spec` is [`SKY_SPEC`] for the built-in sky, else the path of a latlong `.exr` or `.hdr`
    /// (recognised by content, not extension). Bad pixel values are repaired with one warning on
    /// stderr; see [`Environment::from_pixels`].
    pub fn load(spec: &str) -> Result<Self> {
        if spec == SKY_SPEC {
            return Ok(Self::sky());
        }
        let path = Path::new(spec);
        let (env, repairs) = Self::read_file(path)?;
        if repairs.total() > 0 {
            eprintln!(
                "vscatter: warning: {}: {} NaN, {} infinite and {} negative pixel values clamped \
                 (NaN and negative to 0, +Inf to {RADIANCE_CAP:e})",
                path.display(),
                repairs.nan,
                repairs.infinite,
                repairs.negative
            );
        }
        Ok(env)
    }

    /// Reads a latlong OpenEXR (RGB or RGBA, any sample type; first RGB layer) or Radiance `.hdr`.
    pub fn read_file(path: &Path) -> Result<(Self, Repairs)> {
        let mut magic = [0u8; 4];
        let mut file = File::open(path).map_err(|e| Error::io(path, e))?;
        let n = read_up_to(&mut file, &mut magic).map_err(|e| Error::io(path, e))?;
        let (width, height, pixels) = if n == 4 && magic == [0x76, 0x2f, 0x31, 0x01] {
            read_exr(path)?
        } else if n >= 2 && &magic[..2] == b"#?" {
            read_hdr(path)?
        } else {
            return Err(Error::format(
                path,
                "not an OpenEXR or Radiance .hdr image (unknown magic number)",
            ));
        };
        Self::from_pixels(width, height, pixels).map_err(|e| match e {
            Error::Runtime(msg) => Error::format(path, msg),
            other => other,
        })
    }

    /// A map from raw pixels (row-major, `width·height`). NaN and negative values become 0 and
    /// ±Inf becomes [`RADIANCE_CAP`] (−Inf, being negative, 0): radiance is never negative, and one
    /// bad pixel must not poison every SH coefficient.
    pub fn from_pixels(
        width: usize,
        height: usize,
        mut pixels: Vec<[f32; 3]>,
    ) -> Result<(Self, Repairs)> {
        if width == 0 || height == 0 || pixels.len() != width * height {
            return Err(Error::Runtime(format!(
                "a {width}x{height} environment needs {} pixels, got {}",
                width * height,
                pixels.len()
            )));
        }
        let mut repairs = Repairs::default();
        for v in pixels.iter_mut().flatten() {
            if v.is_nan() {
                repairs.nan += 1;
                *v = 0.0;
            } else if *v == f32::INFINITY {
                repairs.infinite += 1;
                *v = RADIANCE_CAP;
            } else if *v < 0.0 {
                repairs.negative += 1;
                *v = 0.0;
            } else if *v > RADIANCE_CAP {
                *v = RADIANCE_CAP;
            }
        }
        Ok((
            Environment {
                width,
                height,
                pixels,
            },
            repairs,
        ))
    }

    /// The built-in sky at its default resolution.
    pub fn sky() -> Self {
        Self::sky_with_size(SKY_WIDTH, SKY_HEIGHT)
    }

    /// The built-in sky sampled at `width × height` (≥ 1 each): the same function at any size, so
    /// benchmarks can build large maps without files.
    pub fn sky_with_size(width: usize, height: usize) -> Self {
        Self::sky_map(width, height, None)
    }

    /// The built-in sky with its sun as pixels of the map rather than a light: what the SH
    /// transfer alone can do with it (`--no-extract-sun`).
    pub fn sky_with_sun_in_map() -> Self {
        Self::sky_map(SKY_WIDTH, SKY_HEIGHT, Some(sky_sun()))
    }

    /// The sky's pixels, with `sun` painted in as a disc of radiance E/Ω, its edge softened over
    /// about one pixel so it does not alias into a jagged disc.
    fn sky_map(width: usize, height: usize, sun: Option<Sun>) -> Self {
        let (width, height) = (width.max(1), height.max(1));
        let soft = PI / height as f64;
        // The disc's radiance E/Ω, its direction and radius, once for the whole map.
        let disc = sun.map(|s| {
            let radiance = s.irradiance.map(|e| e as f64 / s.solid_angle());
            (s.direction.as_dvec3(), s.radius as f64, radiance)
        });
        let mut pixels = Vec::with_capacity(width * height);
        for row in 0..height {
            let (theta, _, _) = sh::latlong_row(row, height);
            for col in 0..width {
                let phi = 2.0 * PI * (col as f64 + 0.5) / width as f64;
                let d = sh::direction(theta, phi);
                let mut c = sky_radiance(d);
                if let Some((centre, r, radiance)) = disc {
                    let cos = glam::DVec3::from(d).dot(centre);
                    let inside = 1.0
                        - smoothstep(r - 0.5 * soft, r + 0.5 * soft, cos.clamp(-1.0, 1.0).acos());
                    for (c, l) in c.iter_mut().zip(radiance) {
                        *c += (inside * l) as f32;
                    }
                }
                pixels.push(c);
            }
        }
        Environment {
            width,
            height,
            pixels,
        }
    }

    pub fn width(&self) -> usize {
        self.width
    }

    pub fn height(&self) -> usize {
        self.height
    }

    /// The pixels, row-major, row 0 at the zenith.
    pub fn pixels(&self) -> &[[f32; 3]] {
        &self.pixels
    }

    /// Bilinear radiance arriving from the unit direction `dir`; periodic in u, clamped in v.
    pub fn lookup(&self, dir: [f64; 3]) -> [f32; 3] {
        let [x, y] = self.texel(dir.map(|c| c as f32));
        self.blend(x, y)
    }

    /// [`Environment::lookup`] of each of `dirs` into `out`, the map turned by `angle` radians
    /// about +Y with the convention of [`crate::light::sh::Sh::rotate_y`] (positive:
    /// counter-clockwise seen from above), so a rendered background matches rotated SH lighting.
    /// The map's coordinates of the whole batch first, in one loop that vectorises
    /// ([`crate::math::arc`]), then the blends: every background pixel of a render makes one
    /// lookup, and one at a time, glibc's `acosf` and `atan2f` and their f64 arithmetic took a
    /// tenth of the bench cloud's render.
    pub fn lookup_batch(&self, dirs: &[Vec3], angle: f64, out: &mut [[f32; 3]]) {
        // Texel coordinates, a chunk at a time on the stack.
        const CHUNK: usize = 64;
        // No turn is the common case, and it skips the sin_cos (the path tracer looks up one
        // direction at a time); otherwise the map turns by −angle, in f64 as `sh::rotate_dir_y`
        // turns the SH lighting.
        let turn = (angle != 0.0).then(|| angle.sin_cos());
        for (dirs, out) in dirs.chunks(CHUNK).zip(out.chunks_mut(CHUNK)) {
            let mut at = [[0f32; 2]; CHUNK];
            for (at, d) in at.iter_mut().zip(dirs) {
                let d = match turn {
                    None => d.to_array(),
                    Some((s, c)) => {
                        let [x, y, z] = d.as_dvec3().to_array();
                        [(c * x - s * z) as f32, y as f32, (s * x + c * z) as f32]
                    }
                };
                *at = self.texel(d);
            }
            for (o, &[x, y]) in out.iter_mut().zip(&at) {
                *o = self.blend(x, y);
            }
        }
    }

    /// The map's continuous pixel coordinates (x, y) of a unit direction: pixel centres at
    /// integers + ½ shifted to integers, so bilinear weights are the fractions.
    #[inline(always)]
    fn texel(&self, dir: [f32; 3]) -> [f32; 2] {
        let (phi, theta) = dir_to_angles(dir);
        // φ ∈ [0, 2π], so x ∈ [−0.5, w − 0.5] and its floor lies in [−1, w − 1]: the columns wrap
        // with one compare each in `blend`.
        let x = phi * (self.width as f32 * (0.5 * FRAC_1_PI)) - 0.5;
        let y =
            (theta * (self.height as f32 * FRAC_1_PI) - 0.5).clamp(0.0, (self.height - 1) as f32);
        [x, y]
    }

    /// The bilinear blend at pixel coordinates `x`, `y` ([`Environment::texel`]).
    #[inline]
    fn blend(&self, x: f32, y: f32) -> [f32; 3] {
        let (x0, y0) = (floor(x as f64), floor(y as f64));
        let (fx, fy) = (x - x0 as f32, y - y0 as f32);
        let c0 = if x0 < 0 { self.width - 1 } else { x0 as usize };
        let c1 = if x0 + 1 >= self.width as i32 {
            0
        } else {
            (x0 + 1) as usize
        };
        let r0 = y0 as usize;
        let r1 = (r0 + 1).min(self.height - 1);
        let p = |r: usize, c: usize| self.pixels[r * self.width + c];
        let mut out = [0.0; 3];
        for (k, o) in out.iter_mut().enumerate() {
            let top = p(r0, c0)[k] * (1.0 - fx) + p(r0, c1)[k] * fx;
            let bottom = p(r1, c0)[k] * (1.0 - fx) + p(r1, c1)[k] * fx;
            *o = top * (1.0 - fy) + bottom * fy;
        }
        out
    }

    /// SH coefficients of the map (pixel-centre values times exact pixel solid angles).
    /// Panics if `bands > sh::MAX_BANDS`; callers validate with [`sh::check_bands`].
    pub fn project(&self, bands: usize) -> ShRgb {
        ShRgb::project_latlong(self.width, self.height, bands, &self.pixels)
    }

    /// Relative L2 difference between this map and `other` (same size) over the sphere: each pixel
    /// weighted by its solid angle, all three channels together.
    pub fn relative_l2_error(&self, other: &[[f32; 3]]) -> f64 {
        let (mut diff, mut norm) = (0.0f64, 0.0f64);
        for row in 0..self.height {
            let w = sh::latlong_pixel_solid_angle(row, self.width, self.height);
            let range = row * self.width..(row + 1) * self.width;
            for (a, b) in self.pixels[range.clone()].iter().zip(&other[range]) {
                for k in 0..3 {
                    diff += w * (a[k] as f64 - b[k] as f64).powi(2);
                    norm += w * (a[k] as f64).powi(2);
                }
            }
        }
        if norm > 0.0 {
            (diff / norm).sqrt()
        } else {
            diff.sqrt()
        }
    }
}

/// Latlong (u, v) ∈ [0,1]×[0,1] of a unit direction: φ/2π and θ/π ([`dir_to_angles`]).
pub fn dir_to_uv(dir: [f64; 3]) -> (f64, f64) {
    let (phi, theta) = dir_to_angles(dir.map(|c| c as f32));
    (phi as f64 / (2.0 * PI), theta as f64 / PI)
}

/// Latlong angles (φ, θ) ∈ [0, 2π]×[0, π] of a unit direction: θ = acos(y), φ = atan2(x, −z)
/// (docs/model.md), in f32 by [`crate::math::arc`].
#[inline(always)]
fn dir_to_angles([x, y, z]: [f32; 3]) -> (f32, f32) {
    let theta = arc::acos(y);
    // atan2 ∈ [−π, π]: one add folds it into [0, 2π], the same value `rem_euclid` gives.
    let phi = arc::atan2(x, -z);
    let phi = if phi < 0.0 { phi + TAU } else { phi };
    (phi, theta)
}

/// Reads into `buf` until it is full or the file ends; returns the count.
fn read_up_to(r: &mut impl Read, buf: &mut [u8]) -> std::io::Result<usize> {
    let mut n = 0;
    while n < buf.len() {
        match r.read(&mut buf[n..])? {
            0 => break,
            k => n += k,
        }
    }
    Ok(n)
}

fn check_size(path: &Path, width: usize, height: usize) -> Result<()> {
    if width == 0 || height == 0 || width.saturating_mul(height) > MAX_ENV_PIXELS {
        return Err(Error::format(
            path,
            format!("{width}x{height} is not a usable environment size (at most {MAX_ENV_PIXELS} pixels)"),
        ));
    }
    Ok(())
}

type Pixels = (usize, usize, Vec<[f32; 3]>);

fn read_exr(path: &Path) -> Result<Pixels> {
    let (width, height, rgba) =
        crate::io::image::read_exr_rgba(path, |w, h| check_size(path, w, h))?;
    Ok((
        width,
        height,
        rgba.into_iter().map(|[r, g, b, _]| [r, g, b]).collect(),
    ))
}

fn read_hdr(path: &Path) -> Result<Pixels> {
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let mut reader = BufReader::new(file);
    let (width, height) = hdr_size(path, &mut reader)?;
    check_size(path, width, height)?;
    // The size is known to be sane: let the decoder read from the start.
    let file = File::open(path).map_err(|e| Error::io(path, e))?;
    let image = radiant::load(BufReader::new(file))
        .map_err(|e| Error::format(path, format!("unreadable Radiance .hdr file: {e}")))?;
    if image.width != width || image.height != height {
        return Err(Error::format(path, "inconsistent Radiance .hdr header"));
    }
    let pixels = image.data.iter().map(|p| [p.r, p.g, p.b]).collect();
    Ok((width, height, pixels))
}

/// The resolution line of a Radiance header ("-Y H +X W", the only orientation accepted — and
/// the only one in practice), read with bounded line lengths so a file without newlines cannot
/// make it allocate.
fn hdr_size(path: &Path, reader: &mut impl BufRead) -> Result<(usize, usize)> {
    const MAX_HEADER_LINE: u64 = 4096;
    const MAX_HEADER_LINES: usize = 1024;
    let bad = || Error::format(path, "malformed Radiance .hdr header");
    let mut seen_blank = false;
    for _ in 0..MAX_HEADER_LINES {
        let mut line = Vec::new();
        let n = reader
            .by_ref()
            .take(MAX_HEADER_LINE)
            .read_until(b'\n', &mut line)
            .map_err(|e| Error::io(path, e))?;
        if n == 0 || line.last() != Some(&b'\n') {
            return Err(bad());
        }
        let text = String::from_utf8_lossy(&line);
        let text = text.trim();
        if !seen_blank {
            seen_blank = text.is_empty();
            continue;
        }
        let fields: Vec<&str> = text.split_whitespace().collect();
        return match fields.as_slice() {
            ["-Y", h, "+X", w] => match (h.parse(), w.parse()) {
                (Ok(h), Ok(w)) => Ok((w, h)),
                _ => Err(bad()),
            },
            _ => Err(Error::format(
                path,
                "unsupported Radiance .hdr orientation (only \"-Y H +X W\")",
            )),
        };
    }
    Err(bad())
}

/// Built-in sky parameters. The sun stands 35° high — a late-morning sun that lights a cloud from
/// the side and above — at azimuth 120° (from −Z towards +X and on, so it is to the right of and
/// behind the default camera, which looks down −Z).
const SUN_ELEVATION_DEG: f64 = 35.0;
const SUN_AZIMUTH_DEG: f64 = 120.0;
/// Angular radius of the disc: 4× the real sun's 0.27°, so it spans a few pixels of a 1080p view.
const SUN_RADIUS_DEG: f32 = 1.1;
/// Sun radiance: a warm white (about 4500 K). Over the disc's 1.16e-3 sr it gives a normal
/// irradiance of ≈ 7, some 3–4× what the whole dome gives a horizontal surface (≈ 2): a clear-day
/// balance of sharp key light and soft blue fill.
const SUN_RADIANCE: [f64; 3] = [6000.0, 5250.0, 4050.0];
const ZENITH: [f64; 3] = [0.25, 0.45, 1.0];
const HORIZON: [f64; 3] = [0.85, 0.92, 1.05];
const GROUND: [f64; 3] = [0.16, 0.14, 0.12];
/// Width of the horizon blend, in units of y = cosθ (≈ 1.7°): avoids a hard ring that would ring in SH.
const HORIZON_BLEND: f64 = 0.03;

/// The built-in sky's sun, in the map's frame: a disc of [`SUN_RADIANCE`] and [`SUN_RADIUS_DEG`],
/// a light beside the map rather than pixels in it, so its shadows are exact (thesis 7.1).
pub fn sky_sun() -> Sun {
    let d = sh::direction(
        (90.0 - SUN_ELEVATION_DEG).to_radians(),
        SUN_AZIMUTH_DEG.to_radians(),
    );
    let radius = (SUN_RADIUS_DEG as f64).to_radians();
    let omega = cap_solid_angle(radius);
    Sun {
        direction: glam::DVec3::from(d).normalize().as_vec3(),
        irradiance: SUN_RADIANCE.map(|l| (l * omega) as f32),
        radius: radius as f32,
    }
}

/// Radiance of the built-in sky (without its sun) from direction `d`.
fn sky_radiance(d: [f64; 3]) -> [f32; 3] {
    let y = d[1];
    // Sky: zenith blue fading to a pale horizon; (1 − y)³ keeps most of the dome saturated.
    let t = (1.0 - y.max(0.0)).powi(3);
    let sky: [f64; 3] = std::array::from_fn(|k| ZENITH[k] * (1.0 - t) + HORIZON[k] * t);
    let s = smoothstep(-HORIZON_BLEND, HORIZON_BLEND, y);
    let c: [f64; 3] = std::array::from_fn(|k| GROUND[k] * (1.0 - s) + sky[k] * s);
    c.map(|v| v as f32)
}

fn smoothstep(a: f64, b: f64, x: f64) -> f64 {
    let t = ((x - a) / (b - a)).clamp(0.0, 1.0);
    t * t * (3.0 - 2.0 * t)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture(name: &str) -> String {
        format!("{}/fixtures/env/{name}", env!("CARGO_MANIFEST_DIR"))
    }

    #[test]
    fn lookup_hits_pixel_centres_and_wraps_in_u() {
        let (w, h) = (8, 4);
        let px: Vec<[f32; 3]> = (0..w * h).map(|i| [i as f32, 0.0, 1.0]).collect();
        let (env, _) = Environment::from_pixels(w, h, px).unwrap();
        // Centre of pixel (col 3, row 1).
        let theta = PI * 1.5 / h as f64;
        let phi = 2.0 * PI * 3.5 / w as f64;
        assert!((env.lookup(sh::direction(theta, phi))[0] - 11.0).abs() < 1e-4);
        // u = 0 lies halfway between the last and the first column: no seam.
        let v = env.lookup(sh::direction(theta, 1e-9))[0];
        assert!((v - 0.5 * (8.0 + 15.0)).abs() < 1e-3, "{v}");
        // Straight up clamps to row 0.
        assert!(env.lookup([0.0, 1.0, 0.0])[0] < 8.0);
    }

    #[test]
    fn a_batch_looks_up_what_single_lookups_do_bit_for_bit() {
        let env = Environment::load(&fixture("studio.exr")).unwrap();
        // Directions all round, poles and the u seam included, in a batch longer than a chunk.
        let dirs: Vec<Vec3> = (0..1000)
            .map(|i| {
                let t = i as f32 * 0.37;
                Vec3::new(t.sin(), (i as f32 / 499.5 - 1.0).clamp(-1.0, 1.0), t.cos()).normalize()
            })
            .chain([Vec3::Y, -Vec3::Y, -Vec3::Z, Vec3::new(-1e-7, 0.0, -1.0)])
            .collect();
        let mut batch = vec![[0.0; 3]; dirs.len()];
        env.lookup_batch(&dirs, 0.0, &mut batch);
        for (d, b) in dirs.iter().zip(&batch) {
            assert_eq!(env.lookup(d.as_dvec3().to_array()), *b, "{d}");
        }
    }

    #[test]
    fn rotated_lookup_agrees_with_rotated_coefficients() {
        let env = Environment::load(&fixture("studio.exr")).unwrap();
        let alpha = 1.3;
        let sh0 = env.project(12);
        let mut sh1 = sh0.clone();
        sh1.rotate_y(alpha);
        // Compare the band-limited versions: rotating the coefficients must equal looking the
        // unrotated band-limited map up at the counter-rotated direction.
        let d = sh::direction(1.2, 0.4);
        let a = sh1.eval(d);
        let b = sh0.eval(sh::rotate_dir_y(d, -alpha));
        for k in 0..3 {
            assert!((a[k] - b[k]).abs() < 1e-4 * (1.0 + b[k].abs()));
        }
        // And the map itself: the light at azimuth 60° (φ) appears at 60° − α after rotation.
        let light = sh::direction((90.0f64 - 30.0).to_radians(), 60f64.to_radians());
        let moved = sh::direction((90.0f64 - 30.0).to_radians(), 60f64.to_radians() - alpha);
        let mut seen = [[0.0; 3]];
        env.lookup_batch(
            &[Vec3::from_array(moved.map(|c| c as f32))],
            alpha,
            &mut seen,
        );
        assert!((seen[0][0] - env.lookup(light)[0]).abs() < 1e-3);
    }

    #[test]
    fn bad_pixels_are_repaired_and_counted() {
        let px = vec![
            [f32::NAN, f32::INFINITY, -1.0],
            [f32::NEG_INFINITY, 2.0, 3.0],
        ];
        let (env, rep) = Environment::from_pixels(2, 1, px).unwrap();
        assert_eq!(
            rep,
            Repairs {
                nan: 1,
                infinite: 1,
                negative: 2
            }
        );
        assert_eq!(env.pixels()[0], [0.0, RADIANCE_CAP, 0.0]);
        assert_eq!(env.pixels()[1], [0.0, 2.0, 3.0]);
    }

    #[test]
    fn sky_is_finite_soft_with_a_bright_sun_beside_it() {
        let env = Environment::load(SKY_SPEC).unwrap();
        assert_eq!((env.width(), env.height()), (SKY_WIDTH, SKY_HEIGHT));
        let sun = sky_sun();
        let at_sun = env.lookup(sun.direction.as_dvec3().to_array());
        let zenith = env.lookup([0.0, 1.0, 0.0]);
        let ground = env.lookup([0.0, -1.0, 0.0]);
        // The sun is a light, not pixels: the map is soft where it stands.
        assert!(at_sun[0] < 2.0 * zenith[0].max(at_sun[2]));
        // Its disc: radiance × solid angle, ≈ 7 on a facing surface, 3–4× the dome's ≈ 2.
        let omega = 2.0 * PI * (1.0 - 1.1f64.to_radians().cos());
        assert!((sun.irradiance[0] as f64 - 6000.0 * omega).abs() < 1e-3);
        assert!(
            (6.5..7.5).contains(&sun.irradiance[0]),
            "{:?}",
            sun.irradiance
        );
        assert!(zenith[2] > zenith[0], "zenith is blue");
        assert!(ground[2] < zenith[2]);
        assert!(all_finite_non_negative(&env));
    }

    fn all_finite_non_negative(env: &Environment) -> bool {
        env.pixels()
            .iter()
            .flatten()
            .all(|v| v.is_finite() && *v >= 0.0)
    }

    #[test]
    fn fixture_reconstruction_error_falls_with_bands() {
        let env = Environment::load(&fixture("sky_sun.exr")).unwrap();
        let errors: Vec<f64> = [5, 10, 15]
            .iter()
            .map(|&b| {
                let recon = env
                    .project(b)
                    .reconstruct_latlong(env.width(), env.height());
                env.relative_l2_error(&recon)
            })
            .collect();
        eprintln!("sky_sun relative L2 error at 5/10/15 bands: {errors:?}");
        assert!(errors[0] > errors[1] && errors[1] > errors[2], "{errors:?}");
    }

    #[test]
    fn every_fixture_loads() {
        for name in [
            "constant.exr",
            "sky_sun.exr",
            "split.exr",
            "studio.exr",
            "studio.hdr",
        ] {
            let env = Environment::load(&fixture(name)).unwrap();
            assert!(all_finite_non_negative(&env));
        }
    }

    #[test]
    fn exr_and_hdr_of_the_same_map_agree() {
        let exr = Environment::load(&fixture("studio.exr")).unwrap();
        let hdr = Environment::load(&fixture("studio.hdr")).unwrap();
        assert_eq!((exr.width(), exr.height()), (hdr.width(), hdr.height()));
        // RGBE keeps 8 bits of mantissa per pixel: ≈ 1 % relative error.
        let (a, b) = (exr.project(4), hdr.project(4));
        for (x, y) in a.coeffs.iter().zip(&b.coeffs) {
            for k in 0..3 {
                assert!((x[k] - y[k]).abs() < 0.02 * a.coeffs[0][k].abs() + 1e-4);
            }
        }
    }

    #[test]
    fn constant_fixture_projects_to_band_zero() {
        let env = Environment::load(&fixture("constant.exr")).unwrap();
        let c = env.pixels()[0];
        let sh = env.project(4);
        for (got, value) in sh.coeffs[0].iter().zip(c) {
            let e0 = value as f64 * (4.0 * PI).sqrt();
            assert!((*got as f64 - e0).abs() < 1e-5 * e0);
        }
    }
}
