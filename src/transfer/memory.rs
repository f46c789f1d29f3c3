//! How much memory a bake or a render will take, estimated before anything big is
//! allocated, and the budget checks that refuse work too large for the machine — naming the
//! settings that would fit.

use indicatif::HumanBytes as human;

use super::{
    fit, lattice, lattice::LatticeKind, refine, single, BakeSettings, Basis, Medium, TransferLayout,
};
use crate::error::{Error, Result};
use crate::math::krylov;
use crate::volume::grid::{TileLevel, LEAF_LOG2};
use crate::volume::visibility::{Resolution, MAX_LEVEL};
use crate::volume::{DensityField, SparseGrid};
use glam::IVec3;

/// Resident memory of the process before a bake allocates anything (binary, thread stacks,
/// allocator arenas), measured as ~20 MB; the estimate counts it so it compares with peak RSS.
const PROCESS_BASELINE: u64 = 24 << 20;

/// What a block of a coarser density level costs against a block of the density itself (leaf or
/// 8³ tile, with its share of the accelerators): more of a coarse level is apron. Measured as the
/// levels' bytes over (the density's bytes per block × the levels' blocks): 1.28 (cloud_large
/// σt 0.2, torus fixture), 1.31 (cloud_quarter), 1.45 (torus300, cloud fixture), 1.61 (cloud_large),
/// 1.21 (helix600); block300, whose 128³ tiles turn into leaves at their rims, 2.6.
const FAR_BLOCK_COST: f64 = 1.5;

/// The coarsest transfer resolution divisor K: beyond it a handful of transfer voxels span any
/// real volume (`--scale` refuses more; a refusal suggests no more).
pub const MAX_SCALE: i32 = 64;

/// Share of available memory a bake may plan to use by default: the rest stays for the system
/// and other processes.
pub const DEFAULT_MEMORY_SHARE: f64 = 0.8;

/// The budget of work given no `--max-memory`: [`DEFAULT_MEMORY_SHARE`] of what the system can
/// still give, or of the control group's limit where that is smaller (a container, a farm job);
/// `None` where neither is known.
pub fn default_limit() -> Option<u64> {
    use crate::io::meminfo::{available_memory, cgroup_limit};
    let room = match (available_memory(), cgroup_limit()) {
        (Some(a), Some(c)) => Some(a.min(c)),
        (a, c) => a.or(c),
    };
    room.map(|r| (r as f64 * DEFAULT_MEMORY_SHARE) as u64)
}

/// Peak memory of a bake, estimated before anything big is allocated.
#[derive(Debug, Clone, Copy)]
pub struct MemoryEstimate {
    /// The density and its accelerators (bricks, occupancy), held through the whole bake.
    pub density: u64,
    pub layout: u64,
    /// T_ri and F_ms as kept in memory (f32).
    pub transfer: u64,
    /// What the largest phase holds beyond the density, the layout and the final T_ri and F_ms
    /// (the lattice's phases hold F_ms alone, so theirs counts one copy less).
    pub working: u64,
}

