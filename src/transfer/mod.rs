//! The transfer: per transfer voxel, SH coefficients of the fraction of environment light from each
//! direction that reaches it — unscattered (`t_ri`, thesis eq. 4.1) and after one or more
//! scattering events (`f_ms`, thesis 4.2) — independent of any environment.

pub mod cache;
pub mod fit;
pub mod grid;
pub mod lattice;
pub mod single;

pub use grid::TransferLayout;

/// The participating medium (DESIGN.md): σt = `sigma_t`·ρ per world unit, σs = `albedo`·σt,
/// isotropic phase.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Medium {
    pub sigma_t: f32,
    pub albedo: f32,
}

/// A baked transfer over a sparse layout: `bands²` coefficients per voxel, voxel after voxel.
#[derive(Clone)]
pub struct Transfer {
    pub layout: TransferLayout,
    pub bands: usize,
    pub medium: Medium,
    /// Unscattered transfer T_ri, `layout.len() × bands²`.
    pub t_ri: Vec<f32>,
    /// Multiply-scattered transfer F_ms (zero after a `--single-scatter` bake), same shape.
    pub f_ms: Vec<f32>,
}

impl Transfer {
    pub fn coeffs(&self) -> usize {
        self.bands * self.bands
    }

    /// T_ri coefficients of the voxel in `slot`.
    pub fn t_ri(&self, slot: usize) -> &[f32] {
        let n = self.coeffs();
        &self.t_ri[slot * n..(slot + 1) * n]
    }

    /// F_ms coefficients of the voxel in `slot`.
    pub fn f_ms(&self, slot: usize) -> &[f32] {
        let n = self.coeffs();
        &self.f_ms[slot * n..(slot + 1) * n]
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
    pub seed: u64,
}

/// What a bake did, for `--stats`.
#[derive(Debug, Clone, Default)]
pub struct BakeStats {
    pub layout_seconds: f64,
    pub single_seconds: f64,
    pub lattice_seconds: f64,
    pub transfer_voxels: usize,
    pub transfer_tiles: usize,
    pub lattice: Option<lattice::LatticeStats>,
}

/// Bakes the transfer of `density`: layout, T_ri, then (unless single-scatter) F_ms.
pub fn bake(
    density: &crate::volume::SparseGrid,
    medium: Medium,
    settings: &BakeSettings,
    quiet: bool,
) -> (Transfer, BakeStats) {
    let mut stats = BakeStats::default();
    let clock = std::time::Instant::now();
    let layout = TransferLayout::build(density, settings.scale);
    stats.layout_seconds = clock.elapsed().as_secs_f64();
    stats.transfer_voxels = layout.len();
    stats.transfer_tiles = layout.tile_count();

    // T_ri twice: at the nodes (the point values the lattice's light is balanced against) and
    // over the density around them (the footprint means the renderer's values are fitted to).
    let clock = std::time::Instant::now();
    let bar = crate::progress::bar(2 * layout.len() as u64, "single", quiet);
    let depth = crate::volume::transmittance::OpticalDepth::new(density, medium.sigma_t, true);
    let single = |origins| {
        let single = single::SingleSettings {
            bands: settings.bands,
            samples: settings.samples,
            seed: settings.seed,
            origins,
        };
        single::bake_single(density, &layout, &depth, single, &bar)
    };
    let point = single(single::Origins::Node);
    let mut t_ri = single(single::Origins::Footprint);
    drop(depth);
    fit::least_squares(density, &layout, &mut t_ri, settings.bands * settings.bands);
    bar.finish_and_clear();
    stats.single_seconds = clock.elapsed().as_secs_f64();

    let clock = std::time::Instant::now();
    let f_ms = match settings.single_scatter {
        true => vec![0.0; t_ri.len()],
        false => {
            let first = lattice::Source {
                t_ri: &point,
                bands: settings.bands,
                medium,
            };
            let (mut f_ms, lattice_stats) =
                lattice::bake_multiple(density, &layout, settings.lattice, &first);
            stats.lattice = Some(lattice_stats);
            // The unscattered light the fit takes away from a node's point value has collided
            // sooner; the share albedo of it is scattered. So T_ri + F_ms at a node is what it
            // is with point values, and at albedo 1 exactly so: the white furnace holds as before.
            for ((f, p), t) in f_ms.iter_mut().zip(&point).zip(&t_ri) {
                *f += medium.albedo * (p - t);
            }
            f_ms
        }
    };
    stats.lattice_seconds = clock.elapsed().as_secs_f64();
    let transfer = Transfer {
        layout,
        bands: settings.bands,
        medium,
        t_ri,
        f_ms,
    };
    (transfer, stats)
}

/// Resident memory of the process before a bake allocates anything (binary, thread stacks,
/// allocator arenas), measured as ~20 MB; the estimate counts it so it compares with peak RSS.
const PROCESS_BASELINE: u64 = 24 << 20;

/// Peak memory of a bake, estimated before anything big is allocated.
#[derive(Debug, Clone, Copy)]
pub struct MemoryEstimate {
    pub density: u64,
    pub layout: u64,
    /// T_ri and F_ms as kept in memory (f32).
    pub transfer: u64,
    /// The larger of the single-scattering and lattice phases' working memory.
    pub working: u64,
}

impl MemoryEstimate {
    /// `bricks_bytes`: the density's sampling bricks, which the single-scattering phase holds
    /// ([`crate::volume::bricks::Bricks::planned_bytes`]).
    pub fn new(
        density_bytes: usize,
        bricks_bytes: usize,
        layout_bytes: usize,
        voxels: usize,
        settings: &BakeSettings,
        threads: usize,
    ) -> MemoryEstimate {
        let (n, c) = (voxels as u64, (settings.bands * settings.bands) as u64);
        let one = n * c * 4;
        let sets = (single::DIRECTION_SETS * settings.samples) as u64 * c * 4;
        // Single: the point values kept beside the fitted T_ri, and batch results before they
        // are scattered into either (two more copies of T_ri); the density's bricks.
        let single = 2 * one + sets + bricks_bytes as u64;
        // Lattice: per-chunk results (one more copy); per link a target and four segment values
        // (20 bytes) and a sweep-order entry (4); four chunk buffers a thread.
        let d = settings.lattice.directions() as u64;
        // The point values of T_ri stay alive through the lattice (one more copy).
        let lattice = if settings.single_scatter {
            0
        } else {
            2 * one + n * d * 24 + threads as u64 * 4 * n * 8 * 4
        };
        MemoryEstimate {
            density: density_bytes as u64,
            layout: layout_bytes as u64,
            transfer: 2 * one,
            working: single.max(lattice) + PROCESS_BASELINE,
        }
    }

    pub fn total(&self) -> u64 {
        self.density + self.layout + self.transfer + self.working
    }
}
