//! Atomic output files: every file vscatter writes (images, caches) goes to a temporary file in the
//! same directory and is renamed over the final name only once it is complete and synced, so a
//! crash, a kill or a full disk never leaves a half-written file under the final name.

use std::fs::{self, File};
use std::io::{self, BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::error::{Error, Result};

/// The temporary name for `path`: hidden, in the same directory (a rename never crosses a file
/// system), and tagged with host and pid so two farm nodes or processes writing the same output into
/// one shared directory never write into each other's temporary file.
pub fn temp_path(path: &Path) -> Result<PathBuf> {
    let name = path.file_name().ok_or_else(|| {
        Error::io(
            path,
            io::Error::new(io::ErrorKind::InvalidInput, "not a file name"),
        )
    })?;
    let host: String = gethostname::gethostname()
        .to_string_lossy()
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' {
                c
            } else {
                '_'
            }
        })
        .collect();
    let tmp = format!(
        ".{}.{}.{}.tmp",
        name.to_string_lossy(),
        host,
        std::process::id()
    );
    Ok(path.with_file_name(tmp))
}

/// Checks, before any long work, that `path` can be written: its directory exists and accepts
/// a new file (tried with the temporary name the write will use, then removed again).
pub fn check_writable(path: &Path) -> Result<()> {
    let tmp = temp_path(path)?;
    File::create(&tmp)
        .map_err(|e| Error::Runtime(format!("{}: cannot be written ({e})", path.display())))?;
    let _ = fs::remove_file(&tmp);
    Ok(())
}

/// Writes `path` atomically: `write` fills a buffered temporary file (which can also seek, as the
/// EXR writer needs), then it is flushed, synced and renamed to `path`. On any failure the temporary
/// file is removed, nothing appears under `path`, and the error names `path`.
pub fn write_atomic<F>(path: &Path, write: F) -> Result<()>
where
    F: FnOnce(&mut BufWriter<File>) -> io::Result<()>,
{
    let tmp = temp_path(path)?;
    let file = File::create(&tmp).map_err(|e| Error::io(path, e))?;
    let result = (|| {
        let mut w = BufWriter::new(file);
        write(&mut w)?;
        w.flush()?;
        let file = w.into_inner().map_err(|e| e.into_error())?;
        file.sync_all()?;
        drop(file);
        fs::rename(&tmp, path)
    })();
    result.map_err(|e| {
        // Best effort: the temporary may already be gone; the write error is what matters.
        let _ = fs::remove_file(&tmp);
        Error::io(path, e)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn writes_and_leaves_no_temporary() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("a.txt");
        write_atomic(&out, |w| w.write_all(b"hello")).unwrap();
        assert_eq!(fs::read(&out).unwrap(), b"hello");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn failed_write_leaves_nothing() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("b.txt");
        let err = write_atomic(&out, |w| {
            w.write_all(b"partial")?;
            Err(io::Error::other("disk on fire"))
        })
        .unwrap_err();
        assert!(err.to_string().contains("b.txt"), "{err}");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 0);
    }

    #[test]
    fn failed_write_keeps_the_previous_file() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("c.txt");
        fs::write(&out, b"old").unwrap();
        assert!(write_atomic(&out, |_| Err(io::Error::other("no"))).is_err());
        assert_eq!(fs::read(&out).unwrap(), b"old");
        assert_eq!(fs::read_dir(dir.path()).unwrap().count(), 1);
    }

    #[test]
    fn unwritable_directory_is_an_io_error_naming_the_file() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("missing").join("d.txt");
        let err = write_atomic(&out, |w| w.write_all(b"x")).unwrap_err();
        assert!(matches!(err, Error::Io { .. }));
        assert!(err.to_string().contains("d.txt"), "{err}");
    }
}
