//! How far a render is from a reference — the measure of the accuracy report and of anyone
//! checking their settings against the path tracer. Relative RMSE √mean((a−b)²) / mean(b) over the volume's pixels and all three channels.
//!
//! **Volume pixels** are those where either image's alpha exceeds [`VOLUME_ALPHA`]: render both
//! with `--no-background`, so RGB is the volume's own light and alpha its coverage.
//!
//! **Reference noise.** A path-traced reference is noisy. Given a second, independent reference
//! (`--reference2`, another `--seed`), the per-pixel noise variance is σ² = mean((b₁−b₂)²)/2; the
//! comparison is then against their mean (noise σ²/2), and the noise's share is subtracted:
//! error² = mean((a − (b₁+b₂)/2)²) − σ²/2, exact in expectation when a is deterministic.
//!
//! **Per pixel.** RMSE can hide a few badly wrong pixels (a shadow edge one voxel off, a bright
//! silhouette). The *lit* pixels are the volume pixels whose reference brightness (mean of RGB)
//! exceeds [`LIT_FRACTION`] of the mean: below that a relative difference is mostly the
//! reference's noise over near-zero light. For each, |a − b|/b of the brightness; the share within
//! [`PIXEL_TOLERANCE`] and the 99th percentile are reported. Noise cannot be subtracted pixel by
//! pixel, so these are upper bounds: the reference must be much less noisy than the tolerance.

use std::path::Path;

use crate::error::{Error, Result};
use crate::io::image::{read_exr_rgba, ImageBuf};

/// Pixels where the volume covers at least this fraction count as the volume's: below it the
/// pixel is mostly background, and relative errors of near-zero light say nothing.
pub const VOLUME_ALPHA: f32 = 0.01;
/// Relative difference shown as full red (a above b) or full blue (a below b) by `--diff`.
const DIFF_FULL_SCALE: f32 = 0.25;
/// A volume pixel is lit when its reference brightness is above this fraction of the mean.
pub const LIT_FRACTION: f64 = 0.1;
/// The per-pixel relative difference a lit pixel may have to count as matching.
pub const PIXEL_TOLERANCE: f64 = 0.1;
/// The percentile of lit pixels' relative differences reported.
const PIXEL_PERCENTILE: f64 = 0.99;

/// The figures of one comparison.
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct Comparison {
    /// Volume pixels compared.
    pub pixels: usize,
    /// Mean reference radiance over them.
    pub reference_mean: f64,
    /// √mean((a−b)²)/mean(b), the reference's noise subtracted when two were given.
    pub relative_rmse: f64,
    /// Before the subtraction.
    pub relative_rmse_raw: f64,
    /// The (averaged) reference's own noise, relative; 0 with one reference.
    pub reference_noise: f64,
    /// mean(a)/mean(b) − 1: the overall bias, which RMSE alone hides.
    pub relative_bias: f64,
    /// Volume pixels brighter than [`LIT_FRACTION`] of the reference's mean.
    pub lit_pixels: usize,
    /// The share of lit pixels within [`PIXEL_TOLERANCE`] of the reference.
    pub lit_within_tolerance: f64,
    /// The 99th percentile of the lit pixels' relative differences.
    pub lit_p99_difference: f64,
}

pub type Rgba = Vec<[f32; 4]>;

/// An EXR's RGBA pixels, refusing sizes no render could have.
pub fn read(path: &Path) -> Result<(usize, usize, Rgba)> {
    read_exr_rgba(path, |w, h| {
        if w.saturating_mul(h) > crate::render::camera::MAX_PIXELS as usize {
            Err(Error::format(
                path,
                format!("{w}x{h} is too large to compare"),
            ))
        } else {
            Ok(())
        }
    })
}

/// Compares `a` with the reference `b` (or the mean of `b` and `b2`), all of one size.
pub fn compare(a: &[[f32; 4]], b: &[[f32; 4]], b2: Option<&[[f32; 4]]>) -> Option<Comparison> {
    let (mut n, mut sum_a, mut sum_b, mut err2, mut noise2) = (0usize, 0.0, 0.0, 0.0, 0.0);
    // Per volume pixel: (reference brightness, image brightness).
    let mut brightness: Vec<(f64, f64)> = Vec::new();
    for (i, (pa, pb)) in a.iter().zip(b).enumerate() {
        let pb2 = b2.map(|r| r[i]);
        let alpha = pa[3].max(pb[3]).max(pb2.map_or(0.0, |p| p[3]));
        if alpha <= VOLUME_ALPHA {
            continue;
        }
        n += 1;
        let (mut pixel_a, mut pixel_b) = (0.0, 0.0);
        for c in 0..3 {
            let reference = match pb2 {
                Some(p2) => {
                    noise2 += (pb[c] as f64 - p2[c] as f64).powi(2) / 2.0;
                    0.5 * (pb[c] as f64 + p2[c] as f64)
                }
                None => pb[c] as f64,
            };
            sum_a += pa[c] as f64;
            sum_b += reference;
            pixel_a += pa[c] as f64 / 3.0;
            pixel_b += reference / 3.0;
            err2 += (pa[c] as f64 - reference).powi(2);
        }
        brightness.push((pixel_b, pixel_a));
    }
    if n == 0 || sum_b <= 0.0 {
        return None;
    }
    let count = (3 * n) as f64;
    let mean_b = sum_b / count;
    let (err2, noise2) = (err2 / count, noise2 / count);
    // The averaged reference carries half the single-reference noise variance.
    let averaged_noise2 = noise2 / 2.0;
    let mut lit: Vec<f64> = brightness
        .iter()
        .filter(|(b, _)| *b > LIT_FRACTION * mean_b)
        .map(|(b, a)| (a - b).abs() / b)
        .collect();
    lit.sort_unstable_by(f64::total_cmp);
    let within = lit.partition_point(|d| *d <= PIXEL_TOLERANCE);
    let p99 = match lit.len() {
        0 => 0.0,
        len => lit[((len as f64 * PIXEL_PERCENTILE).ceil() as usize).clamp(1, len) - 1],
    };
    Some(Comparison {
        pixels: n,
        reference_mean: mean_b,
        relative_rmse: (err2 - averaged_noise2).max(0.0).sqrt() / mean_b,
        relative_rmse_raw: err2.sqrt() / mean_b,
        reference_noise: averaged_noise2.sqrt() / mean_b,
        relative_bias: sum_a / sum_b - 1.0,
        lit_pixels: lit.len(),
        lit_within_tolerance: match lit.len() {
            0 => 1.0,
            len => within as f64 / len as f64,
        },
        lit_p99_difference: p99,
    })
}

