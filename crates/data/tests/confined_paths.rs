//! Paths read from dataset metadata stay inside the dataset (issue 69, item
//! 2): a DROID episode's `<role>_mp4_path` and camera serial, a LeRobot
//! dataset's `data_path`/`video_path` templates and video feature keys.
//! Absolute paths, `..`, symbolic links out of the folder and files that are
//! not regular files are refused with the metadata file and the field named,
//! and the message never holds the outside file's content. The files the
//! readers open at fixed places (LeRobot's `meta/*`, episode index, masks,
//! labels, calibration; DROID's metadata, `trajectory.h5` and timestamps;
//! AgiBot World's HDF5, videos and JSON) are held to the same: a FIFO is
//! refused without blocking, a link out of the folder without being read.
#![allow(clippy::unwrap_used)]

use bridgev2w_data::clip_masks::{read_link_labels, EpisodeMasks};
use bridgev2w_data::lerobot::{DatasetError, LeRobotDataset};
use bridgev2w_data::raw::agibot::{self, AgibotOptions};
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
    /// The fixture folder (`droid/`, `agibot/`, ...).
    root: PathBuf,
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
        root: tmp.path().to_path_buf(),
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

/// What a file is replaced by for a check.
enum Stand {
    /// A FIFO (opening it would block with no writer).
    Fifo,
    /// A symbolic link to a copy of the file outside the dataset
    /// (`outside`, a folder beside it), or to `to` when given.
    LinkOut(Option<PathBuf>),
}

/// Replaces `path` (a file or a folder) as `stand` says, runs `check`, and
/// puts the original back; `outside` is where copies out of the dataset go.
fn replaced(path: &Path, outside: &Path, stand: Stand, check: impl FnOnce()) {
    let kept = path.with_extension("kept-by-test");
    std::fs::rename(path, &kept).unwrap();
    match stand {
        Stand::Fifo => mkfifo(path),
        Stand::LinkOut(to) => {
            let target = to.unwrap_or_else(|| {
                std::fs::create_dir_all(outside).unwrap();
                let copy = outside.join(path.file_name().unwrap());
                // A folder moves out whole; a file is copied.
                if kept.is_dir() {
                    std::fs::rename(&kept, &copy).unwrap();
                    std::os::unix::fs::symlink(&copy, &kept).unwrap();
                } else {
                    std::fs::copy(&kept, &copy).unwrap();
                }
                copy
            });
            std::os::unix::fs::symlink(target, path).unwrap();
        }
    }
    check();
    std::fs::remove_file(path).unwrap();
    if kept.is_symlink() {
        let moved = std::fs::read_link(&kept).unwrap();
        std::fs::remove_file(&kept).unwrap();
        std::fs::rename(moved, path).unwrap();
    } else {
        std::fs::rename(&kept, path).unwrap();
    }
}

/// `e` must be a dataset metadata error on `path`, saying `expected`,
/// without the secret's content.
fn meta_refused(e: DatasetError, path: &Path, expected: &str) {
    let message = e.to_string();
    match &e {
        DatasetError::Meta { path: p, .. } => assert_eq!(p, path, "{message}"),
        other => panic!("expected an error on {}, got {other}", path.display()),
    }
    assert!(message.contains(expected), "{message}");
    assert!(!message.contains(SECRET), "{message}");
}

/// Opens the dataset at `root` on a thread (a FIFO must not block it).
fn open_within_seconds(root: &Path) -> Result<LeRobotDataset, DatasetError> {
    let root = root.to_path_buf();
    within_seconds(move || LeRobotDataset::open(&root))
}

