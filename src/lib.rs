//! vscatter: read sparse OpenVDB fog volumes, bake a light-independent spherical-harmonic transfer
//! with multiple scattering, and relight it with any HDR environment.

pub mod atomic;
pub mod bake;
pub mod cli;
pub mod compare;
pub mod env;
pub mod env_cmd;
pub mod error;
pub mod floor;
pub mod image;
pub mod info;
pub mod pathtrace;
pub mod progress;
pub mod render;
pub mod render_cmd;
pub mod sh;
pub mod transfer;
pub mod volume;

pub use error::{Error, Result};

use cli::{Cli, Command};

/// Runs one command line; the binary turns the result into an exit code.
pub fn run(cli: Cli) -> Result<()> {
    let threads = cli.global.thread_count()?;
    // A second initialisation (tests that call `run` twice in one process) keeps the first pool.
    let _ = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global();
    match cli.command {
        Command::Info(args) => info::run(&args),
        Command::Env(args) => env_cmd::run(&args),
        Command::Bake(args) => bake::run(&args, &cli.global),
        Command::Render(args) => render_cmd::run(&args, &cli.global),
        Command::Compare(args) => compare::run(&args),
    }
}
