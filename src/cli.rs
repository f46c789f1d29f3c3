//! The command line: clap-derived raw flags, and their conversion into validated settings.
//! Commands never see a raw flag that has not been checked here.

use std::path::PathBuf;

use clap::{Args, Parser, Subcommand};

use crate::error::{Error, Result};

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
#[derive(Debug, Args)]
pub struct GlobalArgs {
    /// Worker threads (default: all cores, or SLURM_CPUS_PER_TASK when set).
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
}

#[derive(Debug, Args)]
pub struct InfoArgs {
    /// The file to describe (.vdb).
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
    #[arg(long, value_name = "N", default_value_t = crate::sh::DEFAULT_BANDS)]
    pub bands: usize,
    /// Windowing of the coefficients against ringing (thesis eq. 6.1).
    #[arg(long, value_enum, default_value_t = crate::sh::Window::None)]
    pub window: crate::sh::Window,
    /// Exposure in stops for PNG output.
    #[arg(
        long,
        value_name = "EV",
        default_value_t = 0.0,
        allow_negative_numbers = true
    )]
    pub exposure: f32,
    /// Also write the input map itself (after clamping bad pixels), for side-by-side figures.
    #[arg(long, value_name = "PATH")]
    pub original: Option<PathBuf>,
}

impl GlobalArgs {
    /// The worker thread count: `--threads`, else `SLURM_CPUS_PER_TASK`, else every core.
    pub fn thread_count(&self) -> Result<usize> {
        if let Some(n) = self.threads {
            if n == 0 {
                return Err(Error::usage("--threads must be at least 1"));
            }
            return Ok(n);
        }
        if let Ok(s) = std::env::var("SLURM_CPUS_PER_TASK") {
            if let Ok(n) = s.trim().parse::<usize>() {
                if n > 0 {
                    return Ok(n);
                }
            }
        }
        Ok(std::thread::available_parallelism().map_or(1, |n| n.get()))
    }
}
