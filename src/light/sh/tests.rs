//! Tests of `sh`.

use super::*;

/// Gauss–Legendre nodes and weights on [−1, 1] (Newton on the Legendre recurrence).
fn gauss_legendre(n: usize) -> Vec<(f64, f64)> {
    (0..n)
        .map(|i| {
            let mut x = (PI * (i as f64 + 0.75) / (n as f64 + 0.5)).cos();
            loop {
                let (mut p0, mut p1) = (1.0, x);
                for k in 2..=n {
                    let kf = k as f64;
                    (p0, p1) = (p1, ((2.0 * kf - 1.0) * x * p1 - (kf - 1.0) * p0) / kf);
                }
                let dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                let dx = p1 / dp;
                x -= dx;
                if dx.abs() < 1e-15 {
                    let (mut p0, mut p1) = (1.0, x);
                    for k in 2..=n {
                        let kf = k as f64;
                        (p0, p1) = (p1, ((2.0 * kf - 1.0) * x * p1 - (kf - 1.0) * p0) / kf);
                    }
                    let dp = n as f64 * (x * p1 - p0) / (x * x - 1.0);
                    return (x, 2.0 / ((1.0 - x * x) * dp * dp));
                }
            }
        })
        .collect()
}

/// Max |∫YᵢYⱼ − δᵢⱼ| over all pairs, by exact quadrature (Gauss–Legendre in cosθ, uniform in φ).
fn orthonormality_error(bands: usize) -> f64 {
    let n = coeff_count(bands);
    let nodes = gauss_legendre(bands + 1);
    let n_phi = 2 * bands + 1;
    let mut gram = vec![0.0f64; n * n];
    let mut y = vec![0.0f64; n];
    for &(t, w) in &nodes {
        for k in 0..n_phi {
            let phi = 2.0 * PI * k as f64 / n_phi as f64;
            eval_basis(direction(t.acos(), phi), bands, &mut y);
            let wk = w * 2.0 * PI / n_phi as f64;
            for i in 0..n {
                for j in 0..n {
                    gram[i * n + j] += wk * y[i] * y[j];
                }
            }
        }
    }
    let mut worst = 0.0f64;
    for i in 0..n {
        for j in 0..n {
            let delta = if i == j { 1.0 } else { 0.0 };
            worst = worst.max((gram[i * n + j] - delta).abs());
        }
    }
    worst
}

#[test]
fn orthonormal_by_gauss_legendre_up_to_band_20() {
    let err = orthonormality_error(MAX_BANDS);
    eprintln!("orthonormality max error ({MAX_BANDS} bands): {err:.3e}");
    assert!(err < 1e-6, "{err}");
}

#[test]
fn low_bands_match_closed_forms() {
    let d = [0.36, 0.48, -0.8];
    let mut y = [0.0f64; 9];
    eval_basis(d, 3, &mut y);
    let k1 = (3.0 / (4.0 * PI)).sqrt();
    let [x, yy, z] = d;
    let expect = [
        (1.0 / (4.0 * PI)).sqrt(),
        k1 * x,
        k1 * yy,
        -k1 * z,
        0.5 * (15.0 / PI).sqrt() * x * -z,
        0.5 * (15.0 / PI).sqrt() * x * yy,
        0.25 * (5.0 / PI).sqrt() * (3.0 * yy * yy - 1.0),
        0.5 * (15.0 / PI).sqrt() * -z * yy,
        0.25 * (15.0 / PI).sqrt() * (z * z - x * x),
    ];
    for i in 0..9 {
        assert!(
            (y[i] - expect[i]).abs() < 1e-12,
            "Y{i}: {} vs {}",
            y[i],
            expect[i]
        );
    }
}

/// Worst |Σ_pixels Yᵢ·Yⱼ·ΔΩ − δᵢⱼ| of the map quadrature on a 2H×H latlong: each Yⱼ is sampled
/// at the pixel centres and projected like an environment.
fn pixel_quadrature_error(bands: usize, height: usize) -> f64 {
    let width = 2 * height;
    let n = coeff_count(bands);
    let mut y = vec![0.0f64; n];
    let mut worst = 0.0f64;
    for j in 0..n {
        let mut map = vec![[0.0f32; 1]; width * height];
        for row in 0..height {
            let (theta, _, _) = latlong_row(row, height);
            for col in 0..width {
                let phi = 2.0 * PI * (col as f64 + 0.5) / width as f64;
                eval_basis(direction(theta, phi), bands, &mut y);
                map[row * width + col] = [y[j] as f32];
            }
        }
        let sh = Sh::<1>::project_latlong(width, height, bands, &map);
        for (i, c) in sh.coeffs.iter().enumerate() {
            let delta = if i == j { 1.0 } else { 0.0 };
            worst = worst.max((c[0] as f64 - delta).abs());
        }
    }
    worst
}

