//! Real orthonormal spherical harmonics (thesis ch. 2): the basis Yᵢ evaluated at a direction, the
//! pixel quadrature that projects a latitude–longitude map onto it, reconstruction, windowing
//! (thesis eq. 6.1) and rotation about +Y.
//!
//! Conventions (docs/model.md): index i = l(l+1)+m, 0-based; polar axis **+Y**, θ measured from +Y, φ as in
//! the latlong mapping, so a direction is ω = (sinθ·sinφ, cosθ, −sinθ·cosφ). The real basis is
//!
//! ```text
//! Y_l^m  = √2 · N_l^m · P_l^m(cosθ) · cos(mφ)     m > 0
//! Y_l^0  =      N_l^0 · P_l^0(cosθ)
//! Y_l^-m = √2 · N_l^m · P_l^m(cosθ) · sin(mφ)     m > 0
//! N_l^m  = √((2l+1)/(4π) · (l−m)!/(l+m)!)
//! ```
//!
//! without the Condon–Shortley phase, so Y₁₋₁ = √(3/4π)·ω.x, Y₁₀ = √(3/4π)·ω.y, Y₁₁ = −√(3/4π)·ω.z.
//! The normalised Legendre values come from the standard stable three-term recurrences with the
//! normalisation folded in (Holmes & Featherstone 2002); everything is f64 inside, f32 in storage.

use std::f64::consts::PI;
use std::sync::LazyLock;

use rayon::prelude::*;

use crate::error::{Error, Result};

/// The most bands any command accepts. 20 bands (400 coefficients) is twice the thesis' production
/// setting (10 bands, thesis 6.4.1) and still a few kilobytes per transfer voxel; the recurrences
/// stay accurate (f64) far beyond it.
pub const MAX_BANDS: usize = 20;

/// The default band count (thesis 6.4.1: "around 10 bands … is sufficient").
pub const DEFAULT_BANDS: usize = 10;

/// Number of coefficients of `bands` bands.
pub const fn coeff_count(bands: usize) -> usize {
    bands * bands
}

/// The 0-based coefficient index of (l, m), |m| ≤ l.
pub const fn index(l: usize, m: isize) -> usize {
    ((l * (l + 1)) as isize + m) as usize
}

/// Checks a user-supplied band count: 1..=MAX_BANDS, else a usage error naming the flag.
pub fn check_bands(bands: usize) -> Result<()> {
    if bands == 0 || bands > MAX_BANDS {
        return Err(Error::usage(format!(
            "--bands must be between 1 and {MAX_BANDS}, got {bands}"
        )));
    }
    Ok(())
}

/// Per-band damping of the environment's coefficients against ringing (thesis 6.4.2).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, clap::ValueEnum)]
pub enum Window {
    /// No damping.
    #[default]
    None,
    /// Thesis eq. 6.1: w_l = 0.54 + 0.46·cos(π·l/Lmax), Lmax = bands − 1.
    Hamming,
}

impl Window {
    /// The weight of band `l` out of `bands` bands.
    pub fn weight(self, l: usize, bands: usize) -> f64 {
        match self {
            Window::None => 1.0,
            // A single band has Lmax = 0; eq. 6.1 is undefined there and band 0 keeps weight 1.
            Window::Hamming if bands <= 1 => 1.0,
            Window::Hamming => 0.54 + 0.46 * (PI * l as f64 / (bands - 1) as f64).cos(),
        }
    }
}

/// A float type the basis can be written into.
pub trait Real: Copy + Send + Sync {
    fn from_f64(x: f64) -> Self;
}
impl Real for f32 {
    fn from_f64(x: f64) -> Self {
        x as f32
    }
}
impl Real for f64 {
    fn from_f64(x: f64) -> Self {
        x
    }
}

/// Index of (l, m ≥ 0) in the triangular Legendre tables.
const fn tri(l: usize, m: usize) -> usize {
    l * (l + 1) / 2 + m
}

