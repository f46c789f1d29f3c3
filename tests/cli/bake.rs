//! `vscatter bake` as a user runs it: determinism, damaged caches, bad input, the thickness warning.

use crate::{assert_clean_failure, fixture, stderr, vscatter, vscatter_in};

#[test]
fn bakes_are_deterministic_and_caches_refuse_damage() {
    let dir = tempfile::tempdir().unwrap();
    let cloud = fixture("small_cloud.vdb");
    let args = |out: &'static str| {
        vec![
            "bake",
            cloud.to_str().unwrap().to_string().leak(),
            "-o",
            out,
            "--bands",
            "4",
            "--samples",
            "64",
        ]
    };
    for out in ["a.vtc", "b.vtc"] {
        let o = vscatter_in(dir.path(), &args(out));
        assert!(o.status.success(), "{}", stderr(&o));
    }
    let a = std::fs::read(dir.path().join("a.vtc")).unwrap();
    assert_eq!(a, std::fs::read(dir.path().join("b.vtc")).unwrap());
    // Truncations and byte flips: one clear line and exit 1, never a panic.
    for (i, cut) in [0, 11, 30, a.len() / 3, a.len() - 9, a.len() - 1]
        .into_iter()
        .enumerate()
    {
        let p = dir.path().join(format!("cut{i}.vtc"));
        std::fs::write(&p, &a[..cut]).unwrap();
        let o = vscatter_in(dir.path(), &["render", p.to_str().unwrap(), "-o", "x.png"]);
        assert_clean_failure(&o, 1, &format!("cut{i}.vtc"));
        // With its magic intact it is a damaged cache, and the error says what to do about it.
        if cut >= 12 {
            assert!(
                stderr(&o).contains("delete it or bake it again"),
                "{}",
                stderr(&o)
            );
        }
    }
    for (i, at) in [12, 40, a.len() / 2, a.len() - 4].into_iter().enumerate() {
        let mut b = a.clone();
        b[at] ^= 0x41;
        let p = dir.path().join(format!("flip{i}.vtc"));
        std::fs::write(&p, &b).unwrap();
        let o = vscatter_in(dir.path(), &["render", p.to_str().unwrap(), "-o", "x.png"]);
        assert_clean_failure(&o, 1, &format!("flip{i}.vtc"));
        assert!(
            stderr(&o).contains("delete it or bake it again"),
            "{}",
            stderr(&o)
        );
        // `info` verifies the checksum too: a damaged cache is not described as if it were whole.
        let o = vscatter(&["info", p.to_str().unwrap()]);
        assert_clean_failure(&o, 1, &format!("flip{i}.vtc"));
    }
    assert!(!dir.path().join("x.png").exists());
}

#[test]
fn bake_refuses_bad_input_clearly() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("x.vtc");
    let out = out.to_str().unwrap();
    let vec3 = fixture("vec3_only.vdb");
    let o = vscatter(&["bake", vec3.to_str().unwrap(), "-o", out]);
    assert_clean_failure(&o, 1, "no scalar grid");
    let ls = fixture("sphere_ls.vdb");
    let o = vscatter(&["bake", ls.to_str().unwrap(), "-o", out]);
    assert_clean_failure(&o, 1, "level set");
    let cloud = fixture("cloud.vdb");
    let cloud = cloud.to_str().unwrap();
    for (flag, value) in [
        ("--bands", "0"),
        ("--bands", "100"),
        ("--scale", "0"),
        ("--albedo", "1.5"),
        ("--sigma-t", "-1"),
        ("--samples", "3"),
        ("--cache-precision", "f8"),
    ] {
        let o = vscatter(&["bake", cloud, "-o", out, flag, value]);
        assert_clean_failure(&o, 2, flag);
    }
    let o = vscatter(&[
        "bake",
        cloud,
        "-o",
        out,
        "--cache-half",
        "--cache-precision",
        "q8",
    ]);
    assert_clean_failure(&o, 2, "--cache-precision");
    let o = vscatter(&["bake", cloud, "-o", out, "--max-memory", "1M"]);
    assert_clean_failure(&o, 1, "--scale");
    assert!(!std::path::Path::new(out).exists());
    let o = vscatter(&["bake", cloud, "-o", out, "--dry-run"]);
    assert!(o.status.success());
    assert!(String::from_utf8_lossy(&o.stdout).contains("estimated peak memory"));
}

