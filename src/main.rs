//! The `vscatter` binary: parse the command line, run, turn the outcome into an exit code.

use std::process::ExitCode;

use clap::Parser;

mod app;

fn main() -> ExitCode {
    end_quietly_on_a_closed_pipe();
    vscatter::io::meminfo::return_large_blocks_when_freed();
    let cli = match app::Cli::try_parse() {
        Ok(cli) => cli,
        Err(e) if !e.use_stderr() => {
            // --help and --version: clap's own output on stdout.
            let _ = e.print();
            return ExitCode::SUCCESS;
        }
        Err(e) => {
            // Usage errors: one line, like every other error (clap's tips and usage block follow
            // its first line; `--help` has them).
            let text = e.render().to_string();
            let mut lines = text.lines().map(str::trim).filter(|l| !l.is_empty());
            let first = lines.next().unwrap_or("invalid command line");
            let first = first.strip_prefix("error: ").unwrap_or(first);
            // "required arguments were not provided:" lists them on the lines that follow.
            let detail = match first.ends_with(':') {
                true => format!(" {}", lines.next().unwrap_or_default()),
                false => String::new(),
            };
            eprintln!("vscatter: error: {first}{detail} (see `vscatter --help`)");
            return ExitCode::from(2);
        }
    };
    match app::run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("vscatter: error: {e}");
            ExitCode::from(e.exit_code())
        }
    }
}

/// Restores SIGPIPE's default action, which Rust's runtime ignores: `vscatter info x.vdb | head -1`
/// then ends when `head` stops reading, silently, as `cat` or `grep` would, where `println!` into
/// a closed pipe would panic. Nothing is lost: the commands print to stdout only once their files
/// are written, or write none.
fn end_quietly_on_a_closed_pipe() {
    #[cfg(unix)]
    // SAFETY: sets a signal's disposition to its default; called before any thread starts.
    unsafe {
        libc::signal(libc::SIGPIPE, libc::SIG_DFL);
    }
}
