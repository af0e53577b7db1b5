//! `scripts/fuzz.sh`, the wall-clock fuzzing entry point: bad arguments are
//! refused with a usage line, and a real run of one target (the trajectory
//! parsers, a one-second budget) builds it, runs it and reports its cases.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn fuzz(args: &[&str]) -> Output {
    Command::new("bash")
        .arg(repo().join("scripts/fuzz.sh"))
        .args(args)
        // The dev profile over the build that runs this test (cargo holds no
        // lock while tests run): nothing to compile, where a release build
        // of its own cost minutes.
        .env("FUZZ_PROFILE", "dev")
        .output()
        .expect("run bash")
}

#[test]
fn fuzz_script_refuses_bad_arguments() {
    let o = fuzz(&["jpeg", "5"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(
        e.contains("unknown fuzz target 'jpeg'") && e.contains("npy, camera, trajectory"),
        "{e}"
    );
    let o = fuzz(&["npy", "ten"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(e.contains("SECONDS must be a whole number"), "{e}");
    let o = fuzz(&["npy"]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("usage"));
    let o = Command::new("bash")
        .arg(repo().join("scripts/fuzz.sh"))
        .args(["npy", "1"])
        .env("FUZZ_PROFILE", "fast")
        .output()
        .expect("run bash");
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{e}");
    assert!(
        e.contains("FUZZ_PROFILE=fast: expected release or dev"),
        "{e}"
    );
}

#[test]
fn fuzz_script_runs_a_target_for_its_budget() {
    let o = fuzz(&["trajectory", "1"]);
    let out = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert!(o.status.success(), "{out}");
    let cases: usize = out
        .lines()
        .find_map(|l| l.strip_prefix("fuzz trajectory: "))
        .and_then(|l| l.split_whitespace().next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no case count in {out}"));
    assert!(cases > 0, "{out}");
}
