//! `vscatter render`: volume in, image out — or a sequence in, images out. Flags are checked
//! (output paths included) before any work; then each frame's scene is opened, baked if it has no
//! transfer, and rendered with the transfer or the path tracer under each map; the EXR (RGBA, and
//! with `--layers` the direct, indirect and depth layers) or PNG is written atomically with a
//! fingerprint of what made it, so a rerun of a sequence skips the images that are current.

use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use glam::Vec3;
use indicatif::{HumanBytes, ProgressBar};
use serde_json::{json, Value};

use super::args::{GlobalArgs, Method, RenderArgs, SequenceArgs};
use super::bake::{bake_stats_json, prepare_bake, warn, warn_once_per_run};
use super::progress::{names, FrameProgress};
use vscatter::io::atomic::{check_writable, remove_stale_temporaries, Inputs};
use vscatter::io::image::{read_fingerprint, write_bands, WriteOptions};
use vscatter::io::meminfo::peak_memory;
use vscatter::io::progress;
use vscatter::light::Lighting;
use vscatter::render::motion::Motion;
use vscatter::render::{band_rows, framing_bounds, Camera, CameraSpec, MarchSettings, Rows};
use vscatter::scene::{self, BakeConfig, Scene, TraceSettings};
use vscatter::sequence::Frame as SequenceFrame;
use vscatter::sequence::{self, FramePattern};
use vscatter::transfer::cache::Source;
use vscatter::transfer::memory::{self, RenderEstimate};
use vscatter::{Error, Result};

pub fn run(args: &RenderArgs, global: &GlobalArgs) -> Result<()> {
    // Every flag and every output path are checked before any work, so a typo costs nothing.
    let config = args.bake.validate()?;
    let (spp, spec) = args.validate()?;
    let light_options = args.light_options()?;
    let shot = Shot::plan(args)?;
    // What the render reads: the volumes and the maps (`sky` is none).
    let inputs = Inputs::new(
        shot.all_inputs
            .iter()
            .map(PathBuf::as_path)
            .chain(shot.envs.iter().map(Path::new)),
    );
    for output in shot.outputs.iter().flatten() {
        inputs.check(output, "-o")?;
        // A sequence's images go to a directory of their own, made as a batch makes its own.
        if let (true, Some(dir)) = (shot.sequence, output.parent()) {
            if !dir.as_os_str().is_empty() {
                std::fs::create_dir_all(dir).map_err(|e| {
                    Error::Runtime(format!("{}: cannot be made ({e})", dir.display()))
                })?;
            }
        }
        check_writable(output)?;
    }
    if shot.sequence {
        let dirs: std::collections::BTreeSet<&Path> = shot
            .outputs
            .iter()
            .flatten()
            .filter_map(|o| o.parent())
            .collect();
        for dir in dirs {
            let dir = if dir.as_os_str().is_empty() {
                Path::new(".")
            } else {
                dir
            };
            for gone in remove_stale_temporaries(dir)? {
                if !global.quiet {
                    eprintln!(
                        "removed {} (left by a process that is gone)",
                        gone.display()
                    );
                }
            }
        }
    }
    if let Some(cache) = &args.cache {
        inputs.check(cache, "--cache")?;
        check_writable(cache)?;
    }

    // The light first: its checks (the number of suns, the map file) cost less than the volume.
    // Each map is read and searched for a sun once, whatever the number of frames.
    let clock = Instant::now();
    let lightings = shot
        .envs
        .iter()
        .map(|env| Lighting::load(env, &light_options))
        .collect::<Result<Vec<Lighting>>>()?;
    let env_seconds = clock.elapsed().as_secs_f64() / lightings.len() as f64;
    for (env, lighting) in shot.envs.iter().zip(&lightings) {
        if let (Some(Ok(found)), false) = (&lighting.sun_search, global.quiet) {
            eprintln!("{env}: {found}");
        }
    }
    let job = Job {
        args,
        global,
        config: &config,
        spec,
        spp,
        lightings: &lightings,
        env_seconds,
        framing: shot.framing(&spec, &config),
        shot: &shot,
    };
    if !shot.sequence {
        // One image: its errors are the command's own.
        return job.frame(0, None).map(|_| ());
    }
    job.sequence()
}

/// What a render makes: the frames (this task's share), the environments, and an image for each
/// pair; a sequence when the input or output names frames, or several maps are given.
struct Shot {
    /// This task's frames, each with its index in the whole sequence.
    frames: Vec<(usize, SequenceFrame)>,
    /// Frames in the whole sequence (every task's).
    total: usize,
    /// Every frame's input, for framing them all alike.
    all_inputs: Vec<PathBuf>,
    missing: Vec<PathBuf>,
    envs: Vec<String>,
    /// Per frame of `frames`, per environment.
    outputs: Vec<Vec<PathBuf>>,
    sequence: bool,
    motion: Motion,
}

