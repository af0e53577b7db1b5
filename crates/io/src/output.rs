//! Output folders as transactions: a command builds its whole output in a
//! temporary folder beside `OUT` and renames it to `OUT` when everything is
//! written, so `OUT` holds either nothing, the earlier output, or the
//! complete new one, never a mix. An existing `OUT` is refused unless the
//! caller asked to replace it.
//!
//! Nothing the tool did not create is touched (issue 69):
//!
//! * the temporary folder is `.OUT.bridgev2w-tmp-<pid>-<random>`, unique to
//!   the run, and holds a marker file [`MARKER`] written first; a failed
//!   command removes it, a killed one leaves it, and a later run removes it
//!   only when it carries the marker and its process is gone;
//! * the earlier `OUT` being replaced is moved aside to
//!   `.OUT.bridgev2w-old-<pid>-<random>` (a name no user chooses) and removed
//!   after the rename;
//! * an output equal to, inside, or containing an input is refused
//!   ([`OutputDir::create_for`], [`check_no_overlap`]);
//! * a run holds the lock `.OUT.bridgev2w-lock` (its pid inside) until it is
//!   dropped: a second writer into the same `OUT` is refused naming the
//!   first's pid (a lock whose process is gone is taken over), and the
//!   commit re-checks that `OUT` is still what the run found (absent, or the
//!   folder it replaces);
//! * a folder written in place (a training run) holds the same lock for the
//!   whole run ([`OutputLock`]).

mod lock;

pub use lock::OutputLock;
use lock::{Lock, LOCK_HEADER};
use std::ffi::OsString;
use std::path::{Component, Path, PathBuf};

/// The marker file inside a temporary output folder: the folder is
/// bridgev2w's own, and may be removed once its process is gone.
pub const MARKER: &str = ".bridgev2w-output";

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
    /// An output file's name is a folder.
    #[error("{}: is a folder, expected a file name", path.display())]
    IsADir {
        /// The output.
        path: PathBuf,
    },
    /// An output file's folder does not exist.
    #[error("{}: the folder {} does not exist", path.display(), dir.display())]
    NoFolder {
        /// The output.
        path: PathBuf,
        /// Its folder.
        dir: PathBuf,
    },
    /// The output path does not end in a folder name (`.`, `..`, `/`).
    #[error("{}: expected an output path that ends in a folder name", path.display())]
    NoName {
        /// The output.
        path: PathBuf,
    },
    /// The output is, is inside, or contains an input: replacing it would
    /// delete the input.
    #[error("{}: the output {how} the input {} (choose an output outside every input)", out.display(), input.display())]
    Overlaps {
        /// The output.
        out: PathBuf,
        /// The input it overlaps.
        input: PathBuf,
        /// "is", "is inside" or "contains".
        how: &'static str,
    },
    /// Another run is writing the same output.
    #[error("{}: another bridgev2w run (pid {pid}) is writing this output (lock {}); wait for it to finish, or remove the lock if that process is gone", out.display(), lock.display())]
    Locked {
        /// The output.
        out: PathBuf,
        /// The lock file.
        lock: PathBuf,
        /// The process holding it.
        pid: u32,
    },
    /// A file with the lock's name exists that bridgev2w did not write.
    #[error("{}: exists and is not a bridgev2w lock (expected a first line {LOCK_HEADER:?} and a pid); it is left alone: move it away to write {}", lock.display(), out.display())]
    ForeignLock {
        /// The output.
        out: PathBuf,
        /// The file in the way.
        lock: PathBuf,
    },
    /// The output changed while the run was writing (another process made,
    /// replaced or removed it); the new output is not renamed over it.
    #[error("{}: changed while this run was writing it (expected {expected}); nothing was replaced", path.display())]
    Changed {
        /// The output.
        path: PathBuf,
        /// What the run expected to find.
        expected: &'static str,
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

/// What a run found at `OUT`, compared again at the commit.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Found {
    /// Nothing.
    Absent,
    /// A folder (its device and inode where the platform has them).
    Dir(Option<(u64, u64)>),
    /// A file, a link or anything else.
    Other,
}

impl Found {
    fn at(path: &Path) -> Result<Self, OutputError> {
        match path.symlink_metadata() {
            Ok(m) if m.is_dir() => Ok(Self::Dir(identity(&m))),
            Ok(_) => Ok(Self::Other),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(Self::Absent),
            Err(e) => Err(io(path)(e)),
        }
    }
}

