//! The command line: clap-derived raw flags, and their conversion into validated settings.
//! Commands never see a raw flag that has not been checked here.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

use glam::Vec3;
use vscatter::error::{Error, Result};
use vscatter::io::image::{ExrPrecision, WriteOptions};
use vscatter::light::sun::Sun;
use vscatter::light::LightOptions;
use vscatter::render::CameraSpec;
use vscatter::scene::BakeConfig;
use vscatter::sequence::{FrameRange, Shard};
use vscatter::transfer::memory::MAX_SCALE;
use vscatter::transfer::packing::Precision;
use vscatter::transfer::{lattice::LatticeKind, BakeSettings, Medium};

/// Multiple-scattering relighting of OpenVDB fog volumes.
#[derive(Debug, Parser)]
#[command(name = "vscatter", version, about, propagate_version = true)]
pub struct Cli {
    #[command(flatten)]
    pub global: GlobalArgs,
    #[command(subcommand)]
    pub command: Command,
}

/// Flags every command takes.
#[derive(Debug, Clone, Args)]
pub struct GlobalArgs {
    /// Worker threads (default: the CPUs a farm job was given — SLURM_CPUS_PER_TASK, CUE_THREADS,
    /// NSLOTS, PBS_NUM_PPN or LSB_DJOB_NUMPROC — else every core this process may use).
    #[arg(long, global = true, value_name = "N")]
    pub threads: Option<usize>,
    /// No progress bars.
    #[arg(long, global = true)]
    pub quiet: bool,
    /// Print a JSON line of timings and counts when done.
    #[arg(long, global = true)]
    pub stats: bool,
}

#[derive(Debug, Subcommand)]
pub enum Command {
    /// Describe a VDB file: grids, types, transforms, bounding boxes, active voxels, tiles, memory.
    Info(InfoArgs),
    /// Project an environment map onto SH and write its reconstruction (thesis fig. 6.4).
    Env(EnvArgs),
    /// Bake a VDB density into a transfer cache (.vtc): single and multiple scattering.
    Bake(BakeCmd),
    /// Bake many VDB frames (files, globs, cloud.####.vdb) into caches, skipping current ones.
    Batch(BatchArgs),
    /// Render a volume lit by an environment, with multiple scattering (.exr or .png); or a
    /// sequence of them.
    Render(Box<RenderArgs>),
    /// Measure a render against a reference (e.g. the path tracer): relative RMSE over the volume.
    Compare(CompareArgs),
}

/// Default extinction per world unit per unit density (docs/model.md).
pub const DEFAULT_SIGMA_T: f32 = 1.0;
/// Default single-scattering albedo: clouds are near 1, 0.9 keeps bakes quick and the look soft.
pub const DEFAULT_ALBEDO: f32 = 0.9;
/// Default transfer resolution divisor: the thesis' 1/6 of the density resolution.
pub const DEFAULT_SCALE: i32 = 6;
/// Default T_ri directions per transfer voxel: the thesis found ≥ 500 needed (fig. 6.3).
pub const DEFAULT_SAMPLES: usize = 512;
/// Fewer directions than this cannot resolve even a few SH bands.
const MIN_SAMPLES: usize = 16;
/// More directions than this only cost time: the projection error is far below the SH truncation.
const MAX_SAMPLES: usize = 65536;

/// `vscatter bake IN.vdb -o OUT.vtc`.
#[derive(Debug, Args)]
pub struct BakeCmd {
    /// The VDB file to bake.
    pub input: PathBuf,
    /// The cache to write (.vtc).
    #[arg(short, long, value_name = "OUT")]
    pub output: PathBuf,
    #[command(flatten)]
    pub bake: BakeArgs,
}

