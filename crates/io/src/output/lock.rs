//! The lock `.OUT.bridgev2w-lock` beside an output: held by one run at a
//! time (an [`OutputDir`](super::OutputDir) while it builds `OUT`, an
//! [`OutputLock`] while a run writes `OUT` in place), taken over when its
//! process is gone, never removed when it is not bridgev2w's.

use super::{beside, io, pid_alive, resolved, split, OutputError};
use std::io::Write;
use std::path::{Path, PathBuf};

/// The first line of a lock file (a file without it is not bridgev2w's).
pub(super) const LOCK_HEADER: &str = "bridgev2w output lock";

/// The lock of a folder a long run writes in place (a training run folder:
/// its metrics, checkpoints and final weights are written into it as the
/// run goes, not built aside and renamed): the same lock file
/// `.OUT.bridgev2w-lock` as [`OutputDir`]'s, so a second run into the same
/// folder, or a command writing an [`OutputDir`] there, is refused naming
/// the first's pid ([`OutputError::Locked`]). A lock whose process is gone
/// is taken over; a file of that name that bridgev2w did not write is left
/// alone and refused ([`OutputError::ForeignLock`]). Released when dropped.
///
/// [`OutputDir`]: super::OutputDir
#[derive(Debug)]
pub struct OutputLock {
    lock: Lock,
}

impl OutputLock {
    /// Takes the lock of `out` (which need not exist yet; its parent folder
    /// is created). An `out` without a folder name (`.`, `run/..`) is
    /// locked by its absolute name.
    pub fn take(out: &Path) -> Result<Self, OutputError> {
        let named = if out.file_name().is_some() {
            out.to_path_buf()
        } else {
            resolved(out)
        };
        let (parent, name) = split(&named)?;
        std::fs::create_dir_all(&parent).map_err(io(&parent))?;
        let lock = Lock::take(out, beside(&parent, &name, "lock"))?;
        Ok(Self { lock })
    }

    /// The lock file (`.OUT.bridgev2w-lock` beside `OUT`).
    pub fn path(&self) -> &Path {
        &self.lock.path
    }

    /// Whether the lock file still holds this run's lock (not removed or
    /// taken over meanwhile).
    pub fn held(&self) -> bool {
        self.lock.held()
    }
}

/// The lock file `.OUT.bridgev2w-lock` of a run (its pid and a random
/// token inside), removed when dropped if it is still this run's.
#[derive(Debug)]
pub(super) struct Lock {
    path: PathBuf,
    content: String,
}

impl Lock {
    pub(super) fn take(out: &Path, path: PathBuf) -> Result<Self, OutputError> {
        let content = format!(
            "{LOCK_HEADER}\npid {}\ntoken {:016x}\n",
            std::process::id(),
            rand::random::<u64>()
        );
        for _ in 0..3 {
            match std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&path)
            {
                Ok(mut f) => {
                    if let Err(e) = f.write_all(content.as_bytes()).and_then(|()| f.sync_all()) {
                        let _ = std::fs::remove_file(&path);
                        return Err(io(&path)(e));
                    }
                    return Ok(Self { path, content });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {}
                Err(e) => return Err(io(&path)(e)),
            }
            let Some(text) = read_lock(&path)? else {
                continue; // released meanwhile
            };
            let Some(pid) = lock_pid(&text) else {
                return Err(OutputError::ForeignLock {
                    out: out.to_path_buf(),
                    lock: path,
                });
            };
            if pid_alive(pid) {
                return Err(OutputError::Locked {
                    out: out.to_path_buf(),
                    lock: path,
                    pid,
                });
            }
            // Its process is gone: taken over (if no one else did first).
            if read_lock(&path)?.as_deref() == Some(text.as_str()) {
                match std::fs::remove_file(&path) {
                    Err(e) if e.kind() != std::io::ErrorKind::NotFound => return Err(io(&path)(e)),
                    _ => {}
                }
            }
        }
        Err(OutputError::Io {
            path,
            source: std::io::Error::other("the lock kept changing; try again"),
        })
    }

    /// Whether the lock file still holds this run's content.
    pub(super) fn held(&self) -> bool {
        std::fs::read_to_string(&self.path).is_ok_and(|t| t == self.content)
    }
}

impl Drop for Lock {
    fn drop(&mut self) {
        if self.held() {
            let _ = std::fs::remove_file(&self.path);
        }
    }
}

