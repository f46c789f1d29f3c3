//! What one sun adds to a transfer render (thesis 7.1), built once per sun direction and kept
//! while the sun does not move:
//!
//! - **single scattering**, exact at the density's resolution: the [`ShadowVolume`] toward the
//!   sun, read by the march ([`super::march::SunRadiance`]);
//! - **multiple scattering**: one scalar solve ([`Lattice::solve_emission`]) on the suns' own
//!   lattice ([`SunLattice`]), finer than the transfer's, seeded per node by the sun's first
//!   scattering gathered from that same exact shadow, Q = albedo·⟨σt·ρ·e^{−τ_sun}⟩ over the
//!   node's footprint (per unit irradiance). Its fluence F is light scattered once or more before
//!   it reaches a node, so the in-scattered radiance there is p·F·E, interpolated between the
//!   suns' nodes as the transfer's are between its own.
//!
//! Bookkeeping: the sun is not in the environment map, so the SH transfer never sees it; its
//! unscattered light is counted once (the shadow volume), its scattered light once (the lattice,
//! driven only by first scatterings). Nothing projects the sun onto SH, so it neither snaps to a
//! lattice direction nor rings, and F ≥ 0 as every term of the solve is.

use std::sync::Arc;
use std::time::Instant;

use glam::{IVec3, Vec3};
use rayon::prelude::*;

use crate::transfer::lattice::{self, Lattice, LatticeKind};
use crate::transfer::memory::sun_solve_bytes;
use crate::transfer::{Medium, TransferLayout, PHASE};
use crate::volume::shadow::{ShadowCursor, ShadowVolume};
use crate::volume::{DensityField, SparseGrid};

/// The smallest cell edge, in density voxels, the suns' lattice is refined to. A sun's first
/// scatterings lie within an optical depth of the lit surface, and cells five or six optical
/// depths thick spread them too deep and read them back too dark; one sun on a black sky, σt 1,
/// albedo 0.9, against the path tracer (256×144): cloud / torus 19.9 / 29.3 % at an edge of 6,
/// 15.5 / 19.9 % at 5, 14.4 / 14.9 % at 4, **10.0 / 11.8 %** at 3 and 10.3 / 12.6 % at 2 (for
/// 3.4 times the nodes of 3).
const MIN_SUN_K: i32 = 3;

/// The most working memory a refined suns' lattice may take ([`sun_solve_bytes`]): past it a
/// volume's suns are solved on the transfer's own cells. Eight times the transfer's nodes, each
/// with its 26 links, is about 30 bytes per active voxel where the density takes 4; this bound
/// keeps a render of a cloud of tens of millions of voxels from growing by gigabytes, and is a
/// fixed figure so a render looks the same on every machine.
const MAX_REFINED_SOLVE_BYTES: u64 = 512 << 20;

/// The cell edge of the suns' lattice for `transfer`: half of its edge, not below [`MIN_SUN_K`],
/// nor past [`MAX_REFINED_SOLVE_BYTES`] — reckoned from the transfer's own nodes, 2³ times as
/// many (fewer where the volume's surface is large against it), so a volume of billions of
/// voxels is answered at once.
pub fn sun_k(
    density: &SparseGrid,
    transfer: &TransferLayout,
    kind: LatticeKind,
    sigma_t: f32,
) -> i32 {
    let k = transfer.k;
    let fine = ((k + 1) / 2).max(MIN_SUN_K).min(k);
    if fine == k {
        return k;
    }
    let nodes = transfer.len() as f64 * (k as f64 / fine as f64).powi(3);
    let reflecting = lattice::DensityMeans::new(density).reflecting_share(sigma_t, fine);
    match sun_solve_bytes(nodes as usize, kind.directions(), reflecting) <= MAX_REFINED_SOLVE_BYTES
    {
        true => fine,
        false => k,
    }
}

/// The lattice the suns' multiple scattering is solved on, one for all of a render's suns: its
/// nodes and, while new suns are solved, its links.
pub struct SunLattice {
    pub layout: Arc<TransferLayout>,
    lattice: Lattice,
}

impl SunLattice {
    pub fn build(
        field: &DensityField,
        layout: Arc<TransferLayout>,
        kind: LatticeKind,
        medium: Medium,
    ) -> SunLattice {
        let lattice = Lattice::build(field, &layout, kind, medium, 1);
        SunLattice { layout, lattice }
    }
}

