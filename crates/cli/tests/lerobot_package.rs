//! The round trip with the real `lerobot` package (PyPI `lerobot` 0.4.4, in
//! `.venv-lerobot`, made by `scripts/setup-lerobot-venv.sh`; Hub offline):
//! `LeRobotDataset(root=...)` loads what `bridgev2w synth` writes (rows,
//! tasks, `meta/stats.json`, and the frames lerobot's metadata points at),
//! and `bridgev2w train` trains on the same episodes written by
//! `LeRobotDataset.create` + `add_frame` + `save_episode` (SVT-AV1 video).
//! The Python side is `scripts/fixtures/lerobot_roundtrip.py`.

use bridgev2w_data::lerobot::LeRobotDataset;
use bridgev2w_data::video::psnr_db;
use std::path::{Path, PathBuf};
use std::process::Command;

use crate::common;

use common::{ok, run, s, synth_tiny, TINY_MODEL_TOML};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Every row of a dataset read by this crate: (episode, frame, task, state, action).
type Row = (i64, i64, String, Vec<f32>, Vec<f32>);

fn rows(ds: &LeRobotDataset) -> Vec<Row> {
    let mut out = Vec::new();
    for e in &ds.episodes {
        for f in ds.read_episode(e.episode_index).expect("episode").frames {
            out.push((
                f.episode_index,
                f.frame_index,
                ds.tasks[&f.task_index].clone(),
                f.state,
                f.action,
            ));
        }
    }
    out
}

fn frames(ds: &LeRobotDataset) -> Vec<Vec<u8>> {
    let key = ds.video_keys[0].clone();
    ds.episodes
        .iter()
        .flat_map(|e| ds.read_video(e.episode_index, &key).expect("video"))
        .collect()
}

/// lerobot_roundtrip.py's `OUT/loaded.json` and `OUT/frames.npy` (what
/// lerobot loaded from `ours`' folder) against this crate's reading of it;
/// returns our rows and frames.
fn assert_lerobot_loaded(ours: &LeRobotDataset, out: &Path) -> (Vec<Row>, Vec<Vec<u8>>) {
    let loaded: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(out.join("loaded.json")).expect("loaded.json"),
    )
    .expect("json");
    assert_eq!(loaded["codebase_version"], "v3.0");
    assert_eq!(
        loaded["episodes"].as_u64(),
        Some(ours.episodes.len() as u64)
    );
    let mine = rows(ours);
    assert_eq!(loaded["frames"].as_u64(), Some(mine.len() as u64));
    let r = &loaded["rows"];
    let tasks = loaded["tasks"].as_object().expect("tasks");
    for (i, (ep, fr, task, state, action)) in mine.iter().enumerate() {
        assert_eq!(r["episode_index"][i].as_i64(), Some(*ep), "row {i}");
        assert_eq!(r["frame_index"][i].as_i64(), Some(*fr), "row {i}");
        assert_eq!(
            tasks[task.as_str()].as_i64(),
            r["task_index"][i].as_i64(),
            "row {i}: task {task:?}"
        );
        for (col, want) in [("observation.state", state), ("action", action)] {
            // float32 values (JSON's decimal text read back to the same f32)
            let got: Vec<f32> = r[col][i]
                .as_array()
                .expect(col)
                .iter()
                .map(|v| v.as_f64().expect("number") as f32)
                .collect();
            assert_eq!(&got, want, "row {i} {col}");
        }
    }
    let stats: Vec<&str> = loaded["stats_keys"]
        .as_array()
        .expect("stats keys")
        .iter()
        .filter_map(|v| v.as_str())
        .collect();
    for k in ["observation.state", "action", "observation.images.main"] {
        assert!(stats.contains(&k), "stats.json lacks {k}: {stats:?}");
    }
    // The frames lerobot's metadata points at (decoded by PyAV) are ours.
    let theirs = bridgev2w_io::npy::read_npy(&out.join("frames.npy")).expect("frames.npy");
    let our_frames = frames(ours);
    let n = our_frames[0].len();
    assert_eq!(theirs.shape[0], our_frames.len());
    for (i, f) in our_frames.iter().enumerate() {
        let t: Vec<u8> = theirs.data[i * n..(i + 1) * n]
            .iter()
            .map(|&v| v as u8)
            .collect();
        let p = psnr_db(f, &t);
        assert!(
            p > 38.0,
            "frame {i}: {p:.1} dB between our and PyAV's decoding"
        );
    }

    (mine, our_frames)
}

