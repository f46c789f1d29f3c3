//! Inverse trigonometric functions in f32 by the minimax polynomials of Abramowitz & Stegun
//! (1964, 4.4.46 and 4.4.49; |ε| ≤ 2·10⁻⁸ in exact arithmetic), without branches or calls, so a
//! loop over a batch of directions vectorises: the latlong angles of every background pixel of a
//! render ([`crate::light::env::Environment::lookup_batch`]). Within a few f32 roundings of the
//! exact angles (the tests bound them at 10⁻⁶ rad, a thousandth of a pixel of a 4096-wide map).

use std::f32::consts::{FRAC_PI_2, PI};

/// acos(x) in [0, π] for x ∈ [−1, 1] (clamped: a unit vector's component may round past ±1).
#[inline(always)]
pub fn acos(x: f32) -> f32 {
    // 4.4.46: acos(a) = √(1 − a)·Σ cₖ aᵏ for a ∈ [0, 1]; acos(−a) = π − acos(a).
    const C: [f32; 8] = [
        FRAC_PI_2,
        -0.214_598_8,
        0.088_978_99,
        -0.050_174_3,
        0.030_891_88,
        -0.017_088_126,
        0.006_670_09,
        -0.001_262_491_1,
    ];
    let a = x.abs().min(1.0);
    let poly = C[..7].iter().rev().fold(C[7], |p, &c| p * a + c);
    let r = (1.0 - a).sqrt() * poly;
    if x < 0.0 {
        PI - r
    } else {
        r
    }
}

/// atan2(y, x) in [−π, π], the angle of (x, y) from the +x axis; 0 at the origin.
#[inline(always)]
pub fn atan2(y: f32, x: f32) -> f32 {
    // 4.4.49: atan(a) = a·Σ cₖ a²ᵏ for a ∈ [0, 1], the octant folded in with π/2 − and π −.
    const C: [f32; 9] = [
        1.0,
        -0.333_331_45,
        0.199_935_51,
        -0.142_089,
        0.106_562_64,
        -0.075_289_64,
        0.042_909_614,
        -0.016_165_737,
        0.002_866_225_7,
    ];
    let (ax, ay) = (x.abs(), y.abs());
    let (lo, hi) = (ax.min(ay), ax.max(ay));
    let a = if hi > 0.0 { lo / hi } else { 0.0 };
    let a2 = a * a;
    let r = a * C[..8].iter().rev().fold(C[8], |p, &c| p * a2 + c);
    let r = if ay > ax { FRAC_PI_2 - r } else { r };
    let r = if x < 0.0 { PI - r } else { r };
    r.copysign(y)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Largest error allowed against the f64 library functions: a few f32 roundings of angles
    /// up to π.
    const MAX_ERROR: f64 = 1e-6;

    #[test]
    fn acos_is_within_a_microradian_everywhere_and_exact_at_the_ends() {
        let n = 200_001;
        let worst = (0..n)
            .map(|i| {
                let x = -1.0 + 2.0 * i as f32 / (n - 1) as f32;
                (acos(x) as f64 - (x as f64).acos()).abs()
            })
            .fold(0.0, f64::max);
        assert!(worst < MAX_ERROR, "worst {worst}");
        assert_eq!(acos(1.0), 0.0);
        assert!((acos(-1.0) - PI).abs() <= f32::EPSILON * PI);
        // Past ±1 by rounding: the end's angle, not NaN.
        assert_eq!(acos(1.000_000_1), 0.0);
    }

    #[test]
    fn atan2_is_within_a_microradian_all_round_and_keeps_the_signs() {
        let n = 100_000;
        let worst = (0..n)
            .map(|i| {
                let phi = -std::f64::consts::PI + 2.0 * std::f64::consts::PI * i as f64 / n as f64;
                let r = 0.3 + i as f64 / n as f64;
                let (y, x) = ((r * phi.sin()) as f32, (r * phi.cos()) as f32);
                (atan2(y, x) as f64 - (y as f64).atan2(x as f64)).abs()
            })
            .fold(0.0, f64::max);
        assert!(worst < MAX_ERROR, "worst {worst}");
        assert_eq!(atan2(0.0, 0.0), 0.0);
        assert_eq!(atan2(0.0, 1.0), 0.0);
        assert!((atan2(0.0, -1.0) - PI).abs() <= f32::EPSILON * PI);
        assert!((atan2(-1e-30, -1.0) + PI).abs() <= f32::EPSILON * PI);
        assert!((atan2(1.0, 0.0) - FRAC_PI_2).abs() <= f32::EPSILON);
        assert!((atan2(-1.0, 0.0) + FRAC_PI_2).abs() <= f32::EPSILON);
    }
}