impl Shot {
    fn plan(args: &RenderArgs) -> Result<Shot> {
        let (range, shard) = args.sequence.validate()?;
        let resolved = sequence::resolve(std::slice::from_ref(&args.input), range)?;
        let envs: Vec<String> = args.env.split(',').map(|e| e.trim().to_string()).collect();
        let output = args.output.to_string_lossy().into_owned();
        let pattern = FramePattern::parse(&output);
        let sequence = resolved.frames.len() > 1
            || range.is_some()
            || shard.is_some()
            || pattern.is_some()
            || envs.len() > 1
            || !resolved.missing.is_empty();
        if sequence && args.cache.is_some() {
            return Err(Error::usage(
                "--cache keeps the bake of one render; `vscatter batch` bakes a sequence",
            ));
        }
        if resolved.frames.len() > 1 && pattern.is_none() {
            return Err(Error::usage(format!(
                "{output}: {} frames need a frame pattern in the output name, e.g. img.####.exr",
                resolved.frames.len()
            )));
        }
        let total = resolved.frames.len();
        let all_inputs: Vec<PathBuf> = resolved.frames.iter().map(|f| f.path.clone()).collect();
        let mut frames: Vec<(usize, SequenceFrame)> =
            resolved.frames.into_iter().enumerate().collect();
        let mut missing = resolved.missing;
        if let Some(shard) = shard {
            frames = shard.select(frames);
            missing = shard.select(missing);
        }
        let outputs = sequence::image_names(&args.output, &frames, &envs)?;
        let motion = match (args.orbit, &args.camera_path) {
            (Some(deg), _) if !deg.is_finite() => {
                return Err(Error::usage("--orbit must be a finite number of degrees"))
            }
            (Some(deg), _) => Motion::Orbit(deg),
            (None, Some(path)) => Motion::read_path(path)?,
            (None, None) => Motion::Still,
        };
        Ok(Shot {
            frames,
            total,
            all_inputs,
            missing,
            envs,
            outputs,
            sequence,
            motion,
        })
    }

    /// The box every frame's camera frames, when frames must share one (a sequence, or an orbit,
    /// without a camera position or path); `None`: each image frames its own volume.
    fn framing(&self, spec: &CameraSpec, config: &BakeConfig) -> Option<(Vec3, Vec3)> {
        let orbit = matches!(self.motion, Motion::Orbit(_));
        if spec.position.is_some() || matches!(self.motion, Motion::Path(_)) {
            return None;
        }
        if !self.sequence && !orbit {
            return None;
        }
        let union = scene::framing_union(&self.all_inputs, config.grid.as_deref());
        union.map(|b| self.motion.widen(b))
    }
}

/// Everything a render needs beside the frame.
struct Job<'a> {
    args: &'a RenderArgs,
    global: &'a GlobalArgs,
    config: &'a BakeConfig,
    spec: CameraSpec,
    spp: u32,
    lightings: &'a [Lighting],
    env_seconds: f64,
    /// The box all frames frame alike, when they do ([`Shot::framing`]).
    framing: Option<(Vec3, Vec3)>,
    shot: &'a Shot,
}

/// What became of a frame of a sequence.
enum Made {
    Rendered,
    Current,
    /// `--dry-run`: planned, nothing rendered.
    Planned,
}

