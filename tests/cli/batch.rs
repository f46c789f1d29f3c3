//! `vscatter batch` as a farm runs it: patterns, skipping current frames, shards run at once,
//! SIGKILL at any moment, a damaged frame, bad command lines, and noise that does not flicker.

use std::collections::BTreeSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::{assert_clean_failure, fixture, sequence_in, stderr, vscatter_in, QUICK_BAKE};

/// Runs a batch with `--stats` and the quick bake; returns the exit code, the stats and stderr.
fn batch(dir: &Path, args: &[&str]) -> (Option<i32>, serde_json::Value, String) {
    let mut all = vec!["batch", "--stats", "--quiet"];
    all.extend(args);
    all.extend(QUICK_BAKE);
    let o = vscatter_in(dir, &all);
    let stats = serde_json::from_slice(&o.stdout).unwrap_or(serde_json::Value::Null);
    (o.status.code(), stats, stderr(&o))
}

/// What `batch --dry-run` of the copied sequence into `out` prints, checking it succeeds.
fn dry_run(dir: &Path) -> String {
    let mut args = vec![
        "batch",
        "seq/cloud.####.vdb",
        "--out-dir",
        "out",
        "--dry-run",
    ];
    args.extend(QUICK_BAKE);
    let o = vscatter_in(dir, &args);
    assert!(o.status.success(), "{}", stderr(&o));
    String::from_utf8_lossy(&o.stdout).into_owned()
}

/// The file names of the frames with `status` in a batch's stats.
fn with_status(stats: &serde_json::Value, status: &str) -> BTreeSet<String> {
    stats["frames"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|f| f["status"] == status)
        .map(|f| {
            let input = f["input"].as_str().unwrap();
            Path::new(input)
                .file_name()
                .unwrap()
                .to_string_lossy()
                .into()
        })
        .collect()
}

fn all_frames() -> BTreeSet<String> {
    (1001..=1012).map(|n| format!("cloud.{n}.vdb")).collect()
}

#[test]
fn every_pattern_names_the_same_frames_and_current_caches_are_skipped() {
    let dir = tempfile::tempdir().unwrap();
    sequence_in(dir.path());
    let (code, stats, err) = batch(dir.path(), &["seq/cloud.####.vdb", "--out-dir", "out"]);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(with_status(&stats, "baked"), all_frames());
    // Every other spelling of the sequence finds the same twelve frames, all current now.
    let glob_list: Vec<String> = (1001..=1012)
        .map(|n| format!("seq/cloud.{n}.vdb"))
        .collect();
    let spellings: Vec<Vec<&str>> = vec![
        vec!["seq/cloud.%04d.vdb"],
        vec!["seq/cloud.$F4.vdb", "--frames", "1001-1012"],
        vec!["seq/cloud.####.vdb", "--frames", "1001-1012:1"],
        vec!["seq/*.vdb"],
        glob_list.iter().map(String::as_str).collect(),
    ];
    for spelling in spellings {
        let mut args = spelling.clone();
        args.extend(["--out-dir", "out"]);
        let (code, stats, err) = batch(dir.path(), &args);
        assert_eq!(code, Some(0), "{spelling:?}: {err}");
        assert_eq!(with_status(&stats, "current"), all_frames(), "{spelling:?}");
        assert!(with_status(&stats, "baked").is_empty(), "{spelling:?}");
    }
    // A dry run says so, frame by frame, and bakes nothing.
    let said = dry_run(dir.path());
    assert_eq!(
        said.lines().filter(|l| l.contains(": current (")).count(),
        12,
        "{said}"
    );
    // Touching one source reconverts that frame alone.
    let touched = dir.path().join("seq/cloud.1005.vdb");
    let f = std::fs::File::options().write(true).open(&touched).unwrap();
    f.set_modified(std::time::SystemTime::now() + Duration::from_secs(5))
        .unwrap();
    drop(f);
    let said = dry_run(dir.path());
    assert_eq!(
        said.lines()
            .filter(|l| l.contains("transfer voxels"))
            .count(),
        1,
        "{said}"
    );
    let (code, stats, _) = batch(dir.path(), &["seq/cloud.####.vdb", "--out-dir", "out"]);
    assert_eq!(code, Some(0));
    assert_eq!(
        with_status(&stats, "baked"),
        BTreeSet::from(["cloud.1005.vdb".to_string()])
    );
    // Other bake settings make every cache stale; --force rebakes a current one.
    let (_, stats, _) = batch(
        dir.path(),
        &["seq/cloud.####.vdb", "--out-dir", "out", "--albedo", "0.5"],
    );
    assert_eq!(with_status(&stats, "baked"), all_frames());
    let (_, stats, _) = batch(
        dir.path(),
        &[
            "seq/cloud.1001.vdb",
            "--out-dir",
            "out",
            "--albedo",
            "0.5",
            "--force",
        ],
    );
    assert_eq!(with_status(&stats, "baked").len(), 1);
}

