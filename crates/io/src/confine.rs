//! Paths read from metadata (a dataset's `meta/info.json`, a recording's
//! metadata file), confined to the folder they belong to.
//!
//! A name written in a file is not a path the user chose: it must be a
//! relative path of plain components (no absolute path, no `..`, no NUL),
//! it must resolve, after every symbolic link is followed, inside the
//! canonical root, and the file it names must be a regular file (not a
//! FIFO, a device, a socket or a folder) of at most a stated size. Nothing
//! here opens or reads the file: an error names the value and the path it
//! resolves to, never the content.
//!
//! The callers wrap a [`Refusal`] in their own error, naming the metadata
//! file and the field the value came from.

use std::path::{Component, Path, PathBuf};

/// The largest video file a reader accepts (64 GiB): videos are streamed a
/// few frames at a time, so this only stops a file that is not a recording.
pub const MAX_VIDEO_BYTES: u64 = 64 << 30;

/// The largest tabular data file (parquet) a reader accepts (16 GiB): its
/// rows are decoded into memory.
pub const MAX_DATA_BYTES: u64 = 16 << 30;

/// The largest metadata file (JSON, JSON lines) a reader accepts (256 MiB):
/// it is read whole and parsed into memory.
pub const MAX_METADATA_BYTES: u64 = 256 << 20;

/// Why a name or path from metadata was refused. Each names the value as
/// written and what was expected; none holds any of the file's content.
#[derive(Debug, thiserror::Error)]
pub enum Refusal {
    /// Empty.
    #[error("\"\" is empty: expected {expected}")]
    Empty {
        /// What was expected.
        expected: &'static str,
    },
    /// Contains a NUL byte.
    #[error("{value:?} contains a NUL byte: expected {expected}")]
    Nul {
        /// The value (escaped when printed).
        value: String,
        /// What was expected.
        expected: &'static str,
    },
    /// An absolute path (or a Windows prefix).
    #[error("{value:?} is an absolute path: expected a path relative to {}", root.display())]
    Absolute {
        /// The value.
        value: String,
        /// The folder it must stay in.
        root: PathBuf,
    },
    /// A `..` component.
    #[error("{value:?} has a \"..\" component: expected a path inside {}", root.display())]
    ParentDir {
        /// The value.
        value: String,
        /// The folder it must stay in.
        root: PathBuf,
    },
    /// Not a plain name (one path component of allowed characters).
    #[error("{value:?} is not a plain name: expected {expected}")]
    NotAName {
        /// The value.
        value: String,
        /// What was expected.
        expected: &'static str,
    },
    /// The path (or the root) could not be resolved: missing, or a dangling link.
    #[error("{value:?} ({}): {source}", path.display())]
    Unresolved {
        /// The value.
        value: String,
        /// The path that was resolved.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Resolves (through a symbolic link) outside the root.
    #[error(
        "{value:?} resolves to {}, outside {} (through a symbolic link): expected a file inside it",
        resolved.display(),
        root.display()
    )]
    Outside {
        /// The value.
        value: String,
        /// Where it resolves.
        resolved: PathBuf,
        /// The canonical root.
        root: PathBuf,
    },
    /// Not a regular file.
    #[error("{value:?} ({}) is a {kind}: expected a regular file", resolved.display())]
    NotRegular {
        /// The value.
        value: String,
        /// Where it resolves.
        resolved: PathBuf,
        /// What it is ("folder", "FIFO", "character device", ...).
        kind: &'static str,
    },
    /// Larger than the stated maximum.
    #[error("{value:?} ({}) is {len} bytes: expected at most {max} bytes", resolved.display())]
    TooLarge {
        /// The value.
        value: String,
        /// Where it resolves.
        resolved: PathBuf,
        /// Its length.
        len: u64,
        /// The maximum.
        max: u64,
    },
}

impl Refusal {
    /// Whether the path does not exist (or is a dangling link): the one
    /// refusal a reader with a fallback location may pass over.
    pub fn is_missing(&self) -> bool {
        matches!(self, Self::Unresolved { source, .. }
            if source.kind() == std::io::ErrorKind::NotFound)
    }
}

