//! `vscatter env` and the environment code: projections, reconstructions, and bad inputs.

use std::path::Path;

use crate::{assert_clean_failure, fixture, stderr, vscatter, vscatter_in};

#[test]
fn env_reconstructs_a_fixture() {
    let dir = tempfile::tempdir().unwrap();
    let sky = fixture("env/sky_sun.exr");
    let out = vscatter_in(
        dir.path(),
        &[
            "env",
            sky.to_str().unwrap(),
            "-o",
            "recon.exr",
            "--bands",
            "5",
        ],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(stdout.contains("relative L2 error"), "{stdout}");
    assert!(
        stdout
            .lines()
            .filter(|l| l.trim_start().starts_with('4'))
            .count()
            >= 1,
        "{stdout}"
    );
    let recon = exr::prelude::read_first_rgba_layer_from_file(
        dir.path().join("recon.exr"),
        |size, _| size,
        |_, _, _: (f32, f32, f32, f32)| (),
    )
    .unwrap();
    assert_eq!(recon.layer_data.size, exr::math::Vec2(256, 128));
    // Only the output: no temporary file left behind.
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn env_builtin_sky_to_png_with_window() {
    let dir = tempfile::tempdir().unwrap();
    let out = vscatter_in(
        dir.path(),
        &[
            "env",
            "sky",
            "-o",
            "sky.png",
            "--window",
            "hamming",
            "--original",
            "orig.png",
        ],
    );
    assert!(out.status.success(), "{}", stderr(&out));
    for name in ["sky.png", "orig.png"] {
        let bytes = std::fs::read(dir.path().join(name)).unwrap();
        assert_eq!(&bytes[1..4], b"PNG");
    }
}

#[test]
fn env_reads_radiance_hdr() {
    let dir = tempfile::tempdir().unwrap();
    let hdr = fixture("env/studio.hdr");
    let out = vscatter_in(dir.path(), &["env", hdr.to_str().unwrap(), "-o", "r.exr"]);
    assert!(out.status.success(), "{}", stderr(&out));
}

#[test]
fn missing_env_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = vscatter_in(dir.path(), &["env", "nope.exr", "-o", "r.exr"]);
    assert_clean_failure(&out, 1, "nope.exr");
    assert!(!dir.path().join("r.exr").exists());
}

#[test]
fn non_image_env_file() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("notes.exr"),
        "just some text, not an image\n",
    )
    .unwrap();
    let out = vscatter_in(dir.path(), &["env", "notes.exr", "-o", "r.exr"]);
    assert_clean_failure(&out, 1, "notes.exr");
}

#[test]
fn truncated_exr_at_many_lengths() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(fixture("env/studio.exr")).unwrap();
    // Inside the magic, the header, the offset table and the pixel data.
    for len in [2, 30, 200, 400, 1000, bytes.len() / 2, bytes.len() - 1] {
        std::fs::write(dir.path().join("cut.exr"), &bytes[..len]).unwrap();
        let out = vscatter_in(dir.path(), &["env", "cut.exr", "-o", "r.exr"]);
        assert_clean_failure(&out, 1, "cut.exr");
        assert!(!dir.path().join("r.exr").exists());
    }
}

#[test]
fn truncated_hdr() {
    let dir = tempfile::tempdir().unwrap();
    let bytes = std::fs::read(fixture("env/studio.hdr")).unwrap();
    for len in [5, 40, bytes.len() / 2] {
        std::fs::write(dir.path().join("cut.hdr"), &bytes[..len]).unwrap();
        let out = vscatter_in(dir.path(), &["env", "cut.hdr", "-o", "r.exr"]);
        assert_clean_failure(&out, 1, "cut.hdr");
    }
}

#[test]
fn huge_hdr_header_is_refused_before_allocating() {
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(
        dir.path().join("huge.hdr"),
        "#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 1000000 +X 1000000\n",
    )
    .unwrap();
    let out = vscatter_in(dir.path(), &["env", "huge.hdr", "-o", "r.exr"]);
    assert_clean_failure(&out, 1, "huge.hdr");
}

#[test]
fn nan_and_inf_pixels_warn_and_clamp() {
    use exr::prelude::write_rgb_file;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bad.exr");
    write_rgb_file(&path, 16, 8, |x, y| match (x, y) {
        (0, 0) => (f32::NAN, 1.0, 1.0),
        (1, 0) => (f32::INFINITY, 1.0, 1.0),
        (2, 0) => (-3.0, 1.0, 1.0),
        _ => (1.0, 1.0, 1.0),
    })
    .unwrap();
    let out = vscatter_in(
        dir.path(),
        &["env", "bad.exr", "-o", "r.exr", "--bands", "3"],
    );
    let err = stderr(&out);
    assert!(out.status.success(), "{err}");
    assert!(err.contains("warning") && err.contains("bad.exr"), "{err}");
    assert_eq!(err.matches("warning").count(), 1, "warn once: {err}");
    assert!(!err.contains("panicked"));
}

#[test]
fn band_counts_out_of_range_are_usage_errors() {
    let sky = fixture("env/constant.exr");
    for bands in ["0", "100", "21"] {
        let out = vscatter(&[
            "env",
            sky.to_str().unwrap(),
            "-o",
            "never-written.exr",
            "--bands",
            bands,
        ]);
        assert_clean_failure(&out, 2, "--bands");
    }
    assert!(!Path::new("never-written.exr").exists());
}

#[test]
fn unknown_output_extension_is_a_usage_error() {
    let dir = tempfile::tempdir().unwrap();
    let out = vscatter_in(dir.path(), &["env", "sky", "-o", "r.jpg"]);
    assert_clean_failure(&out, 2, "r.jpg");
}

#[test]
fn unwritable_output_names_the_file_and_leaves_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = vscatter_in(
        dir.path(),
        &["env", "sky", "-o", "no/such/dir/r.exr", "--bands", "2"],
    );
    assert_clean_failure(&out, 1, "r.exr");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[test]
fn exr_without_rgb_channels_is_refused() {
    use exr::prelude::*;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("lum.exr");
    let y = AnyChannel::new("Y", FlatSamples::F32(vec![1.0; 8 * 4]));
    let layer = Layer::new(
        (8, 4),
        LayerAttributes::default(),
        Encoding::UNCOMPRESSED,
        AnyChannels::sort(SmallVec::from_vec(vec![y])),
    );
    Image::from_layer(layer).write().to_file(&path).unwrap();
    let out = vscatter_in(dir.path(), &["env", "lum.exr", "-o", "r.exr"]);
    assert_clean_failure(&out, 1, "lum.exr");
    assert!(stderr(&out).contains("R, G and B"), "{}", stderr(&out));
}

#[test]
fn tiny_maps_work() {
    use exr::prelude::write_rgb_file;
    let dir = tempfile::tempdir().unwrap();
    write_rgb_file(dir.path().join("one.exr"), 1, 1, |_, _| (2.0, 2.0, 2.0)).unwrap();
    let out = vscatter_in(
        dir.path(),
        &["env", "one.exr", "-o", "r.exr", "--bands", "20"],
    );
    assert!(out.status.success(), "{}", stderr(&out));
}
