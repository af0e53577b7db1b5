//! `bridgev2w masks` with moving cameras (a pose per frame, a camera mounted
//! on a link), flange end effectors, out-of-limit joints, and `bridgev2w
//! overlay` scoring its own masks.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use bridgev2w_io::npy::{read_npy, write_npy};
use std::path::Path;
use std::process::{Command, Output};

fn run(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
        .args(args)
        .env("RUST_BACKTRACE", "0")
        .output()
        .expect("run bridgev2w")
}

fn ok(o: &Output) -> String {
    assert!(
        o.status.success(),
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    String::from_utf8_lossy(&o.stderr).into_owned()
}

const POSE_A: [[f64; 4]; 4] = [
    [-0.3939, 0.3019, -0.8682, 1.7],
    [0.9191, 0.1294, -0.3721, 0.6],
    [0.0, -0.9445, -0.3284, 1.0],
    [0.0, 0.0, 0.0, 1.0],
];
/// POSE_A turned 20 degrees about the world z axis.
fn pose_b() -> [[f64; 4]; 4] {
    let (c, s) = (20f64.to_radians().cos(), 20f64.to_radians().sin());
    let mut m = POSE_A;
    for col in 0..4 {
        let (x, y) = (POSE_A[0][col], POSE_A[1][col]);
        m[0][col] = c * x - s * y;
        m[1][col] = s * x + c * y;
    }
    m
}

fn camera_json(pose: serde_json::Value) -> String {
    let mut v = serde_json::json!({"fx": 120, "fy": 120, "cx": 63.5, "cy": 47.5, "width": 128, "height": 96});
    for (k, x) in pose.as_object().unwrap() {
        v[k] = x.clone();
    }
    v.to_string()
}

const HOME: [f64; 8] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785, 0.04];

fn write(dir: &Path, name: &str, text: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p.display().to_string()
}

fn labels(dir: &Path) -> (Vec<usize>, Vec<f64>) {
    let a = read_npy(&dir.join("labels.npy")).unwrap();
    (a.shape, a.data)
}

fn masks(dir: &Path, out: &str, camera: &str, joints: &str, extra: &[&str]) -> Output {
    let mut args = vec![
        "masks", "--robot", "franka", "--camera", camera, "--joints", joints, "--width", "128",
        "--height", "96", "--no-png", "--out",
    ];
    let out = dir.join(out).display().to_string();
    args.push(&out);
    args.extend_from_slice(extra);
    run(&args)
}

#[test]
fn a_camera_moving_per_frame_renders_each_frame_from_its_pose() {
    let d = tempfile::tempdir().unwrap();
    let joints = write(
        d.path(),
        "q.json",
        &serde_json::to_string(&vec![HOME; 2]).unwrap(),
    );
    let one = write(
        d.path(),
        "q1.json",
        &serde_json::to_string(&vec![HOME]).unwrap(),
    );
    let a = write(
        d.path(),
        "a.json",
        &camera_json(serde_json::json!({"world_from_camera": POSE_A})),
    );
    let b = write(
        d.path(),
        "b.json",
        &camera_json(serde_json::json!({"world_from_camera": pose_b()})),
    );
    let per_frame = write(
        d.path(),
        "ab.json",
        &camera_json(serde_json::json!({"world_from_camera_per_frame": [POSE_A, pose_b()]})),
    );
    ok(&masks(d.path(), "fa", &a, &one, &[]));
    ok(&masks(d.path(), "fb", &b, &one, &[]));
    ok(&masks(d.path(), "moving", &per_frame, &joints, &[]));
    let (shape, moving) = labels(&d.path().join("moving"));
    let n = shape[1] * shape[2];
    let (_, fa) = labels(&d.path().join("fa"));
    let (_, fb) = labels(&d.path().join("fb"));
    assert_eq!(&moving[..n], &fa[..], "frame 0 from pose A");
    assert_eq!(&moving[n..], &fb[..], "frame 1 from pose B");
    assert_ne!(fa, fb, "the two poses see different masks");

    // The same poses from a [T, 4, 4] .npy (--camera-poses).
    let flat: Vec<f64> = [POSE_A, pose_b()]
        .iter()
        .flatten()
        .flatten()
        .copied()
        .collect();
    let npy = d.path().join("poses.npy");
    write_npy(&npy, &[2, 4, 4], &flat).unwrap();
    ok(&masks(
        d.path(),
        "npy",
        &a,
        &joints,
        &["--camera-poses", npy.to_str().unwrap()],
    ));
    assert_eq!(labels(&d.path().join("npy")).1, moving);

    // One pose too few: an error naming both counts.
    write_npy(&npy, &[1, 4, 4], &flat[..16]).unwrap();
    let o = masks(
        d.path(),
        "short",
        &a,
        &joints,
        &["--camera-poses", npy.to_str().unwrap()],
    );
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("1 poses") && e.contains("(2)"),
        "{e}"
    );
}

