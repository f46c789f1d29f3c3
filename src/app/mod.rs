//! The commands: each turns validated flags into calls of the library and prints what the user
//! asked for. Nothing here computes a picture or a transfer; the library does.

mod args;
mod bake;
mod batch;
mod compare;
mod env;
mod info;
mod progress;
mod render;

pub use args::Cli;

use args::Command;
use vscatter::Result;

/// Runs one command line; the binary turns the result into an exit code.
pub fn run(cli: Cli) -> Result<()> {
    let threads = cli.global.thread_count()?;
    // A second initialisation keeps the first pool (the pool is process-wide).
    let _ = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build_global();
    match cli.command {
        Command::Info(args) => info::run(&args),
        Command::Env(args) => env::run(&args),
        Command::Bake(args) => bake::run(&args, &cli.global),
        Command::Batch(args) => batch::run(&args, &cli.global, threads),
        Command::Render(args) => render::run(&args, &cli.global),
        Command::Compare(args) => compare::run(&args),
    }
}
