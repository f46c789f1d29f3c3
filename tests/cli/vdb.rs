//! `vscatter info` against Debian's OpenVDB (`fixtures/expected.json`), and damaged files as a user
//! meets them.

use serde_json::Value;

use crate::{assert_clean_failure, fixture, vscatter};

fn expected() -> Value {
    let text = std::fs::read_to_string(fixture("expected.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn close(a: f64, b: f64, rel: f64) -> bool {
    (a - b).abs() <= rel * b.abs().max(1e-12)
}

#[test]
fn info_json_agrees_with_openvdb_on_every_fixture() {
    let exp = expected();
    let files = exp["files"].as_object().unwrap();
    assert!(files.len() >= 12, "expected.json lists every fixture");
    for (file, want) in files {
        let out = vscatter(&["info", "--json", fixture(file).to_str().unwrap()]);
        assert!(
            out.status.success(),
            "{file}: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        let got: Value = serde_json::from_slice(&out.stdout).unwrap();
        let (got, want) = (
            got["grids"].as_array().unwrap(),
            want["grids"].as_array().unwrap(),
        );
        assert_eq!(got.len(), want.len(), "{file}: grid count");
        for (g, w) in got.iter().zip(want) {
            let at = format!("{file}/{}", w["name"]);
            for key in [
                "name",
                "value_type",
                "class",
                "active_voxels",
                "tiles",
                "leaves",
            ] {
                assert_eq!(g[key], w[key], "{at}: {key}");
            }
            for key in ["bbox_min", "bbox_max"] {
                assert_eq!(g[key], w[key], "{at}: {key}");
            }
            for key in ["voxel_size", "translation"] {
                let (a, b) = (g[key].as_array().unwrap(), w[key].as_array().unwrap());
                for (x, y) in a.iter().zip(b) {
                    assert!(
                        close(x.as_f64().unwrap(), y.as_f64().unwrap(), 1e-9),
                        "{at}: {key}"
                    );
                }
            }
            if let Some(sum) = w["value_sum"].as_f64() {
                let got_sum = g["value_sum"].as_f64().unwrap_or(0.0);
                assert!(
                    close(got_sum, sum, 1e-5),
                    "{at}: value sum {got_sum} vs {sum}"
                );
            }
            for key in ["value_min", "value_max"] {
                if let Some(v) = w[key].as_f64() {
                    assert!(close(g[key].as_f64().unwrap(), v, 1e-6), "{at}: {key}");
                }
            }
        }
    }
}

#[test]
fn double_precision_real_data_is_read() {
    // Facts measured with Debian's vdb_print on a file written by OpenVDB 7 (fixtures/README.md).
    let out = vscatter(&[
        "info",
        "--json",
        fixture("smoke_double_openvdb7.vdb").to_str().unwrap(),
    ]);
    assert!(out.status.success());
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    let g = &v["grids"][0];
    assert_eq!(g["value_type"], "double");
    assert_eq!(g["active_voxels"], 524_288);
    assert_eq!(g["tiles"], 0);
    assert_eq!(g["bbox_min"], serde_json::json!([0, 0, 0]));
    assert_eq!(g["bbox_max"], serde_json::json!([127, 63, 63]));
    assert_eq!(g["translation"], serde_json::json!([-64.0, -32.0, 0.0]));
    assert!(g["value_min"].as_f64().unwrap() >= 0.0 && g["value_max"].as_f64().unwrap() <= 1.0);
}

#[test]
fn info_on_a_missing_grid_lists_the_grids() {
    let out = vscatter(&[
        "info",
        "--grid",
        "density",
        fixture("vec3_only.vdb").to_str().unwrap(),
    ]);
    assert_clean_failure(&out, 1, "vec3_only.vdb");
    assert!(String::from_utf8_lossy(&out.stderr).contains("vel (vec3s)"));
    let out = vscatter(&[
        "info",
        "--grid",
        "vel",
        fixture("multi.vdb").to_str().unwrap(),
    ]);
    assert_clean_failure(&out, 1, "not a scalar density");
}

#[test]
fn damaged_files_are_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let write = |name: &str, bytes: &[u8]| {
        let p = dir.path().join(name);
        std::fs::write(&p, bytes).unwrap();
        p
    };
    let cloud = std::fs::read(fixture("cloud.vdb")).unwrap();
    let mut wrong_magic = cloud.clone();
    wrong_magic[0] = b'X';
    let random: Vec<u8> = (0..5000u32)
        .map(|i| (i.wrapping_mul(2654435761) >> 13) as u8)
        .collect();
    let mut cases = vec![
        write("empty.vdb", &[]),
        write("random.vdb", &random),
        write("magic.vdb", &wrong_magic),
    ];
    for pct in (5..100).step_by(5) {
        let cut = cloud.len() * pct / 100;
        cases.push(write(&format!("cut{pct}.vdb"), &cloud[..cut]));
    }
    for path in cases {
        let out = vscatter(&["info", path.to_str().unwrap()]);
        let name = path.file_name().unwrap().to_str().unwrap();
        assert_clean_failure(&out, 1, name);
    }
    // A directory opens as a file does, and its map fails with "No such device".
    let folder = dir.path().join("folder.vdb");
    std::fs::create_dir(&folder).unwrap();
    let out = vscatter(&["info", folder.to_str().unwrap()]);
    assert_clean_failure(&out, 1, "a directory");
}

#[test]
fn billions_of_voxels_in_tiles_are_answered_at_once() {
    // tools/make_tile_fixtures.sh: a root tile (68.7 G voxels) and a 2048³ box of 128³ tiles.
    let expected: Value =
        serde_json::from_str(&std::fs::read_to_string(fixture("huge_tiles.json")).unwrap())
            .unwrap();
    let dir = tempfile::tempdir().unwrap();
    for name in ["huge_root_tile.vdb", "huge_tiles_2048.vdb"] {
        let path = fixture(name);
        let path = path.to_str().unwrap();
        let clock = std::time::Instant::now();
        let o = vscatter(&["info", path, "--json"]);
        assert!(o.status.success());
        let info: Value = serde_json::from_slice(&o.stdout).unwrap();
        assert_eq!(
            info["grids"][0]["active_voxels"],
            expected[name]["active_voxels"]
        );
        // A dry run estimates without listing billions of voxels; a bake refuses with the estimate
        // and the coarser --scale that would fit.
        for command in ["bake", "render"] {
            let out = dir.path().join(format!(
                "x.{}",
                if command == "bake" { "vtc" } else { "png" }
            ));
            let o = vscatter(&[command, path, "-o", out.to_str().unwrap(), "--dry-run"]);
            let said = String::from_utf8_lossy(&o.stdout);
            assert!(
                o.status.success(),
                "{name} {command}: {}",
                crate::stderr(&o)
            );
            assert!(said.starts_with("about "), "{name} {command}: {said}");
        }
        let out = dir.path().join("x.vtc");
        let o = vscatter(&[
            "bake",
            path,
            "-o",
            out.to_str().unwrap(),
            "--max-memory",
            "16G",
        ]);
        assert_clean_failure(&o, 1, "--scale");
        assert!(
            crate::stderr(&o).contains("would need about"),
            "{}",
            crate::stderr(&o)
        );
        // Generous: the benchmark measures 0.14 s on 2 cores; a hang or a fill takes minutes.
        assert!(
            clock.elapsed().as_secs() < 30,
            "{name}: {:?}",
            clock.elapsed()
        );
    }
}

#[test]
fn a_format_222_file_reads_as_its_224_original() {
    // What the reader says of a file depends on its bytes, not on the version word: the same grid
    // written as format 222 (ZIP) gives the same `info` as the 224 original.
    let dir = tempfile::tempdir().unwrap();
    let old = dir.path().join("format_222.vdb");
    std::fs::write(&old, crate::mutation::as_format_222()).unwrap();
    let info = |path: &str| {
        let out = vscatter(&["info", "--json", path]);
        assert!(
            out.status.success(),
            "{}",
            String::from_utf8_lossy(&out.stderr)
        );
        let mut v: Value = serde_json::from_slice(&out.stdout).unwrap();
        let file = v.as_object_mut().unwrap();
        file.remove("file");
        (
            file.remove("format_version"),
            file.remove("library_version"),
            v,
        )
    };
    let (version, library, grids) = info(old.to_str().unwrap());
    let (version_224, _, grids_224) = info(fixture("small_cloud_zip.vdb").to_str().unwrap());
    assert_eq!((version, version_224), (Some(222.into()), Some(224.into())));
    assert_eq!(library, Some("3.2".into()));
    assert_eq!(grids, grids_224);
}

#[test]
fn output_into_a_closed_pipe_ends_quietly() {
    // A pipe whose read end is closed before vscatter starts, as when `vscatter info x.vdb | head`
    // stops reading: the first line written meets a broken pipe, and the process ends as a Unix
    // tool does, by SIGPIPE, with nothing on stderr (no panic from println!).
    let (reader, writer) = std::io::pipe().expect("a pipe");
    drop(reader);
    let child = std::process::Command::new(env!("CARGO_BIN_EXE_vscatter"))
        .args(["info", fixture("cloud.vdb").to_str().unwrap()])
        .stdout(writer)
        .stderr(std::process::Stdio::piped())
        .spawn()
        .expect("the vscatter binary runs");
    let out = child.wait_with_output().expect("it ends");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.is_empty(), "stderr: {err}");
    #[cfg(unix)]
    {
        use std::os::unix::process::ExitStatusExt;
        // 13: SIGPIPE on every Unix.
        assert_eq!(out.status.signal(), Some(13), "status {:?}", out.status);
    }
}