/// `vscatter batch INPUT… --out-dir DIR`.
#[derive(Debug, Args)]
pub struct BatchArgs {
    /// VDB files, globs (`'v/*.vdb'`) or frame patterns (`cloud.####.vdb`, `cloud.%04d.vdb`,
    /// `cloud.$F4.vdb`; quote them from the shell).
    #[arg(required = true, value_name = "INPUT")]
    pub inputs: Vec<String>,
    /// Where the caches go, named after their inputs (`cloud.1001.vdb` → `DIR/cloud.1001.vtc`).
    #[arg(long, value_name = "DIR")]
    pub out_dir: PathBuf,
    #[command(flatten)]
    pub sequence: SequenceArgs,
    #[command(flatten)]
    pub bake: BakeArgs,
}

/// Which frames of a sequence to do, and whether current outputs are done again: shared by
/// `batch` and sequence renders.
#[derive(Debug, Clone, Default, Args)]
pub struct SequenceArgs {
    /// The frames of a pattern: FIRST-LAST[:STEP] (default: every file that matches).
    #[arg(long, value_name = "FIRST-LAST[:STEP]", allow_hyphen_values = true)]
    pub frames: Option<String>,
    /// Take task K's share of N (1 ≤ K ≤ N): N farm tasks cover every frame exactly once.
    #[arg(long, value_name = "K/N")]
    pub shard: Option<String>,
    /// Do every frame, even where its output (a cache, an image) is current.
    #[arg(long)]
    pub force: bool,
}

impl SequenceArgs {
    /// `--frames` and `--shard`, checked.
    pub fn validate(&self) -> Result<(Option<FrameRange>, Option<Shard>)> {
        let range = self.frames.as_deref().map(FrameRange::parse).transpose()?;
        let shard = self.shard.as_deref().map(Shard::parse).transpose()?;
        Ok((range, shard))
    }
}

/// The bake flags, shared by every command that bakes.
#[derive(Debug, Clone, Args)]
pub struct BakeArgs {
    /// The grid to read (default: `density`, else the first scalar grid).
    #[arg(long, value_name = "NAME")]
    pub grid: Option<String>,
    /// Extinction per world unit at density 1.
    #[arg(long, value_name = "F", default_value_t = DEFAULT_SIGMA_T, allow_negative_numbers = true)]
    pub sigma_t: f32,
    /// Single-scattering albedo σs/σt, 0 to 1.
    #[arg(long, value_name = "F", default_value_t = DEFAULT_ALBEDO, allow_negative_numbers = true)]
    pub albedo: f32,
    /// SH bands (bands² coefficients per transfer voxel), 1 to 20.
    #[arg(long, value_name = "N", default_value_t = vscatter::light::sh::DEFAULT_BANDS)]
    pub bands: usize,
    /// Density voxels per transfer voxel along each axis (K).
    #[arg(long, value_name = "K", default_value_t = DEFAULT_SCALE)]
    pub scale: i32,
    /// Directions marched per transfer voxel for single scattering.
    #[arg(long, value_name = "N", default_value_t = DEFAULT_SAMPLES)]
    pub samples: usize,
    /// Lattice directions for multiple scattering.
    #[arg(long, value_enum, default_value_t = LatticeKind::All)]
    pub lattice: LatticeKind,
    /// Skip multiple scattering (T_ri only; thesis fig. 6.1).
    #[arg(long)]
    pub single_scatter: bool,
    /// Fit the direct light to the density around each node at any albedo (from 0.8 up a bake
    /// keeps the nodes' point values): the EXR's direct and indirect layers come closer to the
    /// path tracer's apart, for about twice the bake's single-scattering time.
    #[arg(long)]
    pub fit_direct: bool,
    /// Seed of the direction-set rotations (and of path tracing).
    #[arg(long, value_name = "N", default_value_t = 0)]
    pub seed: u64,
    /// How a bake holds and its cache stores the transfer: q8 (8 bits per coefficient, scaled
    /// per band; images within 0.1 %) at a third of f32's size; f16 (the density too) at half;
    /// f32 exactly (docs/cache-format.md).
    #[arg(long, value_enum, value_name = "P", default_value_t = Precision::default())]
    pub cache_precision: Precision,
    /// Same as `--cache-precision f16`.
    #[arg(long, conflicts_with = "cache_precision")]
    pub cache_half: bool,
    /// Print the memory estimate and stop.
    #[arg(long)]
    pub dry_run: bool,
    /// Refuse bakes estimated to need more (e.g. 8G; default 80 % of the available memory or of
    /// the job's cgroup limit, whichever is smaller; for `batch`, of all frames in flight).
    #[arg(long, value_name = "SIZE")]
    pub max_memory: Option<String>,
}

