//! `vscatter render`: a real render of a fixture to EXR (with its layers) and PNG, and bad flags.

use crate::{assert_clean_failure, exr_channels, fixture, stderr, vscatter_in, QUICK_BAKE};

#[test]
fn render_writes_an_exr_with_layers_and_a_png() {
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("small_cloud.vdb");
    let mut args = vec![
        "render",
        input.to_str().unwrap(),
        "-o",
        "out.exr",
        "--res",
        "24x16",
        "--sigma-t",
        "20",
        "--stats",
        "--layers",
    ];
    args.extend(QUICK_BAKE);
    let out = vscatter_in(dir.path(), &args);
    assert!(out.status.success(), "{}", stderr(&out));
    let stats: serde_json::Value =
        serde_json::from_str(String::from_utf8_lossy(&out.stdout).trim()).unwrap();
    assert_eq!(stats["rays"], 24 * 16);
    let names = exr_channels(&dir.path().join("out.exr"));
    for want in ["R", "G", "B", "A", "direct.R", "indirect.B", "depth.Z"] {
        assert!(
            names.iter().any(|n| n == want),
            "{want} missing from {names:?}"
        );
    }
    let meta = exr::meta::MetaData::read_from_file(dir.path().join("out.exr"), false).unwrap();
    let size = meta.headers[0].layer_size;
    assert_eq!(size, exr::math::Vec2(24, 16));

    let mut args = vec![
        "render",
        input.to_str().unwrap(),
        "-o",
        "out.png",
        "--res",
        "24x16",
        "--no-background",
        "--camera-pos",
        "-3,1,2",
        "--single-scatter",
        "--stats",
    ];
    args.extend(QUICK_BAKE);
    let out = vscatter_in(dir.path(), &args);
    assert!(out.status.success(), "{}", stderr(&out));
    // A single-scattering bake keeps the density's visibility, which shapes its direct light;
    // the default one does not.
    let single: serde_json::Value =
        serde_json::from_str(String::from_utf8_lossy(&out.stdout).trim()).unwrap();
    let held = |s: &serde_json::Value| s["bake"]["visibility_bytes"].as_u64();
    assert!(held(&single) > Some(0), "{single}");
    assert_eq!(held(&stats), Some(0), "{stats}");
    // A cache renders the same as the VDB it was baked from, with the same bake flags.
    let mut args = vec![
        "bake",
        input.to_str().unwrap(),
        "-o",
        "c.vtc",
        "--sigma-t",
        "20",
    ];
    args.extend(QUICK_BAKE);
    let out = vscatter_in(dir.path(), &args);
    assert!(out.status.success(), "{}", stderr(&out));
    let from_cache = [
        "render",
        "c.vtc",
        "-o",
        "cache.exr",
        "--res",
        "24x16",
        "--stats",
        "--layers",
    ];
    let out = vscatter_in(dir.path(), &from_cache);
    assert!(out.status.success(), "{}", stderr(&out));
    let stats: serde_json::Value =
        serde_json::from_str(String::from_utf8_lossy(&out.stdout).trim()).unwrap();
    assert_eq!(stats["from_cache"], true);
    let read = |name: &str| std::fs::read(dir.path().join(name)).unwrap();
    assert_eq!(read("cache.exr"), read("out.exr"));
    // Without --layers the EXR holds the RGBA alone.
    let plain = ["render", "c.vtc", "-o", "plain.exr", "--res", "24x16"];
    let out = vscatter_in(dir.path(), &plain);
    assert!(out.status.success(), "{}", stderr(&out));
    assert_eq!(
        exr_channels(&dir.path().join("plain.exr")),
        ["A", "B", "G", "R"]
    );
    for f in ["c.vtc", "cache.exr", "plain.exr"] {
        std::fs::remove_file(dir.path().join(f)).unwrap();
    }

    let mut files: Vec<String> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    files.sort();
    assert_eq!(files, ["out.exr", "out.png"]);
}

