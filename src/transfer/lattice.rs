//! Multiple scattering on the lattice (thesis 4.2): light scattered once or more, transported
//! between transfer voxels along a discrete set of directions over a sparse neighbour map.
//!
//! # The discrete equations
//!
//! Nodes are the transfer voxels x (spacing h = K·voxel size), each owning a cell of volume V = h³.
//! Directions are the D lattice offsets d_j (6 faces, 12 edges, 8 corners; the suns' set: 6 faces
//! and 24 offsets like (2, 2, 1)), link length ℓ_j = h·|d_j|, with weights w_j = the share of the
//! sphere closest to d_j (Σ w_j = 1, so the isotropic redistribution below conserves energy
//! exactly on the discrete set).
//!
//! Every quantity is an SH vector (the transfer is linear in the environment, so one scalar
//! transport serves every right-hand side) and every power is per cell volume V. Only the first
//! [`LATTICE_BANDS`] bands are transported: a few beams per node carry no finer angular detail.
//!
//! * **Cells along a direction.** Along direction j, cell x is the segment
//!   [x − d_j·h/2, x + d_j·h/2] of length ℓ_j; its optical depth τ_j is integrated through the
//!   fine density in sub-steps, an even number of them so the node lies between two (links are
//!   attenuated by their own length and density, not a per-voxel constant), and every
//!   transmittance and escape below is exact for that piecewise-constant profile — a midpoint
//!   rule is 4 % off at one optical depth per sub-step, which breaks the equilibrium below by
//!   about as much.
//! * **Emission shares.** A cell scatters Q(x) isotropically, but along j it is represented by
//!   its one line through the node, so beam j emits the share e_j = w_j·σ̄_j / Σ_k w_k·σ̄_k of Q,
//!   σ̄_j = τ_j/ℓ_j, spread along the segment in proportion to the density (emission where the
//!   collisions are). A beam emits in proportion to what it absorbs (reciprocity): in a uniform
//!   cell e_j = w_j; in a surface cell whose face line is empty but whose corner line is full, the
//!   empty line emits nothing, as it absorbs nothing. Σ e_j = 1, so energy is exact.
//! * **Transport.** With P the flux entering cell x along j and E = e_j·Q(x):
//!   - leaving: P·e^(−τ) + E·ε, ε the escaping share of the emission (for uniform density
//!     (1 − e^(−τ))/τ); it enters the **next active cell along d_j** — links jump across empty
//!     space, where light travels unchanged; only when no active cell lies ahead does it leave;
//!   - collided in the cell: P·(1 − e^(−τ)) + E·(1 − ε); the fraction α of it is scattered and
//!     feeds the cell's emission in the next generation.
//!
//!   A uniform radiance field is an exact equilibrium of every cell, however thick or partly
//!   filled: with P_j ∝ w_j/ℓ_j (below) and Q = Σ_k P_k·τ_k (the emission after the
//!   self-scattering gain below), E·ε = P·(1 − e^(−τ)) on every line. With the plain weights w_j
//!   as shares it was not: driven from the boundary, the cloud's interior came out 16 % / 25 %
//!   low on average at σt 1 / 2.
//! * **Thick cells reflect at their faces.** A cell whose line j is optically thick,
//!   t_j = σ̄_j·h > t₀ ([`LatticeKind::reflect_depth`]: 0.75 on the 26 directions, 1 on the
//!   others), sends the share λ_j = (√(t_j/t₀) − 1)/(√(t_j/t₀) + 1) of
//!   the flux entering that line straight back along −d_j (times α, as a scattering: it leaves
//!   when −d_j is next swept), and only 1 − λ_j enters, collides and feeds the emission, whose
//!   shares become e_j ∝ (1 − λ_j)·w_j·σ̄_j. Without it, a cell many optical depths thick still
//!   spreads whatever enters it uniformly over its volume and re-emits it isotropically, so two
//!   such cells exchange light as opaque emitters, πΔc per unit area, where a resolved medium
//!   carries the diffusion flux (4π/3)·Δc/t: clouds at the default density came out flat, too
//!   dark on the lit side and too bright behind (a 30-voxel slab at σt 1: 2.1× the transmitted
//!   light). Between two reflecting cells the net exchange is scaled by (1 − λ)/(1 + λ) =
//!   √(t₀/t), which matched exact slab solutions from 1.8 to 12 optical depths per cell to about
//!   10 % at t₀ = 1, and the 6-optical-depth slab of
//!   `a_thick_slab_conducts_light_as_diffusion_does` to 0.2 % on the 26 directions at t₀ = 0.75
//!   (6.4 % at 1). A uniform field stays an exact
//!   equilibrium (what a line reflects, its opposite line sends back), energy is conserved at
//!   α = 1, and the node reads the entering light times 1/(1 − λ_j), so a uniform field still
//!   reads back exactly. Below t₀ optical depths per cell edge nothing changes.
//! * **Self-scattering, summed.** Of a cell's own emission the share s = Σ_j e_j·(1 − ε_j)
//!   collides in the cell itself, and α·s of that is emitted again: a geometric series summed in
//!   closed form by emitting Q/(1 − α·s) and not feeding those self-collisions back. Thick cells
//!   would otherwise need thousands of generations to pass light on.
//! * **Source: the environment, at the boundary.** Generation 0 is the unscattered light itself,
//!   entering the lattice from outside. Light travelling along +d_j comes from ω = −d_j, and line j
//!   stands for the directions Ω_j of the Voronoi cell of −d_j (solid angle 4π·w_j). So for SH
//!   coefficient i, the flux entering each line at its first active cell — one with no active
//!   cell upstream along −d_j; behind a gap, the light comes across the gap instead — is
//!   P_ij = (1/ℓ_j)·∫_{Ω_j} y_i dω = 4π·w_j·ȳ_ij/ℓ_j, ȳ_ij the mean of y_i over Ω_j (by
//!   quadrature), times a gain per band g_ℓ that gives the beams each band's power: a mean over
//!   Ω_j blurs band ℓ, so that Σ_j w_j·|ȳ_ℓj|² falls short of its power over the sphere,
//!   (2ℓ + 1)/4π, and g_ℓ restores it (1.04, 1.14 and 1.30 for bands 1–3 on 26 directions; the
//!   DC term is exact). Generation 0 is swept like the others, without emission, and α times its
//!   collisions feed generation 1. Its unscattered light is **not** read out: the renderer's
//!   unscattered part is the fine-resolution T_ri, so F_ms = generations ≥ 1 and the light thick
//!   cells reflect in generation 0, which travels beside the unscattered light, apart from it. In a white furnace the lattice's own total
//!   (generation 0 + F_ms) is then exactly √(4π) everywhere, and T_ri + F_ms = √(4π) + (T_ri −
//!   generation 0): off only where the fine and the lattice's unscattered light still differ, a
//!   cell or two under a surface. The former source, the first collisions gathered from the fine
//!   T_ri, paired a fine injection with the lattice's coarser exchange across a surface (its
//!   half-range moment is 0.23, not ¼): worst −22 % to −31 % inside a thick cloud with the plain
//!   weights as shares, +10 % to +13 % with the shares above.
//! * **Fluence readout, at the node.** Lattice lines along d_j carry one node per ℓ_j, so each
//!   line's cross-section is V/ℓ_j and the flux crossing the node, times ℓ_j/V, is fluence there:
//!   F_ms(x) = Σ over generations ≥ 1 and directions of ℓ_j·(P·e^(−τ_½) + E·η), τ_½ the depth
//!   from the segment's start to the node and η the share of the emission upstream of the node
//!   that reaches it. An isotropic radiance c gives fluxes that read back 4πc·Σw_j = 4πc (for the
//!   DC coefficient, whose basis function is 1/√(4π), c·√(4π)). The renderer's T_ri is a value
//!   at the node too, and in an equilibrium the flux is the same all along a line, so the lattice
//!   total stays exact; a track-length readout (the segment's mean) compared a cell average with
//!   T_ri's point value and put the surface voxels of the thick furnace up to 11 % off, not
//!   5–8.5 %.
//!
//! A generation is computed by sweeping each direction once over its lines, each line's nodes in
//! the order of x·d_j, so flux crosses the whole volume in one sweep (Gauss–Seidel in the
//! direction of flight); lines exchange no light within a sweep, so they go in parallel. Light a
//! cell reflects on the sweep of d_j waits for the sweep of −d_j, which takes it before the cell
//! reflects anything along d_j again: a direction and its opposite share one buffer.
//! Generations go on until the estimated **remaining** energy — the geometric tail Δₙ·r/(1−r) of
//! the per-generation increments Δₙ of the DC fluence, r = Δₙ/Δₙ₋₁ — is below
//! [`CONVERGENCE`] of the total. That tail is then added, not dropped: each node's fluence gains
//! r/(1−r) times what the last generation added to it. After a few generations every
//! generation's fluence is nearly the previous one's times r (the transport's slowest-decaying
//! mode), so the tail's shape is right to well within its own small size, and half the
//! generations reach the accuracy that stopping without it needed. The other coefficients' runs
//! stop after the DC run's generations and add the tail with its r. A sun's scalar solve
//! ([`Lattice::solve_emission`]) finds the sum of its generations by GMRES instead wherever that
//! fits beside the links ([`solve_krylov`]): on thin, bright cells the ratio r nears 1 and the
//! generations run into the hundreds.

