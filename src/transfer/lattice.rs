//! Multiple scattering on the lattice (thesis 4.2): light scattered once or more, transported
//! between transfer voxels along a discrete set of directions over a sparse neighbour map.
//!
//! # The discrete equations
//!
//! Nodes are the transfer voxels x (spacing h = K·voxel size), each owning a cell of volume V = h³.
//! Directions are the D lattice offsets d_j (6 faces, 12 edges, 8 corners), link length
//! ℓ_j = h·|d_j|, with weights w_j = the share of the sphere closest to d_j (Σ w_j = 1, so the
//! isotropic redistribution below conserves energy exactly on the discrete set).
//!
//! Every quantity is an SH vector (the transfer is linear in the environment, so one scalar
//! transport serves all `bands²` right-hand sides) and every power is per cell volume V.
//!
//! * **Sources.** The first scattered generation is emitted where unscattered light collides:
//!   Q₁(x) = α·σt·ρ̄(x)·T_ri(x), with ρ̄ the mean density of the cell's footprint. (T_ri is the
//!   unscattered *fluence* transfer φ₀; the collision rate density is σt·φ₀, a fraction α of it
//!   is scattered.) Each later generation n+1 is fed by what generation n scattered.
//! * **Emission.** A cell emits Q(x) isotropically: w_j·Q(x) into direction j, starting at the node.
//! * **Transport.** Flux travelling along j crosses a cell as two half-links: in through
//!   [x − d_j·h/2, x], out through [x, x + d_j·h/2], with optical depths τ⁻ = τ_½(x, −j) and
//!   τ⁺ = τ_½(x, j) integrated through the fine density (links are attenuated by their own
//!   length and density, not a per-voxel constant). With P the flux arriving at x along j:
//!   - after the in-half:  a = P·e^(−τ⁻), collided P·(1 − e^(−τ⁻));
//!   - the out-half carries b = a + w_j·Q(x): collided b·(1 − e^(−τ⁺)), and b·e^(−τ⁺) arrives at
//!     the **next active node along d_j** — links jump across empty space, where light travels
//!     unchanged; only when no active node lies ahead does it leave the system.
//!   - of everything collided in cell x, the fraction α is scattered: it is next generation's Q(x).
//! * **Fluence readout** (track-length estimator, weighted by link length). A flux P crossing a
//!   half-link of length ℓ/2 with depth τ spends a track length of (ℓ/2)·(1 − e^(−τ))/τ per unit
//!   flux in the cell; for lattice lines in direction d_j one node per ℓ_j, the cross-section per
//!   line is V/ℓ_j, so flux·track/V is fluence. F_ms(x) = Σ over generations, directions and both
//!   half-links of flux × track. An isotropic radiance c gives fluxes that read back 4πc·Σw_j = 4πc.
//!
//! A generation is computed by sweeping each direction once over the nodes in the order of
//! x·d_j, so flux crosses the whole volume in one sweep (Gauss–Seidel in the direction of flight).
//! Generations go on until the estimated **remaining** energy — the geometric tail Δₙ·r/(1−r) of
//! the per-generation increments Δₙ of the DC fluence, r = Δₙ/Δₙ₋₁ — is below
//! [`CONVERGENCE`] of the total.

use glam::IVec3;
use rayon::prelude::*;

use super::grid::TransferLayout;
use super::Medium;
use crate::volume::transmittance::OpticalDepth;
use crate::volume::SparseGrid;

/// Stop when the estimated energy still to come is below this fraction of the total (issue 4).
pub const CONVERGENCE: f64 = 1e-4;
/// A hard cap on generations, reached only by pathological inputs (albedo 1 in an enormous volume).
pub const MAX_GENERATIONS: usize = 5000;
/// Coefficients transported together: 8 f32 fill a SIMD-friendly run, and the per-chunk buffers
/// (3 × nodes × 8 floats) keep peak memory bounded whatever the band count.
const CHUNK: usize = 8;
const NO_LINK: u32 = u32::MAX;

/// Voronoi shares of the sphere of the lattice directions, by class (face, edge, corner), measured
/// by a 4000 × 8000 (cos θ, φ) quadrature; `lattice_weights_are_voronoi_shares` re-derives them.
const WEIGHTS_6: [f64; 3] = [1.0 / 6.0, 0.0, 0.0];
const WEIGHTS_18: [f64; 3] = [0.046_782_333, 0.059_942_167, 0.0];
const WEIGHTS_26: [f64; 3] = [0.045_776_417, 0.036_981_958, 0.035_194_750];

