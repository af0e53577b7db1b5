//! The `bridgev2w` binary: the masks contract, robot-info and bad input.

use std::path::Path;
use std::process::{Command, Output};

mod common;

fn bin() -> Command {
    Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
}

fn run(args: &[&str]) -> Output {
    bin().args(args).output().expect("run bridgev2w")
}

/// `bridgev2w masks --robot franka --camera CAMERA REST...`
fn franka_masks(camera: &str, rest: &[&str]) -> Output {
    let mut args = vec!["masks", "--robot", "franka", "--camera", camera];
    args.extend_from_slice(rest);
    run(&args)
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

const CAMERA: &str = r#"{"fx": 300, "fy": 300, "cx": 159.5, "cy": 119.5, "width": 320, "height": 240,
  "world_from_camera": [[-0.3939, 0.3019, -0.8682, 1.7],
                        [0.9191, 0.1294, -0.3721, 0.6],
                        [0.0, -0.9445, -0.3284, 1.0],
                        [0, 0, 0, 1]]}"#;

fn write(dir: &Path, name: &str, text: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, text).expect("write");
    p.display().to_string()
}

const HOME: [f64; 8] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785, 0.04];

fn joints_json(frames: usize) -> String {
    let rows: Vec<Vec<f64>> = (0..frames)
        .map(|t| {
            let mut q = HOME.to_vec();
            q[0] = 0.05 * t as f64;
            q
        })
        .collect();
    serde_json::to_string(&rows).expect("json")
}

fn npy_shape(path: &Path) -> (String, Vec<usize>) {
    let a = bridgev2w_embodiment_npy(path);
    (a.0, a.1)
}

/// Minimal .npy header reader (independent of the crate's reader).
fn bridgev2w_embodiment_npy(path: &Path) -> (String, Vec<usize>) {
    let bytes = std::fs::read(path).expect("read npy");
    assert_eq!(&bytes[..6], b"\x93NUMPY");
    let len = u16::from_le_bytes([bytes[8], bytes[9]]) as usize;
    let header = std::str::from_utf8(&bytes[10..10 + len]).expect("utf8");
    let descr = header
        .split("'descr': '")
        .nth(1)
        .and_then(|s| s.split('\'').next())
        .expect("descr")
        .to_string();
    let shape = header
        .split("'shape': (")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .expect("shape")
        .split(',')
        .filter_map(|s| s.trim().parse().ok())
        .collect();
    (descr, shape)
}

