//! Batch conversion of VDB frames to transfer caches: each frame goes through the same
//! [`Scene`] calls as `vscatter bake`; this module only decides which frames need it, runs
//! several at once within a memory budget, and reports each frame's phases and outcome.
//!
//! Small frames run side by side (one frame's reading and writing overlap another's bake on the
//! shared thread pool); a large frame takes the pool alone, because a frame starts only when its
//! estimated peak fits beside the frames already running.

use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Condvar, Mutex};
use std::time::Instant;

use indicatif::ProgressBar;

use crate::error::{Error, Result};
use crate::io::progress::Phases;
use crate::scene::{cache_is_current, BakeConfig, Scene};

/// What became of one frame.
#[derive(Debug, Clone, PartialEq)]
pub enum Status {
    /// Baked and written.
    Baked,
    /// Its cache was current: nothing done.
    Current,
    /// Not converted; the one-line reason.
    Failed(String),
}

impl Status {
    pub fn name(&self) -> &'static str {
        match self {
            Status::Baked => "baked",
            Status::Current => "current",
            Status::Failed(_) => "failed",
        }
    }
}

/// One frame's outcome, with what it cost.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameReport {
    pub input: PathBuf,
    pub output: PathBuf,
    pub status: Status,
    pub read_seconds: f64,
    pub bake_seconds: f64,
    pub write_seconds: f64,
    pub input_bytes: u64,
    pub output_bytes: u64,
    pub transfer_voxels: usize,
    /// The bake's estimated peak, what it held of the batch's memory budget.
    pub estimated_bytes: u64,
    /// What a user should know before trusting the frame's pictures ([`Scene::warnings`]).
    pub warnings: Vec<String>,
    /// The process's peak resident memory when the frame was done (frames in flight together
    /// share it).
    pub peak_memory: Option<u64>,
}

/// Where a batch says what it is doing: the phase a frame enters, and each frame's outcome.
/// Called from several threads at once.
pub trait Report: Sync {
    fn phase(&self, frame: usize, phase: &str);
    fn done(&self, frame: usize, report: &FrameReport);
}

/// A batch of frames to convert.
pub struct Batch<'a> {
    /// Each input with the cache it converts to.
    pub jobs: &'a [(PathBuf, PathBuf)],
    pub config: &'a BakeConfig,
    /// Bake even frames whose cache is current.
    pub force: bool,
    /// Bytes the frames running at once may plan to use together.
    pub memory: u64,
    /// Frames in flight at most.
    pub workers: usize,
}

impl Batch<'_> {
    /// Converts every frame, in order of the jobs as far as workers allow, and returns each one's
    /// report in the jobs' order. A frame that fails is reported and the rest go on.
    pub fn run(&self, report: &dyn Report) -> Vec<FrameReport> {
        let next = AtomicUsize::new(0);
        let budget = Budget::new(self.memory);
        let results: Mutex<Vec<Option<FrameReport>>> = Mutex::new(vec![None; self.jobs.len()]);
        let workers = self.workers.clamp(1, self.jobs.len().max(1));
        std::thread::scope(|scope| {
            for _ in 0..workers {
                scope.spawn(|| loop {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    let Some((input, output)) = self.jobs.get(i) else {
                        break;
                    };
                    let r = self.frame(i, input, output, &budget, report);
                    report.done(i, &r);
                    results.lock().unwrap_or_else(|e| e.into_inner())[i] = Some(r);
                });
            }
        });
        results
            .into_inner()
            .unwrap_or_else(|e| e.into_inner())
            .into_iter()
            .flatten()
            .collect()
    }

    /// Converts frame `i` unless its cache is current.
    fn frame(
        &self,
        i: usize,
        input: &Path,
        output: &Path,
        budget: &Budget,
        report: &dyn Report,
    ) -> FrameReport {
        let mut r = FrameReport {
            input: input.to_path_buf(),
            output: output.to_path_buf(),
            status: Status::Current,
            read_seconds: 0.0,
            bake_seconds: 0.0,
            write_seconds: 0.0,
            input_bytes: std::fs::metadata(input).map_or(0, |m| m.len()),
            output_bytes: 0,
            transfer_voxels: 0,
            estimated_bytes: 0,
            warnings: Vec::new(),
            peak_memory: None,
        };
        let outcome = (|| -> Result<Status> {
            if !self.force && cache_is_current(input, output, self.config)? {
                return Ok(Status::Current);
            }
            report.phase(i, "read");
            let clock = Instant::now();
            let mut scene = Scene::open(input, self.config)?;
            if scene.transfer.is_some() {
                return Err(Error::usage(format!(
                    "{}: already a transfer cache; batch reads VDB files",
                    input.display()
                )));
            }
            r.read_seconds = clock.elapsed().as_secs_f64();
            r.warnings = scene.warnings(Some(self.config.settings.scale));
            let plan = scene.plan(self.config);
            plan.check_budget(&scene.field, &self.config.settings, Some(budget.limit))?;
            r.estimated_bytes = plan.estimate.total();
            r.transfer_voxels = plan.transfer_voxels;
            let _held = budget.hold(r.estimated_bytes, || report.phase(i, "waiting for memory"));
            let clock = Instant::now();
            scene.bake(self.config, &FramePhases { frame: i, report });
            r.bake_seconds = clock.elapsed().as_secs_f64();
            report.phase(i, "write");
            let clock = Instant::now();
            scene.write_cache(output, self.config)?;
            r.write_seconds = clock.elapsed().as_secs_f64();
            Ok(Status::Baked)
        })();
        r.status = outcome.unwrap_or_else(|e| Status::Failed(e.to_string()));
        if !matches!(r.status, Status::Failed(_)) {
            r.output_bytes = std::fs::metadata(output).map_or(0, |m| m.len());
        }
        r.peak_memory = crate::io::meminfo::peak_memory();
        r
    }
}

