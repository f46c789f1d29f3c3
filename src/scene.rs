//! The pipeline every command goes through: open a volume (a VDB density or a `.vtc` cache),
//! bake its transfer when it has none, and render it — with the transfer or the path tracer —
//! under a [`Lighting`]. `render`, and any other front end, calls these and nothing below them.

use std::borrow::Cow;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Instant;

use glam::Vec3;
use indicatif::ProgressBar;

use crate::error::Result;
use crate::io::progress::Phases;
use crate::light::Lighting;
use crate::pathtrace::{Medium3d, PathStats, PathTracer};
use crate::render::sunlight::{self, SunLattice, SunLight};
use crate::render::{self, Background, Camera, CameraSpec, MarchSettings, MarchStats, Rows};
use crate::transfer::cache::{self, Cache, Header, Origin, Source};
use crate::transfer::lattice::DensityMeans;
use crate::transfer::memory::RADIANCE_BYTES_PER_TRANSFER_VOXEL;
use crate::transfer::memory::{BakePlan, MAX_LAID_OUT_VOXELS};
use crate::transfer::packing::Precision;
use crate::transfer::{BakeSettings, BakeStats, Medium, Transfer, TransferLayout, TransferLight};
use crate::volume::{load_density, DensityField};

/// How to bake, validated: the grid to read, the medium, the bake settings and the cache's form.
#[derive(Debug, Clone)]
pub struct BakeConfig {
    /// The grid to read from a VDB (`None`: `density`, else the first scalar grid).
    pub grid: Option<String>,
    pub medium: Medium,
    pub settings: BakeSettings,
    /// How the cache stores the coefficients (and the density).
    pub precision: Precision,
    /// Refuse bakes estimated above this many bytes (`None`: a share of available memory).
    pub max_memory: Option<u64>,
}

/// A volume ready to render: its density field, its medium and, once baked or read, its transfer.
pub struct Scene {
    pub field: DensityField,
    pub medium: Medium,
    pub transfer: Option<Transfer>,
    /// The source file's identity and grid, for a cache written from this scene (`None` for a
    /// cache).
    origin: Option<Origin>,
    /// Seconds spent reading the input and building the density's occupancy (its bricks come
    /// when the work ahead repays them: [`Scene::render_bricks`]).
    pub read_seconds: f64,
    pub field_seconds: f64,
    /// The suns' shadow volumes and lattice solves, kept while a sun does not move: another
    /// camera, or another environment with the same sun, reuses them.
    sun_lights: Mutex<Vec<Arc<SunLight>>>,
    /// The suns' lattice's nodes ([`sunlight::sun_layout`]), laid out once for every sun and render
    /// of this transfer.
    sun_layout: Mutex<Option<Arc<TransferLayout>>>,
}

/// The light of a sun shining from `direction` in `medium` among `kept`, if there is one.
fn kept_light(kept: &[Arc<SunLight>], direction: Vec3, medium: Medium) -> Option<Arc<SunLight>> {
    kept.iter().find(|l| l.is_for(direction, medium)).cloned()
}

/// Camera rays per leaf from which a march builds the density's bricks. Bricks hold about twice
/// the leaves' memory. On the half-size bench cloud at 1920×1080 (21 rays per leaf) building them
/// took about what they saved the march (0.3 s against 0.45 s; the render 3.1 s either way) and
/// they held 407 MB beside 202 MB of leaves; on the 200×170×320 bench cloud (765 rays per leaf)
/// they cut the render from 1.02 to 0.73 s. Three times the break-even leaves them where they
/// clearly pay.
const BRICKED_RAYS_PER_LEAF: u64 = 64;
/// Bytes of the suns' multiple-scattered radiance the march reads per node (RGB).
const SUN_RECORD_BYTES: u64 = 12;

/// What the light of one render cost beyond relighting, for `--stats`.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct LightReport {
    pub shadow_seconds: f64,
    pub lattice_seconds: f64,
    /// Bytes held by the suns' shadow volumes and fluences.
    pub bytes: u64,
    /// The suns' lattice: its nodes and its cells' edge in density voxels (0 without one).
    pub lattice_nodes: usize,
    pub lattice_edge: i32,
    /// Generations the new suns' solves swept, summed.
    pub lattice_sweeps: usize,
    /// Building the density's bricks for this render (0 when built before or not built).
    pub brick_seconds: f64,
}

impl Scene {
    /// Opens `path`: a `.vtc` cache (density, medium and transfer; recognised by its content, so
    /// a renamed file still works), or a VDB file whose density grid `config.grid` chooses, with
    /// the medium of `config`.
    pub fn open(path: &Path, config: &BakeConfig) -> Result<Scene> {
        Scene::open_lit(path, config, None)
    }

