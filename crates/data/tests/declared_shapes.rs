//! What the LeRobot reader reads is checked against what the dataset
//! declares (issue 69, item 4: `bw.read_episode` and training once handed on
//! arrays of another shape): the widths of `observation.state` and `action`
//! rows against `meta/info.json`'s `features` shapes, the video frames' size
//! against the video feature's shape, stored masks against `[T, H, W]` of
//! the episode's length and the declared frame size. A mismatch is an error
//! naming the file, the feature, the declared and the found shape.
#![allow(clippy::unwrap_used)]

use bridgev2w_data::lerobot::{DatasetError, LeRobotDataset};
use bridgev2w_data::synth::{write_dataset, SynthConfig, VIDEO_KEY};
use bridgev2w_io::npy::write_npy;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};

/// Frames, height and width of the fixture's episodes.
const T: usize = 4;
const H: usize = 24;
const W: usize = 32;

/// A synthetic dataset of two 4-frame 32x24 episodes.
fn dataset() -> (tempfile::TempDir, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("ds");
    let cfg = SynthConfig {
        frames: T,
        width: W as u32,
        height: H as u32,
        seed: 3,
        episodes_per_split: [1, 1, 0, 0],
        ..SynthConfig::default()
    };
    write_dataset(&cfg, &root, &|| {}).unwrap();
    (tmp, root)
}

/// Sets `features.<feature>.<field>` of `meta/info.json`; returns the old value.
fn set_feature(root: &Path, feature: &str, field: &str, value: Value) -> Value {
    let path = root.join("meta/info.json");
    let mut info: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let old = std::mem::replace(&mut info["features"][feature][field], value);
    std::fs::write(&path, info.to_string()).unwrap();
    old
}

/// `e` must be a field error on `path` for `field`, its message holding each of `needles`.
fn field_refused(e: DatasetError, path: &Path, field: &str, needles: &[&str]) {
    let message = e.to_string();
    match &e {
        DatasetError::Field {
            path: p, field: f, ..
        } => {
            assert_eq!(p, path, "{message}");
            assert_eq!(f, field, "{message}");
        }
        other => panic!("expected a field error on {}, got {other}", path.display()),
    }
    for n in needles {
        assert!(message.contains(n), "{n:?} not in: {message}");
    }
}

#[test]
fn state_and_action_rows_must_have_the_declared_width() {
    let (_tmp, root) = dataset();
    let ds = LeRobotDataset::open(&root).unwrap();
    let rows = ds.read_episode(0).unwrap().frames;
    let (state, action) = (rows[0].state.len(), rows[0].action.len());
    let data = ds.episodes[0].data_path.clone();

    let old = set_feature(&root, "observation.state", "shape", json!([state + 1]));
    let ds = LeRobotDataset::open(&root).unwrap();
    field_refused(
        ds.read_episode(0).unwrap_err(),
        &data,
        "observation.state",
        &[
            &format!("{state} values (shape [{state}])"),
            &format!("declares shape [{}]", state + 1),
        ],
    );
    set_feature(&root, "observation.state", "shape", old);

    // A shape of several dimensions holds their product.
    let old = set_feature(&root, "action", "shape", json!([action, 2]));
    let ds = LeRobotDataset::open(&root).unwrap();
    field_refused(
        ds.read_episode(1).unwrap_err(),
        &data,
        "action",
        &[&format!("declares shape [{action}, 2]")],
    );
    set_feature(&root, "action", "shape", json!([1, action]));
    LeRobotDataset::open(&root)
        .unwrap()
        .read_episode(1)
        .unwrap();
    set_feature(&root, "action", "shape", old);

    // A shape that is not a list of sizes is refused when the dataset opens.
    set_feature(&root, "action", "shape", json!("seven"));
    let e = LeRobotDataset::open(&root).unwrap_err().to_string();
    assert!(
        e.contains("info.json") && e.contains("features.action.shape") && e.contains("\"seven\""),
        "{e}"
    );
}

#[test]
fn video_frames_must_have_the_declared_size() {
    let (_tmp, root) = dataset();
    let ds = LeRobotDataset::open(&root).unwrap();
    assert_eq!(ds.video_size(VIDEO_KEY).unwrap(), (H, W));
    assert_eq!(ds.read_video(0, VIDEO_KEY).unwrap()[0].len(), H * W * 3);
    let video = ds.episodes[0].videos[VIDEO_KEY].path.clone();

    // Declared wider than the frames are.
    let old = set_feature(&root, VIDEO_KEY, "shape", json!([H, W + 2, 3]));
    let ds = LeRobotDataset::open(&root).unwrap();
    field_refused(
        ds.read_video(0, VIDEO_KEY).unwrap_err(),
        &video,
        VIDEO_KEY,
        &[
            &format!("[{H}, {W}, 3]"),
            &format!("declares [{H}, {}, 3]", W + 2),
        ],
    );
    // Transposed.
    set_feature(&root, VIDEO_KEY, "shape", json!([W, H, 3]));
    let ds = LeRobotDataset::open(&root).unwrap();
    field_refused(
        ds.read_video(0, VIDEO_KEY).unwrap_err(),
        &video,
        VIDEO_KEY,
        &[&format!("declares [{W}, {H}, 3]")],
    );
    // Channels first, as older LeRobot datasets declare it: the same size.
    set_feature(&root, VIDEO_KEY, "shape", json!([3, H, W]));
    let names = set_feature(
        &root,
        VIDEO_KEY,
        "names",
        json!(["channels", "height", "width"]),
    );
    let ds = LeRobotDataset::open(&root).unwrap();
    assert_eq!(ds.read_video(1, VIDEO_KEY).unwrap().len(), T);
    set_feature(&root, VIDEO_KEY, "names", names);
    // Not the shape of a video: refused when the dataset opens.
    for bad in [
        json!([H, W]),
        json!([H, W, 4]),
        json!([0, W, 3]),
        json!(null),
    ] {
        set_feature(&root, VIDEO_KEY, "shape", bad.clone());
        let e = LeRobotDataset::open(&root).unwrap_err().to_string();
        assert!(
            e.contains("info.json") && e.contains(&format!("features.{VIDEO_KEY}.shape")),
            "{bad}: {e}"
        );
    }
    set_feature(&root, VIDEO_KEY, "shape", old);
    LeRobotDataset::open(&root).unwrap();
}

#[test]
fn stored_masks_must_be_the_episode_length_by_the_declared_size() {
    let (_tmp, root) = dataset();
    let ds = LeRobotDataset::open(&root).unwrap();
    let (shape, _) = ds.read_masks(0).unwrap();
    assert_eq!(shape, [T, H, W]);
    let path = root.join("masks/episode_000000.npy");
    for bad in [[T - 1, H, W], [T + 1, H, W], [T, W, H], [T, H / 2, W / 2]] {
        write_npy(&path, &bad, &vec![0u8; bad.iter().product()]).unwrap();
        field_refused(
            ds.read_masks(0).unwrap_err(),
            &path,
            "masks",
            &[
                &format!("shape {bad:?}"),
                &format!("{T} frames"),
                &format!("expected [{T}, {H}, {W}] (features.{VIDEO_KEY})"),
            ],
        );
        assert!(ds.stored_masks(0).is_err());
    }
    write_npy(&path, &[T, H, W], &vec![1u8; T * H * W]).unwrap();
    let (shape, masks) = ds.read_masks(0).unwrap();
    assert_eq!((shape, masks.len()), (vec![T, H, W], T * H * W));
}
