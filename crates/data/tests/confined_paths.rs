//! Paths read from dataset metadata stay inside the dataset (issue 69, item
//! 2): a DROID episode's `<role>_mp4_path` and camera serial, a LeRobot
//! dataset's `data_path`/`video_path` templates and video feature keys.
//! Absolute paths, `..`, symbolic links out of the folder and files that are
//! not regular files are refused with the metadata file and the field named,
//! and the message never holds the outside file's content.
#![allow(clippy::unwrap_used)]

use bridgev2w_data::lerobot::{DatasetError, LeRobotDataset};
use bridgev2w_data::raw::droid::{self, DroidOptions};
use bridgev2w_data::raw::RawError;
use bridgev2w_data::synth::{write_dataset, SynthConfig, VIDEO_KEY};
use bridgev2w_data::video::write_test_pattern;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

/// The content of the file outside the dataset that no message may show.
const SECRET: &str = "SECRET-CONTENT-root:x:0:0";

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn mkfifo(path: &Path) {
    let status = Command::new("mkfifo").arg(path).status().unwrap();
    assert!(status.success(), "mkfifo {}", path.display());
}

/// Runs `f` on a thread: a refusal must come back without opening a FIFO
/// (which would block with no writer).
fn within_seconds<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(Duration::from_secs(60))
        .expect("the reader blocked: it opened a FIFO instead of refusing it")
}

/// The fixture generator's good DROID episode (videos written), its
/// metadata file, the options to read it, and a secret file beside the episode.
struct Droid {
    _tmp: tempfile::TempDir,
    episode: PathBuf,
    meta_path: PathBuf,
    meta: Value,
    options: DroidOptions,
    secret: PathBuf,
}

fn droid_fixture() -> Droid {
    let python = repo_root().join(".venv/bin/python");
    assert!(
        python.is_file(),
        "{} not found: run scripts/setup-venv.sh (./run test does)",
        python.display()
    );
    let tmp = tempfile::tempdir().unwrap();
    let status = Command::new(&python)
        .arg(repo_root().join("scripts/fixtures/write_raw_episodes.py"))
        .arg(tmp.path())
        .status()
        .unwrap();
    assert!(status.success(), "write_raw_episodes.py failed");
    let expected: Value =
        serde_json::from_str(&std::fs::read_to_string(tmp.path().join("expected.json")).unwrap())
            .unwrap();
    let size = |k: &str| expected[k].as_u64().unwrap() as usize;
    for v in expected["videos"].as_array().unwrap() {
        let p = Path::new(v.as_str().unwrap());
        write_test_pattern(p, (size("width"), size("height")), size("frames"), 15).unwrap();
    }
    let episode = tmp
        .path()
        .join("droid/TEST/success/2023-07-07/Fri_Jul__7_12:00:00_2023");
    let meta_path = std::fs::read_dir(&episode)
        .unwrap()
        .map(|e| e.unwrap().path())
        .find(|p| {
            p.file_name()
                .is_some_and(|n| n.to_string_lossy().starts_with("metadata_"))
        })
        .unwrap();
    let meta = serde_json::from_str(&std::fs::read_to_string(&meta_path).unwrap()).unwrap();
    let options =
        DroidOptions::from_files(&tmp.path().join("droid_intrinsics.json"), None).unwrap();
    let secret = tmp.path().join("secret.txt");
    std::fs::write(&secret, SECRET).unwrap();
    Droid {
        _tmp: tmp,
        episode,
        meta_path,
        meta,
        options,
        secret,
    }
}

impl Droid {
    /// Reads the episode with metadata `field` set to `value`.
    fn read_with(&self, field: &str, value: &str) -> Result<(), RawError> {
        let mut meta = self.meta.clone();
        meta[field] = Value::String(value.into());
        std::fs::write(&self.meta_path, meta.to_string()).unwrap();
        let (dir, options) = (self.episode.clone(), self.options.clone());
        within_seconds(move || droid::read_episode(&dir, &options).map(|_| ()))
    }

    /// `read_with` must be refused naming the metadata file and `field`, the
    /// value, and `expected`; without the secret's or `/etc/passwd`'s content.
    fn refused(&self, field: &str, value: &str, expected: &str) {
        let e = self.read_with(field, value).unwrap_err();
        let message = e.to_string();
        match &e {
            RawError::Json { path, field: f, .. } => {
                assert_eq!(path, &self.meta_path, "{message}");
                assert_eq!(f, field, "{message}");
            }
            other => panic!("{field} = {value:?}: expected a metadata error, got {other}"),
        }
        assert!(message.contains(value), "{message}");
        assert!(message.contains(expected), "{message}");
        assert!(!message.contains(SECRET), "{message}");
        assert!(!message.contains("root:x:0:0"), "{message}");
    }
}