impl Job<'_> {
    /// Renders every frame of this task's share: a frame whose images are all current is skipped,
    /// a frame that fails is reported and the rest go on; exit 1 at the end naming what failed.
    fn sequence(&self) -> Result<()> {
        let shot = self.shot;
        if !shot.missing.is_empty() {
            eprintln!(
                "vscatter: warning: {} frames missing: {}",
                shot.missing.len(),
                names(&shot.missing)
            );
        }
        warn_once_per_run();
        let inputs: Vec<PathBuf> = shot.frames.iter().map(|(_, f)| f.path.clone()).collect();
        let progress = FrameProgress::new(&inputs, "render", self.global.quiet);
        // A frame's own bars would fight the sequence's.
        let global = GlobalArgs {
            quiet: self.global.quiet || progress.has_bar(),
            ..self.global.clone()
        };
        let job = Job {
            global: &global,
            ..*self
        };
        let clock = Instant::now();
        let (mut rendered, mut current) = (0, 0);
        let mut failed = Vec::new();
        for (k, input) in inputs.iter().enumerate() {
            match job.frame(k, Some(&progress)) {
                Ok(Made::Rendered) => {
                    rendered += 1;
                    progress.done(k, &format!("rendered {}", names(&shot.outputs[k])), None);
                }
                Ok(Made::Current) => {
                    current += 1;
                    progress.done(k, "current", None);
                }
                Ok(Made::Planned) => progress.done(k, "planned", None),
                Err(e) => {
                    progress.done(k, "", Some(&e.to_string()));
                    failed.push(input.clone());
                }
            }
        }
        progress.finish();
        if !self.global.quiet {
            eprintln!(
                "render: {} frames × {} map(s) in {:.1} s: {rendered} rendered, {current} current, {} failed, {} missing",
                shot.frames.len() + shot.missing.len(),
                shot.envs.len(),
                clock.elapsed().as_secs_f64(),
                failed.len(),
                shot.missing.len(),
            );
        }
        let mut what = Vec::new();
        if !failed.is_empty() {
            what.push(format!("{} failed ({})", failed.len(), names(&failed)));
        }
        if !shot.missing.is_empty() {
            what.push(format!(
                "{} missing ({})",
                shot.missing.len(),
                names(&shot.missing)
            ));
        }
        match what.is_empty() {
            true => Ok(()),
            false => Err(Error::Runtime(format!(
                "sequence incomplete: of {} frames, {}",
                shot.frames.len() + shot.missing.len(),
                what.join(", ")
            ))),
        }
    }

    /// The camera of the `k`-th frame of this task's share, as moved over the sequence.
    fn camera_spec(&self, k: usize, bounds: Option<(Vec3, Vec3)>) -> Result<CameraSpec> {
        let (index, frame) = &self.shot.frames[k];
        let (lo, hi) = bounds.unwrap_or((Vec3::splat(-0.5), Vec3::splat(0.5)));
        let lookat = self.spec.lookat.unwrap_or(0.5 * (lo + hi));
        let start = CameraSpec {
            position: None,
            ..self.spec
        }
        .camera(bounds)?
        .position;
        let number = frame.number.unwrap_or(*index as i64 + 1) as f64;
        Ok(self
            .shot
            .motion
            .spec_at(&self.spec, start, lookat, number, *index, self.shot.total))
    }

    /// A fingerprint of everything that makes each of the `k`-th frame's images, one per map: the
    /// input file's identity, the map's, the flags, and the camera.
    fn fingerprints(&self, k: usize, spec: &CameraSpec) -> Vec<u64> {
        let file = |p: &Path| Source::of(p).map(|s| format!("{s:?}")).unwrap_or_default();
        let flags = RenderArgs {
            input: String::new(),
            output: PathBuf::new(),
            env: String::new(),
            sequence: SequenceArgs::default(),
            ..self.args.clone()
        };
        let frame = format!(
            "{}|{flags:?}|{spec:?}|{:?}",
            file(&self.shot.frames[k].1.path),
            self.framing
        );
        self.shot
            .envs
            .iter()
            .map(|env| {
                let env_file = match env.as_str() {
                    vscatter::light::env::SKY_SPEC => String::new(),
                    path => file(Path::new(path)),
                };
                xxhash_rust::xxh3::xxh3_64(format!("{env}|{env_file}|{frame}").as_bytes())
            })
            .collect()
    }

    /// Renders the `k`-th frame of this task's share under every map, unless (in a sequence)
    /// every one of its images is current.
    fn frame(&self, k: usize, progress: Option<&FrameProgress>) -> Result<Made> {
        let (args, global, shot) = (self.args, self.global, self.shot);
        let phase = |p: &str| {
            if let Some(progress) = progress {
                progress.phase(k, p);
            }
        };
        let input = &shot.frames[k].1.path;
        let outputs = &shot.outputs[k];
        // With a shared framing the camera is known before the volume is read.
        let known = self
            .framing
            .map(|b| self.camera_spec(k, Some(b)))
            .transpose()?;
        let known_prints = known
            .filter(|_| shot.sequence)
            .map(|spec| self.fingerprints(k, &spec));
        if let (Some(prints), false) = (&known_prints, args.sequence.force) {
            let current = outputs
                .iter()
                .zip(prints)
                .all(|(o, p)| read_fingerprint(o) == Some(*p));
            if current && !args.bake.dry_run {
                return Ok(Made::Current);
            }
        }
        phase("read");
        let mut scene = Scene::open_for(input, self.config, self.lightings)?;
        let bounds = self.framing.or_else(|| framing_bounds(&scene.field.grid));
        let spec = match known {
            Some(spec) => spec,
            None => self.camera_spec(k, bounds)?,
        };
        let camera = spec.camera(bounds)?;
        // Only a sequence skips current images; a single render always renders.
        let prints = match known_prints {
            Some(prints) => prints,
            None if shot.sequence => self.fingerprints(k, &spec),
            None => Vec::new(),
        };
        for (e, lighting) in self.lightings.iter().enumerate() {
            let mut stats = json!({
                "command": "render",
                "input": input.display().to_string(),
                "output": outputs[e].display().to_string(),
                "frame": shot.frames[k].1.number,
                "env": shot.envs[e],
                "read_seconds": scene.read_seconds,
                "field_seconds": scene.field_seconds,
                "env_seconds": self.env_seconds,
                "sun_search": lighting.sun_search.as_ref().map(|r| match r {
                    Ok(found) => found,
                    Err(none) => none,
                }),
                "active_voxels": scene.field.grid.active_voxels(),
            });
            let view = View {
                camera: &camera,
                lighting,
                background: !args.no_background,
                spp: self.spp,
                png: outputs[e]
                    .extension()
                    .is_some_and(|x| x.eq_ignore_ascii_case("png")),
                bar: progress::bar(0, "render", global.quiet),
            };
            phase(&format!(
                "render under {}",
                sequence::map_name(&shot.envs[e])
            ));
            let options = WriteOptions {
                fingerprint: prints.get(e).copied(),
                ..args.write_options()
            };
            // The image is written band by band as it is rendered; the write's time is what of
            // it is not rendering.
            let (mut rendering, mut writing) = (Duration::ZERO, Duration::ZERO);
            let write = |rows: &mut Rows| -> Result<()> {
                let clock = Instant::now();
                let written = write_bands(
                    &outputs[e],
                    &options,
                    camera.height as usize,
                    band_rows(camera.width) as usize,
                    &mut |r| {
                        let t = Instant::now();
                        let frame = rows(r.start as u32..r.end as u32, args.layers);
                        rendering += t.elapsed();
                        Ok(frame.into_image(args.layers))
                    },
                );
                writing = clock.elapsed();
                written
            };
            match args.method {
                Method::Pathtrace => pathtrace(&scene, args, &view, &mut stats, write)?,
                Method::Transfer => {
                    if transfer(
                        &mut scene,
                        args,
                        self.config,
                        &view,
                        global,
                        &mut stats,
                        write,
                    )?
                    .is_none()
                    {
                        // --dry-run: the estimate is printed, nothing is rendered.
                        return Ok(Made::Planned);
                    }
                }
            }
            view.bar.finish_and_clear();
            stats["brick_bytes"] = json!(match scene.field.has_bricks() {
                true => scene.field.brick_bytes(),
                false => 0,
            });
            stats["write_seconds"] = json!(writing.saturating_sub(rendering).as_secs_f64());
            if global.stats {
                stats["peak_memory_bytes"] = json!(peak_memory());
                println!("{stats}");
            }
        }
        Ok(Made::Rendered)
    }
}

