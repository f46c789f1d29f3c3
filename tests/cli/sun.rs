//! Suns on the command line: `--sun`, `--light`, the built-in sky's sun, a sun found in an HDRI,
//! and bad lights refused in one line.

use crate::{assert_clean_failure, fixture, stderr, vscatter_in, QUICK_BAKE};

/// The cloud fixture small and thin, so its on-the-fly bake is quick.
const QUICK: [&str; 4] = ["--res", "48x27", "--sigma-t", "0.3"];

fn render(dir: &std::path::Path, out: &str, extra: &[&str]) -> std::process::Output {
    let input = fixture("cloud.vdb");
    let mut args = vec!["render", input.to_str().unwrap(), "-o", out];
    args.extend_from_slice(&QUICK);
    args.extend_from_slice(&QUICK_BAKE);
    args.extend_from_slice(extra);
    vscatter_in(dir, &args)
}

#[test]
fn bad_suns_are_refused_in_one_line_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let nine: Vec<&str> = std::iter::repeat_n(["--sun", "0,1,0"], 9)
        .flatten()
        .collect();
    let cases: [(&[&str], &str); 6] = [
        (&["--sun", "0,0,0"], "--sun 0,0,0"),
        (&["--sun", "nan,1,0"], "--sun nan,1,0"),
        (&["--sun", "0,1,0,1,-1,1"], "--sun 0,1,0,1,-1,1"),
        (&["--sun", "0,1,0,1,1,inf"], "--sun 0,1,0,1,1,inf"),
        (&["--light", "1,2"], "--light 1,2"),
        (&nine, "at most 8"),
    ];
    for (extra, names) in cases {
        assert_clean_failure(&render(dir.path(), "x.png", extra), 2, names);
    }
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

/// Mean of the `direct.R` channel over the image.
fn mean_direct(path: &std::path::Path) -> f64 {
    use exr::prelude::*;
    let image = read()
        .no_deep_data()
        .largest_resolution_level()
        .all_channels()
        .first_valid_layer()
        .all_attributes()
        .from_file(path)
        .unwrap();
    let red = image
        .layer_data
        .channel_data
        .list
        .iter()
        .find(|c| c.name.to_string() == "direct.R")
        .expect("a direct layer");
    let values: Vec<f32> = red.sample_data.values_as_f32().collect();
    values.iter().map(|v| *v as f64).sum::<f64>() / values.len() as f64
}

#[test]
fn a_sun_lights_the_direct_layer_and_light_means_what_vdb_render_means() {
    let dir = tempfile::tempdir().unwrap();
    // Black environment: all the light is the sun's.
    let black = [
        "--env",
        "sky",
        "--env-scale",
        "0",
        "--single-scatter",
        "--layers",
    ];
    let sun: Vec<&str> = black
        .iter()
        .copied()
        .chain(["--sun", "0.3,0.3,0,1,1,1"])
        .collect();
    let out = render(dir.path(), "sun.exr", &sun);
    assert!(out.status.success());
    // vdb_render's colour C is an irradiance of 4π·C.
    let c = 1.0 / (4.0 * std::f64::consts::PI);
    let spec = format!("0.3,0.3,0,{c},{c},{c}");
    let light: Vec<&str> = black.iter().copied().chain(["--light", &spec]).collect();
    assert!(render(dir.path(), "light.exr", &light).status.success());
    assert!(render(dir.path(), "none.exr", &black).status.success());
    let (s, l, n) = (
        mean_direct(&dir.path().join("sun.exr")),
        mean_direct(&dir.path().join("light.exr")),
        mean_direct(&dir.path().join("none.exr")),
    );
    assert_eq!(n, 0.0);
    assert!(
        s > 0.0 && (l - s).abs() < 1e-5 * s,
        "--sun {s}, --light {l}"
    );
}

#[test]
fn the_sun_of_an_hdri_is_found_and_said_unless_asked_not_to() {
    let dir = tempfile::tempdir().unwrap();
    let env = fixture("env/sky_sun.exr");
    let env = env.to_str().unwrap();
    let out = render(dir.path(), "a.png", &["--env", env]);
    assert!(out.status.success(), "{}", stderr(&out));
    let err = stderr(&out);
    assert!(
        err.lines()
            .any(|l| l.contains("sun found at elevation 35.0°")),
        "{err}"
    );
    let out = render(dir.path(), "b.png", &["--env", env, "--no-extract-sun"]);
    assert!(out.status.success());
    assert!(!stderr(&out).contains("sun found"), "{}", stderr(&out));
    // A studio map has no sun; nothing is said of one (the resolution warning names suns in
    // general).
    let studio = fixture("env/studio.exr");
    let out = render(dir.path(), "c.png", &["--env", studio.to_str().unwrap()]);
    let err = stderr(&out);
    assert!(
        out.status.success()
            && !err
                .lines()
                .filter(|l| !l.contains("optical depths per transfer voxel"))
                .any(|l| l.contains("sun")),
        "{err}"
    );
}

