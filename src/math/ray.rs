//! The one ray type: `origin + t·dir`, with `1/dir` kept for slab tests and DDA steps. `dir`
//! need not be unit length; every `t` is in its parameter.

use glam::DVec3;

/// A ray and the reciprocal of its direction, computed once: a walk clips many cells, and a
/// multiplication costs a fraction of a division.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ray {
    pub origin: DVec3,
    pub dir: DVec3,
    /// 1/`dir` per axis; infinite on an axis the ray runs parallel to.
    pub inv_dir: DVec3,
}

impl Ray {
    pub fn new(origin: DVec3, dir: DVec3) -> Ray {
        Ray {
            origin,
            dir,
            inv_dir: dir.recip(),
        }
    }

    /// The point at parameter `t`.
    #[inline]
    pub fn at(&self, t: f64) -> DVec3 {
        self.origin + self.dir * t
    }

    /// Whether walking this ray can make progress: a non-finite origin or direction, or a zero
    /// direction, would stall a walk over cells.
    pub fn is_walkable(&self) -> bool {
        self.origin.is_finite() && self.dir.is_finite() && self.dir != DVec3::ZERO
    }

    /// The part of [t0, t1] where the ray lies in the box [lo, hi] (slab test). An axis whose
    /// `inv_dir` is infinite (a zero or subnormal direction) is parallel to the slabs: inside or
    /// a miss, never 0·∞ = NaN.
    #[inline]
    pub fn clip(&self, t0: f64, t1: f64, lo: DVec3, hi: DVec3) -> Option<(f64, f64)> {
        let (mut a, mut b) = (t0, t1);
        for axis in 0..3 {
            let o = self.origin[axis];
            let inv = self.inv_dir[axis];
            if !inv.is_finite() {
                if o < lo[axis] || o > hi[axis] {
                    return None;
                }
            } else {
                let ta = (lo[axis] - o) * inv;
                let tb = (hi[axis] - o) * inv;
                let (near, far) = if ta < tb { (ta, tb) } else { (tb, ta) };
                a = max(a, near);
                b = min(b, far);
            }
        }
        (a < b).then_some((a, b))
    }
}

/// The smaller of two numbers that are not NaN (rays are checked before walking): one compare,
/// where `f64::min`'s NaN rules cost several instructions in the DDA's innermost loop.
#[inline(always)]
pub fn min(a: f64, b: f64) -> f64 {
    if a < b {
        a
    } else {
        b
    }
}

/// The larger of two numbers that are not NaN; see [`min`].
#[inline(always)]
pub fn max(a: f64, b: f64) -> f64 {
    if a > b {
        a
    } else {
        b
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clip_gives_the_exact_chord_of_a_box() {
        let ray = Ray::new(DVec3::new(-2.0, 0.5, 0.5), DVec3::new(1.0, 0.0, 0.0));
        let chord = ray.clip(0.0, f64::INFINITY, DVec3::ZERO, DVec3::ONE);
        assert_eq!(chord, Some((2.0, 3.0)));
        assert_eq!(ray.at(2.5), DVec3::new(0.5, 0.5, 0.5));
        // Limited by t1, and a miss above the box.
        assert_eq!(
            ray.clip(0.0, 2.25, DVec3::ZERO, DVec3::ONE),
            Some((2.0, 2.25))
        );
        let above = Ray::new(DVec3::new(-2.0, 1.5, 0.5), DVec3::X);
        assert_eq!(
            above.clip(0.0, f64::INFINITY, DVec3::ZERO, DVec3::ONE),
            None
        );
    }

    #[test]
    fn a_ray_parallel_to_a_slab_is_inside_or_a_miss_never_nan() {
        let inside = Ray::new(DVec3::new(0.5, 0.5, -1.0), DVec3::Z);
        assert_eq!(
            inside.clip(0.0, 10.0, DVec3::ZERO, DVec3::ONE),
            Some((1.0, 2.0))
        );
        let outside = Ray::new(DVec3::new(1.5, 0.5, -1.0), DVec3::Z);
        assert_eq!(outside.clip(0.0, 10.0, DVec3::ZERO, DVec3::ONE), None);
        assert!(!Ray::new(DVec3::ZERO, DVec3::ZERO).is_walkable());
        assert!(!Ray::new(DVec3::NAN, DVec3::X).is_walkable());
    }
}
