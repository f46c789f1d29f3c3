//! The ray march ([docs/model.md](../../docs/model.md), "Pixel radiance"): camera rays through the density, front to back,
//! L = Σ Tr·albedo·(1 − e^{−σt Δ})·Ls + Tr·E(ray direction), with empty-space skipping by the
//! hierarchical DDA, early termination, and image tiles in parallel.
//!
//! **Step lattice.** Step k sits at t_k = t_entry + (k + ξ)·Δ, where t_entry is the ray's entry
//! into the trilinear support of the density (the active box widened by one voxel), ξ ∈ [0, 1) a
//! per-sample hash jitter and Δ a fixed world length. The DDA's spans only *select* which k are
//! evaluated; the positions never depend on the skipping, and every skipped step has density exactly
//! 0 (see `volume::dda` on dilation). So a skipping march equals a plain march over the box, which
//! a test checks bit for bit.
//!
//! **One step.** Density is taken at the step's midpoint and held over its length Δ, so the step's
//! transmittance is exactly e^{−σt Δ} and the in-scatter integral ∫₀^Δ e^{−σt s} σs Ls ds is exactly
//! albedo·(1 − e^{−σt Δ})·Ls, weighted by the transmittance Tr in front of the step. With or
//! without suns a ray's transmittance is the same; a sun's light, which can fall by e^{−τ} within
//! a thick step, is summed over sub-steps ([`SunRadiance`]).
//!
//! **Surface entries.** One sample per step places a thick medium's face anywhere within a step:
//! the face's one-voxel density ramp is missed by the step whose midpoint is still outside it and
//! held over the whole of the next, so a pixel's light jumps with the jitter. The first step that
//! finds density after one that found none (or that the DDA skipped: density 0) is therefore
//! marched again with that empty step, in [`ENTRY_SUBSTEPS`] pieces that each hold their own
//! midpoint's density. The empty step added nothing, so nothing counts twice, and which steps
//! are entries depends on the densities alone, so a skipping march still equals a plain one.
//!
//! Units: the ray is parametrised by *world* distance t (the index-space direction is the world
//! direction divided by the voxel scale per axis), so σt = sigma_t·ρ per world unit multiplies a
//! world length Δ — anisotropic voxels included.

use std::ops::ControlFlow;

use glam::{DVec3, IVec3, Vec3};
use indicatif::ProgressBar;

use crate::math::floor::ceil;
use crate::math::hash::hash_unit;
use crate::render::camera::{Camera, STREAM_STEP};
use crate::render::film::{self, Background, RayResult};
use crate::render::relight::Radiance;
use crate::transfer::basis::{window_index, window_row, MAX_EDGE, WINDOW};
use crate::transfer::{Basis, Medium, TransferLayout, PHASE};
use crate::volume::bricks::BrickSampler;
use crate::volume::shadow::{ShadowCursor, ShadowVolume};
use crate::volume::visibility::{Visibility, VisibilitySampler};
use crate::volume::DensityField;

/// Stop marching when less than this fraction of the background still shows through. The rest of
/// the ray (its in-scatter and the background it would dim further) is replaced by Tr·E: exact in
/// a white furnace, and otherwise off by at most 0.1 % of the brighter of Ls and E.
pub const TERMINATION_TRANSMITTANCE: f32 = 1e-3;
/// Default step length in voxels (of the smallest voxel edge), as `vdb_render`'s primary step.
/// Measured against 0.25-voxel steps at 960×540 on the cloud and cloud_large caches (σt 1.6): the
/// mean pixel error is 0.24–0.34 % (a −0.1 to −0.3 % bias; 0.05–0.07 % at 0.5 voxel), below 1 % on
/// 95 % of the cloud's pixels, with no visible banding (the per-pixel jitter turns it into noise);
/// the albedo-0 chord error is 1.5e-3 (3.8e-4 at 0.5) and the white furnace through the whole
/// chain is unchanged (2.75 %). Half the steps of 0.5 voxel, at half the march's cost.
pub const DEFAULT_STEP_VOXELS: f32 = 1.0;

/// Pieces a surface entry is marched in (module doc, "Surface entries"): the step that first
/// finds density after an empty one, and that empty one, in pieces of half a step. Measured on the
/// torus fixture under one sun at one optical depth per voxel, one sample per pixel (256×144,
/// single scattering, against 8192-sample path-traced references): 5.54 % relative RMSE, 82.1 %
/// of the lit pixels within 10 %, with one sample per step; 4.26 % and 92.5 % with these four
/// pieces (eight: 4.21 %; every step halved instead: 3.84 % and 94.9 %, for twice the march).
const ENTRY_SUBSTEPS: usize = 4;

