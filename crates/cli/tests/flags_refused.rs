//! Flags whose values would give silent garbage (issue 69, item 4) are
//! refused up front: exit status 1 or 2, an error naming the flag and the
//! value, and nothing written.

#![allow(clippy::unwrap_used)]

use crate::common;

use common::{refused, run, s};
use std::path::Path;
use std::process::Output;

/// `convert --format agibot SRC --out OUT REST...` (SRC need not exist: the
/// flags are checked before it is read).
fn convert(dir: &Path, rest: &[&str]) -> Output {
    let (src, out) = (dir.join("src"), dir.join("out"));
    let mut args = vec!["convert", "--format", "agibot", s(&src), "--out", s(&out)];
    args.extend_from_slice(rest);
    run(&args)
}

#[test]
fn convert_refuses_a_frame_rate_the_dataset_reader_would_refuse() {
    let tmp = tempfile::tempdir().unwrap();
    refused(
        &convert(tmp.path(), &["--fps", "0"]),
        &["--fps 0", "1..=1000"],
    );
    // fps * 1000 ticks must fit the MP4 time base.
    refused(
        &convert(tmp.path(), &["--fps", "5000000"]),
        &["--fps 5000000"],
    );
    assert!(!tmp.path().join("out").exists());
    assert!(std::fs::read_dir(tmp.path()).expect("read_dir").all(|e| !e
        .expect("entry")
        .file_name()
        .to_string_lossy()
        .contains("bridgev2w-tmp")));
}

#[test]
fn convert_ctrl_world_needs_fixed_exterior_cameras() {
    let tmp = tempfile::tempdir().unwrap();
    let (src, out) = (tmp.path().join("src"), tmp.path().join("out"));
    let cw = |rest: &[&str]| {
        let mut args = vec![
            "convert",
            "--format",
            "ctrl-world",
            s(&src),
            "--out",
            s(&out),
        ];
        args.extend_from_slice(rest);
        run(&args)
    };
    refused(&cw(&[]), &["no camera given", "bridgev2w calibrate"]);
    refused(
        &cw(&["--camera", "ext1"]),
        &["--camera \"ext1\"", "ROLE=CAMERA_JSON"],
    );
    refused(&cw(&["--camera", "wrist=c.json"]), &["moves with the hand"]);
    refused(
        &cw(&["--split-rule", "a/val/1:wrist=test"]),
        &[
            "split rule \"a/val/1:wrist=test\"",
            "role \"wrist\"",
            "EPISODE[:ROLE]=SPLIT",
        ],
    );
    refused(
        &cw(&["--camera", "ext1=absent.json"]),
        &["ext1 camera absent.json"],
    );
    // The flags belong to this layout only.
    refused(
        &convert(tmp.path(), &["--camera", "ext1=c.json"]),
        &["camera (ROLE=CAMERA_JSON), include, split rules: apply to the ctrl-world format"],
    );
    assert!(!out.exists());
}

#[test]
fn convert_refuses_duplicate_or_no_cameras() {
    let tmp = tempfile::tempdir().unwrap();
    refused(
        &convert(tmp.path(), &["--cameras", "head,head"]),
        &["--cameras \"head,head\"", "\"head\" is named twice"],
    );
    refused(
        &convert(tmp.path(), &["--cameras", "head, hand_left ,hand_left"]),
        &["--cameras", "\"hand_left\" is named twice"],
    );
    refused(
        &convert(tmp.path(), &["--cameras", " , "]),
        &["--cameras \" , \"", "at least one camera"],
    );
    assert!(!tmp.path().join("out").exists());
}

#[test]
fn eval_run_refuses_empty_or_duplicate_splits() {
    let tmp = tempfile::tempdir().unwrap();
    let (cfg, runs) = (tmp.path().join("run.toml"), tmp.path().join("run"));
    let eval_run =
        |splits: &str| run(&["eval-run", s(&cfg), "--run", s(&runs), "--splits", splits]);
    refused(&eval_run(""), &["--splits \"\"", "at least one split"]);
    refused(
        &eval_run(" , ,"),
        &["--splits \" , ,\"", "at least one split"],
    );
    refused(
        &eval_run("test,unseen_scene, test"),
        &[
            "--splits \"test,unseen_scene, test\"",
            "\"test\" is named twice",
        ],
    );
}