#[test]
fn masks_contract_with_joints_json_csv_and_actions() {
    let dir = tempfile::tempdir().expect("tmp");
    let cam = write(dir.path(), "camera.json", CAMERA);
    let joints = write(dir.path(), "joints.json", &joints_json(4));
    let out = dir.path().join("out");
    let o = franka_masks(
        &cam,
        &[
            "--joints",
            &joints,
            "--width",
            "160",
            "--height",
            "120",
            "--out",
            out.to_str().expect("utf8"),
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(
        npy_shape(&out.join("masks.npy")),
        ("|u1".to_string(), vec![4, 120, 160])
    );
    assert_eq!(
        npy_shape(&out.join("labels.npy")),
        ("<u2".to_string(), vec![4, 120, 160])
    );
    assert!(out.join("labels.json").is_file());
    assert!(out.join("frames/000003.png").is_file());

    // CSV with a header row, rendered with depth (the other renderer path),
    // gives the same masks and labels, and a float depth map.
    let mut csv = String::from("j1,j2,j3,j4,j5,j6,j7,finger\n");
    for t in 0..4 {
        let mut q = HOME.to_vec();
        q[0] = 0.05 * t as f64;
        csv.push_str(
            &q.iter()
                .map(|v| v.to_string())
                .collect::<Vec<_>>()
                .join(","),
        );
        csv.push('\n');
    }
    let csv_path = write(dir.path(), "joints.csv", &csv);
    let out2 = dir.path().join("out2");
    let o = franka_masks(
        &cam,
        &[
            "--joints",
            &csv_path,
            "--width",
            "160",
            "--height",
            "120",
            "--depth",
            "--out",
            out2.to_str().expect("utf8"),
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    for f in ["masks.npy", "labels.npy"] {
        assert_eq!(
            std::fs::read(out.join(f)).expect("a"),
            std::fs::read(out2.join(f)).expect("b"),
            "{f}"
        );
    }
    assert!(!out.join("depth.npy").exists());
    assert_eq!(
        npy_shape(&out2.join("depth.npy")),
        ("<f4".to_string(), vec![4, 120, 160])
    );

    // End-effector actions through IK.
    let actions = write(
        dir.path(),
        "actions.json",
        "[[0.45, 0.0, 0.3, 3.14159, 0.0, 0.0, 0.0], [0.45, 0.05, 0.3, 3.14159, 0.0, 0.0, 1.0]]",
    );
    let out3 = dir.path().join("out3");
    let o = franka_masks(
        &cam,
        &[
            "--actions",
            &actions,
            "--width",
            "160",
            "--height",
            "120",
            "--out",
            out3.to_str().expect("utf8"),
        ],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(npy_shape(&out3.join("masks.npy")).1, vec![2, 120, 160]);
    let ik: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out3.join("ik.json")).expect("ik"))
            .expect("json");
    assert_eq!(ik["frames_not_reached"].as_array().map(Vec::len), Some(0));
}

#[test]
fn bad_input_gets_clear_errors() {
    let dir = tempfile::tempdir().expect("tmp");
    let cam = write(dir.path(), "camera.json", CAMERA);
    let joints = write(dir.path(), "joints.json", &joints_json(2));
    let out = dir.path().join("o").display().to_string();
    let cases: Vec<(Vec<String>, Vec<&str>)> = vec![
        (
            vec![
                "--joints".into(),
                write(dir.path(), "short.json", "[[0.1, 0.2]]"),
            ],
            vec!["short.json", "2 values per frame", "8 actuated joints"],
        ),
        (
            vec![
                "--joints".into(),
                write(dir.path(), "nan.csv", "0,0,0,-2,0,1.5,0,nan\n"),
            ],
            vec!["nan.csv", "frame 0, column 7"],
        ),
        (
            vec![
                "--joints".into(),
                write(dir.path(), "limits.json", "[[0,0,0,1.0,0,1.5,0,0.01]]"),
            ],
            vec!["limits.json", "frame 0", "panda_joint4", "limits"],
        ),
        (
            vec![
                "--actions".into(),
                write(dir.path(), "far.json", "[[3.0, 0, 0.3, 3.14, 0, 0, 0]]"),
            ],
            vec!["far.json", "frame 0", "not reached", "--allow-ik-residual"],
        ),
        (
            vec![
                "--actions".into(),
                write(dir.path(), "dim.json", "[[0.4, 0, 0.3, 3.14, 0, 0]]"),
            ],
            vec!["dim.json", "6 values per frame", "expects 7"],
        ),
        (
            vec!["--joints".into(), write(dir.path(), "bad.txt", "1 2 3")],
            vec!["bad.txt", "unknown extension"],
        ),
    ];
    for (extra, needles) in cases {
        let mut args: Vec<String> = [
            "masks", "--robot", "franka", "--camera", &cam, "--out", &out,
        ]
        .iter()
        .map(|s| s.to_string())
        .collect();
        args.extend(extra);
        let o = bin().args(&args).output().expect("run");
        let err = stderr(&o);
        assert!(!o.status.success(), "{args:?} should fail");
        assert!(!err.contains("panicked"), "{err}");
        for n in needles {
            assert!(
                err.contains(n),
                "stderr for {args:?} should mention {n:?}: {err}"
            );
        }
    }
    // Camera errors.
    let bad_cam = write(
        dir.path(),
        "badcam.json",
        &CAMERA.replace("\"fx\": 300", "\"fx\": -3"),
    );
    let o = franka_masks(&bad_cam, &["--joints", &joints, "--out", &out]);
    assert!(
        !o.status.success() && stderr(&o).contains("fx") && stderr(&o).contains("badcam.json"),
        "{}",
        stderr(&o)
    );
    let rot_cam = write(
        dir.path(),
        "rotcam.json",
        &CAMERA.replace("-0.3939", "-0.9"),
    );
    let o = franka_masks(&rot_cam, &["--joints", &joints, "--out", &out]);
    assert!(
        !o.status.success() && stderr(&o).contains("rotation"),
        "{}",
        stderr(&o)
    );
    // Unknown robot, missing URDF.
    let o = run(&[
        "masks", "--robot", "ur5", "--camera", &cam, "--joints", &joints, "--out", &out,
    ]);
    assert!(
        !o.status.success() && stderr(&o).contains("franka, agibot-g1"),
        "{}",
        stderr(&o)
    );
    let bad_urdf = write(dir.path(), "broken.urdf", "<robot name='x'><link name='a'>");
    let o = run(&[
        "masks", "--robot", &bad_urdf, "--camera", &cam, "--joints", &joints, "--out", &out,
    ]);
    assert!(
        !o.status.success()
            && stderr(&o).contains("broken.urdf")
            && stderr(&o).contains("malformed"),
        "{}",
        stderr(&o)
    );
}

#[test]
fn camera_looking_away_warns() {
    let dir = tempfile::tempdir().expect("tmp");
    let away = r#"{"fx": 300, "fy": 300, "cx": 159.5, "cy": 119.5, "width": 320, "height": 240, "extrinsics_xyz_rpy": [3.0, 0.0, 0.5, 0.0, 1.5707963, 0.0]}"#;
    let cam = write(dir.path(), "away.json", away);
    let joints = write(dir.path(), "joints.json", &joints_json(2));
    let out = dir.path().join("o");
    let o = franka_masks(
        &cam,
        &["--joints", &joints, "--out", out.to_str().expect("utf8")],
    );
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("every mask is empty"), "{}", stderr(&o));
}

#[test]
fn robot_info_prints_joint_order() {
    let o = run(&["robot-info", "--robot", "agibot-g1", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("json");
    assert_eq!(v["action_dim"], 14);
    assert_eq!(v["joints"][0]["name"], "left_arm_joint1");
    assert_eq!(v["end_effectors"][1]["arm"], "right");
}

#[test]
fn convert_droid_and_agibot_with_skip_report() {
    let tmp = tempfile::tempdir().expect("tmp");
    let d = tmp.path();
    common::raw_fixtures(d);
    // Good and bad DROID episodes together: the bad one is skipped and reported.
    let droid_root = d.join("all_droid");
    std::fs::create_dir_all(&droid_root).expect("mkdir");
    std::fs::rename(d.join("droid"), droid_root.join("good")).expect("mv");
    std::fs::rename(d.join("droid_bad"), droid_root.join("bad")).expect("mv");
    let out = d.join("droid_ds");
    let intrinsics = d.join("droid_intrinsics.json");
    let args = [
        "convert",
        "--format",
        "droid",
        droid_root.to_str().expect("utf8"),
        "--out",
        out.to_str().expect("utf8"),
        "--intrinsics",
        intrinsics.to_str().expect("utf8"),
        "--width",
        "32",
        "--height",
        "24",
    ];
    let o = run(&args);
    assert!(
        !o.status.success(),
        "without --skip-bad the bad episode stops it"
    );
    let err = stderr(&o);
    assert!(
        err.contains("trajectory_length") || err.contains("NaN"),
        "{err}"
    );
    assert!(!out.exists(), "nothing half-written at --out");
    let mut skip = args.to_vec();
    skip.push("--skip-bad");
    let o = run(&skip);
    assert!(o.status.success(), "{}", stderr(&o));
    let text = String::from_utf8_lossy(&o.stdout);
    assert!(
        text.contains("1 episodes read, 2 camera episodes of 32x24")
            && text.contains("skipped 2 item(s)"),
        "{text}"
    );
    assert!(out.join("meta/info.json").is_file() && out.join("skipped.json").is_file());
    assert!(out.join("masks/episode_000001.npy").is_file());
    // Refuses to overwrite, and names the flag that does.
    std::fs::write(out.join("notes.txt"), "mine").expect("write");
    let o = run(&skip);
    assert!(
        stderr(&o).contains("already exists") && stderr(&o).contains("--overwrite"),
        "{}",
        stderr(&o)
    );
    assert!(out.join("notes.txt").is_file());
    let mut replace = skip.clone();
    replace.push("--overwrite");
    let o = run(&replace);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!out.join("notes.txt").exists() && out.join("meta/info.json").is_file());
    // DROID needs intrinsics.
    let o = run(&[
        "convert",
        "--format",
        "droid",
        droid_root.to_str().expect("utf8"),
        "--out",
        d.join("x").to_str().expect("utf8"),
    ]);
    assert!(
        stderr(&o).contains("--intrinsics FILE is required"),
        "{}",
        stderr(&o)
    );

    // AgiBot World onto the built-in dual-arm robot.
    let out = d.join("agibot_ds");
    let o = run(&[
        "convert",
        "--format",
        "agibot",
        d.join("agibot").to_str().expect("utf8"),
        "--out",
        out.to_str().expect("utf8"),
        "--width",
        "32",
        "--height",
        "24",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(String::from_utf8_lossy(&o.stdout).contains("robot agibot-g1"));
    let o = run(&[
        "convert",
        "--format",
        "agibot",
        d.join("agibot").to_str().expect("utf8"),
        "--out",
        d.join("y").to_str().expect("utf8"),
        "--gripper-range",
        "abc",
    ]);
    assert!(
        stderr(&o).contains("--gripper-range \"abc\""),
        "{}",
        stderr(&o)
    );
}

/// `bridgev2w demo` on built-in defaults: masks and overlay, then the shipped
/// world model predicts a clip: an MP4 the project's decoder reads back at
/// the model's size, a side-by-side GIF of four panels.
#[test]
fn demo_predicts_with_the_shipped_model() {
    let (tmp, out, o) = run_demo(&["--steps", "4"]);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(stdout.contains("world model"), "{stdout}");
    // Where the videos are: its own, and the proof run's grids.
    assert!(
        stdout.contains(&format!("{}/prediction.mp4 (H.264)", out.display()))
            && stdout.contains("docs/results/grids/<split>.gif"),
        "{stdout}"
    );
    assert_eq!(npy_shape(&out.join("masks.npy")).1, vec![9, 480, 720]);
    let v = bridgev2w_data::video::decode_mp4(&out.join("prediction.mp4")).expect("demo test");
    assert_eq!((v.frames.len(), v.width, v.height), (9, 96, 64));
    // Not a blank video: the prediction has structure.
    let f = &v.frames[4];
    let mean = f.iter().map(|&x| f64::from(x)).sum::<f64>() / f.len() as f64;
    let var = f
        .iter()
        .map(|&x| (f64::from(x) - mean).powi(2))
        .sum::<f64>()
        / f.len() as f64;
    assert!(var > 25.0, "flat prediction frame: variance {var}");
    let gif = image::open(out.join("prediction.gif")).expect("demo test");
    assert_eq!((gif.width(), gif.height()), (4 * 96 * 3, 64 * 3));
    let actions: Vec<Vec<f64>> = serde_json::from_str(
        &std::fs::read_to_string(out.join("prediction-actions.json")).expect("demo test"),
    )
    .expect("demo test");
    assert_eq!((actions.len(), actions[0].len()), (9, 7));
    // Scored against its ground truth, next to copying the first frame.
    let scores = demo_scores(&out);
    for who in ["prediction", "copy_first_frame"] {
        for what in ["psnr", "ssim", "dynamic_psnr"] {
            assert!(
                scores[who][what].as_f64().is_some_and(f64::is_finite),
                "{scores}"
            );
        }
    }
    assert!(
        stdout.contains("against the ground truth: PSNR"),
        "{stdout}"
    );

    let o = run(&[
        "demo",
        "--model",
        tmp.path().to_str().expect("demo test"),
        "--out",
        out.to_str().expect("demo test"),
    ]);
    assert!(!o.status.success());
    assert!(stderr(&o).contains("expected backbone/"), "{}", stderr(&o));
}

/// `bridgev2w demo --frames 9 ARGS --out TMP/demo-out`, which must succeed.
fn run_demo(args: &[&str]) -> (tempfile::TempDir, std::path::PathBuf, std::process::Output) {
    let tmp = tempfile::tempdir().expect("demo test");
    let out = tmp.path().join("demo-out");
    let mut line = vec!["demo", "--frames", "9"];
    line.extend_from_slice(args);
    line.extend_from_slice(&["--out", out.to_str().expect("demo test")]);
    let o = run(&line);
    assert!(o.status.success(), "{}", stderr(&o));
    (tmp, out, o)
}

/// `prediction-scores.json` of a demo output folder.
fn demo_scores(out: &std::path::Path) -> serde_json::Value {
    serde_json::from_str(
        &std::fs::read_to_string(out.join("prediction-scores.json")).expect("demo scores"),
    )
    .expect("demo scores")
}

/// The shipped model predicts the demo clip (its default 2 steps) better
/// than copying the first frame, which knows nothing of the motion: on the
/// predicted frames (frame 0 is the input) and on the pixels that move
/// (2026-11-27, the link-coded wide model: 26.10 vs 20.80 dB, dynamic
/// 18.92 vs 11.96 dB).
#[test]
fn demo_prediction_beats_copying_the_first_frame() {
    let (_tmp, out, _) = run_demo(&[]);
    let scores = demo_scores(&out);
    let score = |who: &str, what: &str| scores[who][what].as_f64().expect("demo scores");
    assert!(
        score("prediction", "psnr") >= score("copy_first_frame", "psnr"),
        "{scores}"
    );
    assert!(
        score("prediction", "dynamic_psnr") > score("copy_first_frame", "dynamic_psnr"),
        "{scores}"
    );
}

#[test]
fn plan_with_the_perfect_model_and_bad_plan_options() {
    let words = |line: &str| run(&line.split_whitespace().collect::<Vec<_>>());
    // A tiny run: 1 trial, 8 samples, 1 iteration, 2 actions, the view
    // limited and traced.
    let tmp = tempfile::tempdir().expect("plan test");
    let trace = tmp.path().join("trace");
    let line = format!(
        "plan --task reach --model perfect --trials 1 --samples 8 --elites 2 --iters 1 \
         --max-steps 2 --waypoints 1 --episode-frames 9 --view-margin 0.1 --trace {}",
        trace.display()
    );
    let out = words(&line);
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stdout.contains("reach: planner (perfect)")
            && stdout.contains("random actions")
            && stdout.contains("deg off"),
        "{stdout}"
    );
    assert!(stderr.contains("reach trial 0: planner"), "{stderr}");
    // The trace: a JSON line per trial, a row per executed step, and a
    // filmstrip of 3 frames (96 wide, 2-pixel gaps) by one row per step.
    let jsonl = std::fs::read_to_string(trace.join("trials.jsonl")).expect("trace");
    let t: serde_json::Value = serde_json::from_str(jsonl.trim()).expect("one JSON line");
    assert_eq!(t["trial"], 0);
    assert_eq!(t["task"], "reach");
    let steps = t["steps"].as_array().expect("steps");
    assert!(!steps.is_empty() && steps.len() <= 2, "{t}");
    for s in steps {
        assert!(
            s["observed_cost"].as_f64().is_some_and(f64::is_finite),
            "{s}"
        );
        assert!(s["task_error_m"].as_f64().is_some(), "{s}");
        assert_eq!(s["ee"].as_array().map(Vec::len), Some(7), "{s}");
    }
    assert_eq!(t["goal_tcp_m"].as_array().map(Vec::len), Some(4), "{t}");
    let png = std::fs::read(trace.join("trial-0.png")).expect("filmstrip");
    let (w, h, _) = bridgev2w_io::png::decode_rgb8(&png).expect("PNG");
    let rows = steps.len() as u32;
    assert_eq!((w, h), (3 * 96 + 4, rows * 64 + (rows - 1) * 2));
    // A trace is never overwritten.
    let out = words(&line);
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && e.contains("--trace") && e.contains("already exists"),
        "{e}"
    );
    // A margin that leaves nothing of the image.
    let out = words("plan --task reach --model perfect --trials 1 --view-margin 0.6");
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && e.contains("--view-margin") && e.contains("0.6"),
        "{e}"
    );
    // k > S.
    let out = words("plan --task reach --model perfect --samples 4 --elites 8");
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && e.contains("elite"), "{e}");
    // Unknown task in plan-report.
    let out = words("plan-report --tasks reach,fly --trials 1");
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && e.contains("fly"), "{e}");
    // A trained-model folder without its files, before any planning.
    let out = words(&format!(
        "plan-report --tasks reach --trials 1 --trained {}",
        tmp.path().display()
    ));
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && e.contains("expected backbone/"),
        "{e}"
    );
}

