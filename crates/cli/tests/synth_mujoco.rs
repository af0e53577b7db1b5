//! `bridgev2w synth --engine mujoco` (issue 72): the synthetic world run by
//! MuJoCo (`.venv-mujoco`, made by `./run test` with
//! scripts/setup-mujoco-venv.sh), the masks checked against MuJoCo's
//! segmentation; what is missing or unstable named, never written.

use crate::common;

use common::{ok, run, s};
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn synth_json(dir: &Path) -> serde_json::Value {
    let text = std::fs::read_to_string(dir.join("meta/synth.json")).expect("synth.json");
    serde_json::from_str(&text).expect("JSON")
}

/// `synth` of two test-split episodes (reach, push) of the Franka with its
/// real meshes, with `engine`; the MuJoCo venv's Python unless `python`.
fn synth(out: &Path, engine: &str, python: Option<&Path>) -> Output {
    let mut c = Command::new(env!("CARGO_BIN_EXE_bridgev2w"));
    c.env("RUST_BACKTRACE", "0").args([
        "synth",
        "--engine",
        engine,
        "--robot",
        "franka-robotiq",
        "--episodes-per-split",
        "0,2,0,0",
        "--frames",
        "16",
        "--width",
        "128",
        "--height",
        "96",
        "--tasks",
        "reach,push",
        "--out",
        s(out),
    ]);
    if let Some(p) = python {
        c.env("BRIDGEV2W_MUJOCO_PYTHON", p);
    }
    c.output().expect("run bridgev2w")
}

#[test]
fn mujoco_runs_the_episodes_and_its_segmentation_matches_the_masks() {
    let python = repo().join(".venv-mujoco/bin/python");
    assert!(
        python.is_file(),
        "{}: no MuJoCo venv (./run test makes it: scripts/setup-mujoco-venv.sh)",
        python.display()
    );
    let dir = tempfile::tempdir().expect("tempdir");
    let (with, without) = (dir.path().join("mujoco"), dir.path().join("builtin"));
    let o = synth(&with, "mujoco", Some(&python));
    ok(&o);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("engine mujoco") && stdout.contains("segmentation of the robot: IoU mean"),
        "{stdout}"
    );
    ok(&synth(&without, "builtin", None));
    let (m, b) = (synth_json(&with), synth_json(&without));
    assert_eq!(m["config"]["engine"], "mujoco");
    let episodes = m["episodes"].as_array().expect("episodes");
    assert_eq!(episodes.len(), 2, "{m}");
    for (e, plain) in episodes
        .iter()
        .zip(b["episodes"].as_array().expect("episodes"))
    {
        let check = &e["mujoco"];
        let f = |k: &str| check[k].as_f64().unwrap_or_else(|| panic!("{k}: {check}"));
        // The target for the masks: IoU 0.98 on average.
        assert!(
            f("mask_iou_mean") >= 0.98 && f("mask_iou_min") >= 0.95,
            "{check}"
        );
        // Position control follows the plan (the arm; radians).
        assert!(f("max_tracking_error") < 0.1, "{check}");
        // The same plan (camera, objects) as the built-in world's.
        assert_eq!(e["objects"], plain["objects"]);
        assert!(plain.get("mujoco").is_none());
        if e["task"] == "reach" {
            // No object involved: MuJoCo's arm ends where the plan does.
            assert_eq!(check["as_planned"], true, "{check}");
        }
    }
    // MuJoCo's frames, not the built-in renderer's; masks alike.
    let video = |d: &Path| {
        std::fs::read(d.join("videos/observation.images.main/chunk-000/file-000.mp4"))
            .expect("video")
    };
    assert_ne!(video(&with), video(&without));
    let masks = |d: &Path| {
        bridgev2w_io::npy::read_npy(&d.join("masks/episode_000000.npy"))
            .expect("masks")
            .data
    };
    // MuJoCo's own robot pixels, saved beside the masks.
    let theirs = bridgev2w_io::npy::read_npy(&with.join("mujoco_masks/episode_000001.npy"))
        .expect("mujoco_masks");
    assert_eq!(theirs.shape, [16, 96, 128]);
    assert!(theirs.data.contains(&1.0));
    assert!(!without.join("mujoco_masks").exists());
    let (a, c) = (masks(&with), masks(&without));
    assert_eq!(a.len(), 16 * 96 * 128);
    let both = a
        .iter()
        .zip(&c)
        .filter(|(x, y)| **x > 0.0 && **y > 0.0)
        .count();
    let either = a
        .iter()
        .zip(&c)
        .filter(|(x, y)| **x > 0.0 || **y > 0.0)
        .count();
    assert!(both as f64 > 0.9 * either as f64, "{both} of {either}");
}

