//! The raw readers on the data as it is really published: DROID's calibration
//! files (`intrinsics.json`, `cam2base_extrinsics.json`, the superset), video
//! frame counts that differ from the states, AgiBot World's gripper readings
//! and dexterous hands, joints outside the robot model's limits. Episodes
//! come from `scripts/fixtures/write_raw_episodes.py` (h5py in the project
//! venv); videos from the project's H.264 encoder.

use bridgev2w_data::lerobot::LeRobotDataset;
use bridgev2w_data::raw::agibot::{self, AgibotOptions, EpisodeKey, GripperSource};
use bridgev2w_data::raw::convert::{convert, ConvertOptions, REPORT_FILE};
use bridgev2w_data::raw::droid::{self, DroidOptions};
use bridgev2w_data::raw::droid_calibration::MissingCalibration;
use bridgev2w_data::raw::report::{AlignMethod, Eye, Note};
use bridgev2w_data::raw::RawEpisode;
use bridgev2w_data::video::write_test_pattern;
use bridgev2w_embodiment::camera::world_from_camera_from_xyz_rpy;
use bridgev2w_embodiment::embodiment::Embodiment;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// The fixture episodes with `frames`-frame videos of `(w, h)` (the DROID
/// videos 16:9 like DROID's 1280x720), and `expected.json`.
fn fixtures() -> (tempfile::TempDir, Value) {
    let python = repo_root().join(".venv/bin/python");
    assert!(
        python.is_file(),
        "{} not found: run scripts/setup-venv.sh (./run test does)",
        python.display()
    );
    let dir = tempfile::tempdir().expect("tempdir");
    let status = Command::new(&python)
        .arg(repo_root().join("scripts/fixtures/write_raw_episodes.py"))
        .arg(dir.path())
        .status()
        .expect("run python");
    assert!(status.success(), "write_raw_episodes.py failed");
    let expected: Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("expected.json")).expect("expected.json"),
    )
    .expect("json");
    for v in expected["videos"].as_array().expect("videos") {
        let p = Path::new(v.as_str().expect("path"));
        let size = if p.to_string_lossy().contains("/droid") {
            (64, 36)
        } else {
            (64, 48)
        };
        write_test_pattern(p, size, 6, 15).expect("mp4");
    }
    (dir, expected)
}

fn f64s(v: &Value) -> Vec<f64> {
    v.as_array()
        .expect("array")
        .iter()
        .map(|x| x.as_f64().expect("number"))
        .collect()
}

fn strs(v: &Value) -> Vec<String> {
    v.as_array()
        .expect("array")
        .iter()
        .map(|x| x.as_str().expect("string").to_string())
        .collect()
}

fn pose(v: &Value) -> nalgebra::Isometry3<f64> {
    let p = f64s(v);
    world_from_camera_from_xyz_rpy([p[0], p[1], p[2], p[3], p[4], p[5]])
}

fn close(a: &nalgebra::Isometry3<f64>, b: &nalgebra::Isometry3<f64>) -> bool {
    (a.translation.vector - b.translation.vector).norm() < 1e-9
        && a.rotation.angle_to(&b.rotation) < 1e-9
}

fn options(dir: &Path, files: &[&str]) -> DroidOptions {
    let pub_dir = dir.join("droid_published");
    let files: Vec<PathBuf> = files.iter().map(|f| pub_dir.join(f)).collect();
    DroidOptions::from_calibration_files(&pub_dir.join("intrinsics.json"), &files)
        .expect("published calibration files")
}

fn opts(source_format: &str) -> ConvertOptions {
    ConvertOptions {
        width: 32,
        height: 18,
        fps: 15,
        joint_names: None,
        skip_bad: true,
        split: None,
        source_format: source_format.into(),
        overwrite: false,
    }
}

fn notes_of<'a>(ep: &'a RawEpisode, kind: &str) -> Vec<&'a Note> {
    ep.notes
        .iter()
        .filter(|n| n.note.kind() == kind)
        .map(|n| &n.note)
        .collect()
}

