//! What one sun adds to a transfer render (thesis 7.1), built once per sun direction and kept
//! while the sun does not move:
//!
//! - **single scattering**, exact at the density's resolution: the [`ShadowVolume`] toward the
//!   sun, read by the march ([`super::march::SunRadiance`]);
//! - **multiple scattering**: one scalar solve ([`Lattice::solve_emission`]) on the suns' own
//!   lattice ([`SunLattice`]), finer than the transfer's, seeded per node by the sun's first
//!   scattering gathered from that same exact shadow, Q = albedo·⟨σt·ρ·e^{−τ_sun}⟩ over the
//!   node's footprint (per unit irradiance; each voxel's e^{−τ_sun} its mean, [`cube_mean`]). Its
//!   fluence F is light scattered once or more before
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

/// The cell edge, in density voxels, the suns' lattice takes where its working memory allows
/// ([`MAX_SUN_SOLVE_BYTES`]): the density's own voxels. A cell larger than a voxel is partly
/// empty wherever a surface crosses it, and its node then reads the light of the wrong depth:
/// a slab of albedo 1 lit by one sun, against the path tracer, is −20.0, +16.2 and +18.1 % off
/// at cells of 3 for heights of 30, 31 and 32 voxels, −18.9, +8.0 and −18.9 % at 2, and −0.5,
/// −0.6 and −0.6 % at 1 (σt 1, docs/accuracy.md#suns).
const VOXEL_SUN_K: i32 = 1;

/// The smallest cell edge, in density voxels, the suns' lattice is refined to where the
/// density's own voxels are too many. A sun's first scatterings lie within an optical depth of
/// the lit surface, and cells five or six optical depths thick spread them too deep and read
/// them back too dark; one sun on a black sky, σt 1, albedo 0.9, against the path tracer
/// (256×144): cloud / torus 19.9 / 29.3 % at an edge of 6, 15.5 / 19.9 % at 5, 14.4 / 14.9 % at
/// 4, **10.0 / 11.8 %** at 3 and 10.3 / 12.6 % at 2 (for 3.4 times the nodes of 3); 6.0 / 6.9 %
/// at the density's voxels ([`VOXEL_SUN_K`]).
const MIN_SUN_K: i32 = 3;

/// The most working memory a suns' lattice finer than the transfer's may take
/// ([`sun_solve_bytes`]); past it a volume's suns are solved on coarser cells. The finest cells
/// cost the most: the fixture cloud's 223 749 voxel nodes take 1.4 s and 197 MiB per sun where its
/// cells of 3 take 0.06 s and 33 MiB. This bound keeps a render of a cloud of tens of millions of
/// voxels from growing by gigabytes, and is a fixed figure so a render looks the same on every
/// machine.
const MAX_SUN_SOLVE_BYTES: u64 = 512 << 20;

/// The directions of the suns' lattice, whatever the transfer's `--lattice`: the faces and the 24
/// offsets like (2, 2, 1). A sun's scattered light is read mostly just under its lit surfaces,
/// where what matters is how fast light leaves through a face, the half-range moment
/// Σ w·max(d̂·n, 0): ¼ on the sphere, 0.232 for the 26 neighbours on an axis face (their 8 level
/// directions stand for a third of the sphere), 0.247 for this set. The energy check's slab
/// (docs/accuracy.md) goes from +4.8 / +2.6 % at σt 0.2 / 1 to 0.0 / −1.6 %, the sphere and cloud
/// stay within 2 %, for 17 % more solve time on the bench cloud.
pub const SUN_LATTICE: LatticeKind = LatticeKind::FacesSkew;

