//! Thick transfer voxels baked finer: where a transfer voxel is more than
//! [`REFINE_CELL_DEPTH`] optical depths across, a multiple-scattering bake takes T_ri's point
//! values at the nodes of cells half as wide and runs the lattice over those cells, then fits
//! both back to the transfer's own nodes ([`super::fit::fitted_from_finer`]) as coefficients of
//! the quadratic B-spline ([`BASIS`]), which the march reads them with (docs/model.md, "Thick
//! cells, baked finer" and "Reading the nodes"). The relight does not change.
//!
//! Why: under soft light the node values are right — against the lattice solved on every density
//! voxel, the torus's nodes at 1.92 optical depths per transfer voxel are 2.5 % brighter in
//! total — but a node outside a lit surface holds the light of an empty point, and the light
//! inside falls (the unscattered part) or peaks (the scattered part) within a fraction of a
//! voxel, so interpolating point values between nodes K voxels apart is what errs: 11.0 % against
//! the path tracer where the same nodes fitted to the finer bake's light, read where the density
//! is, give 7.1 % (docs/accuracy.md, "Soft light: thick transfer voxels baked finer").
//!
//! Both layers come back through one linear fit, so at a node T_ri + F_ms is the fit of the fine
//! nodes' totals, which in a white furnace are √(4π) + (point − the lattice's unscattered light)
//! as on the transfer's own cells: the furnace holds as well as it did.

use super::basis::Basis;
use super::layout::TransferLayout;
use super::memory;
use super::{cell_optical_depth, BakeSettings, Medium, POINT_DIRECT_ALBEDO};
use crate::volume::SparseGrid;

/// Mean optical depth of a transfer voxel ([`cell_optical_depth`]) above which a bake that keeps
/// point values bakes finer. Measured against the path tracer (256×144, studio.exr, albedo 0.9,
/// docs/accuracy.md), baking finer brings the torus / cloud at 1.92 optical depths per transfer
/// voxel from 11.0 / 9.9 % to 7.1 / 7.3 % (read as B-splines, [`BASIS`]: 6.4 / 4.6 %), and at 0.96
/// from 6.6 / 5.2 % to 4.8 / 3.7 % (read trilinearly); it costs the bake 3.2× its time and 3.3×
/// its peak on the bench cloud at σt 1.6 (8.6 per transfer voxel; 4.7× its time with the
/// B-spline's fit back) and 3.7× / 3.5× on the quarter-size cloud at σt 0.2 (1.08), where the
/// scale's time target (a fifth of `a4d4a99`'s bake) would no longer hold. 1.5 lies between 1.08
/// and 1.92.
pub const REFINE_CELL_DEPTH: f64 = 1.5;

/// The share of `--samples` traced at each finer node. A finer node stands for an eighth of a
/// transfer voxel and the fit averages the eight or more around each node, so a quarter of the
/// directions there traces twice the rays of the transfer's own nodes. Two bake seeds of the
/// torus at 1.92 / 5.2 optical depths per transfer voxel then differ by 0.41 / 0.64 % per image
/// (all the directions: 0.06 / 0.13 %, an eighth 0.92 / 1.31 %; issue 16 asks ≤ 1 %), and no
/// accuracy row moves by more than 0.1 point between all and an eighth.
pub const FINE_SAMPLE_SHARE: usize = 4;

/// How a transfer baked finer reads its nodes: the quadratic B-spline, whose read-out has a
/// continuous slope. Fitted for trilinear reading, the nodes of a transfer whose voxels are
/// several optical depths across draw the cell faces as faint lines across a lit surface where
/// the slope jumps (the README's torus under studio.exr at the default σt); read as B-splines
/// they do not, and the fit, with room to follow the light's fall within a cell, can be pulled
/// less toward the footprint means ([`FIT_BACK_REGULARISATION`]).
pub const BASIS: Basis = Basis::Quadratic;