use glam::{IVec3, Vec3, Vec4};
use rayon::prelude::*;

use super::layout::TransferLayout;
use super::memory::sun_krylov_bytes;
use super::Medium;
use crate::volume::bricks::BrickSampler;
use crate::volume::transmittance::through_and_leaving;
use crate::volume::DensityField;

/// Stop when the estimated energy still to come is below this fraction of the total; that tail is
/// then added in the shape of the last generation (module doc). Measured against runs to 1e-7
/// (640×360 renders under the studio map, albedo 0.9 and 0.99): the image is 0.01–0.05 % off at
/// this tolerance with the tail, where stopping at 1e-4 without it was 0.00–0.01 % off and took
/// 1.7–2× the generations (torus at 0.9: 12 → 6, cloud at 0.99: 67 → 36); at 1e-2 the image
/// is 0.26 % off.
pub const CONVERGENCE: f64 = 3e-3;
/// The most SH bands a lattice transports ([`LatticeKind::bands`]); F_ms's higher coefficients
/// are the fit's correction alone where T_ri is fitted, and zero where it holds point values. D
/// beams per node carry about D angular degrees of freedom, and light that has scattered once
/// has lost the rest: past band 3 the lattice's fluence is
/// the beams' aliasing of the environment's detail, not its multiple scattering. Measured against
/// the path tracer (256×144, albedo 0.9, `docs/accuracy.md`, before the band gains of
/// [`inflow`]), transporting 2, 3, 4, 5, 6 or all 10 bands: every row is as close or closer at 4
/// than at 10 — the cloud under studio.exr at σt 0.08 3.31 → 2.81 %, the torus at 1.92 optical
/// depths per transfer voxel 14.11 → 12.82 %, and with `--lattice 18` alike — where 2 bands lose
/// the light's direction (14.11 → 18.95 %). It is 2 of 13 chunks of coefficients:
/// cloud_quarter's lattice at σt 0.2 took 29.9 s with 10 bands, 4.3 s with 4.
pub const LATTICE_BANDS: usize = 4;
/// The chunks of coefficients (first, count) a lattice carrying `bands` transports after the DC
/// term's own run.
fn chunks_after_dc(bands: usize) -> Vec<(usize, usize)> {
    let coeffs = bands * bands;
    (1..coeffs)
        .step_by(CHUNK)
        .map(|c0| (c0, CHUNK.min(coeffs - c0)))
        .collect()
}

/// How many chunks a bake of `bands` on a lattice of `kind` transports after the DC term's own
/// run.
pub(crate) fn chunks_transported(kind: LatticeKind, bands: usize) -> usize {
    chunks_after_dc(kind.bands(bands)).len()
}
/// A hard cap on generations, reached only by pathological inputs (albedo 1 in an enormous volume).
pub const MAX_GENERATIONS: usize = 5000;
/// Coefficients transported together: 8 f32 fill a SIMD-friendly run, and the per-chunk buffers
/// (3 × nodes × 8 floats) keep peak memory bounded whatever the band count.
pub(crate) const CHUNK: usize = 8;

/// What a transport carries per node and link: one value (the DC term, whose run decides the
/// generation count, or a sun's fluence) or a [`Chunk`] of coefficients. Every operation is lane
/// by lane the same arithmetic as on scalars, so a value comes out the same either way; one value
/// a node keeps a sun's transport state an eighth of a chunk's, mostly in cache, where the
/// sweep's reads of its nodes in line order are what it waits for.
trait Lanes:
    Copy
    + Send
    + Sync
    + std::ops::Add<Output = Self>
    + std::ops::Sub<Output = Self>
    + std::ops::Mul<f32, Output = Self>
{
    const ZERO: Self;
    /// The first lane.
    fn first(self) -> f32;
    /// `values` in the first lanes, the rest zero.
    fn from_values(values: &[f32]) -> Self;
}

impl Lanes for f32 {
    const ZERO: f32 = 0.0;

    fn first(self) -> f32 {
        self
    }

    fn from_values(values: &[f32]) -> f32 {
        values.first().copied().unwrap_or(0.0)
    }
}

/// A node's coefficients of one chunk as SIMD lanes (the unused ones stay zero): the per-link
/// update is then a few vector instructions.
#[derive(Debug, Clone, Copy)]
struct Chunk([Vec4; CHUNK / 4]);

impl std::ops::Add for Chunk {
    type Output = Chunk;
    #[inline(always)]
    fn add(self, o: Chunk) -> Chunk {
        Chunk(std::array::from_fn(|c| self.0[c] + o.0[c]))
    }
}

impl std::ops::Sub for Chunk {
    type Output = Chunk;
    #[inline(always)]
    fn sub(self, o: Chunk) -> Chunk {
        Chunk(std::array::from_fn(|c| self.0[c] - o.0[c]))
    }
}

impl std::ops::Mul<f32> for Chunk {
    type Output = Chunk;
    #[inline(always)]
    fn mul(self, f: f32) -> Chunk {
        Chunk(self.0.map(|v| v * f))
    }
}

impl Lanes for Chunk {
    const ZERO: Chunk = Chunk([Vec4::ZERO; CHUNK / 4]);

    fn first(self) -> f32 {
        self.0[0].x
    }

    fn from_values(values: &[f32]) -> Chunk {
        let mut row = Chunk::ZERO;
        for (c, v) in values.iter().take(CHUNK).enumerate() {
            row.0[c / 4][c % 4] = *v;
        }
        row
    }
}

impl Chunk {
    /// The lanes in order.
    fn values(&self) -> impl Iterator<Item = f32> + '_ {
        self.0.iter().flat_map(|v| v.to_array())
    }
}
const NO_LINK: u32 = u32::MAX;
/// Longest segment marched, in sub-steps: a (2, 2, 1) link at K = 64 is 64·3 / 0.5 = 384 steps.
const MAX_SEGMENT_STEPS: usize = 384;
/// A line through a cell reflects part of the light entering it once its optical depth per cell
/// edge, t = σ̄·h, exceeds its lattice's t₀ ([`LatticeKind::reflect_depth`], module doc, "Thick
/// cells"); below, nothing is reflected and the lattice is the plain transport. This t₀ is the
/// one whose slab conducts as the exact one does: the slab of
/// `a_thick_slab_conducts_light_as_diffusion_does` (6 optical depths per cell edge) falls with
/// the exact slope × 0.936 on the 26 directions at t₀ = 1 and × 0.998 at 0.75; on 18, × 0.986 at
/// 1 and × 1.053 at 0.75; on 6, × 1.235 at 1. Against the path tracer (256×144, studio.exr,
/// docs/accuracy.md), the 26 directions at 0.75 bring eight rows 0.03–0.70 point closer (the
/// torus at 1.92 optical depths per transfer voxel 11.53 → 11.01 %) and none further.
const REFLECT_DEPTH_26: f64 = 0.75;
/// t₀ of the other lattices: 18 directions match the exact slab at 1 (above); the suns' set was
/// checked at 1 against the path tracer's energy (docs/accuracy.md, the energy check); 6
/// directions, a coarse option, conduct too well at any t₀ near 1.
const REFLECT_DEPTH: f64 = 1.0;
/// Cap on α·s, the share of a cell's emission it scatters again itself: s < 1 always, but at
/// α = 1 in an extremely thick cell 1/(1 − α·s) would lose all precision.
const MAX_SELF_GAIN: f64 = 0.999_999;