#[test]
fn pixel_quadrature_converges_with_rows() {
    let bands = 8;
    let errs: Vec<f64> = [32, 64, 128, 256]
        .iter()
        .map(|&h| pixel_quadrature_error(bands, h))
        .collect();
    eprintln!("pixel quadrature Gram error, {bands} bands, H=32,64,128,256: {errs:?}");
    // Midpoint rule in θ: error O(1/H²), so each doubling divides it by ≈ 4.
    for w in errs.windows(2) {
        assert!(w[1] < w[0] / 3.0, "{errs:?}");
    }
    assert!(errs[3] < 2e-3, "{errs:?}");
}

fn map_of(width: usize, height: usize, f: impl Fn([f64; 3]) -> f64) -> Vec<[f32; 1]> {
    let mut map = Vec::with_capacity(width * height);
    for row in 0..height {
        let (theta, _, _) = latlong_row(row, height);
        for col in 0..width {
            let phi = 2.0 * PI * (col as f64 + 0.5) / width as f64;
            map.push([f(direction(theta, phi)) as f32]);
        }
    }
    map
}

#[test]
fn constant_projects_onto_band_zero_only() {
    // The solid angles sum to exactly 4π, so E₀ is exact at any size; the other coefficients
    // vanish up to the O(1/H²) midpoint error in θ, hence 1024 rows.
    let c = 2.5;
    let (w, h) = (2048, 1024);
    let sh = Sh::<1>::project_latlong(w, h, 6, &map_of(w, h, |_| c));
    let e0 = c * (4.0 * PI).sqrt();
    assert!((sh.coeffs[0][0] as f64 - e0).abs() < 1e-6 * e0);
    for c in &sh.coeffs[1..] {
        assert!((c[0] as f64).abs() < 1e-5 * e0, "{c:?}");
    }
}

#[test]
fn cos_theta_projects_onto_y10_only() {
    let (w, h) = (2048, 1024);
    let sh = Sh::<1>::project_latlong(w, h, 6, &map_of(w, h, |d| d[1]));
    let e10 = (4.0 * PI / 3.0).sqrt();
    for (i, c) in sh.coeffs.iter().enumerate() {
        let expect = if i == index(1, 0) { e10 } else { 0.0 };
        assert!((c[0] as f64 - expect).abs() < 1e-5, "coeff {i}: {}", c[0]);
    }
}

/// A band-limited function with fixed pseudo-random coefficients.
fn random_coeffs(bands: usize, seed: u64) -> Vec<f64> {
    let mut s = seed;
    (0..coeff_count(bands))
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        })
        .collect()
}

fn eval_coeffs(c: &[f64], bands: usize, d: [f64; 3]) -> f64 {
    let mut y = vec![0.0; coeff_count(bands)];
    eval_basis(d, bands, &mut y);
    y.iter().zip(c).map(|(a, b)| a * b).sum()
}

#[test]
fn band_limited_function_round_trips() {
    let bands = 6;
    let (w, h) = (2048, 1024);
    let c = random_coeffs(bands, 7);
    let sh = Sh::<1>::project_latlong(w, h, bands, &map_of(w, h, |d| eval_coeffs(&c, bands, d)));
    for (got, want) in sh.coeffs.iter().zip(&c) {
        assert!((got[0] as f64 - want).abs() < 1e-4, "{} vs {want}", got[0]);
    }
    // Reconstruction at pixel centres and at an arbitrary direction.
    let recon = sh.reconstruct_latlong(w, h);
    let orig = map_of(w, h, |d| eval_coeffs(&c, bands, d));
    let worst = recon
        .iter()
        .zip(&orig)
        .map(|(a, b)| (a[0] - b[0]).abs())
        .fold(0.0f32, f32::max);
    assert!(worst < 1e-4, "{worst}");
    let d = direction(1.1, 4.0);
    assert!((sh.eval(d)[0] as f64 - eval_coeffs(&c, bands, d)).abs() < 1e-4);
}