/// Most optical depth a sun's light is held over: across a thicker step it falls by e^{−τ_sun}
/// as the camera's does, and the step's share of it is summed over sub-steps of depth
/// ≤ ~MAX_STEP_DEPTH ([`SunRadiance`]). At 0.25 the in-scatter of a uniform slab lit from behind
/// the camera is within 0.5 % of exact (1 − τ²/12 relative), where a whole step of depth 2 would
/// be 30 % off.
const MAX_STEP_DEPTH: f32 = 0.25;
/// Most sub-steps of one step: at 64 a step of optical depth 16 is still split to 0.25, and
/// anything thicker is opaque within one step anyway.
const MAX_SUBSTEPS: usize = 64;
/// Tr·e^{−τ_sun} at a thick step's midpoint below which the step is not split: what splitting
/// moves is a part of the step's sun light, and below this that light is under 0.3 % of a
/// sunlit step's in front of the camera. Measured on the one-sun fixtures of
/// [docs/accuracy.md](../../docs/accuracy.md#suns) (torus and cloud, 0.5 and 1 optical depth per
/// voxel, 64 samples per pixel): relative RMSE within 0.03 points of splitting every thick step
/// (the torus at 1: 2.56 against 2.53 %), where a threshold of 0.03 gave 2.82 %; the bench
/// cloud's sun march (1920×1080) takes 1.23–1.25 s against 1.67–1.77 s.
const SPLIT_ABOVE: f32 = 0.003;
/// Bend of a split step's sun depth, |τ(start) + τ(end) − 2·τ(middle)|, past which each of its
/// sub-steps reads the depth itself instead of the parabola through the three ([`Split`]): where
/// the depth turns within one step (a shadow's edge crossing it, a surface the light grazes) no
/// parabola follows it. Measured on the one-sun fixtures of
/// [docs/accuracy.md](../../docs/accuracy.md#suns) (64 samples per pixel against 8192-sample
/// references): the torus at σt 1 had 98.7 % of its lit pixels within 10 % with the parabola
/// everywhere, 99.1 % with a lookup per sub-step everywhere, 99.0 % past a bend of 0.25 (98.9 %
/// past 1); the sun's march of the fixture cloud (the bench cloud, 1920×1080) took medians of
/// 0.94 (2.12) s, 1.39 (2.77) s and 0.92 (2.27) s (five alternating runs): a lookup per sub-step
/// where the depth bends, at the parabola's speed.
const MAX_BEND: f32 = 0.25;

/// One step of the march as a source sees it: where it is and the medium in front of it and in
/// it. Density is held over the step (its midpoint's), so a source constant over it adds
/// `weight()`·Ls.
#[derive(Debug, Clone, Copy)]
pub struct Step {
    /// Its midpoint, in density index space.
    pub p: Vec3,
    /// The step from its start to its end (index space).
    pub span: Vec3,
    /// The density at `p`.
    pub rho: f32,
    /// Tr, the transmittance in front of the step.
    pub front: f32,
    /// albedo·Tr.
    pub scatter: f32,
    /// Its optical depth τ = σt·ρ·Δ.
    pub tau: f32,
    /// e^{−τ}.
    pub tr: f32,
}

impl Step {
    /// albedo·Tr·(1 − e^{−τ}): what a source constant over the step is weighted by.
    #[inline]
    pub fn weight(&self) -> f32 {
        self.scatter * (1.0 - self.tr)
    }
}

/// The in-scattered radiance Ls of the medium, summed along a ray: the march needs only
/// Σ_k ∫_step Tr·σs·Ls over its steps, never Ls at one point, and an interpolated source can sum
/// its interpolation weights per cell and read its node data once per cell instead of once per
/// step.
pub trait InScatter: Sync {
    /// A ray's running sum, kept by one thread from ray to ray ([`RayScratch`]): what it caches
    /// (the last cell, the last shadow brick) stays valid across rays.
    type Sum;
    /// An empty sum.
    fn begin(&self) -> Self::Sum;
    /// Adds one step's in-scattered light; `sampler` reads the density.
    fn add(&self, step: &Step, sum: &mut Self::Sum, sampler: &mut BrickSampler);
    /// The ray's light, ([direct RGB], [indirect RGB]); leaves `sum` empty for the next ray.
    fn total(&self, sum: &mut Self::Sum) -> [[f32; 3]; 2];
}

/// Two sources lit together (the environment's transfer and the suns): their sums side by side.
impl<A: InScatter, B: InScatter> InScatter for (A, B) {
    type Sum = (A::Sum, B::Sum);

    fn begin(&self) -> Self::Sum {
        (self.0.begin(), self.1.begin())
    }

    #[inline]
    fn add(&self, step: &Step, sum: &mut Self::Sum, sampler: &mut BrickSampler) {
        self.0.add(step, &mut sum.0, sampler);
        self.1.add(step, &mut sum.1, sampler);
    }

    fn total(&self, sum: &mut Self::Sum) -> [[f32; 3]; 2] {
        let (a, b) = (self.0.total(&mut sum.0), self.1.total(&mut sum.1));
        std::array::from_fn(|part| std::array::from_fn(|ch| a[part][ch] + b[part][ch]))
    }
}

/// The suns' light. Single scattering, exact at the density's resolution (thesis 7.1):
/// Ls(p) = Σ_suns p·E·e^{−τ_sun(p)}, τ_sun read from each sun's [`ShadowVolume`], the `direct`
/// layer. A step reads each sun's depth at its midpoint; a thick one ([`MAX_STEP_DEPTH`]) that
/// the sun lights ([`SPLIT_ABOVE`]) is summed over sub-steps ([`Split`]). Multiple scattering,
/// the `indirect` layer: p·Σ_suns F·E at the nodes of the suns' lattice
/// ([`crate::render::sunlight`]), interpolated trilinearly and summed per cell as the transfer's
/// light is ([`TransferRadiance`]).
pub struct SunRadiance<'a> {
    /// Each sun's shadow and its p·E per channel.
    suns: Vec<(&'a ShadowVolume, [f32; 3])>,
    multiple: Option<SunNodes<'a>>,
}