impl MemoryEstimate {
    /// `field_bytes`: the density with its accelerators, of which `brick_bytes` are released for
    /// the lattice's transport; `far`: the far field's coarser levels ([`far_field_bytes`]);
    /// `reflecting`: the share of cells that reflect ([`lattice::DensityMeans::reflecting_share`]).
    #[allow(clippy::too_many_arguments)]
    fn new(
        field_bytes: usize,
        brick_bytes: usize,
        layout_bytes: usize,
        voxels: usize,
        settings: &BakeSettings,
        footprints: bool,
        far: u64,
        reflecting: f64,
        threads: usize,
        visibility: VisibilityBytes,
        refined: Option<RefinedBytes>,
    ) -> MemoryEstimate {
        let (n, c) = (voxels as u64, (settings.bands * settings.bands) as u64);
        let one = n * c * 4;
        // What each phase holds beyond the density and the layout (`transfer::bake`):
        // - T_ri's passes: the direction sets' SH weights and the far field's coarser density,
        //   beside F_ms (the point values) and then, in the footprint pass, T_ri too, and a
        //   single-scattering bake's visibility, which draws the footprint means' starts;
        let sets = (single::DIRECTION_SETS * settings.samples) as u64 * c * 4;
        // - the fit: the mass matrix's rows and a CG solve's vectors a thread, beside both;
        let rows_of =
            |basis| n * (fit::row_bytes(basis) + threads as u64 * fit::solve_bytes(basis));
        let rows = rows_of(Basis::Tent);
        let (single, fit) = match footprints {
            true => (
                2 * one + sets + far + visibility.held,
                2 * one + rows + visibility.held,
            ),
            false => (one + sets + far, 0),
        };
        // - the lattice, beside F_ms and the coarser density kept for the footprint pass, or,
        //   where the point values are the direct light, beside them and the lattice's light in
        //   the bands it carries (widened to F_ms at the end, beside both): its links, with their
        //   places while they are built, and then the transport's state, the bricks released.
        let carried = settings.lattice.bands(settings.bands) as u64;
        let light = n * carried * carried * 4;
        let (beside, widen) = match footprints {
            true => (one + far, 0),
            false => (one + light, 2 * one + light),
        };
        let lattice = match settings.single_scatter {
            true => 0,
            false => beside + lattice_bytes(voxels, settings, reflecting, threads, brick_bytes),
        };
        // - a bake on finer cells ([`crate::transfer::refine`]) does the point values' and the
        //   lattice's phases there instead, and then fits both back beside the transfer.
        let (single, lattice) = match refined {
            Some(r) => (
                single.max(r.single + sets / refine::FINE_SAMPLE_SHARE as u64 + far),
                // The two layers' fitted columns side by side, then apart.
                r.lattice
                    .max(r.held + 2 * (one + light) + rows_of(refine::BASIS)),
            ),
            None => (single, lattice),
        };
        // - the visibility, before T_ri's footprint pass, beside F_ms: its sweep, then the
        //   visibility built and its fit (rows and solves as above).
        let shape = one
            + visibility
                .sweep
                .max(visibility.held + visibility.fit + rows);
        let peak = single.max(fit).max(lattice).max(shape).max(widen);
        MemoryEstimate {
            density: field_bytes as u64,
            layout: layout_bytes as u64,
            transfer: 2 * one + visibility.held,
            working: peak.saturating_sub(2 * one + visibility.held) + PROCESS_BASELINE,
        }
    }

    pub fn total(&self) -> u64 {
        self.density + self.layout + self.transfer + self.working
    }
}

/// What the visibility of a bake ([`crate::transfer::shape`]) holds while it is swept, once
/// built, and beside that while it is fitted.
#[derive(Debug, Clone, Copy, Default)]
pub struct VisibilityBytes {
    pub sweep: u64,
    pub held: u64,
    pub fit: u64,
}

/// Bytes per value of the visibility while it is swept: the voxel (3 × i32) and the running mean.
const SWEEP_POINT_BYTES: u64 = 16;

/// What one direction's shadow volume may hold while the visibility is swept, at least: a volume
/// of huge tiles would need one in proportion to its volume (a 4096³ tile: about 400 GB at the
/// density's resolution), so its visibility is swept at a coarser level, where the tiles' uniform
/// interiors lose nothing. Above this floor the density's own bytes are the budget.
const VISIBILITY_SWEEP_FLOOR: u64 = 256 << 20;

/// One direction's shadow volume over `field`'s density at `level`, estimated: a coarse level
/// holds an eighth of the blocks per level, each costing [`FAR_BLOCK_COST`] times as much.
fn sweep_bytes(field: &DensityField, level: usize) -> u64 {
    let fine = crate::volume::shadow::ShadowVolume::estimate_bytes(&field.grid);
    match level {
        0 => fine,
        l => (FAR_BLOCK_COST * (fine >> (3 * l).min(63)) as f64) as u64,
    }
}

/// `wanted`, at the first level from its own whose sweep fits [`VISIBILITY_SWEEP_FLOOR`] or the
/// density's bytes, whichever is more.
pub fn visibility_resolution(field: &DensityField, wanted: Resolution) -> Resolution {
    let budget =
        VISIBILITY_SWEEP_FLOOR.max((field.grid.memory_bytes() + field.brick_bytes()) as u64);
    let level = (wanted.level..MAX_LEVEL)
        .find(|&l| sweep_bytes(field, l) <= budget)
        .unwrap_or(MAX_LEVEL);
    Resolution { level, ..wanted }
}

