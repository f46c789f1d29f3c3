//! The pinhole camera (docs/model.md, "The camera"): position, look-at point, up vector, **horizontal**
//! field of view, image row 0 at the top; the automatic framing used when the user gives no camera;
//! and the deterministic per-pixel sample positions of `--spp`.

use glam::{Vec2, Vec3};

use crate::error::{Error, Result};
use crate::math::hash::hash_unit;

/// Fraction of the image left free around the framed bounding box on its tighter axis, so the
/// volume's silhouette never touches the image border.
const FRAMING_MARGIN: f32 = 0.05;
/// Smallest half-extent used for framing, in world units relative to the box size (or absolute for
/// a point-like box), so a flat or single-voxel box still gives a finite, positive distance.
const MIN_HALF_EXTENT: f32 = 1e-6;
/// Largest image accepted: 2²⁶ pixels (8192×8192 or any shape of that area). A frame with its
/// layers takes 44 bytes per pixel, so this bounds the image memory at about 3 GB; a typo such as
/// `--res 100000x100000` is a usage error, not an allocation failure.
pub const MAX_PIXELS: u64 = 1 << 26;
/// The R2 low-discrepancy sequence (Roberts 2018): generalised golden ratio steps. Any sample count
/// is well stratified, which a square grid is not.
const R2_ALPHA: Vec2 = Vec2::new(0.754_877_7, 0.569_840_3);

/// A pinhole camera with an orthonormal basis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Camera {
    pub position: Vec3,
    /// Unit view direction.
    pub forward: Vec3,
    /// Unit vector towards increasing pixel x.
    pub right: Vec3,
    /// Unit vector towards the top of the image (decreasing pixel y).
    pub up: Vec3,
    pub width: u32,
    pub height: u32,
    /// tan(fov_x / 2) and tan(fov_y / 2), square pixels.
    tan_half: Vec2,
}

impl Camera {
    /// A camera at `position` looking at `lookat`, `up` giving the image's vertical, with a
    /// horizontal field of view of `fov_deg` degrees and `width`×`height` pixels.
    pub fn look_at(
        position: Vec3,
        lookat: Vec3,
        up: Vec3,
        fov_deg: f32,
        width: u32,
        height: u32,
    ) -> Result<Camera> {
        if width == 0 || height == 0 || width as u64 * height as u64 > MAX_PIXELS {
            return Err(Error::usage(format!(
                "resolution {width}x{height}: both sides must be at least 1 and the image at most {MAX_PIXELS} pixels"
            )));
        }
        if !(fov_deg > 0.0 && fov_deg < 180.0) {
            return Err(Error::usage(format!(
                "--fov {fov_deg}: the horizontal field of view must lie strictly between 0 and 180 degrees"
            )));
        }
        let all_finite = [position, lookat, up].iter().all(|v| v.is_finite());
        let forward = (lookat - position).normalize_or_zero();
        if !all_finite || forward == Vec3::ZERO {
            return Err(Error::usage(
                "camera: --camera-pos and --lookat must be finite and distinct",
            ));
        }
        let right = forward.cross(up).normalize_or_zero();
        if right == Vec3::ZERO {
            return Err(Error::usage(
                "camera: --up must not be zero or parallel to the view direction",
            ));
        }
        let up = right.cross(forward);
        let tan_x = (fov_deg.to_radians() * 0.5).tan();
        let tan_half = Vec2::new(tan_x, tan_x * height as f32 / width as f32);
        Ok(Camera {
            position,
            forward,
            right,
            up,
            width,
            height,
            tan_half,
        })
    }

