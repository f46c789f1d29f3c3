//! Progress over many frames (a batch, a sequence render): which frame is in which phase, how
//! many are done, and when the rest will be.

use std::collections::BTreeMap;
use std::io::IsTerminal;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant, SystemTime};

use indicatif::{ProgressBar, ProgressStyle};

/// How work over frames shows its progress: a bar over the frames with each running frame's phase
/// on a terminal; off a terminal (a farm log), one timestamped line per frame and phase; nothing
/// but failures with `--quiet`.
pub struct FrameProgress {
    names: Vec<String>,
    start: Instant,
    done: AtomicUsize,
    bar: Option<ProgressBar>,
    plain: bool,
    /// The phase of each frame in flight, for the bar's message.
    running: Mutex<BTreeMap<usize, String>>,
}

impl FrameProgress {
    /// Progress over the frames read from `inputs`, labelled `what` (`batch`, `render`).
    pub fn new(inputs: &[PathBuf], what: &str, quiet: bool) -> FrameProgress {
        let terminal = std::io::stderr().is_terminal();
        let bar = (!quiet && terminal).then(|| {
            let style = ProgressStyle::with_template(
                "{prefix:>6} {pos}/{len} [{elapsed_precise}] {bar:20} eta {eta} {wide_msg}",
            )
            .unwrap_or_else(|_| ProgressStyle::default_bar());
            ProgressBar::new(inputs.len() as u64)
                .with_style(style)
                .with_prefix(what.to_string())
        });
        FrameProgress {
            names: inputs
                .iter()
                .map(|i| names(std::slice::from_ref(i)))
                .collect(),
            start: Instant::now(),
            done: AtomicUsize::new(0),
            bar,
            plain: !quiet && !terminal,
            running: Mutex::new(BTreeMap::new()),
        }
    }

    /// `elapsed 12s, eta 1m 40s`: the ETA from the mean time of the frames finished so far.
    fn timing(&self) -> String {
        let elapsed = self.start.elapsed();
        let done = self.done.load(Ordering::Relaxed);
        let left = self.names.len() - done;
        let eta = match done {
            0 => "unknown".to_string(),
            _ => seconds(elapsed.mul_f64(left as f64 / done as f64)),
        };
        format!("elapsed {}, eta {eta}", seconds(elapsed))
    }

    /// One line of a farm log: time, frame count, frame, what happened, timing.
    fn line(&self, frame: usize, what: &str) {
        eprintln!(
            "{} [{}/{}] {} {what} ({})",
            humantime::format_rfc3339_seconds(SystemTime::now()),
            self.done.load(Ordering::Relaxed),
            self.names.len(),
            self.names[frame],
            self.timing()
        );
    }

    fn show_running(&self) {
        if let Some(bar) = &self.bar {
            let running = self.running.lock().unwrap_or_else(|e| e.into_inner());
            let msg: Vec<String> = running
                .iter()
                .map(|(i, p)| format!("{}: {p}", self.names[*i]))
                .collect();
            bar.set_message(msg.join(", "));
        }
    }

    /// Runs `f` (which prints) with the bar cleared, so its lines do not land inside the bar's.
    pub fn suspend<R>(&self, f: impl FnOnce() -> R) -> R {
        match &self.bar {
            Some(bar) => bar.suspend(f),
            None => f(),
        }
    }

    /// Whether a bar is shown (a frame's own bars would fight it).
    pub fn has_bar(&self) -> bool {
        self.bar.is_some()
    }

    pub fn finish(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}

/// The file names of `paths`, comma-separated (the directory is the same for a sequence).
pub fn names(paths: &[PathBuf]) -> String {
    paths
        .iter()
        .map(|p| {
            p.file_name()
                .map_or_else(|| p.display().to_string(), |n| n.to_string_lossy().into())
        })
        .collect::<Vec<String>>()
        .join(", ")
}

/// Whole seconds, as humans read them (`1m 40s`).
fn seconds(d: Duration) -> String {
    humantime::format_duration(Duration::from_secs(d.as_secs_f64().round() as u64)).to_string()
}

impl FrameProgress {
    /// Frame `frame` enters `phase`.
    pub fn phase(&self, frame: usize, phase: &str) {
        self.running
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .insert(frame, phase.to_string());
        self.show_running();
        if self.plain {
            self.line(frame, phase);
        }
    }

    /// Frame `frame` is done: `what` became of it, or it failed with `failure`.
    pub fn done(&self, frame: usize, what: &str, failure: Option<&str>) {
        self.done.fetch_add(1, Ordering::Relaxed);
        self.running
            .lock()
            .unwrap_or_else(|e| e.into_inner())
            .remove(&frame);
        if let Some(bar) = &self.bar {
            bar.inc(1);
            if let Some(e) = failure {
                bar.println(format!("{} failed: {e}", self.names[frame]));
            }
        } else if self.plain {
            match failure {
                Some(e) => self.line(frame, &format!("FAILED: {e}")),
                None => self.line(frame, what),
            }
        } else if let Some(e) = failure {
            // --quiet still says what failed, as it happens.
            eprintln!("{} failed: {e}", self.names[frame]);
        }
        self.show_running();
    }
}
