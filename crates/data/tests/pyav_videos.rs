//! MP4 files as the world writes them (PyAV, i.e. FFmpeg's encoders: x264's
//! High profile with B-frames, SVT-AV1 as LeRobot writes it), decoded by this
//! crate and compared frame by frame with PyAV's own decoding of the same
//! files (`scripts/fixtures/write_pyav_videos.py`, the project venv's PyAV).

#![allow(clippy::unwrap_used)]

use bridgev2w_data::video::decode_mp4;
use std::path::{Path, PathBuf};
use std::process::Command;

fn fixtures() -> tempfile::TempDir {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let python = root.join(".venv/bin/python");
    assert!(
        python.is_file(),
        "{}: no project venv (scripts/setup-venv.sh)",
        python.display()
    );
    let dir = tempfile::tempdir().unwrap();
    let o = Command::new(python)
        .arg(root.join("scripts/fixtures/write_pyav_videos.py"))
        .arg(dir.path())
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "write_pyav_videos.py: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    dir
}

/// Mean and max absolute difference per channel value between our decoding
/// and PyAV's, frame by frame.
fn compare(dir: &Path, name: &str) -> Vec<(f64, u8)> {
    let ours = decode_mp4(&dir.join(format!("{name}.mp4"))).unwrap();
    let theirs = bridgev2w_io::npy::read_npy(&dir.join(format!("{name}.npy"))).unwrap();
    let (t, h, w) = (theirs.shape[0], theirs.shape[1], theirs.shape[2]);
    assert_eq!(ours.frames.len(), t, "{name}: frame count");
    assert_eq!((ours.height, ours.width), (h, w), "{name}: size");
    let pts: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.join("pts.json")).unwrap()).unwrap();
    for (i, (a, b)) in ours
        .timestamps_s
        .iter()
        .zip(pts[name].as_array().unwrap())
        .enumerate()
    {
        let b = b.as_f64().unwrap();
        assert!(
            (a - b).abs() < 1e-6,
            "{name} frame {i}: pts {a} vs PyAV's {b}"
        );
    }
    let n = h * w * 3;
    (0..t)
        .map(|i| {
            let ref_frame = &theirs.data[i * n..(i + 1) * n];
            let mut sum = 0.0;
            let mut max = 0u8;
            for (x, y) in ours.frames[i].iter().zip(ref_frame) {
                let d = (f64::from(*x) - y).abs();
                sum += d;
                max = max.max(d as u8);
            }
            (sum / n as f64, max)
        })
        .collect()
}

/// Our RGB conversion rounds and samples chroma a little differently from
/// swscale's: about 1.1 per value on average (measured), never more than a few.
fn check(diffs: &[(f64, u8)]) {
    for (i, (mean, max)) in diffs.iter().enumerate() {
        assert!(
            *mean < 1.5 && *max <= 8,
            "frame {i}: mean difference {mean}, max {max} from PyAV"
        );
    }
}

#[test]
fn x264_high_profile_with_b_frames_decodes_like_pyav() {
    let dir = fixtures();
    let diffs = compare(dir.path(), "h264-bframes");
    eprintln!("h264-bframes (mean, max) per frame: {diffs:?}");
    check(&diffs);
}

#[test]
fn svt_av1_as_lerobot_writes_it_decodes_like_pyav() {
    let dir = fixtures();
    let diffs = compare(dir.path(), "av1-svt");
    eprintln!("av1-svt (mean, max) per frame: {diffs:?}");
    check(&diffs);
}

#[test]
fn corrupt_streams_and_unsupported_profiles_are_errors_naming_them() {
    let dir = fixtures();
    let d = dir.path();
    let find = |data: &[u8], kind: &[u8]| data.windows(4).position(|w| w == kind).unwrap();
    // H.264 High 10: the avcC's profile byte says so.
    let mut h264 = std::fs::read(d.join("h264-bframes.mp4")).unwrap();
    let at = find(&h264, b"avcC") + 5;
    h264[at] = 110;
    let path = d.join("high10.mp4");
    std::fs::write(&path, &h264).unwrap();
    let e = decode_mp4(&path).unwrap_err().to_string();
    assert!(
        e.contains("high10.mp4") && e.contains("H.264 High 10 (profile_idc 110) is not supported"),
        "{e}"
    );
    // AV1 samples overwritten with garbage: an error naming a frame (or
    // frames that decode to something), never an abort.
    let mut av1 = std::fs::read(d.join("av1-svt.mp4")).unwrap();
    let mdat = find(&av1, b"mdat") + 4;
    for b in av1.iter_mut().skip(mdat + 40).take(2000) {
        *b = 0xA5;
    }
    let path = d.join("garbage-av1.mp4");
    std::fs::write(&path, &av1).unwrap();
    match decode_mp4(&path) {
        Err(e) => {
            let e = e.to_string();
            eprintln!("{e}");
            assert!(
                e.contains("garbage-av1.mp4") && e.contains("AV1 decode failed at frame"),
                "{e}"
            );
        }
        Ok(v) => assert_eq!(v.frames.len(), 24),
    }
    // A truncated file: the container says where.
    let av1 = std::fs::read(d.join("av1-svt.mp4")).unwrap();
    let path = d.join("cut.mp4");
    std::fs::write(&path, &av1[..av1.len() / 2]).unwrap();
    let e = decode_mp4(&path).unwrap_err().to_string();
    assert!(e.contains("cut.mp4") && e.contains("truncated"), "{e}");
}