#[test]
fn three_shards_at_once_convert_every_frame_exactly_once() {
    let dir = tempfile::tempdir().unwrap();
    sequence_in(dir.path());
    let children: Vec<_> = (1..=3)
        .map(|k| {
            let shard = format!("{k}/3");
            let mut args = vec![
                "batch",
                "--stats",
                "--quiet",
                "--threads",
                "1",
                "seq/cloud.####.vdb",
                "--out-dir",
                "out",
                "--shard",
                &shard,
            ];
            args.extend(QUICK_BAKE);
            Command::new(env!("CARGO_BIN_EXE_vscatter"))
                .args(&args)
                .current_dir(dir.path())
                .stdout(Stdio::piped())
                .stderr(Stdio::piped())
                .spawn()
                .unwrap()
        })
        .collect();
    let mut seen = Vec::new();
    for child in children {
        let o = child.wait_with_output().unwrap();
        assert!(o.status.success(), "{}", stderr(&o));
        let stats: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(stats["frames"].as_array().unwrap().len(), 4);
        seen.extend(with_status(&stats, "baked"));
    }
    seen.sort();
    assert_eq!(seen, all_frames().into_iter().collect::<Vec<_>>());
    assert_eq!(
        std::fs::read_dir(dir.path().join("out")).unwrap().count(),
        12
    );
}

#[test]
fn sigkill_at_any_moment_then_a_rerun_finishes_clean() {
    let dir = tempfile::tempdir().unwrap();
    sequence_in(dir.path());
    let out = dir.path().join("out");
    // Full resolution and 8 bands: megabyte caches, so writing one takes long enough to be
    // caught in the act.
    let heavy = [
        "batch",
        "--quiet",
        "seq/cloud.####.vdb",
        "--out-dir",
        "out",
        "--scale",
        "1",
        "--bands",
        "8",
        "--samples",
        "32",
    ];
    let temporaries = || -> Vec<PathBuf> {
        std::fs::read_dir(&out)
            .map(|d| {
                d.flatten()
                    .map(|e| e.path())
                    .filter(|p| p.to_string_lossy().ends_with(".tmp"))
                    .collect()
            })
            .unwrap_or_default()
    };
    let start = || {
        Command::new(env!("CARGO_BIN_EXE_vscatter"))
            .args(heavy)
            .current_dir(dir.path())
            .stderr(Stdio::null())
            .spawn()
            .unwrap()
    };
    // Kills after fixed delays, then kills the moment a temporary cache appears, until one was
    // killed while writing (its temporary file is left behind for the rerun to clear).
    let mut killed_while_writing = 0;
    let mut kills = 0;
    for attempt in 0..40 {
        let mut child = start();
        let clock = Instant::now();
        if attempt < 3 {
            std::thread::sleep(Duration::from_millis(50 + 150 * attempt));
        } else {
            while temporaries().is_empty() && clock.elapsed() < Duration::from_secs(20) {
                if child.try_wait().unwrap().is_some() {
                    break;
                }
            }
        }
        let finished = child.try_wait().unwrap().is_some();
        child.kill().ok();
        child.wait().unwrap();
        kills += usize::from(!finished);
        killed_while_writing += usize::from(!finished && !temporaries().is_empty());
        if killed_while_writing >= 1 && attempt >= 3 {
            break;
        }
        // Start afresh now and then, so there is always work left to kill.
        if attempt % 4 == 3 {
            std::fs::remove_dir_all(&out).ok();
        }
    }
    eprintln!("{kills} runs killed, {killed_while_writing} while writing a cache");
    assert!(kills >= 3, "only {kills} runs were killed before finishing");
    assert!(
        killed_while_writing >= 1,
        "no kill landed while a cache was being written"
    );
    let o = vscatter_in(dir.path(), &heavy);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(temporaries().is_empty(), "{:?}", temporaries());
    for n in 1001..=1012 {
        let cache = out.join(format!("cloud.{n}.vtc"));
        // `info` verifies a cache's checksum over the whole file.
        let o = vscatter_in(dir.path(), &["info", cache.to_str().unwrap()]);
        assert!(o.status.success(), "{}: {}", cache.display(), stderr(&o));
    }
}