    /// Opens `path` as [`Scene::open`] does, to render it under `lightings` only: a cache's
    /// coefficients are relit under each as they are read ([`cache::read_relit`]) and never held.
    pub fn open_for(path: &Path, config: &BakeConfig, lightings: &[Lighting]) -> Result<Scene> {
        Scene::open_lit(path, config, Some(lightings))
    }

    fn open_lit(path: &Path, config: &BakeConfig, lightings: Option<&[Lighting]>) -> Result<Scene> {
        let clock = Instant::now();
        let (grid, medium, transfer, origin) = if cache::is_cache(path)? {
            let relit = |lightings: &[Lighting]| -> Result<Cache> {
                let bands = cache::read_header(path)?
                    .and_then(|h| h.settings())
                    .map_or(0, |s| s.bands);
                let envs: Vec<_> = lightings.iter().map(|l| l.sh_coefficients(bands)).collect();
                cache::read_relit(path, &envs)
            };
            let c = match lightings {
                Some(lightings) => relit(lightings)?,
                None => cache::read(path)?,
            };
            let medium = c.transfer.medium;
            (c.density, medium, Some(c.transfer), None)
        } else {
            // The identity first: a file rewritten while it is read then looks stale, never current.
            let source = Source::of(path)?;
            let loaded = load_density(path, config.grid.as_deref())?;
            let origin = Origin {
                source,
                grid: loaded.name,
                requested_grid: config.grid.clone(),
            };
            (loaded.grid, config.medium, None, Some(origin))
        };
        // A cache relit as it was read counts that time as relight (`RelitMap::seconds`).
        let relit: f64 = match transfer.as_ref().map(|t| &t.light) {
            Some(TransferLight::Relit(maps)) => maps.iter().map(|m| m.seconds).sum(),
            _ => 0.0,
        };
        let read_seconds = (clock.elapsed().as_secs_f64() - relit).max(0.0);
        let clock = Instant::now();
        let field = DensityField::without_bricks(grid);
        Ok(Scene {
            field,
            medium,
            transfer,
            origin,
            read_seconds,
            field_seconds: clock.elapsed().as_secs_f64(),
            sun_lights: Mutex::new(Vec::new()),
            sun_layout: Mutex::new(None),
        })
    }

    /// Takes the transfer from the cache at `path` when it was baked from this very source with
    /// this configuration ([`cache_is_current`]); returns whether it did. A missing cache, or one in
    /// an older format (what a bake computes changed), is stale and the caller bakes afresh; a
    /// damaged one is an error.
    pub fn reuse_cache(&mut self, path: &Path, config: &BakeConfig) -> Result<bool> {
        let Some(origin) = &self.origin else {
            return Ok(false);
        };
        if !path.exists() {
            return Ok(false);
        }
        let current = cache::read_header(path)?
            .is_some_and(|h| h.grid == origin.grid && baked_from(&h, &origin.source, config));
        if current {
            // The density too: the cache holds it as the bake's render did ([`Scene::bake`]).
            let c = cache::read(path)?;
            self.field = DensityField::without_bricks(c.density);
            self.transfer = Some(c.transfer);
            self.forget_suns();
        }
        Ok(current)
    }

    /// What baking this scene with `settings` will make and need, before it runs.
    pub fn plan(&self, config: &BakeConfig) -> BakePlan {
        BakePlan::new(&self.field, &config.settings, config.medium)
    }

    /// Bakes the transfer (check [`BakePlan::check_budget`] first: a bake allocates what its
    /// plan says), reporting its phases to `progress`.
    pub fn bake(&mut self, config: &BakeConfig, progress: &dyn Phases) -> BakeStats {
        let (mut transfer, stats) =
            crate::transfer::bake(&mut self.field, config.medium, &config.settings, progress);
        // Held as its cache will hold it (`config.precision`), so a render of this bake and one
        // of its cache are the same image.
        if let Some(grid) = cache::as_stored(&self.field.grid, &mut transfer, config.precision) {
            self.field = DensityField::without_bricks(grid);
        }
        self.medium = config.medium;
        self.transfer = Some(transfer);
        self.forget_suns();
        stats
    }

    /// Writes the baked transfer with the density to a cache at `path` (atomically).
    pub fn write_cache(&self, path: &Path, config: &BakeConfig) -> Result<()> {
        let (Some(transfer), Some(origin)) = (&self.transfer, &self.origin) else {
            return Err(crate::Error::Runtime(format!(
                "{}: nothing baked to write",
                path.display()
            )));
        };
        let grid = &self.field.grid;
        let header = cache::header(
            grid,
            transfer,
            &config.settings,
            origin.clone(),
            config.precision,
        );
        cache::write(path, &header, grid, transfer)
    }

