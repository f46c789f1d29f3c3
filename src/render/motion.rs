//! How the camera moves over a sequence: still, an orbit about the volume's centre, or a keyed
//! path read from a small text file (docs/cli.md, "Camera paths"), interpolated linearly.

use std::path::Path;

use glam::{Quat, Vec3};

use super::CameraSpec;
use crate::error::{Error, Result};

/// One key of a camera path.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Key {
    pub frame: f64,
    pub position: Vec3,
    pub lookat: Vec3,
    pub fov_deg: f32,
}

/// The camera's motion over a sequence.
#[derive(Debug, Clone, PartialEq)]
pub enum Motion {
    Still,
    /// Turns about the vertical axis through the look-at point by this many degrees over the
    /// sequence (360: a loop whose last frame leads back into the first).
    Orbit(f32),
    /// Keys in increasing frame order.
    Path(Vec<Key>),
}

impl Motion {
    /// Reads a camera path: one key a line, `FRAME PX PY PZ LX LY LZ FOV` (whitespace or commas
    /// between), `#` comments and blank lines ignored, frames strictly increasing.
    pub fn read_path(path: &Path) -> Result<Motion> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Motion::parse_path(&text).map_err(|m| Error::format(path, m))
    }

    fn parse_path(text: &str) -> std::result::Result<Motion, String> {
        let mut keys: Vec<Key> = Vec::new();
        for (n, line) in text.lines().enumerate() {
            let line = line.split('#').next().unwrap_or("").trim();
            if line.is_empty() {
                continue;
            }
            let bad = || {
                format!(
                    "line {}: expected FRAME PX PY PZ LX LY LZ FOV (8 finite numbers, FOV in (0, 180))",
                    n + 1
                )
            };
            let v: Vec<f64> = line
                .split(|c: char| c.is_whitespace() || c == ',')
                .filter(|s| !s.is_empty())
                .map(|s| s.parse::<f64>().map_err(|_| bad()))
                .collect::<std::result::Result<_, _>>()?;
            if v.len() != 8 || !v.iter().all(|x| x.is_finite()) || !(v[7] > 0.0 && v[7] < 180.0) {
                return Err(bad());
            }
            let key = Key {
                frame: v[0],
                position: Vec3::new(v[1] as f32, v[2] as f32, v[3] as f32),
                lookat: Vec3::new(v[4] as f32, v[5] as f32, v[6] as f32),
                fov_deg: v[7] as f32,
            };
            if keys.last().is_some_and(|k| k.frame >= key.frame) {
                return Err(format!("line {}: frames must increase", n + 1));
            }
            keys.push(key);
        }
        if keys.is_empty() {
            return Err("no keys (one a line: FRAME PX PY PZ LX LY LZ FOV)".into());
        }
        Ok(Motion::Path(keys))
    }

    /// The box a camera moving this way must frame for the volume in `bounds` to stay in the
    /// picture: for an orbit, widened to a square about the vertical axis (seen from any side, the
    /// box's horizontal extent is its widest).
    pub fn widen(&self, (lo, hi): (Vec3, Vec3)) -> (Vec3, Vec3) {
        match self {
            Motion::Orbit(_) => {
                let (c, h) = (0.5 * (lo + hi), 0.5 * (hi - lo));
                let r = h.x.max(h.z);
                let half = Vec3::new(r, h.y, r);
                (c - half, c + half)
            }
            _ => (lo, hi),
        }
    }

    /// The camera of frame `frame`, the `index`-th of `count`, moved from `base`: an orbit turns
    /// `base`'s position (or, without one, the framing camera's at `framing` distance) about the
    /// look-at point; a path sets position, look-at and field of view from its keys, held before
    /// the first and after the last.
    pub fn spec_at(
        &self,
        base: &CameraSpec,
        framing_position: Vec3,
        lookat: Vec3,
        frame: f64,
        index: usize,
        count: usize,
    ) -> CameraSpec {
        match self {
            Motion::Still => *base,
            Motion::Orbit(degrees) => {
                let angle = (degrees * index as f32 / count.max(1) as f32).to_radians();
                let from = base.position.unwrap_or(framing_position) - lookat;
                CameraSpec {
                    position: Some(lookat + Quat::from_axis_angle(Vec3::Y, angle) * from),
                    lookat: Some(lookat),
                    ..*base
                }
            }
            Motion::Path(keys) => {
                let after = keys.partition_point(|k| k.frame <= frame);
                let key = match after {
                    0 => keys[0],
                    n if n == keys.len() => keys[n - 1],
                    n => {
                        let (a, b) = (keys[n - 1], keys[n]);
                        let t = ((frame - a.frame) / (b.frame - a.frame)) as f32;
                        Key {
                            frame,
                            position: a.position.lerp(b.position, t),
                            lookat: a.lookat.lerp(b.lookat, t),
                            fov_deg: a.fov_deg + t * (b.fov_deg - a.fov_deg),
                        }
                    }
                };
                CameraSpec {
                    position: Some(key.position),
                    lookat: Some(key.lookat),
                    fov_deg: key.fov_deg,
                    ..*base
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn base() -> CameraSpec {
        CameraSpec {
            position: None,
            lookat: None,
            up: Vec3::Y,
            fov_deg: 45.0,
            width: 8,
            height: 8,
        }
    }

    #[test]
    fn an_orbit_turns_about_the_lookat_and_keeps_its_distance() {
        let m = Motion::Orbit(360.0);
        let centre = Vec3::new(1.0, 2.0, 3.0);
        let start = centre + Vec3::new(0.0, 0.5, 4.0);
        for i in 0..8 {
            let s = m.spec_at(&base(), start, centre, 0.0, i, 8);
            let p = s.position.unwrap();
            assert!(((p - centre).length() - (start - centre).length()).abs() < 1e-4);
            assert!((p.y - start.y).abs() < 1e-5);
            assert_eq!(s.lookat, Some(centre));
        }
        // A quarter of the way round a 360° orbit: +Z has turned to +X.
        let q = m
            .spec_at(&base(), start, centre, 0.0, 2, 8)
            .position
            .unwrap();
        assert!(
            (q - (centre + Vec3::new(4.0, 0.5, 0.0))).length() < 1e-4,
            "{q}"
        );
    }

    #[test]
    fn a_path_interpolates_between_keys_and_holds_at_its_ends() {
        let m = Motion::parse_path(
            "# frame  position  lookat  fov\n1001 0 0 10  0 0 0  40\n\n1011, 10,0,10, 0,0,0, 60 # wide\n",
        )
        .unwrap();
        let at = |f: f64| m.spec_at(&base(), Vec3::ZERO, Vec3::ZERO, f, 0, 1);
        let mid = at(1006.0);
        assert_eq!(mid.position, Some(Vec3::new(5.0, 0.0, 10.0)));
        assert_eq!(mid.fov_deg, 50.0);
        assert_eq!(at(900.0).position, Some(Vec3::new(0.0, 0.0, 10.0)));
        assert_eq!(at(2000.0).fov_deg, 60.0);
        for bad in [
            "",
            "1 0 0 0 0 0 0",
            "1 0 0 0 0 0 0 200",
            "2 0 0 1 0 0 0 40\n1 0 0 1 0 0 0 40",
            "1 0 0 nan 0 0 0 40",
        ] {
            assert!(Motion::parse_path(bad).is_err(), "{bad:?}");
        }
    }
}