/// Which directions the lattice links: the 6 faces, faces and the 12 edges, or all 26 neighbours
/// (`--lattice`); or the suns' set, the faces and the 24 offsets like (2, 2, 1)
/// ([`crate::render::sunlight::SUN_LATTICE`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum LatticeKind {
    #[value(name = "6")]
    Faces,
    #[value(name = "18")]
    FacesEdges,
    #[value(name = "26")]
    All,
    #[value(skip)]
    FacesSkew,
}

impl LatticeKind {
    pub fn directions(self) -> usize {
        Directions::new(self).len()
    }

    /// t₀: the optical depth per cell edge above which this lattice's thick lines reflect.
    pub fn reflect_depth(self) -> f64 {
        match self {
            LatticeKind::All => REFLECT_DEPTH_26,
            LatticeKind::Faces | LatticeKind::FacesEdges | LatticeKind::FacesSkew => REFLECT_DEPTH,
        }
    }

    /// The SH bands this lattice transports for a bake of `bands`: at most [`LATTICE_BANDS`], and
    /// no more coefficients than it has directions — six beams carry bands 0 and 1 alone, and
    /// the gain that gives a band its power ([`inflow`]) would blow up their aliasing of band 2
    /// (the torus under studio.exr at σt 0.368 with `--lattice 6`: 28.9 % off the path tracer
    /// with four bands, against 15.8 % without the gain).
    pub fn bands(self, bands: usize) -> usize {
        let d = self.directions();
        let fit = (1..=LATTICE_BANDS)
            .take_while(|b| b * b <= d)
            .last()
            .unwrap_or(1);
        bands.min(fit)
    }

    /// The offset families linked, each as its sorted magnitudes, and the Voronoi share of the
    /// sphere of each of its offsets, measured by a 4000 × 8000 (cos θ, φ) quadrature
    /// (`lattice_weights_are_voronoi_shares` re-derives them).
    fn families(self) -> &'static [([i32; 3], f64)] {
        match self {
            LatticeKind::Faces => &[([0, 0, 1], 1.0 / 6.0)],
            LatticeKind::FacesEdges => &[([0, 0, 1], 0.046_782_333), ([0, 1, 1], 0.059_942_167)],
            LatticeKind::All => &[
                ([0, 0, 1], 0.045_776_417),
                ([0, 1, 1], 0.036_981_958),
                ([1, 1, 1], 0.035_194_750),
            ],
            LatticeKind::FacesSkew => &[([0, 0, 1], 0.045_848_750), ([1, 2, 2], 0.030_204_479)],
        }
    }
}

/// The sorted magnitudes of offset `d`: the family it belongs to.
fn family(d: IVec3) -> [i32; 3] {
    let mut a = d.abs().to_array();
    a.sort_unstable();
    a
}

/// The lattice's discrete directions and their weights.
#[derive(Debug, Clone)]
pub struct Directions {
    pub offsets: Vec<IVec3>,
    pub weights: Vec<f32>,
    /// Index of −d_j.
    pub opposite: Vec<usize>,
    /// t₀ of thick lines' reflection ([`LatticeKind::reflect_depth`]).
    pub reflect_depth: f64,
}

impl Directions {
    /// The directions of `kind`, in the order of their offsets (x, then y, then z).
    pub fn new(kind: LatticeKind) -> Directions {
        let weight = |d: IVec3| {
            let base = family(d);
            kind.families()
                .iter()
                .find(|(b, _)| *b == base)
                .map(|(_, w)| *w)
        };
        let mut offsets = Vec::new();
        let mut raw = Vec::new();
        for x in -2..=2 {
            for y in -2..=2 {
                for z in -2..=2 {
                    let d = IVec3::new(x, y, z);
                    if let Some(w) = weight(d) {
                        offsets.push(d);
                        raw.push(w);
                    }
                }
            }
        }
        // Renormalise the rounded constants so the weights sum to 1 exactly in f64.
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
            reflect_depth: kind.reflect_depth(),
        }
    }

    pub fn len(&self) -> usize {
        self.offsets.len()
    }

    pub fn is_empty(&self) -> bool {
        self.offsets.is_empty()
    }

    /// Each direction with its opposite, `(j, o)` with j < o: a pair shares its lines, its cells'
    /// segments and its reflected light.
    fn opposite_pairs(&self) -> impl Iterator<Item = (usize, usize)> + '_ {
        self.opposite
            .iter()
            .enumerate()
            .filter_map(|(j, &o)| (j < o).then_some((j, o)))
    }

    /// Per direction, from what each of [`Directions::opposite_pairs`] gave its two directions
    /// (`[along j, along o]`, in the pairs' order).
    fn spread<T>(&self, pairs: impl IntoIterator<Item = [T; 2]>) -> Vec<T> {
        let mut out: Vec<Option<T>> = (0..self.len()).map(|_| None).collect();
        for ((j, o), [along_j, along_o]) in self.opposite_pairs().zip(pairs) {
            (out[j], out[o]) = (Some(along_j), Some(along_o));
        }
        // Every direction has its opposite among them (`Directions::new`).
        out.into_iter().flatten().collect()
    }
}

/// One cell's segment along one direction: how it transmits, emits and accumulates fluence. Per
/// unit of what the cell scatters, the emission terms include the share e_j and the
/// self-scattering gain 1/(1 − α·s). Where its light goes is where it stands in its sweep: the
/// next link of its line.
#[derive(Debug, Clone, Copy, Default)]
struct Link {
    /// The cell's slot, with [`LINE_START`] set on the first cell of a line and [`REFLECTS`] on
    /// a cell that reflects.
    node: u32,
    /// e^(−τ) of the whole segment.
    trans: f32,
    /// Fluence at the node per unit entering flux, ℓ·e^(−τ_½) (world units).
    read_in: f32,
    /// Share of the cell's scattered power that leaves along d_j: e_j·ε/(1 − α·s).
    emit_out: f32,
    /// Fluence at the node per unit of the cell's scattered power: ℓ·e_j·η/(1 − α·s).
    read_emit: f32,
}

/// Marks a line's first cell in [`Link::node`]: no active cell lies upstream of it along −d_j,
/// so the environment enters there.
const LINE_START: u32 = 1 << 31;
/// Marks a reflecting cell's link in [`Link::node`]: its λ_j is in [`Links::reflectance`]. Most
/// cells reflect nothing, and a sweep streams every link once a generation: a λ in every link
/// would add a fifth to the bytes a sun's solve streams.
const REFLECTS: u32 = 1 << 30;
/// The slot in [`Link::node`]: a layout holds far fewer than 2³⁰ cells.
const SLOT: u32 = REFLECTS - 1;

/// Links per task of a sweep, at least (a task ends where a line does): enough that scheduling
/// costs nothing next to the links, few enough that two threads share a small lattice.
const TASK_LINKS: usize = 4096;

/// Links a sweep holds, at least, for its tasks to run in parallel, one chunk of coefficients
/// at a time; below it the chunks run in parallel, each sweep one task. A parallel sweep ends
/// where every task has, so on a busy machine a thread the system pauses holds the others up at
/// each of the 26 sweeps a generation: worth it only where a sweep is long, and that is where one
/// chunk's state in memory instead of one a thread counts (its reflected light is 416 bytes a cell).
pub(crate) const PARALLEL_SWEEP_LINKS: usize = 1 << 16;

/// Cells whose links are computed together before they are written to their sweeps: the block's
/// links (26 × 20 bytes a cell) and λs (26 × 4) are all the building holds beyond the sweeps
/// themselves, 5 MiB. A block four times larger took the fixture cloud's default render (its
/// suns' lattice on 223 749 voxels) 13 MiB higher, 173 against 160 MiB, in the same time.
const LINK_BLOCK: usize = 1 << 13;

/// One direction's links. A *line* is the active cells on one lattice line along d_j in
/// ascending x·d_j: light leaving a cell enters the next one of its line (across empty space,
/// unchanged), and lines never exchange light within a sweep. So the lines are stored one after
/// another, a sweep carries the flux from link to link in a register, and its tasks — runs of
/// whole lines — go in parallel.
struct Sweep {
    links: Vec<Link>,
    /// Where each task starts (at a line start), then `links.len()`.
    tasks: Vec<usize>,
}