#[cfg(unix)]
fn identity(m: &std::fs::Metadata) -> Option<(u64, u64)> {
    use std::os::unix::fs::MetadataExt;
    Some((m.dev(), m.ino()))
}

#[cfg(not(unix))]
fn identity(_: &std::fs::Metadata) -> Option<(u64, u64)> {
    None
}

/// An output folder being written: write into [`OutputDir::path`], then
/// [`OutputDir::commit`]. Dropped without a commit, it removes its
/// temporary folder; dropped at all, it releases its lock.
#[derive(Debug)]
pub struct OutputDir {
    out: PathBuf,
    tmp: PathBuf,
    found: Found,
    committed: bool,
    // Dropped after `Drop::drop` has removed the temporary folder.
    lock: Lock,
}

impl OutputDir {
    /// Starts writing `out`. An existing `out` that is not an empty folder is
    /// refused unless `overwrite` (then it is replaced at the commit, not
    /// before). Another run writing `out` is refused naming its pid; stale
    /// temporary folders of killed runs (marked, their process gone) are
    /// removed. See the module documentation.
    pub fn create(out: &Path, overwrite: bool) -> Result<Self, OutputError> {
        Self::create_for(out, overwrite, &[])
    }

    /// [`OutputDir::create`] for a command that reads `inputs`: an output
    /// equal to, inside, or containing any of them is refused first
    /// ([`check_no_overlap`]).
    pub fn create_for(out: &Path, overwrite: bool, inputs: &[&Path]) -> Result<Self, OutputError> {
        check_no_overlap(out, inputs)?;
        let (parent, name) = split(out)?;
        std::fs::create_dir_all(&parent).map_err(io(&parent))?;
        let lock = Lock::take(out, beside(&parent, &name, "lock"))?;
        // Checked under the lock: no other bridgev2w run changes it now.
        let found = Found::at(out)?;
        match found {
            Found::Other => {
                return Err(OutputError::NotADir {
                    path: out.to_path_buf(),
                })
            }
            Found::Dir(_) => {
                let empty = std::fs::read_dir(out).map_err(io(out))?.next().is_none();
                if !empty && !overwrite {
                    return Err(OutputError::Exists {
                        path: out.to_path_buf(),
                    });
                }
            }
            Found::Absent => {}
        }
        remove_stale(&parent, &name);
        let pid = std::process::id();
        let tmp = beside(
            &parent,
            &name,
            &format!("tmp-{pid}-{:016x}", rand::random::<u64>()),
        );
        // `create_dir`, not `create_dir_all`: a folder already there (of
        // anyone) is never written into.
        std::fs::create_dir(&tmp).map_err(io(&tmp))?;
        let marker = tmp.join(MARKER);
        let marked = std::fs::write(
            &marker,
            format!(
                "bridgev2w temporary output of process {pid} for {}; \
                 a later run removes it once that process is gone\n",
                out.display()
            ),
        );
        if let Err(e) = marked {
            let _ = std::fs::remove_dir_all(&tmp);
            return Err(io(&marker)(e));
        }
        Ok(Self {
            out: out.to_path_buf(),
            tmp,
            found,
            committed: false,
            lock,
        })
    }

    /// The folder to write into (`.OUT.bridgev2w-tmp-<pid>-<random>`; it
    /// holds the marker file [`MARKER`], removed at the commit).
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// The final output folder (`OUT`).
    pub fn target(&self) -> &Path {
        &self.out
    }