#[test]
fn a_damaged_frame_fails_alone_and_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let seq = sequence_in(dir.path());
    let bad = seq.join("cloud.1006.vdb");
    let bytes = std::fs::read(&bad).unwrap();
    std::fs::write(&bad, &bytes[..bytes.len() / 2]).unwrap();
    let mut args = vec!["batch", "seq/cloud.####.vdb", "--out-dir", "out", "--stats"];
    args.extend(QUICK_BAKE);
    let o = vscatter_in(dir.path(), &args);
    assert_eq!(o.status.code(), Some(1));
    let err = stderr(&o);
    assert!(!err.contains("panicked"), "{err}");
    let last = err.trim_end().lines().last().unwrap();
    assert!(
        last.starts_with("vscatter: error: batch incomplete") && last.contains("cloud.1006.vdb"),
        "{last}"
    );
    let stats: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    let mut others = all_frames();
    others.remove("cloud.1006.vdb");
    assert_eq!(with_status(&stats, "baked"), others);
    assert_eq!(
        with_status(&stats, "failed"),
        BTreeSet::from(["cloud.1006.vdb".to_string()])
    );
    assert!(!dir.path().join("out/cloud.1006.vtc").exists());
    // A range with a hole: the frames there convert, the missing ones are named, exit 1.
    std::fs::remove_file(seq.join("cloud.1003.vdb")).unwrap();
    let (code, stats, err) = batch(
        dir.path(),
        &[
            "seq/cloud.####.vdb",
            "--frames",
            "1001-1005",
            "--out-dir",
            "o2",
        ],
    );
    assert_eq!(code, Some(1));
    assert_eq!(with_status(&stats, "baked").len(), 4);
    assert!(err.contains("missing (cloud.1003.vdb)"), "{err}");
}

#[test]
fn bad_batch_command_lines_are_one_line_and_bake_nothing() {
    let dir = tempfile::tempdir().unwrap();
    sequence_in(dir.path());
    std::fs::write(dir.path().join("file"), b"x").unwrap();
    std::fs::create_dir(dir.path().join("other")).unwrap();
    std::fs::copy(
        dir.path().join("seq/cloud.1001.vdb"),
        dir.path().join("other/cloud.1001.vdb"),
    )
    .unwrap();
    let cases: [(&[&str], i32, &str); 6] = [
        (
            &["nothing.####.vdb", "--out-dir", "o"],
            2,
            "nothing.####.vdb",
        ),
        (&["none*.vdb", "--out-dir", "o"], 2, "none*.vdb"),
        (
            &["seq/cloud.####.vdb", "--out-dir", "o", "--shard", "0/3"],
            2,
            "0/3",
        ),
        (
            &["seq/cloud.####.vdb", "--out-dir", "o", "--shard", "4/3"],
            2,
            "4/3",
        ),
        (
            &[
                "seq/cloud.1001.vdb",
                "other/cloud.1001.vdb",
                "--out-dir",
                "o",
            ],
            2,
            "would both write",
        ),
        (&["seq/cloud.####.vdb", "--out-dir", "file/o"], 1, "file/o"),
    ];
    for (args, code, names) in cases {
        let mut all = vec!["batch"];
        all.extend(args);
        let o = vscatter_in(dir.path(), &all);
        assert_clean_failure(&o, code, names);
    }
    assert!(!dir.path().join("o").exists());
}

