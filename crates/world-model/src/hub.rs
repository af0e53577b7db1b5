//! Hugging Face Hub names for model folders, resolved offline from the local
//! cache: `--model THUDM/CogVideoX-5b-I2V` finds the folder that
//! `huggingface_hub` downloaded (`snapshot_download`, `from_pretrained`,
//! `huggingface-cli download`), without a network.
//!
//! The cache layout (huggingface_hub's "cache system"):
//! `CACHE/models--OWNER--NAME/refs/REVISION` holds a commit hash, and
//! `CACHE/models--OWNER--NAME/snapshots/COMMIT/` the repository's files at
//! that commit. `CACHE` is `$HF_HUB_CACHE`, else `$HF_HOME/hub`, else
//! `$XDG_CACHE_HOME/huggingface/hub`, else `~/.cache/huggingface/hub`
//! (`$HUGGINGFACE_HUB_CACHE`, the older name, is read too).
//!
//! A local folder always wins: a name is looked up in the cache only when no
//! folder of that path exists.

use crate::error::WorldModelError;
use bridgev2w_io::confine;
use std::path::{Path, PathBuf};

/// A Hub repository name, `OWNER/NAME`, with an optional `@REVISION`
/// (a branch, tag or commit; default `main`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HubName {
    /// `OWNER/NAME`.
    pub repo: String,
    /// Branch, tag or commit hash.
    pub revision: String,
}

impl HubName {
    /// `text` as a Hub name, if it has that form: two non-empty parts of
    /// letters, digits, `-`, `_` and `.` around one `/` (not starting with
    /// `.`), and an optional `@REVISION`.
    pub fn parse(text: &str) -> Option<Self> {
        let (repo, revision) = match text.split_once('@') {
            Some((r, rev)) if !rev.is_empty() => (r, rev.to_owned()),
            Some(_) => return None,
            None => (text, "main".to_owned()),
        };
        let (owner, name) = repo.split_once('/')?;
        let part = |p: &str| {
            !p.is_empty()
                && !p.starts_with('.')
                && p.chars()
                    .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        };
        (part(owner) && part(name)).then(|| Self {
            repo: repo.to_owned(),
            revision,
        })
    }

    /// Checks the revision: a branch, tag or commit name of letters,
    /// digits, `.`, `-` and `_`, in `/`-separated parts (a branch such as
    /// `pr/1`), none empty, `.` or `..`; so it can only name a file under the
    /// repository's `refs/` folder. The error says what was expected.
    pub fn check_revision(&self) -> Result<(), String> {
        const EXPECTED: &str = "expected a branch, tag or commit: letters, digits, '.', '-', '_', \
             in parts separated by '/' (none empty, \".\" or \"..\")";
        let rev = &self.revision;
        let plain = |p: &str| {
            !p.is_empty()
                && p != "."
                && p != ".."
                && p.chars()
                    .all(|c| c.is_ascii_alphanumeric() || matches!(c, '-' | '_' | '.'))
        };
        if rev.split('/').all(plain) {
            Ok(())
        } else {
            Err(format!("revision {rev:?}: {EXPECTED}"))
        }
    }

    /// The repository's folder name in the cache: `models--OWNER--NAME`.
    pub fn cache_folder(&self) -> String {
        format!("models--{}", self.repo.replace('/', "--"))
    }
}

/// The Hub cache folder from the environment (`var` reads a variable), as
/// huggingface_hub computes it.
pub fn hub_cache_dir(var: &dyn Fn(&str) -> Option<String>) -> Option<PathBuf> {
    let set = |name: &str| var(name).filter(|v| !v.is_empty()).map(PathBuf::from);
    if let Some(d) = set("HF_HUB_CACHE").or_else(|| set("HUGGINGFACE_HUB_CACHE")) {
        return Some(d);
    }
    if let Some(home) = set("HF_HOME") {
        return Some(home.join("hub"));
    }
    if let Some(xdg) = set("XDG_CACHE_HOME") {
        return Some(xdg.join("huggingface").join("hub"));
    }
    set("HOME").map(|h| h.join(".cache").join("huggingface").join("hub"))
}