/// The suns' lattice for `transfer`: on the density's own voxels where their solve fits
/// [`MAX_SUN_SOLVE_BYTES`], else on cells of half the transfer's edge (not below [`MIN_SUN_K`])
/// where theirs does, else the transfer's own. A finer layout is laid out only once it may fit —
/// reckoned from the active voxels, each a node at least, and from the transfer's nodes, k³
/// times as many per cell at most — so a volume of billions of voxels is answered at once.
pub fn sun_layout(density: &SparseGrid, transfer: &TransferLayout, sigma_t: f32) -> TransferLayout {
    let k = transfer.k;
    let means = lattice::DensityMeans::new(density);
    let solve_bytes = |nodes: u64, fine: i32| {
        let reflecting = means.reflecting_share(sigma_t, fine, SUN_LATTICE);
        sun_solve_bytes(nodes as usize, SUN_LATTICE.directions(), reflecting)
    };
    if k > VOXEL_SUN_K && solve_bytes(density.active_voxels(), VOXEL_SUN_K) <= MAX_SUN_SOLVE_BYTES {
        let voxels = TransferLayout::build(density, VOXEL_SUN_K);
        if solve_bytes(voxels.len() as u64, VOXEL_SUN_K) <= MAX_SUN_SOLVE_BYTES {
            return voxels;
        }
    }
    let refined = ((k + 1) / 2).max(MIN_SUN_K).min(k);
    let nodes = transfer.len() as f64 * (k as f64 / refined as f64).powi(3);
    match refined < k && solve_bytes(nodes as u64, refined) <= MAX_SUN_SOLVE_BYTES {
        true => TransferLayout::build(density, refined),
        false => transfer.clone(),
    }
}

/// The lattice the suns' multiple scattering is solved on, one for all of a render's suns: its
/// nodes and, while new suns are solved, its links.
pub struct SunLattice {
    pub layout: Arc<TransferLayout>,
    lattice: Lattice,
}

impl SunLattice {
    pub fn build(field: &DensityField, layout: Arc<TransferLayout>, medium: Medium) -> SunLattice {
        let lattice = Lattice::build(field, &layout, SUN_LATTICE, medium, 1);
        SunLattice { layout, lattice }
    }
}

/// A sun's multiple scattering: per node of `layout`, the fluence of its light scattered once or
/// more, per unit irradiance.
pub struct SunFluence {
    pub layout: Arc<TransferLayout>,
    pub fluence: Vec<f32>,
    /// How many generations its solve swept ([`Lattice::solve_emission`]).
    pub sweeps: usize,
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
            let (fluence, sweeps) = l.lattice.solve_emission(&seed);
            SunFluence {
                layout: l.layout.clone(),
                fluence,
                sweeps,
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
                            let mut depth = |v| shadow.core_value(v, &mut cursor);
                            let tau = depth(voxel).unwrap_or(0.0);
                            // τ_sun's change across the voxel along each axis, from its
                            // neighbours' depths (one side where the other is not stored).
                            let mut across = Vec3::ZERO;
                            for a in 0..3 {
                                let e = IVec3::AXES[a];
                                across[a] = match (depth(voxel - e), depth(voxel + e)) {
                                    (Some(lo), Some(hi)) => 0.5 * (hi - lo),
                                    (Some(lo), None) => tau - lo,
                                    (None, Some(hi)) => hi - tau,
                                    (None, None) => 0.0,
                                };
                            }
                            sum += rho * (-tau).exp() * cube_mean(across.abs());
                        }
                    }
                }
            }
            sum * scale
        })
        .collect()
}