/// The lattice's links, a [`Sweep`] per direction.
struct Links {
    sweeps: Vec<Sweep>,
    /// Flux entering each line from the environment, `D × coeffs`: P_ij = 4π·w_j·ȳ_ij/ℓ_j.
    inflow: Vec<f32>,
    /// Per direction, the reflected-light buffer it shares with its opposite (module doc).
    pair: Vec<usize>,
    /// Per cell, its row in the reflected-light buffers (`NO_LINK`: it reflects nothing).
    reflecting: Vec<u32>,
    reflecting_cells: usize,
    /// λ_j per direction and reflecting cell (its row), `j × reflecting_cells + row`: the share
    /// of the flux entering the cell along d_j that it sends straight back along −d_j. A sweep
    /// reads one direction's run, which stays in cache where a cell's whole record would not.
    reflectance: Vec<f32>,
    /// Whether a sweep's tasks run in parallel ([`PARALLEL_SWEEP_LINKS`]).
    parallel_sweeps: bool,
}

/// What the lattice did, for `--stats`.
#[derive(Debug, Clone, Copy, Default)]
pub struct LatticeStats {
    pub generations: usize,
    /// Σ over nodes of the DC coefficient of T_ri and of F_ms (its tail included).
    pub energy_single: f64,
    pub energy_multiple: f64,
    /// The estimated energy of the generations not swept when iteration stopped, relative to the
    /// total: the tail added in the last generation's shape.
    pub remaining: f64,
    pub converged: bool,
    /// The ratio of the last two generations' energies, which the tail extrapolates; 0 unless
    /// the energy criterion stopped the run.
    pub ratio: f64,
}

fn build_links(
    field: &DensityField,
    layout: &TransferLayout,
    medium: Medium,
    dirs: Directions,
    bands: usize,
) -> Links {
    let n = layout.len();
    let d = dirs.len();
    let k = layout.k;
    let scale = field.grid.transform.scale.as_vec3();
    let lengths: Vec<f32> = dirs
        .offsets
        .iter()
        .map(|off| (off.as_vec3() * k as f32 * scale).length())
        .collect();
    // The lines of every direction first, and where each cell's link goes in them.
    // A direction and its opposite share their lines, so one sort lays out both.
    let firsts: Vec<usize> = dirs.opposite_pairs().map(|(j, _)| j).collect();
    let laid: Vec<[(Sweep, Vec<u32>); 2]> = firsts
        .par_iter()
        .map(|&j| lines(layout, dirs.offsets[j]))
        .collect();
    let (mut sweeps, places): (Vec<Sweep>, Vec<Vec<u32>>) = dirs.spread(laid).into_iter().unzip();
    // Then each cell's links, a block of cells at a time, written straight to their places.
    let mut reflects = vec![false; n];
    let mut reflectance = Vec::new();
    for start in (0..n).step_by(LINK_BLOCK) {
        let end = (start + LINK_BLOCK).min(n);
        let block: Vec<([Link; MAX_DIRECTIONS], [f32; MAX_DIRECTIONS])> = layout.voxels()
            [start..end]
            .par_iter()
            .map_init(
                || (field.sampler(), Box::new(SegmentScratch::new())),
                |(acc, scratch), &v| {
                    let x = layout.position(v);
                    cell_links(acc, scratch, x, k, &dirs, &lengths, medium)
                },
            )
            .collect();
        for (r, (_, lambda)) in reflects[start..end].iter_mut().zip(&block) {
            *r = lambda[..d].iter().any(|&l| l > 0.0);
            if *r {
                reflectance.extend_from_slice(&lambda[..d]);
            }
        }
        let flags = &reflects[start..end];
        sweeps
            .par_iter_mut()
            .zip(&places)
            .enumerate()
            .for_each(|(j, (sweep, place))| {
                for (((cell, _), &at), &r) in block.iter().zip(&place[start..end]).zip(flags) {
                    let link = &mut sweep.links[at as usize];
                    *link = Link {
                        node: link.node | if r { REFLECTS } else { 0 },
                        ..cell[j]
                    };
                }
            });
    }
    // Gathered a cell at a time, kept a direction at a time.
    let rows = reflectance.len() / d.max(1);
    let reflectance: Vec<f32> = (0..d)
        .flat_map(|j| (0..rows).map(move |row| (j, row)))
        .map(|(j, row)| reflectance[row * d + j])
        .collect();
    let mut reflecting_cells = 0;
    let reflecting = reflects
        .iter()
        .map(|&r| match r {
            true => {
                reflecting_cells += 1;
                reflecting_cells as u32 - 1
            }
            false => NO_LINK,
        })
        .collect();
    Links {
        inflow: inflow(&dirs, &lengths, bands),
        pair: pairs(&dirs),
        reflecting,
        reflecting_cells,
        reflectance,
        parallel_sweeps: n >= PARALLEL_SWEEP_LINKS,
        sweeps,
    }
}

/// Numbers each pair of opposite directions: the pair's buffer.
fn pairs(dirs: &Directions) -> Vec<usize> {
    dirs.spread((0..).map(|count| [count, count]))
}

/// The most lattice directions there are (30).
const MAX_DIRECTIONS: usize = 30;

/// The lines of the layout along `off` and along −`off` ([`Sweep`]), their links holding only the
/// cells' slots, and each cell's place among them. The two directions have the same lines, each
/// run the other way.
fn lines(layout: &TransferLayout, off: IVec3) -> [(Sweep, Vec<u32>); 2] {
    let voxels = layout.voxels();
    // A cell's line is named by the point where it crosses the plane through the origin normal to
    // an axis the direction moves along, and the cell's place on it by the steps t from there.
    // An axis the direction moves one step along (every lattice offset has one), so that t counts
    // the cells of the line.
    let axis = (0..3).find(|&a| off[a].abs() == 1).unwrap_or(0);
    let line = |v: IVec3| {
        let t = v[axis] * off[axis];
        (v - off * t, t)
    };
    // Each cell's place as one integer, sorted as such: 16 bytes a cell, no key computed at a
    // comparison.
    let mut order: Vec<Placed> = voxels
        .iter()
        .enumerate()
        .map(|(s, &v)| {
            let (key, t) = line(v);
            placed(key, axis, t, s as u32)
        })
        .collect();
    order.sort_unstable();
    let there = sweep_of(&order);
    // The same lines, each run reversed: −off's order.
    let mut start = 0;
    while start < order.len() {
        let end = start
            + order[start..]
                .iter()
                .take_while(|o| same_line(o, &order[start]))
                .count();
        order[start..end].reverse();
        start = end;
    }
    [there, sweep_of(&order)]
}

/// Whether two cells of [`lines`]' order lie on one line (their keys agree).
fn same_line(a: &Placed, b: &Placed) -> bool {
    a >> 64 == b >> 64
}

/// A cell placed on its line: the line's key (its two coordinates across `axis`; the one along
/// it is 0), then t, then the cell's slot, each in 32 bits of its own (an i32 with its sign bit
/// flipped, so the unsigned order is the signed one). The order is that of (line, t): no two
/// cells share a line and a t.
type Placed = u128;

/// Cell `slot` placed at `t` on the line of `key`, which is 0 along `axis`.
fn placed(key: IVec3, axis: usize, t: i32, slot: u32) -> Placed {
    let bits = |v: i32| (v as u32 ^ 1 << 31) as u128;
    let [b, c] = match axis {
        0 => [1, 2],
        1 => [0, 2],
        _ => [0, 1],
    }
    .map(|a| bits(key[a]));
    b << 96 | c << 64 | bits(t) << 32 | slot as u128
}

/// A sweep over cells in line order (`order`: each line's key, t and a cell's slot, lines
/// contiguous), and each cell's place in it.
fn sweep_of(order: &[Placed]) -> (Sweep, Vec<u32>) {
    let n = order.len();
    let mut place = vec![0u32; n];
    let mut links = Vec::with_capacity(n);
    let mut tasks = vec![0];
    for (i, &p) in order.iter().enumerate() {
        let s = p as u32;
        place[s as usize] = i as u32;
        let start = i == 0 || !same_line(&order[i - 1], &order[i]);
        if start && i - tasks[tasks.len() - 1] >= TASK_LINKS {
            tasks.push(i);
        }
        links.push(Link {
            node: s | if start { LINE_START } else { 0 },
            ..Link::default()
        });
    }
    tasks.push(n);
    (Sweep { links, tasks }, place)
}

