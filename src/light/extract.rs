//! Sun extraction: finds a dominant compact peak — a sun — in a latlong environment map, takes it
//! out of the map and returns it as a [`Sun`] of the same power. The SH projection then keeps only
//! the soft light it represents without ringing, and the sun casts exact shadows (thesis 7.1).
//!
//! The method, in the map's own frame:
//! 1. the core: the connected region (8 neighbours, wrapping round the u seam and across the
//!    poles) around the brightest pixel that is at least half as bright as it;
//! 2. the test: the core must fit a disc of [`MAX_RADIUS_DEG`], a ring of sky around it must be
//!    far darker than the peak, and the peak must hold a real share of the map's power;
//! 3. the fill: a disc a little wider than the core is filled, row by row, by interpolation
//!    between the sky pixels on either side (never above the original), and the sun is what was
//!    taken out — so sun plus residual map is the original map's power exactly.

use std::f64::consts::PI;

use glam::DVec3;

use crate::light::env::Environment;
use crate::light::sun::{cap_solid_angle, Sun, MAX_RADIUS_DEG};

/// Rec. 709 luminance weights: HDRIs are almost always linear Rec. 709 / sRGB primaries, and
/// brightness, not any one channel, is what makes a peak a sun.
const LUMINANCE: [f64; 3] = [0.2126, 0.7152, 0.0722];

/// The core is where the map is at least this fraction of its peak (the half maximum): a width
/// measure that ignores both a disc's partly covered edge pixels and the sky's own level.
const CORE_FRACTION: f64 = 0.5;

/// The filled disc reaches this many pixels beyond the core: a hard disc's partly covered pixels
/// lie within one pixel of it, the second takes a little glare and the latlong's stretch.
const EDGE_PIXELS: f64 = 2.0;

/// Width of the ring of sky beyond the filled disc that the peak is compared with, in pixels (at
/// least; see [`RING_CORE_RADII`]): two pixels average away a single odd one.
const RING_PIXELS: f64 = 2.0;

/// …and at least this many core radii, so a soft lobe is judged at the same multiple of its width
/// at any map resolution (an exponential or Gaussian lobe is still ≥ 1/16 of its peak at twice its
/// half-maximum radius; a disc's surroundings are sky).
const RING_CORE_RADII: f64 = 1.0;

/// The ring's mean luminance may be at most this fraction of the peak's: a real sun stands 10³–10⁵
/// above the sky around it, a soft area light fades over its own width and fails by far.
const RING_CONTRAST: f64 = 0.01;

/// The least share of the map's power a sun must hold: a peak with less barely rings in the SH,
/// and is better left in the map than made the key light that casts the scene's hard shadows.
const MIN_SHARE: f64 = 0.1;

/// What the search for a sun in a map found.
#[derive(Debug, Clone)]
pub enum SunSearch {
    /// A dominant compact peak, removed from the map and turned into a light of the same power.
    Found {
        /// The sun, in the map's own frame, unscaled.
        sun: Sun,
        /// The map without it.
        residual: Environment,
        /// The sun's fraction of the map's total power (luminance × solid angle).
        share: f64,
    },
    /// No sun taken out; the reason, one short line for the user.
    None(String),
}

impl SunSearch {
    /// One line for the user: where the sun is and how strong, or why there is none.
    pub fn describe(&self) -> String {
        match self {
            SunSearch::Found { sun, share, .. } => {
                let d = sun.direction.as_dvec3();
                let elevation = d.y.clamp(-1.0, 1.0).asin().to_degrees();
                // φ = atan2(x, −z), the latlong mapping's azimuth, rounded to the 0.1° shown and
                // then folded into [0°, 360°), so a sun on the seam never reads 360.0°; + 0.0
                // turns the −0 that `rem_euclid` keeps into 0.
                let azimuth = (d.x.atan2(-d.z).to_degrees() * 10.0)
                    .round()
                    .rem_euclid(3600.0)
                    / 10.0
                    + 0.0;
                let [r, g, b] = sun.irradiance;
                format!(
                    "sun found at elevation {elevation:.1}°, azimuth {azimuth:.1}°, radius {:.1}°, \
                     irradiance ({r:.2}, {g:.2}, {b:.2}), {:.0} % of the map's power",
                    sun.radius.to_degrees(),
                    share * 100.0
                )
            }
            SunSearch::None(reason) => reason.clone(),
        }
    }
}