/// The mean of e^(−g·v) over the unit cube v ∈ [−½, ½]³ (e^(−τ) at the centre being 1):
/// Π sinh(g_a/2)/(g_a/2). Under a lit face τ_sun falls by g_a per voxel along axis a, and
/// e^(−τ) is convex, so a voxel's first scatterings are its centre's times this, not its
/// centre's alone: 4.2 % more where τ_sun changes by 1 across the voxel, 17.5 % where by 2.
fn cube_mean(g: Vec3) -> f32 {
    let mean = |g: f32| {
        let h = 0.5 * g;
        // sinh(h)/h = 1 + h²/6 + h⁴/120 + h⁶/5040 + …, within 3·10⁻⁶ for h ≤ 1 (most voxels)
        // and a third of the time of sinh: the seed takes it three times per voxel.
        let h2 = h * h;
        match h2 <= 1.0 {
            true => 1.0 + h2 * (1.0 / 6.0 + h2 * (1.0 / 120.0 + h2 / 5040.0)),
            false => h.sinh() / h,
        }
    };
    mean(g.x) * mean(g.y) * mean(g.z)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::grid::{block_box, TileLevel, Transform};

    /// The edge of the suns' lattice for `g` at transfer edge `k`.
    fn sun_k(g: &SparseGrid, k: i32) -> i32 {
        sun_layout(g, &TransferLayout::build(g, k), 1.0).k
    }

    #[test]
    fn a_voxels_first_scatterings_are_its_mean_not_its_centres() {
        // A uniform slab, the sun straight above: τ_sun falls by σt per voxel along z, so a
        // voxel's first scatterings are albedo·σt·e^(−τ_centre)·sinh(σt/2)/(σt/2) per unit
        // irradiance (the mean of e^(−τ) across it) — 4.2 % above the centre's at σt 1, 17.5 % at 2.
        let field = DensityField::new(block_box(IVec3::new(16, 16, 32)));
        let layout = TransferLayout::build(&field.grid, 1);
        for sigma_t in [1.0f32, 2.0] {
            let medium = Medium {
                sigma_t,
                albedo: 0.8,
            };
            let shadow = ShadowVolume::build(&field, sigma_t, Vec3::Z);
            let seed = first_scattering(&field, &layout, &shadow, medium);
            let h = 0.5 * sigma_t;
            for z in [20, 25, 28] {
                let voxel = IVec3::new(8, 8, z);
                let slot = layout.slot(voxel).unwrap();
                let tau = shadow
                    .core_value(voxel, &mut ShadowCursor::default())
                    .unwrap();
                let want = medium.albedo * sigma_t * (-tau).exp() * h.sinh() / h;
                assert!(
                    (seed[slot] / want - 1.0).abs() < 1e-4,
                    "{sigma_t} {z}: {} vs {want}",
                    seed[slot]
                );
            }
        }
        // The factor itself against a midpoint quadrature of e^(−g·v) over the cube.
        let g = Vec3::new(0.3, 1.7, 4.0);
        let n = 200;
        let axis = |g: f32| {
            (0..n)
                .map(|i| (-g * ((i as f32 + 0.5) / n as f32 - 0.5)).exp())
                .sum::<f32>()
                / n as f32
        };
        let quadrature = axis(g.x) * axis(g.y) * axis(g.z);
        assert!((cube_mean(g) / quadrature - 1.0).abs() < 1e-4);
        assert_eq!(cube_mean(Vec3::ZERO), 1.0);
    }

    #[test]
    fn the_suns_lattice_takes_the_density_voxels_where_they_fit() {
        let g = block_box(IVec3::splat(48));
        assert_eq!([1, 2, 3, 6, 12].map(|k| sun_k(&g, k)), [1; 5]);
    }

    #[test]
    fn a_volume_too_large_for_voxel_cells_halves_the_transfers_cells_or_keeps_them() {
        // 3³ node tiles, a box of 384³ voxels: 57 M voxel nodes; 2.3 M at an edge of 3 (1.4 GiB of
        // links) and 305 000 at 6, so the suns keep the transfer's cells; at an edge of 12 the
        // transfer has 38 000 and its half-edge cells (6) fit.
        let mut g = SparseGrid::new(Transform::default(), 0.0);
        for n in 0..27 {
            let origin = IVec3::new(n / 9, (n / 3) % 3, n % 3) * 128;
            g.insert_tile(TileLevel::Node, origin, 1.0);
        }
        assert_eq!([6, 12].map(|k| sun_k(&g, k)), [6, 6]);
        // A 128³ node tile: 2.1 M voxel nodes are too many; its cells of 3 (85 000) fit.
        let mut one = SparseGrid::new(Transform::default(), 0.0);
        one.insert_tile(TileLevel::Node, IVec3::ZERO, 1.0);
        assert_eq!(
            [2, 3, 4, 5, 6, 7, 8, 12].map(|k| sun_k(&one, k)),
            [2, 3, 3, 3, 3, 4, 4, 6]
        );
    }
}