/// Which neighbour directions the lattice links: faces, faces + edges, or all 26.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LatticeKind {
    #[value(name = "6")]
    Faces,
    #[value(name = "18")]
    FacesEdges,
    #[value(name = "26")]
    All,
}

impl LatticeKind {
    pub fn directions(self) -> usize {
        match self {
            LatticeKind::Faces => 6,
            LatticeKind::FacesEdges => 18,
            LatticeKind::All => 26,
        }
    }
}

/// The lattice's discrete directions and their weights.
#[derive(Debug, Clone)]
pub struct Directions {
    pub offsets: Vec<IVec3>,
    pub weights: Vec<f32>,
    /// Index of −d_j.
    pub opposite: Vec<usize>,
}

impl Directions {
    /// The 6, 18 or 26 neighbour directions.
    pub fn new(kind: LatticeKind) -> Directions {
        let (classes, table) = match kind {
            LatticeKind::Faces => (1, WEIGHTS_6),
            LatticeKind::FacesEdges => (2, WEIGHTS_18),
            LatticeKind::All => (3, WEIGHTS_26),
        };
        let mut offsets = Vec::new();
        for x in -1..=1 {
            for y in -1..=1 {
                for z in -1..=1 {
                    let d = IVec3::new(x, y, z);
                    let class = d.abs().element_sum();
                    if class >= 1 && class <= classes {
                        offsets.push(d);
                    }
                }
            }
        }
        // Renormalise the rounded constants so the weights sum to 1 exactly in f64.
        let raw: Vec<f64> = offsets
            .iter()
            .map(|d| table[d.abs().element_sum() as usize - 1])
            .collect();
        let total: f64 = raw.iter().sum();
        let weights = raw.iter().map(|w| (w / total) as f32).collect();
        let opposite = offsets
            .iter()
            .map(|d| offsets.iter().position(|e| *e == -*d).unwrap_or(0))
            .collect();
        Directions {
            offsets,
            weights,
            opposite,
        }
    }

    pub fn len(&self) -> usize {
        self.offsets.len()
    }

    pub fn is_empty(&self) -> bool {
        self.offsets.is_empty()
    }
}

/// Per node and direction: where the link lands, and the half-link's transmittance and track.
struct Links {
    dirs: Directions,
    /// `target[x·D + j]`: slot of the next active node along d_j, or `NO_LINK`.
    target: Vec<u32>,
    /// e^(−τ_½(x, j)).
    trans: Vec<f32>,
    /// Track length per unit flux over the half-link, (ℓ_j/2)·(1 − e^(−τ))/τ, in world units.
    track: Vec<f32>,
    /// α·σt·ρ̄(x): turns unscattered fluence into first-generation emission.
    source: Vec<f32>,
    /// Node order of the sweep for each direction (ascending x·d_j).
    order: Vec<Vec<u32>>,
}

/// What the lattice did, for `--stats`.
#[derive(Debug, Clone, Copy, Default)]
pub struct LatticeStats {
    pub generations: usize,
    /// Σ over nodes of the DC coefficient of T_ri and of F_ms.
    pub energy_single: f64,
    pub energy_multiple: f64,
    /// The estimated energy not yet added when iteration stopped, relative to the total.
    pub remaining: f64,
    pub converged: bool,
}

fn build_links(
    density: &SparseGrid,
    layout: &TransferLayout,
    medium: Medium,
    dirs: Directions,
) -> Links {
    let n = layout.len();
    let d = dirs.len();
    let k = layout.k;
    let depth = OpticalDepth::new(density, medium.sigma_t, true);
    let scale = density.transform.scale.as_vec3();
    let (lo, hi) = layout
        .voxels()
        .iter()
        .fold((IVec3::MAX, IVec3::MIN), |(a, b), v| (a.min(*v), b.max(*v)));
    let mut links = Links {
        target: vec![NO_LINK; n * d],
        trans: vec![1.0; n * d],
        track: vec![0.0; n * d],
        source: vec![0.0; n],
        order: Vec::with_capacity(d),
        dirs,
    };
    let dirs = &links.dirs;
    links
        .target
        .par_chunks_mut(d)
        .zip(links.trans.par_chunks_mut(d))
        .zip(links.track.par_chunks_mut(d))
        .zip(links.source.par_iter_mut())
        .zip(layout.voxels().par_iter())
        .for_each(|((((target, trans), track), source), &v)| {
            let x = layout.position(v);
            for (j, off) in dirs.offsets.iter().enumerate() {
                let mut step = v + *off;
                while step.cmpge(lo).all() && step.cmple(hi).all() {
                    if let Some(s) = layout.slot(step) {
                        target[j] = s as u32;
                        break;
                    }
                    step += *off;
                }
                let world = (off.as_vec3() * k as f32) * scale;
                let half = 0.5 * world.length();
                let tau = depth.optical_depth(x, world.normalize(), half);
                trans[j] = (-tau).exp();
                // (1 − e^(−τ))/τ → 1 as τ → 0: −expm1(−τ)/τ keeps full precision there.
                track[j] = if tau > 1e-6 {
                    half * (-(-tau).exp_m1() / tau)
                } else {
                    half * (1.0 - 0.5 * tau)
                };
            }
            *source = medium.albedo * medium.sigma_t * cell_mean(density, v, k);
        });
    for off in &links.dirs.offsets {
        let mut order: Vec<u32> = (0..n as u32).collect();
        // Links always increase x·d_j, so ascending order sees every arrival before it leaves.
        order.sort_by_key(|&s| (layout.voxels()[s as usize].dot(*off), s));
        links.order.push(order);
    }
    links
}

