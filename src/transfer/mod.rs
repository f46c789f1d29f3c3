//! The transfer: per transfer voxel, SH coefficients of the fraction of environment light from each
//! direction that reaches it — unscattered (`t_ri`, thesis eq. 4.1) and after one or more
//! scattering events (`f_ms`, thesis 4.2) — independent of any environment.

pub mod grid;
pub mod single;

pub use grid::TransferLayout;

/// The participating medium (DESIGN.md): σt = `sigma_t`·ρ per world unit, σs = `albedo`·σt,
/// isotropic phase.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Medium {
    pub sigma_t: f32,
    pub albedo: f32,
}

/// A baked transfer over a sparse layout: `bands²` coefficients per voxel, voxel after voxel.
#[derive(Clone)]
pub struct Transfer {
    pub layout: TransferLayout,
    pub bands: usize,
    pub medium: Medium,
    /// Unscattered transfer T_ri, `layout.len() × bands²`.
    pub t_ri: Vec<f32>,
    /// Multiply-scattered transfer F_ms (zero after a `--single-scatter` bake), same shape.
    pub f_ms: Vec<f32>,
}

impl Transfer {
    pub fn coeffs(&self) -> usize {
        self.bands * self.bands
    }

    /// T_ri coefficients of the voxel in `slot`.
    pub fn t_ri(&self, slot: usize) -> &[f32] {
        let n = self.coeffs();
        &self.t_ri[slot * n..(slot + 1) * n]
    }

    /// F_ms coefficients of the voxel in `slot`.
    pub fn f_ms(&self, slot: usize) -> &[f32] {
        let n = self.coeffs();
        &self.f_ms[slot * n..(slot + 1) * n]
    }
}