/// A sun's multiple scattering: per node of `layout`, the fluence of its light scattered once or
/// more, per unit irradiance.
pub struct SunFluence {
    pub layout: Arc<TransferLayout>,
    pub fluence: Vec<f32>,
}

/// A sun's light on one volume.
pub struct SunLight {
    pub shadow: ShadowVolume,
    /// `None` after a `--single-scatter` bake.
    pub multiple: Option<SunFluence>,
    pub shadow_seconds: f64,
    pub lattice_seconds: f64,
}

impl SunLight {
    /// Sweeps the shadow toward `direction` (world, unit) and solves the multiple scattering on
    /// `lattice` (`None`: single scattering only).
    pub fn build(
        field: &DensityField,
        medium: Medium,
        lattice: Option<&SunLattice>,
        direction: Vec3,
    ) -> SunLight {
        let clock = Instant::now();
        let shadow = ShadowVolume::build(field, medium.sigma_t, direction);
        let shadow_seconds = clock.elapsed().as_secs_f64();
        let clock = Instant::now();
        let multiple = lattice.map(|l| {
            let seed = first_scattering(field, &l.layout, &shadow, medium);
            SunFluence {
                layout: l.layout.clone(),
                fluence: l.lattice.solve_emission(&seed),
            }
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

    /// Bytes held (the suns' shared layout not counted).
    pub fn memory_bytes(&self) -> u64 {
        self.shadow.memory_bytes()
            + self
                .multiple
                .as_ref()
                .map_or(0, |m| m.fluence.len() as u64 * 4)
    }
}

/// The suns' multiply scattered radiance p·Σ F·E at each node of their lattice, from each sun's
/// fluence and irradiance, and a last all-zero record for missing corners; `None` without any.
/// The suns of one render share one lattice ([`crate::scene`]).
pub fn multiple_radiance<'a>(
    suns: impl Iterator<Item = (&'a SunFluence, [f32; 3])>,
) -> Option<(Arc<TransferLayout>, Vec<[f32; 3]>)> {
    let mut out: Option<(Arc<TransferLayout>, Vec<[f32; 3]>)> = None;
    for (sun, irradiance) in suns {
        let (_, nodes) =
            out.get_or_insert_with(|| (sun.layout.clone(), vec![[0.0; 3]; sun.layout.len() + 1]));
        for (node, f) in nodes.iter_mut().zip(&sun.fluence) {
            for (c, e) in node.iter_mut().zip(irradiance) {
                *c += PHASE * f * e;
            }
        }
    }
    out
}

/// Q per node of `layout`: albedo × the mean over its footprint of σt·ρ·e^{−τ_sun}, the power
/// the sun's unit irradiance has scattered there per unit volume after its exact shadow.
fn first_scattering(
    field: &DensityField,
    layout: &TransferLayout,
    shadow: &ShadowVolume,
    medium: Medium,
) -> Vec<f32> {
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::grid::{block_box, TileLevel, Transform};

    #[test]
    fn the_suns_lattice_halves_the_transfers_cells_down_to_three_voxels() {
        let g = block_box(IVec3::splat(48));
        let k = |k| sun_k(&g, &TransferLayout::build(&g, k), LatticeKind::All, 1.0);
        assert_eq!([2, 3, 4, 5, 6, 7, 8, 12].map(k), [2, 3, 3, 3, 3, 4, 4, 6]);
    }

    #[test]
    fn a_volume_too_large_to_refine_keeps_the_transfers_cells() {
        // 3³ node tiles, a box of 384³ voxels: 66³ nodes at an edge of 6, 2.3 M at 3 (1.4 GiB of
        // links); a single block of them refines.
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        for n in 0..27 {
            let origin = IVec3::new(n / 9, (n / 3) % 3, n % 3) * 128;
            g.insert_tile(TileLevel::Node, origin, 1.0);
        }
        assert_eq!(
            sun_k(&g, &TransferLayout::build(&g, 6), LatticeKind::All, 1.0),
            6
        );
        let small = block_box(IVec3::splat(8));
        let layout = TransferLayout::build(&small, 6);
        assert_eq!(sun_k(&small, &layout, LatticeKind::All, 1.0), 3);
    }
}