/// One cell's links along every direction (the first `dirs.len()` entries), its node at
/// `x`: each segment marched, then the emission shares, reflections and the self-scattering gain
/// that couple them (module doc). The links' `node` is left for the sweep to set.
fn cell_links(
    acc: &mut BrickSampler,
    scratch: &mut SegmentScratch,
    x: Vec3,
    k: i32,
    dirs: &Directions,
    lengths: &[f32],
    medium: Medium,
) -> ([Link; MAX_DIRECTIONS], [f32; MAX_DIRECTIONS]) {
    let d = dirs.len();
    // Fixed arrays, not vectors: a bake links hundreds of thousands of cells, each in a few
    // microseconds.
    let mut segments = [Segment::default(); MAX_DIRECTIONS];
    for (j, o) in dirs.opposite_pairs() {
        let half = dirs.offsets[j].as_vec3() * (k as f32 / 2.0);
        [segments[j], segments[o]] =
            segment_pair(acc, scratch, x - half, x + half, lengths[j], medium.sigma_t);
    }
    let segments = &segments[..d];
    let mut lambda = [0f64; MAX_DIRECTIONS];
    for ((lam, seg), off) in lambda.iter_mut().zip(segments).zip(&dirs.offsets) {
        *lam = reflection(
            seg.tau as f64 / off.as_vec3().length() as f64,
            dirs.reflect_depth,
        );
    }
    // Emission shares e_j ∝ (1 − λ_j)·w_j·σ̄_j: what enters line j and collides there; an empty
    // cell scatters nothing, any shares will do.
    let mut absorbing = [0f64; MAX_DIRECTIONS];
    for ((((a, seg), w), l), lam) in absorbing
        .iter_mut()
        .zip(segments)
        .zip(&dirs.weights)
        .zip(lengths)
        .zip(&lambda)
    {
        *a = (1.0 - lam) * *w as f64 * seg.tau as f64 / *l as f64;
    }
    let total: f64 = absorbing[..d].iter().sum();
    let share = |j: usize| match total > 0.0 {
        true => absorbing[j] / total,
        false => dirs.weights[j] as f64,
    };
    let self_share: f64 = (0..d)
        .map(|j| share(j) * (1.0 - segments[j].escape as f64))
        .sum();
    let gain = 1.0 / (1.0 - (medium.albedo as f64 * self_share).min(MAX_SELF_GAIN));
    let mut links = [Link::default(); MAX_DIRECTIONS];
    for (j, seg) in segments.iter().enumerate() {
        links[j] = Link {
            node: 0,
            trans: seg.trans,
            read_in: seg.read_in,
            emit_out: (share(j) * gain * seg.escape as f64) as f32,
            // The node reads the light that entered line j, not what it reflected at the face:
            // 1/(1 − λ_j) keeps a uniform field's readout exact.
            read_emit: (share(j) * gain * seg.read_emit as f64 / (1.0 - lambda[j])) as f32,
        };
    }
    (links, lambda.map(|l| l as f32))
}

/// λ = (√(t/t₀) − 1)/(√(t/t₀) + 1) above t₀, else 0: the share of the light entering a line of
/// optical depth t per cell edge that the cell sends back (module doc, "Thick cells"). Between
/// two such cells it scales the net exchange by (1 − λ)/(1 + λ) = √(t₀/t).
fn reflection(t: f64, t0: f64) -> f64 {
    if t <= t0 {
        return 0.0;
    }
    let r = (t / t0).sqrt();
    (r - 1.0) / (r + 1.0)
}

/// The mean density of each leaf and tile with its active voxel count, gathered once, so the
/// memory estimate can ask at any σt and scale which share of a bake's cells can reflect (each
/// holds one row of reflected light per lattice direction in a chunk's sweep).
pub struct DensityMeans {
    /// (mean value, active voxels) per leaf and tile.
    means: Vec<(f32, f64)>,
    /// The largest voxel edge in world units.
    voxel: f64,
}

impl DensityMeans {
    pub fn new(density: &crate::volume::grid::SparseGrid) -> DensityMeans {
        use crate::volume::grid::{TileLevel, LEAF_VOXELS};
        let leaves = density.leaves().iter().map(|leaf| {
            let count = leaf.active_count() as f64;
            let sum: f32 = (0..LEAF_VOXELS)
                .filter(|&slot| leaf.is_active(slot))
                .map(|slot| leaf.values.get(slot))
                .sum();
            (sum / count.max(1.0) as f32, count)
        });
        let tiles = TileLevel::ALL.into_iter().flat_map(|level| {
            density
                .tiles(level)
                .map(move |(_, value)| (value, level.voxel_count() as f64))
        });
        DensityMeans {
            means: leaves.chain(tiles).collect(),
            voxel: density.transform.voxel_size().max_element(),
        }
    }

    /// The active voxels of the leaves and tiles whose mean is more than `kind`'s t₀ optical
    /// depths per cell edge at `sigma_t` and scale `k`, of all active voxels (a cell's lines
    /// average the density as a leaf's mean does).
    pub fn reflecting_share(&self, sigma_t: f32, k: i32, kind: LatticeKind) -> f64 {
        let edge = self.voxel * k as f64;
        let t0 = kind.reflect_depth();
        let thick = |mean: f32| sigma_t as f64 * mean as f64 * edge > t0;
        let all: f64 = self.means.iter().map(|m| m.1).sum();
        let reflecting: f64 = self.means.iter().filter(|m| thick(m.0)).map(|m| m.1).sum();
        if all > 0.0 {
            reflecting / all
        } else {
            0.0
        }
    }
}

/// Quadrature points for the Voronoi means ȳ_ij: 65 536 spherical-Fibonacci points put ~2 500 in
/// each of the 26 cells, so the means of the 100 basis functions are good to ~10⁻³, far below the
/// lattice's own angular error; it takes milliseconds, once per bake.
const INFLOW_QUADRATURE: usize = 1 << 16;

/// The environment's flux into each lattice line, `D × coeffs` (module doc, "Source"):
/// P_ij = 4π·w_j·ȳ_ij·g_ℓ/ℓ_j, ȳ_ij the mean of y_i over the directions nearer −d_j than any other
/// lattice direction and g_ℓ the gain that gives the beams band ℓ's power. The mean of y₀ is
/// exactly 1/√(4π), so the DC inflow is exact.
///
/// Why the gain: the means are a blur, which the beams carry on into the lattice as a light
/// flatter than the environment's; restoring each band's power restores its contrast. Measured
/// against the path tracer (256×144, albedo 0.9, `docs/accuracy.md`): of twelve scenes ten come
/// closer, the cloud under studio.exr at σt 0.08 2.81 → 2.35 %, the torus at 1.92 optical depths
/// per transfer voxel 12.82 → 11.88 %, and the torus under studio.exr at σt 0.08 moves 4.18 →
/// 4.23 %; a constant environment, its DC term alone, not at all.
fn inflow(dirs: &Directions, lengths: &[f32], bands: usize) -> Vec<f32> {
    let coeffs = bands * bands;
    let units: Vec<Vec3> = dirs
        .offsets
        .iter()
        .map(|d| d.as_vec3().normalize())
        .collect();
    let mut sums = vec![0f64; dirs.len() * coeffs];
    let mut counts = vec![0usize; dirs.len()];
    let mut basis = vec![0f64; coeffs];
    for w in crate::math::sphere::fibonacci(INFLOW_QUADRATURE) {
        // Environment light from ω travels along −ω: line j carries ω when d_j is nearest −ω.
        let j = (0..units.len())
            .max_by(|&a, &b| units[a].dot(-w).total_cmp(&units[b].dot(-w)))
            .unwrap_or(0);
        crate::light::sh::eval_basis(w.as_dvec3().to_array(), bands, &mut basis);
        counts[j] += 1;
        for (s, y) in sums[j * coeffs..(j + 1) * coeffs].iter_mut().zip(&basis) {
            *s += y;
        }
    }
    // Per coefficient, the gain of its band: √(power over the sphere / power of the means).
    let mut gain = vec![1f64; coeffs];
    for band in 1..bands {
        let range = band * band..(band + 1) * (band + 1);
        let carried: f64 = (0..dirs.len())
            .map(|j| {
                let n = counts[j].max(1) as f64;
                let sq: f64 = range
                    .clone()
                    .map(|i| (sums[j * coeffs + i] / n).powi(2))
                    .sum();
                dirs.weights[j] as f64 * sq
            })
            .sum();
        let power = (2 * band + 1) as f64 / (4.0 * std::f64::consts::PI);
        if carried > 0.0 {
            gain[range].fill((power / carried).sqrt());
        }
    }
    let mut flux = vec![0f32; dirs.len() * coeffs];
    for (j, row) in flux.chunks_exact_mut(coeffs).enumerate() {
        let solid_angle = 4.0 * std::f64::consts::PI * dirs.weights[j] as f64;
        let per_point = solid_angle / (counts[j].max(1) as f64 * lengths[j] as f64);
        for ((f, s), g) in row.iter_mut().zip(&sums[j * coeffs..]).zip(&gain) {
            *f = (s * per_point * g) as f32;
        }
    }
    flux
}

