//! `vscatter render`: volume in, image out. Flags are checked (output path included) before any
//! work; then the scene is opened, baked if it has no transfer, and rendered with the transfer or
//! the path tracer; the EXR (RGBA plus direct, indirect and depth layers) or PNG is written
//! atomically.

use std::time::Instant;

use indicatif::{HumanBytes, ProgressBar};
use serde_json::{json, Value};

use super::args::{GlobalArgs, Method, RenderArgs};
use super::bake::{bake_stats_json, prepare_bake, warn};
use vscatter::io::atomic::check_writable;
use vscatter::io::meminfo::peak_memory;
use vscatter::io::progress;
use vscatter::light::Lighting;
use vscatter::render::{Camera, Frame, MarchSettings};
use vscatter::scene::{BakeConfig, Scene, TraceSettings};
use vscatter::transfer::memory::check_sun_budget;
use vscatter::Result;

pub fn run(args: &RenderArgs, global: &GlobalArgs) -> Result<()> {
    // Every flag and the output path are checked before any work, so a typo costs nothing.
    let config = args.bake.validate()?;
    let (spp, spec) = args.validate()?;
    let light_options = args.light_options()?;
    check_writable(&args.output)?;
    if let Some(cache) = &args.cache {
        check_writable(cache)?;
    }

    // The light first: its checks (the number of suns, the map file) cost less than the volume.
    let clock = Instant::now();
    let lighting = Lighting::load(&args.env, &light_options)?;
    let env_seconds = clock.elapsed().as_secs_f64();
    let mut scene = Scene::open(&args.input, &config)?;
    if let Some(Ok(found)) = &lighting.sun_search {
        if !global.quiet {
            eprintln!("{}: {found}", args.env);
        }
    }
    let camera = scene.camera(&spec)?;
    let mut stats = json!({
        "command": "render",
        "input": args.input.display().to_string(),
        "read_seconds": scene.read_seconds,
        "field_seconds": scene.field_seconds,
        "env_seconds": env_seconds,
        "sun_search": lighting.sun_search.as_ref().map(|r| match r {
            Ok(found) => found,
            Err(none) => none,
        }),
        "active_voxels": scene.field.grid.active_voxels(),
        "brick_bytes": scene.field.accelerator_bytes(),
    });
    let view = View {
        camera: &camera,
        lighting: &lighting,
        background: !args.no_background,
        spp,
        bar: progress::bar(0, "render", global.quiet),
    };
    let frame = match args.method {
        Method::Pathtrace => pathtrace(&scene, args, &view, &mut stats),
        Method::Transfer => match transfer(&mut scene, args, &config, &view, global, &mut stats)? {
            Some(frame) => frame,
            // --dry-run: the estimate is printed, nothing is rendered.
            None => return Ok(()),
        },
    };
    view.bar.finish_and_clear();
    let clock = Instant::now();
    frame
        .into_image()
        .write(&args.output, &args.write_options())?;
    stats["write_seconds"] = json!(clock.elapsed().as_secs_f64());
    if global.stats {
        stats["peak_memory_bytes"] = json!(peak_memory());
        println!("{stats}");
    }
    Ok(())
}

/// What a render looks at, with what light, and how finely.
struct View<'a> {
    camera: &'a Camera,
    lighting: &'a Lighting,
    background: bool,
    spp: u32,
    bar: ProgressBar,
}

/// `--method pathtrace`: the density (of a VDB, or of a cache with its medium) path-traced.
fn pathtrace(scene: &Scene, args: &RenderArgs, view: &View, stats: &mut Value) -> Frame {
    let trace = TraceSettings {
        spp: view.spp,
        max_bounces: args.max_bounces.unwrap_or(u32::MAX),
        seed: args.bake.seed,
    };
    warn(&scene.warnings(None));
    let clock = Instant::now();
    let (frame, path_stats) = scene.pathtrace(
        view.camera,
        view.lighting,
        view.background,
        &trace,
        &view.bar,
    );
    stats["method"] = json!("pathtrace");
    stats["trace_seconds"] = json!(clock.elapsed().as_secs_f64());
    stats["spp"] = json!(view.spp);
    stats["paths"] = json!(path_stats.paths);
    stats["scatterings"] = json!(path_stats.scatterings);
    stats["density_lookups"] = json!(path_stats.lookups);
    frame
}

/// `--method transfer`: the cache's transfer, a kept bake's, or a fresh bake (kept when asked),
/// relit and marched; `None` for a dry run.
fn transfer(
    scene: &mut Scene,
    args: &RenderArgs,
    config: &BakeConfig,
    view: &View,
    global: &GlobalArgs,
    stats: &mut Value,
) -> Result<Option<Frame>> {
    if let Some(cache) = &args.cache {
        if scene.reuse_cache(cache, config)? && !global.quiet {
            eprintln!("using cache {}", cache.display());
        }
    }
    stats["from_cache"] = json!(scene.transfer.is_some());
    if scene.transfer.is_none() {
        let clock = Instant::now();
        let Some(bake) = prepare_bake(scene, config, args.bake.dry_run, global)? else {
            println!("{}", sun_plan(scene, view.lighting));
            return Ok(None);
        };
        if let Some(cache) = &args.cache {
            scene.write_cache(cache, config)?;
        }
        stats["bake"] = bake_stats_json(&bake);
        stats["bake_seconds"] = json!(clock.elapsed().as_secs_f64());
    }
    let from_cache = stats["bake"].is_null();
    if args.bake.dry_run {
        warn(&scene.warnings(Some(config.settings.scale)));
        println!("{}", sun_plan(scene, view.lighting));
        return Ok(None);
    }
    let sun_bytes = scene.sun_plan(view.lighting);
    let held = scene.field.grid.memory_bytes() as u64
        + scene.field.accelerator_bytes() as u64
        + scene
            .transfer
            .as_ref()
            .map_or(0, |t| (t.t_ri.len() + t.f_ms.len()) as u64 * 4);
    check_sun_budget(sun_bytes, held, config.max_memory)?;
    // Warnings after the last refusal, so an error stays one line (a bake warned already).
    if from_cache {
        warn(&scene.warnings(Some(config.settings.scale)));
    }
    let settings = MarchSettings {
        spp: view.spp,
        ..MarchSettings::default()
    };
    let (frame, march, report, suns) = scene.render(
        view.camera,
        view.lighting,
        view.background,
        &settings,
        &view.bar,
    )?;
    stats["method"] = json!("transfer");
    stats["transfer_voxels"] = json!(scene.transfer.as_ref().map(|t| t.layout.len()));
    stats["env_seconds"] =
        json!(stats["env_seconds"].as_f64().unwrap_or(0.0) + report.project.as_secs_f64());
    stats["relight_seconds"] = json!(report.relight.as_secs_f64());
    stats["suns"] = json!(view.lighting.suns.len());
    stats["sun_shadow_seconds"] = json!(suns.shadow_seconds);
    stats["sun_lattice_seconds"] = json!(suns.lattice_seconds);
    stats["sun_bytes"] = json!(suns.bytes);
    stats["march_seconds"] = json!(report.march.as_secs_f64());
    stats["rays"] = json!(march.rays);
    stats["samples_taken"] = json!(march.samples_taken);
    stats["samples_skipped"] = json!(march.samples_skipped);
    Ok(Some(frame))
}

/// What the suns will hold, for `--dry-run`: one line.
fn sun_plan(scene: &Scene, lighting: &Lighting) -> String {
    format!(
        "{} suns: shadow volumes and fluences about {}",
        lighting.suns.len(),
        HumanBytes(scene.sun_plan(lighting))
    )
}