/// Recurrence constants, computed once so that evaluating the basis costs no square roots.
struct Recurrence {
    /// N_m^m·(2m−1)!!: the normalised sectoral value divided by sin^mθ.
    diag: [f64; MAX_BANDS],
    /// a_lm = √((4l²−1)/(l²−m²)), for l ≥ m+2.
    a: Vec<f64>,
    /// b_lm = √(((l−1)²−m²)/(4(l−1)²−1)), for l ≥ m+2.
    b: Vec<f64>,
}

static RECURRENCE: LazyLock<Recurrence> = LazyLock::new(|| {
    let mut diag = [0.0; MAX_BANDS];
    diag[0] = (1.0 / (4.0 * PI)).sqrt();
    for m in 1..MAX_BANDS {
        let m2 = 2.0 * m as f64;
        diag[m] = diag[m - 1] * ((m2 + 1.0) / m2).sqrt();
    }
    let n = tri(MAX_BANDS, 0);
    let (mut a, mut b) = (vec![0.0; n], vec![0.0; n]);
    for l in 2..MAX_BANDS {
        for m in 0..l - 1 {
            let (lf, mf) = (l as f64, m as f64);
            a[tri(l, m)] = ((4.0 * lf * lf - 1.0) / (lf * lf - mf * mf)).sqrt();
            let l1 = lf - 1.0;
            b[tri(l, m)] = ((l1 * l1 - mf * mf) / (4.0 * l1 * l1 - 1.0)).sqrt();
        }
    }
    Recurrence { diag, a, b }
});

/// Calls `emit(l, q)` for l = m … bands−1 with q = N_l^m·P_l^m(t)/sin^mθ, t = cosθ.
#[inline(always)]
fn legendre_column(
    rec: &Recurrence,
    t: f64,
    m: usize,
    bands: usize,
    mut emit: impl FnMut(usize, f64),
) {
    let mut q0 = rec.diag[m];
    emit(m, q0);
    if m + 1 >= bands {
        return;
    }
    let mut q1 = t * (2.0 * m as f64 + 3.0).sqrt() * q0;
    emit(m + 1, q1);
    for l in m + 2..bands {
        let k = tri(l, m);
        let q2 = rec.a[k] * (t * q1 - rec.b[k] * q0);
        emit(l, q2);
        q0 = q1;
        q1 = q2;
    }
}

/// Writes N_l^m·P_l^m(cosθ) (m ≥ 0, sin^mθ included) into `out[tri(l, m)]`: the θ part of the basis
/// for one latlong row.
fn legendre_row(cos_theta: f64, sin_theta: f64, bands: usize, out: &mut [f64]) {
    let rec = &*RECURRENCE;
    let mut sin_m = 1.0;
    for m in 0..bands {
        legendre_column(rec, cos_theta, m, bands, |l, q| out[tri(l, m)] = q * sin_m);
        sin_m *= sin_theta;
    }
}

/// Evaluates all `bands²` basis functions at the unit direction `dir` into `out[..bands²]`.
///
/// No allocation, no trigonometry: sin^mθ·cos(mφ) and sin^mθ·sin(mφ) are the real and imaginary parts
/// of (sinθ·cosφ + i·sinθ·sinφ)^m = (−z + i·x)^m, built up by complex multiplication.
/// Panics if `bands > MAX_BANDS` or `out` is shorter than `bands²` (callers check `bands` first).
pub fn eval_basis<T: Real>(dir: [f64; 3], bands: usize, out: &mut [T]) {
    assert!(bands <= MAX_BANDS && out.len() >= coeff_count(bands));
    let rec = &*RECURRENCE;
    let [x, t, z] = dir;
    let (ca, sa) = (-z, x); // sinθ·cosφ, sinθ·sinφ
    let (mut cm, mut sm) = (1.0, 0.0); // sin^mθ·cos(mφ), sin^mθ·sin(mφ)
    for m in 0..bands {
        if m == 0 {
            legendre_column(rec, t, 0, bands, |l, q| out[index(l, 0)] = T::from_f64(q));
        } else {
            let (c, s) = (std::f64::consts::SQRT_2 * cm, std::f64::consts::SQRT_2 * sm);
            let mi = m as isize;
            legendre_column(rec, t, m, bands, |l, q| {
                out[index(l, mi)] = T::from_f64(q * c);
                out[index(l, -mi)] = T::from_f64(q * s);
            });
        }
        (cm, sm) = (cm * ca - sm * sa, cm * sa + sm * ca);
    }
}