#[test]
fn droid_video_paths_are_confined_to_the_episode() {
    let d = droid_fixture();
    // The fixture as written reads (its paths are relative and inside).
    let good = d.meta["ext1_mp4_path"].as_str().unwrap().to_string();
    d.read_with("ext1_mp4_path", &good).unwrap();

    d.refused("ext1_mp4_path", "../../etc/passwd", "\"..\" component");
    d.refused(
        "ext1_mp4_path",
        "recordings/../../../../../../secret.txt",
        "\"..\" component",
    );
    d.refused("ext1_mp4_path", "/etc/passwd", "absolute path");
    d.refused(
        "ext1_mp4_path",
        &d.secret.to_string_lossy(),
        "absolute path",
    );

    // A link inside the episode to a file outside it.
    let link = d.episode.join("recordings/MP4/link.mp4");
    std::os::unix::fs::symlink(&d.secret, &link).unwrap();
    d.refused("ext1_mp4_path", "recordings/MP4/link.mp4", "outside");
    // A linked folder out of the episode.
    std::os::unix::fs::symlink(d.secret.parent().unwrap(), d.episode.join("up")).unwrap();
    d.refused("ext1_mp4_path", "up/secret.txt", "outside");

    // A FIFO and a folder are not videos.
    mkfifo(&d.episode.join("recordings/MP4/pipe.mp4"));
    d.refused("ext1_mp4_path", "recordings/MP4/pipe.mp4", "FIFO");
    d.refused("ext1_mp4_path", "recordings/MP4", "folder");

    // The fallback `recordings/MP4/<serial>.mp4`: a serial is a plain name.
    d.refused("ext1_cam_serial", "../../../secret", "plain serial number");
    d.refused("ext1_cam_serial", "/etc/passwd", "plain serial number");

    // A recorded path that does not exist still falls back to the serial's video.
    d.read_with("ext1_mp4_path", "elsewhere/recordings/MP4/x.mp4")
        .unwrap();
}

/// A small synthetic LeRobot v3.0 dataset at `tmp/ds` and a secret file beside it.
fn lerobot_fixture() -> (tempfile::TempDir, PathBuf, PathBuf) {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("ds");
    let cfg = SynthConfig {
        frames: 4,
        width: 32,
        height: 32,
        seed: 5,
        episodes_per_split: [1, 1, 1, 1],
        ..SynthConfig::default()
    };
    write_dataset(&cfg, &root, &|| {}).unwrap();
    let secret = tmp.path().join("secret.txt");
    std::fs::write(&secret, SECRET).unwrap();
    (tmp, root, secret)
}

fn set_info(root: &Path, key: &str, value: Value) -> Value {
    let path = root.join("meta/info.json");
    let mut info: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let old = info[key].clone();
    info[key] = value;
    std::fs::write(&path, info.to_string()).unwrap();
    old
}

/// `LeRobotDataset::open` must refuse with a metadata error on
/// `meta/info.json` naming `field` and `expected`.
fn open_refused(root: &Path, field: &str, expected: &str) {
    let e = LeRobotDataset::open(root).unwrap_err();
    let message = e.to_string();
    match &e {
        DatasetError::Meta { path, .. } => assert_eq!(path, &root.join("meta/info.json")),
        other => panic!("expected a meta/info.json error, got {other}"),
    }
    assert!(message.contains(field), "{message}");
    assert!(message.contains(expected), "{message}");
    assert!(!message.contains(SECRET), "{message}");
}

#[test]
fn lerobot_templates_and_keys_are_confined_to_the_dataset() {
    let (_tmp, root, _secret) = lerobot_fixture();
    let ds = LeRobotDataset::open(&root).unwrap();
    ds.read_episode(0).unwrap();

    let data = set_info(&root, "data_path", "../secret.txt".into());
    open_refused(&root, "\"data_path\"", "\"..\" component");
    set_info(&root, "data_path", "/etc/passwd".into());
    open_refused(&root, "\"data_path\"", "absolute path");
    set_info(
        &root,
        "data_path",
        "data/{chunk_index}/../../../{file_index}.parquet".into(),
    );
    open_refused(&root, "\"data_path\"", "\"..\" component");
    // A width read from the template is allocated when it is filled: bounded.
    set_info(
        &root,
        "data_path",
        "data/chunk-{chunk_index:0999999999999d}/file-{file_index:03d}.parquet".into(),
    );
    open_refused(
        &root,
        "\"data_path\"",
        "width 999999999999: expected at most 32",
    );
    set_info(&root, "data_path", data);

    let video = set_info(&root, "video_path", "/etc/{video_key}.mp4".into());
    open_refused(&root, "\"video_path\"", "absolute path");
    set_info(&root, "video_path", "videos/../../{video_key}.mp4".into());
    open_refused(&root, "\"video_path\"", "\"..\" component");
    set_info(&root, "video_path", video);

    // A video feature key is substituted into `video_path`: a plain name only.
    let features = set_info(&root, "features", Value::Null);
    let mut bad = features.clone();
    let spec = bad[VIDEO_KEY].take();
    bad.as_object_mut().unwrap().remove(VIDEO_KEY);
    bad["../../secret"] = spec;
    set_info(&root, "features", bad);
    open_refused(&root, "features", "not a plain name");
    set_info(&root, "features", features);

    LeRobotDataset::open(&root).unwrap();
}