/// The suns' multiply scattered radiance at the nodes of their lattice: RGB per slot, and a last
/// all-zero record that missing nodes point at. Point values, read trilinearly.
struct SunNodes<'a> {
    inv_k: f32,
    layout: &'a TransferLayout,
    nodes: &'a [[f32; 3]],
}

/// The basis the suns' lattice is read with: its nodes hold point values.
const SUN_BASIS: Basis = Basis::Tent;
const SUN_EDGE: usize = SUN_BASIS.edge();

impl<'a> SunRadiance<'a> {
    /// `multiple`: the suns' lattice and its nodes' radiance, one record more than it has nodes
    /// (`None`: single scattering only).
    pub fn new(
        suns: impl IntoIterator<Item = (&'a ShadowVolume, [f32; 3])>,
        multiple: Option<(&'a TransferLayout, &'a [[f32; 3]])>,
    ) -> Self {
        SunRadiance {
            suns: suns
                .into_iter()
                .map(|(v, e)| (v, e.map(|e| e * PHASE)))
                .collect(),
            multiple: multiple.map(|(layout, nodes)| SunNodes {
                inv_k: 1.0 / layout.k as f32,
                layout,
                nodes,
            }),
        }
    }

    /// Moves the weights gathered in the current window of the suns' lattice into the sum.
    fn flush(&self, sum: &mut SunSum) {
        if let Some(m) = &self.multiple {
            let [indirect] = &mut sum.indirect;
            sum.window.flush::<SUN_EDGE, 3, 1>(m.nodes, [(0, indirect)]);
        }
    }
}

/// A ray's sum for [`SunRadiance`]: one shadow cursor per sun and the direct RGB so far; the
/// window of the suns' lattice with its steps' weights, and the indirect RGB so far.
pub struct SunSum {
    tracks: Vec<SunTrack>,
    direct: [f32; 3],
    window: Window<1>,
    indirect: [[f32; 3]; 1],
}

/// What a ray keeps per sun: its shadow cursor, and the depth read at the end of its last split
/// step, which the next step starts from when the two steps meet.
#[derive(Clone, Default)]
pub struct SunTrack {
    cursor: ShadowCursor,
    last_end: Option<(Vec3, f32)>,
}

/// Squared distance (index space) within which two points are the same step boundary.
const SAME_POINT: f32 = 1e-6;

impl InScatter for SunRadiance<'_> {
    type Sum = SunSum;

    fn begin(&self) -> SunSum {
        SunSum {
            tracks: vec![SunTrack::default(); self.suns.len()],
            direct: [0.0; 3],
            window: Window::default(),
            indirect: [[0.0; 3]],
        }
    }

    #[inline]
    fn add(&self, step: &Step, sum: &mut SunSum, sampler: &mut BrickSampler) {
        for ((volume, e), track) in self.suns.iter().zip(&mut sum.tracks) {
            let depth = volume.optical_depth(step.p, step.front, sampler, &mut track.cursor);
            let light = (-depth).exp();
            let w = if step.tau > MAX_STEP_DEPTH && step.scatter * light >= SPLIT_ABOVE {
                let split = Split {
                    step,
                    volume,
                    middle: depth,
                };
                split.light(sampler, track)
            } else {
                step.weight() * light
            };
            for (d, e) in sum.direct.iter_mut().zip(e) {
                *d += w * e;
            }
        }
        if let Some(m) = &self.multiple {
            let (b, axes) = SUN_BASIS.window(step.p * m.inv_k);
            if sum.window.base != Some(b) {
                self.flush(sum);
                sum.window
                    .enter(m.layout, b, SUN_EDGE, (m.nodes.len() - 1) as u32);
            }
            sum.window.add::<SUN_EDGE, 1>(&axes, [step.weight()]);
        }
    }

    #[inline]
    fn total(&self, sum: &mut SunSum) -> [[f32; 3]; 2] {
        self.flush(sum);
        for track in &mut sum.tracks {
            track.last_end = None;
            track.cursor.end_ray();
        }
        let [indirect] = std::mem::take(&mut sum.indirect);
        [std::mem::take(&mut sum.direct), indirect]
    }
}

/// A thick, sunlit step split for one sun ([`MAX_STEP_DEPTH`]). The march holds the midpoint's
/// density over the whole step, so its transmittance, and every other source's light, are those
/// of a render without suns; within the step, the sub-steps' own densities only share out its
/// optical depth τ. The sun's depth is looked up at the step's ends as well as its midpoint and
/// taken between them along the parabola through the three ([`sun_depth_along`]): a lookup walks
/// the shadow volume toward the light, and one per sub-step cost a sunlit render 10–17 % more
/// march time (the fixture cloud under the built-in sky, σt 1.6–8 per voxel) for images within
/// 0.1–0.5 % of these. Where the three bend past [`MAX_BEND`] each sub-step is looked up after
/// all. Split steps come in runs (a sunlit face a few steps deep), and a step that starts where
/// the ray's last split step ended takes that end's depth instead of looking it up again
/// ([`SunTrack`]).
struct Split<'s> {
    step: &'s Step,
    volume: &'s ShadowVolume,
    /// The sun's depth at the step's midpoint, already read.
    middle: f32,
}

