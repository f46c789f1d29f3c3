//! Single scattering: the unscattered transfer T_ri (thesis 4.1). For every transfer voxel, rays are
//! marched from its centre *toward* a set of well-spread directions ω through the fine density,
//! T_ri(x, ω) = exp(−∫ σt ρ ds), and the results are projected onto SH as one matrix product with
//! precomputed, quadrature-weighted basis values.
//!
//! To keep quadrature errors from lining up into visible patterns, there are [`DIRECTION_SETS`]
//! spherical-Fibonacci sets, each under its own fixed random rotation, and each voxel picks one by a
//! hash of its coordinates — deterministic for a given seed.

use glam::{IVec3, Quat, Vec3};
use rand::{Rng, SeedableRng};
use rayon::prelude::*;

use super::basis::Basis;
use super::layout::TransferLayout;
use crate::light::sh;
use crate::volume::transmittance::{FarField, OpticalDepth, MIN_TRANSMITTANCE};
use crate::volume::visibility::Visibility;
use crate::volume::SparseGrid;

/// Independently rotated direction sets: enough that neighbouring voxels rarely share one, few
/// enough that all basis matrices stay in cache-friendly memory (32 × 512 × 100 × 4 B = 6.5 MB).
pub const DIRECTION_SETS: usize = 32;
/// Voxels projected per matrix product: large enough for sgemm to pay off, small enough to spread
/// over threads evenly.
const PROJECTION_BATCH: usize = 64;

/// How many times narrower than a direction's cone a T_ri ray's coarse voxels stay. The coarse
/// density darkens a wispy cloud a little (e^(−mean τ) < mean e^(−τ) over the cone); measured on
/// torus300 (σt 0.1) and cloud_large (σt 0.2) against the fine march, 1920×1080-class renders
/// under the studio map: margin 1 changes the image by 1.7–1.8 % relative RMSE (bias −0.6 %,
/// T_ri 2.0× faster), margin 2 by 0.6–0.7 % (bias −0.2 %, 1.5× faster).
const FAR_FIELD_MARGIN: f32 = 2.0;

/// The largest optical depth across one coarse voxel at the density's maximum. A coarse voxel
/// stands for the mean of what it covers, and e^(−mean τ) is darker than the mean of e^(−τ) by
/// about half the variance of τ across it: at a dense cloud's edge, a grazing ray either stays
/// out or is lost, and the mean loses it. Measured: the thick white furnace's surface voxels
/// (σt 1–2) went from −4.7 % to −6.3 % (cloud) and −8.5 % to −9.9 % (torus) with levels up to
/// 4–8 optical depths across; capped at one, a medium that thick marches at full resolution.
const FAR_FIELD_MAX_DEPTH: f32 = 1.0;

/// The largest optical depth one step of a footprint's chord may cross at the density's maximum.
/// A step's mean transmittance is exact for the density at its midpoint, so a thin medium can take
/// longer steps; where T falls within a step, where within it the density sits matters. Measured
/// on the torus fixture (studio, single scattering, 256×144): two-voxel steps left σt 0.092 as it
/// was (4.0 against 4.1 % off the path tracer) and cost 8 % less of the bake on torus300 at σt
/// 0.1, but at σt 1 moved the bias from −10.5 to −14.0 %.
const CHORD_STEP_DEPTH: f32 = 0.25;
/// The longest chord step, in voxels: past two, a step spans more than a density voxel's
/// neighbours, whose trilinear ramp it would sample once.
const CHORD_MAX_STEP: f32 = 2.0;

/// The chord step, in voxels, for `density` at `sigma_t` ([`CHORD_STEP_DEPTH`]).
pub fn chord_step(density: &SparseGrid, sigma_t: f32) -> f32 {
    let max = density.value_stats().map_or(0.0, |s| s.max.max(0.0));
    let voxel_depth = sigma_t * max * density.transform.voxel_size().min_element() as f32;
    match voxel_depth > 0.0 {
        true => (CHORD_STEP_DEPTH / voxel_depth).clamp(1.0, CHORD_MAX_STEP),
        false => CHORD_MAX_STEP,
    }
}

/// Fine steps a T_ri ray takes before it moves on to coarser density, and how many coarser levels
/// it uses, for `samples` directions through `density` at `sigma_t`.
///
/// Each direction stands for a cone of solid angle 4π/n, half-angle ≈ 2/√n, whose width 4t/√n
/// reaches a level-ℓ voxel (2^ℓ fine voxels) at t ≈ 2^ℓ·√n/4; level ℓ starts (2^ℓ − 1)·near
/// voxels out, so `near` = m·√n/4 keeps the coarse voxels m times narrower than the cone. Levels
/// go on until they reach across the density's box, or until a voxel could hold more than
/// [`FAR_FIELD_MAX_DEPTH`].
pub fn far_field(density: &SparseGrid, sigma_t: f32, samples: usize) -> (u32, usize) {
    let near = (FAR_FIELD_MARGIN * (samples as f32).sqrt() / 4.0).ceil() as u32;
    let diagonal = density
        .active_bbox()
        .map_or(0.0, |(lo, hi)| (hi - lo + 1).as_vec3().length());
    let reach = FarField::levels_for(diagonal, near);
    let max = density.value_stats().map_or(0.0, |s| s.max.max(0.0));
    let voxel_depth = sigma_t * max * density.transform.voxel_size().min_element() as f32;
    let thin = match voxel_depth > 0.0 {
        true => (FAR_FIELD_MAX_DEPTH / voxel_depth).log2().floor().max(0.0) as usize,
        false => reach,
    };
    (near, reach.min(thin))
}