/// What [`check_name`] accepts.
const NAME: &str = "a plain name (letters, digits, '.', '-', '_', ' ', ':'; not \".\" or \"..\")";

/// Checks that `value` is a plain name that can stand for one path
/// component: not empty, not `.` or `..`, no `/`, `\` or NUL, no control
/// character.
pub fn check_name(value: &str) -> Result<(), Refusal> {
    if value.is_empty() {
        return Err(Refusal::Empty { expected: NAME });
    }
    if value.contains('\0') {
        return Err(Refusal::Nul {
            value: value.to_owned(),
            expected: NAME,
        });
    }
    let ok = value != "."
        && value != ".."
        && value
            .chars()
            .all(|c| c.is_alphanumeric() || matches!(c, '.' | '-' | '_' | ' ' | ':'));
    if ok {
        Ok(())
    } else {
        Err(Refusal::NotAName {
            value: value.to_owned(),
            expected: NAME,
        })
    }
}

/// Checks `value` without touching the file system: a non-empty relative
/// path of plain components (`.` components allowed), no `..`, no NUL.
/// `root` is only named in the refusal.
pub fn check_relative(root: &Path, value: &str) -> Result<(), Refusal> {
    const REL: &str = "a relative path inside the dataset";
    if value.is_empty() {
        return Err(Refusal::Empty { expected: REL });
    }
    if value.contains('\0') {
        return Err(Refusal::Nul {
            value: value.to_owned(),
            expected: REL,
        });
    }
    for c in Path::new(value).components() {
        match c {
            Component::Normal(_) | Component::CurDir => {}
            Component::ParentDir => {
                return Err(Refusal::ParentDir {
                    value: value.to_owned(),
                    root: root.to_path_buf(),
                })
            }
            Component::RootDir | Component::Prefix(_) => {
                return Err(Refusal::Absolute {
                    value: value.to_owned(),
                    root: root.to_path_buf(),
                })
            }
        }
    }
    Ok(())
}

/// The regular file that `value` (a relative path read from metadata)
/// names under `root`: checked by [`check_relative`], then resolved
/// (symbolic links followed) and required to lie inside the canonical
/// `root`, to be a regular file and to hold at most `max_bytes` bytes.
///
/// Returns `root.join(value)`, the path as named (so messages show the
/// dataset's own layout); the file is not opened. A link swapped between
/// this check and the caller's open is not caught.
pub fn confined_file(root: &Path, value: &str, max_bytes: u64) -> Result<PathBuf, Refusal> {
    check_relative(root, value)?;
    let path = root.join(value);
    let canonical_root = root.canonicalize().map_err(|source| Refusal::Unresolved {
        value: value.to_owned(),
        path: root.to_path_buf(),
        source,
    })?;
    let resolved = path.canonicalize().map_err(|source| Refusal::Unresolved {
        value: value.to_owned(),
        path: path.clone(),
        source,
    })?;
    if !resolved.starts_with(&canonical_root) {
        return Err(Refusal::Outside {
            value: value.to_owned(),
            resolved,
            root: canonical_root,
        });
    }
    let meta = std::fs::metadata(&resolved).map_err(|source| Refusal::Unresolved {
        value: value.to_owned(),
        path: resolved.clone(),
        source,
    })?;
    let kind = file_kind(&meta.file_type());
    if kind != "regular file" {
        return Err(Refusal::NotRegular {
            value: value.to_owned(),
            resolved,
            kind,
        });
    }
    if meta.len() > max_bytes {
        return Err(Refusal::TooLarge {
            value: value.to_owned(),
            resolved,
            len: meta.len(),
            max: max_bytes,
        });
    }
    Ok(path)
}