impl Split<'_> {
    /// albedo·Tr·Σ_j e^{−τ_<j}·(1 − e^{−τ_j})·e^{−τ_sun(s_j)}, with τ_j = τ·ρ_j/Σρ and s_j the
    /// sub-step's midpoint: the step's sun light, which at a constant e^{−τ_sun} is
    /// `weight()`·e^{−τ_sun} exactly.
    // Out of line: the step loop, which most steps take without it, keeps its registers.
    #[inline(never)]
    fn light(&self, sampler: &mut BrickSampler, track: &mut SunTrack) -> f32 {
        let step = self.step;
        let n = ((step.tau / MAX_STEP_DEPTH).ceil() as usize).min(MAX_SUBSTEPS);
        let at = |s: f32| step.p + step.span * (s - 0.5);
        let mid = |j: usize| (j as f32 + 0.5) / n as f32;
        let mut rho = [0f32; MAX_SUBSTEPS];
        for (j, r) in rho[..n].iter_mut().enumerate() {
            *r = sampler.sample(at(mid(j)));
        }
        let total: f32 = rho[..n].iter().sum();
        if total <= 0.0 {
            return step.weight() * (-self.middle).exp();
        }
        let previous = track.last_end.take();
        let mut depth_at = |s: f32| {
            self.volume
                .optical_depth(at(s), step.front, sampler, &mut track.cursor)
        };
        let start = match previous {
            Some((q, depth)) if (q - at(0.0)).length_squared() < SAME_POINT => depth,
            _ => depth_at(0.0),
        };
        let end = depth_at(1.0);
        let end_at = at(1.0);
        let along = sun_depth_along(start, self.middle, end);
        let bends = (start + end - 2.0 * self.middle).abs() > MAX_BEND;
        let per_density = step.tau / total;
        let (mut tr, mut sum) = (1.0f32, 0.0f32);
        for (j, &r) in rho[..n].iter().enumerate() {
            if r <= 0.0 {
                continue;
            }
            let depth = match bends {
                true => depth_at(mid(j)),
                false => along(mid(j)),
            };
            let sub_tr = (-r * per_density).exp();
            sum += tr * (1.0 - sub_tr) * (-depth).exp();
            tr *= sub_tr;
        }
        track.last_end = Some((end_at, end));
        step.scatter * sum
    }
}

/// The sun's depth at s ∈ [0, 1] along a step whose start, midpoint and end read `start`,
/// `middle` and `end`: the parabola through the three, which follows the quadratic growth of the
/// depth into a lit surface's one-voxel density ramp, held within the three values' range so it
/// never overshoots where the depth turns sharply (a shadow's edge).
fn sun_depth_along(start: f32, middle: f32, end: f32) -> impl Fn(f32) -> f32 {
    let slope = 4.0 * middle - 3.0 * start - end;
    let curve = 2.0 * (start + end) - 4.0 * middle;
    let lo = start.min(middle).min(end);
    let hi = start.max(middle).max(end);
    move |s| (start + s * (slope + s * curve)).clamp(lo, hi)
}

/// The window of nodes around a ray's last step ([`Basis::window`]), their record slots, and per
/// layer the Σ c·w of its steps there per node. A ray takes about K steps per window, so the
/// layout's lookup and the products with node data are paid once per window crossed; a step
/// adds only its weights.
struct Window<const L: usize> {
    base: Option<IVec3>,
    /// Where in `recent` the current window's slots are.
    current: usize,
    /// The windows entered lately, by a hash of their lowest node: the next ray, next to this
    /// one, crosses the same windows, and finds their slots here instead of in the layout.
    recent: [(Option<IVec3>, Option<[u32; WINDOW]>); RECENT_WINDOWS],
    sums: [[f32; WINDOW]; L],
    /// Whether a step has added to `sums` since they were last flushed: most rays end, and many
    /// cross a window, without adding anything there, and flush nothing.
    weighted: bool,
}

/// Windows a ray's sum remembers ([`Window::recent`]): a ray crosses a few, its neighbours the
/// same ones.
const RECENT_WINDOWS: usize = 32;

impl<const L: usize> Default for Window<L> {
    fn default() -> Self {
        Window {
            base: None,
            current: 0,
            recent: [(None, None); RECENT_WINDOWS],
            sums: [[0.0; WINDOW]; L],
            weighted: false,
        }
    }
}

impl<const L: usize> Window<L> {
    /// Moves to the window whose lowest node is `base` of `layout`, `edge` nodes wide
    /// (`missing`: the record its absent nodes point at).
    #[inline]
    fn enter(&mut self, layout: &TransferLayout, base: IVec3, edge: usize, missing: u32) {
        self.base = Some(base);
        let key = base.as_uvec3() * glam::UVec3::new(0x9E37_79B1, 0x85EB_CA77, 0xC2B2_AE3D);
        self.current = ((key.x ^ key.y ^ key.z) >> 27) as usize % RECENT_WINDOWS;
        let entry = &mut self.recent[self.current];
        if entry.0 != Some(base) {
            *entry = (Some(base), layout.window(base, edge, missing));
        }
    }