#[test]
fn lerobot_metadata_and_episode_index_must_be_regular_files_inside() {
    let (tmp, root, _secret) = lerobot_fixture();
    let outside = tmp.path().join("outside");
    let open_refused = |rel: &str, expected: &str| {
        meta_refused(
            open_within_seconds(&root).unwrap_err(),
            &root.join(rel),
            expected,
        )
    };
    for rel in ["meta/info.json", "meta/tasks.parquet"] {
        replaced(&root.join(rel), &outside, Stand::Fifo, || {
            open_refused(rel, "FIFO")
        });
        replaced(&root.join(rel), &outside, Stand::LinkOut(None), || {
            open_refused(rel, "outside")
        });
    }
    // The episode index scan: a linked chunk folder, a linked or FIFO file,
    // the whole linked folder.
    let chunk = "meta/episodes/chunk-000";
    replaced(&root.join(chunk), &outside, Stand::LinkOut(None), || {
        open_refused(chunk, "outside")
    });
    let index = "meta/episodes/chunk-000/file-000.parquet";
    replaced(&root.join(index), &outside, Stand::LinkOut(None), || {
        open_refused(index, "outside")
    });
    replaced(&root.join(index), &outside, Stand::Fifo, || {
        open_refused(index, "FIFO")
    });
    let episodes = "meta/episodes";
    replaced(&root.join(episodes), &outside, Stand::LinkOut(None), || {
        open_refused(episodes, "outside")
    });
    // A FIFO with another name in the index folder is passed over unopened.
    mkfifo(&root.join("meta/episodes/chunk-000/notes.txt"));
    open_within_seconds(&root).unwrap();

    // v2.1's JSON lines.
    let v21 = tmp.path().join("v21");
    std::fs::create_dir_all(v21.join("meta")).unwrap();
    let info = serde_json::json!({
        "codebase_version": "v2.1", "fps": 10, "chunks_size": 1000,
        "data_path": "data/episode_{episode_index:06d}.parquet",
        "features": {},
    });
    std::fs::write(v21.join("meta/info.json"), info.to_string()).unwrap();
    mkfifo(&v21.join("meta/tasks.jsonl"));
    meta_refused(
        open_within_seconds(&v21).unwrap_err(),
        &v21.join("meta/tasks.jsonl"),
        "FIFO",
    );
}

#[test]
fn lerobot_calibration_masks_and_labels_must_be_regular_files_inside() {
    let (tmp, root, secret) = lerobot_fixture();
    let outside = tmp.path().join("outside");
    let ds = LeRobotDataset::open(&root).unwrap();
    let (shape, data) = ds.read_masks(0).unwrap();
    let masks = EpisodeMasks {
        frames: shape[0],
        height: shape[1],
        width: shape[2],
        data,
    };
    assert!(read_link_labels(&ds, 0, &masks).unwrap().is_some());
    ds.read_calibration(0, VIDEO_KEY).unwrap();
    let on_thread = |f: fn(&LeRobotDataset, &EpisodeMasks) -> Result<(), DatasetError>| {
        let (ds, masks) = (ds.clone(), masks.clone());
        within_seconds(move || f(&ds, &masks)).unwrap_err()
    };
    let calibration =
        |ds: &LeRobotDataset, _: &EpisodeMasks| ds.read_calibration(0, VIDEO_KEY).map(|_| ());
    let stored = |ds: &LeRobotDataset, _: &EpisodeMasks| ds.stored_masks(0).map(|_| ());
    let labels = |ds: &LeRobotDataset, m: &EpisodeMasks| read_link_labels(ds, 0, m).map(|_| ());
    for (rel, read) in [
        (
            "meta/calibration/episode_000000.json",
            calibration as fn(&_, &_) -> _,
        ),
        ("masks/episode_000000.npy", stored),
        ("labels/episode_000000.npy", labels),
    ] {
        let path = root.join(rel);
        // A FIFO is refused, not taken for a missing file nor opened.
        replaced(&path, &outside, Stand::Fifo, || {
            meta_refused(on_thread(read), &path, "FIFO")
        });
        replaced(
            &path,
            &outside,
            Stand::LinkOut(Some(secret.clone())),
            || meta_refused(on_thread(read), &path, "outside"),
        );
        // A link to a device outside: refused without reading it.
        replaced(
            &path,
            &outside,
            Stand::LinkOut(Some("/dev/zero".into())),
            || meta_refused(on_thread(read), &path, "outside"),
        );
    }
    let e = ds.read_masks(0);
    assert!(e.is_ok(), "restored: {e:?}");
    // Missing stays missing: no calibration, no stored masks or labels.
    std::fs::remove_file(root.join("meta/calibration/episode_000000.json")).unwrap();
    assert!(matches!(
        ds.read_calibration(0, VIDEO_KEY),
        Err(DatasetError::MissingCalibration { .. })
    ));
    std::fs::remove_file(root.join("labels/episode_000000.npy")).unwrap();
    assert_eq!(read_link_labels(&ds, 0, &masks).unwrap(), None);
    std::fs::remove_file(root.join("masks/episode_000000.npy")).unwrap();
    assert!(ds.stored_masks(0).unwrap().is_none());
}