    /// The default camera: on the +Z side of the box `[bmin, bmax]`, looking down −Z at its centre
    /// with +Y up, just far enough that the whole box fits both the horizontal and the vertical
    /// field of view with a small margin.
    pub fn framing(
        bmin: Vec3,
        bmax: Vec3,
        width: u32,
        height: u32,
        fov_deg: f32,
    ) -> Result<Camera> {
        // Validate resolution and fov first through a throw-away camera at a known-good pose.
        let probe = Camera::look_at(Vec3::Z, Vec3::ZERO, Vec3::Y, fov_deg, width, height)?;
        if !(bmin.is_finite() && bmax.is_finite()) {
            return Err(Error::Runtime(
                "cannot frame a volume with a non-finite bounding box".into(),
            ));
        }
        let centre = 0.5 * (bmin + bmax);
        let floor = MIN_HALF_EXTENT * (bmax - bmin).abs().max_element().max(1.0);
        let half = (0.5 * (bmax - bmin).abs()).max(Vec3::splat(floor));
        // Seen along −Z from a point on the box's axis, the widest projection of the box is its
        // near face (z = centre + half.z): x/(distance to that face) ≤ tan(fov_x/2), same in y.
        let fit = (1.0 - FRAMING_MARGIN) * probe.tan_half;
        let distance = half.z + (half.x / fit.x).max(half.y / fit.y);
        Camera::look_at(
            centre + Vec3::new(0.0, 0.0, distance),
            centre,
            Vec3::Y,
            fov_deg,
            width,
            height,
        )
    }

    /// The world-space ray through continuous pixel coordinates (`px`, `py`): pixel (x, y) covers
    /// [x, x+1)×[y, y+1), row 0 at the top. Returns (origin, unit direction).
    pub fn ray(&self, px: f32, py: f32) -> (Vec3, Vec3) {
        let ndc = Vec2::new(
            2.0 * px / self.width as f32 - 1.0,
            1.0 - 2.0 * py / self.height as f32,
        ) * self.tan_half;
        let dir = (self.forward + ndc.x * self.right + ndc.y * self.up).normalize();
        (self.position, dir)
    }
}

/// Stream ids for [`hash_unit`](crate::math::hash::hash_unit).
pub const STREAM_PIXEL: u32 = 0x5049_5845;
pub const STREAM_STEP: u32 = 0x5354_4550;

