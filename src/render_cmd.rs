//! `vscatter render`: volume in, image out. With `--method transfer` (the default) it reads a
//! `.vtc` cache (density and transfer) or a VDB whose transfer it bakes first, projects the
//! environment onto SH, relights and marches; with `--method pathtrace` it path-traces the density
//! under the environment itself. Either way it writes the EXR (RGBA plus direct, indirect and depth
//! layers) or PNG atomically.

use std::path::Path;
use std::time::Instant;

use glam::Vec3;

use crate::cli::{GlobalArgs, Method, RenderArgs};
use crate::env::Environment;
use crate::error::{Error, Result};
use crate::image::{ExrPrecision, WriteOptions};
use crate::pathtrace::{EnvLight, Medium3d, PathStats, PathTracer};
use crate::render::{render_volume, world_bounds, Background, CameraSpec, Frame, MarchSettings};
use crate::volume::dda::Occupancy;
use crate::volume::load_density;

/// Most samples per pixel accepted: beyond this a box filter has long converged.
const MAX_SPP: u32 = 65536;
/// Default samples per pixel of the transfer method: its march is smooth, one ray per pixel is a
/// clean image; more only antialias edges.
const DEFAULT_SPP: u32 = 1;
/// Default samples per pixel of the path tracer: enough for a recognisable preview of a cloud
/// (a few percent noise on its bright side); references take thousands.
const DEFAULT_PATHTRACE_SPP: u32 = 64;

