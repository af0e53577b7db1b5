//! The files of a LeRobot dataset at fixed places (`meta/info.json`,
//! `meta/tasks.parquet`, the episode index, calibration, masks, labels):
//! each checked before it is opened to be a regular file of bounded size
//! that lies, symbolic links followed, inside the dataset's root. A FIFO is
//! refused without being opened (opening it would block), a device such as
//! `/dev/zero` without being read (the read would never end), a link out of
//! the root without its target being read. The error names the path.

use super::error::{io_err, meta_err};
use super::DatasetError;
use bridgev2w_io::confine::{self, Refusal};
use std::path::{Path, PathBuf};

/// A refusal of the file `rel` under `root` as a dataset error: a missing
/// file is the I/O error opening it would give; anything else names the
/// path and why.
fn refused(root: &Path, rel: &str, e: Refusal) -> DatasetError {
    match e {
        Refusal::Unresolved { path, source, .. }
            if source.kind() == std::io::ErrorKind::NotFound =>
        {
            DatasetError::Io { path, source }
        }
        e => meta_err(&root.join(rel), e.to_string()),
    }
}

/// `root/rel`, a file the dataset must have, checked (see the module
/// documentation) to hold at most `max_bytes`.
pub(super) fn required(root: &Path, rel: &str, max_bytes: u64) -> Result<PathBuf, DatasetError> {
    confine::confined_file(root, rel, max_bytes).map_err(|e| refused(root, rel, e))
}

/// `root/rel` when something is there (a dangling link counts as nothing),
/// checked like [`required`]; `None` when nothing is.
pub(super) fn optional(
    root: &Path,
    rel: &str,
    max_bytes: u64,
) -> Result<Option<PathBuf>, DatasetError> {
    match confine::confined_file(root, rel, max_bytes) {
        Ok(p) => Ok(Some(p)),
        Err(e) if e.is_missing() => Ok(None),
        Err(e) => Err(refused(root, rel, e)),
    }
}

/// The folder `root/rel`, resolved (links followed) inside the canonical
/// `root`; a folder that resolves outside is refused naming both.
fn inside_folder(root: &Path, canonical_root: &Path, rel: &str) -> Result<PathBuf, DatasetError> {
    let path = root.join(rel);
    let resolved = path.canonicalize().map_err(io_err(&path))?;
    if !resolved.starts_with(canonical_root) {
        return Err(meta_err(
            &path,
            format!(
                "resolves to {}, outside the dataset {} (through a symbolic link): expected a folder inside it",
                resolved.display(),
                canonical_root.display()
            ),
        ));
    }
    Ok(path)
}

/// The v3.0 episode index files, `meta/episodes/chunk-*/file-*.parquet`
/// (every `*.parquet` in every folder of `meta/episodes`), sorted. The
/// folders must resolve inside the root, each file must pass [`required`]
/// with at most [`confine::MAX_DATA_BYTES`]; entries that are neither
/// folders nor `*.parquet` names are passed over without being opened.
pub(super) fn episode_index_files(root: &Path) -> Result<Vec<PathBuf>, DatasetError> {
    let canonical_root = root.canonicalize().map_err(io_err(root))?;
    let dir = inside_folder(root, &canonical_root, "meta/episodes")?;
    let mut files = Vec::new();
    for chunk in std::fs::read_dir(&dir).map_err(io_err(&dir))? {
        let chunk = chunk.map_err(io_err(&dir))?;
        // `is_dir` follows links: a linked folder is checked below.
        if !chunk.path().is_dir() {
            continue;
        }
        let chunk_rel = format!("meta/episodes/{}", chunk.file_name().to_string_lossy());
        let chunk_dir = inside_folder(root, &canonical_root, &chunk_rel)?;
        for f in std::fs::read_dir(&chunk_dir).map_err(io_err(&chunk_dir))? {
            let name = f.map_err(io_err(&chunk_dir))?.file_name();
            let name = name.to_string_lossy();
            if Path::new(&*name)
                .extension()
                .is_some_and(|e| e == "parquet")
            {
                let rel = format!("{chunk_rel}/{name}");
                files.push(required(root, &rel, confine::MAX_DATA_BYTES)?);
            }
        }
    }
    files.sort();
    if files.is_empty() {
        return Err(meta_err(
            &dir,
            "no episode parquet files (meta/episodes/chunk-*/file-*.parquet)",
        ));
    }
    Ok(files)
}