#[test]
fn droid_published_calibration_files_are_read_as_published() {
    let (dir, expected) = fixtures();
    let d = &expected["droid"];
    let p = &d["published"];
    let serials = strs(&d["serials"]);
    let ep_dir = PathBuf::from(d["dir"].as_str().expect("dir"));
    let o = options(
        dir.path(),
        &[
            "cam2base_extrinsics.json",
            "cam2base_extrinsic_superset.json",
        ],
    );
    let ep = droid::read_episode(&ep_dir, &o).expect("read");
    assert_eq!(
        ep.id,
        d["uuid"].as_str().expect("uuid"),
        "the episode id is the metadata uuid"
    );
    assert_eq!(ep.ee_frames, vec!["panda_link8".to_string()]);

    // intrinsics.json is [fx, cx, fy, cy] at 1280x720: 620, 639.5, 610, 359.5
    // (read as fx, fy, cx, cy it would give fy = 639.5).
    let k = ep.views[0].intrinsics;
    assert_eq!(
        f64s(&p["intrinsics"][&serials[0]]),
        vec![620.0, 639.5, 610.0, 359.5]
    );
    assert_eq!((k.fx, k.cx, k.fy, k.cy), (620.0, 639.5, 610.0, 359.5));
    assert_eq!((k.width, k.height), (1280, 720));

    // ext1: the bare serial of cam2base_extrinsics.json (its quality fields
    // ignored) is the left image's pose, used for every frame.
    let v0 = &ep.views[0];
    assert!(v0.is_static());
    assert!(close(&v0.world_from_camera[3], &pose(&p["ext1"])));
    // ext2: a right-eye pose in the superset, moved to the left eye with the
    // recorded stereo offset (0.12 m): the left pose the fixture built it from.
    let v1 = &ep.views[1];
    assert!(
        close(&v1.world_from_camera[0], &pose(&p["ext2_left"])),
        "{:?}",
        v1.world_from_camera[0]
    );
    let cal = notes_of(&ep, "calibration");
    assert_eq!(cal.len(), 2);
    assert!(
        matches!(cal[0], Note::Calibration { eye: Eye::Left, right_to_left: false, extrinsics, .. } if extrinsics.contains("cam2base_extrinsics.json"))
    );
    assert!(
        matches!(cal[1], Note::Calibration { eye: Eye::Right, right_to_left: true, extrinsics, .. } if extrinsics.contains("superset"))
    );
    // The serial of no camera of this episode is a counted warning.
    let unmatched = notes_of(&ep, "calibration_key_unmatched");
    assert_eq!(unmatched.len(), 1, "{:?}", ep.notes);
    assert!(matches!(unmatched[0], Note::CalibrationKeyUnmatched { key, .. } if key == "99999999"));

    // Without the superset, ext2 has no published pose: recorded extrinsics, counted.
    let only = options(dir.path(), &["cam2base_extrinsics.json"]);
    let ep2 = droid::read_episode(&ep_dir, &only).expect("read");
    let missing = notes_of(&ep2, "calibration_missing");
    assert_eq!(missing.len(), 1);
    assert!(
        matches!(missing[0], Note::CalibrationMissing { reason, .. } if reason.contains(&format!("has no key \"{}\"", serials[1])) && reason.contains("recorded extrinsics are used"))
    );
    // ... or refused when asked.
    let strict = DroidOptions {
        missing_calibration: MissingCalibration::Error,
        ..only.clone()
    };
    let err = droid::read_episode(&ep_dir, &strict).expect_err("missing calibration");
    assert!(
        err.to_string()
            .contains(&format!("camera {}: no published extrinsics", serials[1])),
        "{err}"
    );
    // A right-eye pose of a camera whose right extrinsics are not recorded is refused.
    let right = options(dir.path(), &["right_only.json"]);
    let err = droid::read_episode(&ep_dir, &right).expect_err("right eye");
    let msg = err.to_string();
    assert!(
        msg.contains("right eye") && msg.contains(&format!("{}_right", serials[0])),
        "{msg}"
    );

    // Converted: intrinsics scaled 1280x720 -> 64x36 and noted, then to 32x18.
    let out = dir.path().join("pub_out");
    let report = convert(
        vec![(ep.id.clone(), Ok(ep.clone()))],
        &Embodiment::builtin("franka").expect("franka"),
        &out,
        &opts("droid"),
        &|_| {},
    )
    .expect("convert");
    assert_eq!(report.views_written, 2);
    let scaled: Vec<_> = report
        .notes
        .iter()
        .filter(|n| n.note.kind() == "intrinsics_scaled")
        .collect();
    assert_eq!(scaled.len(), 2);
    assert!(
        matches!(&scaled[0].note, Note::IntrinsicsScaled { from: [1280, 720], to: [64, 36], scale, uniform: true } if (scale[0] - 0.05).abs() < 1e-12 && (scale[1] - 0.05).abs() < 1e-12)
    );
    let ds = LeRobotDataset::open(&out).expect("open");
    let cam = ds
        .read_calibration(0, "observation.images.main")
        .expect("static camera");
    assert!(
        (cam.intrinsics.fx - 620.0 * 32.0 / 1280.0).abs() < 1e-9,
        "{:?}",
        cam.intrinsics
    );
    assert!(
        (cam.intrinsics.fy - 610.0 * 18.0 / 720.0).abs() < 1e-9,
        "{:?}",
        cam.intrinsics
    );
    // The metadata names the flange frame; the report file lists the notes.
    let info: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("meta/info.json")).expect("info"))
            .expect("json");
    assert_eq!(
        info["bridgev2w_source"]["ee_frame"],
        serde_json::json!(["panda_link8"])
    );
    assert!(info["bridgev2w_source"]["action"]
        .as_str()
        .expect("action")
        .contains("flange"));
    let file: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join(REPORT_FILE)).expect("report"))
            .expect("json");
    let kinds: Vec<&str> = file["notes"]
        .as_array()
        .expect("notes")
        .iter()
        .filter_map(|n| n["kind"].as_str())
        .collect();
    assert!(
        kinds.contains(&"calibration_key_unmatched") && kinds.contains(&"intrinsics_scaled"),
        "{kinds:?}"
    );
    assert!(out.join("skipped.json").is_file());
}

