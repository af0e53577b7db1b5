//! Atomic file writes: a temporary file beside the target, written, synced
//! and renamed over it. A rename within one folder is atomic on POSIX file
//! systems, so readers and resumed runs see the old or the new content.

use crate::{FileError, Result};
use std::io::Write;
use std::path::{Path, PathBuf};

/// A fresh temporary name beside `path`: hidden, carrying this process's id
/// and a random part, so no user's file is ever taken for it (issue 69).
pub fn temporary_beside(path: &Path) -> PathBuf {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "file".to_owned());
    dir.join(format!(
        ".{name}.bridgev2w-tmp-{}-{:016x}",
        std::process::id(),
        rand::random::<u64>()
    ))
}

/// Writes `bytes` to `path` atomically (temporary file, `fsync`, rename).
/// The folder must exist.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_io(path, bytes).map_err(|e| FileError::io(path, e))
}

/// [`write_atomic`] with the bare `std::io::Error`, for callers that wrap
/// errors in their own type. The temporary file is created new (an
/// existing file of that name is never opened, truncated or removed).
pub fn write_atomic_io(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    let (tmp, mut f) = create_temporary(path)?;
    let result = (|| {
        f.write_all(bytes)?;
        f.sync_all()?;
        drop(f);
        std::fs::rename(&tmp, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// A new temporary file beside `path` (a few tries with fresh names).
fn create_temporary(path: &Path) -> std::io::Result<(PathBuf, std::fs::File)> {
    let mut last = None;
    for _ in 0..4 {
        let tmp = temporary_beside(path);
        match std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .open(&tmp)
        {
            Ok(f) => return Ok((tmp, f)),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => last = Some(e),
            Err(e) => return Err(e),
        }
    }
    Err(last.unwrap_or_else(|| std::io::Error::other("no free temporary name")))
}

/// Creates `path`'s parent folders, then writes it atomically.
pub fn write_atomic_creating_dirs(path: &Path, bytes: &[u8]) -> Result<()> {
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(|e| FileError::io(dir, e))?;
    }
    write_atomic(path, bytes)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn replaces_the_file_and_leaves_no_temporary() {
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("a.txt");
        write_atomic(&p, b"one").unwrap();
        write_atomic(&p, b"two").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        let names: Vec<_> = std::fs::read_dir(tmp.path()).unwrap().collect();
        assert_eq!(names.len(), 1, "a temporary file was left behind");
    }

    #[test]
    fn a_user_file_named_like_a_temporary_is_left_alone() {
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("a.txt");
        // The name this module used before issue 69, and a name of today's
        // pattern: neither is opened, truncated or removed.
        let old = tmp
            .path()
            .join(format!(".a.txt.tmp-{}", std::process::id()));
        let today = tmp
            .path()
            .join(format!(".a.txt.bridgev2w-tmp-{}-0", std::process::id()));
        std::fs::write(&old, b"user").unwrap();
        std::fs::write(&today, b"user too").unwrap();
        write_atomic(&p, b"one").unwrap();
        assert_eq!(std::fs::read(&old).unwrap(), b"user");
        assert_eq!(std::fs::read(&today).unwrap(), b"user too");
        assert_eq!(std::fs::read(&p).unwrap(), b"one");
        assert_eq!(std::fs::read_dir(tmp.path()).unwrap().count(), 3);
    }

    #[test]
    fn a_missing_folder_is_an_error_naming_the_file() {
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("no/such/a.txt");
        let e = write_atomic(&p, b"x").unwrap_err().to_string();
        assert!(e.contains("no/such/a.txt"), "{e}");
        write_atomic_creating_dirs(&p, b"x").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"x");
    }
}
