//! Grid transforms (docs/vdb-format.md, "Transforms"): the scale/translate family is read into a [`Transform`];
//! rotations, shears, frustums and unknown maps are refused with their name.

use glam::DVec3;

use super::cursor::Cursor;
use super::VdbError;
use crate::volume::Transform;

/// Longest map type name accepted, so a forged length allocates nothing big.
const MAX_MAP_NAME: usize = 256;

/// Reads a transform; also returns the map's type name for display.
pub fn read_transform(cur: &mut Cursor) -> Result<(Transform, String), VdbError> {
    let name = cur.string(MAX_MAP_NAME, "transform map name")?;
    let mut vec3 = |what: &str| -> Result<DVec3, VdbError> {
        Ok(DVec3::new(cur.f64(what)?, cur.f64(what)?, cur.f64(what)?))
    };
    let t = match name.as_str() {
        "UniformScaleMap" | "ScaleMap" => {
            let scale = vec3("map scale")?;
            for _ in 0..4 {
                vec3("map derived values")?;
            }
            Transform {
                scale,
                translation: DVec3::ZERO,
            }
        }
        "UniformScaleTranslateMap" | "ScaleTranslateMap" => {
            let translation = vec3("map translation")?;
            let scale = vec3("map scale")?;
            for _ in 0..4 {
                vec3("map derived values")?;
            }
            Transform { scale, translation }
        }
        "TranslationMap" => Transform {
            scale: DVec3::ONE,
            translation: vec3("map translation")?,
        },
        "AffineMap" | "UnitaryMap" => {
            let mut m = [0f64; 16];
            for v in m.iter_mut() {
                *v = cur.f64("affine matrix")?;
            }
            // Row-vector convention: world = (i,j,k,1)·M. Only a diagonal 3×3 with no projective
            // part is a scale+translate in disguise.
            let off_diagonal = [1, 2, 4, 6, 8, 9];
            if off_diagonal.iter().any(|&i| m[i] != 0.0) || m[3] != 0.0 || m[7] != 0.0 || m[11] != 0.0 || m[15] != 1.0 {
                return Err(VdbError::new(format!(
                    "{name} with rotation, shear or projection is not supported (only scale and translation)"
                )));
            }
            Transform {
                scale: DVec3::new(m[0], m[5], m[10]),
                translation: DVec3::new(m[12], m[13], m[14]),
            }
        }
        "NonlinearFrustumMap" => {
            return Err(VdbError::new(
                "NonlinearFrustumMap (frustum) transforms are not supported (only scale and translation)",
            ))
        }
        other => {
            return Err(VdbError::new(format!(
                "unknown transform map type {other:?}"
            )))
        }
    };
    if !(t.scale.is_finite() && t.translation.is_finite()) {
        return Err(VdbError::new(format!("{name} has a non-finite value")));
    }
    if t.scale.cmpeq(DVec3::ZERO).any() {
        return Err(VdbError::new(format!("{name} has a zero scale")));
    }
    Ok((t, name))
}