#[test]
fn a_missing_mujoco_or_an_unstable_run_is_named_and_nothing_is_written() {
    let dir = tempfile::tempdir().expect("tempdir");
    let out = dir.path().join("out");
    // No such Python.
    let o = synth(&out, "mujoco", Some(&dir.path().join("nope/python")));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("BRIDGEV2W_MUJOCO_PYTHON=") && e.contains("no such file"),
        "{e}"
    );
    assert!(!out.exists());
    // A Python without MuJoCo: the project venv's.
    let o = synth(&out, "mujoco", Some(&repo().join(".venv/bin/python")));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success()
            && e.contains("cannot import mujoco")
            && e.contains("scripts/setup-mujoco-venv.sh"),
        "{e}"
    );
    assert!(!out.exists());
    // A run whose physics goes unstable (a stand-in worker speaking the
    // session's protocol reports it):
    // dropped with the reason; with every episode dropped, nothing written.
    let fake = dir.path().join("python");
    std::fs::write(
        &fake,
        "#!/bin/sh\nif [ \"$1\" = -c ]; then echo 4.0.1; exit 0; fi\n\
         while read -r line; do echo '{\"frames\": [], \"stable\": false, \"reason\": \"frame 3: the state is not finite (NaN or inf)\", \"mujoco\": \"4.0.1\", \"substeps\": 50}'; done\n",
    )
    .expect("write");
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        std::fs::set_permissions(&fake, std::fs::Permissions::from_mode(0o755)).expect("chmod");
    }
    let o = synth(&out, "mujoco", Some(&fake));
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success()
            && e.contains("every episode's physics went unstable")
            && e.contains("frame 3: the state is not finite"),
        "{e}"
    );
    assert!(!out.exists());
    // An unknown engine, by name.
    let o = run(&["synth", "--engine", "physx", "--out", s(&out)]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("builtin, mujoco"), "{e}");
}

/// `eval-policy-rollout --engine mujoco`: the policies' true success from
/// executing them in MuJoCo, named so in the report and its JSON.
#[test]
fn policies_are_executed_in_mujoco_for_their_true_success() {
    let dir = tempfile::tempdir().expect("tempdir");
    let json = dir.path().join("report.json");
    let o = run(&[
        "eval-policy-rollout",
        "--task",
        "pick_place",
        "--trials",
        "1",
        "--model",
        "perfect",
        "--offsets-mm",
        "0,30",
        "--engine",
        "mujoco",
        "--json",
        s(&json),
    ]);
    ok(&o);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("MuJoCo-world success") && !stdout.contains("synthetic-world"),
        "{stdout}"
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("JSON");
    assert_eq!(v["executed_in"], "mujoco");
    // The expert's own actions, executed in MuJoCo, succeed against MuJoCo's
    // run of the expert's plan.
    assert_eq!(v["policies"][0]["synthetic_world_success"], 1.0, "{v}");
}

/// `plan-report --engine mujoco` (issue 72): plans and policies executed in
/// MuJoCo with the robot asked (the real-mesh one the MuJoCo study's data
/// has), the section saying so, both tables filled.
#[test]
fn plan_report_runs_its_trials_in_mujoco() {
    let dir = tempfile::tempdir().expect("tempdir");
    let results = dir.path().join("results.md");
    let o = run(&[
        "plan-report",
        "--engine",
        "mujoco",
        "--robot",
        "franka-robotiq",
        "--tasks",
        "push",
        "--models",
        "perfect",
        "--trials",
        "1",
        "--eval-trials",
        "1",
        "--samples",
        "8",
        "--elites",
        "2",
        "--iters",
        "1",
        "--max-steps",
        "2",
        "--section",
        "planning-mujoco",
        "--out",
        s(&results),
    ]);
    ok(&o);
    let md = std::fs::read_to_string(&results).expect("results");
    assert!(
        md.contains("## Goal-image planning and policy evaluation in the MuJoCo world")
            && md.contains("MuJoCo (the synthetic world's scenes, robot `franka-robotiq`")
            && md.contains("| push | perfect | ")
            && md.contains("MuJoCo-world success: the task's state check on MuJoCo's state")
            && !md.contains("synthetic-world success |"),
        "{md}"
    );
}