/// A lock file's text, `None` when it is gone. A lock being written (empty
/// still) is read again after a moment.
fn read_lock(path: &Path) -> Result<Option<String>, OutputError> {
    for attempt in 0..3 {
        match std::fs::read_to_string(path) {
            Ok(t) if t.is_empty() && attempt < 2 => {
                std::thread::sleep(std::time::Duration::from_millis(50));
            }
            Ok(t) => return Ok(Some(t)),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
            Err(e) => return Err(io(path)(e)),
        }
    }
    Ok(Some(String::new()))
}

/// The pid of a bridgev2w lock's text (`None`: not a bridgev2w lock).
fn lock_pid(text: &str) -> Option<u32> {
    let mut lines = text.lines();
    if lines.next()? != LOCK_HEADER {
        return None;
    }
    lines.next()?.strip_prefix("pid ")?.parse().ok()
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::super::tests::{dead_pid, names};
    use super::super::OutputDir;
    use super::*;

    #[test]
    fn a_second_writer_is_refused_naming_the_first_pid() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let first = OutputDir::create(&out, true).unwrap();
        let e = OutputDir::create(&out, true).unwrap_err().to_string();
        assert!(
            e.contains(&format!("pid {}", std::process::id())) && e.contains("another"),
            "{e}"
        );
        std::fs::write(first.path().join("a"), "1").unwrap();
        first.commit().unwrap();
        // Released at the end: the next run may write.
        let again = OutputDir::create(&out, true).unwrap();
        drop(again);
        assert_eq!(names(dir.path()), ["out"]);
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn a_lock_of_a_gone_process_is_taken_over_a_foreign_file_is_not() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let lock = dir.path().join(".out.bridgev2w-lock");
        std::fs::write(&lock, format!("{LOCK_HEADER}\npid {}\n", dead_pid())).unwrap();
        let o = OutputDir::create(&out, false).unwrap();
        o.commit().unwrap();
        assert!(!lock.exists());
        std::fs::write(&lock, "my notes").unwrap();
        let e = OutputDir::create(&out, true).unwrap_err().to_string();
        assert!(e.contains("not a bridgev2w lock"), "{e}");
        assert_eq!(std::fs::read_to_string(&lock).unwrap(), "my notes");
    }

    #[test]
    fn the_public_lock_refuses_a_second_writer_and_is_released_when_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join("runs/run");
        let first = OutputLock::take(&run).unwrap();
        assert_eq!(first.path(), dir.path().join("runs/.run.bridgev2w-lock"));
        assert!(first.held());
        // A second trainer, and a command writing an OutputDir there.
        let e = OutputLock::take(&run).unwrap_err();
        assert!(
            matches!(e, OutputError::Locked { pid, .. } if pid == std::process::id()),
            "{e}"
        );
        assert!(e
            .to_string()
            .contains(&format!("pid {}", std::process::id())));
        let e = OutputDir::create(&run, true).unwrap_err();
        assert!(matches!(e, OutputError::Locked { .. }), "{e}");
        drop(first);
        assert_eq!(names(&dir.path().join("runs")), Vec::<String>::new());
        let again = OutputLock::take(&run).unwrap();
        // A path without a folder name is locked by its absolute name.
        std::fs::create_dir_all(run.join("sub")).unwrap();
        let e = OutputLock::take(&run.join("sub/..")).unwrap_err();
        assert!(matches!(e, OutputError::Locked { .. }), "{e}");
        drop(again);
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn the_public_lock_of_a_live_process_is_refused_a_dead_one_taken_over() {
        let dir = tempfile::tempdir().unwrap();
        let run = dir.path().join("run");
        let lock = dir.path().join(".run.bridgev2w-lock");
        let mut child = std::process::Command::new("sleep")
            .arg("30")
            .spawn()
            .unwrap();
        std::fs::write(&lock, format!("{LOCK_HEADER}\npid {}\n", child.id())).unwrap();
        let refused = OutputLock::take(&run).map(drop);
        child.kill().unwrap();
        child.wait().unwrap();
        let e = refused.unwrap_err().to_string();
        assert!(e.contains(&format!("pid {}", child.id())), "{e}");
        // Its process is gone now: taken over.
        let taken = OutputLock::take(&run).unwrap();
        assert!(taken.held());
        drop(taken);
        assert!(!lock.exists());
        std::fs::write(&lock, "my notes").unwrap();
        let e = OutputLock::take(&run).unwrap_err();
        assert!(matches!(e, OutputError::ForeignLock { .. }), "{e}");
        assert_eq!(std::fs::read_to_string(&lock).unwrap(), "my notes");
    }
}