/// A false-colour image of (a − b)/mean(b): red where a is brighter, blue where darker, black
/// where they agree, grey outside the volume.
pub fn diff_image(w: usize, h: usize, a: &Rgba, b: &Rgba, mean_b: f64) -> ImageBuf {
    let mut image = ImageBuf::new(w, h);
    for (out, (pa, pb)) in image.rgba.iter_mut().zip(a.iter().zip(b)) {
        if pa[3].max(pb[3]) <= VOLUME_ALPHA {
            *out = [0.05, 0.05, 0.05, 1.0];
            continue;
        }
        let d = ((pa[0] + pa[1] + pa[2]) - (pb[0] + pb[1] + pb[2])) as f64 / (3.0 * mean_b);
        let v = (d as f32 / DIFF_FULL_SCALE).clamp(-1.0, 1.0);
        *out = [v.max(0.0), 0.0, (-v).max(0.0), 1.0];
    }
    image
}

#[cfg(test)]
mod tests {
    use super::*;

    fn px(v: f32, a: f32) -> [f32; 4] {
        [v, v, v, a]
    }

    #[test]
    fn identical_images_have_zero_error() {
        let a = vec![px(1.0, 1.0), px(2.0, 0.5), px(9.0, 0.0)];
        let c = compare(&a, &a, None).unwrap();
        assert_eq!(c.pixels, 2);
        assert_eq!((c.relative_rmse, c.relative_bias), (0.0, 0.0));
        assert_eq!(c.reference_mean, 1.5);
    }

    #[test]
    fn a_uniform_ten_percent_excess_reads_ten_percent() {
        let b = vec![px(1.0, 1.0), px(3.0, 1.0)];
        let a: Vec<_> = b
            .iter()
            .map(|p| [p[0] * 1.1, p[1] * 1.1, p[2] * 1.1, 1.0])
            .collect();
        let c = compare(&a, &b, None).unwrap();
        // √mean(0.1², 0.3²) / 2 = √0.05 / 2.
        assert!((c.relative_rmse - 0.05f64.sqrt() / 2.0).abs() < 1e-6);
        assert!((c.relative_bias - 0.1).abs() < 1e-6);
    }

    #[test]
    fn reference_noise_is_subtracted() {
        // Two references = truth + independent noise of σ = 0.3/√3 (uniform on ±0.3); the image
        // = truth + 0.1. Raw error² = 0.01 + σ²/2; with the noise subtracted, 0.1 again.
        use crate::math::hash::hash_unit;
        let truth = 2.0f32;
        let n = 20_000u32;
        let noisy = |stream: u32| -> Vec<[f32; 4]> {
            (0..n)
                .map(|i| px(truth + 0.6 * (hash_unit(i, 0, 0, stream) - 0.5), 1.0))
                .collect()
        };
        let (b1, b2) = (noisy(1), noisy(2));
        let a: Vec<_> = (0..n).map(|_| px(truth + 0.1, 1.0)).collect();
        let c = compare(&a, &b1, Some(&b2)).unwrap();
        let sigma2 = 0.09 / 3.0;
        assert!((c.relative_rmse_raw - (0.01f64 + sigma2 / 2.0).sqrt() / 2.0).abs() < 2e-3);
        assert!((c.reference_noise - (sigma2 / 2.0).sqrt() / 2.0).abs() < 2e-3);
        assert!((c.relative_rmse - 0.05).abs() < 3e-3, "{c:?}");
    }

    #[test]
    fn per_pixel_figures_count_the_lit_pixels_off_by_more_than_the_tolerance() {
        // 100 lit pixels, of which 3 are 20 % off and one 50 %; a dim pixel (below a tenth of
        // the mean) 90 % off does not count.
        let mut b: Vec<_> = (0..100).map(|_| px(1.0, 1.0)).collect();
        b.push(px(0.01, 1.0));
        let mut a = b.clone();
        for p in &mut a[..3] {
            *p = px(1.2, 1.0);
        }
        a[3] = px(0.5, 1.0);
        a[100] = px(0.001, 1.0);
        let c = compare(&a, &b, None).unwrap();
        assert_eq!(c.lit_pixels, 100);
        assert!((c.lit_within_tolerance - 0.96).abs() < 1e-12);
        // The 99th of 100 sorted differences: the largest but one.
        assert!((c.lit_p99_difference - 0.2).abs() < 1e-6, "{c:?}");
    }

    #[test]
    fn nothing_to_compare_is_none() {
        let a = vec![px(1.0, 0.0)];
        assert_eq!(compare(&a, &a, None), None);
    }
}