    /// Renames the written folder to `OUT`, replacing an earlier `OUT` (moved
    /// aside to `.OUT.bridgev2w-old-<pid>-<random>` first and removed after
    /// the rename). Refused, replacing nothing, when `OUT` is no longer what
    /// [`OutputDir::create`] found there or the run's lock was taken away.
    pub fn commit(mut self) -> Result<PathBuf, OutputError> {
        if !self.lock.held() {
            return Err(OutputError::Changed {
                path: self.out.clone(),
                expected: "this run's lock to be still in place",
            });
        }
        if Found::at(&self.out)? != self.found {
            return Err(OutputError::Changed {
                path: self.out.clone(),
                expected: match self.found {
                    Found::Absent => "no file or folder there",
                    _ => "the folder it replaces",
                },
            });
        }
        let marker = self.tmp.join(MARKER);
        std::fs::remove_file(&marker).map_err(io(&marker))?;
        let (parent, name) = split(&self.out)?;
        let old = beside(
            &parent,
            &name,
            &format!("old-{}-{:016x}", std::process::id(), rand::random::<u64>()),
        );
        let had_old = self.found != Found::Absent;
        if had_old {
            if old.symlink_metadata().is_ok() {
                // Never renamed over (a random name: no one else's).
                return Err(OutputError::Io {
                    path: old,
                    source: std::io::ErrorKind::AlreadyExists.into(),
                });
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
            std::fs::remove_dir_all(&old).map_err(io(&old))?;
        }
        Ok(self.out.clone())
    }
}

impl Drop for OutputDir {
    fn drop(&mut self) {
        if !self.committed {
            // Created by this run (`create_dir`), so its own.
            let _ = std::fs::remove_dir_all(&self.tmp);
        }
    }
}

/// Checks, before any work, that the output file `path` can be written:
/// not existing unless `overwrite`, not a folder, its folder present (the
/// file itself is then written atomically, e.g. with
/// [`crate::json::write_json_atomic`]).
pub fn check_new_file(path: &Path, overwrite: bool) -> Result<(), OutputError> {
    let path_buf = || path.to_path_buf();
    if path.is_dir() {
        return Err(OutputError::IsADir { path: path_buf() });
    }
    if path.exists() && !overwrite {
        return Err(OutputError::Exists { path: path_buf() });
    }
    let parent = path.parent().filter(|p| !p.as_os_str().is_empty());
    if let Some(dir) = parent.filter(|d| !d.is_dir()) {
        return Err(OutputError::NoFolder {
            path: path_buf(),
            dir: dir.to_path_buf(),
        });
    }
    Ok(())
}

/// Refuses an output `out` equal to, inside, or containing any of `inputs`
/// (compared as canonical paths; the part of a path that does not exist yet
/// is appended to its nearest existing ancestor's canonical path), naming
/// both.
pub fn check_no_overlap(out: &Path, inputs: &[&Path]) -> Result<(), OutputError> {
    let o = resolved(out);
    for input in inputs {
        let i = resolved(input);
        let how = if o == i {
            "is"
        } else if o.starts_with(&i) {
            "is inside"
        } else if i.starts_with(&o) {
            "contains"
        } else {
            continue;
        };
        return Err(OutputError::Overlaps {
            out: out.to_path_buf(),
            input: input.to_path_buf(),
            how,
        });
    }
    Ok(())
}

/// `path` made absolute: its longest existing prefix canonicalized, the
/// rest appended with `.` and `..` resolved by name.
fn resolved(path: &Path) -> PathBuf {
    let abs = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir()
            .map(|d| d.join(path))
            .unwrap_or_else(|_| path.to_path_buf())
    };
    let comps: Vec<Component> = abs.components().collect();
    for n in (0..=comps.len()).rev() {
        let prefix: PathBuf = comps[..n].iter().collect();
        let base = if n == 0 {
            Some(PathBuf::new())
        } else {
            prefix.canonicalize().ok()
        };
        if let Some(mut r) = base {
            for c in &comps[n..] {
                match c {
                    Component::ParentDir => {
                        r.pop();
                    }
                    Component::CurDir => {}
                    other => r.push(other.as_os_str()),
                }
            }
            return r;
        }
    }
    abs
}

/// `OUT`'s folder and name.
fn split(out: &Path) -> Result<(PathBuf, OsString), OutputError> {
    let name = out.file_name().ok_or_else(|| OutputError::NoName {
        path: out.to_path_buf(),
    })?;
    let parent = out
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    Ok((parent.to_path_buf(), name.to_os_string()))
}

/// `.NAME.bridgev2w-KIND` in `parent`.
fn beside(parent: &Path, name: &std::ffi::OsStr, kind: &str) -> PathBuf {
    let mut s = OsString::from(".");
    s.push(name);
    s.push(".bridgev2w-");
    s.push(kind);
    parent.join(s)
}

/// Whether process `pid` may still run: `true` unless it is known to be
/// gone (Linux: no `/proc/<pid>`; elsewhere, always `true`, so nothing of
/// another process is ever removed or taken over).
fn pid_alive(pid: u32) -> bool {
    let proc = Path::new("/proc");
    if pid == std::process::id() || !cfg!(target_os = "linux") || !proc.join("self").exists() {
        return true;
    }
    proc.join(pid.to_string()).exists()
}

