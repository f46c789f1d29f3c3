//! The integration tests: one binary that runs the real `vscatter` program in temporary
//! directories, plus cross-checks of the library against independent references.

#[path = "cli/bake.rs"]
mod bake;
#[path = "cli/vdb.rs"]
mod vdb;

use std::path::{Path, PathBuf};
use std::process::Output;

/// The repository's fixtures directory.
pub fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures")
        .join(name)
}

/// Runs the real binary with `args`.
pub fn vscatter(args: &[&str]) -> Output {
    std::process::Command::new(env!("CARGO_BIN_EXE_vscatter"))
        .args(args)
        .env("NO_COLOR", "1")
        .output()
        .expect("the vscatter binary runs")
}

/// Asserts a failure the way users must see it: the exit code, one line on stderr naming `names`,
/// and no panic message.
pub fn assert_clean_failure(out: &Output, code: i32, names: &str) {
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(code), "stderr: {stderr}");
    assert!(!stderr.contains("panicked"), "panic: {stderr}");
    assert_eq!(
        stderr.trim_end().lines().count(),
        1,
        "not one line: {stderr}"
    );
    assert!(stderr.contains(names), "{stderr:?} does not name {names:?}");
}