#[test]
fn render_refuses_bad_flags_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("small_cloud.vdb");
    let input = input.to_str().unwrap();
    let cases: [(&[&str], i32, &str); 8] = [
        (&["render", input, "-o", "x.png", "--spp", "0"], 2, "--spp"),
        (&["render", input, "-o", "x.png", "--layers"], 2, "--layers"),
        // Without --camera-pos too: the framing camera looks down −Z.
        (
            &["render", input, "-o", "x.png", "--up", "0,0,1"],
            2,
            "--up",
        ),
        (&["render", input, "-o", "x.tif"], 2, "x.tif"),
        (
            &["render", input, "-o", "x.png", "--albedo", "1.5"],
            2,
            "--albedo",
        ),
        (
            &["render", input, "-o", "x.png", "--fov", "180"],
            2,
            "--fov",
        ),
        (
            &["render", input, "-o", "x.png", "--bands", "0"],
            2,
            "--bands",
        ),
        (&["render", "missing.vdb", "-o", "x.png"], 1, "missing.vdb"),
    ];
    for (args, code, names) in cases {
        let out = vscatter_in(dir.path(), args);
        assert_clean_failure(&out, code, names);
    }
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[test]
fn render_keeps_and_reuses_its_bake() {
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("small_cloud.vdb");
    // Whether the render baked (its --stats line has a `bake` part) and what it said on stderr.
    let run = |out: &str, albedo: &str| {
        let mut args = vec![
            "render",
            input.to_str().unwrap(),
            "-o",
            out,
            "--res",
            "16x12",
            "--cache",
            "kept.vtc",
            "--albedo",
            albedo,
            "--stats",
        ];
        args.extend(QUICK_BAKE);
        let o = vscatter_in(dir.path(), &args);
        assert!(o.status.success(), "{}", stderr(&o));
        let stats: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
        (stats.get("bake").is_some(), stderr(&o))
    };
    let (baked, said) = run("a.exr", "0.9");
    assert!(baked && !said.contains("using cache"), "{said}");
    let cache = dir.path().join("kept.vtc");
    let kept = std::fs::read(&cache).unwrap();
    // Reused: no bake, one line saying so, the cache untouched and the image identical.
    let (baked, said) = run("b.exr", "0.9");
    assert!(!baked, "baked again");
    assert_eq!(said.trim_end(), format!("using cache {}", "kept.vtc"));
    assert_eq!(std::fs::read(&cache).unwrap(), kept);
    let (a, b) = (dir.path().join("a.exr"), dir.path().join("b.exr"));
    assert_eq!(std::fs::read(a).unwrap(), std::fs::read(b).unwrap());
    // Other bake options: baked afresh, the cache rewritten.
    let (baked, _) = run("c.exr", "0.5");
    assert!(baked);
    assert_ne!(std::fs::read(&cache).unwrap(), kept);
    // A cache in an older format (the version follows the 12-byte magic) is stale, not damaged:
    // baked afresh and rewritten in the current format, equal to a fresh bake.
    let mut bytes = std::fs::read(&cache).unwrap();
    let current = bytes[12..16].to_vec();
    bytes[12..16].copy_from_slice(&1u32.to_le_bytes());
    std::fs::write(&cache, &bytes).unwrap();
    let (baked, _) = run("d.exr", "0.5");
    assert!(baked);
    assert_eq!(std::fs::read(&cache).unwrap()[12..16], current[..]);
    let (c, d) = (dir.path().join("c.exr"), dir.path().join("d.exr"));
    assert_eq!(std::fs::read(c).unwrap(), std::fs::read(d).unwrap());
}

/// Every pixel's RGB of an EXR written by vscatter.
fn read_rgb(path: &std::path::Path) -> Vec<[f32; 3]> {
    let img = exr::prelude::read_first_rgba_layer_from_file(
        path,
        |size, _| (size.width(), vec![[0f32; 3]; size.width() * size.height()]),
        |(w, px): &mut (usize, Vec<[f32; 3]>), pos, (r, g, b, _a): (f32, f32, f32, f32)| {
            px[pos.y() * *w + pos.x()] = [r, g, b];
        },
    )
    .unwrap();
    img.layer_data.channel_data.pixels.1
}

