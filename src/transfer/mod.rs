//! The transfer: per transfer voxel, SH coefficients of the fraction of environment light from each
//! direction that reaches it — unscattered (`t_ri`, thesis eq. 4.1) and after one or more
//! scattering events (`f_ms`, thesis 4.2) — independent of any environment.

pub mod cache;
pub(crate) mod coefficients;
pub use coefficients::Coefficients;
pub mod basis;
pub use basis::Basis;
pub(crate) mod fit;
pub use fit::fitted_visibility;
pub mod lattice;
mod layout;
pub mod memory;
pub mod packing;
pub mod refine;
pub mod shape;
mod single;
#[cfg(test)]
mod tests;

pub use layout::TransferLayout;

use crate::render::relight::Radiance;
use crate::volume::mip::DensityMip;
use crate::volume::transmittance::{FarField, OpticalDepth};
use crate::volume::{DensityField, SparseGrid};

/// The participating medium ([docs/model.md](../../docs/model.md)): σt = `sigma_t`·ρ per world unit, σs = `albedo`·σt,
/// isotropic phase.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Medium {
    pub sigma_t: f32,
    pub albedo: f32,
}

/// The phase function: isotropic, p = 1/(4π) per steradian. Relighting, the suns' in-scatter and
/// the path tracer all take it from here.
pub const PHASE: f32 = 1.0 / (4.0 * std::f32::consts::PI);

/// A baked transfer over a sparse layout: `bands²` coefficients per voxel, voxel after voxel.
#[derive(Clone)]
pub struct Transfer {
    pub layout: TransferLayout,
    pub bands: usize,
    pub medium: Medium,
    pub light: TransferLight,
    /// The lattice that solved F_ms, and that solves the suns' multiple scattering (`None`: the
    /// bake was `--single-scatter`, and so is the suns' light).
    pub lattice: Option<lattice::LatticeKind>,
    /// What shapes the direct light between nodes (`None`: plain interpolation).
    pub shape: Option<std::sync::Arc<shape::TransferShape>>,
    /// How the node values are read between nodes.
    pub basis: Basis,
}

/// What a transfer holds of its light.
#[derive(Debug, Clone, PartialEq)]
pub enum TransferLight {
    /// Unscattered transfer T_ri, `layout.len() × bands²`, and multiply-scattered transfer F_ms
    /// (zero after a `--single-scatter` bake), same shape.
    Coefficients {
        t_ri: Coefficients,
        f_ms: Coefficients,
    },
    /// What the coefficients give under each of a render's maps, relit as a cache streamed them
    /// in ([`cache::read_relit`]) and never held.
    Relit(Vec<RelitMap>),
}

/// One map's light on a transfer relit as a cache streamed in.
#[derive(Debug, Clone)]
pub struct RelitMap {
    /// The map's SH coefficients, as [`crate::render::relight::relight`] takes them.
    pub env: Vec<[f32; 3]>,
    pub radiance: Radiance,
    /// The time its relighting took while the cache was read (`--stats` counts it as relight,
    /// not read).
    pub seconds: f64,
}

/// The same light under the same map, however long it took.
impl PartialEq for RelitMap {
    fn eq(&self, other: &RelitMap) -> bool {
        self.env == other.env && self.radiance == other.radiance
    }
}

impl Transfer {
    pub fn coeffs(&self) -> usize {
        self.bands * self.bands
    }

    /// Bytes the [`shape::TransferShape`] holds.
    pub fn shape_bytes(&self) -> usize {
        self.shape.as_ref().map_or(0, |s| s.memory_bytes() as usize)
    }

    /// T_ri and F_ms (`None`: relit as read, [`TransferLight::Relit`]).
    pub fn coefficients(&self) -> Option<(&Coefficients, &Coefficients)> {
        match &self.light {
            TransferLight::Coefficients { t_ri, f_ms } => Some((t_ri, f_ms)),
            TransferLight::Relit(_) => None,
        }
    }