#[test]
fn a_bake_too_thick_to_resolve_says_so_and_which_flag_helps() {
    // The cloud (voxel 1, mean density 0.9) at σt 1 and K 6: 5.4 optical depths per transfer
    // voxel, where docs/accuracy.md measures errors of 27-61 %.
    let input = fixture("cloud.vdb");
    let dry = |sigma_t: &str, quiet: bool| {
        let mut args = vec![
            "bake",
            input.to_str().unwrap(),
            "-o",
            "unused.vtc",
            "--dry-run",
            "--sigma-t",
            sigma_t,
        ];
        if quiet {
            args.push("--quiet");
        }
        let out = vscatter(&args);
        assert!(out.status.success(), "{}", stderr(&out));
        stderr(&out)
    };
    let thick = dry("1", false);
    assert!(
        thick.contains("warning: 5.38 optical depths per transfer voxel"),
        "{thick}"
    );
    assert_eq!(thick.lines().count(), 1, "{thick}");
    // --quiet hides progress, never a warning.
    assert_eq!(dry("1", true), thick);
    // The σt the warning suggests clears it.
    let suggested = thick
        .split("--sigma-t ")
        .nth(1)
        .and_then(|rest| rest.split_whitespace().next())
        .expect("the warning names a --sigma-t");
    assert_eq!(
        dry(suggested, false),
        "",
        "--sigma-t {suggested} still warns"
    );
    // 1.94 optical depths per transfer voxel are baked on cells of 3 (0.97 there): no warning;
    // 1.18 are not, and warn.
    assert_eq!(dry("0.36", false), "");
    assert!(dry("0.22", false).contains("warning: 1.18 optical depths"));
}

#[test]
fn a_render_from_a_thick_cache_warns_too_unless_no_soft_light_is_relit() {
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("small_cloud.vdb");
    let bake = vscatter_in(
        dir.path(),
        &[
            "bake",
            input.to_str().unwrap(),
            "-o",
            "c.vtc",
            "--samples",
            "16",
            "--bands",
            "2",
            "--sigma-t",
            "20",
        ],
    );
    assert!(bake.status.success(), "{}", stderr(&bake));
    assert!(
        stderr(&bake).contains("optical depths per transfer voxel"),
        "{}",
        stderr(&bake)
    );
    let render = vscatter_in(
        dir.path(),
        &[
            "render", "c.vtc", "-o", "c.png", "--res", "32x18", "--quiet",
        ],
    );
    assert!(render.status.success(), "{}", stderr(&render));
    assert!(
        stderr(&render).contains("optical depths per transfer voxel"),
        "{}",
        stderr(&render)
    );
    // Lit by a sun alone (no environment's light), nothing is held at the transfer's resolution,
    // from the cache or from a bake on the way.
    let input = input.to_str().unwrap();
    for source in ["c.vtc", input] {
        let sun_only = vscatter_in(
            dir.path(),
            &[
                "render",
                source,
                "-o",
                "s.png",
                "--res",
                "32x18",
                "--sigma-t",
                "20",
                "--samples",
                "16",
                "--bands",
                "2",
                "--env-scale",
                "0",
                "--sun",
                "0,1,0",
                "--quiet",
            ],
        );
        assert!(sun_only.status.success(), "{}", stderr(&sun_only));
        assert_eq!(stderr(&sun_only), "", "{source}");
    }
}

