//! One markdown results file (`docs/results.md`), several commands: each
//! report command owns one section (between `<!-- section: NAME -->` and
//! `<!-- end section: NAME -->`) and replaces only that section, so the
//! video-prediction and the planning reports can be rerun independently.

use crate::{atomic::write_atomic_creating_dirs, FileError, Result};
use std::path::Path;

/// The first lines of a results file that does not exist yet.
const HEADER: &str = "# Results\n\nEach section below is written by the command it names; rerunning a command replaces only its own section.\n";

/// What a section name may hold.
pub const SECTION_NAME_EXPECTED: &str = "expected a name of letters, digits, - and _";

/// Whether `name` is a valid section name: letters, digits, `-` and `_`
/// (see [`SECTION_NAME_EXPECTED`]).
pub fn is_section_name(name: &str) -> bool {
    !name.is_empty()
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
}

/// Replaces (or appends) section `name` of the markdown file `path` with
/// `body`, keeping the rest of the file; written atomically.
pub fn write_section(path: &Path, name: &str, body: &str) -> Result<()> {
    if !is_section_name(name) {
        return Err(FileError::format(
            path,
            format!("section {name:?}: {SECTION_NAME_EXPECTED}"),
        ));
    }
    let begin = format!("<!-- section: {name} -->");
    let end = format!("<!-- end section: {name} -->");
    let old = match std::fs::read_to_string(path) {
        Ok(s) => s,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => HEADER.to_string(),
        Err(e) => return Err(FileError::io(path, e)),
    };
    let block = format!("{begin}\n{}\n{end}", body.trim_end());
    let new = match (old.find(&begin), old.find(&end)) {
        (Some(b), Some(e)) if e > b => {
            format!("{}{block}{}", &old[..b], &old[e + end.len()..])
        }
        (None, None) => format!("{}\n{block}\n", old.trim_end()),
        _ => {
            return Err(FileError::format(
                path,
                format!("section `{name}` has a broken marker pair ({begin} ... {end}); fix or delete the file"),
            ))
        }
    };
    write_atomic_creating_dirs(path, new.as_bytes())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn sections_are_replaced_in_place_and_others_kept() {
        let tmp = tempfile::tempdir().unwrap();
        let p = tmp.path().join("docs/results.md");
        write_section(&p, "video", "video v1").unwrap();
        write_section(&p, "planning", "plan v1").unwrap();
        write_section(&p, "video", "video v2\nline 2").unwrap();
        let s = std::fs::read_to_string(&p).unwrap();
        assert!(s.starts_with("# Results"), "{s}");
        assert!(
            s.contains("video v2\nline 2") && !s.contains("video v1"),
            "{s}"
        );
        assert!(s.contains("plan v1"), "{s}");
        assert!(s.find("video v2").unwrap() < s.find("plan v1").unwrap());
        std::fs::write(&p, "<!-- end section: video --> <!-- section: video -->").unwrap();
        let e = write_section(&p, "video", "x").unwrap_err().to_string();
        assert!(
            e.contains("broken marker pair") && e.contains("results.md"),
            "{e}"
        );
        let e = write_section(&p, "a/b", "x").unwrap_err().to_string();
        assert!(e.contains("\"a/b\""), "{e}");
    }
}
