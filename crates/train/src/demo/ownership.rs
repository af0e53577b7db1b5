//! Which existing `--out` folder the demo may replace without `--overwrite`:
//! only an earlier demo's output, known by the marker file [`DEMO_MARKER`]
//! every demo writes into it, holding nothing but what a demo writes
//! ([`DEMO_FILES`], `frames/NNNNNN.png`). A folder that merely contains some
//! of those names, or a demo's output the user added a file to, is not
//! replaced: replacing it would delete the user's files (issue 69).

use super::DemoError;
use std::path::Path;

/// The marker file in a demo's output: the folder is the demo's own.
pub const DEMO_MARKER: &str = ".bridgev2w-demo";

/// The files a demo writes at the top of its output (the marker aside).
pub const DEMO_FILES: [&str; 12] = [
    "masks.npy",
    "labels.npy",
    "labels.json",
    "ik.json",
    "camera.json",
    "actions.json",
    "overlay.gif",
    "overlay.png",
    "prediction.mp4",
    "prediction.gif",
    "prediction-actions.json",
    "prediction-scores.json",
];

/// The folder of per-frame mask PNGs (`NNNNNN.png`) in a demo's output.
const FRAMES_DIR: &str = "frames";

/// Writes the marker into the output being built (`dir`).
pub(super) fn write_marker(dir: &Path) -> Result<(), DemoError> {
    let text = "This folder was written by `bridgev2w demo`; a later `bridgev2w demo --out` \
                of it replaces it as long as it holds nothing but the demo's files.\n";
    Ok(bridgev2w_io::atomic::write_atomic(
        &dir.join(DEMO_MARKER),
        text.as_bytes(),
    )?)
}

/// Why the existing `out` is not an earlier demo's output (`None`: it is
/// one, or `out` is absent or empty, so there is nothing of anyone's to
/// replace).
pub fn not_an_earlier_demo(out: &Path) -> Result<Option<String>, DemoError> {
    let io = |e: std::io::Error| DemoError::File(bridgev2w_io::FileError::io(out, e));
    match out.symlink_metadata() {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(io(e)),
        Ok(m) if !m.is_dir() => return Ok(Some("not a folder".to_owned())),
        Ok(_) => {}
    }
    let mut names = Vec::new();
    for entry in std::fs::read_dir(out).map_err(io)? {
        names.push(entry.map_err(io)?.file_name());
    }
    if names.is_empty() {
        return Ok(None);
    }
    if !is_file(&out.join(DEMO_MARKER)) {
        return Ok(Some(format!(
            "no {DEMO_MARKER} marker: not written by `bridgev2w demo`"
        )));
    }
    let mut foreign = Vec::new();
    for name in &names {
        let text = name.to_string_lossy();
        let path = out.join(name);
        let ours = if text == FRAMES_DIR {
            frames_only(&path)?
        } else {
            (text == DEMO_MARKER || DEMO_FILES.contains(&&*text)) && is_file(&path)
        };
        if !ours {
            foreign.push(text.into_owned());
        }
    }
    if foreign.is_empty() {
        return Ok(None);
    }
    foreign.sort();
    let shown: Vec<&str> = foreign.iter().take(5).map(String::as_str).collect();
    Ok(Some(format!(
        "it holds {} that a demo does not write ({}{})",
        if foreign.len() == 1 {
            "a file or folder"
        } else {
            "files or folders"
        },
        shown.join(", "),
        if foreign.len() > shown.len() {
            ", ..."
        } else {
            ""
        }
    )))
}

/// Refuses an existing `out` that is not an earlier demo's output, unless
/// `overwrite`.
pub(super) fn check_replaceable(out: &Path, overwrite: bool) -> Result<(), DemoError> {
    if overwrite {
        return Ok(());
    }
    match not_an_earlier_demo(out)? {
        None => Ok(()),
        Some(reason) => Err(DemoError::NotADemo {
            path: out.to_path_buf(),
            reason,
        }),
    }
}

/// A regular file (not a link).
fn is_file(path: &Path) -> bool {
    path.symlink_metadata().is_ok_and(|m| m.is_file())
}

/// Whether `dir` is a folder holding only frame PNGs `NNNNNN.png`.
fn frames_only(dir: &Path) -> Result<bool, DemoError> {
    if !dir.symlink_metadata().is_ok_and(|m| m.is_dir()) {
        return Ok(false);
    }
    let io = |e: std::io::Error| DemoError::File(bridgev2w_io::FileError::io(dir, e));
    for entry in std::fs::read_dir(dir).map_err(io)? {
        let entry = entry.map_err(io)?;
        let name = entry.file_name();
        let frame = name
            .to_str()
            .and_then(|n| n.strip_suffix(".png"))
            .is_some_and(|stem| stem.len() == 6 && stem.bytes().all(|b| b.is_ascii_digit()));
        if !frame || !is_file(&entry.path()) {
            return Ok(false);
        }
    }
    Ok(true)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A folder with every file a demo writes, and the marker if `marked`.
    fn demo_like(dir: &Path, marked: bool) {
        std::fs::create_dir_all(dir.join(FRAMES_DIR)).unwrap();
        std::fs::write(dir.join("frames/000000.png"), "png").unwrap();
        for f in DEMO_FILES {
            std::fs::write(dir.join(f), f).unwrap();
        }
        if marked {
            write_marker(dir).unwrap();
        }
    }

    #[test]
    fn only_a_marked_folder_of_demo_files_is_an_earlier_demo() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("out");
        assert_eq!(not_an_earlier_demo(&out).unwrap(), None, "absent");
        std::fs::create_dir(&out).unwrap();
        assert_eq!(not_an_earlier_demo(&out).unwrap(), None, "empty");
        demo_like(&out, true);
        assert_eq!(not_an_earlier_demo(&out).unwrap(), None);
        check_replaceable(&out, false).unwrap();
        // The recognised names alone, without the marker: not a demo.
        let unmarked = tmp.path().join("unmarked");
        demo_like(&unmarked, false);
        let e = check_replaceable(&unmarked, false).unwrap_err().to_string();
        assert!(
            e.contains(&*unmarked.to_string_lossy())
                && e.contains(DEMO_MARKER)
                && e.contains("--overwrite"),
            "{e}"
        );
        check_replaceable(&unmarked, true).unwrap();
        // A user's file beside the demo's, or among its frames.
        std::fs::write(out.join("notes.txt"), "mine").unwrap();
        let e = check_replaceable(&out, false).unwrap_err().to_string();
        assert!(e.contains("notes.txt") && e.contains("--overwrite"), "{e}");
        std::fs::remove_file(out.join("notes.txt")).unwrap();
        std::fs::write(out.join("frames/keep.png"), "mine").unwrap();
        let e = check_replaceable(&out, false).unwrap_err().to_string();
        assert!(e.contains("frames"), "{e}");
        std::fs::remove_file(out.join("frames/keep.png")).unwrap();
        // A demo file name that is a folder is not the demo's file.
        std::fs::remove_file(out.join("ik.json")).unwrap();
        std::fs::create_dir(out.join("ik.json")).unwrap();
        let e = check_replaceable(&out, false).unwrap_err().to_string();
        assert!(e.contains("ik.json"), "{e}");
        // A file in the way is no demo either.
        std::fs::write(tmp.path().join("file"), "f").unwrap();
        let e = check_replaceable(&tmp.path().join("file"), false).unwrap_err();
        assert!(e.to_string().contains("not a folder"), "{e}");
    }
}