#[test]
fn lerobot_data_and_video_files_must_be_regular_files_inside() {
    let (_tmp, root, secret) = lerobot_fixture();
    let ds = LeRobotDataset::open(&root).unwrap();
    let ep = ds.episodes[0].clone();
    let field_refused = |e: DatasetError, field: &str, expected: &str| {
        let message = e.to_string();
        match &e {
            DatasetError::Field { path, field: f, .. } => {
                assert_eq!(path, &root.join("meta/info.json"), "{message}");
                assert_eq!(f, field, "{message}");
            }
            other => panic!("expected a field error, got {other}"),
        }
        assert!(message.contains(expected), "{message}");
        assert!(!message.contains(SECRET), "{message}");
    };

    // The data parquet replaced by a link out of the dataset.
    let data = ep.data_path.clone();
    let kept = data.with_extension("kept");
    std::fs::rename(&data, &kept).unwrap();
    std::os::unix::fs::symlink(&secret, &data).unwrap();
    field_refused(
        ds.read_episode(ep.episode_index).unwrap_err(),
        "data_path",
        "outside",
    );
    // ... by a FIFO.
    std::fs::remove_file(&data).unwrap();
    mkfifo(&data);
    let (d2, i) = (ds.clone(), ep.episode_index);
    let e = within_seconds(move || d2.read_episode(i).map(|_| ())).unwrap_err();
    field_refused(e, "data_path", "FIFO");
    // ... missing: the I/O error of the file, as before.
    std::fs::remove_file(&data).unwrap();
    assert!(matches!(
        ds.read_episode(ep.episode_index).unwrap_err(),
        DatasetError::Io { .. }
    ));
    std::fs::rename(&kept, &data).unwrap();
    ds.read_episode(ep.episode_index).unwrap();

    // The video replaced by a FIFO, then a link out, then a folder.
    let video = ep.videos[VIDEO_KEY].path.clone();
    let kept = video.with_extension("kept");
    std::fs::rename(&video, &kept).unwrap();
    mkfifo(&video);
    let (d2, i) = (ds.clone(), ep.episode_index);
    let e = within_seconds(move || d2.read_video(i, VIDEO_KEY).map(|_| ())).unwrap_err();
    field_refused(e, "video_path", "FIFO");
    std::fs::remove_file(&video).unwrap();
    std::os::unix::fs::symlink(&secret, &video).unwrap();
    field_refused(
        ds.read_video(ep.episode_index, VIDEO_KEY).unwrap_err(),
        "video_path",
        "outside",
    );
    std::fs::remove_file(&video).unwrap();
    std::fs::create_dir(&video).unwrap();
    field_refused(
        ds.read_video(ep.episode_index, VIDEO_KEY).unwrap_err(),
        "video_path",
        "folder",
    );
    std::fs::remove_dir(&video).unwrap();
    std::fs::rename(&kept, &video).unwrap();
    ds.read_video(ep.episode_index, VIDEO_KEY).unwrap();
}

#[test]
fn lerobot_v21_templates_are_confined() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("ds");
    std::fs::create_dir_all(root.join("meta")).unwrap();
    let info = serde_json::json!({
        "codebase_version": "v2.1",
        "fps": 10,
        "chunks_size": 1000,
        "data_path": "../../{episode_index}.parquet",
        "video_path": "videos/{video_key}/episode_{episode_index:06d}.mp4",
        "features": {
            "observation.images.top": {"dtype": "video", "shape": [16, 32, 3]},
        }
    });
    std::fs::write(root.join("meta/info.json"), info.to_string()).unwrap();
    std::fs::write(
        root.join("meta/tasks.jsonl"),
        "{\"task_index\": 0, \"task\": \"stack\"}\n",
    )
    .unwrap();
    std::fs::write(
        root.join("meta/episodes.jsonl"),
        "{\"episode_index\": 0, \"tasks\": [\"stack\"], \"length\": 3}\n",
    )
    .unwrap();
    open_refused(&root, "\"data_path\"", "\"..\" component");
}
