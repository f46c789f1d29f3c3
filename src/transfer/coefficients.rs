//! The transfer's coefficients as held in memory: f32 as a bake makes them, or in the reduced
//! precision a cache stores them ([`super::packing::Precision`]), decoded a voxel at a time where
//! they are used.
//!
//! A render from a cache needs the coefficients only to relight, which reads each voxel's once.
//! Held as f32, an f16 or q8 cache's coefficients would take two or three times the memory — on a
//! big cloud the largest thing a render holds — for values that are the cache's own either way.
//! So a reduced cache is held as stored, and every value decodes to exactly the f32 its precision
//! gives.

use std::borrow::Cow;

use half::f16;
use half::slice::HalfFloatSliceExt;

use crate::light::sh::MAX_BANDS;
use crate::transfer::packing::Precision;

/// The largest magnitude of a q8 coefficient: 8-bit signed, symmetric.
pub const Q8_MAX: f32 = 127.0;

/// The most coefficients a voxel holds: what one voxel decodes into on the stack.
pub const MAX_COEFFS: usize = MAX_BANDS * MAX_BANDS;

/// `coeffs` coefficients per voxel, voxel after voxel.
#[derive(Debug, Clone, PartialEq)]
pub enum Coefficients {
    F32(Vec<f32>),
    F16(Vec<f16>),
    /// Per voxel an f16 DC term; per voxel and band l ≥ 1 an f16 scale s and 2l + 1 signed bytes
    /// q, the coefficient being q·s/127 ([`super::packing::put_coefficients`]).
    Q8 {
        dc: Vec<f16>,
        scales: Vec<f16>,
        bytes: Vec<i8>,
    },
}

impl Coefficients {
    /// Values held: voxels × coefficients per voxel.
    pub fn len(&self) -> usize {
        match self {
            Coefficients::F32(v) => v.len(),
            Coefficients::F16(v) => v.len(),
            Coefficients::Q8 { dc, bytes, .. } => dc.len() + bytes.len(),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The precision the values are held at.
    pub fn precision(&self) -> Precision {
        match self {
            Coefficients::F32(_) => Precision::F32,
            Coefficients::F16(_) => Precision::F16,
            Coefficients::Q8 { .. } => Precision::Q8,
        }
    }

    /// Bytes held.
    pub fn memory_bytes(&self) -> usize {
        match self {
            Coefficients::F32(v) => v.len() * 4,
            Coefficients::F16(v) => v.len() * 2,
            Coefficients::Q8 { dc, scales, bytes } => (dc.len() + scales.len()) * 2 + bytes.len(),
        }
    }

    /// Voxel `slot`'s `out.len()` coefficients (`coeffs` per voxel) as f32, written to `out`.
    pub fn voxel(&self, slot: usize, out: &mut [f32]) {
        let n = out.len();
        match self {
            Coefficients::F32(v) => out.copy_from_slice(&v[slot * n..(slot + 1) * n]),
            Coefficients::F16(v) => v[slot * n..(slot + 1) * n].convert_to_f32_slice(out),
            Coefficients::Q8 { dc, scales, bytes } => {
                let per_voxel = bands_of(n) - 1;
                q8_voxel(
                    dc[slot],
                    &scales[slot * per_voxel..(slot + 1) * per_voxel],
                    &bytes[slot * (n - 1)..(slot + 1) * (n - 1)],
                    out,
                );
            }
        }
    }

    /// Every value as f32 (borrowed when held so).
    pub fn to_f32(&self, coeffs: usize) -> Cow<'_, [f32]> {
        match self {
            Coefficients::F32(v) => Cow::Borrowed(v),
            _ => {
                let mut out = vec![0.0; self.len()];
                for (slot, voxel) in out.chunks_exact_mut(coeffs.max(1)).enumerate() {
                    self.voxel(slot, voxel);
                }
                Cow::Owned(out)
            }
        }
    }
}

/// One q8 voxel's `out.len()` coefficients as f32: its DC term, its scale per band l ≥ 1 and its
/// signed bytes after the DC term.
fn q8_voxel(dc: f16, scales: &[f16], q: &[i8], out: &mut [f32]) {
    out[0] = dc.to_f32();
    for (l, scale) in (1..bands_of(out.len())).zip(scales) {
        let s = scale.to_f32() / Q8_MAX;
        let (lo, hi) = (l * l, (l + 1) * (l + 1));
        for (o, b) in out[lo..hi].iter_mut().zip(&q[lo - 1..hi - 1]) {
            *o = *b as f32 * s;
        }
    }
}

/// Bands of a voxel with `coeffs` = bands² coefficients.
pub fn bands_of(coeffs: usize) -> usize {
    (1..).find(|b| b * b >= coeffs).unwrap_or(1)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_precision_decodes_each_voxel_as_stored() {
        // Two voxels of 2 bands: DC, then band 1's three coefficients.
        let f32s = vec![1.0, -0.5, 0.25, 2.0, 3.0, 0.0, 0.0, -1.0];
        let held = [
            Coefficients::F32(f32s.clone()),
            Coefficients::F16(f32s.iter().map(|v| f16::from_f32(*v)).collect()),
            Coefficients::Q8 {
                dc: vec![f16::from_f32(1.0), f16::from_f32(3.0)],
                // Scales of 31.75 make q·s/127 = q/4 exactly.
                scales: vec![f16::from_f32(31.75); 2],
                bytes: vec![-2, 1, 8, 0, 0, -4],
            },
        ];
        for c in &held {
            assert_eq!(c.len(), 8);
            assert_eq!(c.to_f32(4).as_ref(), &f32s[..], "{c:?}");
            let mut one = [0.0; 4];
            c.voxel(1, &mut one);
            assert_eq!(one, [3.0, 0.0, 0.0, -1.0]);
        }
        assert_eq!(held.map(|c| c.memory_bytes()), [32, 16, 14]);
    }
}