#[test]
fn dry_run_counts_the_shadow_volumes_and_the_budget_refuses_them() {
    let dir = tempfile::tempdir().unwrap();
    let out = render(
        dir.path(),
        "x.png",
        &["--dry-run", "--sun", "0,1,0", "--sun", "1,1,0"],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        stdout.contains("2 suns: shadow volumes and fluences about"),
        "{stdout}"
    );
    // From a VDB the suns' lattice is planned on the transfer the bake will lay out: the
    // cloud's 223 749 voxel nodes, 26 links of 24 bytes each, are over 130 MiB while they solve.
    let solve = stdout
        .split("their lattice solve about ")
        .nth(1)
        .and_then(|s| s.split(" MiB").next())
        .and_then(|s| s.parse::<f64>().ok());
    assert!(solve.is_some_and(|m| m > 130.0), "{stdout}");
    // From a cache (so the bake's own budget is not what refuses): the render's whole peak is
    // estimated, and refused. A PNG this small is one band of rows, held twice (44 bytes a pixel
    // each), and the 8-bit pixels (4): 48 × 27 × 92 = 119 232 B.
    let input = fixture("cloud.vdb");
    let mut bake = vec!["bake", input.to_str().unwrap(), "-o", "c.vtc"];
    bake.extend_from_slice(&QUICK[2..]);
    bake.extend_from_slice(&QUICK_BAKE);
    assert!(vscatter_in(dir.path(), &bake).status.success());
    let args = ["render", "c.vtc", "-o", "x.png", "--res", "48x27"];
    let dry = vscatter_in(dir.path(), &[&args[..], &["--dry-run"]].concat());
    let stdout = String::from_utf8_lossy(&dry.stdout);
    assert!(
        dry.status.success() && stdout.contains("render: estimated peak memory"),
        "{stdout}{}",
        stderr(&dry)
    );
    assert!(stdout.contains("image 116.44 KiB, "), "{stdout}");
    // The default sky's sun is new to this process: its lattice solve is counted.
    assert!(stdout.contains("a sun's lattice solve "), "{stdout}");
    assert_clean_failure(
        &vscatter_in(dir.path(), &[&args[..], &["--max-memory", "5M"]].concat()),
        1,
        "this render needs about",
    );
    assert!(!dir.path().join("x.png").exists());
}

#[test]
fn a_suns_multiple_scattering_is_solved_on_finer_cells_than_the_transfers() {
    let dir = tempfile::tempdir().unwrap();
    let lattice = |out: &std::process::Output| {
        assert!(out.status.success(), "{}", stderr(out));
        let stats: serde_json::Value =
            serde_json::from_str(String::from_utf8_lossy(&out.stdout).trim()).unwrap();
        let n = |key: &str| stats[key].as_u64().unwrap();
        (
            n("sun_lattice_edge"),
            n("sun_lattice_nodes"),
            n("transfer_voxels"),
        )
    };
    // The quick bake's cells are 4 voxels: the sky's sun is solved on the density's own voxels,
    // each active one a node.
    let (edge, nodes, transfer) = lattice(&render(dir.path(), "a.exr", &["--stats"]));
    assert_eq!(edge, 1);
    assert!(
        nodes > 195_762 && nodes > transfer,
        "{nodes} against {transfer}"
    );
    // With the transfer's cells at 3 voxels the suns' nodes are the same voxels.
    let input = fixture("cloud.vdb");
    let args = ["render", input.to_str().unwrap(), "-o", "b.exr", "--stats"];
    let quick = ["--bands", "3", "--scale", "3", "--samples", "64"];
    let out = vscatter_in(dir.path(), &[&args[..], &QUICK[..], &quick[..]].concat());
    let (edge, voxel_nodes, transfer) = lattice(&out);
    assert_eq!((edge, voxel_nodes), (1, nodes));
    assert!(transfer < nodes, "{transfer}");
    // Without a sun there is no lattice of theirs.
    let out = render(
        dir.path(),
        "c.exr",
        &["--stats", "--env", "sky", "--no-extract-sun"],
    );
    assert_eq!(lattice(&out).0, 0);
}
