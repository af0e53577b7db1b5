//! The Python package (`python/`, PyO3 + maturin): `pip install ./python`
//! into a fresh venv (numpy from the project venv), then its tests
//! (`python/tests/test_bridgev2w.py`: masks and IK against `bridgev2w
//! masks`, metrics against closed forms, bad input as Python exceptions).
//! The wheel is built in its own target folder (`target/python`): this test
//! runs inside `cargo test`, which holds the workspace's.

use std::path::{Path, PathBuf};
use std::process::Command;

mod common;

use common::ok;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .canonicalize()
        .expect("repo root")
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
    let venv = dir.path().join("venv");
    ok(&Command::new("python3")
        .args(["-m", "venv"])
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
        .env("CARGO_TARGET_DIR", repo().join("target/python"))
        .output()
        .expect("pip install ./python");
    ok(&install);
    let work = dir.path().join("work");
    std::fs::create_dir(&work).expect("mkdir");
    let o = Command::new(venv.join("bin/python"))
        .arg(repo().join("python/tests/test_bridgev2w.py"))
        .arg(env!("CARGO_BIN_EXE_bridgev2w"))
        .arg(&work)
        .current_dir(dir.path())
        .output()
        .expect("run the package's tests");
    eprintln!("{}", String::from_utf8_lossy(&o.stdout));
    ok(&o);
    assert!(String::from_utf8_lossy(&o.stdout).contains("6 passed"));
}