/// [`confined_file`] for a `path` that should already lie under `root`
/// (one built earlier by joining a checked value to `root`): the part after
/// `root` is checked. A path not under `root` is refused as absolute.
pub fn confined_under(root: &Path, path: &Path, max_bytes: u64) -> Result<PathBuf, Refusal> {
    match path.strip_prefix(root) {
        Ok(rel) => confined_file(root, &rel.to_string_lossy(), max_bytes),
        Err(_) => Err(Refusal::Absolute {
            value: path.to_string_lossy().into_owned(),
            root: root.to_path_buf(),
        }),
    }
}

/// Checks a path the user gave (not confined to any folder; symbolic
/// links followed) without opening it: it must be a regular file (not a
/// FIFO, which would block the open, a device such as `/dev/zero`, which
/// would never end, a socket or a folder) of at most `max_bytes` bytes.
pub fn regular_file(path: &Path, max_bytes: u64) -> Result<(), Refusal> {
    let value = path.to_string_lossy().into_owned();
    let meta = std::fs::metadata(path).map_err(|source| Refusal::Unresolved {
        value: value.clone(),
        path: path.to_path_buf(),
        source,
    })?;
    let kind = file_kind(&meta.file_type());
    if kind != "regular file" {
        return Err(Refusal::NotRegular {
            value,
            resolved: path.to_path_buf(),
            kind,
        });
    }
    if meta.len() > max_bytes {
        return Err(Refusal::TooLarge {
            value,
            resolved: path.to_path_buf(),
            len: meta.len(),
            max: max_bytes,
        });
    }
    Ok(())
}

