//! Progress bars for long phases: shown on a terminal, hidden with `--quiet` or when stderr is not a
//! terminal (farm logs, tests), so output stays clean where nobody watches it.

use std::io::IsTerminal;

use indicatif::{ProgressBar, ProgressStyle};

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