/// Looks for a sun in `env`; see the module documentation for the method and its criteria.
pub fn find_sun(env: &Environment) -> SunSearch {
    match search(env) {
        Ok((sun, residual, share)) => SunSearch::Found {
            sun,
            residual,
            share,
        },
        Err(reason) => SunSearch::None(reason),
    }
}

fn luminance(p: [f32; 3]) -> f64 {
    luminance_f64(p.map(f64::from))
}

fn luminance_f64(p: [f64; 3]) -> f64 {
    LUMINANCE[0] * p[0] + LUMINANCE[1] * p[1] + LUMINANCE[2] * p[2]
}

/// The search proper; `Err` carries the reason there is no sun.
fn search(env: &Environment) -> Result<(Sun, Environment, f64), String> {
    let grid = Grid::new(env.width(), env.height());
    let pixels = env.pixels();
    let total: f64 = pixels
        .chunks(grid.width)
        .zip(&grid.rows)
        .map(|(line, row)| row.omega * line.iter().map(|&p| luminance(p)).sum::<f64>())
        .sum();
    if total <= 0.0 {
        return Err("no sun: the map is black".into());
    }
    let max_omega = cap_solid_angle((MAX_RADIUS_DEG as f64).to_radians());
    let Some(core) = Core::grow(&grid, pixels, max_omega) else {
        return Err(format!(
            "no compact peak: the brightest region spans more than {max_omega:.2} sr (a sun is at \
             most a {MAX_RADIUS_DEG}° disc)"
        ));
    };
    if core.radius > (MAX_RADIUS_DEG as f64).to_radians() {
        return Err(format!(
            "no compact peak: the brightest region reaches {:.1}° from its centre (a sun is at \
             most a {MAX_RADIUS_DEG}° disc)",
            core.radius.to_degrees()
        ));
    }
    let pixel = grid.pixel_angle();
    let fill_radius = (core.radius + EDGE_PIXELS * pixel).min(PI);
    let ring_radius =
        (fill_radius + (RING_PIXELS * pixel).max(RING_CORE_RADII * core.radius)).min(PI);
    let ring = grid.ring_luminance(pixels, core.centre, fill_radius, ring_radius);
    let Some(ring) = ring else {
        return Err("no sun: no sky is left around the brightest region to fill it from".into());
    };
    if ring > RING_CONTRAST * core.peak {
        return Err(format!(
            "no sharp peak: the sky around the brightest region is {:.1} % of its radiance (a sun \
             stands over {:.0}× above it)",
            100.0 * ring / core.peak,
            1.0 / RING_CONTRAST
        ));
    }
    let cut = grid.cut(pixels, core.centre, fill_radius)?;
    let share = cut.power / total;
    if share < MIN_SHARE {
        return Err(format!(
            "no dominant peak: the brightest region holds {:.1} % of the map's power (a sun holds \
             at least {:.0} %)",
            100.0 * share,
            100.0 * MIN_SHARE
        ));
    }
    // A disc of uniform radiance equal to the peak's, carrying the sun's power.
    let omega = cut.power / cut.peak;
    let radius = (1.0 - omega / (2.0 * PI))
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees();
    let sun = Sun::new(
        cut.direction.as_vec3(),
        cut.irradiance.map(|e| e as f32),
        (radius as f32).min(MAX_RADIUS_DEG),
    )
    .map_err(|e| format!("no sun: {e}"))?;
    let (residual, _) = Environment::from_pixels(grid.width, grid.height, cut.residual)
        .map_err(|e| format!("no sun: {e}"))?;
    Ok((sun, residual, share))
}

