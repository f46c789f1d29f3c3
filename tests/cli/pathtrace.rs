//! `render --method pathtrace` and `compare`: the reference renderer's outputs, determinism and
//! flags, and a small version of the accuracy report (tools/accuracy.sh) whose thresholds sit just
//! above what the two renderers achieve today, so a regression in either fails here.

use std::path::Path;

use crate::{assert_clean_failure, exr_channels, fixture, stderr, vscatter_in};

fn stats_of(out: &std::process::Output) -> serde_json::Value {
    serde_json::from_str(String::from_utf8_lossy(&out.stdout).trim()).unwrap()
}

#[test]
fn pathtrace_writes_the_same_layers_on_any_thread_count() {
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("small_cloud.vdb");
    let render = |threads: &str, out: &str| {
        let o = vscatter_in(
            dir.path(),
            &[
                "render",
                input.to_str().unwrap(),
                "-o",
                out,
                "--method",
                "pathtrace",
                "--res",
                "24x16",
                "--spp",
                "8",
                "--sigma-t",
                "20",
                "--threads",
                threads,
                "--stats",
                "--layers",
            ],
        );
        assert!(o.status.success(), "{}", stderr(&o));
        // σt 20 would make transfer voxels far too thick, but the path tracer has none: no warning.
        assert_eq!(stderr(&o), "");
        stats_of(&o)
    };
    let stats = render("1", "one.exr");
    assert_eq!(stats["method"], "pathtrace");
    assert_eq!(stats["paths"], 24 * 16 * 8);
    assert!(stats["scatterings"].as_u64().unwrap() > 0);
    render("2", "two.exr");
    let read = |name: &str| std::fs::read(dir.path().join(name)).unwrap();
    assert_eq!(
        read("one.exr"),
        read("two.exr"),
        "thread count changed the image"
    );
    let names = exr_channels(&dir.path().join("one.exr"));
    for want in ["R", "A", "direct.R", "indirect.G", "depth.Z"] {
        assert!(names.iter().any(|n| n == want), "{want} missing: {names:?}");
    }
}

#[test]
fn flags_that_mean_nothing_to_the_method_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let input = fixture("small_cloud.vdb");
    let cases: [(&str, &[&str], &str); 6] = [
        ("transfer", &["--max-bounces", "2"], "--max-bounces"),
        ("pathtrace", &["--single-scatter"], "--max-bounces 1"),
        ("pathtrace", &["--fit-direct"], "--fit-direct"),
        ("pathtrace", &["--cache", "c.vtc"], "--cache"),
        ("pathtrace", &["--max-bounces", "0"], "--max-bounces 0"),
        ("pathtrace", &["--spp", "0"], "--spp"),
    ];
    for (method, extra, names) in cases {
        let mut args = vec![
            "render",
            input.to_str().unwrap(),
            "-o",
            "x.png",
            "--method",
            method,
        ];
        args.extend_from_slice(extra);
        assert_clean_failure(&vscatter_in(dir.path(), &args), 2, names);
    }
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

/// Renders `fixture` under the studio environment at the accuracy test's settings.
fn render(dir: &Path, fixture_name: &str, out: &str, extra: &[&str]) {
    render_studio(dir, fixture_name, out, ("64x36", "0.08"), extra);
}

/// Renders `fixture` under the studio environment, albedo 0.9, the volume alone, at the
/// resolution and σt of `(res, sigma_t)`.
fn render_studio(
    dir: &Path,
    fixture_name: &str,
    out: &str,
    (res, sigma_t): (&str, &str),
    extra: &[&str],
) {
    let (input, env) = (fixture(fixture_name), fixture("env/studio.exr"));
    let mut args = vec![
        "render",
        input.to_str().unwrap(),
        "-o",
        out,
        "--env",
        env.to_str().unwrap(),
        "--res",
        res,
        "--sigma-t",
        sigma_t,
        "--albedo",
        "0.9",
        "--no-background",
    ];
    args.extend_from_slice(extra);
    let o = vscatter_in(dir, &args);
    assert!(o.status.success(), "{}", stderr(&o));
}