impl BakeArgs {
    /// The bake flags as a validated configuration (`--dry-run` stays a flag of the command).
    pub fn validate(&self) -> Result<BakeConfig> {
        vscatter::light::sh::check_bands(self.bands)?;
        if !(self.sigma_t.is_finite() && self.sigma_t > 0.0) {
            return Err(Error::usage("--sigma-t must be a positive number"));
        }
        if !(0.0..=1.0).contains(&self.albedo) {
            return Err(Error::usage("--albedo must be between 0 and 1"));
        }
        if !(1..=MAX_SCALE).contains(&self.scale) {
            return Err(Error::usage(format!("--scale must be 1 to {MAX_SCALE}")));
        }
        if !(MIN_SAMPLES..=MAX_SAMPLES).contains(&self.samples) {
            return Err(Error::usage(format!(
                "--samples must be {MIN_SAMPLES} to {MAX_SAMPLES}"
            )));
        }
        let max_memory = match &self.max_memory {
            Some(s) => Some(
                parse_size::parse_size(s)
                    .map_err(|e| Error::usage(format!("--max-memory {s:?}: {e}")))?,
            ),
            None => None,
        };
        Ok(BakeConfig {
            grid: self.grid.clone(),
            medium: Medium {
                sigma_t: self.sigma_t,
                albedo: self.albedo,
            },
            settings: BakeSettings {
                bands: self.bands,
                scale: self.scale,
                samples: self.samples,
                lattice: self.lattice,
                single_scatter: self.single_scatter,
                fit_direct: self.fit_direct,
                seed: self.seed,
            },
            precision: match self.cache_half {
                true => Precision::F16,
                false => self.cache_precision,
            },
            max_memory,
        })
    }
}

#[derive(Debug, Args)]
pub struct InfoArgs {
    /// The file to describe: a VDB file or a .vtc transfer cache.
    pub file: PathBuf,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
    /// Describe only this grid, as the density that `render` would read (it must be scalar).
    #[arg(long, value_name = "NAME")]
    pub grid: Option<String>,
}

/// `vscatter env ENV -o RECON.(exr|png)`.
#[derive(Debug, Args)]
pub struct EnvArgs {
    /// Latlong environment: an OpenEXR or Radiance .hdr file, or `sky` for the built-in sky.
    #[arg(value_name = "ENV")]
    pub env: String,
    /// Where to write the reconstruction, the same size as the input (.exr linear, .png tonemapped).
    #[arg(short, long, value_name = "RECON")]
    pub output: PathBuf,
    /// SH bands (bands² coefficients), 1 to 20.
    #[arg(long, value_name = "N", default_value_t = vscatter::light::sh::DEFAULT_BANDS)]
    pub bands: usize,
    /// Windowing of the coefficients against ringing (thesis eq. 6.1).
    #[arg(long, value_enum, default_value_t = vscatter::light::sh::Window::None)]
    pub window: vscatter::light::sh::Window,
    #[command(flatten)]
    pub png: PngArgs,
    /// Also write the input map itself (after clamping bad pixels), for side-by-side figures.
    #[arg(long, value_name = "PATH")]
    pub original: Option<PathBuf>,
}

/// Flags of PNG output, shared by every command that writes images.
#[derive(Debug, Clone, Args)]
pub struct PngArgs {
    /// Exposure in stops for PNG output.
    #[arg(
        long,
        value_name = "EV",
        default_value_t = 0.0,
        allow_negative_numbers = true
    )]
    pub exposure: f32,
}