    /// What a user should know before trusting a picture of this scene: a volume with no density
    /// to show, or — for a transfer at 1/`scale` resolution (`None`: no soft light through a
    /// transfer, as the path tracer's, even of a cache, or a render without an environment's
    /// light) — transfer voxels too thick to resolve the light; a cache's own scale wins over
    /// `scale`.
    pub fn warnings(&self, scale: Option<i32>) -> Vec<String> {
        let grid = &self.field.grid;
        if grid.value_stats().is_none_or(|s| s.max <= 0.0) {
            return vec![
                "the volume has no positive density: the picture shows only the environment".into(),
            ];
        }
        let scale = scale.map(|k| self.transfer.as_ref().map_or(k, |t| t.layout.k));
        scale
            .and_then(|k| crate::transfer::resolution_warning(grid, self.medium, k))
            .into_iter()
            .collect()
    }

    /// The camera of `spec` for this volume: framing where the density is when `spec` has no
    /// position ([`render::framing_bounds`]).
    pub fn camera(&self, spec: &CameraSpec) -> Result<Camera> {
        spec.camera(render::framing_bounds(&self.field.grid))
    }

    /// Relights the transfer under `lighting` and hands `consume` its march as `camera` sees it,
    /// row by row ([`render::render_volume`]), with the environment behind the volume unless
    /// `background` is false.
    pub fn render<R>(
        &self,
        camera: &Camera,
        lighting: &Lighting,
        background: bool,
        settings: &MarchSettings,
        progress: &ProgressBar,
        consume: impl FnOnce(&mut Rows) -> R,
    ) -> Result<(R, MarchStats, render::RenderReport, LightReport)> {
        let Some(transfer) = &self.transfer else {
            return Err(crate::Error::Runtime(
                "the scene has no transfer: bake it first".into(),
            ));
        };
        let bricks = self.render_bricks(camera, settings.spp, lighting);
        let brick_seconds = match bricks {
            true => self.field.build_bricks(),
            false => 0.0,
        };
        let (lights, mut report) = self.sun_lights(transfer, lighting);
        report.brick_seconds = brick_seconds;
        let refs: Vec<&SunLight> = lights.iter().map(|l| l.as_ref()).collect();
        let lookup = |d: &[Vec3], out: &mut [[f32; 3]]| lighting.backgrounds(d, out);
        let background: Option<Background> = background.then_some(&lookup);
        let (out, stats, times) = render::render_volume(
            &self.field,
            transfer,
            &render::Light {
                lighting,
                suns: &refs,
            },
            background,
            camera,
            settings,
            progress,
            consume,
        )?;
        Ok((out, stats, times, report))
    }

    /// Whether a render of `camera` at `spp` under `lighting` holds the density's bricks: built
    /// before (by a bake), or built for it when the light has shadow volumes to build (they
    /// sample every voxel of the active region) or the march has
    /// [`BRICKED_RAYS_PER_LEAF`] camera rays per leaf.
    pub fn render_bricks(&self, camera: &Camera, spp: u32, lighting: &Lighting) -> bool {
        let rays = camera.width as u64 * camera.height as u64 * spp as u64;
        let leaves = self.field.grid.leaf_count() as u64;
        self.field.has_bricks()
            || self.new_suns(lighting) > 0
            || rays >= BRICKED_RAYS_PER_LEAF * leaves
    }

    /// Bytes relighting the transfer under `lighting` makes beside what the transfer holds: held
    /// coefficients relight into two parts and then their records (the parts beside the records
    /// while they combine); a transfer relit as read lends its records.
    pub fn relight_plan(&self) -> u64 {
        let Some(t) = &self.transfer else {
            return 0;
        };
        let records = t.layout.len() as u64 * RADIANCE_BYTES_PER_TRANSFER_VOXEL;
        match &t.light {
            TransferLight::Coefficients { .. } => 2 * records,
            TransferLight::Relit(_) => 0,
        }
    }