#[test]
fn a_camera_mounted_on_a_link_moves_with_it() {
    let d = tempfile::tempdir().unwrap();
    let joints = write(
        d.path(),
        "q.json",
        &serde_json::to_string(&vec![HOME]).unwrap(),
    );
    let fixed = write(
        d.path(),
        "a.json",
        &camera_json(serde_json::json!({"world_from_camera": POSE_A})),
    );
    // On the base link (the world frame) at POSE_A: the fixed camera.
    let base = write(
        d.path(),
        "base.json",
        &camera_json(serde_json::json!({"parent_link": "panda_link0", "link_from_camera": POSE_A})),
    );
    ok(&masks(d.path(), "fixed", &fixed, &joints, &[]));
    ok(&masks(d.path(), "base", &base, &joints, &[]));
    assert_eq!(
        labels(&d.path().join("base")).1,
        labels(&d.path().join("fixed")).1
    );
    // A wrist camera behind the hand, looking along the fingers: it sees
    // the fingers in every configuration.
    let wrist = write(
        d.path(),
        "wrist.json",
        &camera_json(
            serde_json::json!({"parent_link": "panda_hand", "link_from_camera":
            [[1, 0, 0, 0], [0, 1, 0, 0.0], [0, 0, 1, -0.05], [0, 0, 0, 1]]}),
        ),
    );
    let moved: Vec<[f64; 8]> = (0..3)
        .map(|t| {
            let mut q = HOME;
            q[0] = 0.4 * t as f64;
            q
        })
        .collect();
    let moved = write(
        d.path(),
        "moved.json",
        &serde_json::to_string(&moved).unwrap(),
    );
    ok(&masks(d.path(), "wrist", &wrist, &moved, &[]));
    let (shape, l) = labels(&d.path().join("wrist"));
    let n = shape[1] * shape[2];
    let frames: Vec<&[f64]> = l.chunks(n).collect();
    assert!(frames[0].iter().any(|&x| x != 0.0), "fingers in view");
    assert_eq!(frames[0], frames[2], "the same view as the arm turns");
    // A mount link that does not exist: named in the error.
    let bad = write(
        d.path(),
        "bad.json",
        &camera_json(serde_json::json!({"parent_link": "no_such_link"})),
    );
    let o = masks(d.path(), "bad", &bad, &joints, &[]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("no_such_link") && e.contains("panda_hand"),
        "{e}"
    );
}

