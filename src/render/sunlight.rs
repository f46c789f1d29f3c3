//! What one sun adds to a transfer render (thesis 7.1), built once per sun direction and kept
//! while the sun does not move:
//!
//! - **single scattering**, exact at the density's resolution: the [`ShadowVolume`] toward the
//!   sun, read by the march ([`super::march::SunRadiance`]);
//! - **multiple scattering**: one scalar lattice solve ([`lattice::solve_emission`]) seeded, per
//!   transfer voxel, by the sun's first scattering gathered from that same exact shadow,
//!   Q = albedo·⟨σt·ρ·e^{−τ_sun}⟩ over the voxel's footprint (per unit irradiance). Its fluence
//!   F is light scattered once or more before it reaches a node, so the in-scattered radiance of
//!   a node is p·F·E, added to the node's indirect part.
//!
//! Bookkeeping: the sun is not in the environment map, so the SH transfer never sees it; its
//! unscattered light is counted once (the shadow volume), its scattered light once (the lattice,
//! driven only by first scatterings). Nothing projects the sun onto SH, so it neither snaps to a
//! lattice direction nor rings, and F ≥ 0 as every term of the solve is.

use std::time::Instant;

use glam::{IVec3, Vec3};
use rayon::prelude::*;

use crate::transfer::lattice;
use crate::transfer::{Medium, Transfer};
use crate::volume::shadow::{ShadowCursor, ShadowVolume};
use crate::volume::DensityField;

/// A sun's light on one volume and transfer.
pub struct SunLight {
    pub shadow: ShadowVolume,
    /// Per transfer voxel (layout slot order): fluence of the sun's light scattered once or more,
    /// per unit irradiance. `None` after a `--single-scatter` bake.
    pub multiple: Option<Vec<f32>>,
    pub shadow_seconds: f64,
    pub lattice_seconds: f64,
}

impl SunLight {
    /// Sweeps the shadow toward `direction` (world, unit) and solves the multiple scattering on
    /// the transfer's lattice.
    pub fn build(field: &DensityField, transfer: &Transfer, direction: Vec3) -> SunLight {
        let medium = transfer.medium;
        let clock = Instant::now();
        let shadow = ShadowVolume::build(field, medium.sigma_t, direction);
        let shadow_seconds = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let multiple = transfer.lattice.map(|kind| {
            let seed = first_scattering(field, transfer, &shadow, medium);
            lattice::solve_emission(field, &transfer.layout, kind, medium, &seed)
        });
        SunLight {
            shadow,
            multiple,
            shadow_seconds,
            lattice_seconds: clock.elapsed().as_secs_f64(),
        }
    }

    /// Whether this light was built for `direction` in `medium` (and can be kept).
    pub fn is_for(&self, direction: Vec3, medium: Medium) -> bool {
        self.shadow.direction == direction && self.shadow.sigma_t == medium.sigma_t
    }

    /// Bytes held.
    pub fn memory_bytes(&self) -> u64 {
        self.shadow.memory_bytes() + self.multiple.as_ref().map_or(0, |m| m.len() as u64 * 4)
    }
}

/// Q per transfer voxel: albedo × the mean over its footprint of σt·ρ·e^{−τ_sun}, the power the
/// sun's unit irradiance has scattered there per unit volume after its exact shadow.
fn first_scattering(
    field: &DensityField,
    transfer: &Transfer,
    shadow: &ShadowVolume,
    medium: Medium,
) -> Vec<f32> {
    let layout = &transfer.layout;
    let k = layout.k;
    // Footprint of voxel a: density voxels i with ⌊(i + ⌊K/2⌋)/K⌋ = a (docs/model.md).
    let low = |a: IVec3| a * k - IVec3::splat(k / 2);
    let scale = medium.albedo * medium.sigma_t / (k * k * k) as f32;
    layout
        .voxels()
        .par_iter()
        .map(|&a| {
            let mut sampler = field.sampler();
            let mut cursor = ShadowCursor::default();
            let base = low(a);
            let mut sum = 0.0f32;
            for x in 0..k {
                for y in 0..k {
                    for z in 0..k {
                        let voxel = base + IVec3::new(x, y, z);
                        let rho = sampler.sample(voxel.as_vec3());
                        if rho > 0.0 {
                            // A voxel's own depth is what the sweep stored there, exactly.
                            let tau = shadow.core_value(voxel, &mut cursor).unwrap_or(0.0);
                            sum += rho * (-tau).exp();
                        }
                    }
                }
            }
            sum * scale
        })
        .collect()
}
