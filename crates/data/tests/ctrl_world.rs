//! The Ctrl-World DROID layout importer (`convert --format ctrl-world`):
//! on the real episodes of `../shared/realdata/droid` (skipped with a
//! message where absent) and on small hand-made annotations for bad input.

use bridgev2w_data::lerobot::LeRobotDataset;
use bridgev2w_data::raw::convert::ConvertOptions;
use bridgev2w_data::raw::ctrl_world::{self, CtrlWorldOptions};
use bridgev2w_data::raw::source::{convert_source, RawSource};
use bridgev2w_embodiment::camera::{Camera, Intrinsics};
use bridgev2w_embodiment::embodiment::Embodiment;
use nalgebra::{Point3, Vector3};
use serde_json::Value;
use std::path::{Path, PathBuf};

fn droid_root() -> Option<PathBuf> {
    bridgev2w_io::realdata::dir(env!("CARGO_MANIFEST_DIR"), "droid")
}

/// A camera looking at the Franka's workspace from the front-left, at the
/// videos' 320x192 (a plausible exterior camera: the masks are not empty).
fn camera_json(dir: &Path) -> PathBuf {
    let mut intrinsics = Intrinsics::centered(140.0, 320, 192);
    intrinsics.fy = 149.3;
    let camera = Camera::look_at(
        intrinsics,
        Point3::new(0.9, 0.6, 0.7),
        Point3::new(0.4, 0.0, 0.2),
        Vector3::z(),
    )
    .expect("camera");
    let path = dir.join("camera.json");
    std::fs::write(&path, camera.to_json()).expect("write camera");
    path
}

fn options(split: &str) -> ConvertOptions {
    ConvertOptions {
        width: 80,
        height: 48,
        fps: ctrl_world::FPS,
        joint_names: None,
        skip_bad: false,
        split: Some(split.into()),
        source_format: "ctrl-world".into(),
        overwrite: false,
    }
}

fn franka() -> Embodiment {
    Embodiment::builtin("franka-robotiq").expect("franka-robotiq")
}

fn annotation(path: &Path) -> Value {
    serde_json::from_str(&std::fs::read_to_string(path).expect("read")).expect("json")
}

