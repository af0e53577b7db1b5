//! `bridgev2w parity`: passes on a diffusers fixture, fails (non-zero exit, naming
//! the output) when the fixture disagrees with the implementation.

use std::path::PathBuf;
use std::process::Command;

fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

#[test]
fn parity_command_passes_and_fails_as_it_should() {
    let python = repo_root().join(".venv/bin/python");
    assert!(
        python.is_file(),
        "{} missing: run scripts/setup-venv.sh (./run test does)",
        python.display()
    );
    let tmp = tempfile::tempdir().expect("tempdir");
    let fixture = tmp.path().join("ddim");
    let status = Command::new(&python)
        .arg(repo_root().join("scripts/parity/make_parity_fixture.py"))
        .args(["scheduler", "--sampler", "ddim", "--steps", "4", "--out"])
        .arg(&fixture)
        .status()
        .expect("run fixture script");
    assert!(status.success());

    let ok = Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
        .arg("parity")
        .arg(&fixture)
        .output()
        .expect("run bridgev2w");
    let table = String::from_utf8_lossy(&ok.stdout);
    assert!(
        ok.status.success(),
        "{table}\n{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    assert!(
        table.contains("prev_sample_step_3") && table.contains("| ok |"),
        "{table}"
    );

    // A different SNR shift than diffusers used: every step must disagree.
    let cfg = fixture.join("model/scheduler_config.json");
    let text = std::fs::read_to_string(&cfg).expect("read config");
    let mut json: serde_json::Value = serde_json::from_str(&text).expect("json");
    json["snr_shift_scale"] = serde_json::json!(2.0);
    std::fs::write(&cfg, json.to_string()).expect("write config");
    let bad = Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
        .arg("parity")
        .arg(&fixture)
        .output()
        .expect("run bridgev2w");
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(
        err.contains("relative error above") && err.contains("prev_sample_step_0"),
        "{err}"
    );

    let missing = Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
        .args(["parity", "/nonexistent-fixture"])
        .output()
        .expect("run bridgev2w");
    assert!(!missing.status.success());
    assert!(String::from_utf8_lossy(&missing.stderr).contains("meta.json"));
}