/// Per-row and per-column geometry of a latlong map's pixel centres.
struct Grid {
    width: usize,
    height: usize,
    rows: Vec<Row>,
    /// sin φ, cos φ at each column centre.
    cols: Vec<(f64, f64)>,
}

struct Row {
    theta: f64,
    sin: f64,
    cos: f64,
    /// Solid angle of one pixel of the row.
    omega: f64,
}

impl Grid {
    fn new(width: usize, height: usize) -> Grid {
        let rows = (0..height)
            .map(|r| {
                let (theta, top, bottom) = crate::light::sh::latlong_row(r, height);
                Row {
                    theta,
                    sin: theta.sin(),
                    cos: theta.cos(),
                    omega: 2.0 * PI / width as f64 * (top - bottom),
                }
            })
            .collect();
        let cols = (0..width)
            .map(|c| (2.0 * PI * (c as f64 + 0.5) / width as f64).sin_cos())
            .collect();
        Grid {
            width,
            height,
            rows,
            cols,
        }
    }

    /// The unit direction of a pixel centre, ω = (sinθ·sinφ, cosθ, −sinθ·cosφ).
    fn dir(&self, row: usize, col: usize) -> DVec3 {
        let r = &self.rows[row];
        let (sin_phi, cos_phi) = self.cols[col];
        DVec3::new(r.sin * sin_phi, r.cos, -r.sin * cos_phi)
    }

    /// The largest angle a pixel spans, in θ or along a row at the equator.
    fn pixel_angle(&self) -> f64 {
        (PI / self.height as f64).max(2.0 * PI / self.width as f64)
    }

    /// Calls `visit` with the index of each of the 8 neighbours of pixel `index`: columns wrap
    /// round the u seam, and over a pole the neighbour is the same row half a turn round.
    fn neighbours(&self, index: usize, mut visit: impl FnMut(usize)) {
        let (w, h) = (self.width as isize, self.height as isize);
        let (row, col) = ((index / self.width) as isize, (index % self.width) as isize);
        for dr in -1..=1 {
            for dc in -1..=1 {
                if dr == 0 && dc == 0 {
                    continue;
                }
                let (mut r, mut c) = (row + dr, col + dc);
                if r < 0 || r >= h {
                    r = row;
                    c += w / 2;
                }
                visit((r * w + c.rem_euclid(w)) as usize);
            }
        }
    }