/// `dir` itself when it is a folder, else the cached snapshot of the Hub
/// name it spells (see the module comment); the error lists every place
/// looked at.
pub fn resolve_model_dir(dir: &Path) -> Result<PathBuf, WorldModelError> {
    resolve_with(dir, &|name| std::env::var(name).ok())
}

/// [`resolve_model_dir`] with the environment given (for tests).
pub fn resolve_with(
    dir: &Path,
    var: &dyn Fn(&str) -> Option<String>,
) -> Result<PathBuf, WorldModelError> {
    if dir.is_dir() {
        return Ok(dir.to_path_buf());
    }
    let text = dir.to_string_lossy();
    let mut looked = vec![format!("{}: no such local folder", dir.display())];
    let not_found = |looked: Vec<String>| WorldModelError::ModelNotFound {
        name: text.to_string(),
        looked,
    };
    let Some(hub) = HubName::parse(&text) else {
        return Err(not_found(looked));
    };
    let refused = |message: String| WorldModelError::ModelName {
        name: text.to_string(),
        message,
    };
    hub.check_revision().map_err(refused)?;
    let Some(cache) = hub_cache_dir(var) else {
        looked.push(
            "the Hugging Face cache: none of HF_HUB_CACHE, HF_HOME, XDG_CACHE_HOME, HOME is set"
                .into(),
        );
        return Err(not_found(looked));
    };
    let repo_dir = cache.join(hub.cache_folder());
    if !repo_dir.is_dir() {
        looked.push(format!("{}: not in the cache", repo_dir.display()));
        return Err(not_found(looked));
    }
    let snapshots = repo_dir.join("snapshots");
    let is_commit = is_commit_hash(&hub.revision);
    let commit = if is_commit {
        hub.revision.clone()
    } else {
        // The revision names a file under refs/ (checked above), which must
        // be a small regular file inside it: no link out, no FIFO.
        let refs_dir = repo_dir.join("refs");
        let refs = refs_dir.join(&hub.revision);
        let file = match confine::confined_file(&refs_dir, &hub.revision, MAX_REF_BYTES) {
            Ok(file) => file,
            Err(e) if e.is_missing() => {
                looked.push(format!(
                    "{}: no such revision file (revision `{}`)",
                    refs.display(),
                    hub.revision
                ));
                return Err(not_found(looked));
            }
            Err(e) => {
                return Err(refused(format!(
                    "revision file under {}: {e}",
                    refs_dir.display()
                )))
            }
        };
        let hash = std::fs::read_to_string(&file)
            .map_err(|e| refused(format!("reading {}: {e}", file.display())))?;
        let hash = hash.trim();
        // Its content is not printed: only a commit hash is accepted.
        if !is_commit_hash(hash) {
            return Err(refused(format!(
                "{} does not hold a commit hash: expected 40 hex digits",
                file.display()
            )));
        }
        hash.to_owned()
    };
    let snapshot = snapshots.join(&commit);
    if !snapshot.is_dir() {
        looked.push(format!(
            "{}: the revision's snapshot is missing",
            snapshot.display()
        ));
        return Err(not_found(looked));
    }
    // The snapshot folder, links followed, stays inside the repository's
    // snapshots/ folder.
    let inside = |p: &Path| {
        p.canonicalize()
            .map_err(|e| refused(format!("resolving {}: {e}", p.display())))
    };
    let (root, resolved) = (inside(&snapshots)?, inside(&snapshot)?);
    if !resolved.starts_with(&root) || resolved == root {
        return Err(refused(format!(
            "the snapshot {} resolves to {}, outside {} (through a symbolic link): \
             expected a folder inside it",
            snapshot.display(),
            resolved.display(),
            root.display()
        )));
    }
    Ok(snapshot)
}

/// The largest `refs/REVISION` file read (it holds one commit hash).
const MAX_REF_BYTES: u64 = 1024;

