//! `bridgev2w parity`: passes on a diffusers fixture, fails (non-zero exit, naming
//! the output) when the fixture disagrees with the implementation.

use std::path::PathBuf;
use std::process::Command;

fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Writes a diffusers parity fixture with `scripts/parity/make_parity_fixture.py
/// ARGS --out TMP/NAME` (the project venv's Python) and returns its folder.
fn make_fixture(tmp: &tempfile::TempDir, name: &str, args: &[&str]) -> PathBuf {
    let python = repo_root().join(".venv/bin/python");
    assert!(
        python.is_file(),
        "{} missing: run scripts/setup-venv.sh (./run test does)",
        python.display()
    );
    let fixture = tmp.path().join(name);
    let status = Command::new(&python)
        .arg(repo_root().join("scripts/parity/make_parity_fixture.py"))
        .args(args)
        .arg("--out")
        .arg(&fixture)
        .status()
        .expect("run fixture script");
    assert!(status.success());
    fixture
}

#[test]
fn parity_command_passes_and_fails_as_it_should() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let fixture = make_fixture(
        &tmp,
        "ddim",
        &["scheduler", "--sampler", "ddim", "--steps", "4"],
    );

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

#[test]
fn bf16_parity_compares_both_sides_with_diffusers_f32() {
    let tmp = tempfile::tempdir().expect("tempdir");
    let fixture = make_fixture(
        &tmp,
        "tf",
        &[
            "transformer",
            "--style",
            "5b-i2v",
            "--shape",
            "1,2,8,4,4",
            "--layers",
            "1",
            "--bf16",
        ],
    );
    let parity = |extra: &[&str]| {
        Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
            .args(["parity", "--precision", "bf16"])
            .args(extra)
            .arg(&fixture)
            .output()
            .expect("run bridgev2w")
    };
    let ok = parity(&[]);
    let table = String::from_utf8_lossy(&ok.stdout);
    assert!(
        ok.status.success(),
        "{table}\n{}",
        String::from_utf8_lossy(&ok.stderr)
    );
    assert!(
        table.contains("diffusers bf16 rms rel") && table.contains("| sample |"),
        "{table}"
    );
    // No room at all: ours (a bf16 run, so not exact) fails, naming the output.
    let strict = parity(&["--bf16-factor", "0", "--bf16-epsilon", "0"]);
    assert!(!strict.status.success());
    let err = String::from_utf8_lossy(&strict.stderr);
    assert!(
        err.contains("bf16 error above") && err.contains("sample"),
        "{err}"
    );

    // A fixture made without --bf16: the error says how to make one.
    let f32_only = make_fixture(
        &tmp,
        "tf32",
        &["transformer", "--shape", "1,2,8,4,4", "--layers", "1"],
    );
    let o = Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
        .args(["parity", "--precision", "bf16"])
        .arg(&f32_only)
        .output()
        .expect("run bridgev2w");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--bf16"), "{err}");
}
