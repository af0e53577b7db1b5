//! The `bridgev2w` binary: the masks contract, robot-info and bad input.

use std::path::Path;
use std::process::{Command, Output};

use crate::common;

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
        // Joints past their limits are rendered and reported, not refused:
        // see masks_cameras.rs.
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
        !o.status.success() && stderr(&o).contains("franka, dual-arm"),
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
    let o = run(&["robot-info", "--robot", "dual-arm", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let v: serde_json::Value = serde_json::from_slice(&o.stdout).expect("json");
    assert_eq!(v["action_dim"], 14);
    assert_eq!(v["joints"][0]["name"], "left_arm_joint1");
    assert_eq!(v["end_effectors"][1]["arm"], "right");
    // `--list` (which `--robot`'s help points to): every built-in robot,
    // each of which `--robot NAME` then loads.
    let o = run(&["robot-info", "--list", "--json"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let list: serde_json::Value = serde_json::from_slice(&o.stdout).expect("json");
    let names: Vec<&str> = list
        .as_array()
        .expect("array")
        .iter()
        .map(|r| r["name"].as_str().expect("name"))
        .collect();
    assert_eq!(names, ["franka", "dual-arm", "agibot-g1", "franka-robotiq"]);
    let text = String::from_utf8_lossy(&run(&["robot-info", "--list"]).stdout).to_string();
    for name in names {
        assert!(text.contains(&format!("  {name} ")), "{text}");
        assert!(
            run(&["robot-info", "--robot", name]).status.success(),
            "{name}"
        );
    }
    let o = run(&["robot-info", "--list", "--robot", "franka"]);
    assert!(!o.status.success() && stderr(&o).contains("cannot be used with"));
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
        stderr(&o).contains("intrinsics: a file is required for DROID"),
        "{}",
        stderr(&o)
    );

    // AgiBot World onto the built-in (real) AgiBot G1.
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

    let not_a_model = tmp.path().join("not-a-model");
    std::fs::create_dir(&not_a_model).expect("demo test");
    let o = run(&[
        "demo",
        "--model",
        not_a_model.to_str().expect("demo test"),
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

/// Sizes no machine gives inside `bench model`: a batch beyond
/// `MAX_PREDICT_BATCH` is refused by name, and a batch within it whose
/// memory floor exceeds this machine's is refused up front with the
/// estimate, what is available and what lowers it; nothing is allocated,
/// no panic, no backtrace. (Out-of-memory inside libtorch, reachable on a
/// GPU, is mapped to the same kind of error: `world-model` unit tests.)
#[test]
fn bench_model_out_of_memory_is_a_clean_error_naming_the_shapes() {
    let o = run(&[
        "bench",
        "model",
        "--layers",
        "1",
        "--batch",
        "10000000000",
        "--no-diffusers",
    ]);
    let err = stderr(&o);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("--batch 10000000000: at most 4096 clips is supported"),
        "{err}"
    );
    assert!(
        !err.contains("panicked") && !err.contains("frame #"),
        "{err}"
    );
    let o = run(&[
        "bench",
        "model",
        "--layers",
        "1",
        "--batch",
        "4096",
        "--frames",
        "1021",
        "--height",
        "8192",
        "--width",
        "8192",
        "--no-diffusers",
    ]);
    let err = stderr(&o);
    assert!(!o.status.success(), "{err}");
    assert!(
        err.contains("timing the model at batch 4096 of 1021 frames at 8192x8192 needs at least")
            && err.contains("is available")
            && err.contains("Lower --batch"),
        "{err}"
    );
    assert!(
        !err.contains("panicked") && !err.contains("frame #"),
        "{err}"
    );
}

/// `bench model --diffusers-limit`: a diffusers run still going at the
/// limit (here still importing torch after 1 s; then the operations left
/// in a new process, three in all, each accepting its `--ops`) is stopped, and the table
/// says what did not run; the limit must be whole positive seconds and
/// needs diffusers.
#[test]
fn bench_model_stops_diffusers_at_its_limit_and_says_what_did_not_run() {
    let tiny = [
        "bench", "model", "--layers", "1", "--frames", "1", "--height", "16", "--width", "16",
    ];
    let o = run(&[&tiny[..], &["--diffusers-limit", "1"]].concat());
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{out}{}", stderr(&o));
    for op in ["transformer forward (b1)", "VAE encode", "VAE decode"] {
        let row = out.lines().find(|l| l.starts_with(op)).unwrap_or_default();
        assert!(row.contains("not run"), "{op}: {out}");
    }
    assert!(
        out.contains("diffusers was stopped at --diffusers-limit 1 (a limit for each"),
        "{out}"
    );
    for bad in [
        &["--diffusers-limit", "0"][..],
        &["--diffusers-limit", "5", "--no-diffusers"],
    ] {
        let o = run(&[&tiny[..], bad].concat());
        assert_eq!(o.status.code(), Some(2), "{bad:?}: {}", stderr(&o));
        assert!(stderr(&o).contains("--diffusers-limit"), "{}", stderr(&o));
    }
}

/// `bench model --precision f32,bf16`: both precisions in one run, each
/// one's table, then the speed-ups side by side (here `-`: diffusers was
/// stopped before it timed anything); a precision named twice is refused.
#[test]
fn bench_model_runs_several_precisions_in_one_call() {
    let tiny = [
        "bench", "model", "--layers", "1", "--frames", "1", "--height", "16", "--width", "16",
    ];
    let o = run(&[
        &tiny[..],
        &["--precision", "f32,bf16", "--diffusers-limit", "1"],
    ]
    .concat());
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{out}{}", stderr(&o));
    assert!(
        out.contains(", F32 on Cpu") && out.contains(", Bf16 on Cpu"),
        "{out}"
    );
    let summary = out
        .split("speed-up over diffusers")
        .nth(1)
        .unwrap_or_default();
    let rows: Vec<&str> = summary.lines().skip(2).collect();
    assert_eq!(rows.len(), 2, "{out}");
    for (row, precision) in rows.iter().zip(["f32", "bf16"]) {
        let cells: Vec<&str> = row.split_whitespace().collect();
        assert_eq!(cells, [precision, "-", "-", "-"], "{out}");
    }
    let o = run(&[
        &tiny[..],
        &[
            "--precision",
            "bf16",
            "--precision",
            "bf16",
            "--no-diffusers",
        ],
    ]
    .concat());
    assert!(!o.status.success());
    assert!(
        stderr(&o).contains("--precision: bf16,bf16: bf16 is named twice"),
        "{}",
        stderr(&o)
    );
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

/// The binary stays thin (issue 73): command files parse, call one library
/// function and print; the work lives in the library crates, at most 2,500
/// lines of CLI in all.
#[test]
fn the_cli_crate_stays_thin() {
    fn lines(dir: &Path) -> usize {
        std::fs::read_dir(dir)
            .expect("read_dir")
            .map(|e| e.expect("entry").path())
            .map(|p| match p.extension() {
                _ if p.is_dir() => lines(&p),
                Some(x) if x == "rs" => std::fs::read_to_string(&p).expect("read").lines().count(),
                _ => 0,
            })
            .sum()
    }
    let n = lines(&Path::new(env!("CARGO_MANIFEST_DIR")).join("src"));
    assert!(
        (1000..=2500).contains(&n),
        "crates/cli/src holds {n} lines: at most 2,500 (move file work into the libraries)"
    );
}
