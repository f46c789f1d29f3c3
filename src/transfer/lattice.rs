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
//!   Q₁(x) = α·σt·(1/V)∫_cell ρ·T_ri dV — T_ri is the unscattered *fluence* transfer φ₀, the
//!   collision rate density is σt·ρ·φ₀, and a fraction α of it is scattered. The integral is
//!   gathered over the cell's octants by the single-scattering pass (`Single::gathered`): with a
//!   node-point sample instead, an optically thick cell's injection would depend on where the
//!   surface falls inside it (measured: ±30 % in a white furnace at 3 optical depths per link).
//!   Each later generation n+1 is fed by what generation n scattered.
//! * **Cells along a direction.** Along direction j, cell x is the segment
//!   [x − d_j·h/2, x + d_j·h/2] of length ℓ_j; its optical depth τ = τ_½(x, −j) + τ_½(x, j) is
//!   integrated through the fine density (links are attenuated by their own length and density,
//!   not a per-voxel constant). Scattered light is emitted isotropically and uniformly along the
//!   segment: w_j·Q(x) into direction j. Uniform emission is what keeps a uniform radiance field an
//!   exact equilibrium even when a cell is optically thick; emitting at the node would attenuate
//!   it by e^(−τ/2) first and break the white furnace by tens of percent.
//! * **Transport.** With P the flux entering cell x along j and E = w_j·Q(x):
//!   - leaving: P·e^(−τ) + E·ε, with ε = (1 − e^(−τ))/τ the escaping share of uniform emission;
//!     it enters the **next active cell along d_j** — links jump across empty space, where light
//!     travels unchanged; only when no active cell lies ahead does it leave the system;
//!   - collided in the cell: P·(1 − e^(−τ)) + E·(1 − ε); the fraction α of it is scattered and
//!     feeds the cell's emission in the next generation.
//! * **Self-scattering, summed.** Of a cell's own emission the share s = Σ_j w_j·(1 − ε_j)
//!   collides in the cell itself, and α·s of that is emitted again: a geometric series summed in
//!   closed form by emitting Q/(1 − α·s) and not feeding those self-collisions back. Thick cells
//!   would otherwise need thousands of generations to pass light on.
//! * **Fluence readout** (track-length estimator, weighted by link length). Per unit flux, the
//!   track length inside the cell is ℓ·ε for entering flux and (ℓ/τ)·(1 − ε) for uniform emission
//!   (→ ℓ and ℓ/2 as τ → 0); collisions are σ̄ = τ/ℓ times the track, consistently. Lattice lines
//!   along d_j carry one node per ℓ_j, so each line's cross-section is V/ℓ_j and flux·track/V is
//!   fluence: F_ms(x) = Σ over generations and directions of flux × track. An isotropic radiance
//!   c gives fluxes that read back 4πc·Σw_j = 4πc.
//!
//! A generation is computed by sweeping each direction once over the nodes in the order of
//! x·d_j, so flux crosses the whole volume in one sweep (Gauss–Seidel in the direction of flight).
//! Generations go on until the estimated **remaining** energy — the geometric tail Δₙ·r/(1−r) of
//! the per-generation increments Δₙ of the DC fluence, r = Δₙ/Δₙ₋₁ — is below
//! [`CONVERGENCE`] of the total.

use glam::{IVec3, Vec3};
use rayon::prelude::*;

use super::grid::TransferLayout;
use super::Medium;
use crate::volume::sampler::BlockSampler;
use crate::volume::SparseGrid;

/// Stop when the estimated energy still to come is below this fraction of the total (issue 4).
pub const CONVERGENCE: f64 = 1e-4;
/// A hard cap on generations, reached only by pathological inputs (albedo 1 in an enormous volume).
pub const MAX_GENERATIONS: usize = 5000;
/// Coefficients transported together: 8 f32 fill a SIMD-friendly run, and the per-chunk buffers
/// (3 × nodes × 8 floats) keep peak memory bounded whatever the band count.
const CHUNK: usize = 8;
const NO_LINK: u32 = u32::MAX;
/// Longest segment marched, in sub-steps: a corner link at K = 64 is 64·√3 / 0.5 ≈ 222 steps.
const MAX_SEGMENT_STEPS: usize = 256;
/// Cap on α·s, the share of a cell's emission it scatters again itself: s < 1 always, but at
/// α = 1 in an extremely thick cell 1/(1 − α·s) would lose all precision.
const MAX_SELF_GAIN: f64 = 0.999_999;

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