/// `e` must be a raw refusal of `path` saying `expected`, without the secret.
fn raw_refused(e: RawError, path: &Path, expected: &str) {
    let message = e.to_string();
    match &e {
        RawError::Refused { path: p, .. } => assert_eq!(p, path, "{message}"),
        other => panic!("expected a refusal of {}, got {other}", path.display()),
    }
    assert!(message.contains(expected), "{message}");
    assert!(!message.contains(SECRET), "{message}");
}

#[test]
fn droid_episode_files_must_be_regular_files_inside() {
    let d = droid_fixture();
    let outside = d.root.join("outside");
    let read = |dir: &Path| {
        let (dir, options) = (dir.to_path_buf(), d.options.clone());
        within_seconds(move || droid::read_episode(&dir, &options).map(|_| ()))
    };
    read(&d.episode).unwrap();
    let h5 = d.episode.join("trajectory.h5");
    replaced(&h5, &outside, Stand::Fifo, || {
        raw_refused(read(&d.episode).unwrap_err(), &h5, "FIFO")
    });
    replaced(&h5, &outside, Stand::LinkOut(None), || {
        raw_refused(read(&d.episode).unwrap_err(), &h5, "outside")
    });
    replaced(&d.meta_path, &outside, Stand::Fifo, || {
        raw_refused(read(&d.episode).unwrap_err(), &d.meta_path, "FIFO")
    });
    replaced(
        &d.meta_path,
        &outside,
        Stand::LinkOut(Some(d.secret.clone())),
        || raw_refused(read(&d.episode).unwrap_err(), &d.meta_path, "outside"),
    );
    // The per-frame timestamps beside a video (read where trajectory.h5
    // has the camera's frame_received times, as in this episode).
    let serial = d.meta["ext1_cam_serial"].as_str().unwrap();
    let times = d
        .episode
        .join(format!("recordings/MP4/{serial}_timestamps.json"));
    mkfifo(&times);
    raw_refused(read(&d.episode).unwrap_err(), &times, "FIFO");
    std::fs::remove_file(&times).unwrap();
    std::os::unix::fs::symlink(&d.secret, &times).unwrap();
    raw_refused(read(&d.episode).unwrap_err(), &times, "outside");
    std::fs::remove_file(&times).unwrap();
    read(&d.episode).unwrap();

    // The folder the user names may itself be a link.
    let link = d.root.join("linked-episode");
    std::os::unix::fs::symlink(&d.episode, &link).unwrap();
    read(&link).unwrap();

    // A calibration file the user names: a FIFO is an error, not a hang.
    let fifo = d.root.join("intrinsics-fifo.json");
    mkfifo(&fifo);
    let f2 = fifo.clone();
    let e = within_seconds(move || DroidOptions::from_files(&f2, None).map(|_| ())).unwrap_err();
    raw_refused(e, &fifo, "FIFO");
}

#[test]
fn agibot_episode_files_must_be_regular_files_inside() {
    let d = droid_fixture();
    let root = d.root.join("agibot");
    let outside = d.root.join("outside");
    let key = agibot::find_episodes(&root).unwrap().remove(0);
    let read = || {
        let (root, key) = (root.clone(), key.clone());
        within_seconds(move || {
            agibot::read_episode(&root, &key, &AgibotOptions::default()).map(|_| ())
        })
    };
    read().unwrap();
    let ep = format!("{}/{}", key.task, key.episode);
    let cams = format!("parameters/{ep}/parameters/camera");
    for (rel, link) in [
        (format!("proprio_stats/{ep}/proprio_stats.h5"), None),
        (format!("observations/{ep}/videos/head_color.mp4"), None),
        (format!("{cams}/head_intrinsic_params.json"), None),
        (
            format!("{cams}/head_extrinsic_params_aligned.json"),
            Some(d.secret.clone()),
        ),
        (format!("task_info/task_{}.json", key.task), None),
    ] {
        let path = root.join(&rel);
        replaced(&path, &outside, Stand::Fifo, || {
            raw_refused(read().unwrap_err(), &path, "FIFO")
        });
        replaced(&path, &outside, Stand::LinkOut(link), || {
            raw_refused(read().unwrap_err(), &path, "outside")
        });
    }
    // A folder of the episode linked out of the root.
    let params = root.join(format!("parameters/{}", key.task));
    replaced(&params, &outside, Stand::LinkOut(None), || {
        let e = read().unwrap_err();
        assert!(
            e.to_string().contains("outside") && matches!(e, RawError::Refused { .. }),
            "{e}"
        );
    });
    read().unwrap();
}
