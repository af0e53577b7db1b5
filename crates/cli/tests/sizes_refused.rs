//! Sizes are bounded before they are allocated (issue 69, item 3): a size
//! flag beyond its stated maximum, or a request whose estimated memory
//! exceeds the machine's, is refused up front with exit status 1 or 2, an
//! error naming the flag, the value and the maximum (or the estimate and
//! what is available), never an abort, and nothing written.

#![allow(clippy::unwrap_used)]

use crate::common;

use common::{refused, run, s};

/// Whether this machine's available memory can be read (Linux): the
/// memory refusals are checked only there.
fn memory_known() -> bool {
    bridgev2w_io::memory::available_bytes().is_some()
}

const CAMERA: &str = r#"{"fx": 300, "fy": 300, "cx": 159.5, "cy": 119.5, "width": 320, "height": 240,
  "world_from_camera": [[-0.3939, 0.3019, -0.8682, 1.7],
                        [0.9191, 0.1294, -0.3721, 0.6],
                        [0.0, -0.9445, -0.3284, 1.0],
                        [0, 0, 0, 1]]}"#;

/// `bridgev2w masks` of 10000 frames at 16384x16384 (13 TB of label maps)
/// is refused before anything is rendered, with the estimate; 9 frames at
/// 48x48 render.
#[test]
fn masks_beyond_the_machine_are_refused_with_the_estimate() {
    let tmp = tempfile::tempdir().unwrap();
    let camera = tmp.path().join("camera.json");
    std::fs::write(&camera, CAMERA).unwrap();
    let home = "[0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785, 0.04]";
    let joints = tmp.path().join("joints.json");
    std::fs::write(&joints, format!("[{}]", vec![home; 10_000].join(","))).unwrap();
    let out = tmp.path().join("out");
    let few = tmp.path().join("few.json");
    std::fs::write(&few, format!("[{}]", [home; 9].join(","))).unwrap();
    let masks = |joints: &std::path::Path, size: &str, extra: &[&str]| {
        let mut args = vec![
            "masks",
            "--robot",
            "franka",
            "--camera",
            s(&camera),
            "--joints",
            s(joints),
            "--width",
            size,
            "--height",
            size,
            "--out",
            s(&out),
        ];
        args.extend_from_slice(extra);
        run(&args)
    };
    if memory_known() {
        refused(
            &masks(&joints, "16384", &[]),
            &[
                "rendering 10000 frames of 16384x16384 pixels needs at least 12500.0 GiB",
                "is available",
                "--width/--height",
            ],
        );
        assert!(!out.exists());
    }
    refused(&masks(&joints, "16385", &[]), &["width 16385", "1..=16384"]);
    // Normal sizes pass.
    let o = masks(&few, "48", &["--no-png"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(out.join("masks.npy").is_file());
}

#[test]
fn plan_refuses_sizes_beyond_their_maximum_naming_the_flag() {
    let plan = |extra: &[&str]| {
        let mut args = vec!["plan", "--task", "reach", "--device", "cpu"];
        if !extra.contains(&"--trials") {
            args.extend_from_slice(&["--trials", "1"]);
        }
        args.extend_from_slice(extra);
        run(&args)
    };
    refused(
        &plan(&["--samples", "65537"]),
        &["--samples 65537", "at most 65536 candidates"],
    );
    refused(
        &plan(&["--width", "100000"]),
        &["--width 100000", "at most 4096 pixels"],
    );
    refused(
        &plan(&["--clip-frames", "100000"]),
        &["--clip-frames 100000", "at most 1024 frames"],
    );
    refused(
        &plan(&["--max-batch", "100000"]),
        &["--max-batch 100000", "at most 4096 clips"],
    );
    refused(&plan(&["--max-batch", "0"]), &["--max-batch", "at least 1"]);
    refused(
        &plan(&["--episode-frames", "20000"]),
        &["--episode-frames 20000", "at most 10000 frames"],
    );
    refused(
        &plan(&["--trials", "1000000"]),
        &["--trials 1000000", "at most 100000"],
    );
    refused(
        &plan(&["--horizon", "1000", "--execute-actions", "1"]),
        &["--horizon 1000 x --frames-per-action 2 + 1", "at most 1024"],
    );
    // 60000 candidates of 4096x4096 at once: 11 TiB of observed frames.
    if memory_known() {
        refused(
            &plan(&[
                "--samples", "60000", "--width", "4096", "--height", "4096",
            ]),
            &[
                "evaluating 60000 candidates (--samples) of 4096x4096 pixels at once needs at least",
                "is available",
                "Lower --samples",
            ],
        );
    }
}

#[test]
fn plan_fidelity_and_rollouts_refuse_sizes_beyond_their_maximum() {
    refused(
        &run(&[
            "plan-fidelity",
            "--candidates",
            "1000000",
            "--device",
            "cpu",
        ]),
        &["--candidates 1000000", "at most 65536 candidates"],
    );
    refused(
        &run(&[
            "eval-policy-rollout",
            "--task",
            "pick_place",
            "--trials",
            "1000000",
            "--device",
            "cpu",
        ]),
        &["--trials 1000000", "at most 100000"],
    );
}

#[test]
fn predict_refuses_a_batch_beyond_its_maximum_before_loading_the_model() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    refused(
        &run(&[
            "predict",
            "--model",
            "random:tiny",
            "--image",
            "first.png",
            "--masks",
            "masks.npy",
            "--out",
            s(&out),
            "--device",
            "cpu",
            "--batch-size",
            "100000",
        ]),
        &["--batch-size 100000", "at most 4096 clips"],
    );
    assert!(!out.exists());
}

#[test]
fn demo_refuses_frames_beyond_the_maximum_or_the_machine() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    let demo = |frames: &str| run(&["demo", "--out", s(&out), "--frames", frames, "--no-predict"]);
    refused(
        &demo("2000000"),
        &["--frames 2000000", "at most 1000000 frames"],
    );
    // 900000 masks of 720x480: 1.4 TiB.
    if memory_known() {
        refused(
            &demo("900000"),
            &[
                "rendering 900000 frames of 720x480 pixels needs at least",
                "is available",
            ],
        );
    }
    assert!(!out.exists());
}