/// The visibility of `field` at `resolution`, estimated without building it. While it is swept:
/// one shadow volume at the level and each value's voxel and running mean (at a coarse level
/// beside that level's density). Kept: its values (f16) and ρ·V on the level's topology with its
/// bricks, at a coarse level beside that level's density — each about what the density costs at
/// that level ([`far_field_bytes`]). While it is fitted, at a coarse level: ρ·V on the density's
/// own topology.
pub fn visibility_bytes(field: &DensityField, resolution: Resolution) -> VisibilityBytes {
    let grid = &field.grid;
    let level = resolution.level;
    let tiles = |level: TileLevel| grid.tiles(level).count() as u64;
    // Voxels kept one by one: the leaves' active ones and the 8³ tiles'.
    let voxels = grid
        .leaves()
        .iter()
        .map(|l| l.active_count() as u64)
        .sum::<u64>()
        + tiles(TileLevel::Block) * TileLevel::Block.voxel_count();
    // A larger tile keeps one value at the density. Coarsened, a 128³ tile halves into 512 tiles
    // of 8³ and a 4096³ one into 4096 of 128³; 8³ tiles go eight into one a level.
    let shrink = |n: u64, levels: usize| (n >> (3 * levels).min(63)).max(1);
    let (node, root) = match level {
        0 => (1, 1),
        1 => (512, 4096),
        l => (shrink(512, l - 1), shrink(4096 * 512, l - 2)),
    };
    let values = shrink(voxels, level).min(voxels)
        + tiles(TileLevel::Node) * node
        + tiles(TileLevel::Root) * root;
    let sweep = sweep_bytes(field, level) + SWEEP_POINT_BYTES * values;
    match level {
        0 => VisibilityBytes {
            sweep,
            held: (grid.memory_bytes() + field.brick_bytes()) as u64 + 2 * values,
            fit: 0,
        },
        level => {
            let coarse = far_field_bytes(field, level);
            VisibilityBytes {
                sweep: sweep + coarse,
                held: 2 * coarse + 2 * values,
                fit: grid.memory_bytes() as u64,
            }
        }
    }
}

/// Bytes of a lattice link's record in its sweep.
const LINK_RECORD_BYTES: u64 = 20;
/// Bytes of a reflecting cell's λ per direction.
const REFLECTANCE_BYTES: f64 = 4.0;

/// Bytes of the links of `nodes` cells along `directions`, `reflecting` the share of cells that
/// reflect.
fn link_bytes(nodes: u64, directions: usize, reflecting: f64) -> u64 {
    let per_cell = LINK_RECORD_BYTES as f64 + reflecting * REFLECTANCE_BYTES;
    (nodes as f64 * directions as f64 * per_cell) as u64
}
/// Bytes per link of its place in its sweep, held while the links are built.
const LINK_PLACE_BYTES: u64 = 4;
/// Bytes of a row of a chunk's transport state: `lattice::CHUNK` f32 lanes.
const TRANSPORT_ROW_BYTES: u64 = lattice::CHUNK as u64 * 4;
/// Bytes of a row of a sun's transport state: its one f32.
const SUN_TRANSPORT_ROW_BYTES: u64 = 4;

/// One transport's state beside the links: per node its fluence, emission and next emission and
/// the fluence before the last generation (for the tail), and per reflecting cell a buffer per
/// pair of opposite directions.
fn transport_bytes(voxels: usize, directions: usize, reflecting: f64, row_bytes: u64) -> u64 {
    let rows = 4.0 + reflecting * (directions / 2) as f64;
    (rows * voxels as f64) as u64 * row_bytes
}

/// Working memory of a lattice over `voxels` cells ([`lattice::Lattice::bake_multiple`]) beside
/// what it adds to: its links, with their places while they are built, and then the
/// transport's state, the bricks (`brick_bytes`) released.
fn lattice_bytes(
    voxels: usize,
    settings: &BakeSettings,
    reflecting: f64,
    threads: usize,
    brick_bytes: usize,
) -> u64 {
    let (n, d) = (voxels as u64, settings.lattice.directions());
    let links = link_bytes(n, d, reflecting);
    let build = links + n * d as u64 * LINK_PLACE_BYTES;
    // Small lattices transport a chunk a thread, large ones one chunk at a time.
    let in_flight = match voxels >= lattice::PARALLEL_SWEEP_LINKS {
        true => 1,
        false => threads
            .min(lattice::chunks_transported(
                settings.lattice,
                settings.bands,
            ))
            .max(1) as u64,
    };
    let transport = (links
        + in_flight * transport_bytes(voxels, d, reflecting, TRANSPORT_ROW_BYTES))
    .saturating_sub(brick_bytes as u64);
    build.max(transport)
}