/// `plan-report --trained DIR`: the shipped model plans and evaluates
/// policies next to the perfect one, each a row / table of its own.
#[test]
fn plan_report_with_the_shipped_trained_model() {
    let tmp = tempfile::tempdir().expect("plan-report test");
    let md = tmp.path().join("results.md");
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo-model");
    // The folder's own weights named as the planning weights: the row says so.
    let line = format!(
        "plan-report --tasks reach --trials 1 --samples 4 --elites 2 --iters 1 --max-steps 1 \
         --waypoints 0 --eval-trials 1 --denoise-steps 1 --plan-clip-frames 3 --trained {} \
         --plan-weights {} --section planning-shipped --out {}",
        model.display(),
        model.join("bridgev2w.safetensors").display(),
        md.display()
    );
    let out = run(&line.split_whitespace().collect::<Vec<_>>());
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-report test");
    // The heading names the planning weights too, as the table does.
    let heading = text
        .lines()
        .find(|l| l.starts_with("## "))
        .expect("a heading");
    assert!(
        heading.contains(": perfect, trained (`") && heading.contains("`, planning weights `"),
        "{heading}"
    );
    assert!(text.contains("| reach | perfect | "), "{text}");
    assert!(
        text.contains("| reach | trained (`") && text.contains("`, planning weights `"),
        "{text}"
    );
    // The planners predicted 3-frame clips (the model trained on 9).
    assert!(
        text.contains("each candidate predicted as a clip of 3 frames"),
        "{text}"
    );
    assert!(text.contains("#### Model: perfect"), "{text}");
    assert!(
        text.contains("#### Model: trained (`")
            && text.contains("(1 denoising steps, shared noise)"),
        "{text}"
    );
    assert!(
        text.contains("| world-model goal progress |")
            && text.contains("Goal progress vs synthetic-world success: MMRV"),
        "{text}"
    );
}

