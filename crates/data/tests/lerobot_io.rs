//! LeRobot v3.0 write/read round trip, v2.1 reading, and bad-input errors.
#![allow(clippy::unwrap_used)]

use bridgev2w_data::lerobot::{
    format_template, write_frames_parquet, DatasetError, FrameRow, LeRobotDataset, Version,
};
use bridgev2w_data::synth::{plan, write_dataset, SynthConfig, World, VIDEO_KEY};
use bridgev2w_data::video::{psnr_db, Mp4VideoWriter};
use std::path::Path;

fn config() -> SynthConfig {
    SynthConfig {
        frames: 8,
        width: 48,
        height: 32,
        seed: 3,
        episodes_per_split: [2, 1, 1, 1],
        ..SynthConfig::default()
    }
}

fn all_files(root: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap() {
            let p = e.unwrap().path();
            if p.is_dir() {
                stack.push(p);
            } else {
                let rel = p.strip_prefix(root).unwrap().display().to_string();
                out.push((rel, std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

#[test]
fn template_formatting() {
    assert_eq!(
        format_template(
            "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
            &[
                ("video_key", "a.b".into()),
                ("chunk_index", "2".into()),
                ("file_index", "13".into())
            ]
        ),
        "videos/a.b/chunk-002/file-013.mp4"
    );
}

#[test]
fn v3_round_trip_and_determinism() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ds");
    let cfg = config();
    let summary = write_dataset(&cfg, &out, &|| {}).unwrap();
    assert_eq!(summary.total_frames, 5 * 8);
    assert!(std::fs::read_dir(dir.path()).expect("read_dir").all(|e| !e
        .expect("entry")
        .file_name()
        .to_string_lossy()
        .contains("bridgev2w-tmp")));
    // Same seed -> identical bytes (and a second write refuses to clobber).
    let out2 = dir.path().join("ds2");
    rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| write_dataset(&cfg, &out2, &|| {}).unwrap());
    let (a, b) = (all_files(&out), all_files(&out2));
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(x.0, y.0);
        assert!(x.1 == y.1, "{} differs between runs", x.0);
    }
    assert!(write_dataset(&cfg, &out, &|| {}).is_err());
    for f in [
        "meta/info.json",
        "meta/tasks.parquet",
        "meta/episodes/chunk-000/file-000.parquet",
        "data/chunk-000/file-000.parquet",
        "meta/synth.json",
        "masks/episode_000004.npy",
        "meta/calibration/episode_000000.json",
    ] {
        assert!(out.join(f).is_file(), "{f} missing");
    }
    assert!(out
        .join(format!("videos/{VIDEO_KEY}/chunk-000/file-000.mp4"))
        .is_file());

    let ds = LeRobotDataset::open(&out).unwrap();
    assert_eq!(ds.version, Version::V30);
    assert_eq!(ds.episodes.len(), 5);
    assert_eq!(ds.video_keys, vec![VIDEO_KEY.to_string()]);
    assert_eq!(ds.info["total_frames"], 40);
    assert_eq!(ds.info["codebase_version"], "v3.0");
    assert!(ds.info["synth_splits"].as_array().unwrap().len() == 4);
    assert_eq!(ds.info["splits"]["unseen_scene"], "4:5");

    let world = World::new(&cfg).unwrap();
    for (ep, (split, i, task)) in plan(&cfg).into_iter().enumerate() {
        let e = world.generate(split, i, task).unwrap();
        let info = &ds.episodes[ep];
        assert_eq!(info.split.as_deref(), Some(split.name()));
        assert_eq!(info.tasks, vec![task.description().to_string()]);
        let data = ds.read_episode(ep as i64).unwrap();
        for (f, row) in data.frames.iter().enumerate() {
            let s: Vec<f32> = e.joints[f].iter().map(|&v| v as f32).collect();
            let a: Vec<f32> = e.actions[f].iter().map(|&v| v as f32).collect();
            assert_eq!(row.state, s);
            assert_eq!(row.action, a);
            assert_eq!(row.frame_index, f as i64);
            assert_eq!(row.index, (ep * 8 + f) as i64);
        }
        let frames = ds.read_video(ep as i64, VIDEO_KEY).unwrap();
        assert_eq!(frames.len(), 8);
        for (f, (d, r)) in frames.iter().zip(&e.rgb).enumerate() {
            let p = psnr_db(d, r);
            assert!(p > 30.0, "episode {ep} frame {f}: PSNR {p:.1} dB");
        }
        let (shape, masks) = ds.read_masks(ep as i64).unwrap();
        assert_eq!(shape, vec![8, 32, 48]);
        assert_eq!(masks, e.masks.concat());
        let cam = ds.read_calibration(ep as i64, VIDEO_KEY).unwrap();
        assert_eq!(cam.intrinsics, e.camera.intrinsics);
        let d = (cam.world_from_camera.to_homogeneous()
            - e.camera.world_from_camera.to_homogeneous())
        .abs()
        .max();
        assert!(d < 1e-9);
    }
}

/// `(states, actions, RGB frames)` of one v2.1 test episode.
type V21Episode = (Vec<Vec<f32>>, Vec<Vec<f32>>, Vec<Vec<u8>>);

/// Writes a LeRobot v2.1 dataset (one parquet and one MP4 per episode).
fn write_v21(root: &Path, episodes: &[V21Episode], fps: u32) {
    let key = "observation.images.top";
    std::fs::create_dir_all(root.join("meta")).unwrap();
    let info = serde_json::json!({
        "codebase_version": "v2.1",
        "robot_type": "franka",
        "fps": fps,
        "chunks_size": 1000,
        "total_episodes": episodes.len(),
        "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
        "video_path": "videos/chunk-{episode_chunk:03d}/{video_key}/episode_{episode_index:06d}.mp4",
        "features": {
            key: {"dtype": "video", "shape": [16, 32, 3], "names": ["height", "width", "channels"]},
            "observation.state": {"dtype": "float32", "shape": [2], "names": null},
            "action": {"dtype": "float32", "shape": [3], "names": null}
        }
    });
    std::fs::write(root.join("meta/info.json"), info.to_string()).unwrap();
    std::fs::write(
        root.join("meta/tasks.jsonl"),
        "{\"task_index\": 0, \"task\": \"stack\"}\n",
    )
    .unwrap();
    let mut lines = String::new();
    let mut index = 0;
    for (ep, (states, actions, rgb)) in episodes.iter().enumerate() {
        lines.push_str(&format!(
            "{{\"episode_index\": {ep}, \"tasks\": [\"stack\"], \"length\": {}}}\n",
            states.len()
        ));
        let rows: Vec<FrameRow> = states
            .iter()
            .zip(actions)
            .enumerate()
            .map(|(f, (s, a))| {
                index += 1;
                FrameRow {
                    index: index - 1,
                    episode_index: ep as i64,
                    frame_index: f as i64,
                    timestamp: f as f32 / fps as f32,
                    task_index: 0,
                    state: s.clone(),
                    action: a.clone(),
                }
            })
            .collect();
        write_frames_parquet(
            &root.join(format!("data/chunk-000/episode_{ep:06}.parquet")),
            &rows,
        )
        .unwrap();
        let vpath = root.join(format!("videos/chunk-000/{key}/episode_{ep:06}.mp4"));
        let mut w = Mp4VideoWriter::new(&vpath, 32, 16, fps).unwrap();
        for (f, frame) in rgb.iter().enumerate() {
            w.push(frame, f == 0).unwrap();
        }
        std::fs::create_dir_all(vpath.parent().unwrap()).unwrap();
        std::fs::write(&vpath, w.to_bytes().unwrap()).unwrap();
    }
    std::fs::write(root.join("meta/episodes.jsonl"), lines).unwrap();
}

fn gradient(seed: u8) -> Vec<u8> {
    let mut v = Vec::new();
    for y in 0..16u32 {
        for x in 0..32u32 {
            v.extend_from_slice(&[(x * 8) as u8, (y * 16) as u8, seed.wrapping_mul(20)]);
        }
    }
    v
}

#[test]
fn v21_reader() {
    let dir = tempfile::tempdir().unwrap();
    let eps: Vec<_> = (0..2u8)
        .map(|e| {
            let n = 4 + e as usize;
            let states = (0..n).map(|f| vec![f as f32 * 0.5, -(e as f32)]).collect();
            let actions = (0..n).map(|f| vec![1.0, f as f32, 0.25]).collect();
            let rgb = (0..n).map(|f| gradient(e * 5 + f as u8)).collect();
            (states, actions, rgb)
        })
        .collect::<Vec<V21Episode>>();
    write_v21(dir.path(), &eps, 15);
    let ds = LeRobotDataset::open(dir.path()).unwrap();
    assert_eq!(ds.version, Version::V21);
    assert_eq!(ds.episodes.len(), 2);
    assert_eq!(ds.tasks[&0], "stack");
    for (e, (states, actions, rgb)) in eps.iter().enumerate() {
        let data = ds.read_episode(e as i64).unwrap();
        let s: Vec<_> = data.frames.iter().map(|r| r.state.clone()).collect();
        let a: Vec<_> = data.frames.iter().map(|r| r.action.clone()).collect();
        assert_eq!(&s, states);
        assert_eq!(&a, actions);
        let frames = ds.read_video(e as i64, "observation.images.top").unwrap();
        assert_eq!(frames.len(), rgb.len());
        for (d, r) in frames.iter().zip(rgb) {
            assert!(psnr_db(d, r) > 30.0);
        }
    }
}

fn small_dataset(dir: &Path) -> std::path::PathBuf {
    let out = dir.join("ds");
    let cfg = SynthConfig {
        episodes_per_split: [1, 1, 0, 0],
        ..config()
    };
    write_dataset(&cfg, &out, &|| {}).unwrap();
    out
}

#[test]
fn corrupt_parquet_names_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = small_dataset(dir.path());
    let data = out.join("data/chunk-000/file-000.parquet");
    let mut bytes = std::fs::read(&data).unwrap();
    let n = bytes.len();
    for b in &mut bytes[n / 3..n - 8] {
        *b ^= 0x5A;
    }
    std::fs::write(&data, &bytes).unwrap();
    let ds = LeRobotDataset::open(&out).unwrap();
    let err = ds.read_episode(0).unwrap_err();
    let msg = err.to_string();
    assert!(msg.contains("file-000.parquet"), "{msg}");
    // A truncated episode index fails at open, naming the file.
    let ep = out.join("meta/episodes/chunk-000/file-000.parquet");
    let bytes = std::fs::read(&ep).unwrap();
    std::fs::write(&ep, &bytes[..bytes.len() / 2]).unwrap();
    let msg = LeRobotDataset::open(&out).unwrap_err().to_string();
    assert!(
        msg.contains("meta/episodes/chunk-000/file-000.parquet"),
        "{msg}"
    );
}

#[test]
fn nan_state_names_episode_and_field() {
    let dir = tempfile::tempdir().unwrap();
    let p = dir.path().join("x.parquet");
    let row = |f: i64, v: f32| FrameRow {
        index: f,
        episode_index: 3,
        frame_index: f,
        timestamp: 0.0,
        task_index: 0,
        state: vec![0.0, v],
        action: vec![0.0],
    };
    write_frames_parquet(&p, &[row(0, 1.0), row(1, f32::NAN)]).unwrap();
    let err = bridgev2w_data::lerobot::read_frames_parquet(&p).unwrap_err();
    match &err {
        DatasetError::Field { episode, field, .. } => {
            assert_eq!(*episode, 3);
            assert_eq!(field, "observation.state");
        }
        other => panic!("unexpected {other}"),
    }
    assert!(err.to_string().contains("x.parquet"));
}

#[test]
fn truncated_mp4_and_unsupported_codec_name_the_file() {
    let dir = tempfile::tempdir().unwrap();
    let out = small_dataset(dir.path());
    let vpath = out.join(format!("videos/{VIDEO_KEY}/chunk-000/file-000.mp4"));
    let bytes = std::fs::read(&vpath).unwrap();
    // An HEVC sample entry (AV1 is read since session 22).
    let mut av1 = bytes.clone();
    let pos = av1.windows(4).position(|w| w == b"avc1").unwrap();
    let pos = pos
        + 4
        + av1[pos + 4..]
            .windows(4)
            .position(|w| w == b"avc1")
            .unwrap();
    av1[pos..pos + 4].copy_from_slice(b"hvc1");
    std::fs::write(&vpath, &av1).unwrap();
    let ds = LeRobotDataset::open(&out).unwrap();
    let msg = ds.read_video(0, VIDEO_KEY).unwrap_err().to_string();
    assert!(
        msg.contains("unsupported codec") && msg.contains("hvc1") && msg.contains("file-000.mp4"),
        "{msg}"
    );
    // Truncated.
    std::fs::write(&vpath, &bytes[..bytes.len() * 2 / 3]).unwrap();
    let msg = ds.read_video(0, VIDEO_KEY).unwrap_err().to_string();
    assert!(
        msg.contains("file-000.mp4") && msg.contains("truncated"),
        "{msg}"
    );
    // Missing calibration.
    std::fs::remove_file(out.join("meta/calibration/episode_000001.json")).unwrap();
    let err = ds.read_calibration(1, VIDEO_KEY).unwrap_err();
    assert!(
        matches!(err, DatasetError::MissingCalibration { episode: 1, .. }),
        "{err}"
    );
    assert!(err.to_string().contains("episode_000001.json"));
    assert!(ds.read_calibration(0, VIDEO_KEY).is_ok());
}

#[test]
fn link_labels_are_stored_next_to_the_masks_and_must_match_them() {
    use bridgev2w_data::clip_masks::{read_link_labels, EpisodeMasks};
    use bridgev2w_io::npy::write_npy;
    let dir = tempfile::tempdir().unwrap();
    let out = small_dataset(dir.path());
    let ds = LeRobotDataset::open(&out).unwrap();
    let (shape, data) = ds.read_masks(0).unwrap();
    let masks = EpisodeMasks {
        frames: shape[0],
        height: shape[1],
        width: shape[2],
        data,
    };
    let labels = read_link_labels(&ds, 0, &masks)
        .unwrap()
        .expect("synth writes labels");
    assert_eq!(labels.len(), masks.data.len());
    assert!(labels
        .iter()
        .zip(&masks.data)
        .all(|(&l, &m)| (l != 0) == (m != 0)));
    assert!(
        labels.iter().any(|&l| l > 1),
        "link labels, not a binary mask"
    );
    // The same labels as uint16 (labels.npy of `bridgev2w masks`): read
    // alike; a label above 255 refused.
    let path = out.join("labels/episode_000000.npy");
    let wide: Vec<u16> = labels.iter().map(|&l| u16::from(l)).collect();
    write_npy(&path, &shape, &wide).unwrap();
    assert_eq!(read_link_labels(&ds, 0, &masks).unwrap().unwrap(), labels);
    let mut big = wide.clone();
    let on = masks.data.iter().position(|&m| m != 0).unwrap();
    big[on] = 300;
    write_npy(&path, &shape, &big).unwrap();
    let msg = read_link_labels(&ds, 0, &masks).unwrap_err().to_string();
    assert!(msg.contains("link label 300"), "{msg}");
    // A label where the mask has background is refused, naming the pixel.
    let i = masks.data.iter().position(|&m| m == 0).unwrap();
    let mut bad = labels.clone();
    bad[i] = 5;
    write_npy(&path, &shape, &bad).unwrap();
    let msg = read_link_labels(&ds, 0, &masks).unwrap_err().to_string();
    assert!(
        msg.contains("episode_000000.npy") && msg.contains("label 5 but mask 0"),
        "{msg}"
    );
    // Of another shape: refused; absent: none.
    write_npy(&path, &[1, shape[1], shape[2]], &bad[..shape[1] * shape[2]]).unwrap();
    let msg = read_link_labels(&ds, 0, &masks).unwrap_err().to_string();
    assert!(msg.contains("the masks' shape"), "{msg}");
    std::fs::remove_file(&path).unwrap();
    assert_eq!(read_link_labels(&ds, 0, &masks).unwrap(), None);
}

#[test]
fn stored_masks_with_an_empty_dimension_or_grey_values_are_refused() {
    use bridgev2w_io::npy::write_npy;
    let dir = tempfile::tempdir().unwrap();
    let out = small_dataset(dir.path());
    let path = out.join("masks/episode_000000.npy");
    let ds = LeRobotDataset::open(&out).unwrap();
    let (shape, _) = ds.read_masks(0).unwrap();
    write_npy(&path, &[shape[0], 0, shape[2]], &[] as &[u8]).unwrap();
    let msg = ds.read_masks(0).unwrap_err().to_string();
    assert!(
        msg.contains("episode_000000.npy") && msg.contains("empty dimension"),
        "{msg}"
    );
    // 0/255 masks (image tools') read as 0/1; a grey value is refused.
    let mut data = vec![0u8; shape.iter().product()];
    data[3] = 255;
    write_npy(&path, &shape, &data).unwrap();
    let (_, masks) = ds.read_masks(0).unwrap();
    assert_eq!((masks[3], masks.iter().map(|&v| v as usize).sum()), (1, 1));
    data[4] = 128;
    write_npy(&path, &shape, &data).unwrap();
    let msg = ds.read_masks(0).unwrap_err().to_string();
    assert!(msg.contains("128"), "{msg}");
}