/// What a bake on finer cells ([`crate::transfer::refine`]) holds beyond the density and the
/// transfer's layout: while it traces the finer point values (the direction sets and far field
/// aside), while its lattice runs, and the finer values kept while they are fitted back.
#[derive(Debug, Clone, Copy)]
pub struct RefinedBytes {
    pub single: u64,
    pub lattice: u64,
    pub held: u64,
}

impl RefinedBytes {
    /// For `nodes` finer cells of edge `fine`, the bricks (`brick_bytes`) released while the
    /// lattice runs.
    fn new(
        density: &SparseGrid,
        nodes: u64,
        fine: i32,
        settings: &BakeSettings,
        medium: Medium,
        threads: usize,
        brick_bytes: usize,
    ) -> RefinedBytes {
        let c = (settings.bands * settings.bands) as u64;
        let carried = settings.lattice.bands(settings.bands) as u64;
        let layout = nodes * LAYOUT_BYTES_PER_VOXEL;
        let (points, light) = (nodes * c * 4, nodes * carried * carried * 4);
        let reflecting = lattice::DensityMeans::new(density).reflecting_share(
            medium.sigma_t,
            fine,
            settings.lattice,
        );
        let voxels = usize::try_from(nodes).unwrap_or(usize::MAX);
        let transport = lattice_bytes(voxels, settings, reflecting, threads, brick_bytes);
        RefinedBytes {
            single: layout + points,
            lattice: layout + points + light + transport,
            held: layout + points + light,
        }
    }
}

/// The most a bake on `nodes` finer cells of edge `fine` holds beyond the density and the
/// transfer: what [`crate::transfer::refine::fine_scale`] bounds. Reckoned with one thread
/// and the bricks kept, so the answer, and the cache, are the same on every machine.
pub fn refined_bytes(
    density: &SparseGrid,
    nodes: u64,
    fine: i32,
    settings: &BakeSettings,
    medium: Medium,
) -> u64 {
    let r = RefinedBytes::new(density, nodes, fine, settings, medium, 1, 0);
    r.single.max(r.lattice)
}

/// Working memory of one sun's multiple-scattering solve on a lattice of `directions` over
/// `transfer_voxels` ([`lattice::solve_emission`]), `reflecting` the share of cells that reflect:
/// its links while they are built, or beside the transport of its one value a node and, where
/// GMRES solves it, GMRES's vectors ([`sun_krylov_bytes`]).
pub fn sun_solve_bytes(transfer_voxels: usize, directions: usize, reflecting: f64) -> u64 {
    let links = link_bytes(transfer_voxels as u64, directions, reflecting);
    let build = transfer_voxels as u64 * directions as u64 * LINK_PLACE_BYTES;
    let transport = transport_bytes(
        transfer_voxels,
        directions,
        reflecting,
        SUN_TRANSPORT_ROW_BYTES,
    );
    let krylov = sun_krylov_bytes(transfer_voxels as u64, directions, reflecting).unwrap_or(0);
    links + build.max(transport + krylov)
}

/// Bytes of the working vectors of a sun's GMRES solve over `nodes` cells along `directions`,
/// `reflecting` the share of cells that reflect ([`lattice::solve_emission`]); `None` where they
/// would weigh more than the links, and the solve sums generations instead. Its state is a
/// node's emission and a reflecting cell's waiting light per pair of directions: 4 bytes a node
/// where no cell reflects (100 for GMRES's vectors, against 520 of links), up to 56 where every
/// cell does (1400). Where most cells reflect, reflected light stays near its cell and the
/// generations converge fast at albedo 0.9 (10–13 of them on the bench cloud's cells of 3 and the
/// fixture cloud's voxels at σt 3); at 0.99 GMRES would halve the solve there (the fixture at
/// σt 3: 4.3 → 2.0 s) but raise the peak by about as much as the links weigh (115 → 178 MiB on
/// the bench cloud).
pub fn sun_krylov_bytes(nodes: u64, directions: usize, reflecting: f64) -> Option<u64> {
    let state = nodes as f64 * (1.0 + reflecting * (directions / 2) as f64);
    let bytes =
        (krylov::working_vectors(lattice::RESTART) as f64 * state) as u64 * SUN_TRANSPORT_ROW_BYTES;
    (bytes <= link_bytes(nodes, directions, reflecting)).then_some(bytes)
}