    /// Bytes the coefficients, or the radiance relit from them, hold.
    pub fn coefficient_bytes(&self) -> usize {
        match &self.light {
            TransferLight::Coefficients { t_ri, f_ms } => t_ri.memory_bytes() + f_ms.memory_bytes(),
            TransferLight::Relit(maps) => maps.iter().map(|m| m.radiance.memory_bytes()).sum(),
        }
    }
}

/// How to bake: the flags of `vscatter bake`, validated.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BakeSettings {
    pub bands: usize,
    /// Density voxels per transfer voxel along each axis (K).
    pub scale: i32,
    pub samples: usize,
    pub lattice: lattice::LatticeKind,
    pub single_scatter: bool,
    /// Fit T_ri to footprint means at any albedo (`--fit-direct`): the direct and indirect
    /// layers apart come closer to the path tracer's, for twice the T_ri work.
    pub fit_direct: bool,
    pub seed: u64,
}

/// The albedo from which a multiple-scattering bake takes T_ri's point values as its direct light
/// and traces no footprint pass ([`BakeSettings::fits_footprints`]). A multiple-scattering image
/// holds the direct light only as its share 1 − albedo (the rest of a node's unscattered light is
/// scattered, and F_ms carries it), and there the fitted footprint means are too dark in thick
/// cells where the point values are a little too bright in thin ones. Measured against the path
/// tracer (256×144, studio.exr, torus and cloud at 0.48, 1.92 and 5.2 optical depths per transfer
/// voxel; docs/accuracy.md): at albedo 0.9 the point values are 0.0–0.2 points further off at
/// 0.48 and 0.3–1.7 points closer in thick cells, at 0.8 0.2–0.3 points further and 0.4–3.1
/// closer, at 0.7 0.4–0.7 further and 0.2–3.6 closer, at 0.5 1.0–1.7 further and mixed in thick
/// cells (+2.3 to −3.1). Without the footprint pass T_ri costs half as much and two bake seeds
/// are half as far apart (its noise is what they differ by). Where cells are thin the fit stays
/// ([`POINT_DIRECT_CELL_DEPTH`]).
pub const POINT_DIRECT_ALBEDO: f32 = 0.8;

/// The mean optical depth of a transfer voxel ([`cell_optical_depth`]) from which a bake at
/// albedo ≥ [`POINT_DIRECT_ALBEDO`] keeps the point values. Below it the interpolation between a
/// node in the empty apron and one inside overshoots more than the fit errs, and the fit is
/// closer: against the path tracer (256×144, studio.exr, albedo 0.9, docs/accuracy.md) the fit
/// is 0.02–0.15 point closer at 0.24 and 0.48 optical depths per transfer voxel, the point
/// values 0.06–0.08 point closer at 0.96 and 0.3–1.7 closer beyond. 0.7 lies between the two
/// measured densities, near their geometric mean.
pub const POINT_DIRECT_CELL_DEPTH: f64 = 0.7;

/// The share of `samples` the footprint pass traces where a bake at albedo ≥
/// [`POINT_DIRECT_ALBEDO`] fits only because its cells are thin ([`POINT_DIRECT_CELL_DEPTH`]).
/// There the fitted values reach the image as the share 1 − albedo (F_ms carries albedo ×
/// (point − fitted)), so their Monte Carlo noise weighs a tenth at the default albedo. Measured
/// (docs/accuracy.md, studio.exr, 256×144, 0.06–0.48 optical depths per transfer voxel): a
/// quarter of the directions moves no row of the report by more than 0.04 point, two bake seeds
/// of the torus at σt 0.1 are 0.45 % apart (0.21 % with all; an eighth: 0.69 %), and the bake of
/// the quarter-size cloud at σt 0.1 takes 40 s against 62–68 s (24 s with the point values).
pub const THIN_FOOTPRINT_SHARE: usize = 4;