/// How one cell's segment along a direction transmits light, found by marching it.
#[derive(Clone, Copy, Default)]
struct Segment {
    tau: f32,
    trans: f32,
    escape: f32,
    read_in: f32,
    read_emit: f32,
}

/// Sub-step of a segment march, in voxels: one density sample per voxel crossed, as T_ri's rays
/// take ([`crate::volume::transmittance::STEP_VOXELS`]). Each sub-step is integrated exactly for
/// its midpoint's density, so a thick voxel costs no accuracy: against half-voxel sub-steps, the
/// torus and cloud fixtures at σt 1 (256×144, built-in sky and studio.exr, albedo 0.9) moved by
/// at most 0.01 point of relative RMSE against the path tracer, and a one-sun render of the bench
/// cloud (σt 1.6, 1920×1080) by 0.26 % relative RMSE, for half the link build's samples.
const SEGMENT_STEP_VOXELS: f32 = 1.0;

/// A segment march's sub-steps: their densities, and each one's e^(−t) and (1 − e^(−t))/t
/// ([`through_and_leaving`]). Held by a thread across the cells it links, so a march fills only
/// the sub-steps it takes.
struct SegmentScratch {
    rho: [f32; MAX_SEGMENT_STEPS],
    exits: [(f32, f32); MAX_SEGMENT_STEPS],
}

impl SegmentScratch {
    fn new() -> SegmentScratch {
        SegmentScratch {
            rho: [0.0; MAX_SEGMENT_STEPS],
            exits: [(0.0, 0.0); MAX_SEGMENT_STEPS],
        }
    }
}

/// Marches the segment from index point `a` to `b` (world length `length`; the node is its
/// midpoint), the density constant over each sub-step, and integrates exactly over that profile
/// both ways: `[a → b, b → a]`. A direction and its opposite cross the same sub-steps, so one
/// march and one set of sub-step terms serve both links.
fn segment_pair(
    acc: &mut BrickSampler,
    scratch: &mut SegmentScratch,
    a: Vec3,
    b: Vec3,
    length: f32,
    sigma_t: f32,
) -> [Segment; 2] {
    let pairs = ((b - a).length() / (2.0 * SEGMENT_STEP_VOXELS)).ceil() as usize;
    let steps = (2 * pairs.max(1)).min(MAX_SEGMENT_STEPS);
    let depth_per_density = sigma_t * length / steps as f32;
    let rho = &mut scratch.rho[..steps];
    let exits = &mut scratch.exits[..steps];
    for (i, (r, e)) in rho.iter_mut().zip(exits.iter_mut()).enumerate() {
        *r = acc
            .sample(a + (b - a) * ((i as f32 + 0.5) / steps as f32))
            .max(0.0);
        *e = through_and_leaving(depth_per_density * *r);
    }
    let forward = segment(rho, exits, length, depth_per_density);
    rho.reverse();
    exits.reverse();
    [forward, segment(rho, exits, length, depth_per_density)]
}

/// A segment of world length `length` through sub-steps of densities `rho` (optical depth
/// `rho·depth_per_density` each, whose e^(−t) and leaving shares are `exits`), its node at the
/// midpoint: how it transmits, and what of the light emitted along it, in proportion to the
/// density as collisions are, escapes past its end (ε) and crosses the node (η).
fn segment(rho: &[f32], exits: &[(f32, f32)], length: f32, depth_per_density: f32) -> Segment {
    let depth = |r: &f32| depth_per_density * r;
    // The whole depth τ; the node sits at the end of sub-step steps/2 − 1, at depth τ½.
    let node = rho.len() / 2;
    let tau: f32 = rho.iter().map(depth).sum();
    // Emission in sub-step i, weighted by ρ_i: the share escaping past the end, e^(−(τ − end_i)),
    // and upstream of the node the share crossing it, e^(−(τ½ − end_i)): products of the
    // sub-steps' own transmittances downstream, from the end back. Run to the start, the two
    // products are the segment's e^(−τ) and e^(−τ½) themselves: no exponential of their own.
    let (mut weight, mut escape, mut crossing) = (0.0f32, 0.0f32, 0.0f32);
    let (mut to_end, mut to_node) = (1.0f32, 1.0f32);
    for (i, (r, &(through, leaving))) in rho.iter().zip(exits).enumerate().rev() {
        if *r > 0.0 {
            let out = r * leaving;
            weight += r;
            escape += out * to_end;
            if i < node {
                crossing += out * to_node;
            }
        }
        to_end *= through;
        if i < node {
            to_node *= through;
        }
    }
    let (escape, crossing) = if weight > 0.0 {
        (escape / weight, crossing / weight)
    } else {
        // Nothing is emitted in an empty segment; these values are never used with Q > 0.
        (1.0, 0.5)
    };
    Segment {
        tau,
        trans: to_end,
        escape,
        read_in: length * to_node,
        read_emit: length * crossing,
    }
}

/// What drives the transport: the environment entering at the boundary (generation 0, then the
/// scattered generations, for coefficients `[c0, c0 + width)`), or the first scattering already
/// known per node (a sun's, gathered from its exact shadow: one right-hand side).
enum Drive<'a> {
    Environment { c0: usize, width: usize },
    Emission(&'a [f32]),
}

/// Rows the tasks of one sweep update in parallel, each row from one task only: a sweep holds
/// exactly one link per cell ([`lines`] places every cell once), and a cell's link alone touches
/// the cell's rows — its fluence, its next emission, and its reflected light in the buffer of the
/// sweep's direction pair.
struct SweepRows<'a, R> {
    rows: *mut R,
    len: usize,
    _rows: std::marker::PhantomData<&'a mut [R]>,
}

// SAFETY: the rows are only reached through `take` and `add`, whose callers guarantee that no two
// threads touch one row during a sweep (above).
unsafe impl<R: Send> Send for SweepRows<'_, R> {}
unsafe impl<R: Sync> Sync for SweepRows<'_, R> {}

