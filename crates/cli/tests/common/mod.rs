//! Helpers shared by the CLI's integration tests.

#![allow(dead_code)]

use std::path::Path;
use std::process::{Command, Output};

/// Runs the `bridgev2w` binary (without backtraces, as a user sees it).
pub fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
        .env("RUST_BACKTRACE", "0")
        .args(args)
        .output()
        .expect("run bridgev2w")
}

/// A path as a `&str` argument.
pub fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

/// Asserts that a run succeeded, printing its output when it did not.
pub fn ok(o: &Output) {
    assert!(
        o.status.success(),
        "failed: {}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
}

/// `bridgev2w synth` of a tiny dataset (2 episodes per split, 9 frames at
/// 96x64) into `out`.
pub fn synth_tiny(out: &Path) {
    ok(&run(&[
        "synth",
        "--out",
        s(out),
        "--episodes-per-split",
        "2",
        "--frames",
        "9",
        "--width",
        "96",
        "--height",
        "64",
    ]));
}

/// The `[model]` section of the trainer tests: the `random:tiny` backbone,
/// LoRA rank 4 and one ControlNet block.
pub const TINY_MODEL_TOML: &str = r#"[model]
backbone = "random:tiny"
lora_rank = 4
lora_alpha = 4.0
controlnet_layers = 1
"#;

/// The repository's markdown: README.md, ARCHITECTURE.md and every `.md`
/// under docs/ (run logs under docs/results/logs excepted).
pub fn markdown_files() -> Vec<std::path::PathBuf> {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let mut out = vec![root.join("README.md"), root.join("ARCHITECTURE.md")];
    let mut dirs = vec![root.join("docs")];
    while let Some(d) = dirs.pop() {
        for e in std::fs::read_dir(&d).expect("docs folder") {
            let p = e.expect("entry").path();
            if p.is_dir() {
                if p.file_name().is_some_and(|n| n != "logs") {
                    dirs.push(p);
                }
            } else if p.extension().is_some_and(|x| x == "md") {
                out.push(p);
            }
        }
    }
    out
}

/// The raw-episode fixtures of `scripts/fixtures/write_raw_episodes.py`
/// (HDF5 through the project venv's h5py) with their videos, written in
/// `dir`; returns its `expected.json`.
pub fn raw_fixtures(dir: &Path) -> serde_json::Value {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    ok(&Command::new(root.join(".venv/bin/python"))
        .arg(root.join("scripts/fixtures/write_raw_episodes.py"))
        .arg(dir)
        .output()
        .expect("run the venv python (scripts/setup-venv.sh)"));
    let expected: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.join("expected.json")).expect("expected.json"),
    )
    .expect("json");
    for v in expected["videos"].as_array().expect("videos") {
        bridgev2w_data::video::write_test_pattern(
            Path::new(v.as_str().expect("path")),
            (64, 48),
            6,
            15,
        )
        .expect("mp4");
    }
    expected
}

/// Asserts that `o` failed with status 1 or 2, without a panic or an abort,
/// and that its stderr holds every one of `needles`; returns the stderr.
pub fn refused(o: &Output, needles: &[&str]) -> String {
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(
        matches!(o.status.code(), Some(1 | 2)),
        "expected exit status 1 or 2, got {:?}; stderr:\n{err}",
        o.status.code()
    );
    for n in needles {
        assert!(err.contains(n), "stderr lacks {n:?}:\n{err}");
    }
    assert!(!err.contains("panicked"), "{err}");
    err
}

/// Runs a copy of a reproduction script (`root/scripts/SCRIPT`, with
/// `root/bridgev2w` a fake binary that appends its calls to
/// `root/calls.log`) with output folder `out` and `env`; asserts it
/// succeeded and returns the fake's calls of this run.
pub fn run_script(root: &Path, script: &str, out: &str, env: &[(&str, &str)]) -> Vec<String> {
    let log = root.join("calls.log");
    let _ = std::fs::remove_file(&log);
    let mut cmd = Command::new("bash");
    cmd.arg(root.join("scripts").join(script))
        .arg(out)
        .env("BRIDGEV2W", root.join("bridgev2w"))
        .env("RESULTS", "results.md");
    for (k, v) in env {
        cmd.env(k, v);
    }
    let o = cmd.output().expect("run bash");
    assert!(
        o.status.success(),
        "{}\n{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    std::fs::read_to_string(&log)
        .unwrap_or_default()
        .lines()
        .map(str::to_string)
        .collect()
}

/// The names trained in `calls` (`train NAME [--resume]`).
pub fn trained(calls: &[String]) -> Vec<&str> {
    calls
        .iter()
        .filter_map(|c| c.strip_prefix("train "))
        .collect()
}