/// One direction set and its quadrature-weighted basis matrix `weights[d·C + c] = Y_c(ω_d)·4π/N`.
struct DirectionSet {
    dirs: Vec<Vec3>,
    weights: Vec<f32>,
}

fn direction_sets(samples: usize, bands: usize, seed: u64) -> Vec<DirectionSet> {
    let base = crate::math::sphere::fibonacci(samples);
    let mut rng = rand_pcg::Pcg64Mcg::seed_from_u64(seed);
    let coeffs = bands * bands;
    let w = (4.0 * std::f64::consts::PI / samples as f64) as f32;
    (0..DIRECTION_SETS)
        .map(|_| {
            // A uniformly random rotation (Shoemake's method).
            let (u1, u2, u3): (f32, f32, f32) = (rng.random(), rng.random(), rng.random());
            let (a, b) = ((1.0 - u1).sqrt(), u1.sqrt());
            let t = std::f32::consts::TAU;
            let q = Quat::from_xyzw(
                a * (t * u2).sin(),
                a * (t * u2).cos(),
                b * (t * u3).sin(),
                b * (t * u3).cos(),
            )
            .normalize();
            let dirs: Vec<Vec3> = base.iter().map(|d| (q * *d).normalize()).collect();
            let mut weights = vec![0f32; samples * coeffs];
            for (d, row) in dirs.iter().zip(weights.chunks_exact_mut(coeffs)) {
                sh::eval_basis(d.as_dvec3().to_array(), bands, row);
                row.iter_mut().for_each(|v| *v *= w);
            }
            DirectionSet { dirs, weights }
        })
        .collect()
}

/// A hash of voxel `v` and the seed: per-voxel choices that differ between neighbours and agree
/// between reruns.
pub(crate) fn voxel_hash(v: IVec3, seed: u64) -> u64 {
    let mut bytes = [0u8; 20];
    bytes[..4].copy_from_slice(&v.x.to_le_bytes());
    bytes[4..8].copy_from_slice(&v.y.to_le_bytes());
    bytes[8..12].copy_from_slice(&v.z.to_le_bytes());
    bytes[12..].copy_from_slice(&seed.to_le_bytes());
    xxhash_rust::xxh3::xxh3_64(&bytes)
}

/// Which direction set voxel `v` uses.
fn set_of(v: IVec3, seed: u64) -> usize {
    (voxel_hash(v, seed) % DIRECTION_SETS as u64) as usize
}

/// Where a voxel's rays start.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Origins {
    /// At the node: T_ri(x_n, ω), the point value.
    Node,
    /// The footprint mean t̄_n: each direction's T_ri averaged, by ρ·w_n, along the footprint's
    /// chord in that direction through its own point of the density around the node
    /// ([`super::fit::spread_starts`]); the node's point value where its footprint is empty.
    Footprint,
}

/// Settings of the single-scattering pass.
#[derive(Debug, Clone, Copy)]
pub struct SingleSettings {
    pub bands: usize,
    pub samples: usize,
    pub seed: u64,
    pub origins: Origins,
    /// Voxels per step along a footprint's chord ([`chord_step`]).
    pub chord_step: f32,
}