/// λ of the fit back ([`super::fit::least_squares`]): how strongly the B-spline nodes are pulled
/// toward their footprint means. The finer light they are fitted to is an average over many
/// finer nodes, smoother than T_ri's footprint means, so it needs less pull than
/// [`super::fit::FIT_REGULARISATION`]. Measured (studio.exr, albedo 0.9, 256×144, against the
/// path tracer), λ 0.1 / 0.03 / 0.01 / 0.003 / 0.001: the torus at σt 1 20.1 / 14.6 / 12.4 /
/// 11.2 / 10.4 %, the cloud at σt 1 22.8 / 15.9 / 12.8 / 11.2 / 10.5 %, the torus at 1.92 optical
/// depths per transfer voxel 6.5 / 6.3 / 6.4 / 6.4 % (from 0.03); two bake seeds of the torus at
/// σt 1 0.74 / 0.80 / 0.84 % apart (from 0.01). At 0.001 dark smudges appear on the torus's lit
/// ring, at 0.003 none (looked at 640×360 beside the path tracer).
pub const FIT_BACK_REGULARISATION: f64 = 0.003;

/// Most working memory the finer bake may take (its point values, its lattice's links and
/// transport, its light, beside the transfer); past it the bake keeps the transfer's own cells.
/// A fixed figure, so a bake gives the same cache on every machine. The bench cloud at σt 1.6
/// peaks at 175 MB in all; the half-size production cloud would need several GB.
pub const MAX_REFINED_BYTES: u64 = 1 << 30;

/// The edge, in density voxels, of the finer cells a bake of `medium` in `density` at `settings`
/// is baked on, or `None` to bake on the transfer's own: [`finer_cells`] for a bake with multiple
/// scattering and without `--fit-direct` (one that keeps point values,
/// [`BakeSettings::fits_footprints`]), where its working memory fits [`MAX_REFINED_BYTES`].
pub fn fine_scale(density: &SparseGrid, medium: Medium, settings: &BakeSettings) -> Option<i32> {
    if settings.single_scatter || settings.fit_direct {
        return None;
    }
    let depth = cell_optical_depth(density, medium.sigma_t, settings.scale);
    let fine = finer_cells(depth, medium, settings.scale)?;
    // The estimated count is up to several times the truth on small cells, whose leaves' boxes
    // overlap: it only rules out what could not fit however it overcounts; below that the finer
    // layout is counted.
    let about = TransferLayout::estimate_len(density, fine);
    let fits = |nodes: u64| {
        memory::refined_bytes(density, nodes, fine, settings, medium) <= MAX_REFINED_BYTES
    };
    if about > memory::MAX_LAID_OUT_VOXELS || !fits(about / ESTIMATE_OVERCOUNT) {
        return None;
    }
    fits(TransferLayout::build(density, fine).len() as u64).then_some(fine)
}

/// The most [`TransferLayout::estimate_len`] is taken to overcount finer cells by: measured 6.0×
/// on the fixture cloud at cells of 3 (69 717 against 11 708).
const ESTIMATE_OVERCOUNT: u64 = 8;

/// The edge of the finer cells a multiple-scattering bake of `medium` at `scale` takes where its
/// transfer voxels are `depth` optical depths across, its flags and memory bound aside: half its
/// own (rounded up, 3 at the default 6) where it keeps point values (albedo ≥
/// [`POINT_DIRECT_ALBEDO`]; its voxels are thicker than [`super::POINT_DIRECT_CELL_DEPTH`] here) and
/// `depth` is over [`REFINE_CELL_DEPTH`]. The resolution warning asks it too.
pub fn finer_cells(depth: f64, medium: Medium, scale: i32) -> Option<i32> {
    let fine = (scale + 1) / 2;
    (depth > REFINE_CELL_DEPTH && medium.albedo >= POINT_DIRECT_ALBEDO && fine < scale)
        .then_some(fine)
}

/// The directions traced at each finer node ([`FINE_SAMPLE_SHARE`]).
pub fn fine_samples(settings: &BakeSettings) -> usize {
    (settings.samples / FINE_SAMPLE_SHARE).max(1)
}