/// Above this many transfer voxels (by [`TransferLayout::estimate_len`]) a plan estimates the
/// bake instead of laying it out: listing them would take gigabytes and minutes, and a bake of so
/// many needs tens of gigabytes (16 M voxels × 100 coefficients × 4 bytes × at least four copies).
pub const MAX_LAID_OUT_VOXELS: u64 = 16_000_000;
/// Bytes of layout per transfer voxel (its coordinate, its slot in a 4³ tile, the tile index's
/// share), for a plan that estimates.
const LAYOUT_BYTES_PER_VOXEL: u64 = 20;

/// What a bake of a density with given settings will make, before it runs.
#[derive(Debug, Clone, Copy)]
pub struct BakePlan {
    pub transfer_voxels: usize,
    pub transfer_tiles: usize,
    pub estimate: MemoryEstimate,
    /// The counts are estimated ([`MAX_LAID_OUT_VOXELS`]), not counted.
    pub estimated: bool,
    /// Bytes of the coarser levels of the density T_ri's rays will read ([`far_field_bytes`]).
    pub far_bytes: u64,
    /// The medium, kept so a refusal can estimate other scales (their cells are thicker or
    /// thinner).
    pub medium: Medium,
    /// The edge of the finer cells the light is baked on ([`refine`]), if it is.
    pub fine_scale: Option<i32>,
}

impl BakePlan {
    pub fn new(field: &DensityField, settings: &BakeSettings, medium: Medium) -> BakePlan {
        let sigma_t = medium.sigma_t;
        let levels = single::far_field(&field.grid, sigma_t, settings.samples).1;
        let far = far_field_bytes(field, levels);
        let reflecting = lattice::DensityMeans::new(&field.grid).reflecting_share(
            sigma_t,
            settings.scale,
            settings.lattice,
        );
        let fine_scale = refine::fine_scale(&field.grid, medium, settings);
        let about = TransferLayout::estimate_len(&field.grid, settings.scale);
        if about > MAX_LAID_OUT_VOXELS {
            let n = usize::try_from(about).unwrap_or(usize::MAX);
            let layout = about.saturating_mul(LAYOUT_BYTES_PER_VOXEL);
            return BakePlan {
                transfer_voxels: n,
                transfer_tiles: n / 64,
                estimate: estimate(
                    field,
                    layout as usize,
                    n,
                    settings,
                    (medium, fine_scale),
                    far,
                    reflecting,
                ),
                estimated: true,
                far_bytes: far,
                medium,
                fine_scale,
            };
        }
        let layout = TransferLayout::build(&field.grid, settings.scale);
        BakePlan {
            transfer_voxels: layout.len(),
            transfer_tiles: layout.tile_count(),
            estimate: estimate(
                field,
                layout.memory_bytes(),
                layout.len(),
                settings,
                (medium, fine_scale),
                far,
                reflecting,
            ),
            estimated: false,
            far_bytes: far,
            medium,
            fine_scale,
        }
    }

    /// The estimate as one line: counts, total and its parts.
    pub fn describe(&self) -> String {
        let e = &self.estimate;
        let finer = self.fine_scale.map_or(String::new(), |k| {
            format!(" (thick: light baked on cells of {k} and fitted back)")
        });
        format!(
            "{}{} transfer voxels in {} tiles{finer}; estimated peak memory {} (density {}, transfer {}, working {})",
            if self.estimated { "about " } else { "" },
            self.transfer_voxels,
            self.transfer_tiles,
            human(e.total()),
            human(e.density),
            human(e.transfer),
            human(e.working)
        )
    }