/// `vscatter compare IMAGE REF --reference2 REF2 --json`.
fn compare(dir: &Path, image: &str, r1: &str, r2: &str) -> serde_json::Value {
    let o = vscatter_in(dir, &["compare", image, r1, "--reference2", r2, "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    stats_of(&o)
}

#[test]
fn transfer_agrees_with_the_path_tracer() {
    // The accuracy report in miniature: 0.48 optical depth per transfer voxel, a soft environment,
    // albedo 0.9, the path tracer's noise (two seeds) subtracted. The report's targets are 5 %
    // (single) and 10 % (multiple); these limits sit just above what is measured here, at this
    // resolution and noise, so either renderer drifting shows:
    //   cloud: single 3.16 %, multiple 3.65 %;  torus: single 2.60 %, multiple 4.41 %.
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for (name, single_limit, multi_limit) in
        [("cloud.vdb", 0.035, 0.039), ("torus.vdb", 0.029, 0.048)]
    {
        for seed in ["1", "2"] {
            let pt = ["--method", "pathtrace", "--spp", "512", "--seed", seed];
            render(
                d,
                name,
                &format!("pt1_{seed}.exr"),
                &[&pt[..], &["--max-bounces", "1"]].concat(),
            );
            render(d, name, &format!("pt_{seed}.exr"), &pt);
        }
        render(d, name, "single.exr", &["--spp", "16", "--single-scatter"]);
        render(d, name, "multi.exr", &["--spp", "16"]);
        let single = compare(d, "single.exr", "pt1_1.exr", "pt1_2.exr");
        let multi = compare(d, "multi.exr", "pt_1.exr", "pt_2.exr");
        let (s, m) = (
            single["relative_rmse"].as_f64().unwrap(),
            multi["relative_rmse"].as_f64().unwrap(),
        );
        eprintln!("{name}: single {s:.4}, multiple {m:.4}");
        assert!(s < single_limit, "{name}: single scattering {s}");
        assert!(m < multi_limit, "{name}: multiple scattering {m}");
        // The reference is good enough to measure at this level.
        assert!(multi["reference_noise"].as_f64().unwrap() < 0.06, "{multi}");
        assert!(multi["pixels"].as_u64().unwrap() > 500, "{multi}");
    }
}

#[test]
fn compare_refuses_bad_input_cleanly() {
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    let (cloud, empty) = (fixture("small_cloud.vdb"), fixture("empty.vdb"));
    for (input, out, res) in [
        (&cloud, "a.exr", "24x16"),
        (&cloud, "b.exr", "24x16"),
        (&cloud, "c.exr", "20x16"),
        (&empty, "e.exr", "24x16"),
    ] {
        let o = vscatter_in(
            d,
            &[
                "render",
                input.to_str().unwrap(),
                "-o",
                out,
                "--res",
                res,
                "--sigma-t",
                "20",
                "--bands",
                "3",
                "--scale",
                "4",
                "--samples",
                "64",
                "--no-background",
            ],
        );
        assert!(o.status.success(), "{}", stderr(&o));
    }
    // An image against itself: no error at all.
    let same = vscatter_in(d, &["compare", "a.exr", "b.exr", "--json"]);
    assert!(same.status.success(), "{}", stderr(&same));
    assert_eq!(stats_of(&same)["relative_rmse"], 0.0);
    std::fs::write(d.join("junk.exr"), b"not an exr").unwrap();
    let cases: [(&[&str], i32, &str); 5] = [
        (&["compare", "a.exr", "c.exr"], 1, "20x16"),
        (&["compare", "a.exr", "missing.exr"], 1, "missing.exr"),
        (&["compare", "a.exr", "junk.exr"], 1, "junk.exr"),
        (
            &["compare", "a.exr", "b.exr", "--diff", "d.jpg"],
            2,
            "d.jpg",
        ),
        (&["compare", "e.exr", "e.exr"], 1, "no volume pixels"),
    ];
    for (args, code, names) in cases {
        assert_clean_failure(&vscatter_in(d, args), code, names);
    }
}

#[test]
fn a_finer_transfer_lights_no_hot_pixels() {
    // At --scale 3 the torus's surface falls midway between nodes in places, where the fit alone
    // cannot tell two nodes apart: unpulled, a few ran off and lit pixels many times too bright
    // (56 % against the --scale 6 render at this size; 9 % with the fit's pull).
    let dir = tempfile::tempdir().unwrap();
    let d = dir.path();
    for (scale, out) in [("3", "k3.exr"), ("6", "k6.exr")] {
        let flags = ["--single-scatter", "--scale", scale, "--quiet"];
        render_studio(d, "torus.vdb", out, ("96x54", "0.368"), &flags);
    }
    let o = vscatter_in(d, &["compare", "k3.exr", "k6.exr", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let rmse = stats_of(&o)["relative_rmse"].as_f64().unwrap();
    assert!(rmse < 0.2, "--scale 3 against --scale 6: {rmse}");
}