/// Removes the temporary folders of `NAME` that killed runs left: only
/// folders named `.NAME.bridgev2w-tmp-<pid>-...` that hold the marker and
/// whose process is gone. Best effort: what cannot be removed stays.
fn remove_stale(parent: &Path, name: &std::ffi::OsStr) {
    let prefix = format!(".{}.bridgev2w-tmp-", name.to_string_lossy());
    let Ok(entries) = std::fs::read_dir(parent) else {
        return;
    };
    for entry in entries.flatten() {
        let file_name = entry.file_name();
        let Some(rest) = file_name.to_str().and_then(|n| n.strip_prefix(&prefix)) else {
            continue;
        };
        let Some(pid) = rest.split('-').next().and_then(|p| p.parse::<u32>().ok()) else {
            continue;
        };
        let path = entry.path();
        let marked = path.symlink_metadata().is_ok_and(|m| m.is_dir())
            && path
                .join(MARKER)
                .symlink_metadata()
                .is_ok_and(|m| m.is_file());
        if marked && !pid_alive(pid) {
            let _ = std::fs::remove_dir_all(&path);
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    pub(super) fn names(dir: &Path) -> Vec<String> {
        let mut n: Vec<_> = std::fs::read_dir(dir)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        n.sort();
        n
    }

    /// The pid of a process that has exited.
    pub(super) fn dead_pid() -> u32 {
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let pid = child.id();
        child.wait().unwrap();
        pid
    }

    #[test]
    fn writes_appear_only_at_commit_and_a_drop_cleans_up() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let o = OutputDir::create(&out, false).unwrap();
        assert!(o.path().join(MARKER).is_file(), "marked first");
        std::fs::write(o.path().join("a.txt"), "a").unwrap();
        assert!(!out.exists());
        o.commit().unwrap();
        assert_eq!(std::fs::read_to_string(out.join("a.txt")).unwrap(), "a");
        // Neither the marker, the temporary folder nor the lock is left.
        assert_eq!(names(&out), ["a.txt"]);
        assert_eq!(names(dir.path()), ["out"]);
        // A failed command (dropped without commit) leaves nothing.
        let o = OutputDir::create(&dir.path().join("other"), false).unwrap();
        std::fs::write(o.path().join("b.txt"), "b").unwrap();
        drop(o);
        assert_eq!(names(dir.path()), ["out"]);
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
        assert_eq!(names(&out), ["fresh.txt"]);
        assert_eq!(names(dir.path()), ["out"], "no backup left");
        // A file in the way is not a folder to replace.
        std::fs::write(dir.path().join("file"), "f").unwrap();
        let e = OutputDir::create(&dir.path().join("file"), true).unwrap_err();
        assert!(e.to_string().contains("not a folder"), "{e}");
        assert_eq!(
            std::fs::read_to_string(dir.path().join("file")).unwrap(),
            "f"
        );
        // A path without a folder name is refused, not renamed.
        let e = OutputDir::create(Path::new("/"), true).unwrap_err();
        assert!(e.to_string().contains("folder name"), "{e}");
    }

    #[test]
    fn user_folders_named_like_the_old_bookkeeping_names_survive() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        for n in ["out.tmp", "out.old"] {
            std::fs::create_dir(dir.path().join(n)).unwrap();
            std::fs::write(dir.path().join(n).join("mine.txt"), n).unwrap();
        }
        for overwrite in [false, true] {
            let o = OutputDir::create(&out, overwrite).unwrap();
            std::fs::write(o.path().join("x"), "x").unwrap();
            o.commit().unwrap();
        }
        for n in ["out.tmp", "out.old"] {
            let kept = std::fs::read_to_string(dir.path().join(n).join("mine.txt")).unwrap();
            assert_eq!(kept, n);
        }
        assert_eq!(names(dir.path()), ["out", "out.old", "out.tmp"]);
    }

    #[test]
    #[cfg(target_os = "linux")]
    fn only_marked_temporary_folders_of_gone_processes_are_removed() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let dead = dead_pid();
        let stale = dir.path().join(format!(".out.bridgev2w-tmp-{dead}-00"));
        std::fs::create_dir_all(stale.join("frames")).unwrap();
        std::fs::write(stale.join(MARKER), "").unwrap();
        std::fs::write(stale.join("frames/9.png"), "old").unwrap();
        // Same name pattern, no marker: the user's (or unknown): kept.
        let unmarked = dir.path().join(format!(".out.bridgev2w-tmp-{dead}-01"));
        std::fs::create_dir(&unmarked).unwrap();
        std::fs::write(unmarked.join("keep.txt"), "k").unwrap();
        // Marked, but its process (this one) still runs: kept.
        let live = dir
            .path()
            .join(format!(".out.bridgev2w-tmp-{}-02", std::process::id()));
        std::fs::create_dir(&live).unwrap();
        std::fs::write(live.join(MARKER), "").unwrap();
        let o = OutputDir::create(&out, false).unwrap();
        assert_eq!(names(o.path()), [MARKER]);
        assert!(!stale.exists(), "the stale marked folder is removed");
        assert!(unmarked.join("keep.txt").exists());
        assert!(live.join(MARKER).exists());
    }

    #[test]
    fn outputs_overlapping_an_input_are_refused_naming_both() {
        let dir = tempfile::tempdir().unwrap();
        let src = dir.path().join("src");
        std::fs::create_dir_all(src.join("episodes")).unwrap();
        std::fs::write(src.join("episodes/a.npy"), "a").unwrap();
        let cases = [
            (src.clone(), "is the input"),
            (src.join("."), "is the input"),
            (src.join("episodes/new"), "is inside the input"),
            (src.join("not-yet/../episodes"), "is inside the input"),
            (dir.path().to_path_buf(), "contains the input"),
        ];
        for (out, how) in cases {
            let e = OutputDir::create_for(&out, true, &[Path::new("/nonexistent-x"), &src])
                .unwrap_err()
                .to_string();
            assert!(e.contains(how), "{}: {e}", out.display());
            assert!(e.contains(&*out.to_string_lossy()), "{e}");
            assert!(e.contains(&*src.to_string_lossy()), "{e}");
        }
        assert_eq!(
            std::fs::read_to_string(src.join("episodes/a.npy")).unwrap(),
            "a"
        );
        // A file input inside the output is refused too; a sibling is fine.
        let e = check_no_overlap(&src, &[&src.join("episodes/a.npy")]).unwrap_err();
        assert!(e.to_string().contains("contains the input"), "{e}");
        check_no_overlap(&dir.path().join("src2"), &[&src]).unwrap();
        let o = OutputDir::create_for(&dir.path().join("src2"), false, &[&src]).unwrap();
        o.commit().unwrap();
    }

    #[test]
    fn the_commit_refuses_an_output_changed_meanwhile() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("out");
        let o = OutputDir::create(&out, false).unwrap();
        std::fs::write(o.path().join("new"), "n").unwrap();
        // Someone else made OUT while this run wrote.
        std::fs::create_dir(&out).unwrap();
        std::fs::write(out.join("theirs"), "t").unwrap();
        let e = o.commit().unwrap_err().to_string();
        assert!(e.contains("changed while"), "{e}");
        assert_eq!(names(&out), ["theirs"]);
        assert_eq!(names(dir.path()), ["out"], "temporary folder and lock gone");
        // And a replaced folder: swapped for another one meanwhile.
        let o = OutputDir::create(&out, true).unwrap();
        std::fs::rename(&out, dir.path().join("moved")).unwrap();
        std::fs::create_dir(&out).unwrap();
        std::fs::write(out.join("other"), "o").unwrap();
        let e = o.commit().unwrap_err().to_string();
        assert!(e.contains("the folder it replaces"), "{e}");
        assert_eq!(names(&out), ["other"]);
    }

    #[test]
    fn check_new_file_refuses_an_existing_file_a_folder_and_a_missing_folder() {
        let tmp = tempfile::tempdir().unwrap();
        let file = tmp.path().join("scores.json");
        check_new_file(&file, false).unwrap();
        std::fs::write(&file, b"{}").unwrap();
        let e = check_new_file(&file, false).unwrap_err().to_string();
        assert!(
            e.contains("scores.json: already exists") && e.contains("--overwrite"),
            "{e}"
        );
        check_new_file(&file, true).unwrap();
        let e = check_new_file(tmp.path(), true).unwrap_err().to_string();
        assert!(e.contains("is a folder, expected a file name"), "{e}");
        let e = check_new_file(&tmp.path().join("no/x.json"), false)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("the folder") && e.contains("does not exist"),
            "{e}"
        );
    }
}