    /// The rows whose centres may lie within `radius` of `centre`: beyond them every pixel is
    /// farther, since the angle to a pixel is at least the difference of their θ.
    fn rows_near(&self, centre: DVec3, radius: f64) -> impl Iterator<Item = usize> + '_ {
        let theta = centre.y.clamp(-1.0, 1.0).acos();
        (0..self.height).filter(move |&r| (self.rows[r].theta - theta).abs() <= radius)
    }

    /// Marks the pixels of `row` within `radius` of `centre` (cosine `cos_radius`); their count.
    fn mark(&self, row: usize, centre: DVec3, cos_radius: f64, marked: &mut [bool]) -> usize {
        let mut count = 0;
        for (col, m) in marked.iter_mut().enumerate() {
            *m = self.dir(row, col).dot(centre) >= cos_radius;
            count += *m as usize;
        }
        count
    }

    /// Mean luminance (solid-angle weighted) of the pixels between `inner` and `outer` radians
    /// from `centre`; `None` if there are none.
    fn ring_luminance(
        &self,
        pixels: &[[f32; 3]],
        centre: DVec3,
        inner: f64,
        outer: f64,
    ) -> Option<f64> {
        let (cos_inner, cos_outer) = (inner.cos(), outer.cos());
        let (mut sum, mut omega) = (0.0, 0.0);
        for row in self.rows_near(centre, outer) {
            let line = &pixels[row * self.width..][..self.width];
            for (col, &p) in line.iter().enumerate() {
                let cos = self.dir(row, col).dot(centre);
                if cos < cos_inner && cos >= cos_outer {
                    sum += luminance(p) * self.rows[row].omega;
                    omega += self.rows[row].omega;
                }
            }
        }
        (omega > 0.0).then(|| sum / omega)
    }

    /// Fills the pixels within `radius` of `centre` from the sky around them and returns what was
    /// taken out. Each row's run of filled pixels is interpolated linearly between the unfilled
    /// pixels on either side — both at the run's elevation, so a sky that changes with elevation
    /// (the horizon above all) is followed exactly; a row filled entirely (the disc holds a pole)
    /// takes the mean of the nearest row's unfilled pixels, the sky all round at about its
    /// elevation. The fill never exceeds the original, so nothing taken out is negative.
    fn cut(&self, pixels: &[[f32; 3]], centre: DVec3, radius: f64) -> Result<Cut, String> {
        let cos_radius = radius.cos();
        let w = self.width;
        let mut residual = pixels.to_vec();
        let (mut marked, mut source_marks) = (vec![false; w], vec![false; w]);
        // How many pixels of each row are filled, known before any row is, so a full row finds
        // its source row in one look per row instead of marking rows again.
        let mut counts = vec![0; self.height];
        for row in self.rows_near(centre, radius) {
            counts[row] = self.mark(row, centre, cos_radius, &mut marked);
        }
        let mut cut = Cut {
            irradiance: [0.0; 3],
            power: 0.0,
            peak: 0.0,
            direction: DVec3::ZERO,
            residual: Vec::new(),
        };
        for row in self.rows_near(centre, radius) {
            if counts[row] == 0 {
                continue;
            }
            self.mark(row, centre, cos_radius, &mut marked);
            let original = &pixels[row * w..][..w];
            let filled = &mut residual[row * w..][..w];
            if counts[row] < w {
                fill_runs(original, &marked, filled);
            } else {
                // The ring check found pixels beyond the disc, so some row is not full.
                let source = (1..self.height)
                    .flat_map(|d| [row.checked_sub(d), Some(row + d)])
                    .flatten()
                    .find(|&r| r < self.height && counts[r] < w)
                    .ok_or("no sun: the brightest region covers the whole map")?;
                self.mark(source, centre, cos_radius, &mut source_marks);
                let sky = mean_unmarked(&pixels[source * w..][..w], &source_marks);
                for (f, o) in filled.iter_mut().zip(original) {
                    *f = std::array::from_fn(|k| sky[k].min(o[k]));
                }
            }
            let omega = self.rows[row].omega;
            for col in (0..w).filter(|&c| marked[c]) {
                let excess: [f64; 3] =
                    std::array::from_fn(|k| original[col][k] as f64 - filled[col][k] as f64);
                for (e, x) in cut.irradiance.iter_mut().zip(excess) {
                    *e += x * omega;
                }
                let lum = luminance_f64(excess);
                cut.power += lum * omega;
                cut.peak = cut.peak.max(lum);
                cut.direction += self.dir(row, col) * lum * omega;
            }
        }
        cut.direction = cut.direction.normalize_or_zero();
        cut.residual = residual;
        Ok(cut)
    }
}

/// What [`Grid::cut`] took out of the map.
struct Cut {
    /// Σ (original − fill)·Ω per channel.
    irradiance: [f64; 3],
    /// Its luminance.
    power: f64,
    /// The largest (original − fill) luminance of one pixel.
    peak: f64,
    /// The power-weighted mean pixel direction, unit.
    direction: DVec3,
    /// The map after the fill.
    residual: Vec<[f32; 3]>,
}

/// Fills each run of marked pixels of a row (at least one unmarked) by linear interpolation
/// between the unmarked pixels on either side, wrapping round the seam, capped by the original.
fn fill_runs(original: &[[f32; 3]], marked: &[bool], filled: &mut [[f32; 3]]) {
    let w = original.len();
    // Runs are walked from an unmarked pixel, so the one across the seam is seen whole.
    let Some(start) = marked.iter().position(|m| !m) else {
        return;
    };
    let mut left = 0;
    for k in 1..=w {
        let right_col = (start + k) % w;
        if marked[right_col] {
            continue;
        }
        let (a, b) = (original[(start + left) % w], original[right_col]);
        let run = k - left - 1;
        for i in 1..=run {
            let col = (start + left + i) % w;
            let t = i as f32 / (run + 1) as f32;
            filled[col] = std::array::from_fn(|c| (a[c] + (b[c] - a[c]) * t).min(original[col][c]));
        }
        left = k;
    }
}

