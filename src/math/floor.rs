//! Floors (and ceilings) of coordinates without libm: x86-64's baseline has no SSE4.1
//! `roundsd`/`roundps`, so `f64::floor` and `f32::floor` are library calls, and the DDA, the
//! march's samples and every environment lookup take floors in their innermost loops; T_ri's
//! rays take ceilings per level they march (`ceil` was 2 % of a bake's samples in `perf`), and
//! the camera's rays per span (1.5 % of a render's).

use glam::{IVec3, Vec3, Vec3A};

/// `x.floor() as i32`, equal to it for every x, saturating the same way.
#[inline(always)]
pub fn floor(x: f64) -> i32 {
    let t = x as i32;
    t.saturating_sub((x < t as f64) as i32)
}

/// `x.ceil() as i32`, equal to it for every x, saturating the same way.
#[inline(always)]
pub fn ceil(x: f64) -> i32 {
    let t = x as i32;
    t.saturating_add((x > t as f64) as i32)
}

/// `p.floor()` as integers, and the fraction `p − floor(p)`, for |p| < 2³¹ (index coordinates of
/// any real grid). Every trilinear sample starts here, twice per march step, so on x86-64 it is five
/// SSE2 instructions for all three axes and three lane moves, where scalar `as i32` casts
/// saturate at a dozen instructions each (measured: 6 % of a render's instructions). The fraction
/// is the same IEEE subtraction either way, so results are bit-identical.
#[inline(always)]
pub fn floor_split(p: Vec3) -> (IVec3, Vec3) {
    #[cfg(target_arch = "x86_64")]
    {
        use std::arch::x86_64::*;
        // SAFETY: SSE2 is part of the x86-64 baseline, so these intrinsics are always available;
        // they only read and write registers.
        unsafe {
            let v: __m128 = Vec3A::from(p).into();
            // Truncation toward zero, then −1 (all bits set) where it went up: negative
            // non-integers.
            let t = _mm_cvttps_epi32(v);
            let up = _mm_castps_si128(_mm_cmplt_ps(v, _mm_cvtepi32_ps(t)));
            let i = _mm_add_epi32(t, up);
            let f: Vec3A = _mm_sub_ps(v, _mm_cvtepi32_ps(i)).into();
            let lane = |m: __m128i| _mm_cvtsi128_si32(m);
            let i3 = IVec3::new(
                lane(i),
                lane(_mm_shuffle_epi32::<0b01>(i)),
                lane(_mm_shuffle_epi32::<0b10>(i)),
            );
            (i3, Vec3::from(f))
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let t = p.as_ivec3(); // truncates toward zero
        let i = t - IVec3::from(p.cmplt(t.as_vec3()));
        (i, p - i.as_vec3())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floor_and_ceil_are_libms_saturated() {
        for x in [
            -3e9,
            -2147483648.5,
            -7.5,
            -1.0,
            -0.25,
            -0.0,
            0.0,
            0.5,
            1.0,
            8.999,
            2147483647.5,
            3e9,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ] {
            assert_eq!(floor(x), x.floor() as i32, "{x}");
            assert_eq!(ceil(x), x.ceil() as i32, "{x}");
        }
    }

    #[test]
    fn floor_split_is_floor_and_fraction() {
        for x in [
            -2.0f32,
            -1.5,
            -1.0,
            -0.25,
            -0.0,
            0.0,
            0.3,
            1.0,
            7.999,
            8.0,
            -1e-7,
            1e6 + 0.5,
        ] {
            let p = Vec3::new(x, -x, x * 3.0);
            let (i, f) = floor_split(p);
            assert_eq!(i, p.floor().as_ivec3(), "{x}");
            assert_eq!(f, p - p.floor(), "{x}");
        }
    }
}