pub fn run(args: &RenderArgs, global: &GlobalArgs) -> Result<()> {
    // Every flag is checked before any work, so a typo costs nothing.
    let ext = |p: &Path| {
        p.extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
    };
    if !matches!(ext(&args.output).as_deref(), Some("exr" | "png")) {
        return Err(Error::usage(format!(
            "{}: output must end in .exr or .png",
            args.output.display()
        )));
    }
    let bake_config = args.bake.validate()?;
    let spp = args.spp.unwrap_or(match args.method {
        Method::Transfer => DEFAULT_SPP,
        Method::Pathtrace => DEFAULT_PATHTRACE_SPP,
    });
    if !(1..=MAX_SPP).contains(&spp) {
        return Err(Error::usage(format!(
            "--spp {spp}: must lie in 1..={MAX_SPP}"
        )));
    }
    check_method_flags(args)?;
    if !(args.env_scale.is_finite() && args.env_scale >= 0.0) {
        return Err(Error::usage(format!(
            "--env-scale {}: must be a finite number ≥ 0",
            args.env_scale
        )));
    }
    if !args.env_rotate.is_finite() || !args.png.exposure.is_finite() {
        return Err(Error::usage(
            "--env-rotate and --exposure must be finite numbers",
        ));
    }
    let spec = CameraSpec {
        position: args.camera_pos.map(Vec3::from),
        lookat: args.lookat.map(Vec3::from),
        up: Vec3::from(args.up),
        fov_deg: args.fov,
        width: args.res.0,
        height: args.res.1,
    };
    // Validates resolution, fov and pose before the bake (a framing camera of a unit box).
    spec.camera(None)?;
    if args.method == Method::Pathtrace {
        return pathtrace(args, global, &bake_config, &spec, spp);
    }
    let clock = Instant::now();
    // A cache is recognised by its content, so a renamed file still works.
    let cached = crate::transfer::cache::is_cache(&args.input)?;
    let mut keep: Option<(crate::transfer::cache::Source, &std::path::Path)> = None;
    let (density, baked) = if cached {
        let cache = crate::transfer::cache::read(&args.input)?;
        (cache.density, Some(cache.transfer))
    } else {
        let loaded = load_density(&args.input, bake_config.grid.as_deref())?;
        match &args.cache {
            Some(path) => {
                let source = crate::bake::source_of(&args.input, &loaded.name)?;
                match reusable(path, &source, &bake_config)? {
                    Some(cache) => (cache.density, Some(cache.transfer)),
                    None => {
                        keep = Some((source, path.as_path()));
                        (loaded.grid, None)
                    }
                }
            }
            None => (loaded.grid, None),
        }
    };
    let read_seconds = clock.elapsed().as_secs_f64();
    let bands = baked
        .as_ref()
        .map_or(bake_config.settings.bands, |t| t.bands);

    let clock = Instant::now();
    let env = Environment::load(&args.env)?;
    let mut sh = env.project(bands);
    sh.apply_window(args.window);
    let angle = args.env_rotate.to_radians();
    sh.rotate_y(angle);
    let scale = args.env_scale;
    let coeffs: Vec<[f32; 3]> = sh.coeffs.iter().map(|c| c.map(|v| v * scale)).collect();
    let env_seconds = clock.elapsed().as_secs_f64();

    let clock = Instant::now();
    let transfer = match baked {
        Some(t) => t,
        None => match crate::bake::bake_checked(&density, &bake_config, global)? {
            Some((t, _)) => t,
            // --dry-run: the estimate is printed, nothing is rendered.
            None => return Ok(()),
        },
    };
    if let Some((source, path)) = keep {
        let header = crate::transfer::cache::header(
            &density,
            &transfer,
            &bake_config.settings,
            source,
            bake_config.half,
        );
        crate::transfer::cache::write(path, &header, &density, &transfer)?;
    }
    let bake_seconds = clock.elapsed().as_secs_f64();

    let camera = spec.camera(world_bounds(&density))?;
    let lookup = |d: Vec3| {
        env.lookup_rotated([d.x as f64, d.y as f64, d.z as f64], angle)
            .map(|v| v * scale)
    };
    let background: Option<Background> = (!args.no_background).then_some(&lookup);
    let settings = MarchSettings {
        spp,
        ..MarchSettings::default()
    };
    let bar = crate::progress::bar(0, "render", global.quiet);
    let (frame, march_stats, report) = render_volume(
        &density, &transfer, &coeffs, background, &camera, &settings, &bar,
    );
    let write_seconds = write_frame(frame, args)?;

    if global.stats {
        let line = serde_json::json!({
            "command": "render",
            "method": "transfer",
            "input": args.input.display().to_string(),
            "read_seconds": read_seconds,
            "env_seconds": env_seconds,
            "bake_seconds": bake_seconds,
            "from_cache": cached,
            "transfer_voxels": transfer.layout.len(),
            "occupancy_seconds": report.occupancy.as_secs_f64(),
            "relight_seconds": report.relight.as_secs_f64(),
            "bricks_seconds": report.bricks.as_secs_f64(),
            "march_seconds": report.march.as_secs_f64(),
            "brick_bytes": report.brick_bytes,
            "write_seconds": write_seconds,
            "rays": march_stats.rays,
            "samples_taken": march_stats.samples_taken,
            "samples_skipped": march_stats.samples_skipped,
            "active_voxels": density.active_voxels(),
            "peak_memory_bytes": crate::bake::peak_memory(),
        });
        println!("{line}");
    }
    Ok(())
}

/// The cache at `path`, when it exists and was baked from this very source with these settings;
/// `None` means bake afresh (and overwrite it). A damaged cache is an error, not silently redone;
/// one in an older format is merely stale, like one baked with other settings (the format
/// changes when what the bake computes does, so a new bake is what the user wants).
fn reusable(
    path: &std::path::Path,
    source: &crate::transfer::cache::Source,
    config: &crate::cli::BakeConfig,
) -> Result<Option<crate::transfer::cache::Cache>> {
    if !path.exists() {
        return Ok(None);
    }
    if let Some(v) = crate::transfer::cache::format_version(path)? {
        if v < crate::transfer::cache::VERSION {
            return Ok(None);
        }
    }
    let cache = crate::transfer::cache::read(path)?;
    let h = &cache.header;
    let same = &h.source == source
        && h.settings().as_ref() == Some(&config.settings)
        && h.sigma_t == config.medium.sigma_t
        && h.albedo == config.medium.albedo
        && (h.coefficients == "f16") == config.half;
    Ok(same.then_some(cache))
}

