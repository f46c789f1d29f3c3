//! Progress bars for long phases: shown on a terminal, hidden with `--quiet` or when stderr is not a
//! terminal (farm logs, tests), so output stays clean where nobody watches it.

use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressStyle};

/// Where long work reports its phases: a bar per phase on a terminal ([`Bars`]), or a batch's
/// own report of which frame is in which phase.
pub trait Phases: Sync {
    /// Starts `phase`, of `len` steps (0: unknown); the bar returned counts them.
    fn phase(&self, phase: &str, len: u64) -> ProgressBar;
}

/// A terminal bar per phase, or none with `quiet`.
pub struct Bars {
    pub quiet: bool,
}

impl Phases for Bars {
    fn phase(&self, phase: &str, len: u64) -> ProgressBar {
        bar(len, phase, self.quiet)
    }
}

/// A bar of `len` steps labelled `phase`, or a hidden one.
pub fn bar(len: u64, phase: &str, quiet: bool) -> ProgressBar {
    if quiet || !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let style = ProgressStyle::with_template(
        "{prefix:>10} [{elapsed_precise}] {wide_bar} {pos}/{len} ({eta} left)",
    )
    .unwrap_or_else(|_| ProgressStyle::default_bar());
    ProgressBar::new(len)
        .with_style(style)
        .with_prefix(phase.to_string())
}
