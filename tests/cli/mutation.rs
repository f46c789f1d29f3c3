//! The VDB reader against damaged files: a fixed-seed run of thousands of byte flips, smashed
//! integers and truncations of small valid files of every kind the reader supports, each given to
//! `info` and `bake --dry-run` under a time and memory limit. Every outcome must be a clean result:
//! success, or one error line with exit 1 or 2 — never a panic, an abort, a signal or a hang.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use rand_pcg::Pcg64;

use crate::fixture;

/// Mutants per file: enough that every header field and node of these small files is hit many
/// times (thousands in all), few enough for CI on 2 cores.
const MUTANTS_PER_FILE: usize = 220;
/// A run longer than this is a hang (a damaged file is refused in milliseconds).
const RUN_LIMIT: Duration = Duration::from_secs(20);
/// Address space a run may have: a reader that trusts a forged count and allocates for it fails
/// here, as an abort this test reports, instead of taking the machine.
const MEMORY_LIMIT: &str = "2147483648";

/// Small valid files of every kind: float (blosc), half, zip, uncompressed, double (OpenVDB 7),
/// several grids, vector-only, tiles at every level, an empty grid; and, made from one of them,
/// format 222 ([`as_format_222`]).
const FILES: [&str; 10] = [
    "small_cloud.vdb",
    "small_cloud_half.vdb",
    "small_cloud_zip.vdb",
    "smoke_double_openvdb7.vdb",
    "multi.vdb",
    "vec3_only.vdb",
    "block_tiles.vdb",
    "huge_root_tile.vdb",
    "huge_tiles_2048.vdb",
    "empty.vdb",
];

/// The ZIP fixture as OpenVDB 3.2 would have written it, format 222: the file format and library
/// version words rewritten. A volume grid's bytes are the same in 222, 223 and 224 when it uses
/// ZIP or no compression (docs/vdb-format.md, "Format versions"; Blosc came with 223), so this is a
/// well-formed 222 file, which Debian's OpenVDB can no longer write.
pub fn as_format_222() -> Vec<u8> {
    let mut bytes = std::fs::read(fixture("small_cloud_zip.vdb")).unwrap();
    // Magic (8 bytes), then u32 file format, u32 library major, u32 library minor.
    for (at, word) in [(8, 222u32), (12, 3), (16, 2)] {
        bytes[at..at + 4].copy_from_slice(&word.to_le_bytes());
    }
    bytes
}

/// One damaged copy of `bytes`: a flipped bit, a byte set to 0 or 255, a 4- or 8-byte field set to
/// a huge or negative value, or a truncation. Half the damage lands in the first 2 kB, where the
/// header, the grid descriptors and the topology's counts are.
fn mutate(bytes: &[u8], rng: &mut Pcg64) -> Vec<u8> {
    let mut b = bytes.to_vec();
    let len = b.len();
    let at = |rng: &mut Pcg64| match rng.random_bool(0.5) {
        true => rng.random_range(0..len.min(2048)),
        false => rng.random_range(0..len),
    };
    match rng.random_range(0..5) {
        0 => {
            let i = at(rng);
            b[i] ^= 1 << rng.random_range(0..8);
        }
        1 => {
            let i = at(rng);
            b[i] = if rng.random_bool(0.5) { 0 } else { 255 };
        }
        2 | 3 => {
            let i = at(rng).min(len.saturating_sub(8));
            let value: u64 = match rng.random_range(0..4) {
                0 => u64::MAX,
                1 => 0x7fff_ffff,
                2 => 0x8000_0000,
                _ => rng.random(),
            };
            let n = if rng.random_bool(0.5) { 4 } else { 8 };
            let end = (i + n).min(len);
            b[i..end].copy_from_slice(&value.to_le_bytes()[..end - i]);
        }
        _ => b.truncate(rng.random_range(0..len)),
    }
    b
}

/// What a run did, if it was not clean.
fn unclean(path: &Path, args: &[&str]) -> Option<String> {
    let mut child = Command::new("prlimit")
        .arg(format!("--as={MEMORY_LIMIT}"))
        .arg(env!("CARGO_BIN_EXE_vscatter"))
        .args(args)
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("prlimit (util-linux) runs");
    let clock = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if clock.elapsed() > RUN_LIMIT {
            child.kill().ok();
            child.wait().ok();
            return Some(format!("hung over {RUN_LIMIT:?}"));
        }
        std::thread::sleep(Duration::from_millis(2));
    };
    let mut err = String::new();
    use std::io::Read;
    child.stderr.take().unwrap().read_to_string(&mut err).ok();
    let errors = err
        .lines()
        .filter(|l| l.starts_with("vscatter: error:"))
        .count();
    match status.code() {
        None => Some(format!("killed by a signal: {err}")),
        Some(0) if !err.contains("panicked") => None,
        Some(1 | 2) if errors == 1 && !err.contains("panicked") => None,
        Some(c) => Some(format!("exit {c} on {}: {err}", path.display())),
    }
}

#[test]
fn no_damaged_file_crashes_the_reader() {
    let dir = tempfile::tempdir().unwrap();
    let jobs: Vec<(PathBuf, Vec<u8>)> = {
        let mut rng = Pcg64::seed_from_u64(0x5eed_f7d6);
        FILES
            .iter()
            .map(|name| (name.to_string(), std::fs::read(fixture(name)).unwrap()))
            .chain([("format_222.vdb".to_string(), as_format_222())])
            .flat_map(|(name, bytes)| {
                (0..MUTANTS_PER_FILE)
                    .map(|i| {
                        let path = dir.path().join(format!("{i}_{name}"));
                        (path, mutate(&bytes, &mut rng))
                    })
                    .collect::<Vec<_>>()
            })
            .collect()
    };
    let next = AtomicUsize::new(0);
    let failures = Mutex::new(Vec::new());
    let out = dir.path().join("x.vtc");
    // Two at a time: the runs are short and mostly start-up.
    std::thread::scope(|s| {
        for _ in 0..2 {
            s.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some((path, bytes)) = jobs.get(i) else {
                    break;
                };
                std::fs::write(path, bytes).unwrap();
                let p = path.to_str().unwrap();
                for args in [
                    vec!["info", p],
                    vec!["bake", p, "-o", out.to_str().unwrap(), "--dry-run"],
                ] {
                    if let Some(what) = unclean(path, &args) {
                        failures.lock().unwrap().push(format!("{args:?}: {what}"));
                    }
                }
                std::fs::remove_file(path).ok();
            });
        }
    });
    let failures = failures.into_inner().unwrap();
    eprintln!(
        "{} mutants of {} files, {} runs, {} unclean",
        jobs.len(),
        FILES.len() + 1,
        2 * jobs.len(),
        failures.len()
    );
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