#[test]
fn white_furnace_through_the_whole_chain() {
    // Albedo 1 under a constant environment 1: every pixel is 1, however the cloud scatters.
    // σt = 0.08 keeps one transfer voxel (K = 6) under 0.5 optical depth: limit 3 %, measured
    // +1.1 %. The default σt 1 puts 6 optical depths on a face link: measured −3.1 %, where the
    // fine T_ri and the lattice's own unscattered light differ in surface voxels (README,
    // "Accuracy"); its limit is a regression guard just above that.
    let dir = tempfile::tempdir().unwrap();
    let (cloud, env) = (fixture("cloud.vdb"), fixture("env/constant.exr"));
    for (sigma_t, limit) in [("0.08", 0.03), ("1", 0.035)] {
        let o = vscatter_in(
            dir.path(),
            &[
                "render",
                cloud.to_str().unwrap(),
                "-o",
                "f.exr",
                "--env",
                env.to_str().unwrap(),
                "--albedo",
                "1",
                "--sigma-t",
                sigma_t,
                "--res",
                "96x64",
                "--samples",
                "256",
            ],
        );
        assert!(o.status.success(), "{}", stderr(&o));
        let worst = read_rgb(&dir.path().join("f.exr"))
            .iter()
            .flat_map(|p| p.iter().map(|v| (v - 1.0).abs()))
            .fold(0f32, f32::max);
        assert!(worst < limit, "σt {sigma_t}: furnace pixel off by {worst}");
    }
}

