//! The Python package (`python/`, PyO3 + maturin): `pip install ./python`
//! into a fresh venv (numpy from the project venv), then its tests
//! (`python/tests/test_bridgev2w.py`: masks and IK against `bridgev2w
//! masks`, `bw.synth.generate` and `bw.convert` against `bridgev2w synth`
//! and `convert`, predictions against `bridgev2w predict`, batches against
//! their single items, the GIL released, metrics against closed forms, bad
//! input as Python exceptions; `python/tests/test_rerun.py`: the Rerun
//! recordings of `bridgev2w.rerun` reloaded with the Rerun SDK), then the
//! Python guides' examples (`docs/guide/python.md`, `own-robot.md`,
//! `rerun.md`: every ```` ```sh ```` and ```` ```python ```` block, in order,
//! in a sandbox).
//! The wheel is built in the dev profile in the workspace's own target
//! folder, where `cargo test` has just built the libraries with the features
//! the module asks for (`the_module_resolves_the_test_builds_features`): only
//! PyO3 and the module itself are compiled for it. The venv sits at a fixed
//! path under the target folder, so that PyO3's build configuration (which
//! names the interpreter) stays the same from one run to the next.

use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common;

use common::ok;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .canonicalize()
        .expect("repo root")
}

/// The target folder this test was built in (the workspace's).
fn target_dir() -> PathBuf {
    Path::new(env!("CARGO_TARGET_TMPDIR"))
        .parent()
        .expect("target folder")
        .to_path_buf()
}

/// `cargo tree`'s `package features` lines, one per package and feature set.
fn resolved_features(args: &[&str]) -> std::collections::BTreeSet<String> {
    let cargo = std::env::var("CARGO").unwrap_or_else(|_| "cargo".into());
    let o = Command::new(cargo)
        .arg("tree")
        .args(args)
        .args(["--format", "{p} {f}", "--prefix", "none"])
        .current_dir(repo())
        .output()
        .expect("cargo tree");
    ok(&o);
    String::from_utf8_lossy(&o.stdout)
        .lines()
        .map(|l| l.trim_end_matches(" (*)").to_string())
        .collect()
}

/// Every package the module depends on resolves the same features alone
/// (what maturin builds) as in the whole workspace with its dev-dependencies
/// (what `cargo test --workspace` builds): else the module's build compiles
/// those packages, and everything above them, a second time.
#[test]
fn the_module_resolves_the_test_builds_features() {
    let module = resolved_features(&["-p", "bridgev2w-python", "-e", "normal,build"]);
    let workspace = resolved_features(&["--workspace"]);
    let drifted: Vec<&String> = module.difference(&workspace).collect();
    assert!(
        module.len() > 100 && drifted.is_empty(),
        "packages whose features differ between the module's build and the test build \
         (align them in crates/python/Cargo.toml): {drifted:#?}"
    );
}

#[test]
fn pip_install_python_then_its_tests_pass() {
    let project_python = repo().join(".venv/bin/python");
    assert!(
        project_python.is_file(),
        "{}: no project venv (scripts/setup-venv.sh)",
        project_python.display()
    );
    let dir = tempfile::tempdir().expect("tempdir");
    let venv = target_dir().join("tmp/python-package-venv");
    ok(&Command::new("python3")
        .args(["-m", "venv", "--clear"])
        .arg(&venv)
        .output()
        .expect("python3 -m venv"));
    // numpy (the package's one dependency) from the project venv.
    let site = Command::new(&project_python)
        .args([
            "-c",
            "import sysconfig; print(sysconfig.get_paths()['purelib'])",
        ])
        .output()
        .expect("project site-packages");
    ok(&site);
    let venv_site = Command::new(venv.join("bin/python"))
        .args([
            "-c",
            "import sysconfig; print(sysconfig.get_paths()['purelib'])",
        ])
        .output()
        .expect("venv site-packages");
    ok(&venv_site);
    let venv_site = PathBuf::from(String::from_utf8_lossy(&venv_site.stdout).trim());
    std::fs::write(
        venv_site.join("project-venv.pth"),
        String::from_utf8_lossy(&site.stdout).trim(),
    )
    .expect("pth");
    let install = Command::new(venv.join("bin/pip"))
        .args(["install", "--disable-pip-version-check", "-q"])
        .arg(repo().join("python"))
        .env("CARGO_TARGET_DIR", target_dir())
        .env("MATURIN_PEP517_ARGS", "--profile dev")
        .output()
        .expect("pip install ./python");
    ok(&install);
    let work = dir.path().join("work");
    std::fs::create_dir(&work).expect("mkdir");
    let raw = dir.path().join("raw");
    common::raw_fixtures(&raw);
    let o = Command::new(venv.join("bin/python"))
        .args(["-m", "pytest", "-q", "-p", "no:cacheprovider"])
        .arg(repo().join("python/tests/test_bridgev2w.py"))
        .arg(repo().join("python/tests/test_wandb_export.py"))
        .env("BRIDGEV2W_BIN", env!("CARGO_BIN_EXE_bridgev2w"))
        .env("BRIDGEV2W_TEST_WORK", &work)
        .env("BRIDGEV2W_TEST_RAW", &raw)
        .current_dir(dir.path())
        .output()
        .expect("run the package's tests with pytest");
    eprintln!("{}", String::from_utf8_lossy(&o.stdout));
    ok(&o);
    // bw.calibrate's test reads ../shared/realdata and skips where it is absent.
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(
        out.contains("20 passed") || out.contains("19 passed, 1 skipped"),
        "{out}"
    );
    // bridgev2w.rerun: its recordings reloaded with the Rerun SDK (rerun-sdk
    // from the project venv).
    let o = Command::new(venv.join("bin/python"))
        .args(["-m", "pytest", "-q", "-p", "no:cacheprovider"])
        .arg(repo().join("python/tests/test_rerun.py"))
        .env("BRIDGEV2W_BIN", env!("CARGO_BIN_EXE_bridgev2w"))
        .env("BRIDGEV2W_TEST_WORK", &work)
        .current_dir(dir.path())
        .output()
        .expect("run the Rerun recordings' tests with pytest");
    eprintln!("{}", String::from_utf8_lossy(&o.stdout));
    ok(&o);
    assert!(String::from_utf8_lossy(&o.stdout).contains("7 passed"));
    for guide in ["python.md", "own-robot.md", "rerun.md"] {
        run_guide(guide, &venv, &raw);
    }
}