    /// The current window's slots (`None`: none of its nodes exists).
    #[inline(always)]
    fn slots(&self) -> Option<&[u32; WINDOW]> {
        self.recent[self.current].1.as_ref()
    }

    /// Adds a step's weight per node, from its weights per axis `axes` ([`Basis::window`]) for
    /// a basis `E` nodes wide, times `c[l]` to layer l (the first `A` layers).
    #[inline(always)]
    fn add<const E: usize, const A: usize>(&mut self, axes: &[Vec3; MAX_EDGE], c: [f32; A]) {
        // The y–z plane's weights once (padded with zeros to whole lanes), then the plane times
        // each x's weight: straight runs of four products.
        let row = window_row(E);
        self.weighted = true;
        let mut yz = [0.0; window_row(MAX_EDGE)];
        for y in 0..E {
            for z in 0..E {
                yz[y * E + z] = axes[y].y * axes[z].z;
            }
        }
        for (sums, c) in self.sums.iter_mut().zip(c) {
            for x in 0..E {
                let cx = c * axes[x].x;
                for (s, w) in sums[x * row..][..row].iter_mut().zip(&yz[..row]) {
                    *s += cx * w;
                }
            }
        }
    }

    /// Σ_n w_n·value(slot_n) at a step with weights per axis `axes`, for a basis `E` nodes wide.
    #[inline(always)]
    fn read<const E: usize>(&self, axes: &[Vec3; MAX_EDGE], value: impl Fn(u32) -> f32) -> f32 {
        let Some(slots) = self.slots() else {
            return 0.0;
        };
        let mut sum = 0.0;
        for x in 0..E {
            for y in 0..E {
                let wxy = axes[x].x * axes[y].y;
                for z in 0..E {
                    sum += wxy * axes[z].z * value(slots[window_index(E, x, y, z)]);
                }
            }
        }
        sum
    }

    /// For each output (layer l, sum), adds Σ_n (Σ c·w)_n of layer l times node n's record,
    /// for a basis `E` nodes wide; then empties the sums.
    #[inline(always)]
    fn flush<const E: usize, const N: usize, const M: usize>(
        &mut self,
        nodes: &[[f32; N]],
        outputs: [(usize, &mut [f32; N]); M],
    ) {
        if !std::mem::take(&mut self.weighted) {
            return;
        }
        let row = window_row(E);
        if let Some(slots) = self.slots() {
            for (layer, out) in outputs {
                // Summed apart from `out`, which the compiler cannot tell from the sums: kept in
                // registers, not stored back node after node.
                let mut total = [0.0; N];
                for x in 0..E {
                    let plane = x * row..x * row + E * E;
                    for (slot, s) in slots[plane.clone()].iter().zip(&self.sums[layer][plane]) {
                        for (t, v) in total.iter_mut().zip(&nodes[*slot as usize]) {
                            *t += s * v;
                        }
                    }
                }
                for (o, t) in out.iter_mut().zip(total) {
                    *o += t;
                }
            }
        }
        for sums in &mut self.sums {
            sums[..E * row].fill(0.0);
        }
    }
}

/// Ls read from the per-transfer-voxel radiance of [`crate::render::relight`] with the
/// transfer's [`Basis`]: trilinear, or, for a transfer baked finer, the quadratic B-spline.
///
/// Direct light included: T_ri falls off exponentially into the medium and a straight line
/// between two nodes lies above it, but the stored T_ri is not the nodes' point value — it is
/// fitted so that exactly this read-out matches T_ri where the density is
/// ([`crate::transfer::fit`]). Within a transfer voxel a trilinear fit can only follow a straight
/// line; with the density's [`Visibility`] the direct light takes the shape of its fall from V:
/// Ls_direct(p)·V(p)/V̂(p), V̂ the read-out of V's own fitted node values, so a transfer that is V
/// times a smooth field is reproduced at the density's resolution.
pub struct TransferRadiance<'a> {
    inv_k: f32,
    basis: Basis,
    /// Per slot, direct and indirect RGB, and a last all-zero record that missing nodes point
    /// at, so a node needs no test ([`Radiance`]).
    nodes: &'a [[f32; 6]],
    /// Where each transfer voxel's record is: a ray entering a window finds its nodes' records
    /// there ([`TransferLayout::window`]).
    layout: &'a TransferLayout,
    /// The all-zero record missing nodes point at.
    missing: u32,
    shaping: Option<Shaping<'a>>,
}

/// What shapes the direct light: the density's V with its fitted value per slot
/// ([`crate::transfer::shape`]).
#[derive(Clone, Copy)]
pub struct Shaping<'a> {
    pub visibility: &'a Visibility,
    pub fitted: &'a [f32],
}

/// Smallest interpolated V the direct light is reshaped by: below it the node values are too
/// dark for their ratio to mean anything.
const MIN_FITTED_VISIBILITY: f32 = 1e-4;
/// Largest factor V/V̂ takes: where the fit of V dips far below the fine V (its ringing at a
/// thin wisp's edge) the ratio must not blow the node light up.
const MAX_VISIBILITY_RATIO: f32 = 4.0;

