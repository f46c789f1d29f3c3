//! The one error type of vscatter: every failure a user can cause ends here, as one line that names
//! the file (where there is one) and what is wrong, and maps to an exit code.

use std::path::{Path, PathBuf};

/// Every way a vscatter command can fail.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// The command line asks for something invalid (exit code 2).
    #[error("{0}")]
    Usage(String),
    /// The operating system refused to open, read or write a file.
    #[error("{}: {source}", path.display())]
    Io {
        path: PathBuf,
        source: std::io::Error,
    },
    /// A file was read, but its content is not what it should be.
    #[error("{}: {msg}", path.display())]
    Format { path: PathBuf, msg: String },
    /// Anything else that stops the work (not enough memory for the requested bake, …).
    #[error("{0}")]
    Runtime(String),
}

/// The crate-wide result.
pub type Result<T> = std::result::Result<T, Error>;

impl Error {
    pub fn usage(msg: impl Into<String>) -> Self {
        Error::Usage(msg.into())
    }

    pub fn io(path: impl AsRef<Path>, source: std::io::Error) -> Self {
        Error::Io {
            path: path.as_ref().to_path_buf(),
            source,
        }
    }

    pub fn format(path: impl AsRef<Path>, msg: impl Into<String>) -> Self {
        Error::Format {
            path: path.as_ref().to_path_buf(),
            msg: msg.into(),
        }
    }

    /// The process exit code: 2 for bad usage, 1 for every runtime failure.
    pub fn exit_code(&self) -> u8 {
        match self {
            Error::Usage(_) => 2,
            _ => 1,
        }
    }
}