/// `plan-report --plan-weights FILE`: the planner loads that file (a broken
/// one stops the run, named), and it is refused up front where no trained
/// model plans or the file is missing.
#[test]
fn plan_report_plan_weights_are_the_planners() {
    let tmp = tempfile::tempdir().expect("plan-report test");
    let md = tmp.path().join("results.md");
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo-model");
    let broken = tmp.path().join("broken-plan.safetensors");
    std::fs::write(&broken, b"not a safetensors file").expect("plan-report test");
    let missing = tmp.path().join("missing.safetensors");
    let common = "--tasks reach --trials 1 --samples 4 --elites 2 --iters 1 --max-steps 1 \
                  --waypoints 0 --eval-trials 1 --denoise-steps 1";
    for (models, weights, want) in [
        ("trained", &broken, "broken-plan.safetensors"),
        ("trained", &missing, "expected a BridgeV2W weights file"),
        ("perfect", &broken, "only a trained model that plans"),
    ] {
        let trained = match models {
            "trained" => format!("--trained {}", model.display()),
            _ => String::new(),
        };
        let line = format!(
            "plan-report {common} --models {models} {trained} --plan-weights {} --out {}",
            weights.display(),
            md.display()
        );
        let out = run(&line.split_whitespace().collect::<Vec<_>>());
        let e = stderr(&out);
        assert!(!out.status.success() && e.contains(want), "{line}: {e}");
        assert!(
            !md.exists(),
            "{line}: a failed report wrote {}",
            md.display()
        );
    }
}

