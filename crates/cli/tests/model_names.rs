//! A Hugging Face name given to `--model` (`OWNER/NAME@REVISION`) is not a
//! path (issue 69, item 2): a revision with `..` or an absolute path is
//! refused at the flag, and a cache entry that leads outside the
//! repository's folder (a `refs/` file or a snapshot linked elsewhere, a
//! `refs/` file that holds no commit hash) is refused naming `--model`. No
//! message shows the content of the file outside.

use std::path::Path;
use std::process::{Command, Output};

/// The content of the files outside the cache that no message may show.
const SECRET: &str = "SECRET-CONTENT-0123456789abcdef0123456789";

const COMMIT: &str = "4f1c2e0b9a8d7c6b5a4f3e2d1c0b9a8f7e6d5c4b";

/// `bridgev2w predict --model MODEL` against the cache `HF_HOME=d/hf`.
fn predict(d: &Path, model: &str, out: &str) -> Output {
    Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
        .env("HF_HOME", d.join("hf"))
        .env("RUST_BACKTRACE", "0")
        .env_remove("HF_HUB_CACHE")
        .env_remove("HUGGINGFACE_HUB_CACHE")
        .current_dir(d)
        .args([
            "predict",
            "--model",
            model,
            "--image",
            "first.png",
            "--masks",
            "masks.npy",
            "--out",
            out,
            "--steps",
            "1",
            "--device",
            "cpu",
        ])
        .output()
        .expect("run bridgev2w")
}

/// A cache folder `d/hf/hub/models--org--tiny` with `refs/` and `snapshots/`,
/// the inputs predict lists first, and secrets outside the cache.
fn layout(d: &Path) -> std::path::PathBuf {
    let repo = d.join("hf/hub/models--org--tiny");
    std::fs::create_dir_all(repo.join("refs")).expect("refs");
    std::fs::create_dir_all(repo.join("snapshots")).expect("snapshots");
    std::fs::write(d.join("first.png"), b"not read").expect("png");
    std::fs::write(d.join("masks.npy"), b"not read").expect("npy");
    // Where `refs/../../../secret` and `refs/../../../../secret` lead.
    std::fs::write(d.join("hf/secret"), SECRET).expect("secret");
    std::fs::write(d.join("secret"), SECRET).expect("secret");
    let outside = d.join("outside");
    std::fs::create_dir_all(&outside).expect("outside");
    std::fs::write(outside.join("model_index.json"), SECRET).expect("outside");
    repo
}

fn refused(o: &Output, what: &str) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(!o.status.success(), "{what}: accepted\n{err}");
    assert!(
        err.contains("--model"),
        "{what}: the flag is not named\n{err}"
    );
    assert!(
        !err.contains(SECRET),
        "{what}: printed the outside file\n{err}"
    );
    assert!(!err.contains("panicked"), "{what}: {err}");
    err
}

#[test]
fn a_revision_that_is_a_path_is_refused_at_the_flag() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    layout(d);
    for model in [
        "org/tiny@../../../secret",
        "org/tiny@../../../../secret",
        "org/tiny@main/../../../../secret",
        "org/tiny@/etc/passwd",
        "org/tiny@a//b",
        "org/tiny@v1@v2",
    ] {
        let err = refused(&predict(d, model, "out"), model);
        let rev = model.split_once('@').expect("a revision").1;
        assert!(
            err.contains(&format!("{rev:?}")) && err.contains("expected a branch, tag or commit"),
            "{model}: {err}"
        );
    }
    // A branch with '/' parts is a name, looked up under refs/.
    let o = predict(d, "org/tiny@pr/1", "out");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("refs/pr/1: no such revision file"),
        "{err}"
    );
}

#[test]
fn cache_entries_linked_out_of_the_repository_are_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let repo = layout(d);
    // A snapshot that is a link to a folder outside the cache.
    std::fs::write(repo.join("refs/main"), COMMIT).expect("refs/main");
    std::os::unix::fs::symlink(d.join("outside"), repo.join("snapshots").join(COMMIT))
        .expect("symlink");
    let err = refused(&predict(d, "org/tiny", "a"), "linked snapshot");
    assert!(
        err.contains("org/tiny") && err.contains("outside") && err.contains("symbolic link"),
        "{err}"
    );
    // A commit named directly, through the same link.
    let err = refused(
        &predict(d, &format!("org/tiny@{COMMIT}"), "b"),
        "linked commit",
    );
    assert!(err.contains("symbolic link"), "{err}");
    // A refs file that is a link to a file outside.
    std::os::unix::fs::symlink(d.join("secret"), repo.join("refs/v1")).expect("symlink");
    let err = refused(&predict(d, "org/tiny@v1", "c"), "linked refs file");
    assert!(err.contains("\"v1\"") && err.contains("outside"), "{err}");
    // A refs file that holds something other than a commit hash.
    std::fs::write(repo.join("refs/v2"), format!("../../../outside\n{SECRET}")).expect("v2");
    let err = refused(&predict(d, "org/tiny@v2", "e"), "refs file content");
    assert!(
        err.contains("does not hold a commit hash") && !err.contains("../../../outside"),
        "{err}"
    );
}