    /// Refuses a bake estimated above `limit` (`None`: [`default_limit`]), naming the `--scale`, `--bands` and `--lattice` that would
    /// need less.
    pub fn check_budget(
        &self,
        field: &DensityField,
        settings: &BakeSettings,
        limit: Option<u64>,
    ) -> Result<()> {
        let limit = limit.or_else(default_limit);
        let Some(limit) = limit.filter(|l| self.estimate.total() > *l) else {
            return Ok(());
        };
        let layout_bytes = self.estimate.layout as usize;
        let n = self.transfer_voxels;
        let s = *settings;
        let fewer = BakeSettings {
            bands: s.bands.saturating_sub(2).max(1),
            ..s
        };
        let faces = BakeSettings {
            lattice: LatticeKind::Faces,
            ..s
        };
        let means = lattice::DensityMeans::new(&field.grid);
        let reflecting = |k, kind| means.reflecting_share(self.medium.sigma_t, k, kind);
        let need = |settings: &BakeSettings, voxels: usize| {
            let r = reflecting(settings.scale, settings.lattice);
            estimate(
                field,
                layout_bytes,
                voxels,
                settings,
                (
                    self.medium,
                    refine::fine_scale(&field.grid, self.medium, settings),
                ),
                self.far_bytes,
                r,
            )
            .total()
        };
        // The finest coarser K that fits, from the estimated count at each K.
        let coarser = (s.scale + 1..=MAX_SCALE).find_map(|k| {
            let about = TransferLayout::estimate_len(&field.grid, k);
            let voxels = usize::try_from(about).unwrap_or(usize::MAX);
            let bytes = (about.saturating_mul(LAYOUT_BYTES_PER_VOXEL)) as usize;
            let at_k = BakeSettings { scale: k, ..s };
            let total = estimate(
                field,
                bytes,
                voxels,
                &at_k,
                (
                    self.medium,
                    refine::fine_scale(&field.grid, self.medium, &at_k),
                ),
                self.far_bytes,
                reflecting(k, s.lattice),
            )
            .total();
            (total <= limit).then_some((k, total))
        });
        let coarser = match coarser {
            Some((k, total)) => format!("--scale {k} would need about {}", human(total)),
            None => format!("no --scale up to {MAX_SCALE} would fit"),
        };
        Err(Error::Runtime(format!(
            "this bake needs about {} but may use {} (--max-memory); {coarser}, --bands {} about {}, --lattice 6 about {}",
            human(self.estimate.total()),
            human(limit),
            fewer.bands,
            human(need(&fewer, n)),
            human(need(&faces, n)),
        )))
    }
}

/// Bytes per transfer voxel of relit radiance: direct and indirect RGB, f32.
pub const RADIANCE_BYTES_PER_TRANSFER_VOXEL: u64 = 24;
/// Bytes per pixel of a frame: RGBA, the direct and indirect RGB layers and depth, f32 each.
const FRAME_BYTES_PER_PIXEL: u64 = 4 * (4 + 3 + 3 + 1);
/// Bands of rows an EXR write holds at once: the one being rendered and the one being
/// compressed, whose lines' bytes are unmapped as they are written (measured at 1920 wide: about
/// 11 MiB beyond the volume on the fixture and cloud_large, 2 bands; 3.7 while the allocator
/// kept freed blocks, `crate::io::meminfo::return_large_blocks_when_freed`).
const EXR_BANDS_IN_FLIGHT: u64 = 2;
/// Bands of rows a PNG write holds at once: the one being rendered and the one being tonemapped.
const PNG_BANDS_IN_FLIGHT: u64 = 2;
/// A render's process before it reads anything: code, thread stacks, the allocator (a 16×9
/// render of the 1.4 MB fixture's cache peaks at 13.7 MiB, 5.4 MiB of it volume and transfer).
const RENDER_BASELINE: u64 = 8 << 20;
/// Resident memory beyond the volume and the transfer, per byte of them: what the allocator keeps
/// of the cache read and the field's build, measured 0.0–0.13 of them at 16×9 on the bench caches
/// (0.10 and 0.07 on the half-size cloud's q8 and f32 caches, docs/benchmarks.md "Render memory").
const RENDER_SLACK: f64 = 0.1;