/// Per cell and direction (index x·D + j): where the link lands and how the cell's segment along
/// d_j transmits, emits and accumulates fluence.
struct Links {
    dirs: Directions,
    /// Slot of the next active cell along d_j, or `NO_LINK`.
    target: Vec<u32>,
    /// e^(−τ) of the whole segment.
    trans: Vec<f32>,
    /// ε = (1 − e^(−τ))/τ: the share of uniform emission that leaves the segment.
    escape: Vec<f32>,
    /// Track length per unit entering flux, ℓ·ε (world units).
    track_in: Vec<f32>,
    /// Track length per unit emitted flux, (ℓ/τ)·(1 − ε).
    track_emit: Vec<f32>,
    /// 1/(1 − α·s): the cell's own emission, with its self-scattering summed.
    boost: Vec<f32>,
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
    let scale = density.transform.scale.as_vec3();
    let (lo, hi) = layout
        .voxels()
        .iter()
        .fold((IVec3::MAX, IVec3::MIN), |(a, b), v| (a.min(*v), b.max(*v)));
    let mut links = Links {
        target: vec![NO_LINK; n * d],
        trans: vec![0.0; n * d],
        escape: vec![0.0; n * d],
        track_in: vec![0.0; n * d],
        track_emit: vec![0.0; n * d],
        boost: vec![1.0; n],
        order: Vec::with_capacity(d),
        dirs,
    };
    let dirs = &links.dirs;
    links
        .target
        .par_chunks_mut(d)
        .zip(links.trans.par_chunks_mut(d))
        .zip(links.escape.par_chunks_mut(d))
        .zip(links.track_in.par_chunks_mut(d))
        .zip(links.track_emit.par_chunks_mut(d))
        .zip(links.boost.par_iter_mut())
        .zip(layout.voxels().par_iter())
        .for_each(
            |((((((target, trans), escape), track_in), track_emit), boost), &v)| {
                let mut acc = BlockSampler::new(density);
                let mut self_share = 0.0f64;
                for (j, off) in dirs.offsets.iter().enumerate() {
                    let mut step = v + *off;
                    while step.cmpge(lo).all() && step.cmple(hi).all() {
                        if let Some(s) = layout.slot(step) {
                            target[j] = s as u32;
                            break;
                        }
                        step += *off;
                    }
                    let half = off.as_vec3() * (k as f32 / 2.0);
                    let x = layout.position(v);
                    let length = (2.0 * half * scale).length();
                    let seg = segment(&mut acc, x - half, x + half, length, medium.sigma_t);
                    trans[j] = seg.trans;
                    escape[j] = seg.escape;
                    track_in[j] = seg.track_in;
                    track_emit[j] = seg.track_emit;
                    self_share += dirs.weights[j] as f64 * (1.0 - seg.escape) as f64;
                }
                let loop_gain = (medium.albedo as f64 * self_share).min(MAX_SELF_GAIN);
                *boost = (1.0 / (1.0 - loop_gain)) as f32;
            },
        );
    for off in &links.dirs.offsets {
        let mut order: Vec<u32> = (0..n as u32).collect();
        // Links always increase x·d_j, so ascending order sees every arrival before it leaves.
        order.sort_by_key(|&s| (layout.voxels()[s as usize].dot(*off), s));
        links.order.push(order);
    }
    links
}

/// How one cell's segment along a direction transmits light, found by marching it.
struct Segment {
    trans: f32,
    escape: f32,
    track_in: f32,
    track_emit: f32,
}

/// Sub-step of a segment march, in voxels: segments are short (K/2 to K·√3 voxels) and marched
/// once per link, so two samples per voxel cost little and resolve a cell's density profile.
const SEGMENT_STEP_VOXELS: f32 = 0.5;

/// Marches the segment from index point `a` to `b` (world length `length`). Emission is spread
/// along it in proportion to the density, as collisions are; ε and the emitted track are the
/// density-weighted means of what escapes and how far it travels inside.
fn segment(acc: &mut BlockSampler, a: Vec3, b: Vec3, length: f32, sigma_t: f32) -> Segment {
    let steps = (((b - a).length() / SEGMENT_STEP_VOXELS).ceil() as usize).max(1);
    let dl = length / steps as f32;
    let mut rho = [0f32; MAX_SEGMENT_STEPS];
    let steps = steps.min(MAX_SEGMENT_STEPS);
    for (i, r) in rho.iter_mut().enumerate().take(steps) {
        *r = acc
            .sample(a + (b - a) * ((i as f32 + 0.5) / steps as f32))
            .max(0.0);
    }
    let mut taus = [0f32; MAX_SEGMENT_STEPS];
    for (t, r) in taus.iter_mut().zip(&rho).take(steps) {
        *t = sigma_t * r * dl;
    }
    let (rho, taus) = (&rho[..steps], &taus[..steps]);
    // Entering flux: transmittance and the track it spends inside.
    let (mut tau, mut track_in) = (0.0f32, 0.0f32);
    for t in taus {
        track_in += dl * (-(tau + 0.5 * t)).exp();
        tau += t;
    }
    // Emission at sub-step i, weighted by ρ_i: share escaping past the end, track until then.
    let (mut weight, mut escape, mut track_emit) = (0.0f32, 0.0f32, 0.0f32);
    for (i, (&r, &t)) in rho.iter().zip(taus).enumerate() {
        if r <= 0.0 {
            continue;
        }
        let mut depth = 0.5 * t;
        let mut track = 0.5 * dl * (-0.25 * t).exp();
        for &later in &taus[i + 1..] {
            track += dl * (-(depth + 0.5 * later)).exp();
            depth += later;
        }
        weight += r;
        escape += r * (-depth).exp();
        track_emit += r * track;
    }
    let (escape, track_emit) = if weight > 0.0 {
        (escape / weight, track_emit / weight)
    } else {
        // Nothing is emitted in an empty segment; these values are never used with Q > 0.
        (1.0, 0.5 * length)
    };
    Segment {
        trans: (-tau).exp(),
        escape,
        track_in,
        track_emit,
    }
}

