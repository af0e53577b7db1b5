//! Parity fixtures for tests: generated on demand by the committed script with the
//! project venv's diffusers, cached under `target/parity-fixtures/` and regenerated
//! when the script, its modules or the arguments change.

#![allow(dead_code, clippy::unwrap_used)]

use std::hash::{Hash, Hasher};
use std::path::{Path, PathBuf};
use std::process::Command;

/// The repository root.
pub fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .canonicalize()
        .unwrap()
}

/// The project venv's python; panics with the fix when it is missing.
pub fn venv_python() -> PathBuf {
    let python = repo_root().join(".venv/bin/python");
    assert!(
        python.is_file(),
        "{} not found: run scripts/setup-venv.sh (./run test does) to install torch and diffusers",
        python.display()
    );
    python
}

fn scripts_digest(args: &[&str]) -> String {
    let dir = repo_root().join("scripts/parity");
    let mut entries: Vec<PathBuf> = std::fs::read_dir(&dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "py"))
        .collect();
    entries.sort();
    let mut h = std::collections::hash_map::DefaultHasher::new();
    for p in entries {
        p.file_name().hash(&mut h);
        std::fs::read(&p).unwrap().hash(&mut h);
    }
    args.hash(&mut h);
    format!("{:016x}", h.finish())
}

/// One lock per fixture name: tests of one binary that share a fixture (the
/// f32 and the bf16 checks) wait for one generation instead of racing.
fn fixture_lock(name: &str) -> std::sync::Arc<std::sync::Mutex<()>> {
    use std::collections::HashMap;
    use std::sync::{Arc, Mutex, OnceLock};
    static LOCKS: OnceLock<Mutex<HashMap<String, Arc<Mutex<()>>>>> = OnceLock::new();
    let mut locks = LOCKS
        .get_or_init(Default::default)
        .lock()
        .unwrap_or_else(|p| p.into_inner());
    locks.entry(name.to_owned()).or_default().clone()
}

/// The fixture `name` made by `make_parity_fixture.py ARGS` (generated if stale).
pub fn fixture(name: &str, args: &[&str]) -> PathBuf {
    let lock = fixture_lock(name);
    let _guard = lock.lock().unwrap_or_else(|p| p.into_inner());
    let out = repo_root().join("target/parity-fixtures").join(name);
    let digest = scripts_digest(args);
    let stamp = out.join("stamp");
    if std::fs::read_to_string(&stamp).is_ok_and(|s| s == digest) {
        return out;
    }
    let status = Command::new(venv_python())
        .arg(repo_root().join("scripts/parity/make_parity_fixture.py"))
        .args(args)
        .arg("--out")
        .arg(&out)
        .status()
        .unwrap();
    assert!(status.success(), "make_parity_fixture.py {args:?} failed");
    std::fs::write(&stamp, digest).unwrap();
    out
}

/// diffusers' parameter count (meta device, `scripts/parity/param_count.py`) of a
/// `component` (`transformer` or `vae`) built from `config`.
pub fn diffusers_param_count(component: &str, config: &impl serde::Serialize) -> i64 {
    let tmp = tempfile::tempdir().unwrap();
    let path = tmp.path().join("config.json");
    std::fs::write(&path, serde_json::to_string(config).unwrap()).unwrap();
    let out = Command::new(venv_python())
        .arg(repo_root().join("scripts/parity/param_count.py"))
        .args(["--component", component, "--config"])
        .arg(&path)
        .output()
        .unwrap();
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    v["parameters"].as_i64().unwrap()
}

/// A copy of the component folder `dir` (config.json + single-file weights) in a
/// temporary directory, without the tensor `key`: for missing-weight errors.
pub fn component_without(dir: &Path, key: &str) -> tempfile::TempDir {
    let tmp = tempfile::tempdir().unwrap();
    std::fs::copy(dir.join("config.json"), tmp.path().join("config.json")).unwrap();
    let named: Vec<(String, tch::Tensor)> = bridgev2w_world_model::weights::read_safetensors(
        &dir.join("diffusion_pytorch_model.safetensors"),
    )
    .unwrap()
    .into_iter()
    .filter(|(k, _)| k != key)
    .collect();
    bridgev2w_world_model::weights::save_safetensors(
        &named,
        &tmp.path().join("diffusion_pytorch_model.safetensors"),
    )
    .unwrap();
    tmp
}