#[test]
fn real_episodes_convert_with_their_joints_and_repeats_are_listed_once() {
    let Some(root) = droid_root() else { return };
    let dir = tempfile::tempdir().expect("tempdir");
    let cam = camera_json(dir.path());
    // Two episodes, one of them a repeat of the other under another name
    // (droid_new_setup/val/0011 is droid_new_setup_full/laptop/val/0001),
    // and one from droid_subset whose joints are the 15 Hz arrays.
    let include: Vec<String> = [
        "droid_new_setup/val/0011",
        "droid_new_setup_full/laptop/val/0001",
        "droid_subset/train/6",
    ]
    .iter()
    .map(|s| s.to_string())
    .collect();
    let source = RawSource::CtrlWorld {
        root: root.clone(),
        options: CtrlWorldOptions {
            cameras: vec![("ext1".into(), cam.clone()), ("ext2".into(), cam)],
            include: Some(include),
            // ext2 only for the first episode, as a held-out view.
            split_rules: vec![
                "droid_new_setup/val/0011:ext2=unseen_camera"
                    .parse()
                    .expect("rule"),
                "*:ext2=-".parse().expect("rule"),
            ],
        },
    };
    let out = dir.path().join("ds");
    let report =
        convert_source(&source, None, &franka(), &out, &options("test"), &|_| {}).expect("convert");
    assert_eq!(report.episodes, 2, "{report:?}");
    assert_eq!(report.views_written, 3);
    assert_eq!(report.skipped.len(), 1, "{:?}", report.skipped);
    assert_eq!(
        report.skipped[0].item,
        "droid_new_setup_full/laptop/val/0001"
    );
    assert!(report.skipped[0].error.contains("droid_new_setup/val/0011"));
    assert!(report.empty_mask_views.is_empty(), "{report:?}");

    let ds = LeRobotDataset::open(&out).expect("open");
    // Episode 0: droid_new_setup/val/0011 (57 states, 57 frames): its
    // recorded joints are the dataset's states, row for row.
    let ann = annotation(&root.join("droid_new_setup/annotation/val/0011.json"));
    let joints = ann["joints"].as_array().expect("joints");
    let info = ds.episode(0).expect("episode 0");
    assert_eq!(info.length, joints.len());
    assert_eq!(info.split.as_deref(), Some("test"));
    assert_eq!(info.tasks, vec!["close the laptop".to_string()]);
    let data = ds.read_episode(0).expect("read");
    for t in [0, joints.len() / 2, joints.len() - 1] {
        let row = joints[t].as_array().expect("row");
        for (j, (want, got)) in row.iter().zip(&data.frames[t].state).take(7).enumerate() {
            let want = want.as_f64().expect("number");
            let got = f64::from(*got);
            assert!(
                (got - want).abs() < 1e-5,
                "frame {t} joint {j}: {got} vs {want}"
            );
        }
    }
    // The camera is the one given, rescaled to the dataset's size.
    let stored = ds
        .read_calibration(0, "observation.images.main")
        .expect("fixed camera");
    assert!(
        (stored.intrinsics.fx - 140.0 / 4.0).abs() < 1e-9,
        "{stored:?}"
    );
    // The masks cover some of the frame in most frames.
    let (shape, masks) = ds.read_masks(0).expect("masks");
    let per_frame = shape[1] * shape[2];
    let covered = masks
        .chunks(per_frame)
        .filter(|m| m.iter().any(|&v| v > 0))
        .count();
    assert!(covered * 2 > shape[0], "{covered} of {} frames", shape[0]);
    // Link labels beside them (for link-coded models), robot pixels
    // exactly the masks'.
    let labels =
        bridgev2w_io::npy::read_npy(&out.join("labels/episode_000000.npy")).expect("labels");
    assert_eq!(labels.descr, "|u1");
    assert_eq!(labels.shape, shape);
    assert!(labels
        .data
        .iter()
        .zip(&masks)
        .all(|(&l, &m)| (l > 0.0) == (m > 0)));
    assert!(labels.data.iter().any(|&l| l > 1.0), "more than one link");

    // Its second view (ext2) is written with the split asked for it.
    let info = ds.episode(1).expect("episode 1");
    assert_eq!(info.split.as_deref(), Some("unseen_camera"));
    assert_eq!(info.length, joints.len());

    // Episode 2: droid_subset/train/6 (its ext2 not converted), 39 video frames from the
    // 15 Hz arrays taken every third row.
    let ann = annotation(&root.join("droid_subset/annotation/train/6.json"));
    let raw = ann["observation.state.joint_position"]
        .as_array()
        .expect("15 Hz joints");
    let info = ds.episode(2).expect("episode 2");
    assert_eq!(info.length, 39);
    assert_eq!(info.split.as_deref(), Some("test"));
    let data = ds.read_episode(2).expect("read");
    let t = 10;
    let want = raw[3 * t][2].as_f64().expect("number");
    assert!((f64::from(data.frames[t].state[2]) - want).abs() < 1e-5);
}

#[test]
fn the_finder_names_episodes_relative_to_the_root_and_selects_by_name() {
    let Some(root) = droid_root() else { return };
    let all = ctrl_world::find_episodes(&root).expect("find");
    assert_eq!(all.len(), 44);
    let (kept, repeats) = ctrl_world::dedupe(all.clone()).expect("dedupe");
    assert_eq!(kept.len(), 39);
    assert_eq!(repeats.len(), 5, "{repeats:?}");
    let one = ctrl_world::find_episodes(&root.join("droid_new_setup_full")).expect("find");
    assert_eq!(one.len(), 20);
    assert_eq!(one[0].name(), "drawer/val/0000");
    let e = ctrl_world::select(all, Some(&["nope/val/1".to_string()]))
        .expect_err("unknown name")
        .to_string();
    assert!(
        e.contains("nope/val/1") && e.contains("collection/split/id"),
        "{e}"
    );
}