impl<'a> TransferRadiance<'a> {
    /// `basis`: how the nodes are read ([`crate::transfer::Transfer::basis`]); `shaping`: what
    /// shapes the direct light (`None`: plain read-out).
    pub fn new(
        layout: &'a TransferLayout,
        basis: Basis,
        radiance: &'a Radiance,
        shaping: Option<Shaping<'a>>,
    ) -> Self {
        TransferRadiance {
            inv_k: 1.0 / layout.k as f32,
            basis,
            nodes: &radiance.nodes,
            layout,
            missing: radiance.len() as u32,
            shaping,
        }
    }

    /// Moves the weights gathered in the current window into the radiance sum. Unshaped, the
    /// direct and indirect light share one layer of weights ([`WindowSum`]).
    #[inline(always)]
    fn flush<const E: usize>(&self, sum: &mut WindowSum) {
        match self.shaping {
            None => sum
                .window
                .flush::<E, 6, 1>(self.nodes, [(0, &mut sum.radiance)]),
            Some(_) => {
                // Each layer's weights times whole records; the direct part of the one, the
                // indirect part of the other.
                let (mut direct, mut indirect) = ([0.0; 6], [0.0; 6]);
                sum.window
                    .flush::<E, 6, 2>(self.nodes, [(1, &mut direct), (0, &mut indirect)]);
                for c in 0..3 {
                    sum.radiance[c] += direct[c];
                    sum.radiance[c + 3] += indirect[c + 3];
                }
            }
        }
    }

    /// [`InScatter::add`] for a basis `E` nodes wide.
    #[inline]
    fn add_in<const E: usize>(&self, step: &Step, sum: &mut WindowSum<'a>) {
        let (p, c) = (step.p, step.weight());
        let (b, axes) = self.basis.window(p * self.inv_k);
        if sum.window.base != Some(b) {
            self.flush::<E>(sum);
            sum.window.enter(self.layout, b, E, self.missing);
        }
        let mut cd = c;
        if let (Some(sampler), Some(shaping)) = (sum.visibility.as_mut(), self.shaping) {
            // The missing node's V is 0, as its light.
            let fitted = sum.window.read::<E>(&axes, |slot| {
                shaping.fitted.get(slot as usize).copied().unwrap_or(0.0)
            });
            if fitted > MIN_FITTED_VISIBILITY {
                if let Some(fine) = sampler.at(p, step.rho) {
                    cd *= (fine / fitted).clamp(0.0, MAX_VISIBILITY_RATIO);
                }
            }
        }
        match self.shaping {
            Some(_) => sum.window.add::<E, 2>(&axes, [c, cd]),
            None => sum.window.add::<E, 1>(&axes, [c]),
        }
    }
}

const TENT: usize = Basis::Tent.edge();
const QUADRATIC: usize = Basis::Quadratic.edge();

/// A ray's sum for [`TransferRadiance`]: the window of nodes around the last step with its
/// steps' weights, for the indirect light (layer 0) and, where V shapes it, the direct light
/// (layer 1); unshaped, the direct light is weighted as the indirect.
pub struct WindowSum<'a> {
    window: Window<2>,
    /// Direct, then indirect RGB.
    radiance: [f32; 6],
    visibility: Option<VisibilitySampler<'a>>,
}

impl<'a> InScatter for TransferRadiance<'a> {
    type Sum = WindowSum<'a>;

    fn begin(&self) -> WindowSum<'a> {
        WindowSum {
            window: Window::default(),
            radiance: [0.0; 6],
            visibility: self.shaping.map(|s| s.visibility.sampler()),
        }
    }

    #[inline]
    fn add(&self, step: &Step, sum: &mut WindowSum<'a>, _: &mut BrickSampler) {
        match self.basis {
            Basis::Tent => self.add_in::<TENT>(step, sum),
            Basis::Quadratic => self.add_in::<QUADRATIC>(step, sum),
        }
    }

    fn total(&self, sum: &mut WindowSum<'a>) -> [[f32; 3]; 2] {
        match self.basis {
            Basis::Tent => self.flush::<TENT>(sum),
            Basis::Quadratic => self.flush::<QUADRATIC>(sum),
        }
        let r = std::mem::take(&mut sum.radiance);
        [[r[0], r[1], r[2]], [r[3], r[4], r[5]]]
    }
}

/// Everything a ray meets.
pub struct Scene<'a, S: InScatter> {
    pub field: &'a DensityField,
    pub medium: Medium,
    pub source: &'a S,
    /// `None` renders the volume alone (`--no-background`): RGB premultiplied, alpha = 1 − Tr.
    pub background: Option<Background<'a>>,
    /// The trilinear support of the density in index space, `None` when nothing is active.
    support: Option<(DVec3, DVec3)>,
}

impl<'a, S: InScatter> Scene<'a, S> {
    pub fn new(
        field: &'a DensityField,
        medium: Medium,
        source: &'a S,
        background: Option<Background<'a>>,
    ) -> Self {
        // Trilinear density reaches one voxel beyond the outermost active voxel, and no further.
        let support = field
            .grid
            .active_bbox()
            .map(|(lo, hi)| (lo.as_dvec3() - 1.0, hi.as_dvec3() + 1.0));
        Scene {
            field,
            medium,
            source,
            background,
            support,
        }
    }
}