#[test]
fn identical_frames_give_identical_caches() {
    // The bake's Monte Carlo noise is seeded, not drawn: a still volume does not flicker.
    let dir = tempfile::tempdir().unwrap();
    let still = dir.path().join("still");
    std::fs::create_dir(&still).unwrap();
    for n in 1..=12 {
        std::fs::copy(
            fixture("sequence/cloud.1006.vdb"),
            still.join(format!("s.{n:04}.vdb")),
        )
        .unwrap();
    }
    let (code, _, err) = batch(dir.path(), &["still/s.####.vdb", "--out-dir", "out"]);
    assert_eq!(code, Some(0), "{err}");
    // The header names its own source file; everything after it must be bit-identical.
    let body = |n: u32| {
        let b = std::fs::read(dir.path().join(format!("out/s.{n:04}.vtc"))).unwrap();
        let h = u64::from_le_bytes(b[16..24].try_into().unwrap()) as usize;
        b[24 + h..b.len() - 8].to_vec()
    };
    let first = body(1);
    for n in 2..=12 {
        assert!(body(n) == first, "frame {n} differs");
    }
    // And so are their images (the files differ only in the fingerprint naming their source).
    let o = vscatter_in(
        dir.path(),
        &[
            "render",
            "out/s.####.vtc",
            "-o",
            "img/s.####.exr",
            "--res",
            "16x9",
            "--quiet",
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let first = pixels(&dir.path().join("img/s.0001.exr"));
    for n in 2..=12 {
        let image = pixels(&dir.path().join(format!("img/s.{n:04}.exr")));
        assert!(image == first, "image {n} differs");
    }
}

/// Every pixel's RGBA of an EXR.
fn pixels(path: &Path) -> Vec<[f32; 4]> {
    let img = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |size, _| vec![[0f32; 4]; size.width() * size.height()],
        |px: &mut Vec<[f32; 4]>, pos, (r, g, b, a): (f32, f32, f32, f32)| {
            let w = px.len() / 9;
            px[pos.y() * w + pos.x()] = [r, g, b, a];
        },
    )
    .unwrap();
    img.layer_data.channel_data.pixels
}

/// The summary line of a sequence render: (rendered, current).
fn rendered_and_current(err: &str) -> (usize, usize) {
    let line = err.lines().find(|l| l.starts_with("render: ")).unwrap();
    let count = |what: &str| -> usize {
        let before = line.split(&format!(" {what}")).next().unwrap();
        before.rsplit(' ').next().unwrap().parse().unwrap()
    };
    (count("rendered"), count("current"))
}

#[test]
fn sequences_render_once_orbit_follow_paths_and_relight_under_several_maps() {
    let dir = tempfile::tempdir().unwrap();
    sequence_in(dir.path());
    let (code, _, err) = batch(dir.path(), &["seq/cloud.####.vdb", "--out-dir", "c"]);
    assert_eq!(code, Some(0), "{err}");
    let studio = fixture("env/studio.exr");
    let maps = format!("sky,{}", studio.display());
    // 16x9: `pixels` reads rows of 16.
    let render = |extra: &[&str]| {
        let mut args = vec!["render", "c/cloud.####.vtc", "--res", "16x9"];
        args.extend(extra);
        let o = vscatter_in(dir.path(), &args);
        (o.status.code(), stderr(&o))
    };
    let orbit = [
        "-o",
        "img/o.####.exr",
        "--orbit",
        "360",
        "--frames",
        "1001-1012",
    ];
    let (code, err) = render(&orbit);
    assert_eq!(code, Some(0), "{err}");
    assert_eq!(rendered_and_current(&err), (12, 0));
    // Nothing changed: every image is current. Another exposure is another picture.
    let (_, err) = render(&orbit);
    assert_eq!(rendered_and_current(&err), (0, 12));
    let mut brighter = orbit.to_vec();
    brighter.extend(["--env-scale", "2"]);
    assert_eq!(rendered_and_current(&render(&brighter).1), (12, 0));
    // The orbit turns: a quarter of the way round, the camera looks along -X.
    let (a, b) = (
        pixels(&dir.path().join("img/o.1001.exr")),
        pixels(&dir.path().join("img/o.1004.exr")),
    );
    assert!(a != b);

    // Under two maps at once: an image per map, each the one a single render under it makes.
    let (code, err) = render(&["-o", "img/m.####.exr", "--env", &maps]);
    assert_eq!(code, Some(0), "{err}");
    for n in [1001, 1012] {
        let single = dir.path().join(format!("s{n}.exr"));
        let input = format!("c/cloud.{n}.vtc");
        let o = vscatter_in(
            dir.path(),
            &[
                "render",
                &input,
                "--res",
                "16x9",
                "--env",
                studio.to_str().unwrap(),
                "-o",
                single.to_str().unwrap(),
                "--camera-pos",
                "24,16,90",
            ],
        );
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(dir.path().join(format!("img/m.sky.{n}.exr")).exists());
        let studio_image = dir.path().join(format!("img/m.studio.{n}.exr"));
        assert!(studio_image.exists());
        // The sequence frames all frames alike, so compare with the same camera position.
        let (_, err) = render(&[
            "-o",
            "img/p.####.exr",
            "--env",
            studio.to_str().unwrap(),
            "--camera-pos",
            "24,16,90",
            "--frames",
            &n.to_string(),
        ]);
        assert!(err.contains("1 rendered"), "{err}");
        assert!(
            pixels(&dir.path().join(format!("img/p.{n}.exr"))) == pixels(&single),
            "frame {n}"
        );
    }

    // A camera path: halfway between two keys is the camera halfway between them.
    std::fs::write(
        dir.path().join("path.txt"),
        "# frame  position  lookat  fov\n1001  0 16 90  24 16 16  40\n1011  40 16 90  24 16 16  60\n",
    )
    .unwrap();
    let (code, err) = render(&["-o", "img/k.####.exr", "--camera-path", "path.txt"]);
    assert_eq!(code, Some(0), "{err}");
    let o = vscatter_in(
        dir.path(),
        &[
            "render",
            "c/cloud.1006.vtc",
            "--res",
            "16x9",
            "-o",
            "mid.exr",
            "--camera-pos",
            "20,16,90",
            "--lookat",
            "24,16,16",
            "--fov",
            "50",
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(pixels(&dir.path().join("img/k.1006.exr")) == pixels(&dir.path().join("mid.exr")));

    // Bad sequence command lines: one line each, nothing rendered.
    std::fs::write(dir.path().join("bad_path.txt"), "1001 0 0 1 0 0 0\n").unwrap();
    let cases: [(&[&str], i32, &str); 4] = [
        (&["-o", "one.exr"], 2, "frame pattern"),
        (&["-o", "x.####.exr", "--cache", "k.vtc"], 2, "--cache"),
        (
            &["-o", "x.####.exr", "--camera-path", "bad_path.txt"],
            1,
            "bad_path.txt",
        ),
        (&["-o", "x.####.exr", "--env", "sky,sky"], 2, "\"sky\""),
    ];
    for (extra, code, names) in cases {
        let mut args = vec!["render", "c/cloud.####.vtc"];
        args.extend(extra);
        assert_clean_failure(&vscatter_in(dir.path(), &args), code, names);
    }
    assert!(!dir.path().join("x.1001.exr").exists());
}