/// `plan-report --models/--section`: the chosen models only, in their own
/// section; bad lists and names are refused before any planning.
#[test]
fn plan_report_models_and_section() {
    let words = |line: &str| run(&line.split_whitespace().collect::<Vec<_>>());
    let tmp = tempfile::tempdir().expect("plan-report test");
    let md = tmp.path().join("results.md");
    let out = words(&format!(
        "plan-report --models perfect --section planning-small --tasks reach --trials 1 \
         --samples 4 --elites 2 --iters 1 --max-steps 1 --waypoints 0 --eval-trials 1 --out {}",
        md.display()
    ));
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-report test");
    assert!(
        text.contains("<!-- section: planning-small -->")
            && !text.contains("<!-- section: planning -->"),
        "{text}"
    );
    assert!(
        text.contains(": perfect\n") && text.contains("| reach | perfect | "),
        "{text}"
    );
    // The section's figures, in the folder named after the results file.
    for name in [
        "planning-small-planner-vs-random.png",
        "planning-small-policy-evaluation.png",
    ] {
        let png = image::open(tmp.path().join("results/figures").join(name)).expect(name);
        assert!(png.width() > 100 && png.height() > 100, "{name}");
        assert!(
            text.contains(&format!("(results/figures/{name})")),
            "{text}"
        );
    }
    // --trials 0: the policy evaluation alone, in its own section.
    let out = words(&format!(
        "plan-report --models perfect --section policies --trials 0 --eval-trials 1 --out {}",
        md.display()
    ));
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-report test");
    let policies = text
        .split("<!-- section: policies -->")
        .nth(1)
        .expect("the policies section");
    assert!(
        policies.contains("## Policy evaluation in the synthetic world: perfect")
            && !policies.contains("Goal-image CEM-MPC")
            && policies.contains("| scripted(offset 50 mm) | "),
        "{text}"
    );
    assert!(text.contains("<!-- section: planning-small -->"), "{text}");
    // --eval-trials 0: the planning alone (no policy table, no policy figure).
    let out = words(&format!(
        "plan-report --models perfect --section plans --tasks reach --trials 1 \
         --samples 4 --elites 2 --iters 1 --max-steps 1 --waypoints 0 --eval-trials 0 --out {}",
        md.display()
    ));
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-report test");
    let plans = text
        .split("<!-- section: plans -->")
        .nth(1)
        .and_then(|s| s.split("<!-- end section: plans -->").next())
        .expect("the plans section");
    assert!(
        plans.contains("## Goal-image planning in the synthetic world: perfect")
            && plans.contains("| reach | perfect | ")
            && !plans.contains("Policy evaluation")
            && !plans.contains("plans-policy-evaluation.png"),
        "{plans}"
    );
    assert!(!tmp
        .path()
        .join("results/figures/plans-policy-evaluation.png")
        .exists());
    let out = words(&format!(
        "plan-report --models perfect --trials 0 --eval-trials 0 --out {}",
        md.display()
    ));
    let e = stderr(&out);
    assert!(
        !out.status.success() && e.contains("nothing to report"),
        "{e}"
    );
    for (line, want) in [
        ("--models trained", "needs --trained"),
        ("--models perfect,fly", "unknown model \"fly\""),
        ("--models perfect,perfect", "named twice"),
        ("--models random", "expected perfect or trained"),
        ("--section a/b", "--section \"a/b\""),
    ] {
        let out = words(&format!(
            "plan-report --tasks reach --trials 1 {line} --out {}",
            md.display()
        ));
        let e = stderr(&out);
        assert!(!out.status.success() && e.contains(want), "{line}: {e}");
    }
}

