//! `vscatter bake`: read a VDB density, plan the bake (memory estimate and budget), bake the
//! transfer (T_ri at the nodes, the lattice, then, where the bake fits footprints, T_ri fitted)
//! and write a `.vtc` cache — with a progress bar per phase and `--stats`.

use std::sync::atomic::{AtomicBool, Ordering};
use std::time::Instant;

use serde_json::json;

use super::args::{BakeCmd, GlobalArgs};
use vscatter::io::atomic::{check_writable, Inputs};
use vscatter::io::meminfo::peak_memory;
use vscatter::io::progress::Bars;
use vscatter::scene::{BakeConfig, Scene};
use vscatter::transfer::BakeStats;
use vscatter::Result;

/// Runs `vscatter bake`.
pub fn run(cmd: &BakeCmd, global: &GlobalArgs) -> Result<()> {
    let config = cmd.bake.validate()?;
    Inputs::new([cmd.input.as_path()]).check(&cmd.output, "-o")?;
    check_writable(&cmd.output)?;
    let mut scene = Scene::open(&cmd.input, &config)?;
    if scene.transfer.is_some() {
        return Err(vscatter::Error::usage(format!(
            "{}: already a transfer cache; bake reads a VDB file",
            cmd.input.display()
        )));
    }
    let Some(stats) = prepare_bake(&mut scene, &config, cmd.bake.dry_run, true, global)? else {
        return Ok(());
    };
    let clock = Instant::now();
    scene.write_cache(&cmd.output, &config)?;
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
        let mut j = bake_stats_json(&stats);
        j["load_seconds"] = json!(scene.read_seconds + scene.field_seconds);
        j["write_seconds"] = json!(write_seconds);
        j["peak_memory_bytes"] = json!(peak_memory());
        println!("{j}");
    }
    Ok(())
}

/// Plans the bake of `scene` and, unless `--dry-run` (which prints the plan and returns `None`),
/// checks the memory budget and bakes. Warnings come before a plan or a bake, never before a
/// refusal, so an error stays one line; `soft_light`: whether an environment's light will be
/// relit through the transfer (a render with `--env-scale 0` has none, so no warning about its
/// resolution).
pub fn prepare_bake(
    scene: &mut Scene,
    config: &BakeConfig,
    dry_run: bool,
    soft_light: bool,
    global: &GlobalArgs,
) -> Result<Option<BakeStats>> {
    let plan = scene.plan(config);
    let scale = soft_light.then_some(config.settings.scale);
    if dry_run {
        warn(&scene.warnings(scale));
        println!("{}", plan.describe());
        return Ok(None);
    }
    plan.check_budget(&scene.field, &config.settings, config.max_memory)?;
    warn(&scene.warnings(scale));
    Ok(Some(scene.bake(
        config,
        &Bars {
            quiet: global.quiet,
        },
    )))
}

/// Prints each warning as one line. `--quiet` hides progress, never a warning. Over many frames
/// ([`warn_once_per_run`]) only the first frame's warnings are printed: the next frames' say the
/// same with other digits.
pub fn warn(warnings: &[String]) {
    if warnings.is_empty() || (ONCE.load(Ordering::Relaxed) && WARNED.swap(true, Ordering::Relaxed))
    {
        return;
    }
    for w in warnings {
        eprintln!("vscatter: warning: {w}");
    }
}

/// Whether warnings are printed for the first frame only.
static ONCE: AtomicBool = AtomicBool::new(false);
/// Whether a frame's warnings have been printed.
static WARNED: AtomicBool = AtomicBool::new(false);

/// From now on, [`warn`] prints only the first frame's warnings (a batch, a sequence render).
pub fn warn_once_per_run() {
    ONCE.store(true, Ordering::Relaxed);
}

/// The `--stats` JSON of a bake.
pub fn bake_stats_json(stats: &BakeStats) -> serde_json::Value {
    json!({
        "layout_seconds": stats.layout_seconds,
        "single_seconds": stats.single_seconds,
        "lattice_seconds": stats.lattice_seconds,
        "transfer_voxels": stats.transfer_voxels,
        "transfer_tiles": stats.transfer_tiles,
        "far_field_bytes": stats.far_field_bytes,
        "fitted": stats.fitted,
        "lattice_scale": stats.lattice_scale,
        "visibility_seconds": stats.visibility_seconds,
        "visibility_bytes": stats.visibility_bytes,
        "lattice_generations": stats.lattice.map(|l| l.generations),
        "lattice_converged": stats.lattice.map(|l| l.converged),
        "energy_single": stats.lattice.map(|l| l.energy_single),
        "energy_multiple": stats.lattice.map(|l| l.energy_multiple),
        "energy_remaining": stats.lattice.map(|l| l.remaining),
    })
}