/// How to march.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MarchSettings {
    /// Samples per pixel (box filter), at least 1.
    pub spp: u32,
    /// Step length in units of the smallest voxel edge.
    pub step_voxels: f32,
    /// Evaluate only steps inside DDA spans (`false`: every step of the support box, for tests).
    pub skip_empty: bool,
}

impl Default for MarchSettings {
    fn default() -> Self {
        MarchSettings {
            spp: 1,
            step_voxels: DEFAULT_STEP_VOXELS,
            skip_empty: true,
        }
    }
}

/// Counts for `--stats`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct MarchStats {
    pub rays: u64,
    /// Steps whose density was looked up.
    pub samples_taken: u64,
    /// Lattice steps the DDA proved empty (before termination).
    pub samples_skipped: u64,
}

impl std::ops::AddAssign for MarchStats {
    fn add_assign(&mut self, o: MarchStats) {
        self.rays += o.rays;
        self.samples_taken += o.samples_taken;
        self.samples_skipped += o.samples_skipped;
    }
}

/// What one thread keeps from ray to ray: its density sampler and its source's sum, whose caches
/// (the last block, brick and cell) stay valid across rays, so a ray neither builds nor copies
/// them: built per ray, their copies alone were 3 % of a render's instructions.
pub struct RayScratch<'a, S: InScatter> {
    sampler: BrickSampler<'a>,
    sum: S::Sum,
}

impl<'a, S: InScatter> Scene<'a, S> {
    /// A thread's [`RayScratch`] for marching this scene.
    pub fn scratch(&self) -> RayScratch<'a, S> {
        RayScratch {
            sampler: self.field.sampler(),
            sum: self.source.begin(),
        }
    }
}

/// What a ray carries through the march.
struct RayState {
    tr: f32,
    depth_sum: f64,
    weight_sum: f64,
}

/// A stretch of a ray the march holds one density over: its midpoint `p` (index space) at `t`
/// from the ray's entry, its density there, its index-space `span` and world `length`.
struct Piece {
    p: Vec3,
    t: f32,
    rho: f32,
    span: Vec3,
    length: f32,
}

impl RayState {
    /// Adds `piece`'s light to `sum` and its transmittance to the ray; `true` once the ray is
    /// spent ([`TERMINATION_TRANSMITTANCE`]).
    #[inline(always)]
    fn take<S: InScatter>(
        &mut self,
        scene: &Scene<S>,
        piece: Piece,
        sum: &mut S::Sum,
        sampler: &mut BrickSampler,
    ) -> bool {
        let Medium { sigma_t, albedo } = scene.medium;
        let tau = sigma_t * piece.rho * piece.length;
        // One exp: glibc's expf costs about a third of expm1f (measured: 10 % of the render's
        // CPU time). The opacity 1 − e^{−τ} loses relative precision only for τ ≲ 1e-4, where
        // the step adds almost nothing, and Tr still telescopes.
        let step_tr = (-tau).exp();
        if albedo > 0.0 {
            let step = Step {
                p: piece.p,
                span: piece.span,
                rho: piece.rho,
                front: self.tr,
                scatter: self.tr * albedo,
                tau,
                tr: step_tr,
            };
            scene.source.add(&step, sum, sampler);
        }
        let w = (self.tr * (1.0 - step_tr)) as f64;
        self.depth_sum += piece.t as f64 * w;
        self.weight_sum += w;
        self.tr *= step_tr;
        self.tr < TERMINATION_TRANSMITTANCE
    }
}