/// θ at the centre of latlong row `row` of `height`, and cosθ at its top and bottom edges.
pub fn latlong_row(row: usize, height: usize) -> (f64, f64, f64) {
    let h = height as f64;
    let theta = PI * (row as f64 + 0.5) / h;
    let top = (PI * row as f64 / h).cos();
    let bottom = (PI * (row as f64 + 1.0) / h).cos();
    (theta, top, bottom)
}

/// The solid angle of one pixel of latlong row `row`: Δφ·(cosθ_top − cosθ_bottom), exact.
pub fn latlong_pixel_solid_angle(row: usize, width: usize, height: usize) -> f64 {
    let (_, top, bottom) = latlong_row(row, height);
    2.0 * PI / width as f64 * (top - bottom)
}

/// cos(mφ) and sin(mφ) at every column centre, laid out `[col * bands + m]`.
fn column_trig(width: usize, bands: usize) -> (Vec<f64>, Vec<f64>) {
    let mut cos = vec![0.0; width * bands];
    let mut sin = vec![0.0; width * bands];
    for col in 0..width {
        let phi = 2.0 * PI * (col as f64 + 0.5) / width as f64;
        for m in 0..bands {
            let (s, c) = (m as f64 * phi).sin_cos();
            cos[col * bands + m] = c;
            sin[col * bands + m] = s;
        }
    }
    (cos, sin)
}

/// SH coefficients of an `N`-channel function on the sphere.
#[derive(Debug, Clone, PartialEq)]
pub struct Sh<const N: usize> {
    pub bands: usize,
    /// `bands²` coefficients, index i = l(l+1)+m.
    pub coeffs: Vec<[f32; N]>,
}

/// Coefficients of an RGB function (an environment map).
pub type ShRgb = Sh<3>;

impl<const N: usize> Sh<N> {
    /// All-zero coefficients.
    pub fn zeros(bands: usize) -> Self {
        Sh {
            bands,
            coeffs: vec![[0.0; N]; coeff_count(bands)],
        }
    }

    /// Projects a latlong map (`width × height`, row-major, row 0 at the zenith) onto `bands` bands.
    ///
    /// Deterministic quadrature: each pixel's centre value times its exact solid angle. It separates:
    /// per column cos(mφ), sin(mφ) once; per row a Fourier sum over the columns for each m, then
    /// the row's Legendre values once. In φ the midpoint rule is exact for every |m| < width/2, so the
    /// whole error is the midpoint rule in θ, O(1/height²) (measured in the tests).
    /// Panics if `pixels.len() != width·height` or `bands > MAX_BANDS`.
    pub fn project_latlong(width: usize, height: usize, bands: usize, pixels: &[[f32; N]]) -> Self {
        assert!(bands <= MAX_BANDS && pixels.len() == width * height);
        let (cos_tab, sin_tab) = column_trig(width, bands);
        let n = coeff_count(bands);
        let sums = pixels
            .par_chunks(width.max(1))
            .enumerate()
            .fold(
                || (vec![0.0f64; n * N], RowScratch::new(bands, N)),
                |(mut acc, mut scratch), (row, line)| {
                    scratch.fourier(line, bands, &cos_tab, &sin_tab);
                    let (theta, top, bottom) = latlong_row(row, height);
                    let weight = 2.0 * PI / width as f64 * (top - bottom);
                    legendre_row(theta.cos(), theta.sin(), bands, &mut scratch.legendre);
                    for l in 0..bands {
                        for m in 0..=l {
                            let p = scratch.legendre[tri(l, m)] * weight;
                            for c in 0..N {
                                let re = scratch.re[c * bands + m];
                                if m == 0 {
                                    acc[index(l, 0) * N + c] += p * re;
                                } else {
                                    let im = scratch.im[c * bands + m];
                                    let p2 = std::f64::consts::SQRT_2 * p;
                                    acc[index(l, m as isize) * N + c] += p2 * re;
                                    acc[index(l, -(m as isize)) * N + c] += p2 * im;
                                }
                            }
                        }
                    }
                    (acc, scratch)
                },
            )
            .map(|(acc, _)| acc)
            .reduce(
                || vec![0.0f64; n * N],
                |mut a, b| {
                    a.iter_mut().zip(&b).for_each(|(x, y)| *x += y);
                    a
                },
            );
        let mut sh = Self::zeros(bands);
        for (i, c) in sh.coeffs.iter_mut().enumerate() {
            for (k, v) in c.iter_mut().enumerate() {
                *v = sums[i * N + k] as f32;
            }
        }
        sh
    }