/// Where farm schedulers say how many CPUs a job was given: Slurm, OpenCue, Grid Engine, PBS, LSF.
const FARM_CPU_VARIABLES: [&str; 5] = [
    "SLURM_CPUS_PER_TASK",
    "CUE_THREADS",
    "NSLOTS",
    "PBS_NUM_PPN",
    "LSB_DJOB_NUMPROC",
];

impl GlobalArgs {
    /// The worker thread count: `--threads`, else a farm job's CPUs, else every core.
    pub fn thread_count(&self) -> Result<usize> {
        if let Some(n) = self.threads {
            if n == 0 {
                return Err(Error::usage("--threads must be at least 1"));
            }
            return Ok(n);
        }
        let farm = FARM_CPU_VARIABLES.iter().find_map(|v| {
            let n = std::env::var(v).ok()?.trim().parse::<usize>().ok()?;
            (n > 0).then_some(n)
        });
        // available_parallelism honours the affinity mask and a cgroup's CPU quota.
        Ok(farm.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get())))
    }
}

/// `vscatter render IN -o OUT.(exr|png)`.
#[derive(Debug, Clone, Args)]
pub struct RenderArgs {
    /// The volume: a VDB (its transfer is baked first, with the bake options) or a .vtc cache;
    /// or a sequence of them, as a frame pattern (`cache.####.vtc`) or a glob.
    #[arg(value_name = "IN")]
    pub input: String,
    /// The image to write: .exr (linear RGBA; `--layers` adds direct, indirect and depth) or
    /// .png; for a sequence, a frame pattern (`img.####.exr`).
    #[arg(short, long, value_name = "OUT")]
    pub output: PathBuf,
    /// Latlong environment (.exr or .hdr), or `sky` for the built-in sky; several, separated by
    /// commas, render an image under each (`img.ENVNAME.####.exr`).
    #[arg(long, value_name = "ENV", default_value = vscatter::light::env::SKY_SPEC)]
    pub env: String,
    #[command(flatten)]
    pub sequence: SequenceArgs,
    /// Orbit the camera this many degrees about the volume's centre over the sequence.
    #[arg(
        long,
        value_name = "DEG",
        allow_negative_numbers = true,
        conflicts_with = "camera_path"
    )]
    pub orbit: Option<f32>,
    /// A camera path: lines of `FRAME PX PY PZ LX LY LZ FOV`, interpolated linearly.
    #[arg(long, value_name = "FILE")]
    pub camera_path: Option<PathBuf>,
    /// Multiplies the environment's radiance.
    #[arg(
        long,
        value_name = "F",
        default_value_t = 1.0,
        allow_negative_numbers = true
    )]
    pub env_scale: f32,
    /// Turns the environment about +Y, degrees.
    #[arg(
        long,
        value_name = "DEG",
        default_value_t = 0.0,
        allow_negative_numbers = true
    )]
    pub env_rotate: f64,
    /// Windowing of the environment's SH coefficients against ringing (thesis eq. 6.1).
    #[arg(long, value_enum, default_value_t = vscatter::light::sh::Window::None)]
    pub window: vscatter::light::sh::Window,
    /// A sun: the direction it shines from, its RGB irradiance on a facing surface [default: the
    /// built-in sky's sun, ≈ 7] and its angular radius in degrees [default: 0]. Repeatable; with
    /// `--env sky` it replaces the sky's own sun.
    #[arg(long, value_name = "X,Y,Z[,R,G,B[,DEG]]", allow_hyphen_values = true)]
    pub sun: Vec<String>,
    /// A sun as `vdb_render -light` reads it: direction toward the light and a colour C that
    /// scatters C·albedo (irradiance 4π·C) [default colour: 0.7]. Repeatable.
    #[arg(long, value_name = "X,Y,Z[,R,G,B]", allow_hyphen_values = true)]
    pub light: Vec<String>,
    /// Leave the sun of an HDRI (or of the built-in sky) as pixels of the map, lit through the SH
    /// transfer alone, instead of a light with exact shadows.
    #[arg(long, overrides_with = "extract_sun")]
    pub no_extract_sun: bool,
    /// Take a sun out of an HDRI and light it as a sun with exact shadows (the default).
    #[arg(long, overrides_with = "no_extract_sun")]
    pub extract_sun: bool,
    /// Image size.
    #[arg(long, value_name = "WxH", default_value = "1280x720", value_parser = parse_resolution)]
    pub res: (u32, u32),
    /// Camera position (default: framing the volume from +Z).
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3, allow_hyphen_values = true)]
    pub camera_pos: Option<[f32; 3]>,
    /// Point the camera looks at (default: the centre of the volume); without --camera-pos the
    /// framing camera turns toward it.
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3, allow_hyphen_values = true)]
    pub lookat: Option<[f32; 3]>,
    /// The camera's up direction (with or without --camera-pos).
    #[arg(long, value_name = "X,Y,Z", value_parser = parse_vec3, allow_hyphen_values = true,
          default_value = "0,1,0")]
    pub up: [f32; 3],
    /// Horizontal field of view, degrees.
    #[arg(long, value_name = "DEG", default_value_t = 45.0)]
    pub fov: f32,
    /// Samples per pixel (box filter) [default: 1 for transfer, 64 for pathtrace].
    #[arg(long, value_name = "N")]
    pub spp: Option<u32>,
    /// How to compute the light: the baked transfer (fast, approximate) or a reference path tracer
    /// (unbiased, slow: the ground truth the transfer is measured against).
    #[arg(long, value_enum, default_value_t = Method::Transfer)]
    pub method: Method,
    /// Path tracer only: most scattering events per path (1 = single scattering) [default: no limit].
    #[arg(long, value_name = "N")]
    pub max_bounces: Option<u32>,
    #[command(flatten)]
    pub png: PngArgs,
    /// No environment behind the volume: transparent where it is thin (premultiplied alpha).
    #[arg(long)]
    pub no_background: bool,
    /// Write EXR as half floats.
    #[arg(long)]
    pub exr_half: bool,
    /// Add the EXR layers `direct.{R,G,B}`, `indirect.{R,G,B}` (single and multiple scattering)
    /// and `depth.Z` to the RGBA.
    #[arg(long)]
    pub layers: bool,
    /// Keep the bake of a .vdb input in this .vtc cache, and reuse it while the source file and
    /// the bake options are unchanged.
    #[arg(long, value_name = "PATH")]
    pub cache: Option<PathBuf>,
    #[command(flatten)]
    pub bake: BakeArgs,
}

