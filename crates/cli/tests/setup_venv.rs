//! `scripts/setup-venv.sh`, the first step of both README commands: it refuses
//! to start on a disk too small for the venv (naming what it found and needs),
//! and keeps a venv whose stamp matches the lock file without touching pip.
//! Run on a copy of the script, with `df` and `python3` replaced by fakes.

use std::fs;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn executable(path: &Path, text: &str) {
    fs::write(path, text).expect("write fake");
    fs::set_permissions(path, fs::Permissions::from_mode(0o755)).expect("chmod fake");
}

/// A copy of the script and lock under `root/scripts`, and fakes in `root/bin`:
/// `df` reports `free_kib` free, `python3` records that it was called.
fn sandbox(free_kib: u64) -> tempfile::TempDir {
    let root = tempfile::tempdir().expect("tempdir");
    let scripts = root.path().join("scripts");
    fs::create_dir(&scripts).expect("mkdir scripts");
    for f in ["setup-venv.sh", "requirements-lock.txt"] {
        fs::copy(repo().join("scripts").join(f), scripts.join(f)).expect("copy script");
    }
    let bin = root.path().join("bin");
    fs::create_dir(&bin).expect("mkdir bin");
    executable(
        &bin.join("df"),
        &format!(
            "#!/bin/sh\necho 'Filesystem 1024-blocks Used Available Capacity Mounted on'\n\
             echo \"/dev/x 100000000 1 {free_kib} 1% /\"\n"
        ),
    );
    executable(
        &bin.join("python3"),
        &format!(
            "#!/bin/sh\ntouch '{}'\nexit 3\n",
            root.path().join("python3-called").display()
        ),
    );
    root
}

fn run(root: &Path) -> Output {
    let path = format!(
        "{}:{}",
        root.join("bin").display(),
        std::env::var("PATH").unwrap_or_default()
    );
    Command::new("bash")
        .arg(root.join("scripts/setup-venv.sh"))
        .env("PATH", path)
        .output()
        .expect("run bash")
}

#[test]
fn too_little_disk_is_refused_before_anything_is_installed() {
    let root = sandbox(1024 * 1024);
    let o = run(root.path());
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("1024 MiB free") && err.contains("needs about 5500 MiB"),
        "{err}"
    );
    assert!(err.contains("cargo clean"), "{err}");
    assert!(!root.path().join(".venv").exists());
    assert!(!root.path().join("python3-called").exists());
}

#[test]
fn a_venv_stamped_with_the_lock_is_kept_as_it_is() {
    let root = sandbox(1024);
    let venv = root.path().join(".venv");
    fs::create_dir_all(venv.join("bin")).expect("mkdir venv");
    fs::create_dir_all(venv.join("lib")).expect("mkdir venv lib");
    fs::create_dir_all(venv.join("libtorch/lib")).expect("mkdir libtorch");
    fs::write(venv.join("libtorch/lib/libtorch_cpu.so"), b"").expect("write lib");
    executable(&venv.join("bin/python"), "#!/bin/sh\nexit 3\n");
    fs::copy(
        root.path().join("scripts/requirements-lock.txt"),
        venv.join(".bridgev2w-requirements"),
    )
    .expect("stamp");
    let o = run(root.path());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(!root.path().join("python3-called").exists());

    // A stale stamp means a changed lock: the script goes on to install (and
    // here, with 1 MiB free and a venv already begun, reaches the fake python3).
    fs::write(venv.join(".bridgev2w-requirements"), "torch==0.0.1\n").expect("restamp");
    let o = run(root.path());
    assert!(!o.status.success());
    assert!(root.path().join("python3-called").exists());
}