#[test]
fn integral_of_product_is_dot_product() {
    let bands = 5;
    let (f, g) = (random_coeffs(bands, 1), random_coeffs(bands, 2));
    // The product has degree ≤ 2·(bands−1): Gauss–Legendre with `bands` nodes in cosθ and
    // 2·bands−1 points in φ integrates it exactly.
    let mut integral = 0.0;
    let n_phi = 2 * bands;
    for (t, w) in gauss_legendre(bands + 1) {
        for k in 0..n_phi {
            let d = direction(t.acos(), 2.0 * PI * k as f64 / n_phi as f64);
            integral +=
                w * 2.0 * PI / n_phi as f64 * eval_coeffs(&f, bands, d) * eval_coeffs(&g, bands, d);
        }
    }
    let dot: f64 = f.iter().zip(&g).map(|(a, b)| a * b).sum();
    assert!(
        (integral - dot).abs() < 1e-5 * dot.abs(),
        "{integral} vs {dot}"
    );
}

#[test]
fn rotating_coefficients_equals_projecting_the_rotated_map() {
    let bands = 8;
    let (w, h) = (256, 128);
    let mut s = 99u64;
    let map: Vec<[f32; 1]> = (0..w * h)
        .map(|_| {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            [(s >> 40) as f32 / (1u64 << 24) as f32]
        })
        .collect();
    let k = 37; // columns
    let alpha = 2.0 * PI * k as f64 / w as f64;
    // f'(θ, φ) = f(θ, φ + α): pixel (col) of the rotated map is pixel (col + k) of the original.
    let rotated: Vec<[f32; 1]> = (0..w * h)
        .map(|i| map[(i / w) * w + (i % w + k) % w])
        .collect();
    let mut by_coeffs = Sh::<1>::project_latlong(w, h, bands, &map);
    by_coeffs.rotate_y(alpha);
    let by_map = Sh::<1>::project_latlong(w, h, bands, &rotated);
    for (a, b) in by_coeffs.coeffs.iter().zip(&by_map.coeffs) {
        assert!((a[0] - b[0]).abs() < 1e-4, "{} vs {}", a[0], b[0]);
    }
}

#[test]
fn positive_rotation_is_counter_clockwise_from_above() {
    // A lobe towards −Z (Y₁₁ = −√(3/4π)·z) rotated by +90° about +Y points towards −X.
    let mut sh = Sh::<1>::zeros(2);
    sh.coeffs[index(1, 1)] = [1.0];
    sh.rotate_y(PI / 2.0);
    let k1 = (3.0 / (4.0 * PI)).sqrt() as f32;
    assert!((sh.eval([-1.0, 0.0, 0.0])[0] - k1).abs() < 1e-6);
    assert!(sh.eval([0.0, 0.0, -1.0])[0].abs() < 1e-6);
}

#[test]
fn rotated_coefficients_equal_lookup_at_counter_rotated_direction() {
    let bands = 6;
    let c = random_coeffs(bands, 5);
    let mut sh = Sh::<1> {
        bands,
        coeffs: c.iter().map(|&v| [v as f32]).collect(),
    };
    let original = sh.clone();
    let alpha = 0.7;
    sh.rotate_y(alpha);
    for d in [direction(0.3, 1.0), direction(2.0, 5.5), [0.0, 0.0, -1.0]] {
        let want = original.eval(rotate_dir_y(d, -alpha))[0];
        assert!((sh.eval(d)[0] - want).abs() < 1e-5, "{d:?}");
    }
}

#[test]
fn hamming_window_matches_eq_6_1() {
    assert_eq!(Window::Hamming.weight(0, 16), 1.0);
    assert!((Window::Hamming.weight(15, 16) - 0.08).abs() < 1e-12);
    assert_eq!(Window::None.weight(7, 16), 1.0);
    assert_eq!(Window::Hamming.weight(0, 1), 1.0);
}

#[test]
fn bands_are_checked() {
    assert!(check_bands(0).is_err());
    assert!(check_bands(MAX_BANDS + 1).is_err());
    assert!(check_bands(MAX_BANDS).is_ok());
}