/// Most samples per pixel accepted: beyond this a box filter has long converged.
const MAX_SPP: u32 = 65536;
/// Default samples per pixel of the transfer method: its march is smooth, one ray per pixel is a
/// clean image; more only antialias edges.
const DEFAULT_SPP: u32 = 1;
/// Default samples per pixel of the path tracer: enough for a recognisable preview of a cloud
/// (a few percent noise on its bright side); references take thousands.
const DEFAULT_PATHTRACE_SPP: u32 = 64;

impl RenderArgs {
    /// The light besides the map: rotation, scale, window and the suns of `--sun` and `--light`.
    pub fn light_options(&self) -> Result<LightOptions> {
        let default_irradiance = vscatter::light::env::sky_sun().irradiance;
        let suns = self
            .sun
            .iter()
            .map(|s| Sun::parse(s, default_irradiance))
            .chain(self.light.iter().map(|s| Sun::parse_vdb_render(s)))
            .collect::<Result<Vec<Sun>>>()?;
        Ok(LightOptions {
            rotation_deg: self.env_rotate,
            scale: self.env_scale,
            window: self.window,
            suns,
            extract_sun: !self.no_extract_sun,
        })
    }

    /// How the image is written: PNG exposure, EXR precision.
    pub fn write_options(&self) -> WriteOptions {
        WriteOptions {
            fingerprint: None,
            exposure: self.png.exposure,
            precision: match self.exr_half {
                true => ExrPrecision::Half,
                false => ExrPrecision::Float,
            },
        }
    }