/// Refuses flags that mean nothing to the chosen method, naming the one that does the job.
fn check_method_flags(args: &RenderArgs) -> Result<()> {
    match args.method {
        Method::Transfer if args.max_bounces.is_some() => Err(Error::usage(
            "--max-bounces applies to --method pathtrace; the transfer's single scattering is --single-scatter",
        )),
        Method::Pathtrace if args.bake.single_scatter => Err(Error::usage(
            "--single-scatter applies to the transfer; the path tracer's single scattering is --max-bounces 1",
        )),
        Method::Pathtrace if args.cache.is_some() => Err(Error::usage(
            "--cache keeps a bake, and --method pathtrace bakes nothing",
        )),
        Method::Pathtrace if args.max_bounces == Some(0) => Err(Error::usage(
            "--max-bounces 0: must be at least 1 (1 = single scattering)",
        )),
        _ => Ok(()),
    }
}

/// Writes `frame` to `args.output` (EXR or PNG by extension); returns the seconds it took.
fn write_frame(frame: Frame, args: &RenderArgs) -> Result<f64> {
    let clock = Instant::now();
    let options = WriteOptions {
        exposure: args.png.exposure,
        precision: if args.exr_half {
            ExrPrecision::Half
        } else {
            ExrPrecision::Float
        },
    };
    frame.into_image().write(&args.output, &options)?;
    Ok(clock.elapsed().as_secs_f64())
}

/// `--method pathtrace`: the density (of a VDB, or of a cache with its medium) path-traced under
/// the full-resolution environment.
fn pathtrace(
    args: &RenderArgs,
    global: &GlobalArgs,
    bake_config: &crate::cli::BakeConfig,
    spec: &CameraSpec,
    spp: u32,
) -> Result<()> {
    let clock = Instant::now();
    let (density, medium) = if crate::transfer::cache::is_cache(&args.input)? {
        let cache = crate::transfer::cache::read(&args.input)?;
        (cache.density, cache.transfer.medium)
    } else {
        let loaded = load_density(&args.input, bake_config.grid.as_deref())?;
        (loaded.grid, bake_config.medium)
    };
    let read_seconds = clock.elapsed().as_secs_f64();

    let clock = Instant::now();
    let env = Environment::load(&args.env)?;
    let light = EnvLight::new(&env, args.env_rotate.to_radians(), args.env_scale);
    let occupancy = Occupancy::build(&density);
    let bricks = crate::volume::bricks::Bricks::build(&density);
    let setup_seconds = clock.elapsed().as_secs_f64();

    let camera = spec.camera(world_bounds(&density))?;
    let tracer = PathTracer {
        medium: Medium3d {
            density: &density,
            bricks: &bricks,
            occupancy: &occupancy,
            sigma_t: medium.sigma_t,
        },
        albedo: medium.albedo,
        light: &light,
        max_bounces: args.max_bounces.unwrap_or(u32::MAX),
        seed: args.bake.seed,
    };
    let lookup = |d: Vec3| light.radiance(d);
    let background: Option<Background> = (!args.no_background).then_some(&lookup);
    let bar = crate::progress::bar(0, "path trace", global.quiet);
    let clock = Instant::now();
    let (frame, stats) = crate::render::film::render_frame(
        &camera,
        spp,
        background,
        &bar,
        |sample, stats: &mut PathStats| tracer.trace(sample, stats),
    );
    let trace_seconds = clock.elapsed().as_secs_f64();
    let write_seconds = write_frame(frame, args)?;

    if global.stats {
        let line = serde_json::json!({
            "command": "render",
            "method": "pathtrace",
            "input": args.input.display().to_string(),
            "read_seconds": read_seconds,
            "env_seconds": setup_seconds,
            "trace_seconds": trace_seconds,
            "write_seconds": write_seconds,
            "spp": spp,
            "paths": stats.paths,
            "scatterings": stats.scatterings,
            "density_lookups": stats.lookups,
            "active_voxels": density.active_voxels(),
            "peak_memory_bytes": crate::bake::peak_memory(),
        });
        println!("{line}");
    }
    Ok(())
}