fn is_commit_hash(s: &str) -> bool {
    s.len() == 40 && s.chars().all(|c| c.is_ascii_hexdigit())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn hub_names_parse_and_paths_do_not() {
        let n = HubName::parse("THUDM/CogVideoX-5b-I2V").unwrap();
        assert_eq!(
            (n.repo.as_str(), n.revision.as_str()),
            ("THUDM/CogVideoX-5b-I2V", "main")
        );
        assert_eq!(n.cache_folder(), "models--THUDM--CogVideoX-5b-I2V");
        assert_eq!(HubName::parse("a/b@v1.0").unwrap().revision, "v1.0");
        for not in [
            "assets/demo-model/backbone",
            "/abs/path",
            "./a/b",
            "a",
            "a/",
            "../x",
            "a/b c",
        ] {
            assert_eq!(HubName::parse(not), None, "{not}");
        }
    }

    #[test]
    fn revisions_are_names_not_paths() {
        let rev = |r: &str| {
            HubName::parse(&format!("a/b@{r}"))
                .unwrap()
                .check_revision()
        };
        for ok in [
            "main",
            "v1.0",
            "pr/1",
            "refs-x_y",
            "0123456789abcdef0123456789abcdef01234567",
        ] {
            rev(ok).unwrap();
        }
        for bad in [
            "..",
            "../x",
            "a/../../b",
            "/etc/passwd",
            "a//b",
            "a/",
            ".",
            "a\0b",
            "a\\b",
            "a b",
        ] {
            let e = rev(bad).unwrap_err();
            assert!(
                e.contains(&format!("{bad:?}")) && e.contains("expected"),
                "{bad:?}: {e}"
            );
        }
    }

    #[test]
    fn the_cache_follows_huggingface_hub() {
        let env = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| {
                pairs
                    .iter()
                    .find(|(n, _)| *n == k)
                    .map(|(_, v)| v.to_string())
            }
        };
        assert_eq!(
            hub_cache_dir(&env(&[("HF_HUB_CACHE", "/c"), ("HF_HOME", "/h")])),
            Some(PathBuf::from("/c"))
        );
        assert_eq!(
            hub_cache_dir(&env(&[("HF_HOME", "/h")])),
            Some(PathBuf::from("/h/hub"))
        );
        assert_eq!(
            hub_cache_dir(&env(&[("XDG_CACHE_HOME", "/x"), ("HOME", "/u")])),
            Some(PathBuf::from("/x/huggingface/hub"))
        );
        assert_eq!(
            hub_cache_dir(&env(&[("HOME", "/u")])),
            Some(PathBuf::from("/u/.cache/huggingface/hub"))
        );
    }

    #[test]
    fn names_resolve_to_snapshots_and_misses_list_where_they_looked() {
        let tmp = tempfile::tempdir().unwrap();
        let cache = tmp.path().join("hub");
        let repo = cache.join("models--org--tiny");
        let commit = "0123456789abcdef0123456789abcdef01234567";
        std::fs::create_dir_all(repo.join("snapshots").join(commit)).unwrap();
        std::fs::create_dir_all(repo.join("refs")).unwrap();
        std::fs::write(repo.join("refs/main"), format!("{commit}\n")).unwrap();
        let cache_s = cache.display().to_string();
        let var = move |k: &str| (k == "HF_HUB_CACHE").then(|| cache_s.clone());
        let got = resolve_with(Path::new("org/tiny"), &var).unwrap();
        assert_eq!(got, repo.join("snapshots").join(commit));
        let got = resolve_with(Path::new(&format!("org/tiny@{commit}")), &var).unwrap();
        assert_eq!(got, repo.join("snapshots").join(commit));
        let e = resolve_with(Path::new("org/tiny@v2"), &var)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("refs/v2") && e.contains("org/tiny@v2: no such local folder"),
            "{e}"
        );
        let e = resolve_with(Path::new("org/other"), &var)
            .unwrap_err()
            .to_string();
        assert!(e.contains("models--org--other: not in the cache"), "{e}");
        std::fs::write(
            repo.join("refs/main"),
            "ffffffffffffffffffffffffffffffffffffffff",
        )
        .unwrap();
        let e = resolve_with(Path::new("org/tiny"), &var)
            .unwrap_err()
            .to_string();
        assert!(e.contains("snapshot is missing"), "{e}");
        // A local folder wins over the cache.
        let local = tmp.path().join("org/tiny");
        std::fs::create_dir_all(&local).unwrap();
        assert_eq!(resolve_with(&local, &var).unwrap(), local);
    }
}