const FENCE: &str = "```";

/// Runs a guide's ```` ```sh ```` and ```` ```python ```` blocks in order in
/// a sandbox: the repository's `assets/`, `configs/` and
/// `crates/embodiment/robots/` linked in, the raw fixtures' DROID episode
/// as `raw/droid` with its intrinsics as `zed_intrinsics.json`, `bridgev2w`
/// and the venv's `python` first on `PATH`.
fn run_guide(name: &str, venv: &Path, raw: &Path) {
    let text = std::fs::read_to_string(repo().join("docs/guide").join(name)).expect("guide");
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let bin = d.join(".bin");
    std::fs::create_dir(&bin).expect("mkdir");
    std::os::unix::fs::symlink(env!("CARGO_BIN_EXE_bridgev2w"), bin.join("bridgev2w"))
        .expect("link bridgev2w");
    for shared in ["assets", "configs"] {
        std::os::unix::fs::symlink(repo().join(shared), d.join(shared)).expect("link");
    }
    std::fs::create_dir(d.join("raw")).expect("mkdir raw");
    std::os::unix::fs::symlink(raw.join("droid"), d.join("raw/droid")).expect("link droid");
    std::os::unix::fs::symlink(
        raw.join("droid_intrinsics.json"),
        d.join("zed_intrinsics.json"),
    )
    .expect("link intrinsics");
    std::fs::create_dir_all(d.join("crates/embodiment")).expect("mkdir");
    std::os::unix::fs::symlink(
        repo().join("crates/embodiment/robots"),
        d.join("crates/embodiment/robots"),
    )
    .expect("link robots");
    let path = format!(
        "{}:{}:{}",
        bin.display(),
        venv.join("bin").display(),
        std::env::var("PATH").unwrap_or_default()
    );
    let (mut ran, mut open): (usize, Option<(String, String)>) = (0, None);
    for line in text.lines() {
        match (&mut open, line.trim_start().strip_prefix(FENCE)) {
            (None, Some(info)) => open = Some((info.trim().to_string(), String::new())),
            (Some(_), Some(_)) => {
                let (info, body) = open.take().expect("open block");
                let mut c = match info.as_str() {
                    "sh" => {
                        let mut c = Command::new("bash");
                        c.args(["-euo", "pipefail", "-c"]);
                        c
                    }
                    // The venv's python (first on PATH).
                    "python" => {
                        let mut c = Command::new(venv.join("bin/python"));
                        c.arg("-c");
                        c
                    }
                    _ => continue,
                };
                let o = c
                    .arg(&body)
                    .current_dir(d)
                    .env("PATH", &path)
                    .env("RUST_BACKTRACE", "0")
                    .output()
                    .expect("run a block");
                assert!(
                    o.status.success(),
                    "{name}: this block failed:\n{body}\nstdout:\n{}\nstderr:\n{}",
                    String::from_utf8_lossy(&o.stdout),
                    String::from_utf8_lossy(&o.stderr)
                );
                ran += 1;
            }
            (Some((_, body)), None) => {
                body.push_str(line);
                body.push('\n');
            }
            (None, None) => {}
        }
    }
    assert!(ran >= 2, "{name}: {ran} runnable blocks");
}