impl<'a, R: Lanes> SweepRows<'a, R> {
    fn new(rows: &'a mut [R]) -> SweepRows<'a, R> {
        SweepRows {
            rows: rows.as_mut_ptr(),
            len: rows.len(),
            _rows: std::marker::PhantomData,
        }
    }

    /// Row `i`.
    ///
    /// # Safety
    /// No task of the sweep writes row `i`.
    unsafe fn get(&self, i: usize) -> R {
        assert!(i < self.len);
        // SAFETY: in bounds, and nobody writes it (the caller's promise).
        unsafe { std::ptr::read(self.rows.add(i)) }
    }

    /// Row `i`, left zero.
    ///
    /// # Safety
    /// No other task of the sweep reaches row `i`.
    unsafe fn take(&self, i: usize) -> R {
        assert!(i < self.len);
        // SAFETY: in bounds, and ours alone (the caller's promise).
        unsafe { std::ptr::replace(self.rows.add(i), R::ZERO) }
    }

    /// Adds `value` to row `i`.
    ///
    /// # Safety
    /// As [`SweepRows::take`].
    unsafe fn add(&self, i: usize, value: R) {
        assert!(i < self.len);
        // SAFETY: in bounds, and ours alone (the caller's promise).
        let row = unsafe { &mut *self.rows.add(i) };
        *row = *row + value;
    }
}

/// The state of one transport: per node the emission of the generation being swept, the
/// collisions that feed the next and the fluence read out so far, side by side (one place in
/// memory a link reaches, not three); per reflecting cell and pair of opposite directions,
/// reflected light waiting to leave.
struct State<R> {
    /// [`NODE_ROWS`] rows a node: `emitting`, the other of the first two (next), then fluence.
    nodes: Vec<R>,
    /// Which of a node's first two rows holds the emission; they trade places each generation.
    emitting: usize,
    reflected: Vec<R>,
}

impl<R: Lanes> State<R> {
    /// The state of a transport over `links` with node rows `nodes`, no light waiting.
    fn new(nodes: Vec<R>, links: &Links) -> State<R> {
        State {
            nodes,
            emitting: 0,
            reflected: vec![R::ZERO; links.reflecting_cells * (links.sweeps.len() / 2)],
        }
    }
}

/// A node's rows in [`State::nodes`].
const NODE_ROWS: usize = 3;
/// The fluence's place among them.
const FLUENCE: usize = 2;

/// Sweeps direction `j` once; returns the DC fluence it read out (when `c0 == 0`), summed task by
/// task in a fixed order, so the result does not depend on the thread count. `INFLOW`: generation
/// 0, the environment's light entering each line (`inflow`), unscattered, so carried apart from
/// the light cells reflect and not read out.
fn sweep<R: Lanes, const INFLOW: bool>(
    links: &Links,
    j: usize,
    state: &mut State<R>,
    inflow: R,
    albedo: f32,
    c0: usize,
) -> f64 {
    let sweep = &links.sweeps[j];
    // The pair's buffers are one run of rows, a reflecting cell's row in it: a sweep touches one
    // pair's rows only, so they share no cache line with the other pairs'.
    let waiting = links.pair[j] * links.reflecting_cells;
    let (emitting, next) = (state.emitting, 1 - state.emitting);
    let nodes = SweepRows::new(&mut state.nodes);
    let reflected = SweepRows::new(&mut state.reflected);
    let task = |task: usize| {
        let mut added = 0.0f64;
        // The scattered flux entering the cell, and in generation 0 the unscattered one.
        let (mut p, mut unscattered) = (R::ZERO, R::ZERO);
        for link in &sweep.links[sweep.tasks[task]..sweep.tasks[task + 1]] {
            if link.node & LINE_START != 0 {
                (p, unscattered) = (R::ZERO, inflow);
            }
            let cell = (link.node & SLOT) as usize;
            let x = cell * NODE_ROWS;
            // SAFETY (here and below): the rows of this link's cell are its alone in this sweep
            // (`SweepRows`), and no link writes an emission.
            let e = unsafe { nodes.get(x + emitting) };
            let reflects = link.node & REFLECTS != 0;
            // A cell that reflects nothing reads neither its row nor its λ (0).
            let (row, lambda) = match reflects {
                true => {
                    let row = links.reflecting[cell] as usize;
                    (row, links.reflectance[j * links.reflecting_cells + row])
                }
                false => (0, 0.0),
            };
            let back = match reflects {
                true => unsafe { reflected.take(waiting + row) },
                false => R::ZERO,
            };
            let entering = match INFLOW {
                true => p + unscattered,
                false => p,
            };
            let enter = 1.0 - lambda;
            let read = p * link.read_in + e * link.read_emit;
            // Only entering flux feeds the next generation: the cell's own emission re-collides
            // inside its self-scattering gain already.
            let collided = entering * (albedo * enter) * (1.0 - link.trans);
            let out = p * enter * link.trans + e * link.emit_out + back;
            if INFLOW {
                unscattered = unscattered * enter * link.trans;
            }
            unsafe {
                nodes.add(x + FLUENCE, read);
                nodes.add(x + next, collided);
            }
            if reflects && lambda > 0.0 {
                let r = entering * (albedo * lambda);
                unsafe { reflected.add(waiting + row, r) };
            }
            if c0 == 0 {
                added += read.first() as f64;
            }
            // What leaves enters the next cell of the line, as it would a fresh cell's zero.
            p = R::ZERO + out;
        }
        added
    };
    let tasks = 0..sweep.tasks.len() - 1;
    let added: Vec<f64> = match links.parallel_sweeps {
        true => tasks.into_par_iter().map(task).collect(),
        false => tasks.map(task).collect(),
    };
    added.iter().sum()
}

/// One generation: every direction swept once from the emission in `state`, into the next
/// generation's row, which then becomes the emission. `inflow(j)`: the environment's light
/// entering direction j's lines (generation 0). Returns the DC fluence read ([`sweep`]).
fn sweep_generation<R: Lanes, const INFLOW: bool>(
    links: &Links,
    state: &mut State<R>,
    albedo: f32,
    c0: usize,
    inflow: impl Fn(usize) -> R,
) -> f64 {
    let next = 1 - state.emitting;
    state
        .nodes
        .chunks_exact_mut(NODE_ROWS)
        .for_each(|node| node[next] = R::ZERO);
    let added = (0..links.sweeps.len()).fold(0.0, |added, j| {
        added + sweep::<R, INFLOW>(links, j, state, inflow(j), albedo, c0)
    });
    state.emitting = next;
    added
}

/// Transports one drive; stops by the energy criterion when `stop` is `None` (the chunk holding
/// the DC term, or a sun), else runs exactly the generations of `stop`. Returns the fluence per
/// node (its first `width` lanes), with the tail of the generations not swept added (module doc).
fn transport_chunk<R: Lanes>(
    links: &Links,
    first: &Source,
    drive: Drive,
    stop: Option<Stop>,
) -> (Vec<R>, LatticeStats) {
    let (coeffs, albedo) = (first.bands * first.bands, first.medium.albedo);
    let n = links.sweeps[0].links.len();
    // The coefficients transported, what the first generation emits, and where it starts:
    // the environment enters at generation 0 and emits nothing; a known emission is generation 1.
    let mut nodes = vec![R::ZERO; n * NODE_ROWS];
    let (c0, width, start) = match drive {
        Drive::Environment { c0, width } => (c0, width, 0),
        Drive::Emission(q) => {
            for (node, &e) in nodes.chunks_exact_mut(NODE_ROWS).zip(q) {
                node[0] = R::from_values(&[e]);
            }
            (0, 1, 1)
        }
    };
    let mut state = State::new(nodes, links);
    let mut stats = LatticeStats {
        energy_single: first.energy_single,
        ..Default::default()
    };
    let mut previous = 0.0f64;
    let limit = stop.map_or(MAX_GENERATIONS, |s| s.generations);
    // The fluence before the generation that may be the last: the tail takes that generation's
    // shape.
    let mut before: Vec<R> = Vec::new();
    for generation in start..=limit {
        if stop.is_none() && generation >= 2 || generation == limit {
            before.clear();
            before.extend(state.nodes.chunks_exact(NODE_ROWS).map(|n| n[FLUENCE]));
        }
        // Generation 0 is the unscattered light: it enters from the environment, emits nothing
        // (`emit` starts at zero) and is not read out, since T_ri stands for it; only what thick
        // cells reflect of it is.
        let inflow = generation == 0;
        let added = match inflow {
            true => sweep_generation::<R, true>(links, &mut state, albedo, c0, |j| {
                R::from_values(&links.inflow[j * coeffs + c0..j * coeffs + c0 + width])
            }),
            false => sweep_generation::<R, false>(links, &mut state, albedo, c0, |_| R::ZERO),
        };
        stats.generations = generation;
        if stop.is_none() {
            stats.energy_multiple += added;
        }
        if stop.is_none() && !inflow {
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
            if generation >= 2 && stats.remaining < first.convergence || added == 0.0 {
                stats.converged = true;
                stats.ratio = r;
                break;
            }
        }
    }
    // The reflected light goes first: the fluence's copy is then no addition to the peak.
    let State {
        mut nodes,
        reflected,
        ..
    } = state;
    drop(reflected);
    // `ratio` stays 0 (no tail) unless the energy criterion stopped the run.
    let tail = tail_factor(stop.map_or(stats.ratio, |s| s.ratio));
    if tail > 0.0 && before.len() * NODE_ROWS == nodes.len() {
        for (node, b) in nodes.chunks_exact_mut(NODE_ROWS).zip(&before) {
            node[FLUENCE] = node[FLUENCE] + (node[FLUENCE] - *b) * tail;
        }
        if stop.is_none() {
            stats.energy_multiple += previous * tail as f64;
        }
    }
    drop(before);
    let fluence = nodes
        .chunks_exact(NODE_ROWS)
        .map(|node| node[FLUENCE])
        .collect();
    (fluence, stats)
}

/// Where a transport of the coefficients that do not decide the generation count stops: after
/// the DC run's generations, with its ratio of successive generations for the tail.
#[derive(Debug, Clone, Copy)]
struct Stop {
    generations: usize,
    ratio: f64,
}

/// The energy of every generation after the last, in units of the last: r + r² + … = r/(1 − r)
/// for a ratio r of successive generations; none unless 0 < r < 1.
fn tail_factor(ratio: f64) -> f32 {
    match ratio > 0.0 && ratio < 1.0 {
        true => (ratio / (1.0 - ratio)) as f32,
        false => 0.0,
    }
}

/// What a transport works with: the medium, the SH band count, and the energy of the unscattered
/// light (Σ over nodes of T_ri's DC coefficient), against which the remaining energy is weighed;
/// the lattice's source is the environment (module doc).
struct Source {
    energy_single: f64,
    /// Where the energy criterion stops ([`CONVERGENCE`]).
    convergence: f64,
    /// The bands transported; the inflow holds `bands²` coefficients per direction.
    bands: usize,
    medium: Medium,
}

/// The lattice of a layout, built from the density: every cell's links along every direction.
/// Once built it needs the density no more.
pub struct Lattice {
    links: Links,
    medium: Medium,
    /// The bands it transports: the caller's, as many as its kind carries ([`LatticeKind::bands`]).
    bands: usize,
    /// Where the energy criterion stops ([`CONVERGENCE`]; tests go further to compare).
    convergence: f64,
}

impl Lattice {
    pub fn build(
        field: &DensityField,
        layout: &TransferLayout,
        kind: LatticeKind,
        medium: Medium,
        bands: usize,
    ) -> Lattice {
        let bands = kind.bands(bands);
        let links = build_links(field, layout, medium, Directions::new(kind), bands);
        Lattice {
            links,
            medium,
            bands,
            convergence: CONVERGENCE,
        }
    }

