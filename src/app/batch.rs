//! `vscatter batch`: resolve the frames, take this task's share, clear what dead runs left, and
//! convert every frame whose cache is not current with [`vscatter::batch`] — with an overall
//! progress bar on a terminal, one timestamped line per frame and phase in a farm log, a summary
//! naming every frame that failed or is missing, and `--stats`.

use std::path::PathBuf;
use std::time::Instant;

use indicatif::HumanBytes;
use serde_json::json;

use super::args::{BatchArgs, GlobalArgs};
use super::bake::{warn, warn_once_per_run};
use super::progress::{names, FrameProgress};
use vscatter::batch::{Batch, FrameReport, Report, Status};
use vscatter::io::atomic::{check_writable, remove_stale_temporaries};
use vscatter::io::meminfo::peak_memory;
use vscatter::scene::{cache_is_current, Scene};
use vscatter::sequence;
use vscatter::transfer::memory::default_limit;
use vscatter::{Error, Result};

/// The memory budget when nothing says otherwise and the system does not tell (not Linux).
const FALLBACK_MEMORY: u64 = 4 << 30;

pub fn run(args: &BatchArgs, global: &GlobalArgs, threads: usize) -> Result<()> {
    let config = args.bake.validate()?;
    let (range, shard) = args.sequence.validate()?;
    let resolved = sequence::resolve(&args.inputs, range)?;
    let outputs = sequence::outputs_in(&args.out_dir, &resolved.frames, "vtc")?;
    let mut jobs: Vec<(PathBuf, PathBuf)> = resolved
        .frames
        .iter()
        .map(|f| f.path.clone())
        .zip(outputs)
        .collect();
    let mut missing = resolved.missing;
    if let Some(shard) = shard {
        jobs = shard.select(jobs);
        missing = shard.select(missing);
    }
    // The output directory is made and tried before any bake, so a typo costs nothing.
    std::fs::create_dir_all(&args.out_dir)
        .map_err(|e| Error::Runtime(format!("{}: cannot be made ({e})", args.out_dir.display())))?;
    check_writable(&args.out_dir.join("batch"))?;
    for gone in remove_stale_temporaries(&args.out_dir)? {
        if !global.quiet {
            eprintln!(
                "removed {} (left by a process that is gone)",
                gone.display()
            );
        }
    }
    if !missing.is_empty() {
        eprintln!(
            "vscatter: warning: {} frames missing: {}",
            missing.len(),
            names(&missing)
        );
    }
    if args.bake.dry_run {
        return dry_run(&jobs, &config, args.sequence.force);
    }

    let memory = config
        .max_memory
        .or_else(default_limit)
        .unwrap_or(FALLBACK_MEMORY);
    let batch = Batch {
        jobs: &jobs,
        config: &config,
        force: args.sequence.force,
        memory,
        workers: threads,
    };
    let clock = Instant::now();
    warn_once_per_run();
    let inputs: Vec<PathBuf> = jobs.iter().map(|(i, _)| i.clone()).collect();
    let progress = FrameProgress::new(&inputs, "batch", global.quiet);
    let reports = batch.run(&progress);
    progress.finish();

    let count = |s: &str| reports.iter().filter(|r| r.status.name() == s).count();
    let failed: Vec<&FrameReport> = reports
        .iter()
        .filter(|r| matches!(r.status, Status::Failed(_)))
        .collect();
    if !global.quiet {
        eprintln!(
            "batch: {} frames in {:.1} s: {} baked, {} current, {} failed, {} missing",
            jobs.len() + missing.len(),
            clock.elapsed().as_secs_f64(),
            count("baked"),
            count("current"),
            failed.len(),
            missing.len()
        );
    }
    if global.stats {
        let frames: Vec<_> = reports.iter().map(frame_json).collect();
        let j = json!({
            "command": "batch",
            "frames": frames,
            "missing": missing.iter().map(|p| p.display().to_string()).collect::<Vec<_>>(),
            "baked": count("baked"),
            "current": count("current"),
            "failed": failed.len(),
            "wall_seconds": clock.elapsed().as_secs_f64(),
            "workers": threads.min(jobs.len()),
            "memory_budget_bytes": memory,
            "peak_memory_bytes": peak_memory(),
        });
        println!("{j}");
    }
    if failed.is_empty() && missing.is_empty() {
        return Ok(());
    }
    let failed_paths: Vec<PathBuf> = failed.iter().map(|r| r.input.clone()).collect();
    let mut what = Vec::new();
    if !failed.is_empty() {
        what.push(format!(
            "{} failed ({})",
            failed.len(),
            names(&failed_paths)
        ));
    }
    if !missing.is_empty() {
        what.push(format!("{} missing ({})", missing.len(), names(&missing)));
    }
    Err(Error::Runtime(format!(
        "batch incomplete: of {} frames, {}",
        jobs.len() + missing.len(),
        what.join(", ")
    )))
}

/// `--dry-run`: what each frame would do, one line each, and nothing baked.
fn dry_run(
    jobs: &[(PathBuf, PathBuf)],
    config: &vscatter::scene::BakeConfig,
    force: bool,
) -> Result<()> {
    for (input, output) in jobs {
        if !force && cache_is_current(input, output, config)? {
            println!("{}: current ({})", input.display(), output.display());
            continue;
        }
        let line = Scene::open(input, config)
            .map(|scene| scene.plan(config).describe())
            .unwrap_or_else(|e| format!("fails: {e}"));
        println!("{} -> {}: {line}", input.display(), output.display());
    }
    Ok(())
}

fn frame_json(r: &FrameReport) -> serde_json::Value {
    json!({
        "input": r.input.display().to_string(),
        "output": r.output.display().to_string(),
        "status": r.status.name(),
        "error": match &r.status { Status::Failed(e) => Some(e), _ => None },
        "read_seconds": r.read_seconds,
        "bake_seconds": r.bake_seconds,
        "write_seconds": r.write_seconds,
        "input_bytes": r.input_bytes,
        "output_bytes": r.output_bytes,
        "transfer_voxels": r.transfer_voxels,
        "estimated_bytes": r.estimated_bytes,
        "peak_memory_bytes": r.peak_memory,
    })
}

impl Report for FrameProgress {
    fn phase(&self, frame: usize, phase: &str) {
        FrameProgress::phase(self, frame, phase);
    }

    fn done(&self, frame: usize, r: &FrameReport) {
        self.suspend(|| warn(&r.warnings));
        let what = match &r.status {
            Status::Baked => format!(
                "baked -> {} ({}, {:.1} s)",
                r.output.display(),
                HumanBytes(r.output_bytes),
                r.read_seconds + r.bake_seconds + r.write_seconds
            ),
            Status::Current => format!("current ({})", r.output.display()),
            Status::Failed(_) => String::new(),
        };
        let failure = match &r.status {
            Status::Failed(e) => Some(e.as_str()),
            _ => None,
        };
        FrameProgress::done(self, frame, &what, failure);
    }
}