#[test]
fn droid_frame_counts_are_aligned_by_timestamps_or_refused() {
    let (dir, expected) = fixtures();
    let d = &expected["droid"];
    let serials = strs(&d["serials"]);
    let o = options(dir.path(), &["cam2base_extrinsics.json"]);
    let franka = Embodiment::builtin("franka").expect("franka");
    let src = PathBuf::from(d["dir"].as_str().expect("dir"));
    let copy = |name: &str| {
        let to = dir.path().join(name);
        copy_tree(&src, &to);
        to
    };
    // ext1's video lacks its first frame; its per-frame timestamps say so.
    let ts = copy("ts");
    let times = f64s(&d["frame_received"]);
    let mp4 = ts.join(format!("recordings/MP4/{}.mp4", serials[0]));
    write_test_pattern(&mp4, (64, 36), 5, 15).expect("video");
    std::fs::write(
        ts.join(format!("recordings/MP4/{}_timestamps.json", serials[0])),
        serde_json::to_string(&times[1..]).expect("json"),
    )
    .expect("write");
    // ext1's video of 11 frames for 6 states: refused.
    let long = copy("long");
    let mp4_long = long.join(format!("recordings/MP4/{}.mp4", serials[0]));
    write_test_pattern(&mp4_long, (64, 36), 11, 15).expect("video");
    let items = [ts.clone(), long.clone()]
        .into_iter()
        .map(|p| (p.display().to_string(), droid::read_episode(&p, &o)));
    let report = convert(
        items,
        &franka,
        &dir.path().join("aligned"),
        &opts("droid"),
        &|_| {},
    )
    .expect("convert");
    assert_eq!(report.views_written, 3, "{report:?}");
    let aligned: Vec<_> = report
        .notes
        .iter()
        .filter(|n| n.note.kind() == "frames_aligned")
        .collect();
    assert_eq!(aligned.len(), 1, "{:?}", report.notes);
    match &aligned[0].note {
        Note::FramesAligned {
            video_frames,
            states,
            frames_used,
            method,
            dropped_states,
            dropped_video_frames,
            ..
        } => {
            assert_eq!((*video_frames, *states, *frames_used), (5, 6, 5));
            assert_eq!(*method, AlignMethod::Timestamps);
            assert_eq!(
                dropped_states,
                &vec![0],
                "the first state has no frame (truncation would drop the last)"
            );
            assert!(dropped_video_frames.is_empty());
        }
        other => panic!("{other:?}"),
    }
    assert_eq!(report.skipped.len(), 1, "{report:?}");
    let e = &report.skipped[0].error;
    assert!(
        e.contains("has 11 frames but the states have 6") && e.contains("differ by 5"),
        "{e}"
    );
    // The aligned view has 5 frames, its states from state 1 on.
    let ds = LeRobotDataset::open(&dir.path().join("aligned")).expect("open");
    let (shape, _) = ds.read_masks(0).expect("masks");
    assert_eq!(shape[0], 5);
}

