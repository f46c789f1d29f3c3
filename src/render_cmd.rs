//! `vscatter render`: volume in, image out. Reads a `.vtc` cache (density and transfer) or a VDB
//! whose transfer it bakes first, projects the environment onto SH, relights, marches, and writes
//! the EXR (RGBA plus direct, indirect and depth layers) or PNG atomically.

use std::path::Path;
use std::time::Instant;

use glam::Vec3;

use crate::cli::{GlobalArgs, RenderArgs};
use crate::env::Environment;
use crate::error::{Error, Result};
use crate::image::{ExrPrecision, WriteOptions};
use crate::render::{render_volume, world_bounds, CameraSpec, MarchSettings};
use crate::volume::load_density;

/// Most samples per pixel accepted: beyond this a box filter has long converged.
const MAX_SPP: u32 = 65536;

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
    if !(1..=MAX_SPP).contains(&args.spp) {
        return Err(Error::usage(format!(
            "--spp {}: must lie in 1..={MAX_SPP}",
            args.spp
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
    let background: Option<crate::render::Background> = if args.no_background {
        None
    } else {
        Some(&lookup)
    };
    let settings = MarchSettings {
        spp: args.spp,
        ..MarchSettings::default()
    };
    let bar = crate::progress::bar(0, "render", global.quiet);
    let (frame, march_stats, report) = render_volume(
        &density, &transfer, &coeffs, background, &camera, &settings, &bar,
    );

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
    let write_seconds = clock.elapsed().as_secs_f64();

    if global.stats {
        let line = serde_json::json!({
            "command": "render",
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
/// `None` means bake afresh (and overwrite it). A damaged cache is an error, not silently redone.
fn reusable(
    path: &std::path::Path,
    source: &crate::transfer::cache::Source,
    config: &crate::cli::BakeConfig,
) -> Result<Option<crate::transfer::cache::Cache>> {
    if !path.exists() {
        return Ok(None);
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