impl BakeSettings {
    /// Whether a bake of `medium` in `density` traces T_ri over the footprints and fits it
    /// ([`POINT_DIRECT_ALBEDO`], [`POINT_DIRECT_CELL_DEPTH`]): a `--single-scatter` bake always
    /// does, its image is all direct light, and so does one asked to (`fit_direct`).
    pub fn fits_footprints(&self, density: &SparseGrid, medium: Medium) -> bool {
        self.fits_at_any_depth(medium)
            || cell_optical_depth(density, medium.sigma_t, self.scale) < POINT_DIRECT_CELL_DEPTH
    }

    /// The directions a bake that fits ([`Self::fits_footprints`]) traces over the footprints:
    /// `samples`, or a [`THIN_FOOTPRINT_SHARE`]th of them where it fits only for thin cells.
    pub fn footprint_samples(&self, medium: Medium) -> usize {
        match self.fits_at_any_depth(medium) {
            true => self.samples,
            false => (self.samples / THIN_FOOTPRINT_SHARE).max(1),
        }
    }

    /// Whether a bake fits whatever its cells' depth: its image is all direct light, it is asked
    /// to, or its albedo leaves the direct light a large share ([`POINT_DIRECT_ALBEDO`]).
    fn fits_at_any_depth(&self, medium: Medium) -> bool {
        self.single_scatter || self.fit_direct || medium.albedo < POINT_DIRECT_ALBEDO
    }
}

/// `light`'s rows of `from`² coefficients as rows of `to`² (`to` ≥ `from`), the bands past `from`
/// zero.
fn widen(light: &[f32], from: usize, to: usize) -> Vec<f32> {
    let (narrow, wide) = (from * from, to * to);
    let mut out = vec![0.0; light.len() / narrow.max(1) * wide];
    for (row, values) in out.chunks_exact_mut(wide).zip(light.chunks_exact(narrow)) {
        row[..narrow].copy_from_slice(values);
    }
    out
}

/// Where a bake's direct light (its stored T_ri) comes from.
enum Direct {
    /// The footprint pass, fitted; it marches the far field's coarser density, kept for it.
    Footprints(DensityMip),
    /// T_ri as it stands: the nodes' point values ([`POINT_DIRECT_ALBEDO`]), or a finer bake's
    /// fitted back ([`refine`]).
    Kept(Vec<f32>),
}

/// What a bake did, for `--stats`.
#[derive(Debug, Clone, Default)]
pub struct BakeStats {
    pub layout_seconds: f64,
    pub single_seconds: f64,
    pub lattice_seconds: f64,
    pub transfer_voxels: usize,
    pub transfer_tiles: usize,
    /// Bytes of the coarser density levels T_ri's rays march far from their origin.
    pub far_field_bytes: usize,
    pub lattice: Option<lattice::LatticeStats>,
    /// Sweeping and fitting the visibility that shapes a single-scattering transfer's direct
    /// light ([`shape`]; 0 for a transfer with multiple scattering).
    pub visibility_seconds: f64,
    pub visibility_bytes: u64,
    /// Whether T_ri was fitted to footprint means (`false`: it holds the point values,
    /// [`POINT_DIRECT_ALBEDO`], or a finer bake's fitted back, [`refine`]).
    pub fitted: bool,
    /// The edge, in density voxels, of the cells the point values and the lattice were baked on:
    /// the transfer's K, or finer where its voxels are thick ([`refine`]); 0 for a
    /// `--single-scatter` bake.
    pub lattice_scale: i32,
}