/// Bytes the image of a `width`×`height` render holds while it is rendered and written
/// ([`crate::io::image::write_bands`]): a few bands of rows for an EXR, one band and the whole
/// image's 8-bit RGBA pixels for a PNG.
pub fn image_bytes(width: u32, height: u32, png: bool) -> u64 {
    let band = crate::render::band_rows(width).min(height) as u64 * width as u64;
    match png {
        true => {
            PNG_BANDS_IN_FLIGHT * band * FRAME_BYTES_PER_PIXEL + width as u64 * height as u64 * 4
        }
        false => EXR_BANDS_IN_FLIGHT * band * FRAME_BYTES_PER_PIXEL,
    }
}

/// Peak memory of a render, estimated before the light and the frame are allocated: the larger of
/// its two phases, a new sun's multiple-scattering solve (its links beside the shadow volumes)
/// and the march (relit nodes and the image beside them).
#[derive(Debug, Clone, Copy)]
pub struct RenderEstimate {
    /// The density and its accelerators.
    pub volume: u64,
    /// The transfer's layout, T_ri and F_ms as held (or the radiance relit from them as read),
    /// and what relighting makes beside them.
    pub transfer: u64,
    /// The relight's share of `transfer`: held only after the suns are solved.
    march: u64,
    /// The suns' shadow volumes and fluences, where not kept from an earlier render.
    pub light: u64,
    /// A new sun's multiple-scattering solve ([`sun_solve_bytes`]; 0 without one).
    pub solve: u64,
    /// The frame's buffers ([`image_bytes`]).
    pub image: u64,
}

impl RenderEstimate {
    /// `bricks`: whether the render holds the density's bricks
    /// ([`crate::scene::Scene::render_bricks`]); `relight`: what relighting makes
    /// ([`crate::scene::Scene::relight_plan`]); `coefficient_bytes`: T_ri and F_ms as held;
    /// `light`: [`crate::scene::Scene::sun_plan`]; `solve`: [`sun_solve_bytes`] when a new sun
    /// will be solved; `image`: [`image_bytes`].
    pub fn new(
        field: &DensityField,
        bricks: bool,
        relight: u64,
        coefficient_bytes: usize,
        light: u64,
        solve: u64,
        image: u64,
    ) -> RenderEstimate {
        RenderEstimate {
            volume: (field.grid.memory_bytes()
                + field.occupancy.memory_bytes()
                + if bricks { field.brick_bytes() } else { 0 }) as u64,
            transfer: coefficient_bytes as u64 + relight,
            march: relight,
            light,
            solve,
            image,
        }
    }

    /// The estimated peak resident memory, the process's own baseline included.
    pub fn total(&self) -> u64 {
        let slack = ((self.volume + self.transfer) as f64 * RENDER_SLACK) as u64;
        let held = self.volume + self.transfer - self.march;
        RENDER_BASELINE + held + slack + self.light + self.solve.max(self.march + self.image)
    }

    /// One line for `--dry-run`.
    pub fn describe(&self) -> String {
        format!(
            "estimated peak memory {} (volume {}, transfer {}, suns {}, image {}{})",
            human(self.total()),
            human(self.volume),
            human(self.transfer),
            human(self.light),
            human(self.image),
            self.describe_solve()
        )
    }

    /// The sun solve's part of a description, when there is one.
    fn describe_solve(&self) -> String {
        match self.solve {
            0 => String::new(),
            b => format!(", a sun's lattice solve {} while it runs", human(b)),
        }
    }

    /// Refuses the render if its estimate is above `limit` (`None`: [`default_limit`]), naming
    /// what would fit.
    pub fn check_budget(&self, limit: Option<u64>) -> Result<()> {
        let limit = limit.or_else(default_limit);
        match limit.filter(|l| self.total() > *l) {
            None => Ok(()),
            Some(limit) => Err(Error::Runtime(format!(
                "this render needs about {} (the volume {}, its transfer {}, suns {}, the image {}{}) but may use {} (--max-memory); fewer suns, a smaller --res, or a volume with fewer active voxels would fit",
                human(self.total()),
                human(self.volume),
                human(self.transfer),
                human(self.light),
                human(self.image),
                self.describe_solve(),
                human(limit)
            ))),
        }
    }
}