/// A bake's phases, passed on to the batch's report under the frame's index.
struct FramePhases<'a> {
    frame: usize,
    report: &'a dyn Report,
}

impl Phases for FramePhases<'_> {
    fn phase(&self, phase: &str, _len: u64) -> ProgressBar {
        self.report.phase(self.frame, phase);
        ProgressBar::hidden()
    }
}

/// Bytes of memory the frames in flight have planned for, against a limit: a frame waits until
/// its estimate fits beside the others' (a frame alone always runs: its own estimate was checked
/// against the whole limit).
struct Budget {
    limit: u64,
    used: Mutex<u64>,
    freed: Condvar,
}

impl Budget {
    fn new(limit: u64) -> Budget {
        Budget {
            limit,
            used: Mutex::new(0),
            freed: Condvar::new(),
        }
    }

    /// Holds `bytes`, waiting (after calling `waiting` once) while they do not fit.
    fn hold(&self, bytes: u64, waiting: impl FnOnce()) -> Held<'_> {
        let mut used = self.used.lock().unwrap_or_else(|e| e.into_inner());
        let fits = |used: u64| used == 0 || used + bytes <= self.limit;
        if !fits(*used) {
            waiting();
        }
        while !fits(*used) {
            used = self.freed.wait(used).unwrap_or_else(|e| e.into_inner());
        }
        *used += bytes;
        Held {
            budget: self,
            bytes,
        }
    }
}

/// Memory held from a [`Budget`] until dropped.
struct Held<'a> {
    budget: &'a Budget,
    bytes: u64,
}

impl Drop for Held<'_> {
    fn drop(&mut self) {
        let mut used = self.budget.used.lock().unwrap_or_else(|e| e.into_inner());
        *used -= self.bytes;
        self.budget.freed.notify_all();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn budget_admits_what_fits_and_a_lone_frame_always() {
        let b = Budget::new(10);
        let a = b.hold(6, || panic!("fits"));
        let c = b.hold(4, || panic!("fits"));
        assert_eq!(*b.used.lock().unwrap(), 10);
        drop((a, c));
        // Alone, a frame above the limit still runs (its estimate was refused or accepted before).
        let big = b.hold(50, || panic!("alone"));
        assert_eq!(*b.used.lock().unwrap(), 50);
        drop(big);
        // A waiting frame starts when memory is freed.
        let first = b.hold(8, || ());
        std::thread::scope(|s| {
            let waiter = s.spawn(|| {
                let _h = b.hold(5, || ());
                let used = *b.used.lock().unwrap();
                used
            });
            std::thread::sleep(std::time::Duration::from_millis(50));
            drop(first);
            assert_eq!(waiter.join().unwrap(), 5);
        });
    }
}