/// `plan-fidelity`: the perfect model orders candidates exactly as the
/// world does (Spearman 1); bad sizes are refused.
#[test]
fn plan_fidelity_of_the_perfect_model() {
    let words = |line: &str| run(&line.split_whitespace().collect::<Vec<_>>());
    let tmp = tempfile::tempdir().expect("plan-fidelity test");
    let md = tmp.path().join("results.md");
    let out = words(&format!(
        "plan-fidelity --model perfect --trials 2 --candidates 6 --out {}",
        md.display()
    ));
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-fidelity test");
    assert!(
        text.contains("<!-- section: planning-fidelity -->")
            && text.contains("| perfect | 1.00 ± 0.00 | "),
        "{text}"
    );
    assert!(
        stderr(&out).contains("reach trial 1: Spearman"),
        "{}",
        stderr(&out)
    );
    let out = words("plan-fidelity --model perfect --candidates 1");
    assert!(
        !out.status.success() && stderr(&out).contains("--candidates 1"),
        "{}",
        stderr(&out)
    );
    // A diffusion model's goal distances on the image pyramid, said in the
    // section; an unknown goal latent is refused with the choices.
    let out = words(&format!(
        "plan-fidelity --model random --trials 1 --candidates 3 --denoise-steps 1 \
         --goal-latent pyramid --device cpu --out {}",
        md.display()
    ));
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-fidelity test");
    assert!(
        text.contains("goal distances on a Gaussian pyramid of the image")
            && text.contains("| random | "),
        "{text}"
    );
    // A clip the random model's VAE cannot decode (it compresses time 4x).
    let out = words("plan-fidelity --model random --clip-frames 4 --device cpu");
    let e = stderr(&out);
    assert!(
        !out.status.success() && e.contains("frames") && e.contains("4k + 1"),
        "{e}"
    );
    let out = words("plan-fidelity --model random --goal-latent vae");
    let e = stderr(&out);
    assert!(
        !out.status.success() && e.contains("goal latent") && e.contains("model, pyramid"),
        "{e}"
    );
}

