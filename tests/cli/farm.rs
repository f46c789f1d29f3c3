//! The README's Slurm array script, submitted as a real array job to a single-node Slurm cluster
//! on this machine (tools/slurm-local.sh). Starting daemons and installing Slurm needs root, so
//! without root this test says loudly that it did not run; CI runs as root.

use std::collections::BTreeSet;
use std::path::Path;
use std::process::Command;

use crate::{sequence_in, QUICK_BAKE};

fn is_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .is_ok_and(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
}

#[test]
fn the_slurm_array_script_converts_every_frame_exactly_once() {
    if !is_root() {
        // Straight to the process's stderr: the harness captures `eprintln!`, and a skip must be
        // seen.
        use std::io::Write;
        let _ = writeln!(
            std::io::stderr(),
            "SKIPPED the Slurm array test: it starts a local Slurm cluster, which needs root"
        );
        return;
    }
    let repo = Path::new(env!("CARGO_MANIFEST_DIR"));
    let started = Command::new(repo.join("tools/slurm-local.sh"))
        .arg("start")
        .output()
        .unwrap();
    assert!(
        started.status.success(),
        "tools/slurm-local.sh start: {}",
        String::from_utf8_lossy(&started.stderr)
    );
    let dir = tempfile::tempdir().unwrap();
    sequence_in(dir.path());
    let mut args = vec![
        "--wait".to_string(),
        "--array=1-3".into(),
        "--cpus-per-task=1".into(),
        format!("--chdir={}", dir.path().display()),
        repo.join("tools/farm/slurm-batch.sh").display().to_string(),
        "seq/cloud.####.vdb".into(),
        "out".into(),
    ];
    args.extend(QUICK_BAKE.iter().map(|s| s.to_string()));
    let o = Command::new("sbatch")
        .args(&args)
        .env("VSCATTER", env!("CARGO_BIN_EXE_vscatter"))
        .output()
        .unwrap();
    let said = String::from_utf8_lossy(&o.stdout);
    assert!(
        o.status.success(),
        "sbatch: {said}{}",
        String::from_utf8_lossy(&o.stderr)
    );
    // Each task's log: its command line, then one timestamped line per frame and phase.
    let mut baked = Vec::new();
    let mut logs: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.to_string_lossy().ends_with(".log"))
        .collect();
    logs.sort();
    assert_eq!(logs.len(), 3, "{logs:?}");
    for log in &logs {
        let text = std::fs::read_to_string(log).unwrap();
        eprintln!("== {}\n{text}", log.display());
        for line in text.lines().filter(|l| l.contains(" baked -> ")) {
            let frame = line.split_whitespace().nth(2).unwrap().to_string();
            baked.push(frame);
        }
    }
    let once: BTreeSet<&String> = baked.iter().collect();
    assert_eq!(baked.len(), 12, "{baked:?}");
    assert_eq!(once.len(), 12, "{baked:?}");
    for n in 1001..=1012 {
        assert!(dir.path().join(format!("out/cloud.{n}.vtc")).exists());
    }
}
