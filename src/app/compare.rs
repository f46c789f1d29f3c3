//! `vscatter compare IMAGE.exr REFERENCE.exr`: the measure of [`vscatter::compare`], printed as
//! text or JSON, with an optional false-colour difference image.

use vscatter::compare::{compare, diff_image, read, Rgba, PIXEL_TOLERANCE, VOLUME_ALPHA};
use vscatter::io::image::WriteOptions;
use vscatter::{Error, Result};

use super::args::CompareArgs;

pub fn run(args: &CompareArgs) -> Result<()> {
    if let Some(diff) = &args.diff {
        if diff.extension().and_then(|e| e.to_str()) != Some("png") {
            return Err(Error::usage(format!(
                "--diff {}: must end in .png",
                diff.display()
            )));
        }
    }
    let (w, h, a) = read(&args.image)?;
    let mut refs = Vec::new();
    for path in std::iter::once(&args.reference).chain(&args.reference2) {
        let (rw, rh, px) = read(path)?;
        if (rw, rh) != (w, h) {
            return Err(Error::format(
                path,
                format!("is {rw}x{rh}, but {} is {w}x{h}", args.image.display()),
            ));
        }
        refs.push(px);
    }
    let Some(c) = compare(&a, &refs[0], refs.get(1).map(Vec::as_slice)) else {
        return Err(Error::Runtime(format!(
            "{}: no volume pixels to compare (render both with --no-background; \
             a pixel counts where alpha > {VOLUME_ALPHA})",
            args.reference.display()
        )));
    };
    if let Some(path) = &args.diff {
        // Against the mean of the references: half the noise variance of either.
        let reference: Rgba = match refs.get(1) {
            Some(r2) => refs[0]
                .iter()
                .zip(r2)
                .map(|(p, q)| std::array::from_fn(|c| 0.5 * (p[c] + q[c])))
                .collect(),
            None => refs[0].clone(),
        };
        diff_image(w, h, &a, &reference, c.reference_mean).write(path, &WriteOptions::default())?;
    }
    if args.json {
        println!("{}", serde_json::to_string(&c).unwrap_or_default());
    } else {
        println!(
            "relative RMSE {:.2} % over {} volume pixels (raw {:.2} %, reference noise {:.2} %, bias {:+.2} %)",
            100.0 * c.relative_rmse,
            c.pixels,
            100.0 * c.relative_rmse_raw,
            100.0 * c.reference_noise,
            100.0 * c.relative_bias
        );
        println!(
            "{:.1} % of {} lit pixels within {:.0} % of the reference; 99th percentile {:.1} %",
            100.0 * c.lit_within_tolerance,
            c.lit_pixels,
            100.0 * PIXEL_TOLERANCE,
            100.0 * c.lit_p99_difference
        );
    }
    Ok(())
}