/// The mean of the unmarked pixels of a row (some are).
fn mean_unmarked(line: &[[f32; 3]], marked: &[bool]) -> [f32; 3] {
    let mut sum = [0.0f64; 3];
    let mut n = 0usize;
    for (p, _) in line.iter().zip(marked).filter(|(_, m)| !**m) {
        for (s, v) in sum.iter_mut().zip(p) {
            *s += *v as f64;
        }
        n += 1;
    }
    sum.map(|s| (s / n as f64) as f32)
}

/// The connected region around the brightest pixel at or above [`CORE_FRACTION`] of its luminance.
struct Core {
    /// The brightest pixel's luminance.
    peak: f64,
    /// Its power-weighted mean direction, unit.
    centre: DVec3,
    /// The largest angle from `centre` to a pixel centre of the region.
    radius: f64,
}

impl Core {
    /// The core, or `None` once it spans more than `max_omega` steradians: no sun is that wide,
    /// and stopping there bounds the work by the widest sun, not by the map (a breadth-first
    /// front over a whole map strides across rows and misses the cache at every step).
    fn grow(grid: &Grid, pixels: &[[f32; 3]], max_omega: f64) -> Option<Core> {
        let (seed, peak) = pixels.iter().map(|&p| luminance(p)).enumerate().fold(
            (0, f64::NEG_INFINITY),
            |best, (i, l)| {
                if l > best.1 {
                    (i, l)
                } else {
                    best
                }
            },
        );
        let threshold = CORE_FRACTION * peak;
        // Breadth first; the queue doubles as the list of the region's pixels.
        let mut inside = vec![false; pixels.len()];
        inside[seed] = true;
        let mut queue = vec![seed];
        let mut head = 0;
        let (mut omega, mut centre) = (0.0, DVec3::ZERO);
        while head < queue.len() {
            let i = queue[head];
            head += 1;
            let (row, col) = (i / grid.width, i % grid.width);
            let pixel_omega = grid.rows[row].omega;
            omega += pixel_omega;
            if omega > max_omega {
                return None;
            }
            centre += grid.dir(row, col) * luminance(pixels[i]) * pixel_omega;
            grid.neighbours(i, |j| {
                if !inside[j] && luminance(pixels[j]) >= threshold {
                    inside[j] = true;
                    queue.push(j);
                }
            });
        }
        let centre = centre.normalize_or_zero();
        let min_cos = queue
            .iter()
            .map(|&i| grid.dir(i / grid.width, i % grid.width).dot(centre))
            .fold(1.0f64, f64::min);
        Some(Core {
            peak,
            centre,
            radius: min_cos.clamp(-1.0, 1.0).acos(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::light::sh;
    use std::time::Instant;

    fn fixture(name: &str) -> Environment {
        Environment::load(&format!(
            "{}/{name}",
            concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/env")
        ))
        .unwrap()
    }

    /// Σ radiance·Ω per channel.
    fn power(env: &Environment) -> [f64; 3] {
        let mut sum = [0.0; 3];
        for (i, p) in env.pixels().iter().enumerate() {
            let omega = sh::latlong_pixel_solid_angle(i / env.width(), env.width(), env.height());
            for k in 0..3 {
                sum[k] += p[k] as f64 * omega;
            }
        }
        sum
    }

    /// The found sun, its residual and share, or a failure naming the reason.
    fn found(search: SunSearch) -> (Sun, Environment, f64) {
        match search {
            SunSearch::Found {
                sun,
                residual,
                share,
            } => (sun, residual, share),
            SunSearch::None(reason) => panic!("no sun found: {reason}"),
        }
    }

    fn direction_deg(elevation: f64, azimuth: f64) -> DVec3 {
        DVec3::from(sh::direction(
            (90.0 - elevation).to_radians(),
            azimuth.to_radians(),
        ))
    }

    fn angle_deg(sun: &Sun, want: DVec3) -> f64 {
        sun.direction
            .as_dvec3()
            .dot(want)
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees()
    }

    /// Largest per-channel relative error of sun + residual against the original's power, after
    /// checking 0 ≤ residual ≤ original pixel by pixel.
    fn conservation_error(original: &Environment, sun: &Sun, residual: &Environment) -> f64 {
        for (r, o) in residual.pixels().iter().zip(original.pixels()) {
            for k in 0..3 {
                assert!(r[k] >= 0.0 && r[k] <= o[k], "{r:?} vs {o:?}");
            }
        }
        let (before, after) = (power(original), power(residual));
        (0..3)
            .map(|k| ((after[k] + sun.irradiance[k] as f64) - before[k]).abs() / before[k])
            .fold(0.0, f64::max)
    }

    /// Largest per-channel relative error of the sun's irradiance against a disc of `radiance`
    /// and `radius_deg`.
    fn power_error(sun: &Sun, radiance: [f64; 3], radius_deg: f64) -> f64 {
        let omega = cap_solid_angle(radius_deg.to_radians());
        (0..3)
            .map(|k| (sun.irradiance[k] as f64 / (radiance[k] * omega) - 1.0).abs())
            .fold(0.0, f64::max)
    }

    #[test]
    fn finds_the_fixture_sun_and_conserves_power() {
        let env = fixture("sky_sun.exr");
        let search = find_sun(&env);
        let line = search.describe();
        eprintln!("sky_sun.exr: {line}");
        assert!(
            line.starts_with("sun found at elevation 35.0°, azimuth 180.0°, radius 2.0°, "),
            "{line}"
        );
        let (sun, residual, share) = found(search);
        let direction = angle_deg(&sun, direction_deg(35.0, 180.0));
        let power = power_error(&sun, [2000.0, 1750.0, 1350.0], 2.0);
        let radius = (sun.radius as f64).to_degrees() - 2.0;
        let conservation = conservation_error(&env, &sun, &residual);
        eprintln!(
            "sky_sun.exr: direction off by {direction:.3}°, power by {:.2} %, radius by \
             {radius:.3}°, conservation by {conservation:.1e}, share {share:.3}",
            100.0 * power
        );
        assert!(direction < 0.5);
        assert!(power < 0.02);
        assert!(radius.abs() < 0.5);
        assert!(conservation < 1e-3);
    }

    #[test]
    fn maps_without_a_compact_peak_have_no_sun() {
        for name in ["studio.exr", "studio.hdr", "split.exr", "constant.exr"] {
            match find_sun(&fixture(name)) {
                SunSearch::None(reason) => {
                    eprintln!("{name}: {reason}");
                    assert!(!reason.is_empty() && !reason.contains('\n'));
                }
                found => panic!("{name}: {}", found.describe()),
            }
        }
    }

    /// Sub-samples per pixel side of the synthetic maps: 64 a pixel put a 2° disc's discretised
    /// area well inside the 2 % the tests allow.
    const SUBSAMPLES: usize = 8;

    /// A sky brighter toward the horizon and toward +X over a dark ground, so both an elevation
    /// step and an azimuth gradient cross a disc near them.
    fn gradient_sky(d: DVec3) -> [f64; 3] {
        if d.y < 0.0 {
            return [0.15, 0.13, 0.1];
        }
        let t = (1.0 - d.y).powi(3);
        [0.3 + 0.6 * t, 0.5 + 0.4 * t, 1.0 + 0.1 * t].map(|c| c + 0.1 * d.x)
    }

    /// A `width × height` latlong map of `sky` plus a disc of `radiance` and `radius_deg` around
    /// `centre`, each pixel the mean of sub-samples spread evenly over its solid angle.
    fn disc_map(
        width: usize,
        height: usize,
        sky: fn(DVec3) -> [f64; 3],
        centre: DVec3,
        radius_deg: f64,
        radiance: [f64; 3],
    ) -> Environment {
        let cos_radius = radius_deg.to_radians().cos();
        let n = SUBSAMPLES as f64;
        let mut pixels = Vec::with_capacity(width * height);
        for row in 0..height {
            for col in 0..width {
                let mut sum = [0.0; 3];
                let (_, top, bottom) = sh::latlong_row(row, height);
                for i in 0..SUBSAMPLES {
                    // Even steps in cos θ are even steps in solid angle: the pixel's mean
                    // radiance, which near a pole even steps in θ would skew.
                    let cos_theta = top + (bottom - top) * (i as f64 + 0.5) / n;
                    for j in 0..SUBSAMPLES {
                        let u = (col as f64 + (j as f64 + 0.5) / n) / width as f64;
                        let d = DVec3::from(sh::direction(cos_theta.acos(), 2.0 * PI * u));
                        let in_disc = d.dot(centre) >= cos_radius;
                        let s = sky(d);
                        for k in 0..3 {
                            sum[k] += s[k] + if in_disc { radiance[k] } else { 0.0 };
                        }
                    }
                }
                pixels.push(sum.map(|s| (s / (n * n)) as f32));
            }
        }
        Environment::from_pixels(width, height, pixels).unwrap().0
    }

    #[test]
    fn finds_discs_near_the_zenith_across_the_seam_and_on_the_horizon() {
        let radiance = [3000.0, 2600.0, 2000.0];
        let radius = 2.0;
        for (what, elevation, azimuth) in [
            ("near the zenith", 80.0, 40.0),
            ("over the zenith", 89.0, 300.0),
            ("across the seam", 20.0, 0.0),
            ("on the horizon", 1.0, 250.0),
        ] {
            let want = direction_deg(elevation, azimuth);
            let env = disc_map(256, 128, gradient_sky, want, radius, radiance);
            let sky = disc_map(256, 128, gradient_sky, want, 0.0, [0.0; 3]);
            let search = find_sun(&env);
            let line = search.describe();
            eprintln!("{what}: {line}");
            // Azimuths read in [0°, 360°) as shown, also just below the seam.
            assert!(
                !line.contains("azimuth 360.0°") && !line.contains("azimuth -"),
                "{line}"
            );
            let (sun, residual, _) = found(search);
            let direction = angle_deg(&sun, want);
            let power = power_error(&sun, radiance, radius);
            let conservation = conservation_error(&env, &sun, &residual);
            // The fill against the sky without the disc, pixel by pixel.
            let fill = residual
                .pixels()
                .iter()
                .zip(sky.pixels())
                .flat_map(|(r, s)| (0..3).map(move |k| (r[k] / s[k] - 1.0).abs()))
                .fold(0.0f32, f32::max);
            eprintln!(
                "{what}: direction off by {direction:.3}°, power by {:.2} %, radius {:.2}°, \
                 conservation by {conservation:.1e}, fill off the sky by {:.2} % at most",
                100.0 * power,
                (sun.radius as f64).to_degrees(),
                100.0 * fill
            );
            assert!(direction < 0.5, "{what}");
            assert!(power < 0.02, "{what}");
            assert!(conservation < 1e-3, "{what}");
            assert!(fill < 0.05, "{what}");
        }
    }

    #[test]
    fn a_bright_hemisphere_a_black_map_and_tiny_maps_have_no_sun() {
        let hemisphere = disc_map(
            64,
            32,
            |d| if d.y > 0.0 { [50.0; 3] } else { [0.1; 3] },
            DVec3::Y,
            0.0,
            [0.0; 3],
        );
        let black = Environment::from_pixels(64, 32, vec![[0.0; 3]; 64 * 32])
            .unwrap()
            .0;
        let one = Environment::from_pixels(1, 1, vec![[5.0, 4.0, 3.0]])
            .unwrap()
            .0;
        let two = Environment::from_pixels(2, 1, vec![[5.0, 4.0, 3.0], [0.0; 3]])
            .unwrap()
            .0;
        for (what, env) in [
            ("hemisphere", hemisphere),
            ("black", black),
            ("1×1", one),
            ("2×1", two),
        ] {
            match find_sun(&env) {
                SunSearch::None(reason) => eprintln!("{what}: {reason}"),
                found => panic!("{what}: {}", found.describe()),
            }
        }
    }

    #[test]
    fn a_soft_lobe_is_no_sun_at_any_resolution() {
        // studio.exr's green light: exp((cos γ − 1)/(1 − cos 8°)) over a dim background, small
        // enough to pass as compact, but fading over its own width.
        fn lobe(d: DVec3) -> [f64; 3] {
            let cos = d.dot(direction_deg(60.0, 300.0));
            let fade = ((cos - 1.0) / (1.0 - 8f64.to_radians().cos())).exp();
            [0.02 + 2.0 * fade, 0.02 + 9.0 * fade, 0.02 + 3.0 * fade]
        }
        for (w, h) in [(128, 64), (256, 128), (512, 256)] {
            match find_sun(&disc_map(w, h, lobe, DVec3::Y, 0.0, [0.0; 3])) {
                SunSearch::None(reason) => {
                    eprintln!("{w}×{h} lobe: {reason}");
                    assert!(reason.starts_with("no sharp peak"), "{reason}");
                }
                found => panic!("{w}×{h} lobe: {}", found.describe()),
            }
        }
    }

    #[test]
    fn a_sharp_peak_with_little_power_stays_in_the_map() {
        let faint = disc_map(
            256,
            128,
            gradient_sky,
            direction_deg(30.0, 90.0),
            1.0,
            [200.0; 3],
        );
        match find_sun(&faint) {
            SunSearch::None(reason) => {
                eprintln!("faint peak: {reason}");
                assert!(reason.starts_with("no dominant peak"), "{reason}");
            }
            found => panic!("faint peak: {}", found.describe()),
        }
    }

    #[test]
    fn a_large_map_takes_well_under_a_second() {
        let (w, h) = (2048, 1024);
        let sky = Environment::sky_with_size(w, h);
        let centre = direction_deg(35.0, 120.0);
        let cos_radius = 1.0f64.to_radians().cos();
        let pixels = sky
            .pixels()
            .iter()
            .enumerate()
            .map(|(i, p)| {
                let d = DVec3::from(sh::direction(
                    PI * ((i / w) as f64 + 0.5) / h as f64,
                    2.0 * PI * ((i % w) as f64 + 0.5) / w as f64,
                ));
                let sun = if d.dot(centre) >= cos_radius {
                    5000.0
                } else {
                    0.0
                };
                p.map(|c| c + sun)
            })
            .collect();
        let with_sun = Environment::from_pixels(w, h, pixels).unwrap().0;
        // The widest sun grows, rings and fills the most pixels; a constant map is a region
        // growth stopped at that width.
        let widest = MAX_RADIUS_DEG as f64 - 1.0;
        let cos_widest = widest.to_radians().cos();
        let pixels = (0..w * h)
            .map(|i| {
                let y = (PI * ((i / w) as f64 + 0.5) / h as f64).cos();
                [if y >= cos_widest { 100.0 } else { 0.1 }; 3]
            })
            .collect();
        let wide = Environment::from_pixels(w, h, pixels).unwrap().0;
        let constant = Environment::from_pixels(w, h, vec![[1.0; 3]; w * h])
            .unwrap()
            .0;
        for (what, env, want_sun) in [
            ("sky and sun", with_sun, true),
            ("19° disc", wide, true),
            ("constant", constant, false),
        ] {
            let start = Instant::now();
            let search = find_sun(&env);
            let seconds = start.elapsed().as_secs_f64();
            eprintln!("{w}×{h} {what}: {seconds:.3} s, {}", search.describe());
            assert_eq!(
                matches!(search, SunSearch::Found { .. }),
                want_sun,
                "{what}"
            );
            assert!(seconds < 1.0, "{what}: {seconds} s");
        }
    }
}