/// Runs the generations for coefficients `[c0, c0 + width)`; stops by the energy criterion when
/// `generations` is `None` (the chunk holding the DC term), else runs exactly that many.
fn transport_chunk(
    links: &Links,
    first: &Source,
    c0: usize,
    width: usize,
    generations: Option<usize>,
) -> (Vec<f32>, LatticeStats) {
    let (coeffs, albedo) = (first.coeffs, first.medium.albedo);
    let n = links.order[0].len();
    let d = links.dirs.len();
    let mut fluence = vec![0f32; n * width];
    let mut emit = vec![0f32; n * width];
    let mut next = vec![0f32; n * width];
    let mut incoming = vec![0f32; n * width];
    let scatter = first.medium.albedo * first.medium.sigma_t;
    for x in 0..n {
        for c in 0..width {
            emit[x * width + c] = scatter * first.gathered[x * coeffs + c0 + c];
        }
    }
    let mut stats = LatticeStats {
        energy_single: (0..n).map(|x| first.t_ri[x * coeffs] as f64).sum(),
        ..Default::default()
    };
    let mut previous = 0.0f64;
    let limit = generations.unwrap_or(MAX_GENERATIONS);
    for generation in 1..=limit {
        next.iter_mut().for_each(|v| *v = 0.0);
        let mut added = 0.0f64;
        for j in 0..d {
            incoming.iter_mut().for_each(|v| *v = 0.0);
            let w = links.dirs.weights[j];
            for &x in &links.order[j] {
                let x = x as usize;
                let i = x * d + j;
                let (trans, escape) = (links.trans[i], links.escape[i]);
                let (track_in, track_emit) = (links.track_in[i], links.track_emit[i]);
                let emitted = w * links.boost[x];
                let r = x * width;
                let mut out = [0f32; CHUNK];
                for c in 0..width {
                    let p = incoming[r + c];
                    let e = emitted * emit[r + c];
                    let contribution = p * track_in + e * track_emit;
                    fluence[r + c] += contribution;
                    // Only entering flux feeds the next generation: the cell's own emission
                    // re-collides inside the boost already.
                    next[r + c] += albedo * p * (1.0 - trans);
                    out[c] = p * trans + e * escape;
                    if c0 + c == 0 {
                        added += contribution as f64;
                    }
                }
                let target = links.target[i];
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

/// What feeds the lattice: the single-scattering results and the medium.
pub struct Source<'a> {
    pub t_ri: &'a [f32],
    pub gathered: &'a [f32],
    pub coeffs: usize,
    pub medium: Medium,
}

/// F_ms for every transfer voxel: `layout.len() × coeffs`.
pub fn bake_multiple(
    density: &SparseGrid,
    layout: &TransferLayout,
    kind: LatticeKind,
    first: &Source,
) -> (Vec<f32>, LatticeStats) {
    let (medium, coeffs) = (first.medium, first.coeffs);
    let dirs = Directions::new(kind);
    let links = build_links(density, layout, medium, dirs);
    let n = layout.len();
    let chunks: Vec<(usize, usize)> = (0..coeffs)
        .step_by(CHUNK)
        .map(|c0| (c0, CHUNK.min(coeffs - c0)))
        .collect();
    // The chunk holding the DC term decides the generation count by energy; the operator is the
    // same for every coefficient, so the other chunks run exactly as many generations.
    let (head, stats) = transport_chunk(&links, first, 0, chunks[0].1, None);
    let rest: Vec<Vec<f32>> = chunks[1..]
        .par_iter()
        .map(|&(c0, w)| transport_chunk(&links, first, c0, w, Some(stats.generations)).0)
        .collect();
    let mut f_ms = vec![0f32; n * coeffs];
    for (&(c0, w), part) in chunks.iter().zip(std::iter::once(&head).chain(&rest)) {
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
