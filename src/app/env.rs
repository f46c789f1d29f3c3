//! `vscatter env`: project an environment onto SH, reconstruct it at the input's size, write the
//! reconstruction, and report how much was lost (the thesis' initial test program, 5.2.1 and fig. 6.4).

use std::path::Path;
use std::time::Instant;

use super::args::EnvArgs;
use vscatter::error::{Error, Result};
use vscatter::io::atomic::Inputs;
use vscatter::io::image::{ImageBuf, WriteOptions};
use vscatter::light::env::Environment;
use vscatter::light::sh;

pub fn run(args: &EnvArgs) -> Result<()> {
    sh::check_bands(args.bands)?;
    // Refuse a bad output name before the work, not after it.
    check_image_extension(&args.output)?;
    let inputs = Inputs::new([Path::new(&args.env)]);
    inputs.check(&args.output, "-o")?;
    if let Some(original) = &args.original {
        check_image_extension(original)?;
        inputs.check(original, "--original")?;
    }
    let env = Environment::load(&args.env)?;
    let (w, h) = (env.width(), env.height());

    let start = Instant::now();
    let mut coeffs = env.project(args.bands);
    let project_time = start.elapsed();
    coeffs.apply_window(args.window);
    let recon = coeffs.reconstruct_latlong(w, h);
    let error = env.relative_l2_error(&recon);

    let options = WriteOptions {
        exposure: args.png.exposure,
        ..WriteOptions::default()
    };
    ImageBuf::from_rgb(w, h, &recon).write(&args.output, &options)?;
    if let Some(original) = &args.original {
        ImageBuf::from_rgb(w, h, env.pixels()).write(original, &options)?;
    }

    println!(
        "{}: {w}x{h}, {} bands ({} coefficients), window {}, projected in {:.1} ms",
        args.env,
        args.bands,
        sh::coeff_count(args.bands),
        window_name(args.window),
        project_time.as_secs_f64() * 1e3
    );
    println!("relative L2 error over the sphere (solid-angle weighted, RGB): {error:.6}");
    println!("band energy sum_m |E_lm|^2:");
    println!("{:>4} {:>14} {:>14} {:>14}", "l", "R", "G", "B");
    for (l, e) in coeffs.band_energy().iter().enumerate() {
        println!("{l:>4} {:>14.6e} {:>14.6e} {:>14.6e}", e[0], e[1], e[2]);
    }
    Ok(())
}

fn check_image_extension(path: &Path) -> Result<()> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    match ext.as_deref() {
        Some("exr" | "png") => Ok(()),
        _ => Err(Error::usage(format!(
            "{}: output must end in .exr or .png",
            path.display()
        ))),
    }
}

fn window_name(window: sh::Window) -> String {
    use clap::ValueEnum;
    window
        .to_possible_value()
        .map_or_else(|| format!("{window:?}"), |v| v.get_name().to_string())
}
