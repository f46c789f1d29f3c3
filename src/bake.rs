//! `vscatter bake`: read a VDB density, estimate memory, bake the transfer (single scattering,
//! then the lattice), and write a `.vtc` cache — with a progress bar per phase and `--stats`.

use std::path::Path;
use std::time::Instant;

use indicatif::HumanBytes as human;
use serde_json::json;

use crate::cli::{BakeCmd, BakeConfig, GlobalArgs};
use crate::error::{Error, Result};
use crate::transfer::cache::{self, Source};
use crate::transfer::{self, BakeSettings, BakeStats, MemoryEstimate, Transfer, TransferLayout};
use crate::volume::bricks::Bricks;
use crate::volume::{load_density, SparseGrid};

/// Share of available memory a bake may plan to use by default: the rest stays for the system
/// and other processes.
const DEFAULT_MEMORY_SHARE: f64 = 0.8;

/// Runs `vscatter bake`.
pub fn run(cmd: &BakeCmd, global: &GlobalArgs) -> Result<()> {
    let config = cmd.bake.validate()?;
    let clock = Instant::now();
    let density = load_density(&cmd.input, config.grid.as_deref())?;
    let load_seconds = clock.elapsed().as_secs_f64();
    let Some((transfer, stats)) = bake_checked(&density.grid, &config, global)? else {
        return Ok(());
    };
    let source = source_of(&cmd.input, &density.name)?;
    let header = cache::header(
        &density.grid,
        &transfer,
        &config.settings,
        source,
        config.half,
    );
    let clock = Instant::now();
    cache::write(&cmd.output, &header, &density.grid, &transfer)?;
    let write_seconds = clock.elapsed().as_secs_f64();
    if !global.quiet {
        eprintln!(
            "baked {} -> {}: {} transfer voxels, {}",
            cmd.input.display(),
            cmd.output.display(),
            stats.transfer_voxels,
            match &stats.lattice {
                Some(l) => format!("{} lattice generations", l.generations),
                None => "single scattering only".into(),
            }
        );
    }
    if global.stats {
        let mut j = stats_json(&stats);
        j["load_seconds"] = json!(load_seconds);
        j["write_seconds"] = json!(write_seconds);
        println!("{j}");
    }
    Ok(())
}

/// Bakes after checking the memory estimate against `--max-memory`; `None` for a dry run, which
/// prints the estimate instead.
pub fn bake_checked(
    density: &SparseGrid,
    config: &BakeConfig,
    global: &GlobalArgs,
) -> Result<Option<(Transfer, BakeStats)>> {
    let layout = TransferLayout::build(density, config.settings.scale);
    let threads = rayon::current_num_threads();
    let bricks = Bricks::planned_bytes(density);
    let estimate = |settings: &BakeSettings, voxels: usize| {
        MemoryEstimate::new(
            density.memory_bytes(),
            bricks,
            layout.memory_bytes(),
            voxels,
            settings,
            threads,
        )
    };
    let plan = estimate(&config.settings, layout.len());
    // Said before a dry run's estimate and before a real bake, not before a refusal: an error
    // stays one line.
    let warn = || {
        if let Some(warning) = resolution_warning(density, config).filter(|_| !global.quiet) {
            eprintln!("vscatter: warning: {warning}");
        }
    };
    if config.dry_run {
        warn();
        println!(
            "{} transfer voxels in {} tiles; estimated peak memory {} (density {}, transfer {}, working {})",
            layout.len(),
            layout.tile_count(),
            human(plan.total()),
            human(plan.density),
            human(plan.transfer),
            human(plan.working)
        );
        return Ok(None);
    }
    let limit = match config.max_memory {
        Some(m) => Some(m),
        None => available_memory().map(|a| (a as f64 * DEFAULT_MEMORY_SHARE) as u64),
    };
    if let Some(limit) = limit.filter(|l| plan.total() > *l) {
        let s = config.settings;
        // A coarser K shrinks the voxel count roughly with K³.
        let k2 = s.scale + 2;
        let shrink = (s.scale as f64 / k2 as f64).powi(3);
        let coarser = BakeSettings { scale: k2, ..s };
        let fewer = BakeSettings {
            bands: s.bands.saturating_sub(2).max(1),
            ..s
        };
        let lattice = BakeSettings {
            lattice: transfer::lattice::LatticeKind::Faces,
            ..s
        };
        return Err(Error::Runtime(format!(
            "this bake needs about {} but may use {} (--max-memory); --scale {} would need about {}, --bands {} about {}, --lattice 6 about {}",
            human(plan.total()),
            human(limit),
            k2,
            human(estimate(&coarser, (layout.len() as f64 * shrink) as usize).total()),
            fewer.bands,
            human(estimate(&fewer, layout.len()).total()),
            human(estimate(&lattice, layout.len()).total()),
        )));
    }
    drop(layout);
    warn();
    Ok(Some(transfer::bake(
        density,
        config.medium,
        &config.settings,
        global.quiet,
    )))
}