    /// Evaluates the function at pixel centres of a `width × height` latlong map (separated like
    /// [`Sh::project_latlong`]).
    pub fn reconstruct_latlong(&self, width: usize, height: usize) -> Vec<[f32; N]> {
        let bands = self.bands;
        let (cos_tab, sin_tab) = column_trig(width, bands);
        let mut out = vec![[0.0f32; N]; width * height];
        out.par_chunks_mut(width.max(1))
            .enumerate()
            .for_each(|(row, line)| {
                let (theta, _, _) = latlong_row(row, height);
                let mut legendre = vec![0.0; tri(bands, 0)];
                legendre_row(theta.cos(), theta.sin(), bands, &mut legendre);
                // This row's amplitude of cos(mφ) and sin(mφ), laid out [channel * bands + m] so
                // the per-pixel sum over m below runs over contiguous memory.
                let mut re = vec![0.0f64; N * bands];
                let mut im = vec![0.0f64; N * bands];
                for l in 0..bands {
                    for m in 0..=l {
                        let p = legendre[tri(l, m)];
                        for c in 0..N {
                            if m == 0 {
                                re[c * bands] += p * self.coeffs[index(l, 0)][c] as f64;
                            } else {
                                let p2 = std::f64::consts::SQRT_2 * p;
                                re[c * bands + m] +=
                                    p2 * self.coeffs[index(l, m as isize)][c] as f64;
                                im[c * bands + m] +=
                                    p2 * self.coeffs[index(l, -(m as isize))][c] as f64;
                            }
                        }
                    }
                }
                for (col, px) in line.iter_mut().enumerate() {
                    let (ct, st) = (
                        &cos_tab[col * bands..][..bands],
                        &sin_tab[col * bands..][..bands],
                    );
                    for (c, v) in px.iter_mut().enumerate() {
                        let (rc, ic) = (&re[c * bands..][..bands], &im[c * bands..][..bands]);
                        let mut sum = 0.0;
                        for m in 0..bands {
                            sum += rc[m] * ct[m] + ic[m] * st[m];
                        }
                        *v = sum as f32;
                    }
                }
            });
        out
    }

    /// The function's value in the unit direction `dir` (tests evaluate projections with it; the
    /// renderers only ever take dot products of coefficients).
    #[cfg(test)]
    pub(crate) fn eval(&self, dir: [f64; 3]) -> [f32; N] {
        let mut basis = [0.0f64; coeff_count(MAX_BANDS)];
        eval_basis(dir, self.bands, &mut basis);
        let mut v = [0.0f64; N];
        for (y, c) in basis.iter().zip(&self.coeffs) {
            for k in 0..N {
                v[k] += y * c[k] as f64;
            }
        }
        v.map(|x| x as f32)
    }

    /// Multiplies band l by `window.weight(l, bands)` (apply once, to the environment only).
    pub fn apply_window(&mut self, window: Window) {
        for l in 0..self.bands {
            let w = window.weight(l, self.bands) as f32;
            for c in &mut self.coeffs[index(l, -(l as isize))..=index(l, l as isize)] {
                c.iter_mut().for_each(|v| *v *= w);
            }
        }
    }