/// Position of sample `s` of `spp` inside pixel (`x`, `y`), as an offset in [0, 1)². One sample
/// takes the pixel centre; more follow the R2 sequence, shifted per pixel by a hash
/// (Cranley–Patterson rotation), so the box filter is well stratified and deterministic.
pub fn pixel_offset(x: u32, y: u32, s: u32, spp: u32) -> Vec2 {
    if spp <= 1 {
        return Vec2::splat(0.5);
    }
    let shift = Vec2::new(
        hash_unit(x, y, 0, STREAM_PIXEL),
        hash_unit(x, y, 1, STREAM_PIXEL),
    );
    (shift + s as f32 * R2_ALPHA).fract()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn angle_deg(a: Vec3, b: Vec3) -> f32 {
        a.normalize()
            .dot(b.normalize())
            .clamp(-1.0, 1.0)
            .acos()
            .to_degrees()
    }

    #[test]
    fn centre_ray_points_at_lookat() {
        let cam = Camera::look_at(
            Vec3::new(3.0, 2.0, 5.0),
            Vec3::new(-1.0, 0.5, 0.0),
            Vec3::Y,
            40.0,
            640,
            360,
        )
        .unwrap();
        let (o, d) = cam.ray(320.0, 180.0);
        assert_eq!(o, cam.position);
        assert!(angle_deg(d, Vec3::new(-1.0, 0.5, 0.0) - o) < 1e-3);
        // Row 0 is the top: the ray through the top edge leans towards `up`.
        assert!(cam.ray(320.0, 0.0).1.dot(cam.up) > 0.0);
        assert!(cam.ray(640.0, 180.0).1.dot(cam.right) > 0.0);
    }

    #[test]
    fn horizontal_fov_at_left_and_right_edges() {
        for (fov, w, h) in [(45.0, 1280, 720), (90.0, 100, 400), (10.0, 7, 3)] {
            let cam = Camera::look_at(Vec3::ZERO, -Vec3::Z, Vec3::Y, fov, w, h).unwrap();
            let (_, l) = cam.ray(0.0, h as f32 / 2.0);
            let (_, r) = cam.ray(w as f32, h as f32 / 2.0);
            assert!((angle_deg(l, r) - fov).abs() < 1e-3, "fov {fov}");
            assert!((angle_deg(l, cam.forward) - fov / 2.0).abs() < 1e-3);
            // Square pixels: the vertical half-angle follows from the aspect ratio.
            let (_, t) = cam.ray(w as f32 / 2.0, 0.0);
            let expect = ((fov / 2.0).to_radians().tan() * h as f32 / w as f32)
                .atan()
                .to_degrees();
            assert!((angle_deg(t, cam.forward) - expect).abs() < 1e-3);
        }
    }

    /// Projects a world point to continuous pixel coordinates.
    fn project(cam: &Camera, p: Vec3) -> Vec2 {
        let v = p - cam.position;
        let z = v.dot(cam.forward);
        let ndc = Vec2::new(v.dot(cam.right), v.dot(cam.up)) / z / cam.tan_half;
        Vec2::new(
            (ndc.x + 1.0) * 0.5 * cam.width as f32,
            (1.0 - ndc.y) * 0.5 * cam.height as f32,
        )
    }

    #[test]
    fn framing_centres_and_fits_the_box() {
        let boxes = [
            (Vec3::new(-1.0, -2.0, -3.0), Vec3::new(5.0, 1.0, 0.0)),
            (Vec3::new(10.0, 10.0, 10.0), Vec3::new(10.5, 14.0, 10.2)),
            (Vec3::splat(2.0), Vec3::splat(2.0)),
        ];
        for (lo, hi) in boxes {
            for (w, h) in [(1280u32, 720u32), (300, 900)] {
                let cam = Camera::framing(lo, hi, w, h, 45.0).unwrap();
                let c = 0.5 * (lo + hi);
                assert_eq!(cam.forward, -Vec3::Z);
                let centre = project(&cam, c);
                assert!((centre - Vec2::new(w as f32, h as f32) / 2.0).length() < 1e-2);
                let (_, d) = cam.ray(w as f32 / 2.0, h as f32 / 2.0);
                assert!(angle_deg(d, c - cam.position) < 1e-3);
                // Every corner inside the image, and the tighter axis filled up to the margin.
                let mut fill = 0.0f32;
                for n in 0..8 {
                    let corner =
                        Vec3::select(glam::BVec3::new(n & 1 != 0, n & 2 != 0, n & 4 != 0), hi, lo);
                    let p = project(&cam, corner);
                    let r = (p - Vec2::new(w as f32, h as f32) / 2.0).abs()
                        / (Vec2::new(w as f32, h as f32) / 2.0);
                    assert!(r.max_element() <= 1.0 - FRAMING_MARGIN + 1e-4, "{r}");
                    fill = fill.max(r.max_element());
                }
                if lo != hi {
                    assert!((fill - (1.0 - FRAMING_MARGIN)).abs() < 1e-3, "fill {fill}");
                }
            }
        }
    }

    #[test]
    fn bad_cameras_are_usage_errors() {
        let bad = [
            Camera::look_at(Vec3::ZERO, Vec3::ZERO, Vec3::Y, 45.0, 10, 10),
            Camera::look_at(Vec3::ZERO, Vec3::Y, Vec3::Y, 45.0, 10, 10),
            Camera::look_at(Vec3::ZERO, Vec3::Z, Vec3::Y, 180.0, 10, 10),
            Camera::look_at(Vec3::ZERO, Vec3::Z, Vec3::Y, f32::NAN, 10, 10),
            Camera::look_at(Vec3::ZERO, Vec3::Z, Vec3::Y, 45.0, 0, 10),
            Camera::look_at(Vec3::ZERO, Vec3::Z, Vec3::Y, 45.0, 100_000, 100_000),
            Camera::framing(Vec3::ZERO, Vec3::ONE, 10, 10, 0.0),
        ];
        for b in bad {
            assert!(matches!(b, Err(Error::Usage(_))));
        }
    }

    #[test]
    fn pixel_offsets_are_deterministic_and_inside_the_pixel() {
        assert_eq!(pixel_offset(3, 4, 0, 1), Vec2::splat(0.5));
        let mut mean = Vec2::ZERO;
        for s in 0..64 {
            let o = pixel_offset(3, 4, s, 64);
            assert_eq!(o, pixel_offset(3, 4, s, 64));
            assert!(o.min_element() >= 0.0 && o.max_element() < 1.0);
            mean += o / 64.0;
        }
        // R2 is well spread: its mean is close to the pixel centre.
        assert!((mean - Vec2::splat(0.5)).length() < 0.03, "{mean}");
        assert_ne!(pixel_offset(3, 4, 0, 4), pixel_offset(4, 3, 0, 4));
    }
}