    /// Checks the flags that depend on each other or on the method (the bake flags are checked
    /// by [`BakeArgs::validate`]); returns the samples per pixel and the camera.
    pub fn validate(&self) -> Result<(u32, CameraSpec)> {
        let args = self;
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
        if ext.as_deref() == Some("png") && (args.layers || args.exr_half) {
            return Err(Error::usage(format!(
                "{}: --layers and --exr-half apply to an .exr output",
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
        Method::Pathtrace if args.bake.fit_direct => {
            Some("--fit-direct applies to the transfer's bake, and --method pathtrace bakes nothing")
        }
        Method::Pathtrace if args.cache.is_some() => {
            Some("--cache keeps a bake, and --method pathtrace bakes nothing")
        }
        Method::Pathtrace if args.max_bounces == Some(0) => {
            Some("--max-bounces 0: must be at least 1 (1 = single scattering)")
        }
        _ => None,
    };
        if let Some(r) = refusal {
            return Err(Error::usage(r));
        }
        let spec = CameraSpec {
            position: args.camera_pos.map(Vec3::from),
            lookat: args.lookat.map(Vec3::from),
            up: Vec3::from(args.up),
            fov_deg: args.fov,
            width: args.res.0,
            height: args.res.1,
        };
        // Resolution, fov and pose: a framing camera of a unit box.
        spec.camera(None)?;
        Ok((spp, spec))
    }
}

/// `vscatter compare IMAGE.exr REFERENCE.exr`.
#[derive(Debug, Args)]
pub struct CompareArgs {
    /// The render to measure (.exr, rendered with --no-background).
    pub image: PathBuf,
    /// The reference (.exr, same size and camera), e.g. `render --method pathtrace`.
    pub reference: PathBuf,
    /// A second reference rendered with another --seed: its noise is then estimated and
    /// subtracted, and the two are averaged.
    #[arg(long, value_name = "EXR")]
    pub reference2: Option<PathBuf>,
    /// Write a false-colour difference image (.png): red brighter, blue darker than the reference,
    /// full colour at ±25 %.
    #[arg(long, value_name = "PNG")]
    pub diff: Option<PathBuf>,
    /// Print JSON instead of text.
    #[arg(long)]
    pub json: bool,
}

/// `render --method`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Method {
    /// Relight the baked SH transfer and ray-march it.
    Transfer,
    /// Monte Carlo volumetric path tracing of the same model.
    Pathtrace,
}

/// `WxH`, both at least 1 (the camera bounds the area).
fn parse_resolution(s: &str) -> std::result::Result<(u32, u32), String> {
    let bad = || format!("{s:?}: expected WIDTHxHEIGHT, e.g. 1280x720");
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(bad)?;
    let w: u32 = w.trim().parse().map_err(|_| bad())?;
    let h: u32 = h.trim().parse().map_err(|_| bad())?;
    if w == 0 || h == 0 {
        return Err(format!("{s:?}: both sides must be at least 1"));
    }
    Ok((w, h))
}

/// `X,Y,Z`, three finite numbers.
fn parse_vec3(s: &str) -> std::result::Result<[f32; 3], String> {
    let parts: Vec<&str> = s.split(',').collect();
    let bad = || format!("{s:?}: expected three numbers X,Y,Z");
    if parts.len() != 3 {
        return Err(bad());
    }
    let mut v = [0.0f32; 3];
    for (o, p) in v.iter_mut().zip(&parts) {
        *o = p.trim().parse().map_err(|_| bad())?;
        if !o.is_finite() {
            return Err(bad());
        }
    }
    Ok(v)
}