    /// Rotates the function about +Y by `alpha` radians, right-handed: a positive angle turns the
    /// environment counter-clockwise seen from above (from +Y), so a feature at azimuth φ moves to
    /// φ − α (towards smaller u in the latlong image; −Z turns towards −X). Afterwards
    /// f'(θ, φ) = f(θ, φ + α); within each band it mixes only the pair (m, −m):
    /// c' = c·cos mα + s·sin mα, s' = s·cos mα − c·sin mα.
    pub fn rotate_y(&mut self, alpha: f64) {
        for l in 1..self.bands {
            for m in 1..=l {
                let (sin, cos) = (m as f64 * alpha).sin_cos();
                let (ic, is) = (index(l, m as isize), index(l, -(m as isize)));
                for k in 0..N {
                    let (c, s) = (self.coeffs[ic][k] as f64, self.coeffs[is][k] as f64);
                    self.coeffs[ic][k] = (c * cos + s * sin) as f32;
                    self.coeffs[is][k] = (s * cos - c * sin) as f32;
                }
            }
        }
    }

    /// Energy per band, Σ_m |c_lm|² for each channel.
    pub fn band_energy(&self) -> Vec<[f64; N]> {
        (0..self.bands)
            .map(|l| {
                let mut e = [0.0; N];
                for c in &self.coeffs[index(l, -(l as isize))..=index(l, l as isize)] {
                    for k in 0..N {
                        e[k] += (c[k] as f64).powi(2);
                    }
                }
                e
            })
            .collect()
    }
}

/// Per-thread buffers of the projection: one row's Fourier sums and Legendre values.
struct RowScratch {
    /// Σ_col pixel·cos(mφ), laid out `[channel * bands + m]`.
    re: Vec<f64>,
    /// Σ_col pixel·sin(mφ), same layout.
    im: Vec<f64>,
    legendre: Vec<f64>,
}

impl RowScratch {
    fn new(bands: usize, channels: usize) -> Self {
        RowScratch {
            re: vec![0.0; bands * channels],
            im: vec![0.0; bands * channels],
            legendre: vec![0.0; tri(bands, 0)],
        }
    }

    /// The row's Fourier sums. The innermost loop runs over m on contiguous tables so it vectorises.
    fn fourier<const N: usize>(
        &mut self,
        line: &[[f32; N]],
        bands: usize,
        cos: &[f64],
        sin: &[f64],
    ) {
        self.re.iter_mut().for_each(|v| *v = 0.0);
        self.im.iter_mut().for_each(|v| *v = 0.0);
        for (col, px) in line.iter().enumerate() {
            let (ct, st) = (&cos[col * bands..][..bands], &sin[col * bands..][..bands]);
            for (c, &value) in px.iter().enumerate() {
                let v = value as f64;
                let re = &mut self.re[c * bands..][..bands];
                let im = &mut self.im[c * bands..][..bands];
                for m in 0..bands {
                    re[m] += v * ct[m];
                    im[m] += v * st[m];
                }
            }
        }
    }
}

/// Rotates `dir` about +Y by `angle` radians, right-handed (counter-clockwise seen from above):
/// −Z turns towards −X. An environment turned by `--env-rotate α` sends radiance arriving from
/// `dir` that the unrotated map sends from `rotate_dir_y(dir, −α)` (see [`Sh::rotate_y`]).
pub fn rotate_dir_y(dir: [f64; 3], angle: f64) -> [f64; 3] {
    let (s, c) = angle.sin_cos();
    let [x, y, z] = dir;
    [c * x + s * z, y, -s * x + c * z]
}

/// The unit direction of spherical angles (θ from +Y, φ per the latlong mapping).
pub fn direction(theta: f64, phi: f64) -> [f64; 3] {
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    [st * sp, ct, -st * cp]
}

#[cfg(test)]
mod tests;