/// A one-episode collection with the annotation `ann` and an empty
/// `0.mp4` (the annotation is read before the video).
fn fake_collection(dir: &Path, ann: &Value) -> PathBuf {
    let root = dir.join("fake");
    std::fs::create_dir_all(root.join("annotation/val")).expect("mkdir");
    std::fs::create_dir_all(root.join("videos/val/0000")).expect("mkdir");
    std::fs::write(root.join("annotation/val/0000.json"), ann.to_string()).expect("write");
    std::fs::write(root.join("videos/val/0000/0.mp4"), b"").expect("write");
    root
}

#[test]
fn bad_annotations_and_cameras_are_refused_by_name() {
    let dir = tempfile::tempdir().expect("tempdir");
    let cam = camera_json(dir.path());
    let row = |x: f64| vec![x, 0.0, 0.0, -2.0, 0.0, 2.0, 0.8, 0.0];
    let state = vec![0.4, 0.0, 0.3, 3.1, 0.0, 0.0, 0.0];
    let good = serde_json::json!({
        "texts": ["t"], "video_length": 2,
        "joints": [row(0.0), row(0.1)], "states": [state, state],
    });
    let ep = |ann: &Value| {
        let root = fake_collection(&tempfile::tempdir_in(dir.path()).expect("t").keep(), ann);
        let eps = ctrl_world::find_episodes(&root).expect("find");
        ctrl_world::read_episode(
            &eps[0],
            &CtrlWorldOptions {
                cameras: vec![("ext1".into(), cam.clone())],
                include: None,
                split_rules: Vec::new(),
            },
        )
    };
    let read = ep(&good).expect("good annotation");
    assert_eq!(read.frames, 2);
    assert_eq!(read.views.len(), 1);
    assert_eq!(read.grippers[1], vec![0.0]);

    let mut nan = good.clone();
    nan["joints"][1][3] = serde_json::json!("x");
    let e = ep(&nan).expect_err("non-number").to_string();
    assert!(
        e.contains("0000.json") && e.contains("\"joints\"") && e.contains("frame 1"),
        "{e}"
    );

    let mut short = good.clone();
    short["joints"][0] = serde_json::json!([0.0, 1.0]);
    let e = ep(&short).expect_err("short row").to_string();
    assert!(e.contains("frame 0 has 2 values: expected 8"), "{e}");

    let mut fewer = good.clone();
    fewer["states"] = serde_json::json!([state]);
    let e = ep(&fewer).expect_err("count").to_string();
    assert!(e.contains("1 states but 2 joint rows"), "{e}");

    let none = serde_json::json!({"states": [state]});
    let e = ep(&none).expect_err("no joints").to_string();
    assert!(e.contains("\"joints\"") && e.contains("missing"), "{e}");

    // Cameras: the wrist, an unknown role, a role twice, none, a missing file.
    for (cameras, want) in [
        (vec![("wrist", cam.clone())], "moves with the hand"),
        (vec![("ext3", cam.clone())], "expected ext1 or ext2"),
        (
            vec![("ext1", cam.clone()), ("ext1", cam.clone())],
            "given twice",
        ),
        (vec![], "no camera given"),
        (
            vec![("ext2", dir.path().join("absent.json"))],
            "absent.json",
        ),
    ] {
        let o = CtrlWorldOptions {
            cameras: cameras
                .into_iter()
                .map(|(r, p)| (r.to_string(), p))
                .collect(),
            include: None,
            split_rules: Vec::new(),
        };
        let e = o.validate().expect_err(want);
        assert!(e.contains(want), "{e}");
    }
    // A view split for a camera not converted.
    let o = CtrlWorldOptions {
        cameras: vec![("ext1".into(), cam.clone())],
        include: None,
        split_rules: vec!["*:ext2=unseen_camera".parse().expect("rule")],
    };
    let e = o.validate().expect_err("no ext2");
    assert!(e.contains("no camera ext2 is converted"), "{e}");
    for bad in ["x", "a/val/1:ext9=test", "*=", "a:ext1=b/c"] {
        let e = bad.parse::<ctrl_world::SplitRule>().expect_err(bad);
        assert!(e.contains("EPISODE[:ROLE]=SPLIT"), "{e}");
    }
    let r: ctrl_world::SplitRule = "a/val/1=-".parse().expect("rule");
    assert_eq!((r.role, r.split), (None, None));
}