    /// The SH bands it transports ([`LatticeKind::bands`]).
    pub fn bands(&self) -> usize {
        self.bands
    }

    /// Adds F_ms for every transfer voxel to `f_ms` (`layout.len() × bands²`), the coefficients of
    /// the lattice's own bands ([`LatticeKind::bands`]) chunk by chunk, the chunks or each chunk's
    /// sweeps in parallel ([`PARALLEL_SWEEP_LINKS`]).
    /// `energy_single` is Σ over nodes of T_ri's DC coefficient (the remaining energy is weighed
    /// against it).
    pub fn bake_multiple(
        &self,
        bands: usize,
        energy_single: f64,
        f_ms: &mut [f32],
    ) -> LatticeStats {
        let coeffs = bands * bands;
        let carried = self.bands.min(bands);
        let first = Source {
            energy_single,
            convergence: self.convergence,
            bands: carried,
            medium: self.medium,
        };
        let add = |f_ms: &mut [f32], (c0, width): (usize, usize), fluence: &[Chunk]| {
            for (f, row) in f_ms.chunks_exact_mut(coeffs).zip(fluence) {
                for (out, value) in f[c0..c0 + width].iter_mut().zip(row.values()) {
                    *out += value;
                }
            }
        };
        // The DC term alone first: its run decides the generation count by energy, so it
        // carries no more than it must; the operator is the same for every coefficient, so the
        // other chunks run exactly as many generations.
        let drive = |(c0, width)| Drive::Environment { c0, width };
        let (head, stats) = transport_chunk::<f32>(&self.links, &first, drive((0, 1)), None);
        let stop = Stop {
            generations: stats.generations,
            ratio: stats.ratio,
        };
        for (f, dc) in f_ms.chunks_exact_mut(coeffs).zip(head) {
            f[0] += dc;
        }
        let rest = chunks_after_dc(carried);
        let in_flight = match self.links.parallel_sweeps {
            true => 1,
            false => rayon::current_num_threads(),
        };
        for group in rest.chunks(in_flight) {
            let parts: Vec<Vec<Chunk>> = group
                .par_iter()
                .map(|&c| transport_chunk::<Chunk>(&self.links, &first, drive(c), Some(stop)).0)
                .collect();
            for (&c, fluence) in group.iter().zip(&parts) {
                add(f_ms, c, fluence);
            }
        }
        stats
    }
}

impl Lattice {
    /// The multiply scattered fluence of light whose first scattering is known: `emission[x]` is
    /// the power node x scatters per cell volume (albedo × collision density, e.g. σs·Tr_sun·E of
    /// a sun at E = 1). Returns the fluence per node of light scattered once or more — that first
    /// scattering included, as it leaves its cell. Non-negative wherever the emission is. The
    /// links do not depend on the light, so one lattice solves every sun of a render. Also
    /// returns how many times the solve swept every direction (a generation each).
    pub fn solve_emission(&self, emission: &[f32]) -> (Vec<f32>, usize) {
        let links = &self.links;
        let (n, d) = (links.sweeps[0].links.len(), links.sweeps.len());
        let reflecting = links.reflecting_cells as f64 / n.max(1) as f64;
        if sun_krylov_bytes(n as u64, d, reflecting).is_some() {
            return solve_krylov(links, self.medium.albedo, emission);
        }
        // The energy criterion weighs what remains against the total: the first scattering
        // stands for the "single" part here.
        let first = Source {
            energy_single: emission.iter().map(|&e| e as f64).sum(),
            convergence: self.convergence,
            bands: 1,
            medium: self.medium,
        };
        let (fluence, stats) =
            transport_chunk::<f32>(links, &first, Drive::Emission(emission), None);
        (fluence, stats.generations)
    }
}

/// Basis vectors a sun's GMRES solve keeps before it restarts. Measured on the fixture cloud's
/// suns' lattice (223 749 voxel nodes, the README's default render) at albedo 0.99 / 1: 39 / 95
/// applications of a generation at 8, 34 / 74 at 12, 33 / 58 at 20, 31 / 56 at 40.
pub(crate) const RESTART: usize = 20;
/// Relative residual at which a sun's GMRES solve stops. Against solves to 1e-6, the fixture
/// cloud's default render (640×360) at albedo 0.9 / 0.99 / 1 is 0.00 / 0.00 / 0.00 % off at 1e-4
/// (13 / 33 / 58 applications) and 0.00 / 0.01 / 0.04 % at 1e-3, as the generations stopped by
/// [`CONVERGENCE`] are (23 generations at 0.9).
const KRYLOV_TOLERANCE: f64 = 1e-4;

/// A sun's fluence by GMRES ([`crate::math::krylov`]): the total emission X of every generation
/// solves X = A·X + Q, A one generation (what a node's emission and a reflecting cell's waiting
/// light make of the next); the fluence is then what one more sweep reads of X. The generations'
/// sum converges as A's largest eigenvalue, near 1 in a bright medium of thin cells, and GMRES
/// takes a fraction of the sweeps: on the fixture cloud's voxels 13 / 33 / 58 applications
/// against 23 / 183 / 797 generations at albedo 0.9 / 0.99 / 1.
/// X is held at 0 or above before it is read, as the exact one is, so F ≥ 0. Returns F and the
/// generations swept, the reading's included.
fn solve_krylov(links: &Links, albedo: f32, emission: &[f32]) -> (Vec<f32>, usize) {
    let n = links.sweeps[0].links.len();
    let mut state = State::new(vec![0f32; n * NODE_ROWS], links);
    let mut b = vec![0f32; n + state.reflected.len()];
    b[..n].copy_from_slice(emission);
    let (mut total, solved) = crate::math::krylov::solve_fixed_point(
        &b,
        RESTART,
        KRYLOV_TOLERANCE,
        MAX_GENERATIONS,
        |v, out| {
            load(&mut state, v);
            sweep_generation::<f32, false>(links, &mut state, albedo, 0, |_| 0.0);
            // The next generation's emission, and the light still waiting to leave.
            let (emission, waiting) = out.split_at_mut(n);
            for (o, node) in emission.iter_mut().zip(state.nodes.chunks_exact(NODE_ROWS)) {
                *o = node[state.emitting];
            }
            waiting.copy_from_slice(&state.reflected);
        },
    );
    total.iter_mut().for_each(|x| *x = x.max(0.0));
    // The reading: one more generation from X, its fluence alone kept.
    load(&mut state, &total);
    state
        .nodes
        .chunks_exact_mut(NODE_ROWS)
        .for_each(|node| node[FLUENCE] = 0.0);
    sweep_generation::<f32, false>(links, &mut state, albedo, 0, |_| 0.0);
    let fluence = state
        .nodes
        .chunks_exact(NODE_ROWS)
        .map(|node| node[FLUENCE])
        .collect();
    (fluence, solved.applications + 1)
}

/// Makes `v` the state a scalar generation starts from: per node the emission, then per
/// reflecting cell and pair of directions the light waiting to leave.
fn load(state: &mut State<f32>, v: &[f32]) {
    let (emission, waiting) = v.split_at(state.nodes.len() / NODE_ROWS);
    for (node, &e) in state.nodes.chunks_exact_mut(NODE_ROWS).zip(emission) {
        node[state.emitting] = e;
    }
    state.reflected.copy_from_slice(waiting);
}

#[cfg(test)]
mod tests;