#[test]
fn a_mesh_parser_panic_is_a_clean_error_without_the_panic_message() {
    let dir = tempfile::tempdir().expect("tmp");
    let mesh = Path::new(env!("CARGO_MANIFEST_DIR")).join(
        "../embodiment/tests/data/mesh/regressions/collada_instance_rs129_position_index_oob.dae",
    );
    std::fs::copy(&mesh, dir.path().join("bad.dae")).expect("copy");
    let urdf = write(
        dir.path(),
        "r.urdf",
        r#"<robot name="r"><link name="a"><visual><geometry><mesh filename="bad.dae"/></geometry></visual></link></robot>"#,
    );
    let o = run(&["robot-info", "--robot", &urdf]);
    let err = stderr(&o);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("bad.dae") && err.contains("parser panicked"),
        "{err}"
    );
    assert!(!err.contains("panicked at"), "{err}");
}

#[test]
fn a_bad_cpu_cache_setting_stops_naming_the_variable() {
    let bad = bin()
        .args(["robot-info", "--robot", "franka"])
        .env("BRIDGEV2W_CPU_CACHE_MB", "lots")
        .output()
        .expect("run");
    assert!(!bad.status.success());
    let e = stderr(&bad);
    assert!(
        e.contains("BRIDGEV2W_CPU_CACHE_MB") && e.contains("lots") && e.contains("megabytes"),
        "{e}"
    );
}

#[test]
fn a_bad_cpu_bf16_setting_stops_naming_the_variable_and_the_choices() {
    let run = |v: &str| {
        bin()
            .args(["robot-info", "--robot", "franka"])
            .env("BRIDGEV2W_CPU_BF16", v)
            .output()
            .expect("run")
    };
    let bad = run("fast");
    assert!(!bad.status.success());
    let e = stderr(&bad);
    assert!(
        e.contains("BRIDGEV2W_CPU_BF16")
            && e.contains("\"fast\"")
            && e.contains("auto, native, f32"),
        "{e}"
    );
    for good in ["auto", "native", " f32 "] {
        assert!(
            run(good).status.success(),
            "{good:?}: {}",
            stderr(&run(good))
        );
    }
}