/// T_ri for every transfer voxel of `layout`, `layout.len() × bands²`, through the optical depth
/// of `density` that `depth` integrates (built once for both passes of a bake: it holds the
/// density's bricks and occupancy); footprint means draw their starts by `visibility` when given
/// ([`super::fit::spread_starts`]).
pub fn bake_single(
    density: &SparseGrid,
    layout: &TransferLayout,
    depth: &OpticalDepth,
    settings: SingleSettings,
    visibility: Option<&Visibility>,
    progress: &indicatif::ProgressBar,
) -> Vec<f32> {
    let coeffs = settings.bands * settings.bands;
    let sets = direction_sets(settings.samples, settings.bands, settings.seed);
    let quadrature = super::fit::Quadrature::new(layout.k, Basis::Tent);
    let mut by_set: Vec<Vec<u32>> = vec![Vec::new(); DIRECTION_SETS];
    for (slot, v) in layout.voxels().iter().enumerate() {
        by_set[set_of(*v, settings.seed)].push(slot as u32);
    }
    let batches: Vec<(usize, &[u32])> = by_set
        .iter()
        .enumerate()
        .flat_map(|(s, slots)| slots.chunks(PROJECTION_BATCH).map(move |c| (s, c)))
        .collect();
    let n = settings.samples;
    // Each batch's result goes into T_ri as soon as it is projected (under a lock, a copy of a
    // few kilobytes), so the phase never holds a second copy of T_ri in batch results.
    let t_ri = std::sync::Mutex::new(vec![0f32; layout.len() * coeffs]);
    batches.par_iter().for_each(|&(s, slots)| {
        let set = &sets[s];
        let mut tr = vec![0f32; slots.len() * n];
        let mut visibility = visibility.map(Visibility::sampler);
        for (row, &slot) in tr.chunks_exact_mut(n).zip(slots) {
            let v = layout.voxels()[slot as usize];
            let x = layout.position(v);
            // Deep in a thick medium every ray from the node, or from anywhere in its footprint,
            // is cut off within a few voxels: it reads as a cut-off ray, at most the cutoff. A
            // footprint mean drawn by the visibility is not bounded by its rays, and is traced.
            let k = layout.k;
            // The footprint: the box K voxels around the node, which its means' chords cross.
            let footprint = (x - k as f32, x + k as f32);
            let dark = match settings.origins {
                Origins::Node => depth.all_cut_off((x, x)),
                Origins::Footprint => visibility.is_none() && depth.all_cut_off(footprint),
            };
            if dark {
                row.fill(MIN_TRANSMITTANCE);
                continue;
            }
            let starts = match settings.origins {
                Origins::Node => None,
                Origins::Footprint => super::fit::spread_starts(
                    density,
                    &quadrature,
                    v,
                    &set.dirs,
                    settings.seed,
                    visibility.as_mut(),
                ),
            };
            match starts {
                None => {
                    for (t, d) in row.iter_mut().zip(&set.dirs) {
                        *t = depth.transmittance(x, *d);
                    }
                }
                Some(starts) => {
                    for ((t, d), p) in row.iter_mut().zip(&set.dirs).zip(&starts.points) {
                        // g read at q itself, as ρ and w are. A start is drawn uniformly
                        // within its quadrature point's cell with that point's g; reading g
                        // there too brings the footprint means' DC closer to a plain run's (−0.3
                        // against −0.9 % on the torus at σt 1) but puts the images 1.5–3 points
                        // darker against the path tracer (studio, σt 0.36–1).
                        let tent = |q: Vec3| Basis::Tent.at(q - x, k);
                        let step = settings.chord_step;
                        let importance = visibility
                            .as_mut()
                            .map(|s| |q, rho| super::fit::importance(s, q, rho));
                        let mean = depth.chord_mean(*p, *d, footprint, step, tent, importance);
                        *t = mean.map_or_else(
                            || depth.transmittance(*p, *d),
                            |m| m * starts.mean_importance,
                        );
                    }
                }
            }
        }
        let mut out = vec![0f32; slots.len() * coeffs];
        // out (m×C) = tr (m×N) · weights (N×C), all row-major.
        // SAFETY: the pointers and strides describe the three buffers exactly.
        unsafe {
            matrixmultiply::sgemm(
                slots.len(),
                n,
                coeffs,
                1.0,
                tr.as_ptr(),
                n as isize,
                1,
                set.weights.as_ptr(),
                coeffs as isize,
                1,
                0.0,
                out.as_mut_ptr(),
                coeffs as isize,
                1,
            );
        }
        {
            let mut t_ri = t_ri.lock().unwrap_or_else(|e| e.into_inner());
            for (&slot, tc) in slots.iter().zip(out.chunks_exact(coeffs)) {
                let at = slot as usize * coeffs;
                t_ri[at..at + coeffs].copy_from_slice(tc);
            }
        }
        progress.inc(slots.len() as u64);
    });
    t_ri.into_inner().unwrap_or_else(|e| e.into_inner())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::DensityField;

    #[test]
    fn empty_space_projects_to_the_constant_one() {
        // Transfer voxels around an 8³ block, marched through an empty density: T_ri ≡ 1, so only
        // the DC term √(4π) survives the projection.
        let mut block = SparseGrid::new(Default::default(), 0.0);
        block.insert_tile(crate::volume::TileLevel::Block, IVec3::ZERO, 1.0);
        let layout = TransferLayout::build(&block, 6);
        let empty = DensityField::new(SparseGrid::new(Default::default(), 0.0));
        let settings = SingleSettings {
            bands: 4,
            samples: 512,
            seed: 1,
            origins: Origins::Node,
            chord_step: 1.0,
        };
        let t = bake_single(
            &empty.grid,
            &layout,
            &OpticalDepth::new(&empty, 1.0, true),
            settings,
            None,
            &indicatif::ProgressBar::hidden(),
        );
        let dc = (4.0 * std::f32::consts::PI).sqrt();
        for c in t.chunks_exact(16) {
            assert!((c[0] - dc).abs() < 1e-4);
            assert!(c[1..].iter().all(|x| x.abs() < 1e-2), "{c:?}");
        }
    }
}
