//! Output folders as transactions: a command builds its whole output in
//! `OUT.tmp` and renames it to `OUT` when everything is written, so `OUT`
//! holds either nothing, the earlier output, or the complete new one, never
//! a mix. An existing `OUT` is refused unless the caller asked to replace it;
//! a failed command removes its `OUT.tmp` (a killed one leaves it, and the
//! next run removes it first).

use std::path::{Path, PathBuf};

/// Errors of [`OutputDir`].
#[derive(Debug, thiserror::Error)]
pub enum OutputError {
    /// The output exists and replacing it was not asked for.
    #[error("{}: already exists (choose another output, or pass --overwrite to replace it)", path.display())]
    Exists {
        /// The output.
        path: PathBuf,
    },
    /// The output exists and is not a folder.
    #[error("{}: exists and is not a folder", path.display())]
    NotADir {
        /// The output.
        path: PathBuf,
    },
    /// A file system operation failed.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// The error.
        source: std::io::Error,
    },
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> OutputError + '_ {
    move |source| OutputError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// An output folder being written: write into [`OutputDir::path`], then
/// [`OutputDir::commit`]. Dropped without a commit, it removes its
/// temporary folder.
#[derive(Debug)]
pub struct OutputDir {
    out: PathBuf,
    tmp: PathBuf,
    committed: bool,
}

impl OutputDir {
    /// Starts writing `out`. An existing `out` that is not an empty folder is
    /// refused unless `overwrite` (then it is replaced at the commit, not
    /// before). A stale `out.tmp` of an earlier, killed run is removed.
    pub fn create(out: &Path, overwrite: bool) -> Result<Self, OutputError> {
        if let Ok(meta) = out.symlink_metadata() {
            if !meta.is_dir() {
                return Err(OutputError::NotADir {
                    path: out.to_path_buf(),
                });
            }
            let empty = std::fs::read_dir(out).map_err(io(out))?.next().is_none();
            if !empty && !overwrite {
                return Err(OutputError::Exists {
                    path: out.to_path_buf(),
                });
            }
        }
        let tmp = sibling(out, "tmp");
        if tmp.symlink_metadata().is_ok() {
            remove(&tmp)?;
        }
        std::fs::create_dir_all(&tmp).map_err(io(&tmp))?;
        Ok(Self {
            out: out.to_path_buf(),
            tmp,
            committed: false,
        })
    }

    /// The folder to write into (`OUT.tmp`).
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// The final output folder (`OUT`).
    pub fn target(&self) -> &Path {
        &self.out
    }

    /// Renames the written folder to `OUT`, replacing an earlier `OUT` (moved
    /// to `OUT.old` first and removed after the rename).
    pub fn commit(mut self) -> Result<PathBuf, OutputError> {
        let old = sibling(&self.out, "old");
        let had_old = self.out.symlink_metadata().is_ok();
        if had_old {
            if old.symlink_metadata().is_ok() {
                remove(&old)?;
            }
            std::fs::rename(&self.out, &old).map_err(io(&self.out))?;
        }
        if let Err(e) = std::fs::rename(&self.tmp, &self.out) {
            if had_old {
                // Put the earlier output back: nothing is lost.
                let _ = std::fs::rename(&old, &self.out);
            }
            return Err(io(&self.out)(e));
        }
        self.committed = true;
        if had_old {
            remove(&old)?;
        }
        Ok(self.out.clone())
    }
}

impl Drop for OutputDir {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_dir_all(&self.tmp);
        }
    }
}

/// `OUT.suffix` beside `OUT`.
fn sibling(out: &Path, suffix: &str) -> PathBuf {
    let mut s = out.as_os_str().to_owned();
    s.push(".");
    s.push(suffix);
    PathBuf::from(s)
}

fn remove(path: &Path) -> Result<(), OutputError> {
    let r = if path.symlink_metadata().is_ok_and(|m| m.is_dir()) {
        std::fs::remove_dir_all(path)
    } else {
        std::fs::remove_file(path)
    };
    r.map_err(io(path))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn writes_appear_only_at_commit_and_a_drop_cleans_up() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let o = OutputDir::create(&out, false).unwrap();
        std::fs::write(o.path().join("a.txt"), "a").unwrap();
        assert!(!out.exists());
        o.commit().unwrap();
        assert_eq!(std::fs::read_to_string(out.join("a.txt")).unwrap(), "a");
        assert!(!dir.path().join("out.tmp").exists());
        // A failed command (dropped without commit) leaves no OUT.tmp.
        let o = OutputDir::create(&dir.path().join("other"), false).unwrap();
        std::fs::write(o.path().join("b.txt"), "b").unwrap();
        drop(o);
        assert!(!dir.path().join("other.tmp").exists());
        assert!(!dir.path().join("other").exists());
    }

    #[test]
    fn an_existing_output_is_refused_or_replaced_whole() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir(&out).unwrap();
        // An empty folder (made by the user beforehand) is fine.
        let o = OutputDir::create(&out, false).unwrap();
        std::fs::write(o.path().join("new.txt"), "1").unwrap();
        o.commit().unwrap();
        let e = OutputDir::create(&out, false).unwrap_err().to_string();
        assert!(
            e.contains("already exists") && e.contains("--overwrite"),
            "{e}"
        );
        assert!(out.join("new.txt").exists());
        // Replacing leaves no file of the earlier output behind.
        std::fs::write(out.join("stale.png"), "x").unwrap();
        let o = OutputDir::create(&out, true).unwrap();
        assert!(
            out.join("stale.png").exists(),
            "replaced at the commit only"
        );
        std::fs::write(o.path().join("fresh.txt"), "2").unwrap();
        o.commit().unwrap();
        let names: Vec<_> = std::fs::read_dir(&out)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, ["fresh.txt"]);
        assert!(!dir.path().join("out.old").exists());
        // A file in the way is not a folder to replace.
        std::fs::write(dir.path().join("file"), "f").unwrap();
        let e = OutputDir::create(&dir.path().join("file"), true).unwrap_err();
        assert!(e.to_string().contains("not a folder"), "{e}");
    }

    #[test]
    fn a_stale_temporary_folder_of_a_killed_run_is_removed() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        std::fs::create_dir_all(dir.path().join("out.tmp/frames")).unwrap();
        std::fs::write(dir.path().join("out.tmp/frames/9.png"), "old").unwrap();
        let o = OutputDir::create(&out, false).unwrap();
        assert_eq!(std::fs::read_dir(o.path()).unwrap().count(), 0);
    }
}