/// Optical depth per transfer voxel (σt × K × voxel size × mean density) above which the 1/K
/// resolution visibly costs accuracy: tools/accuracy.sh measures single scattering 12 % and
/// multiple scattering 8 % off the path tracer at 0.96 on the cloud (5 % and 4 % at 0.48).
pub const MAX_RESOLVED_CELL_DEPTH: f64 = 1.0;

/// The warning for a bake whose transfer voxels are too thick to resolve where light enters
/// (see [`MAX_RESOLVED_CELL_DEPTH`]), naming the flags that help.
pub fn resolution_warning(density: &SparseGrid, config: &BakeConfig) -> Option<String> {
    let stats = density.value_stats()?;
    let active = density.active_voxels();
    if active == 0 {
        return None;
    }
    let mean = stats.sum / active as f64;
    let voxel = density.transform.voxel_size().min_element();
    let k = config.settings.scale as f64;
    let depth = config.medium.sigma_t as f64 * k * voxel * mean;
    (depth > MAX_RESOLVED_CELL_DEPTH).then(|| {
        format!(
            "{depth:.2} optical depths per transfer voxel (σt {} × K {} × voxel {voxel:.3} × mean density {mean:.3}): \
             light enters within a fraction of a transfer voxel, so expect errors well above 10 % \
             (docs/accuracy.md); a smaller --scale helps, --sigma-t {:.3} keeps it at {MAX_RESOLVED_CELL_DEPTH}",
            config.medium.sigma_t,
            config.settings.scale,
            MAX_RESOLVED_CELL_DEPTH / (k * voxel * mean),
        )
    })
}

/// The `--stats` JSON of a bake.
pub fn stats_json(stats: &BakeStats) -> serde_json::Value {
    json!({
        "layout_seconds": stats.layout_seconds,
        "single_seconds": stats.single_seconds,
        "lattice_seconds": stats.lattice_seconds,
        "transfer_voxels": stats.transfer_voxels,
        "transfer_tiles": stats.transfer_tiles,
        "lattice_generations": stats.lattice.map(|l| l.generations),
        "lattice_converged": stats.lattice.map(|l| l.converged),
        "energy_single": stats.lattice.map(|l| l.energy_single),
        "energy_multiple": stats.lattice.map(|l| l.energy_multiple),
        "energy_remaining": stats.lattice.map(|l| l.remaining),
        "peak_memory_bytes": peak_memory(),
    })
}

/// Name, size and modification time of a bake's source file, as a cache records them.
pub fn source_of(path: &Path, grid: &str) -> Result<Source> {
    let meta = std::fs::metadata(path).map_err(|e| Error::io(path, e))?;
    let mtime = meta
        .modified()
        .ok()
        .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
        .map_or(0, |d| d.as_secs());
    Ok(Source {
        name: path
            .file_name()
            .map_or_else(String::new, |n| n.to_string_lossy().into_owned()),
        grid: grid.to_string(),
        size: meta.len(),
        mtime,
    })
}

/// A `kB` field of a `/proc` status file, in bytes.
fn proc_kb(file: &str, field: &str) -> Option<u64> {
    let text = std::fs::read_to_string(file).ok()?;
    let line = text.lines().find(|l| l.starts_with(field))?;
    let kb: u64 = line[field.len()..]
        .trim()
        .trim_end_matches("kB")
        .trim()
        .parse()
        .ok()?;
    Some(kb * 1024)
}

/// Memory the system can still give (Linux's `MemAvailable`); `None` where unknown.
fn available_memory() -> Option<u64> {
    proc_kb("/proc/meminfo", "MemAvailable:")
}

/// This process's peak resident memory (Linux's `VmHWM`).
pub fn peak_memory() -> Option<u64> {
    proc_kb("/proc/self/status", "VmHWM:")
}