#[test]
fn eval_grid_refuses_empty_or_duplicate_splits() {
    let tmp = tempfile::tempdir().unwrap();
    let (cfg, runs, out) = (
        tmp.path().join("run.toml"),
        tmp.path().join("run"),
        tmp.path().join("grids"),
    );
    let grid = |splits: &str| {
        run(&[
            "eval-grid",
            s(&cfg),
            "--run",
            s(&runs),
            "--out",
            s(&out),
            "--splits",
            splits,
        ])
    };
    refused(&grid(""), &["--splits \"\"", "at least one split"]);
    refused(
        &grid("test,test"),
        &["--splits \"test,test\"", "\"test\" is named twice"],
    );
    assert!(!out.exists());
}

#[test]
fn demo_refuses_fewer_than_two_frames() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("demo");
    for frames in ["0", "1"] {
        refused(
            &run(&["demo", "--out", s(&out), "--frames", frames, "--no-predict"]),
            &[&format!("--frames {frames}"), "at least 2"],
        );
    }
    assert!(!out.exists());
}

#[test]
fn predict_refuses_weights_or_prompt_embeds_with_a_random_model() {
    let tmp = tempfile::tempdir().unwrap();
    let (w, p, out) = (
        tmp.path().join("w.safetensors"),
        tmp.path().join("prompt.safetensors"),
        tmp.path().join("out"),
    );
    let base = [
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
    ];
    let with = |flag: &str, path: &Path| {
        let mut args = base.to_vec();
        args.extend_from_slice(&[flag, s(path)]);
        run(&args)
    };
    refused(&with("--weights", &w), &["--weights", s(&w), "random:tiny"]);
    refused(
        &with("--prompt-embeds", &p),
        &["--prompt-embeds", s(&p), "random:tiny"],
    );
    assert!(!out.exists());
}

#[test]
fn plan_refuses_weights_with_a_random_model() {
    let tmp = tempfile::tempdir().unwrap();
    let w = tmp.path().join("w.safetensors");
    for model in ["random", "random:tiny"] {
        refused(
            &run(&[
                "plan",
                "--task",
                "reach",
                "--trials",
                "1",
                "--model",
                model,
                "--weights",
                s(&w),
                "--device",
                "cpu",
            ]),
            &["--weights", s(&w), "random:tiny"],
        );
    }
}

#[test]
fn predict_refuses_sampling_values_before_the_model_is_loaded() {
    let tmp = tempfile::tempdir().unwrap();
    let out = tmp.path().join("out");
    // The image and masks do not exist: the flags are checked first.
    for (flag, value, expected) in [
        ("--steps", "0", "at least 1"),
        ("--guidance", "0.5", ">= 1"),
        ("--guidance", "NaN", ">= 1"),
        ("--guidance", "inf", ">= 1"),
        ("--strength", "0", "(0, 1]"),
        ("--strength", "1.5", "(0, 1]"),
    ] {
        let o = run(&[
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
            flag,
            value,
        ]);
        refused(&o, &[flag, value, expected]);
    }
    assert!(!out.exists());
}

#[test]
fn plan_refuses_weights_or_prompt_embeds_with_the_perfect_model() {
    let tmp = tempfile::tempdir().unwrap();
    let w = tmp.path().join("w.safetensors");
    for (command, flag) in [
        ("plan", "--weights"),
        ("plan", "--prompt-embeds"),
        ("plan-fidelity", "--weights"),
    ] {
        let mut args = vec![command, "--task", "reach", "--trials", "1"];
        args.extend_from_slice(&["--model", "perfect", flag, s(&w), "--device", "cpu"]);
        refused(&run(&args), &[flag, s(&w), "--model perfect"]);
    }
}

#[test]
fn export_lora_refuses_non_finite_weights_naming_the_tensor() {
    use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
    use bridgev2w_world_model::lora::LoraConfig;
    use bridgev2w_world_model::scheduler::SchedulerConfig;
    use bridgev2w_world_model::transformer::TransformerConfig;
    use bridgev2w_world_model::vae::VaeConfig;
    use bridgev2w_world_model::ComputeDevice;

    let tmp = tempfile::tempdir().unwrap();
    let cfg = BridgeV2WConfig {
        lora: Some(LoraConfig {
            rank: 4,
            alpha: 4.0,
        }),
        ..BridgeV2WConfig::tiny()
    };
    let model = BridgeV2W::random(
        cfg,
        &VaeConfig::tiny(),
        &TransformerConfig::tiny(),
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        3,
    )
    .unwrap();
    // One value of one adapter becomes NaN (a diverged run).
    let mut keys: Vec<String> = model
        .adapters
        .variables()
        .into_keys()
        .filter(|k| k.starts_with("transformer.") && k.ends_with("lora_B.weight"))
        .collect();
    keys.sort();
    let key = keys.first().unwrap().clone();
    tch::no_grad(|| {
        let v = &model.adapters.variables()[&key];
        let _ = v.flatten(0, -1).get(0).fill_(f64::NAN);
    });
    let (backbone, weights, out) = (
        tmp.path().join("backbone"),
        tmp.path().join("bw.safetensors"),
        tmp.path().join("lora"),
    );
    model.save_backbone(&backbone).unwrap();
    model.save_weights(&weights).unwrap();
    refused(
        &run(&[
            "export-lora",
            "--model",
            s(&backbone),
            "--weights",
            s(&weights),
            "--out",
            s(&out),
        ]),
        &[s(&weights), &format!("`{key}`"), "NaN or infinite"],
    );
    assert!(!out.exists());
}

