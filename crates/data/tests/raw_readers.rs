//! DROID raw and AgiBot World readers on episodes written in the exact layouts
//! by `scripts/fixtures/write_raw_episodes.py` (HDF5 through h5py/libhdf5 in
//! the project venv); the MP4 videos either with the project's H.264
//! encoder or, as cameras' recordings are, with x264 (High profile,
//! B-frames) through PyAV.

use bridgev2w_data::lerobot::LeRobotDataset;
use bridgev2w_data::raw::agibot::{self, AgibotOptions, EpisodeKey};
use bridgev2w_data::raw::convert::{convert, resize_rgb, ConvertOptions};
use bridgev2w_data::raw::droid::{self, DroidOptions};
use bridgev2w_data::raw::source::{convert_source, ConvertProgress, RawSource};
use bridgev2w_data::raw::RawError;
use bridgev2w_data::video::write_test_pattern;
use bridgev2w_embodiment::camera::world_from_camera_from_xyz_rpy;
use bridgev2w_embodiment::embodiment::Embodiment;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Runs the fixture generator into a fresh temp dir, writes the videos it
/// lists (`frames` frames of a moving gradient each; with PyAV's x264 when
/// `pyav`), returns the dir and `expected.json`.
fn fixtures(pyav: bool) -> (tempfile::TempDir, Value) {
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
        .args(pyav.then_some("--pyav-videos"))
        .status()
        .expect("run python");
    assert!(status.success(), "write_raw_episodes.py failed");
    let expected: Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("expected.json")).expect("expected.json"),
    )
    .expect("json");
    let (w, h, t) = (
        expected["width"].as_u64().expect("w") as usize,
        expected["height"].as_u64().expect("h") as usize,
        expected["frames"].as_u64().expect("t") as usize,
    );
    assert_eq!(expected["videos_written"].as_bool(), Some(pyav));
    for v in expected["videos"]
        .as_array()
        .expect("videos")
        .iter()
        .filter(|_| !pyav)
    {
        write_test_pattern(Path::new(v.as_str().expect("path")), (w, h), t, 15).expect("mp4");
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

fn rows(v: &Value) -> Vec<Vec<f64>> {
    v.as_array().expect("rows").iter().map(f64s).collect()
}

/// Element-wise equality within 1e-12 (JSON float parsing may differ in the last ulp).
fn assert_close(got: &[Vec<f64>], want: &[Vec<f64>], what: &str) {
    assert_eq!(got.len(), want.len(), "{what}: row count");
    for (t, (g, w)) in got.iter().zip(want).enumerate() {
        assert_eq!(g.len(), w.len(), "{what}: frame {t} width");
        for (a, b) in g.iter().zip(w) {
            assert!((a - b).abs() < 1e-12, "{what}: frame {t}: {g:?} vs {w:?}");
        }
    }
}

fn droid_options(dir: &Path, calibration: bool) -> DroidOptions {
    DroidOptions::from_files(
        &dir.join("droid_intrinsics.json"),
        calibration
            .then(|| dir.join("droid_calibration.json"))
            .as_deref(),
    )
    .expect("options")
}

#[test]
fn droid_and_agibot_read_convert_and_fail_clearly() {
    read_convert_and_fail_clearly(false);
}

#[test]
fn droid_and_agibot_with_x264_b_frame_videos_from_pyav() {
    read_convert_and_fail_clearly(true);
}

fn read_convert_and_fail_clearly(pyav: bool) {
    let (dir, expected) = fixtures(pyav);
    // Every video decodes to the moving gradient it was written with.
    for v in expected["videos"].as_array().expect("videos") {
        let path = Path::new(v.as_str().expect("path"));
        let video = bridgev2w_data::video::decode_mp4(path).expect("decode");
        for (t, f) in video.frames.iter().enumerate() {
            let want: Vec<u8> = (0..f.len())
                .map(|i| ((i / 3 % video.width) * 4 + t * 10) as u8)
                .collect();
            let psnr = bridgev2w_data::video::psnr_db(f, &want);
            assert!(psnr > 30.0, "{}: frame {t} at {psnr:.1} dB", path.display());
        }
    }
    let d = &expected["droid"];

    // --- DROID: values as recorded, per-frame extrinsics, the recorded task.
    let found = droid::find_episodes(&dir.path().join("droid")).expect("find");
    assert_eq!(found, vec![PathBuf::from(d["dir"].as_str().expect("dir"))]);
    let ep = droid::read_episode(&found[0], &droid_options(dir.path(), false)).expect("read droid");
    assert_eq!(ep.id, d["uuid"].as_str().expect("uuid"));
    assert_eq!(ep.task.as_deref(), Some("put the cup in the bowl"));
    assert_eq!(ep.frames, 6);
    assert_close(&ep.joints, &rows(&d["joints"]), "joints");
    let grip = f64s(&d["gripper"]);
    for (t, g) in ep.grippers.iter().enumerate() {
        assert_close(std::slice::from_ref(g), &[vec![grip[t]]], "gripper");
        let mut ee = rows(&d["cartesian"])[t].clone();
        ee.push(grip[t]);
        assert_close(&[ep.ee_actions[t].clone()], &[ee], "ee actions");
    }
    assert_eq!(ep.views.len(), 2, "ext1 and ext2 by default");
    let serials: Vec<String> = f64s_str(&d["serials"]);
    assert_eq!(ep.views[0].name, serials[0]);
    for (t, e) in rows(&d["ext1"]).iter().enumerate() {
        let want = world_from_camera_from_xyz_rpy([e[0], e[1], e[2], e[3], e[4], e[5]]);
        let got = ep.views[0].world_from_camera[t];
        assert!((got.translation.vector - want.translation.vector).norm() < 1e-12);
        assert!(got.rotation.angle_to(&want.rotation) < 1e-9);
    }
    assert!(
        !ep.views[0].is_static(),
        "ext1 drifts per frame in the fixture"
    );
    assert!(ep.views[1].is_static());
    assert!((droid::robotiq_opening_m(0.0) - 0.085).abs() < 1e-15);

    // The override file replaces ext1's extrinsics with the re-calibrated pose.
    let cal = droid::read_episode(&found[0], &droid_options(dir.path(), true))
        .expect("read with calibration");
    let o = f64s(&d["override_ext1"]);
    let want = world_from_camera_from_xyz_rpy([o[0], o[1], o[2], o[3], o[4], o[5]]);
    assert!(cal.views[0].is_static());
    assert!(
        (cal.views[0].world_from_camera[3].translation.vector - want.translation.vector).norm()
            < 1e-12
    );
    assert_eq!(
        cal.views[1], ep.views[1],
        "only the overridden camera changes"
    );

    // Joints onto the built-in franka: arm joints by name, gripper closure to the fingers.
    let franka = Embodiment::builtin("franka").expect("franka");
    let jt = ep.joint_trajectory(&franka, None).expect("q");
    assert!(jt.notes.is_empty(), "{:?}", jt.notes);
    let finger = franka
        .robot
        .dof_index("panda_finger_joint1")
        .expect("finger");
    let limits = franka.robot.dof_limits()[finger];
    for (t, row) in jt.q.iter().enumerate() {
        for j in 0..7 {
            let d = franka
                .robot
                .dof_index(&format!("panda_joint{}", j + 1))
                .expect("joint");
            assert_eq!(row[d], ep.joints[t][j], "recorded values pass unchanged");
        }
        let want = limits.1 - grip[t] * (limits.1 - limits.0);
        assert!((row[finger] - want).abs() < 1e-12);
    }
    let err = ep
        .joint_trajectory(&franka, Some(&["a".to_string()]))
        .expect_err("wrong rename length");
    assert!(
        err.to_string().contains("1 joint names given for 7"),
        "{err}"
    );

    // --- DROID bad input: each error names the file and what is wrong.
    let opts = droid_options(dir.path(), false);
    let err = droid::read_episode(&dir.path().join("droid_bad/nan"), &opts).expect_err("nan");
    let msg = err.to_string();
    assert!(
        msg.contains("trajectory.h5")
            && msg.contains("observation/robot_state/joint_positions")
            && msg.contains("[3, 2]")
            && msg.contains("NaN"),
        "{msg}"
    );
    let err = droid::read_episode(&dir.path().join("droid_bad/length"), &opts).expect_err("length");
    let msg = err.to_string();
    assert!(
        msg.contains("trajectory_length") && msg.contains("9") && msg.contains("6 states"),
        "{msg}"
    );
    let mut no_k = droid_options(dir.path(), false);
    no_k.intrinsics.global.remove(&serials[1]);
    let err = droid::read_episode(&found[0], &no_k).expect_err("no intrinsics");
    assert!(
        err.to_string().contains(&format!(
            "no intrinsics for camera ext2 (serial {})",
            serials[1]
        )),
        "{err}"
    );
    // A truncated trajectory.h5.
    let trunc = dir.path().join("truncated");
    std::fs::create_dir_all(trunc.join("recordings/MP4")).expect("mkdir");
    for entry in std::fs::read_dir(&found[0]).expect("ls").flatten() {
        if entry.path().is_file() {
            let bytes = std::fs::read(entry.path()).expect("read");
            let keep = if entry.file_name() == "trajectory.h5" {
                bytes.len() / 3
            } else {
                bytes.len()
            };
            std::fs::write(trunc.join(entry.file_name()), &bytes[..keep]).expect("write");
        }
    }
    let err = droid::read_episode(&trunc, &opts).expect_err("truncated");
    assert!(
        matches!(err, RawError::Hdf5 { .. }) && err.to_string().contains("truncated/trajectory.h5"),
        "{err}"
    );

    // --- AgiBot World.
    let root = dir.path().join("agibot");
    let a = &expected["agibot"];
    let keys = agibot::find_episodes(&root).expect("find agibot");
    assert_eq!(
        keys,
        vec![EpisodeKey {
            task: "327".into(),
            episode: "648642".into()
        }]
    );
    let ag = agibot::read_episode(&root, &keys[0], &AgibotOptions::default()).expect("read agibot");
    assert_eq!(ag.id, "327/648642");
    assert_eq!(ag.task.as_deref(), Some("Pickup items in the supermarket"));
    // The 14 arm columns, then the head's 2 (the fixture records no waist).
    let arms: Vec<Vec<f64>> = ag.joints.iter().map(|r| r[..14].to_vec()).collect();
    assert_close(&arms, &rows(&a["joints"]), "agibot joints");
    assert_eq!(ag.joint_names.len(), 16);
    assert_eq!(ag.arms(), 2);
    // The default gripper source: action/effector/position (0..1) where recorded.
    let eff = rows(&a["action_effector"]);
    let yaw = f64s(&a["yaw_left"]);
    let roll = f64s(&a["roll_right"]);
    for t in 0..ag.frames {
        assert!((ag.grippers[t][0] - eff[t][0]).abs() < 1e-12);
        assert!((ag.grippers[t][1] - eff[t][1]).abs() < 1e-12);
        let e = &ag.ee_actions[t];
        assert_eq!(e.len(), 14);
        assert!(
            (e[5] - yaw[t]).abs() < 1e-6 && e[3].abs() < 1e-6,
            "left yaw {e:?}"
        );
        assert!(
            (e[10] - roll[t]).abs() < 1e-6 && e[12].abs() < 1e-6,
            "right roll {e:?}"
        );
        assert!((e[6] - ag.grippers[t][0]).abs() < 1e-15);
    }
    let head = ag.view("head").expect("head");
    assert!((head.world_from_camera[2].translation.vector.y - 0.02).abs() < 1e-12);
    assert_eq!(head.intrinsics.fx, 50.0);
    let err = agibot::read_episode(
        &dir.path().join("agibot_bad"),
        &keys[0],
        &AgibotOptions::default(),
    )
    .expect_err("frame mismatch");
    let msg = err.to_string();
    assert!(
        msg.contains("head_extrinsic_params_aligned.json")
            && msg.contains("5 extrinsics")
            && msg.contains("6 frames"),
        "{msg}"
    );

    // --- Conversion: one LeRobot episode per view, masks where the robot is.
    let out = dir.path().join("converted");
    let opts = ConvertOptions {
        width: 32,
        height: 24,
        fps: 15,
        joint_names: None,
        skip_bad: true,
        split: Some("train".into()),
        source_format: "droid".into(),
        overwrite: false,
    };
    let items = [found[0].clone(), dir.path().join("droid_bad/nan")]
        .into_iter()
        .map(|p| {
            (
                p.display().to_string(),
                droid::read_episode(&p, &droid_options(dir.path(), false)),
            )
        });
    let report = convert(items, &franka, &out, &opts, &|_| {}).expect("convert");
    assert_eq!(report.episodes, 1);
    assert_eq!(report.views_written, 2);
    assert_eq!(report.skipped.len(), 1, "{report:?}");
    assert!(
        report.skipped[0].item.ends_with("droid_bad/nan")
            && report.skipped[0].error.contains("NaN")
    );
    assert!(
        report.empty_mask_views.is_empty(),
        "the fixture cameras look at the robot: {report:?}"
    );
    let skipped: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("skipped.json")).expect("report"))
            .expect("json");
    assert_eq!(skipped["skipped"].as_array().map(Vec::len), Some(1));
    let ds = LeRobotDataset::open(&out).expect("open converted");
    assert_eq!(ds.episodes.len(), 2);
    assert_eq!(ds.episodes[0].split.as_deref(), Some("train"));
    let (shape, masks) = ds.read_masks(0).expect("masks");
    assert_eq!(shape, vec![6, 24, 32]);
    let on = masks.iter().filter(|&&m| m == 1).count();
    assert!(
        on > 20 && on < masks.len() / 2,
        "{on} mask pixels of {}",
        masks.len()
    );
    let frames = ds.read_video(1, "observation.images.main").expect("video");
    assert_eq!(frames.len(), 6);
    // Static camera -> calibration stored; drifting camera -> none.
    assert!(ds.read_calibration(1, "observation.images.main").is_ok());
    assert!(ds.read_calibration(0, "observation.images.main").is_err());

    // Without skip_bad the first bad episode stops the conversion, naming it.
    let strict = ConvertOptions {
        skip_bad: false,
        ..opts
    };
    let items = [dir.path().join("droid_bad/nan")].into_iter().map(|p| {
        (
            p.display().to_string(),
            droid::read_episode(&p, &droid_options(dir.path(), false)),
        )
    });
    let err =
        convert(items, &franka, &dir.path().join("strict"), &strict, &|_| {}).expect_err("strict");
    assert!(err.to_string().contains("joint_positions"), "{err}");

    // A video one frame short is aligned (truncated: no timestamps for it) and reported.
    let short = dir.path().join("short");
    copy_tree(&found[0], &short);
    let ext2_video = short.join(format!("recordings/MP4/{}.mp4", serials[1]));
    write_test_pattern(&ext2_video, (64, 48), 5, 15).expect("short video");
    let items = vec![(
        short.display().to_string(),
        droid::read_episode(&short, &droid_options(dir.path(), false)),
    )];
    let report = convert(
        items,
        &franka,
        &dir.path().join("short_out"),
        &ConvertOptions {
            skip_bad: true,
            ..strict.clone()
        },
        &|_| {},
    )
    .expect("convert short");
    assert_eq!((report.views_written, report.skipped.len()), (2, 0));
    let aligned: Vec<_> = report
        .notes
        .iter()
        .filter(|n| n.note.kind() == "frames_aligned")
        .collect();
    assert_eq!(aligned.len(), 1, "{:?}", report.notes);
    assert_eq!(aligned[0].camera.as_deref(), Some(serials[1].as_str()));

    // AgiBot onto the built-in G1 (its real joint names).
    let g1 = Embodiment::builtin("agibot-g1").expect("g1");
    let out = dir.path().join("converted_g1");
    let items = vec![(ag.id.clone(), Ok(ag.clone()))];
    let report = convert(
        items,
        &g1,
        &out,
        &ConvertOptions {
            source_format: "agibot".into(),
            ..strict.clone()
        },
        &|_| {},
    )
    .expect("convert g1");
    assert_eq!(report.views_written, 1);
    let ds = LeRobotDataset::open(&out).expect("open g1");
    let (_, masks) = ds.read_masks(0).expect("masks");
    assert!(masks.contains(&1));

    // The head and the moving hand camera: one episode each; the hand
    // camera's masks change from frame to frame with its per-frame pose.
    let both = agibot::read_episode(
        &root,
        &keys[0],
        &AgibotOptions {
            cameras: vec!["head".into(), "hand_left".into()],
            ..AgibotOptions::default()
        },
    )
    .expect("read agibot head + hand");
    let hand = both.view("hand_left").expect("hand view");
    assert!(!hand.is_static(), "the hand camera moves");
    let out = dir.path().join("converted_g1_hands");
    let report = convert(
        vec![(both.id.clone(), Ok(both.clone()))],
        &g1,
        &out,
        &ConvertOptions {
            source_format: "agibot".into(),
            ..strict.clone()
        },
        &|_| {},
    )
    .expect("convert g1 head + hand");
    assert_eq!(report.views_written, 2);
    let ds = LeRobotDataset::open(&out).expect("open g1 hands");
    let (shape, masks) = ds.read_masks(1).expect("hand masks");
    let n = shape[1] * shape[2];
    assert!(masks.contains(&1), "the hand camera sees the robot");
    assert_ne!(
        &masks[..n],
        &masks[masks.len() - n..],
        "frames seen from different poses"
    );

    // The whole workflow in one call (what `convert` and `bw.convert` run):
    // find, limit, convert into a temporary folder, rename.
    let whole = ConvertOptions {
        width: 32,
        height: 24,
        fps: 15,
        joint_names: None,
        skip_bad: false,
        split: None,
        source_format: "droid".into(),
        overwrite: false,
    };
    let source = RawSource::Droid {
        root: dir.path().join("droid"),
        options: droid_options(dir.path(), false),
    };
    let events = std::sync::Mutex::new(Vec::new());
    let out = dir.path().join("whole");
    let progress = |p: ConvertProgress| {
        if let Ok(mut e) = events.lock() {
            e.push(format!("{p:?}"));
        }
    };
    let report =
        convert_source(&source, Some(1), &franka, &out, &whole, &progress).expect("convert_source");
    assert_eq!((report.episodes, report.views_written), (1, 2));
    let seen = events.lock().expect("events").clone();
    assert_eq!(seen.len(), 2, "{seen:?}");
    assert_eq!(seen[0], "Found(1)");
    assert!(seen[1].starts_with("Done("), "{seen:?}");
    assert_eq!(LeRobotDataset::open(&out).expect("open").episodes.len(), 2);
    // An existing output is kept and named.
    let err = convert_source(&source, None, &franka, &out, &whole, &|_| {}).expect_err("exists");
    assert!(
        err.to_string().starts_with("out: ") && err.to_string().contains("already exists"),
        "{err}"
    );
    assert_eq!(LeRobotDataset::open(&out).expect("kept").episodes.len(), 2);
    // ... or replaced whole when asked (nothing of the old one is left).
    std::fs::write(out.join("notes.txt"), "mine").expect("write");
    let replace = ConvertOptions {
        overwrite: true,
        ..whole.clone()
    };
    convert_source(&source, None, &franka, &out, &replace, &|_| {}).expect("overwrite");
    assert!(!out.join("notes.txt").exists());
    assert_eq!(
        LeRobotDataset::open(&out).expect("replaced").episodes.len(),
        2
    );
    // A source without episodes is refused, naming it, and leaves nothing.
    let empty = dir.path().join("no_episodes");
    std::fs::create_dir(&empty).expect("mkdir");
    let source = RawSource::Droid {
        root: empty.clone(),
        options: droid_options(dir.path(), false),
    };
    let out = dir.path().join("from_empty");
    let err = convert_source(&source, None, &franka, &out, &whole, &|_| {}).expect_err("empty");
    assert!(
        err.to_string().contains("no DROID episodes") && err.to_string().contains("no_episodes"),
        "{err}"
    );
    let left: Vec<_> = std::fs::read_dir(dir.path())
        .expect("ls")
        .flatten()
        .filter(|e| e.file_name().to_string_lossy().starts_with("from_empty"))
        .collect();
    assert!(left.is_empty(), "left behind: {left:?}");
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

fn f64s_str(v: &Value) -> Vec<String> {
    v.as_array()
        .expect("array")
        .iter()
        .map(|x| x.as_str().expect("string").to_string())
        .collect()
}

#[test]
fn area_resize_preserves_means_and_constant_images() {
    // 4x2 -> 2x1: each output pixel is the mean of a 2x2 block.
    let src: Vec<u8> = [10u8, 20, 30, 40, 50, 60, 70, 80]
        .iter()
        .flat_map(|&v| [v, v, v])
        .collect();
    let out = resize_rgb(&src, (4, 2), (2, 1));
    assert_eq!(out, vec![35, 35, 35, 55, 55, 55]);
    // Non-integer factor on a constant image stays constant.
    let flat = vec![123u8; 7 * 5 * 3];
    assert!(resize_rgb(&flat, (7, 5), (3, 2)).iter().all(|&v| v == 123));
    assert!(resize_rgb(&flat, (7, 5), (10, 9)).iter().all(|&v| v == 123));
}