/// What a render looks at, with what light, and how finely.
struct View<'a> {
    camera: &'a Camera,
    lighting: &'a Lighting,
    background: bool,
    spp: u32,
    /// The image is a PNG (else an EXR): what its write holds differs.
    png: bool,
    bar: ProgressBar,
}

/// `--method pathtrace`: the density (of a VDB, or of a cache with its medium) path-traced, each
/// band of rows handed to `write`.
fn pathtrace(
    scene: &Scene,
    args: &RenderArgs,
    view: &View,
    stats: &mut Value,
    write: impl FnOnce(&mut Rows) -> Result<()>,
) -> Result<()> {
    let trace = TraceSettings {
        spp: view.spp,
        max_bounces: args.max_bounces.unwrap_or(u32::MAX),
        seed: args.bake.seed,
    };
    warn(&scene.warnings(None));
    let clock = Instant::now();
    let (written, path_stats) = scene.pathtrace(
        view.camera,
        view.lighting,
        view.background,
        &trace,
        &view.bar,
        write,
    );
    stats["method"] = json!("pathtrace");
    stats["trace_seconds"] = json!(clock.elapsed().as_secs_f64());
    stats["spp"] = json!(view.spp);
    stats["paths"] = json!(path_stats.paths);
    stats["scatterings"] = json!(path_stats.scatterings);
    stats["density_lookups"] = json!(path_stats.lookups);
    written
}