/// Bytes of `levels` coarser levels of `field`'s density ([`crate::volume::mip::DensityMip`]),
/// estimated without building them: a level holds a block wherever the level below has a leaf or
/// an 8³ tile in it, and each costs [`FAR_BLOCK_COST`] times what the density costs a block.
/// (Their share of the density runs from 0.21 to 0.57 on the bench inputs; building them to count
/// them left their freed memory in the allocator's heap under the bake.)
fn far_field_bytes(field: &DensityField, levels: usize) -> u64 {
    let grid = &field.grid;
    let mut blocks: Vec<IVec3> = grid
        .leaves()
        .iter()
        .map(|leaf| leaf.origin >> LEAF_LOG2 as i32)
        .chain(
            grid.tiles(TileLevel::Block)
                .map(|(o, _)| o >> LEAF_LOG2 as i32),
        )
        .collect();
    let fine = blocks.len();
    if fine == 0 {
        return 0;
    }
    let mut coarse = 0;
    for _ in 0..levels {
        blocks.iter_mut().for_each(|b| *b = *b >> 1);
        blocks.sort_unstable_by_key(|b| (b.x, b.y, b.z));
        blocks.dedup();
        coarse += blocks.len();
    }
    let per_block = (grid.memory_bytes() + field.brick_bytes()) as f64 / fine as f64;
    (FAR_BLOCK_COST * per_block * coarse as f64) as u64
}

/// The estimate of a bake of `voxels` transfer voxels at `settings`, of `medium` on the finer
/// cells `fine_scale` decided for it ([`refine::fine_scale`], asked once by the caller).
fn estimate(
    field: &DensityField,
    layout_bytes: usize,
    voxels: usize,
    settings: &BakeSettings,
    (medium, fine_scale): (Medium, Option<i32>),
    far: u64,
    reflecting: f64,
) -> MemoryEstimate {
    let visibility = match settings.single_scatter {
        true => visibility_bytes(
            field,
            crate::transfer::shape::TransferShape::resolution(field),
        ),
        false => VisibilityBytes::default(),
    };
    let threads = rayon::current_num_threads();
    let refined = fine_scale.map(|fine| {
        // A finer bake is only chosen where its layout was counted (`refine::fine_scale`).
        let nodes = TransferLayout::build(&field.grid, fine).len() as u64;
        RefinedBytes::new(
            &field.grid,
            nodes,
            fine,
            settings,
            medium,
            threads,
            field.brick_bytes(),
        )
    });
    MemoryEstimate::new(
        field.grid.memory_bytes() + field.brick_bytes(),
        field.brick_bytes(),
        layout_bytes,
        voxels,
        settings,
        settings.fits_footprints(&field.grid, medium),
        far,
        reflecting,
        threads,
        visibility,
        refined,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::mip::DensityMip;

    #[test]
    fn the_far_field_estimate_follows_the_levels_built() {
        // The fixtures' three levels, counted by their blocks against built: measured 1.03 (cloud)
        // and 1.17 (torus) of the built bytes.
        for file in ["cloud.vdb", "torus.vdb"] {
            let field = DensityField::new(crate::transfer::tests::load(file));
            let built = DensityMip::build(&field.grid, 3).memory_bytes() as f64;
            let estimated = far_field_bytes(&field, 3) as f64;
            let ratio = estimated / built;
            assert!((0.9..1.3).contains(&ratio), "{file}: {ratio}");
        }
        let field = DensityField::new(crate::transfer::tests::load("cloud.vdb"));
        assert_eq!(far_field_bytes(&field, 0), 0);
    }

    #[test]
    fn a_streamed_exr_holds_bands_not_the_frame() {
        // 1920 wide: bands of 64 rows, two in flight, whatever the height.
        let band = 64 * 1920 * FRAME_BYTES_PER_PIXEL;
        assert_eq!(image_bytes(1920, 1080, false), 2 * band);
        assert_eq!(image_bytes(1920, 4320, false), 2 * band);
        // A PNG keeps its 8-bit pixels besides the bands being rendered and tonemapped.
        assert_eq!(image_bytes(1920, 1080, true), 2 * band + 1920 * 1080 * 4);
        // A frame shorter than a band is one band.
        assert_eq!(
            image_bytes(100, 10, false),
            2 * 1000 * FRAME_BYTES_PER_PIXEL
        );
    }
}