#[test]
fn lerobot_loads_what_synth_writes_and_bridgev2w_trains_on_what_lerobot_writes() {
    let python = repo().join(".venv-lerobot/bin/python");
    assert!(
        python.is_file(),
        "{}: no LeRobot test venv (./run test makes it: scripts/setup-lerobot-venv.sh)",
        python.display()
    );
    let dir = tempfile::tempdir().expect("tempdir");
    let (src, dst, out) = (
        dir.path().join("synth"),
        dir.path().join("by-lerobot"),
        dir.path().join("loaded"),
    );
    synth_tiny(&src);
    let o = Command::new(&python)
        .arg(repo().join("scripts/fixtures/lerobot_roundtrip.py"))
        .args([&src, &dst, &out])
        .output()
        .expect("run lerobot_roundtrip.py");
    ok(&o);

    // 1. What lerobot loaded from bridgev2w's dataset is what bridgev2w reads.
    let ours = LeRobotDataset::open(&src).expect("open synth");
    let (mine, our_frames) = assert_lerobot_loaded(&ours, &out);

    // 2. The dataset lerobot wrote (AV1) reads back: same rows, frames close
    // to what went in (lossy), and bridgev2w trains on it with masks
    // rendered from the copied calibration.
    let by_lerobot = LeRobotDataset::open(&dst).expect("open lerobot's dataset");
    let theirs_rows = rows(&by_lerobot);
    assert_eq!(theirs_rows, mine, "rows written by lerobot");
    let back = frames(&by_lerobot);
    assert_eq!(back.len(), our_frames.len());
    let worst = back
        .iter()
        .zip(&our_frames)
        .map(|(a, b)| psnr_db(a, b))
        .fold(f64::INFINITY, f64::min);
    eprintln!("lerobot's AV1 frames vs the originals: worst {worst:.1} dB");
    assert!(worst > 25.0, "lerobot's AV1 frames at {worst:.1} dB");
    let cfg = dir.path().join("train.toml");
    std::fs::write(
        &cfg,
        format!(
            r#"{TINY_MODEL_TOML}
[data]
dataset = "{}"
robot = "franka"

[train]
batch_size = 1
max_steps = 2
checkpoint_every = 0
warmup_steps = 1
lr = 1e-4
"#,
            s(&dst)
        ),
    )
    .expect("config");
    let run_dir = dir.path().join("run");
    ok(&run(&["train", s(&cfg), "--quiet", "--out", s(&run_dir)]));
    let metrics = std::fs::read_to_string(run_dir.join("metrics.jsonl")).expect("metrics");
    assert_eq!(metrics.lines().count(), 2);
    for l in metrics.lines() {
        let v: serde_json::Value = serde_json::from_str(l).expect("json");
        assert!(v["loss"].as_f64().expect("loss").is_finite(), "{l}");
    }
    let cache = dst.join(".bridgev2w-mask-cache");
    assert!(
        std::fs::read_dir(&cache)
            .map(|d| d.count() > 0)
            .unwrap_or(false),
        "no masks rendered into {}",
        cache.display()
    );

    // 3. What `bridgev2w convert` writes loads too: a DROID episode whose
    // videos x264 wrote with B-frames (PyAV), as cameras record them.
    let raw = dir.path().join("raw");
    let status = Command::new(repo().join(".venv/bin/python"))
        .arg(repo().join("scripts/fixtures/write_raw_episodes.py"))
        .arg(&raw)
        .arg("--pyav-videos")
        .status()
        .expect("run write_raw_episodes.py");
    assert!(status.success());
    let converted = dir.path().join("converted");
    ok(&run(&[
        "convert",
        "--format",
        "droid",
        s(&raw.join("droid")),
        "--out",
        s(&converted),
        "--intrinsics",
        s(&raw.join("droid_intrinsics.json")),
        "--width",
        "32",
        "--height",
        "24",
    ]));
    let out2 = dir.path().join("loaded-converted");
    let o = Command::new(&python)
        .arg(repo().join("scripts/fixtures/lerobot_roundtrip.py"))
        .arg(&converted)
        .arg("-")
        .arg(&out2)
        .output()
        .expect("run lerobot_roundtrip.py");
    ok(&o);
    let conv = LeRobotDataset::open(&converted).expect("open converted");
    let (conv_rows, _) = assert_lerobot_loaded(&conv, &out2);
    assert!(!conv_rows.is_empty());
}
