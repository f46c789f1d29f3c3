//! The integration tests: one binary that runs the real `vscatter` program in temporary
//! directories, plus cross-checks of the library against independent references.

#[path = "cli/bake.rs"]
mod bake;
#[path = "cli/batch.rs"]
mod batch;
#[path = "cli/env.rs"]
mod env;
#[path = "cli/farm.rs"]
mod farm;
#[path = "cli/mutation.rs"]
mod mutation;
#[path = "cli/pathtrace.rs"]
mod pathtrace;
#[path = "cli/render.rs"]
mod render;
#[path = "cli/sun.rs"]
mod sun;
#[path = "cli/vdb.rs"]
mod vdb;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

/// Bake flags that keep the on-the-fly bake of a small fixture quick.
pub const QUICK_BAKE: [&str; 6] = ["--bands", "3", "--scale", "4", "--samples", "64"];

/// A file in the repository's fixtures directory.
pub fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("fixtures")
        .join(name)
}

/// Runs the real binary with `args` in the current directory.
pub fn vscatter(args: &[&str]) -> Output {
    vscatter_in(Path::new("."), args)
}

/// Runs the real binary with `args`, with `dir` as working directory.
pub fn vscatter_in(dir: &Path, args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_vscatter"))
        .args(args)
        .current_dir(dir)
        .output()
        .expect("the vscatter binary runs")
}

pub fn stderr(out: &Output) -> String {
    String::from_utf8_lossy(&out.stderr).into_owned()
}

/// The channel names of an EXR's first layer, in the file's (alphabetical) order.
pub fn exr_channels(path: &std::path::Path) -> Vec<String> {
    let image = exr::prelude::read_all_flat_layers_from_file(path).unwrap();
    image.layer_data[0]
        .channel_data
        .list
        .iter()
        .map(|c| c.name.to_string())
        .collect()
}

/// Asserts a failure the way users must see it: the exit code, one line on stderr naming `names`,
/// and no panic message.
pub fn assert_clean_failure(out: &Output, code: i32, names: &str) {
    let err = stderr(out);
    assert_eq!(out.status.code(), Some(code), "stderr: {err}");
    assert!(!err.contains("panicked"), "panic: {err}");
    assert_eq!(err.trim_end().lines().count(), 1, "not one line: {err}");
    assert!(err.contains(names), "{err:?} does not name {names:?}");
}

/// The fixture sequence (tools/make_sequence.sh), copied into `dir/seq`: tests touch and damage
/// their own copy.
pub fn sequence_in(dir: &Path) -> PathBuf {
    let seq = dir.join("seq");
    std::fs::create_dir_all(&seq).unwrap();
    for n in 1001..=1012 {
        let name = format!("cloud.{n}.vdb");
        std::fs::copy(fixture("sequence").join(&name), seq.join(&name)).unwrap();
    }
    seq
}