/// Marches one world-space ray (`dir` unit length); `jitter` ∈ [0, 1) shifts the step lattice.
pub fn march_ray<S: InScatter>(
    scene: &Scene<S>,
    origin: Vec3,
    dir: Vec3,
    jitter: f32,
    settings: &MarchSettings,
    scratch: &mut RayScratch<S>,
    stats: &mut MarchStats,
) -> RayResult {
    let mut out = RayResult::CLEAR;
    stats.rays += 1;
    let Some((lo, hi)) = scene.support else {
        return out;
    };
    let xf = &scene.field.grid.transform;
    let ray = xf.ray_to_index(origin, dir);
    let (o, d) = (ray.origin, ray.dir);
    let Some((t_entry, t_exit)) = ray.clip(0.0, f64::INFINITY, lo, hi) else {
        return out;
    };
    let step = settings.step_voxels as f64 * xf.voxel_size().min_element();
    // A zero or non-finite step would make the lattice endless; such a march sees nothing.
    if !(step > 0.0 && step.is_finite()) {
        return out;
    }
    let jitter = jitter as f64;
    let step_f32 = step as f32;
    // First k whose t_k reaches `t`: t_entry + (k + ξ)·Δ ≥ t.
    let k_at = |t: f64| ceil((t - t_entry) / step - jitter).max(0) as u64;
    let k_end = k_at(t_exit);
    let entry = (o + d * t_entry).as_vec3();
    let d32 = d.as_vec3();
    let span = d32 * step_f32;
    let mut state = RayState {
        tr: 1.0,
        depth_sum: 0.0,
        weight_sum: 0.0,
    };
    let RayScratch { sampler, sum } = scratch;
    let mut next_k = 0u64;
    let mut taken = 0u64;
    let mut terminated_at: Option<u64> = None;
    // The last step that held density: a step after any other enters the medium.
    let mut filled: Option<u64> = None;
    let mut run = |t_a: f64, t_b: f64| -> ControlFlow<()> {
        let k_hi = k_at(t_b).min(k_end);
        let k_lo = k_at(t_a).max(next_k);
        // k as f64, counted in f64 (exact below 2^53): a u64 → f64 conversion per step costs
        // a dozen instructions on x86-64's baseline.
        let mut kf = k_lo as f64;
        // Position from the entry point in f32: exact enough (the DDA's dilation leaves a voxel
        // of slack) and the same arithmetic whether or not steps are skipped.
        let at = |kf: f64| {
            let s = ((kf + jitter) * step) as f32;
            (s, entry + d32 * s)
        };
        // Each step's density is read a step ahead, before the light of the one in front is
        // added: its loads then overlap that work instead of waiting on it. Measured on the bench
        // cloud (1920×1080, nine alternating runs), with the pieces of an entry read together
        // and `sample_positive`: march medians 0.412 s against 0.447 s, the same image.
        let (mut s_next, mut p_next) = at(kf);
        let mut rho_next = match k_lo < k_hi {
            true => sampler.sample_positive(p_next),
            false => 0.0,
        };
        for k in k_lo..k_hi {
            taken += 1;
            let (s, p, rho) = (s_next, p_next, rho_next);
            kf += 1.0;
            if k + 1 < k_hi {
                (s_next, p_next) = at(kf);
                rho_next = sampler.sample_positive(p_next);
            }
            if rho <= 0.0 {
                continue;
            }
            // A surface entry (module doc): this step and the empty one before it, from no
            // nearer than the ray's start, in ENTRY_SUBSTEPS pieces.
            let entering = filled != Some(k.wrapping_sub(1));
            filled = Some(k);
            let spent = match entering {
                false => {
                    let piece = Piece {
                        p,
                        t: s,
                        rho,
                        span,
                        length: step_f32,
                    };
                    state.take(scene, piece, sum, sampler)
                }
                true => {
                    let start = (s - 1.5 * step_f32).max(0.0);
                    let length = (s + 0.5 * step_f32 - start) / ENTRY_SUBSTEPS as f32;
                    // Every piece's density first: their loads overlap.
                    let pieces: [(f32, Vec3, f32); ENTRY_SUBSTEPS] = std::array::from_fn(|j| {
                        let t = start + (j as f32 + 0.5) * length;
                        let p = entry + d32 * t;
                        (t, p, sampler.sample_positive(p))
                    });
                    let span = d32 * length;
                    pieces.into_iter().any(|(t, p, rho)| {
                        let piece = Piece {
                            p,
                            t,
                            rho,
                            span,
                            length,
                        };
                        rho > 0.0 && state.take(scene, piece, sum, sampler)
                    })
                }
            };
            if spent {
                terminated_at = Some(k + 1);
                return ControlFlow::Break(());
            }
        }
        next_k = next_k.max(k_hi);
        ControlFlow::Continue(())
    };
    if settings.skip_empty {
        scene
            .field
            .occupancy
            .visit_spans(&ray, t_entry, t_exit, |s| run(s.t0, s.t1));
    } else {
        let _ = run(t_entry, t_exit);
    }
    let RayState {
        tr,
        depth_sum,
        weight_sum,
    } = state;
    [out.direct, out.indirect] = scene.source.total(sum);
    let reached = terminated_at.unwrap_or(k_end);
    stats.samples_taken += taken;
    stats.samples_skipped += reached.saturating_sub(taken);
    out.transmittance = tr;
    if weight_sum > 0.0 {
        out.depth = (t_entry + depth_sum / weight_sum) as f32;
    }
    out
}

/// Hands `consume` `camera`'s view of `scene` row by row ([`film::stream_rows`]): image tiles in
/// parallel, `settings.spp` jittered samples per pixel averaged with a box filter, `progress`
/// advanced by one per finished tile; returns what `consume` made, the statistics of the rows it
/// asked for and the march's time. Deterministic: every sample position comes from a hash of its
/// pixel and index, never from the thread that runs it or the band it is rendered in.
pub fn stream<S: InScatter, R>(
    scene: &Scene<S>,
    camera: &Camera,
    settings: &MarchSettings,
    progress: &ProgressBar,
    consume: impl FnOnce(&mut film::Rows) -> R,
) -> (R, MarchStats, std::time::Duration) {
    film::stream_rows(
        camera,
        settings.spp,
        scene.background,
        progress,
        || scene.scratch(),
        |sample, stats: &mut MarchStats, scratch| {
            let jitter = hash_unit(sample.x, sample.y, sample.index, STREAM_STEP);
            march_ray(
                scene,
                sample.origin,
                sample.dir,
                jitter,
                settings,
                scratch,
                stats,
            )
        },
        consume,
    )
}

#[cfg(test)]
mod tests;