/// Bakes the transfer of `field`: layout, T_ri, then (unless single-scatter) F_ms. The field's
/// bricks are built first (unless they are), released while the lattice transports light, and
/// built again after.
pub fn bake(
    field: &mut DensityField,
    medium: Medium,
    settings: &BakeSettings,
    progress: &dyn crate::io::progress::Phases,
) -> (Transfer, BakeStats) {
    let mut stats = BakeStats::default();
    // T_ri samples each leaf's density many thousands of times.
    field.build_bricks();
    let clock = std::time::Instant::now();
    let layout = TransferLayout::build(&field.grid, settings.scale);
    stats.layout_seconds = clock.elapsed().as_secs_f64();
    stats.transfer_voxels = layout.len();
    stats.transfer_tiles = layout.tile_count();

    // T_ri at the nodes (the point values the lattice's light is balanced against), then, where
    // the bake fits footprints, over the density around them (the footprint means the
    // renderer's values are fitted to), with the lattice between them. The unscattered light the
    // fit takes away from a node's point value has collided sooner, and the share albedo of it is
    // scattered: F_ms gets albedo × (point − fitted), so T_ri + F_ms at a node is what it is with
    // point values, and at albedo 1 exactly so (the white furnace). The point values go into F_ms
    // as albedo × point before the lattice adds to it, and the fitted T_ri comes off at the end,
    // so no phase holds the point values beside both F_ms and T_ri. A bake that does not fit
    // footprints ([`POINT_DIRECT_ALBEDO`]) keeps the point values as T_ri, and its F_ms is the
    // lattice's scattered light alone; where its voxels are thick it takes both on finer cells
    // and fits them back ([`refine`]).
    let coeffs = settings.bands * settings.bands;
    let n = layout.len();
    let footprints = settings.fits_footprints(&field.grid, medium);
    stats.fitted = footprints;
    let refined = refine::fine_scale(&field.grid, medium, settings);
    stats.lattice_scale = match settings.single_scatter {
        true => 0,
        false => refined.unwrap_or(settings.scale),
    };
    let clock = std::time::Instant::now();
    // The coarser density lives through the T_ri passes.
    let (near, levels) = single::far_field(&field.grid, medium.sigma_t, settings.samples);
    let mip = DensityMip::build(&field.grid, levels);
    stats.far_field_bytes = mip.memory_bytes();
    let chord_step = single::chord_step(&field.grid, medium.sigma_t);
    let single_on = |layout: &TransferLayout,
                     field: &DensityField,
                     mip: &DensityMip,
                     origins,
                     samples,
                     visibility,
                     bar: &indicatif::ProgressBar| {
        let far = FarField { mip, near };
        let depth = OpticalDepth::new(field, medium.sigma_t, true)
            .with_far_field(far)
            .with_dark_test();
        let single = single::SingleSettings {
            bands: settings.bands,
            samples,
            seed: settings.seed,
            origins,
            chord_step,
        };
        single::bake_single(&field.grid, layout, &depth, single, visibility, bar)
    };
    let (mut f_ms, direct) = match settings.single_scatter {
        true => (vec![0.0; n * coeffs], Direct::Footprints(mip)),
        false => {
            // The point values and the lattice: on the transfer's cells, or on finer ones
            // (`refine`), whose light is fitted back to the transfer's nodes at the end.
            let fine = refined.map(|k| TransferLayout::build(&field.grid, k));
            let (on, samples) = match &fine {
                Some(fine) => (fine, refine::fine_samples(settings)),
                None => (&layout, settings.samples),
            };
            let bar = progress.phase("single", on.len() as u64);
            let point = single_on(on, field, &mip, single::Origins::Node, samples, None, &bar);
            bar.finish_and_clear();
            stats.single_seconds = clock.elapsed().as_secs_f64();

            let clock = std::time::Instant::now();
            progress.phase("lattice", 0);
            let energy_single = point.iter().step_by(coeffs).map(|&t| t as f64).sum();
            let lattice =
                lattice::Lattice::build(field, on, settings.lattice, medium, settings.bands);
            // The transport samples no density: it runs without the bricks, built again once the
            // links are gone.
            field.release_bricks();
            let (f_ms, direct) = match footprints {
                true => {
                    let mut f_ms = point;
                    f_ms.iter_mut().for_each(|p| *p *= medium.albedo);
                    let done = lattice.bake_multiple(settings.bands, energy_single, &mut f_ms);
                    stats.lattice = Some(done);
                    drop(lattice);
                    (f_ms, Direct::Footprints(mip))
                }
                // The point values are T_ri, and F_ms the lattice's light alone: it is gathered
                // in the bands the lattice carries, beside them, and widened at the end. No
                // coarser density is needed past the point values' pass.
                false => {
                    drop(mip);
                    let carried = lattice.bands();
                    let mut light = vec![0.0; on.len() * carried * carried];
                    let done = lattice.bake_multiple(carried, energy_single, &mut light);
                    stats.lattice = Some(done);
                    drop(lattice);
                    // Both layers come back through one linear fit, so at a node their sum is
                    // the fit of the finer nodes' sums.
                    let (t_ri, light) = match &fine {
                        Some(fine) => {
                            let bar = progress.phase("fit", n as u64);
                            let fields = [(&point[..], coeffs), (&light[..], carried * carried)];
                            let [t_ri, light] = fit::fitted_from_finer(
                                &field.grid,
                                &layout,
                                refine::BASIS,
                                fine,
                                fields,
                                refine::FIT_BACK_REGULARISATION,
                            );
                            bar.finish_and_clear();
                            (t_ri, light)
                        }
                        None => (point, light),
                    };
                    (widen(&light, carried, settings.bands), Direct::Kept(t_ri))
                }
            };
            field.build_bricks();
            stats.lattice_seconds = clock.elapsed().as_secs_f64();
            (f_ms, direct)
        }
    };

    // A single-scattering transfer's direct light is shaped by the density's visibility
    // (`shape`), which also draws where its footprint means start; a transfer with multiple
    // scattering is not shaped.
    let shape = settings.single_scatter.then(|| {
        let clock = std::time::Instant::now();
        progress.phase("visibility", 0);
        let resolution = shape::TransferShape::resolution(field);
        let shape = shape::TransferShape::build(field, &layout, medium.sigma_t, resolution);
        stats.visibility_seconds = clock.elapsed().as_secs_f64();
        stats.visibility_bytes = shape.memory_bytes();
        std::sync::Arc::new(shape)
    });
    let clock = std::time::Instant::now();
    let t_ri = match direct {
        Direct::Kept(t_ri) => t_ri,
        Direct::Footprints(mip) => {
            let bar = progress.phase("fit", n as u64);
            let visibility = shape.as_ref().map(|s| &s.visibility);
            let mut t_ri = single_on(
                &layout,
                field,
                &mip,
                single::Origins::Footprint,
                settings.footprint_samples(medium),
                visibility,
                &bar,
            );
            drop(mip);
            fit::least_squares(
                &field.grid,
                &layout,
                Basis::Tent,
                &mut t_ri,
                coeffs,
                fit::FIT_REGULARISATION,
            );
            bar.finish_and_clear();
            if !settings.single_scatter {
                for (f, t) in f_ms.iter_mut().zip(&t_ri) {
                    *f -= medium.albedo * t;
                }
            }
            t_ri
        }
    };
    stats.single_seconds += clock.elapsed().as_secs_f64();

    let transfer = Transfer {
        layout,
        bands: settings.bands,
        medium,
        light: TransferLight::Coefficients {
            t_ri: Coefficients::F32(t_ri),
            f_ms: Coefficients::F32(f_ms),
        },
        lattice: (!settings.single_scatter).then_some(settings.lattice),
        shape,
        basis: match refined {
            Some(_) => refine::BASIS,
            None => Basis::Tent,
        },
    };
    (transfer, stats)
}

