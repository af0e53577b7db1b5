//! Where the real robot episodes for tests and experiments are:
//! `../shared/realdata/` beside the repository (see its README; nothing of
//! it is copied into the repository). Tests that read it skip, with a
//! message, where it is absent.

use std::path::{Path, PathBuf};

/// `../shared/realdata/<sub>` seen from a crate's `CARGO_MANIFEST_DIR`
/// (`crates/<name>`), or `None` after printing that it is absent.
pub fn dir(manifest_dir: &str, sub: &str) -> Option<PathBuf> {
    let p = Path::new(manifest_dir)
        .join("../../../shared/realdata")
        .join(sub);
    if p.is_dir() {
        Some(p)
    } else {
        eprintln!(
            "skipped: {} is absent (real episodes, see the project's data guide)",
            p.display()
        );
        None
    }
}