/// `--method transfer`: the cache's transfer, a kept bake's, or a fresh bake (kept when asked),
/// relit and marched, each band of rows handed to `write`; `None` for a dry run.
fn transfer(
    scene: &mut Scene,
    args: &RenderArgs,
    config: &BakeConfig,
    view: &View,
    global: &GlobalArgs,
    stats: &mut Value,
    write: impl FnOnce(&mut Rows) -> Result<()>,
) -> Result<Option<()>> {
    if let Some(cache) = &args.cache {
        if scene.reuse_cache(cache, config)? && !global.quiet {
            eprintln!("using cache {}", cache.display());
        }
    }
    stats["from_cache"] = json!(scene.transfer.is_some());
    // Only an environment's soft light is held at the transfer's resolution.
    let soft_light = view.lighting.scale > 0.0;
    let warn_scale = soft_light.then_some(config.settings.scale);
    if scene.transfer.is_none() {
        let clock = Instant::now();
        let Some(bake) = prepare_bake(scene, config, args.bake.dry_run, soft_light, global)? else {
            println!("{}", sun_plan(scene, view.lighting, Some(config)));
            return Ok(None);
        };
        if let Some(cache) = &args.cache {
            scene.write_cache(cache, config)?;
        }
        stats["bake"] = bake_stats_json(&bake);
        stats["bake_seconds"] = json!(clock.elapsed().as_secs_f64());
    }
    let from_cache = stats["bake"].is_null();
    let estimate = RenderEstimate::new(
        &scene.field,
        scene.render_bricks(view.camera, view.spp, view.lighting),
        scene.relight_plan(),
        scene.transfer.as_ref().map_or(0, |t| {
            t.layout.memory_bytes() + t.coefficient_bytes() + t.shape_bytes()
        }),
        scene.sun_plan(view.lighting, None),
        scene.sun_solve_plan(view.lighting, None),
        memory::image_bytes(view.camera.width, view.camera.height, view.png),
    );
    if args.bake.dry_run {
        warn(&scene.warnings(warn_scale));
        println!("{}", sun_plan(scene, view.lighting, None));
        println!("render: {}", estimate.describe());
        return Ok(None);
    }
    estimate.check_budget(config.max_memory)?;
    // Warnings after the last refusal, so an error stays one line (a bake warned already).
    if from_cache {
        warn(&scene.warnings(warn_scale));
    }
    let settings = MarchSettings {
        spp: view.spp,
        ..MarchSettings::default()
    };
    let (written, march, report, suns) = scene.render(
        view.camera,
        view.lighting,
        view.background,
        &settings,
        &view.bar,
        write,
    )?;
    written?;
    stats["method"] = json!("transfer");
    stats["transfer_voxels"] = json!(scene.transfer.as_ref().map(|t| t.layout.len()));
    stats["env_seconds"] =
        json!(stats["env_seconds"].as_f64().unwrap_or(0.0) + report.project.as_secs_f64());
    stats["relight_seconds"] = json!(report.relight.as_secs_f64());
    stats["suns"] = json!(view.lighting.suns.len());
    stats["brick_seconds"] = json!(suns.brick_seconds);
    stats["sun_shadow_seconds"] = json!(suns.shadow_seconds);
    stats["sun_lattice_seconds"] = json!(suns.lattice_seconds);
    stats["sun_bytes"] = json!(suns.bytes);
    stats["sun_lattice_nodes"] = json!(suns.lattice_nodes);
    stats["sun_lattice_edge"] = json!(suns.lattice_edge);
    stats["sun_lattice_sweeps"] = json!(suns.lattice_sweeps);
    stats["march_seconds"] = json!(report.march.as_secs_f64());
    stats["rays"] = json!(march.rays);
    stats["samples_taken"] = json!(march.samples_taken);
    stats["samples_skipped"] = json!(march.samples_skipped);
    Ok(Some(()))
}

/// What the suns will hold, for `--dry-run`: one line; `bake`: the bake a VDB's transfer will
/// come from, whose lattice the suns' solve is then planned on, and said.
fn sun_plan(scene: &Scene, lighting: &Lighting, bake: Option<&BakeConfig>) -> String {
    let held = HumanBytes(scene.sun_plan(lighting, bake));
    let line = format!(
        "{} suns: shadow volumes and fluences about {held}",
        lighting.suns.len()
    );
    match bake.map(|b| scene.sun_solve_plan(lighting, Some(b))) {
        Some(solve) if solve > 0 => {
            format!(
                "{line}; their lattice solve about {} while it runs",
                HumanBytes(solve)
            )
        }
        _ => line,
    }
}