#[test]
fn a_q8_cache_is_smaller_and_says_what_it_holds() {
    let dir = tempfile::tempdir().unwrap();
    let cloud = fixture("small_cloud.vdb");
    let cloud = cloud.to_str().unwrap();
    let mut sizes = Vec::new();
    for p in ["f32", "f16", "q8"] {
        let out = format!("{p}.vtc");
        let o = vscatter_in(
            dir.path(),
            &["bake", cloud, "-o", &out, "--cache-precision", p],
        );
        assert!(o.status.success(), "{}", stderr(&o));
        sizes.push(std::fs::metadata(dir.path().join(&out)).unwrap().len());
        let o = vscatter_in(dir.path(), &["info", &out]);
        assert!(
            String::from_utf8_lossy(&o.stdout).contains(&format!("{p} coefficients")),
            "{}",
            String::from_utf8_lossy(&o.stdout)
        );
    }
    assert!(sizes[0] > sizes[1] && sizes[1] > sizes[2], "{sizes:?}");
    // A q8 cache renders like any other.
    let o = vscatter_in(
        dir.path(),
        &["render", "q8.vtc", "-o", "q8.png", "--res", "32x18"],
    );
    assert!(o.status.success(), "{}", stderr(&o));
}

#[test]
fn an_output_that_names_the_input_is_refused_and_the_input_kept() {
    // Written atomically, a cache or image over an input (the VDB, the map) would replace it:
    // outputs naming one, by any path, are refused before anything is read or written.
    let dir = tempfile::tempdir().unwrap();
    let (input, map) = (dir.path().join("in.vdb"), dir.path().join("map.exr"));
    std::fs::copy(fixture("small_cloud.vdb"), &input).unwrap();
    std::fs::copy(fixture("env/studio.exr"), &map).unwrap();
    let originals = [&input, &map].map(|p| std::fs::read(p).unwrap());
    let other_path = dir.path().join(".").join("in.vdb");
    let cases: [&[&str]; 4] = [
        &["bake", "in.vdb", "-o", other_path.to_str().unwrap()],
        &["render", "in.vdb", "--cache", "in.vdb", "-o", "x.png"],
        &["render", "in.vdb", "--env", "map.exr", "-o", "map.exr"],
        &["env", "map.exr", "-o", "map.exr"],
    ];
    for args in cases {
        let out = vscatter_in(dir.path(), args);
        assert_clean_failure(&out, 2, "that is an input file");
    }
    assert_eq!([&input, &map].map(|p| std::fs::read(p).unwrap()), originals);
    assert!(!dir.path().join("x.png").exists());
}

#[test]
fn stats_say_whether_t_ri_was_fitted() {
    // From albedo 0.8 up a multiple-scattering bake of optically thick transfer voxels keeps
    // T_ri's point values; below it, where a transfer voxel holds under 0.7 optical depths, in a
    // single-scattering bake and with `--fit-direct`, T_ri is fitted to footprint means
    // (docs/method.md, "The bake"). The small cloud's transfer voxel holds σt × 6 × 0.05 × 0.898
    // optical depths: 1.35 at σt 5, 0.54 at σt 2, 0.75 at σt 2.8.
    let dir = tempfile::tempdir().unwrap();
    let cloud = fixture("small_cloud.vdb");
    for (extra, fitted) in [
        (&["--sigma-t", "5"][..], false),
        (&["--sigma-t", "5", "--albedo", "0.8"][..], false),
        (&["--sigma-t", "5", "--albedo", "0.79"][..], true),
        (&["--sigma-t", "2"][..], true),
        (&["--sigma-t", "2.8"][..], false),
        (&["--sigma-t", "5", "--single-scatter"][..], true),
        (&["--sigma-t", "5", "--fit-direct"][..], true),
    ] {
        let mut args = vec!["bake", cloud.to_str().unwrap(), "-o", "a.vtc", "--stats"];
        args.extend_from_slice(&["--bands", "4", "--samples", "64", "--quiet"]);
        args.extend_from_slice(extra);
        let o = vscatter_in(dir.path(), &args);
        assert!(o.status.success(), "{}", stderr(&o));
        let stats: serde_json::Value =
            serde_json::from_slice(o.stdout.trim_ascii()).expect("one JSON line");
        assert_eq!(stats["fitted"], fitted, "{extra:?}: {stats}");
    }
}