    /// Bytes the suns' light will hold beyond the transfer, estimated before it is built: a
    /// shadow volume and a fluence per node of the suns' lattice for each sun not kept from an
    /// earlier render, the lattice's layout, and the radiance the march reads from its nodes.
    /// `bake`: before the transfer is baked, the bake it will come from (see
    /// [`Self::planned_sun_layout`]).
    pub fn sun_plan(&self, lighting: &Lighting, bake: Option<&BakeConfig>) -> u64 {
        // The shadow volume's estimate walks the density's blocks: only for suns to build.
        let new_suns = self.new_suns(lighting) as u64;
        if new_suns == 0 {
            return 0;
        }
        let shadow = crate::volume::shadow::ShadowVolume::estimate_bytes(&self.field.grid);
        let lattice = self.planned_sun_layout(bake).map_or(0, |layout| {
            layout.memory_bytes() as u64 + layout.len() as u64 * (4 * new_suns + SUN_RECORD_BYTES)
        });
        new_suns * shadow + lattice
    }

    /// The working memory of the new suns' multiple-scattering solve, while it runs (one at a
    /// time, on links built once): 0 when every sun is kept or the transfer has no lattice.
    /// `bake`: as for [`Self::sun_plan`].
    pub fn sun_solve_plan(&self, lighting: &Lighting, bake: Option<&BakeConfig>) -> u64 {
        if self.new_suns(lighting) == 0 {
            return 0;
        }
        self.planned_sun_layout(bake).map_or(0, |layout| {
            let reflecting = DensityMeans::new(&self.field.grid).reflecting_share(
                self.medium.sigma_t,
                layout.k,
                sunlight::SUN_LATTICE,
            );
            let directions = sunlight::SUN_LATTICE.directions();
            crate::transfer::memory::sun_solve_bytes(layout.len(), directions, reflecting)
        })
    }

    /// The suns' lattice's nodes: for the baked transfer's layout, or, before a bake, for the
    /// transfer layout the bake `bake` will lay out; `None` without a lattice, or
    /// before a bake of more transfer voxels than a plan lays out ([`MAX_LAID_OUT_VOXELS`]),
    /// whose suns are solved on its own cells and counted with it.
    fn planned_sun_layout(&self, bake: Option<&BakeConfig>) -> Option<Arc<TransferLayout>> {
        if let Some(t) = &self.transfer {
            return t
                .lattice
                .map(|_| self.sun_layout(|| Cow::Borrowed(&t.layout)));
        }
        let settings = &bake?.settings;
        let grid = &self.field.grid;
        if settings.single_scatter
            || TransferLayout::estimate_len(grid, settings.scale) > MAX_LAID_OUT_VOXELS
        {
            return None;
        }
        let layout = || Cow::Owned(TransferLayout::build(grid, settings.scale));
        Some(self.sun_layout(layout))
    }

    /// How many of `lighting.suns` have no light kept from an earlier render.
    fn new_suns(&self, lighting: &Lighting) -> usize {
        let kept = self.sun_lights.lock().unwrap_or_else(|e| e.into_inner());
        lighting
            .suns
            .iter()
            .filter(|s| kept_light(&kept, s.direction, self.medium).is_none())
            .count()
    }

    /// Drops the kept suns' light: it was built on the transfer now replaced.
    fn forget_suns(&mut self) {
        self.sun_lights
            .get_mut()
            .unwrap_or_else(|e| e.into_inner())
            .clear();
        *self.sun_layout.get_mut().unwrap_or_else(|e| e.into_inner()) = None;
    }

    /// The light of each of `lighting.suns`: kept from an earlier render where the sun has not
    /// moved, else built now, the new suns' multiple scattering on one lattice.
    fn sun_lights(
        &self,
        transfer: &Transfer,
        lighting: &Lighting,
    ) -> (Vec<Arc<SunLight>>, LightReport) {
        let mut kept = self.sun_lights.lock().unwrap_or_else(|e| e.into_inner());
        let mut report = LightReport::default();
        let medium = transfer.medium;
        let new_suns = lighting
            .suns
            .iter()
            .any(|s| kept_light(&kept, s.direction, medium).is_none());
        let lattice = transfer.lattice.filter(|_| new_suns).map(|_| {
            let clock = Instant::now();
            let layout = self.sun_layout(|| Cow::Borrowed(&transfer.layout));
            let lattice = SunLattice::build(&self.field, layout, medium);
            report.lattice_seconds += clock.elapsed().as_secs_f64();
            lattice
        });
        let lights: Vec<Arc<SunLight>> = lighting
            .suns
            .iter()
            .map(|sun| {
                if let Some(l) = kept_light(&kept, sun.direction, medium) {
                    return l;
                }
                let light = Arc::new(SunLight::build(
                    &self.field,
                    medium,
                    lattice.as_ref(),
                    sun.direction,
                ));
                report.shadow_seconds += light.shadow_seconds;
                report.lattice_seconds += light.lattice_seconds;
                report.lattice_sweeps += light.multiple.as_ref().map_or(0, |m| m.sweeps);
                kept.push(light.clone());
                light
            })
            .collect();
        report.bytes = lights.iter().map(|l| l.memory_bytes()).sum();
        if let Some(m) = lights.iter().find_map(|l| l.multiple.as_ref()) {
            report.bytes += m.layout.memory_bytes() as u64;
            (report.lattice_nodes, report.lattice_edge) = (m.layout.len(), m.layout.k);
        }
        (lights, report)
    }