/// Mean density over the footprint of transfer voxel `v`: the K³ density voxels nearest to it.
fn cell_mean(density: &SparseGrid, v: IVec3, k: i32) -> f32 {
    let lo = v * k - IVec3::splat(k / 2);
    let mut sum = 0.0f64;
    for x in 0..k {
        for y in 0..k {
            for z in 0..k {
                sum += density.value(lo + IVec3::new(x, y, z)).max(0.0) as f64;
            }
        }
    }
    (sum / (k * k * k) as f64) as f32
}

/// Runs the generations for coefficients `[c0, c0 + width)`; stops by the energy criterion when
/// `generations` is `None` (the chunk holding the DC term), else runs exactly that many.
fn transport_chunk(
    links: &Links,
    t_ri: &[f32],
    coeffs: usize,
    c0: usize,
    width: usize,
    albedo: f32,
    generations: Option<usize>,
) -> (Vec<f32>, LatticeStats) {
    let n = links.source.len();
    let d = links.dirs.len();
    let mut fluence = vec![0f32; n * width];
    let mut emit = vec![0f32; n * width];
    let mut next = vec![0f32; n * width];
    let mut incoming = vec![0f32; n * width];
    for x in 0..n {
        for c in 0..width {
            emit[x * width + c] = links.source[x] * t_ri[x * coeffs + c0 + c];
        }
    }
    let mut stats = LatticeStats {
        energy_single: (0..n).map(|x| t_ri[x * coeffs] as f64).sum(),
        ..Default::default()
    };
    let mut previous = 0.0f64;
    let limit = generations.unwrap_or(MAX_GENERATIONS);
    for generation in 1..=limit {
        next.iter_mut().for_each(|v| *v = 0.0);
        let mut added = 0.0f64;
        for j in 0..d {
            incoming.iter_mut().for_each(|v| *v = 0.0);
            let (w, back) = (links.dirs.weights[j], links.dirs.opposite[j]);
            for &x in &links.order[j] {
                let x = x as usize;
                let (ein, gin) = (links.trans[x * d + back], links.track[x * d + back]);
                let (eout, gout) = (links.trans[x * d + j], links.track[x * d + j]);
                let target = links.target[x * d + j];
                let r = x * width;
                let mut out = [0f32; CHUNK];
                for c in 0..width {
                    let p = incoming[r + c];
                    let b = p * ein + w * emit[r + c];
                    let contribution = p * gin + b * gout;
                    fluence[r + c] += contribution;
                    next[r + c] += albedo * (p * (1.0 - ein) + b * (1.0 - eout));
                    out[c] = b * eout;
                    if c0 + c == 0 {
                        added += contribution as f64;
                    }
                }
                if target != NO_LINK {
                    let t = target as usize * width;
                    for c in 0..width {
                        incoming[t + c] += out[c];
                    }
                }
            }
        }
        std::mem::swap(&mut emit, &mut next);
        stats.generations = generation;
        if generations.is_none() {
            stats.energy_multiple += added;
            let total = stats.energy_single + stats.energy_multiple;
            let r = if previous > 0.0 {
                added / previous
            } else {
                0.0
            };
            stats.remaining = if r < 1.0 {
                added * r / (1.0 - r) / total.max(f64::MIN_POSITIVE)
            } else {
                f64::INFINITY
            };
            previous = added;
            if generation >= 2 && stats.remaining < CONVERGENCE || added == 0.0 {
                stats.converged = true;
                break;
            }
        }
    }
    (fluence, stats)
}