/// Optical depth of the cells a transfer's light is baked on (σt × K × voxel size × mean density,
/// K halved where [`refine`] bakes finer) above which the resolution visibly costs accuracy under
/// soft light: docs/accuracy.md measures the fixtures under studio.exr 4–5 % (single) and 5–7 %
/// (multiple) off the path tracer at 0.96 optical depths per transfer voxel, 7 % at 1.92 (baked
/// on cells of 3: 0.96 there), and 13 % (single) and 18–20 % (multiple) at the default σt (2.6
/// on cells of 3); a sun's light, resolved per density voxel, leaves the default scene (the
/// built-in sky) 7 % off.
pub const MAX_RESOLVED_CELL_DEPTH: f64 = 1.0;

/// The warning for a transfer whose voxels are too thick to resolve where light enters (see
/// [`MAX_RESOLVED_CELL_DEPTH`]), naming a `--sigma-t` that clears it and the other flag that helps.
/// A multiple-scattering bake at the albedo that keeps point values ([`POINT_DIRECT_ALBEDO`])
/// is taken to bake its thick voxels finer ([`refine`]), as it does unless `--fit-direct` is
/// given or its memory bound stops it.
pub fn resolution_warning(density: &SparseGrid, medium: Medium, scale: i32) -> Option<String> {
    let (mean, voxel) = mean_density(density)?;
    let k = scale as f64;
    let depth = cell_depth(medium.sigma_t, k, voxel, mean);
    let (resolved, on) = match refine::finer_cells(depth, medium, scale) {
        Some(fine) => (
            cell_depth(medium.sigma_t, fine as f64, voxel, mean),
            format!(", baked on cells of {fine}"),
        ),
        None => (depth, String::new()),
    };
    (resolved > MAX_RESOLVED_CELL_DEPTH).then(|| {
        format!(
            "{depth:.2} optical depths per transfer voxel (σt {} × K {scale} × voxel {voxel:.3} × mean density {mean:.3}{on}): \
             an environment map's soft light enters within a fraction of a voxel the light is baked on, so without a \
             sun expect errors above 10 % (a sun's light is resolved per density voxel; \
             docs/accuracy.md); a smaller --scale helps, and --sigma-t {} keeps it below \
             {MAX_RESOLVED_CELL_DEPTH} optical depth per transfer voxel",
            medium.sigma_t,
            clearing_sigma_t(k, voxel, mean),
        )
    })
}