fn refs(a: &[String]) -> Vec<&str> {
    a.iter().map(String::as_str).collect()
}

/// `eval-policy --json FILE` (and `eval`) leave an existing file alone unless
/// `--overwrite`, and `eval-grid --out` an existing folder: refused before
/// any work, the user's file unchanged.
#[test]
fn result_files_are_not_overwritten_without_overwrite() {
    let tmp = tempfile::tempdir().unwrap();
    let d = tmp.path();
    let rates =
        r#"{"reach": {"a": 0.9, "b": 0.4, "c": 0.1}, "push": {"a": 0.7, "b": 0.5, "c": 0.2}}"#;
    std::fs::write(d.join("real.json"), rates).unwrap();
    std::fs::write(d.join("sim.json"), rates).unwrap();
    std::fs::write(d.join("mine.json"), "my notes").unwrap();
    let args = |extra: &[&'static str]| {
        let mut a = vec![
            "eval-policy".to_string(),
            "--real".into(),
            s(&d.join("real.json")).into(),
            "--sim".into(),
            s(&d.join("sim.json")).into(),
            "--json".into(),
            s(&d.join("mine.json")).into(),
        ];
        a.extend(extra.iter().map(|x| x.to_string()));
        a
    };
    let a = args(&[]);
    refused(
        &run(&refs(&a)),
        &["--json", "mine.json", "already exists", "--overwrite"],
    );
    assert_eq!(
        std::fs::read_to_string(d.join("mine.json")).unwrap(),
        "my notes"
    );
    let a = args(&["--overwrite"]);
    let o = run(&refs(&a));
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert!(std::fs::read_to_string(d.join("mine.json"))
        .unwrap()
        .contains("pearson"));

    // eval-grid: an existing --out folder is refused before the runs load.
    std::fs::create_dir(d.join("grids")).unwrap();
    std::fs::write(d.join("grids/keep.txt"), "mine").unwrap();
    std::fs::create_dir(d.join("run")).unwrap();
    refused(
        &run(&[
            "eval-grid",
            s(&d.join("config.toml")),
            "--run",
            s(&d.join("run")),
            "--out",
            s(&d.join("grids")),
        ]),
        &["grids", "already exists"],
    );
    assert!(d.join("grids/keep.txt").is_file());
}

#[test]
fn calibrate_refuses_marks_that_fit_no_episode() {
    let tmp = tempfile::tempdir().unwrap();
    let (video, joints, marks) = (
        tmp.path().join("0002/0.mp4"),
        tmp.path().join("0002.json"),
        tmp.path().join("marks.json"),
    );
    let out = tmp.path().join("cal");
    let cal = |marks_text: &str| {
        std::fs::write(&marks, marks_text).unwrap();
        run(&[
            "calibrate",
            "--robot",
            "franka-robotiq",
            "--video",
            s(&video),
            "--joints",
            s(&joints),
            "--marks",
            s(&marks),
            "--out",
            s(&out),
        ])
    };
    refused(
        &cal(r#"{"videos": [{"video": "0003/0.mp4", "marks": [[0, 1, 2]]}]}"#),
        &[
            "marks.json",
            "none of its videos (0003/0.mp4)",
            "0002/0.mp4",
        ],
    );
    refused(
        &cal(r#"{"videos": [{"video": "0002/0.mp4", "marks": [[0, 1, 2], [0, 3, 4]]}]}"#),
        &[
            "marks.json",
            "videos[0].marks[1]",
            "frame 0 is marked twice",
        ],
    );
    assert!(!out.exists());
}