    /// The suns' lattice's nodes for the transfer layout `transfer` gives, laid out on first use
    /// (a plan's transfer layout is then laid out once, not once per estimate).
    fn sun_layout<'t>(
        &self,
        transfer: impl FnOnce() -> Cow<'t, TransferLayout>,
    ) -> Arc<TransferLayout> {
        let mut held = self.sun_layout.lock().unwrap_or_else(|e| e.into_inner());
        held.get_or_insert_with(|| {
            Arc::new(sunlight::sun_layout(
                &self.field.grid,
                &transfer(),
                self.medium.sigma_t,
            ))
        })
        .clone()
    }

    /// Path-traces the density under `lighting`, handing `consume` the image row by row: the
    /// ground truth the transfer is measured against.
    pub fn pathtrace<R>(
        &self,
        camera: &Camera,
        lighting: &Lighting,
        background: bool,
        trace: &TraceSettings,
        progress: &ProgressBar,
        consume: impl FnOnce(&mut Rows) -> R,
    ) -> (R, PathStats) {
        // Every path samples the density many times per leaf.
        self.field.build_bricks();
        let light = lighting.sampler();
        let tracer = PathTracer {
            medium: Medium3d {
                field: &self.field,
                sigma_t: self.medium.sigma_t,
            },
            albedo: self.medium.albedo,
            light: &light,
            suns: &lighting.suns,
            max_bounces: trace.max_bounces,
            seed: trace.seed,
        };
        let lookup = |d: &[Vec3], out: &mut [[f32; 3]]| lighting.backgrounds(d, out);
        let background: Option<Background> = background.then_some(&lookup);
        let (out, stats, _) = render::film::stream_rows(
            camera,
            trace.spp,
            background,
            progress,
            || (),
            |sample, st, _| tracer.trace(sample, st),
            consume,
        );
        (out, stats)
    }
}

/// The box a camera framing every one of `inputs` looks at: the union of their framing boxes
/// ([`render::framing_bounds`]). A cache's box is in its header, so only a VDB (of `grid`) is read.
/// An input that cannot be read adds nothing (its frame reports the error when it renders).
pub fn framing_union(inputs: &[std::path::PathBuf], grid: Option<&str>) -> Option<(Vec3, Vec3)> {
    let mut union: Option<(Vec3, Vec3)> = None;
    for input in inputs {
        let bounds = match cache::read_header(input) {
            Ok(Some(h)) => h.framing.map(|[lo, hi]| (Vec3::from(lo), Vec3::from(hi))),
            _ => load_density(input, grid)
                .ok()
                .and_then(|loaded| render::framing_bounds(&loaded.grid)),
        };
        if let Some((lo, hi)) = bounds {
            union = Some(union.map_or((lo, hi), |(a, b)| (a.min(lo), b.max(hi))));
        }
    }
    union
}

/// Whether the cache at `cache` holds a bake of the file at `input`, as it is now, with `config`:
/// its identity (size, time, first bytes), the grid asked for, the medium, the bake settings, the
/// coefficients' precision and the format version all match. What lets a batch skip a frame
/// without reading its volume. A missing cache, or one that cannot be read as a current cache,
/// is not current (it is baked again and replaced); a missing input is an error.
pub fn cache_is_current(input: &Path, cache: &Path, config: &BakeConfig) -> Result<bool> {
    let source = Source::of(input)?;
    if !cache.exists() {
        return Ok(false);
    }
    Ok(cache::read_header(cache)
        .ok()
        .flatten()
        .is_some_and(|h| baked_from(&h, &source, config)))
}

/// Whether the header `h` describes a bake of `source` with `config`.
fn baked_from(h: &Header, source: &Source, config: &BakeConfig) -> bool {
    h.source == *source
        && h.requested_grid == config.grid
        && h.settings().as_ref() == Some(&config.settings)
        && h.sigma_t == config.medium.sigma_t
        && h.albedo == config.medium.albedo
        && h.coefficients == config.precision
}

/// How to path-trace.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TraceSettings {
    pub spp: u32,
    /// Most scattering events per path (1: single scattering).
    pub max_bounces: u32,
    /// Picks the random streams; the image is the same on any thread count.
    pub seed: u64,
}