#[test]
fn joints_outside_the_model_limits_are_reported_not_clamped() {
    let (dir, expected) = fixtures();
    let d = &expected["droid"];
    let o = options(dir.path(), &["cam2base_extrinsics.json"]);
    let mut ep = droid::read_episode(Path::new(d["dir"].as_str().expect("dir")), &o).expect("read");
    ep.joints[2][6] = 3.2;
    ep.joints[4][6] = 3.0;
    let franka = Embodiment::builtin("franka").expect("franka");
    let jt = ep.joint_trajectory(&franka, None).expect("trajectory");
    let j7 = franka.robot.dof_index("panda_joint7").expect("j7");
    assert_eq!(jt.q[2][j7], 3.2, "kept as recorded");
    let (lo, hi) = franka.robot.dof_limits()[j7];
    assert_eq!(
        jt.notes,
        vec![Note::JointOutOfLimits {
            joint: "panda_joint7".into(),
            count: 2,
            worst: 3.2,
            lower: lo,
            upper: hi
        }]
    );
    let out = dir.path().join("limits");
    let report = convert(
        vec![(ep.id.clone(), Ok(ep))],
        &franka,
        &out,
        &opts("droid"),
        &|_| {},
    )
    .expect("convert");
    assert!(report
        .notes
        .iter()
        .any(|n| n.note.kind() == "joint_out_of_limits" && n.camera.is_none()));
    assert!(std::fs::read_to_string(out.join(REPORT_FILE))
        .expect("report")
        .contains("\"joint_out_of_limits\""));
}

#[test]
fn agibot_grippers_waist_head_and_dexterous_hands() {
    let (dir, expected) = fixtures();
    let a = &expected["agibot"];
    let root = dir.path().join("agibot");
    let key = EpisodeKey {
        task: "327".into(),
        episode: "648642".into(),
    };
    // From the state's readings, 35 open .. 120 closed: 200 is clamped and counted.
    let state = AgibotOptions {
        gripper: GripperSource::State,
        ..AgibotOptions::default()
    };
    let ep = agibot::read_episode(&root, &key, &state).expect("read");
    let left: Vec<f64> = ep.grippers.iter().map(|g| g[0]).collect();
    assert_eq!(left, vec![0.0, 1.0, 1.0, 0.5, 0.0, 1.0]);
    let right = (50.0 - 35.0) / 85.0;
    assert!((ep.grippers[2][1] - right).abs() < 1e-12);
    assert_eq!(
        notes_of(&ep, "gripper_clamped"),
        vec![&Note::GripperClamped {
            arm: 0,
            field: "state/effector/position".into(),
            count: 1,
            worst: 200.0,
            open: 35.0,
            closed: 120.0
        }]
    );
    // From action/effector/position (0..1) by default, where recorded.
    let act = agibot::read_episode(&root, &key, &AgibotOptions::default()).expect("read");
    let want: Vec<Vec<f64>> = a["action_effector"]
        .as_array()
        .expect("a")
        .iter()
        .map(f64s)
        .collect();
    assert_eq!(act.grippers, want);
    assert!(notes_of(&act, "gripper_clamped").is_empty());
    // The real G1's joint names; the head read, the waist missing (noted).
    assert_eq!(&act.joint_names[..1], &["idx21_arm_l_joint1".to_string()]);
    assert_eq!(&act.joint_names[7..8], &["idx61_arm_r_joint1".to_string()]);
    assert_eq!(
        &act.joint_names[14..],
        &[
            "idx11_head_joint1".to_string(),
            "idx12_head_joint2".to_string()
        ]
    );
    assert!((act.joints[0][14] - 0.1).abs() < 1e-6 && (act.joints[0][15] + 0.2).abs() < 1e-6);
    assert!(
        matches!(notes_of(&act, "joints_missing")[..], [Note::JointsMissing { field, joints }] if field == "state/waist/position" && joints.len() == 2)
    );
    assert_eq!(act.ee_frames, agibot::EE_FRAMES.map(String::from).to_vec());
    // A dexterous hand is refused by name.
    let err = agibot::read_episode(
        &dir.path().join("agibot_dex"),
        &key,
        &AgibotOptions::default(),
    )
    .expect_err("dex");
    let msg = err.to_string();
    assert!(
        msg.contains("dexterous hand: 12 effector values")
            && msg.contains("2-value gripper")
            && msg.contains("proprio_stats.h5"),
        "{msg}"
    );
    // A range whose ends are equal is refused.
    let bad = AgibotOptions {
        gripper: GripperSource::State,
        gripper_open: 50.0,
        gripper_closed: 50.0,
        ..AgibotOptions::default()
    };
    assert!(agibot::read_episode(&root, &key, &bad).is_err());
    assert_eq!("state".parse::<GripperSource>(), Ok(GripperSource::State));
    assert!("closed".parse::<GripperSource>().is_err());
}

fn copy_tree(from: &Path, to: &Path) {
    std::fs::create_dir_all(to).expect("mkdir");
    for e in std::fs::read_dir(from).expect("ls").flatten() {
        let p = e.path();
        if p.is_dir() {
            copy_tree(&p, &to.join(e.file_name()));
        } else {
            std::fs::copy(&p, to.join(e.file_name())).expect("copy");
        }
    }
}
