//! `vscatter render`: volume in, image out. Flags are checked (output path included) before any
//! work; then the scene is opened, baked if it has no transfer, and rendered with the transfer or
//! the path tracer; the EXR (RGBA plus direct, indirect and depth layers) or PNG is written
//! atomically.

use std::time::Instant;

use glam::Vec3;
use serde_json::json;

use super::args::{GlobalArgs, Method, RenderArgs};
use super::bake::{bake_stats_json, prepare_bake, warn};
use vscatter::io::atomic::check_writable;
use vscatter::io::image::{ExrPrecision, WriteOptions};
use vscatter::io::meminfo::peak_memory;
use vscatter::io::progress;
use vscatter::light::Lighting;
use vscatter::render::{CameraSpec, Frame, MarchSettings};
use vscatter::scene::{Scene, TraceSettings};
use vscatter::{Error, Result};

/// Most samples per pixel accepted: beyond this a box filter has long converged.
const MAX_SPP: u32 = 65536;
/// Default samples per pixel of the transfer method: its march is smooth, one ray per pixel is a
/// clean image; more only antialias edges.
const DEFAULT_SPP: u32 = 1;
/// Default samples per pixel of the path tracer: enough for a recognisable preview of a cloud
/// (a few percent noise on its bright side); references take thousands.
const DEFAULT_PATHTRACE_SPP: u32 = 64;

pub fn run(args: &RenderArgs, global: &GlobalArgs) -> Result<()> {
    // Every flag and the output path are checked before any work, so a typo costs nothing.
    let config = args.bake.validate()?;
    let spp = check_flags(args)?;
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
    check_writable(&args.output)?;
    if let Some(cache) = &args.cache {
        check_writable(cache)?;
    }

    let mut scene = Scene::open(&args.input, &config)?;
    let clock = Instant::now();
    let lighting = Lighting::load(&args.env, args.env_rotate, args.env_scale, args.window)?;
    let env_seconds = clock.elapsed().as_secs_f64();
    let camera = scene.camera(&spec)?;
    let background = !args.no_background;
    let bar = progress::bar(0, "render", global.quiet);
    let mut stats = json!({
        "command": "render",
        "input": args.input.display().to_string(),
        "read_seconds": scene.read_seconds,
        "field_seconds": scene.field_seconds,
        "env_seconds": env_seconds,
        "active_voxels": scene.field.grid.active_voxels(),
        "brick_bytes": scene.field.accelerator_bytes(),
    });

    let frame = if args.method == Method::Pathtrace {
        let trace = TraceSettings {
            spp,
            max_bounces: args.max_bounces.unwrap_or(u32::MAX),
            seed: args.bake.seed,
        };
        warn(&scene.warnings(config.settings.scale));
        let clock = Instant::now();
        let (frame, path_stats) = scene.pathtrace(&camera, &lighting, background, &trace, &bar);
        stats["method"] = json!("pathtrace");
        stats["trace_seconds"] = json!(clock.elapsed().as_secs_f64());
        stats["spp"] = json!(spp);
        stats["paths"] = json!(path_stats.paths);
        stats["scatterings"] = json!(path_stats.scatterings);
        stats["density_lookups"] = json!(path_stats.lookups);
        frame
    } else {
        if let Some(cache) = &args.cache {
            if scene.reuse_cache(cache, &config)? && !global.quiet {
                eprintln!("using cache {}", cache.display());
            }
        }
        stats["from_cache"] = json!(scene.transfer.is_some());
        if scene.transfer.is_none() {
            let clock = Instant::now();
            // --dry-run: the estimate is printed, nothing is rendered.
            let Some(bake) = prepare_bake(&mut scene, &config, args.bake.dry_run, global)? else {
                return Ok(());
            };
            if let Some(cache) = &args.cache {
                scene.write_cache(cache, &config)?;
            }
            stats["bake"] = bake_stats_json(&bake);
            stats["bake_seconds"] = json!(clock.elapsed().as_secs_f64());
        } else {
            warn(&scene.warnings(config.settings.scale));
        }
        let settings = MarchSettings {
            spp,
            ..MarchSettings::default()
        };
        let (frame, march, report) =
            scene.render(&camera, &lighting, background, &settings, &bar)?;
        stats["method"] = json!("transfer");
        stats["transfer_voxels"] = json!(scene.transfer.as_ref().map(|t| t.layout.len()));
        stats["env_seconds"] = json!(env_seconds + report.project.as_secs_f64());
        stats["relight_seconds"] = json!(report.relight.as_secs_f64());
        stats["march_seconds"] = json!(report.march.as_secs_f64());
        stats["rays"] = json!(march.rays);
        stats["samples_taken"] = json!(march.samples_taken);
        stats["samples_skipped"] = json!(march.samples_skipped);
        frame
    };
    bar.finish_and_clear();
    stats["write_seconds"] = json!(write_frame(frame, args)?);
    if global.stats {
        stats["peak_memory_bytes"] = json!(peak_memory());
        println!("{stats}");
    }
    Ok(())
}

/// Checks the flags that depend on each other or on the method; returns the samples per pixel.
fn check_flags(args: &RenderArgs) -> Result<u32> {
    let ext = args
        .output
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    if !matches!(ext.as_deref(), Some("exr" | "png")) {
        return Err(Error::usage(format!(
            "{}: output must end in .exr or .png",
            args.output.display()
        )));
    }
    let spp = args.spp.unwrap_or(match args.method {
        Method::Transfer => DEFAULT_SPP,
        Method::Pathtrace => DEFAULT_PATHTRACE_SPP,
    });
    if !(1..=MAX_SPP).contains(&spp) {
        return Err(Error::usage(format!(
            "--spp {spp}: must lie in 1..={MAX_SPP}"
        )));
    }
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
    // Flags that mean nothing to the chosen method are refused, naming the one that does the job.
    let refusal = match args.method {
        Method::Transfer if args.max_bounces.is_some() => Some(
            "--max-bounces applies to --method pathtrace; the transfer's single scattering is --single-scatter",
        ),
        Method::Pathtrace if args.bake.single_scatter => Some(
            "--single-scatter applies to the transfer; the path tracer's single scattering is --max-bounces 1",
        ),
        Method::Pathtrace if args.cache.is_some() => {
            Some("--cache keeps a bake, and --method pathtrace bakes nothing")
        }
        Method::Pathtrace if args.max_bounces == Some(0) => {
            Some("--max-bounces 0: must be at least 1 (1 = single scattering)")
        }
        _ => None,
    };
    refusal.map_or(Ok(spp), |r| Err(Error::usage(r)))
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