#[test]
fn zero_density_shows_the_environment() {
    // The empty fixture under the split environment: sky above the horizon, ground below,
    // exactly as the environment lookup gives them (the image holds the lookup itself).
    let dir = tempfile::tempdir().unwrap();
    let (empty, env) = (fixture("empty.vdb"), fixture("env/split.exr"));
    let o = vscatter_in(
        dir.path(),
        &[
            "render",
            empty.to_str().unwrap(),
            "-o",
            "e.exr",
            "--env",
            env.to_str().unwrap(),
            "--res",
            "32x24",
            "--camera-pos",
            "0,0,5",
            "--lookat",
            "0,0,0",
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let px = read_rgb(&dir.path().join("e.exr"));
    // Looking along −Z at the horizon: the top rows see (1, 0.95, 0.9), the bottom (0.2, 0.1, 0.05).
    let top = px[32 + 16];
    let bottom = px[22 * 32 + 16];
    for (got, want) in top.iter().zip([1.0, 0.95, 0.9]) {
        assert!((got - want).abs() < 1e-3, "top {top:?}");
    }
    for (got, want) in bottom.iter().zip([0.2, 0.1, 0.05]) {
        assert!((got - want).abs() < 1e-3, "bottom {bottom:?}");
    }
}

#[test]
fn relight_from_a_cache_equals_a_fresh_bake_bit_for_bit() {
    // Bake once, relight the cache under a second HDRI; a render that bakes afresh under that
    // HDRI must give the very same bytes.
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("small_cloud.vdb");
    let studio = fixture("env/studio.exr");
    let (input, studio) = (input.to_str().unwrap(), studio.to_str().unwrap());
    let run = |args: &[&str]| {
        let mut all = args.to_vec();
        all.extend(QUICK_BAKE);
        let o = vscatter_in(dir.path(), &all);
        assert!(o.status.success(), "{}", stderr(&o));
    };
    run(&["bake", input, "-o", "c.vtc"]);
    run(&["render", "c.vtc", "-o", "sky.exr", "--res", "32x24"]);
    run(&[
        "render",
        "c.vtc",
        "-o",
        "relit.exr",
        "--res",
        "32x24",
        "--env",
        studio,
    ]);
    run(&[
        "render",
        input,
        "-o",
        "fresh.exr",
        "--res",
        "32x24",
        "--env",
        studio,
    ]);
    let read = |name: &str| std::fs::read(dir.path().join(name)).unwrap();
    assert_eq!(read("relit.exr"), read("fresh.exr"));
    assert_ne!(read("relit.exr"), read("sky.exr"));
}

#[test]
fn an_unwritable_output_fails_before_any_bake() {
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("cloud.vdb");
    let missing = dir.path().join("no/such/dir/x.png");
    let o = vscatter_in(
        dir.path(),
        &[
            "render",
            input.to_str().unwrap(),
            "-o",
            missing.to_str().unwrap(),
            "--cache",
            "kept.vtc",
            "--stats",
        ],
    );
    assert_clean_failure(&o, 1, "x.png: cannot be written");
    // Nothing was baked: no cache, no statistics.
    assert!(!dir.path().join("kept.vtc").exists());
    assert!(o.stdout.is_empty());
    let o = vscatter_in(
        dir.path(),
        &[
            "bake",
            input.to_str().unwrap(),
            "-o",
            missing.to_str().unwrap(),
        ],
    );
    assert_clean_failure(&o, 1, "cannot be written");
}

#[test]
fn a_volume_without_density_renders_the_environment_with_a_warning() {
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("empty.vdb");
    let o = vscatter_in(
        dir.path(),
        &[
            "render",
            input.to_str().unwrap(),
            "-o",
            "e.png",
            "--res",
            "32x18",
            "--quiet",
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        stderr(&o).trim_end(),
        "vscatter: warning: the volume has no positive density: the picture shows only the environment"
    );
    assert!(dir.path().join("e.png").exists());
}

#[test]
fn automatic_framing_fills_the_frame_with_the_smoke() {
    // The real smoke frame's active box is mostly near-zero density; framed on the density, the
    // visible smoke covers a good part of the picture rather than a blob in its middle.
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("smoke_double_openvdb7.vdb");
    let o = vscatter_in(
        dir.path(),
        &[
            "render",
            input.to_str().unwrap(),
            "-o",
            "s.exr",
            "--res",
            "64x36",
            "--no-background",
            "--sigma-t",
            "0.2",
            "--samples",
            "16",
            "--bands",
            "2",
            "--quiet",
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    let img = exr::prelude::read_first_rgba_layer_from_file(
        dir.path().join("s.exr"),
        |res, _| vec![0f32; res.width() * res.height()],
        |alpha: &mut Vec<f32>, pos, (_, _, _, a): (f32, f32, f32, f32)| {
            alpha[pos.y() * 64 + pos.x()] = a
        },
    )
    .unwrap();
    let alpha = &img.layer_data.channel_data.pixels;
    let covered = alpha.iter().filter(|a| **a > 0.01).count();
    assert!(
        covered * 4 > alpha.len(),
        "the smoke covers {covered} of {} pixels",
        alpha.len()
    );
}

#[test]
fn the_framing_camera_turns_to_a_lookat_and_rolls_to_an_up() {
    // Without --camera-pos the camera frames the volume from +Z; --lookat and --up, given alone,
    // turn it where it stands rather than go unheard.
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("small_cloud.vdb");
    let input = input.to_str().unwrap();
    let render = |name: &str, extra: &[&str]| {
        let mut args = vec!["render", input, "-o", name, "--res", "32x18", "--quiet"];
        args.extend(QUICK_BAKE);
        args.extend(extra);
        let out = vscatter_in(dir.path(), &args);
        assert!(out.status.success(), "{}", stderr(&out));
        read_rgb(&dir.path().join(name))
    };
    let plain = render("plain.exr", &[]);
    assert_eq!(plain, render("default_up.exr", &["--up", "0,1,0"]));
    assert_ne!(plain, render("rolled.exr", &["--up", "1,0,0"]));
    assert_ne!(plain, render("turned.exr", &["--lookat", "2,0,0"]));
}