/// F_ms for every transfer voxel: `layout.len() × coeffs`, from `t_ri` of the same shape.
pub fn bake_multiple(
    density: &SparseGrid,
    layout: &TransferLayout,
    medium: Medium,
    kind: LatticeKind,
    t_ri: &[f32],
    coeffs: usize,
) -> (Vec<f32>, LatticeStats) {
    let dirs = Directions::new(kind);
    let links = build_links(density, layout, medium, dirs);
    let n = layout.len();
    let chunks: Vec<(usize, usize)> = (0..coeffs)
        .step_by(CHUNK)
        .map(|c0| (c0, CHUNK.min(coeffs - c0)))
        .collect();
    // The chunk holding the DC term decides the generation count by energy; the operator is the
    // same for every coefficient, so the other chunks run exactly as many generations.
    let (first, stats) = transport_chunk(&links, t_ri, coeffs, 0, chunks[0].1, medium.albedo, None);
    let rest: Vec<Vec<f32>> = chunks[1..]
        .par_iter()
        .map(|&(c0, w)| {
            transport_chunk(
                &links,
                t_ri,
                coeffs,
                c0,
                w,
                medium.albedo,
                Some(stats.generations),
            )
            .0
        })
        .collect();
    let mut f_ms = vec![0f32; n * coeffs];
    for (&(c0, w), part) in chunks.iter().zip(std::iter::once(&first).chain(&rest)) {
        for x in 0..n {
            f_ms[x * coeffs + c0..x * coeffs + c0 + w].copy_from_slice(&part[x * w..(x + 1) * w]);
        }
    }
    (f_ms, stats)
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    fn unit(d: IVec3) -> Vec3 {
        d.as_vec3().normalize()
    }

    #[test]
    fn lattice_weights_are_voronoi_shares() {
        // Re-derive the shares by a (cos θ, φ) midpoint quadrature, nearest direction wins.
        for kind in [
            LatticeKind::Faces,
            LatticeKind::FacesEdges,
            LatticeKind::All,
        ] {
            let dirs = Directions::new(kind);
            let count = kind.directions();
            let units: Vec<Vec3> = dirs.offsets.iter().map(|d| unit(*d)).collect();
            let (nu, nphi) = (600, 1200);
            let mut share = vec![0f64; count];
            for i in 0..nu {
                let z = -1.0 + (i as f32 + 0.5) * 2.0 / nu as f32;
                let r = (1.0 - z * z).sqrt();
                for k in 0..nphi {
                    let p = (k as f32 + 0.5) * std::f32::consts::TAU / nphi as f32;
                    let w = Vec3::new(r * p.cos(), r * p.sin(), z);
                    let best = (0..count)
                        .max_by(|&a, &b| units[a].dot(w).total_cmp(&units[b].dot(w)))
                        .unwrap();
                    share[best] += 1.0 / (nu * nphi) as f64;
                }
            }
            for (s, w) in share.iter().zip(&dirs.weights) {
                assert!((s - *w as f64).abs() < 2e-4, "{count}: {s} vs {w}");
            }
            let sum: f64 = dirs.weights.iter().map(|w| *w as f64).sum();
            assert!((sum - 1.0).abs() < 1e-6);
        }
    }

    #[test]
    fn half_range_moment_is_near_a_quarter() {
        // Σ_{d·n>0} w·(d·n) is ¼ for the true sphere: how well a flat surface's in- and out-flow
        // are represented (DESIGN.md). 26 directions: 0.2317; 6 directions: 1/6.
        let moment = |kind| {
            let dirs = Directions::new(kind);
            dirs.offsets
                .iter()
                .zip(&dirs.weights)
                .map(|(d, w)| w * unit(*d).z.max(0.0))
                .sum::<f32>()
        };
        assert!((moment(LatticeKind::All) - 0.2317).abs() < 1e-3);
        assert!((moment(LatticeKind::FacesEdges) - 0.2163).abs() < 1e-3);
        assert!((moment(LatticeKind::Faces) - 1.0 / 6.0).abs() < 1e-6);
    }

    #[test]
    fn opposite_directions_pair_up() {
        let dirs = Directions::new(LatticeKind::All);
        for (j, d) in dirs.offsets.iter().enumerate() {
            assert_eq!(dirs.offsets[dirs.opposite[j]], -*d);
        }
    }
}