/// What a file type is, in words.
fn file_kind(t: &std::fs::FileType) -> &'static str {
    if t.is_file() {
        return "regular file";
    }
    if t.is_dir() {
        return "folder";
    }
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return "FIFO (named pipe)";
        }
        if t.is_char_device() {
            return "character device";
        }
        if t.is_block_device() {
            return "block device";
        }
        if t.is_socket() {
            return "socket";
        }
    }
    "special file"
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A root folder with `a/clip.mp4` (5 bytes) and, beside the root, a
    /// secret file outside it.
    fn layout() -> (tempfile::TempDir, PathBuf) {
        let tmp = tempfile::tempdir().unwrap();
        let root = tmp.path().join("root");
        std::fs::create_dir_all(root.join("a")).unwrap();
        std::fs::write(root.join("a/clip.mp4"), b"12345").unwrap();
        std::fs::write(tmp.path().join("secret.txt"), b"TOP-SECRET-CONTENT").unwrap();
        (tmp, root)
    }

    #[test]
    fn a_relative_regular_file_inside_is_accepted() {
        let (_tmp, root) = layout();
        assert_eq!(
            confined_file(&root, "a/clip.mp4", 5).unwrap(),
            root.join("a/clip.mp4")
        );
        assert_eq!(
            confined_file(&root, "./a/clip.mp4", 5).unwrap(),
            root.join("./a/clip.mp4")
        );
        // A link that stays inside the root is fine.
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink("a/clip.mp4", root.join("inside.mp4")).unwrap();
            assert!(confined_file(&root, "inside.mp4", 5).is_ok());
        }
        assert!(confined_under(&root, &root.join("a/clip.mp4"), 5).is_ok());
    }

    #[test]
    fn absolute_and_parent_paths_are_refused() {
        let (tmp, root) = layout();
        let secret = tmp.path().join("secret.txt");
        let e = confined_file(&root, &secret.to_string_lossy(), u64::MAX).unwrap_err();
        assert!(matches!(e, Refusal::Absolute { .. }), "{e}");
        assert!(e.to_string().contains("absolute"), "{e}");
        let e = confined_file(&root, "../secret.txt", u64::MAX).unwrap_err();
        assert!(matches!(e, Refusal::ParentDir { .. }), "{e}");
        let e = confined_file(&root, "a/../../secret.txt", u64::MAX).unwrap_err();
        assert!(matches!(e, Refusal::ParentDir { .. }), "{e}");
        for e in [
            confined_file(&root, "", 9).unwrap_err(),
            confined_file(&root, "a\0b", 9).unwrap_err(),
        ] {
            assert!(
                matches!(e, Refusal::Empty { .. } | Refusal::Nul { .. }),
                "{e}"
            );
        }
        let e = confined_under(&root, &secret, u64::MAX).unwrap_err();
        assert!(matches!(e, Refusal::Absolute { .. }), "{e}");
    }

    #[cfg(unix)]
    #[test]
    fn a_symlink_out_of_the_root_is_refused_without_reading_it() {
        let (tmp, root) = layout();
        std::os::unix::fs::symlink(tmp.path().join("secret.txt"), root.join("a/link.mp4")).unwrap();
        let e = confined_file(&root, "a/link.mp4", u64::MAX).unwrap_err();
        assert!(matches!(e, Refusal::Outside { .. }), "{e}");
        assert!(!e.to_string().contains("TOP-SECRET"), "{e}");
        // A linked folder out of the root, too.
        std::os::unix::fs::symlink(tmp.path(), root.join("up")).unwrap();
        let e = confined_file(&root, "up/secret.txt", u64::MAX).unwrap_err();
        assert!(matches!(e, Refusal::Outside { .. }), "{e}");
        // A dangling link is missing, not outside.
        std::os::unix::fs::symlink(root.join("nowhere"), root.join("dangling.mp4")).unwrap();
        let e = confined_file(&root, "dangling.mp4", u64::MAX).unwrap_err();
        assert!(e.is_missing(), "{e}");
    }

    #[cfg(unix)]
    #[test]
    fn a_fifo_is_refused_without_opening_it() {
        let (_tmp, root) = layout();
        let fifo = root.join("a/pipe.mp4");
        let status = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap();
        assert!(status.success());
        // Opening a FIFO with no writer blocks: returning at all shows it was not opened.
        let e = confined_file(&root, "a/pipe.mp4", u64::MAX).unwrap_err();
        assert!(
            matches!(e, Refusal::NotRegular { kind, .. } if kind.starts_with("FIFO")),
            "{e}"
        );
    }

    #[test]
    fn folders_missing_files_and_large_files_are_refused() {
        let (_tmp, root) = layout();
        let e = confined_file(&root, "a", u64::MAX).unwrap_err();
        assert!(
            matches!(e, Refusal::NotRegular { kind: "folder", .. }),
            "{e}"
        );
        let e = confined_file(&root, "a/none.mp4", u64::MAX).unwrap_err();
        assert!(e.is_missing(), "{e}");
        let e = confined_file(&root, "a/clip.mp4", 4).unwrap_err();
        assert!(matches!(e, Refusal::TooLarge { len: 5, max: 4, .. }), "{e}");
        assert!(e.to_string().contains("at most 4 bytes"), "{e}");
    }

    #[cfg(unix)]
    #[test]
    fn a_user_path_must_be_a_bounded_regular_file() {
        let (_tmp, root) = layout();
        assert!(regular_file(&root.join("a/clip.mp4"), 5).is_ok());
        let e = regular_file(&root.join("a/clip.mp4"), 4).unwrap_err();
        assert!(matches!(e, Refusal::TooLarge { len: 5, .. }), "{e}");
        let e = regular_file(Path::new("/dev/zero"), u64::MAX).unwrap_err();
        assert!(
            matches!(
                e,
                Refusal::NotRegular {
                    kind: "character device",
                    ..
                }
            ),
            "{e}"
        );
        let fifo = root.join("pipe.json");
        let status = std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap();
        assert!(status.success());
        let e = regular_file(&fifo, u64::MAX).unwrap_err();
        assert!(e.to_string().contains("FIFO"), "{e}");
        let e = regular_file(&root.join("none.json"), u64::MAX).unwrap_err();
        assert!(e.is_missing(), "{e}");
    }

    #[test]
    fn plain_names() {
        for ok in [
            "observation.images.top",
            "22008760",
            "cam_high",
            "Fri_Jul__7_09:42",
        ] {
            assert!(check_name(ok).is_ok(), "{ok}");
        }
        for bad in ["", ".", "..", "a/b", "../x", "a\\b", "a\0b", "/etc", "a\nb"] {
            assert!(check_name(bad).is_err(), "{bad:?}");
        }
    }
}