#[test]
fn flange_poses_with_ee_link_and_joints_past_their_limits() {
    let d = tempfile::tempdir().unwrap();
    let cam = write(
        d.path(),
        "a.json",
        &camera_json(serde_json::json!({"world_from_camera": POSE_A})),
    );
    // IK to the home pose's flange (panda_link8) pose, from the home pose,
    // through --ee-link: the joints' own masks.
    let joints = write(
        d.path(),
        "q.json",
        &serde_json::to_string(&vec![HOME]).unwrap(),
    );
    ok(&masks(d.path(), "joints", &cam, &joints, &[]));
    let e = bridgev2w_embodiment::embodiment::Embodiment::builtin("franka").unwrap();
    let flange = e.robot.link_index("panda_link8").unwrap();
    let pose = e.robot.link_pose(flange, &HOME);
    let mut row = bridgev2w_embodiment::kinematics::xyz_rpy_from_pose(&pose).to_vec();
    row.push(0.0);
    let actions = write(
        d.path(),
        "actions.json",
        &serde_json::to_string(&vec![row]).unwrap(),
    );
    let mut args = vec![
        "masks",
        "--robot",
        "franka",
        "--ee-link",
        "panda_link8",
        "--camera",
        &cam,
        "--actions",
        &actions,
        "--width",
        "128",
        "--height",
        "96",
        "--no-png",
        "--out",
    ];
    let out = d.path().join("flange").display().to_string();
    args.push(&out);
    ok(&run(&args));
    assert_eq!(
        labels(&d.path().join("flange")).1,
        labels(&d.path().join("joints")).1,
        "IK to the flange pose gives the joints' masks"
    );
    let o = run(&["robot-info", "--robot", "franka", "--json"]);
    let info: serde_json::Value = serde_json::from_slice(&o.stdout).unwrap();
    assert_eq!(info["end_effectors"][0]["flange_link"], "panda_link8");
    // A flange link that is not on the arm's end: refused by name.
    let o = run(&[
        "robot-info",
        "--robot",
        "franka",
        "--ee-link",
        "panda_link3",
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("panda_link3") && e.contains("rigidly"),
        "{e}"
    );

    // Joint 7 past its limit (2.8973): rendered as given, reported.
    let mut q = HOME;
    q[6] = 3.1;
    let past = write(
        d.path(),
        "past.json",
        &serde_json::to_string(&vec![q, HOME]).unwrap(),
    );
    let e = ok(&masks(d.path(), "past", &cam, &past, &[]));
    assert!(
        e.contains("panda_joint7") && e.contains("1 frame(s)") && e.contains("3.1"),
        "{e}"
    );
    let report: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.path().join("past/limits.json")).unwrap())
            .unwrap();
    assert_eq!(report[0]["joint"], "panda_joint7");
    assert_eq!(report[0]["count"], 1);
    assert_eq!(report[0]["worst_value"], 3.1);
}

#[test]
fn overlay_scores_masks_against_a_truth() {
    let d = tempfile::tempdir().unwrap();
    let cam = write(
        d.path(),
        "a.json",
        &camera_json(serde_json::json!({"world_from_camera": POSE_A})),
    );
    let joints = write(
        d.path(),
        "q.json",
        &serde_json::to_string(&vec![HOME; 2]).unwrap(),
    );
    // The masks (with their PNG frames) of the same camera and joints.
    let out = d.path().join("m").display().to_string();
    ok(&run(&[
        "masks", "--robot", "franka", "--camera", &cam, "--joints", &joints, "--width", "128",
        "--height", "96", "--out", &out,
    ]));
    let m = read_npy(&d.path().join("m/masks.npy")).unwrap();
    let robot_pixel = m.data.iter().position(|&v| v != 0.0).unwrap();
    let (u, v) = (robot_pixel % 128, robot_pixel / 128);
    let points = write(
        d.path(),
        "pts.json",
        &serde_json::json!([
            {"frame": 0, "u": u, "v": v, "name": "on the robot"},
            {"frame": 1, "u": 0.0, "v": 0.0, "name": "a corner"}
        ])
        .to_string(),
    );
    let o = run(&[
        "overlay",
        "--robot",
        "franka",
        "--camera",
        &cam,
        "--joints",
        &joints,
        "--frames",
        &format!("{out}/frames"),
        "--truth-masks",
        &format!("{out}/masks.npy"),
        "--truth-points",
        &points,
        "--out",
        d.path().join("o").to_str().unwrap(),
    ]);
    ok(&o);
    let stdout = String::from_utf8_lossy(&o.stdout);
    assert!(
        stdout.contains("mean IoU") && stdout.contains("1.0000"),
        "{stdout}"
    );
    assert!(stdout.contains("1 of 2"), "{stdout}");
    let scores: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(d.path().join("o/scores.json")).unwrap())
            .unwrap();
    assert_eq!(scores["per_point"][0]["inside"], true);
    assert_eq!(scores["per_point"][1]["inside"], false);
    assert!(d.path().join("o/overlay/000001.png").is_file());
    assert!(d.path().join("o/overlay.gif").is_file());
    // Frame counts that differ: an error naming both.
    let one = write(
        d.path(),
        "q1.json",
        &serde_json::to_string(&vec![HOME]).unwrap(),
    );
    let o = run(&[
        "overlay",
        "--robot",
        "franka",
        "--camera",
        &cam,
        "--joints",
        &one,
        "--frames",
        &format!("{out}/frames"),
        "--out",
        d.path().join("o2").to_str().unwrap(),
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("2 real frames") && e.contains("1 joint"),
        "{e}"
    );
    assert!(!d.path().join("o2").exists(), "nothing written");
}