/// The mean optical depth of a transfer voxel, σt × K × voxel size × mean density; 0 where the
/// density holds nothing.
pub fn cell_optical_depth(density: &SparseGrid, sigma_t: f32, scale: i32) -> f64 {
    mean_density(density).map_or(0.0, |(mean, voxel)| {
        cell_depth(sigma_t, scale as f64, voxel, mean)
    })
}

/// The density's mean over its active voxels and its (smallest) voxel size; `None` where it
/// holds no positive density.
fn mean_density(density: &SparseGrid) -> Option<(f64, f64)> {
    let stats = density.value_stats()?;
    let active = density.active_voxels();
    (active > 0 && stats.sum > 0.0).then(|| {
        let voxel = density.transform.voxel_size().min_element();
        (stats.sum / active as f64, voxel)
    })
}

/// σt × K × voxel × mean, in the f32 σt the bake uses.
fn cell_depth(sigma_t: f32, k: f64, voxel: f64, mean: f64) -> f64 {
    sigma_t as f64 * k * voxel * mean
}

/// A σt, written with three significant digits, whose cell depth is at most
/// [`MAX_RESOLVED_CELL_DEPTH`]: rounded down, so the value a user copies clears the warning.
fn clearing_sigma_t(k: f64, voxel: f64, mean: f64) -> String {
    let exact = MAX_RESOLVED_CELL_DEPTH / (k * voxel * mean);
    let decimals = (2 - exact.log10().floor() as i32).max(0);
    let unit = 10f64.powi(decimals);
    let mut shown = (exact * unit).floor() / unit;
    let text = |v: f64| format!("{v:.*}", decimals as usize);
    // The printed value, parsed as the flag parser will, must not land above the limit.
    while shown > 0.0
        && cell_depth(text(shown).parse().unwrap_or(0.0), k, voxel, mean) > MAX_RESOLVED_CELL_DEPTH
    {
        shown -= 1.0 / unit;
    }
    text(shown)
}
