//! `convert`'s inputs (issue 69, item 4): a camera list that names no
//! camera or one twice is refused by the library's options, before anything
//! is read or written, so the CLI and the Python package refuse it alike;
//! and a video whose MP4 edit list (`elst`) hides leading frames is
//! converted from the frames a player shows, as the LeRobot reader reads
//! them, not from the first coded sample.
#![allow(clippy::unwrap_used)]

use bridgev2w_data::lerobot::LeRobotDataset;
use bridgev2w_data::raw::agibot::AgibotOptions;
use bridgev2w_data::raw::convert::{ConvertError, ConvertOptions};
use bridgev2w_data::raw::droid::DroidOptions;
use bridgev2w_data::raw::report::Note;
use bridgev2w_data::raw::source::{convert_source, RawSource};
use bridgev2w_data::video::{decode_mp4, psnr_db, write_test_pattern, VideoStream};
use bridgev2w_embodiment::embodiment::Embodiment;
use serde_json::Value;
use std::path::{Path, PathBuf};
use std::process::Command;

fn repo_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

fn options(format: &str) -> ConvertOptions {
    ConvertOptions {
        width: 32,
        height: 24,
        fps: 30,
        joint_names: None,
        skip_bad: false,
        split: Some("train".into()),
        source_format: format.into(),
        overwrite: false,
    }
}

fn names(v: &[&str]) -> Vec<String> {
    v.iter().map(|s| s.to_string()).collect()
}

#[test]
fn camera_lists_naming_none_or_one_twice_are_refused_by_the_options() {
    let tmp = tempfile::tempdir().unwrap();
    let root = tmp.path().join("no-such-source");
    let agibot = |cams: &[&str]| RawSource::Agibot {
        root: root.clone(),
        options: AgibotOptions {
            cameras: names(cams),
            ..AgibotOptions::default()
        },
    };
    let droid = |roles: &[&str]| RawSource::Droid {
        root: root.clone(),
        options: DroidOptions {
            roles: names(roles),
            intrinsics: Default::default(),
            calibration: Vec::new(),
            missing_calibration: Default::default(),
        },
    };
    agibot(&["head", "hand_left"]).validate().unwrap();
    droid(&["ext1", "wrist"]).validate().unwrap();
    for (source, needles) in [
        (
            agibot(&["head", "head"]),
            &["cameras [\"head\", \"head\"]", "\"head\" is named twice"][..],
        ),
        (
            agibot(&["head", "hand_left", "head"]),
            &["\"head\" is named twice"],
        ),
        (agibot(&[]), &["cameras []", "at least one camera"]),
        (agibot(&["../secret"]), &["\"../secret\"", "plain name"]),
        (
            droid(&["ext1", "ext1"]),
            &["cameras [\"ext1\", \"ext1\"]", "\"ext1\" is named twice"],
        ),
        (droid(&[]), &["at least one camera"]),
        (droid(&["ext3"]), &["\"ext3\"", "expected one of"]),
    ] {
        let e = source.validate().unwrap_err();
        for n in needles {
            assert!(e.contains(n), "{n:?} not in: {e}");
        }
        // convert_source refuses it first: before the source (which does
        // not exist) is searched and before the output is created.
        let out = tmp.path().join("out");
        let embodiment = Embodiment::builtin("agibot-g1").unwrap();
        let opts = options("agibot");
        match convert_source(&source, None, &embodiment, &out, &opts, &|_| {}) {
            Err(ConvertError::Options(m)) => assert_eq!(m, e),
            other => panic!("expected the options' error {e:?}, got {other:?}"),
        }
        assert!(!out.exists() && std::fs::read_dir(tmp.path()).unwrap().count() == 0);
    }
}

/// `mp4` as this crate's muxer writes it (`ftyp`, `mdat`, then `moov`) with
/// an edit list in its track: one edit that starts at media time
/// `media_time` (track timescale ticks). The boxes after `mdat` grow, so no
/// sample offset moves.
fn with_edit_list(mp4: &[u8], media_time: u32) -> Vec<u8> {
    let be32 = |b: &[u8], at: usize| u32::from_be_bytes(b[at..at + 4].try_into().unwrap()) as usize;
    // The child boxes of `data[from..to]`: (start, size, kind).
    let boxes = |data: &[u8], from: usize, to: usize| {
        let mut out = Vec::new();
        let mut at = from;
        while at + 8 <= to {
            let size = be32(data, at);
            out.push((at, size, data[at + 4..at + 8].to_vec()));
            at += size;
        }
        out
    };
    let top = boxes(mp4, 0, mp4.len());
    let kinds: Vec<&[u8]> = top.iter().map(|b| &b.2[..]).collect();
    assert_eq!(
        kinds,
        [&b"ftyp"[..], b"mdat", b"moov"],
        "the muxer's layout"
    );
    let (moov, moov_size, _) = top[2].clone();
    let trak = boxes(mp4, moov + 8, moov + moov_size)
        .into_iter()
        .find(|b| b.2 == b"trak")
        .unwrap();
    let tkhd = boxes(mp4, trak.0 + 8, trak.0 + trak.1)
        .into_iter()
        .find(|b| b.2 == b"tkhd")
        .unwrap();
    let mut elst = Vec::new();
    elst.extend_from_slice(&28u32.to_be_bytes());
    elst.extend_from_slice(b"elst");
    elst.extend_from_slice(&[0, 0, 0, 0]); // version 0, flags
    elst.extend_from_slice(&1u32.to_be_bytes()); // one edit
    elst.extend_from_slice(&0u32.to_be_bytes()); // its duration (movie ticks): unused here
    elst.extend_from_slice(&media_time.to_be_bytes());
    elst.extend_from_slice(&[0, 1, 0, 0]); // rate 1.0
    let mut edts = ((elst.len() + 8) as u32).to_be_bytes().to_vec();
    edts.extend_from_slice(b"edts");
    edts.extend_from_slice(&elst);
    let at = tkhd.0 + tkhd.1;
    let mut out = mp4[..at].to_vec();
    out.extend_from_slice(&edts);
    out.extend_from_slice(&mp4[at..]);
    for (start, size) in [(moov, moov_size), (trak.0, trak.1)] {
        out[start..start + 4].copy_from_slice(&((size + edts.len()) as u32).to_be_bytes());
    }
    out
}

#[test]
fn convert_skips_the_leading_frames_an_edit_list_hides() {
    let python = repo_root().join(".venv/bin/python");
    assert!(
        python.is_file(),
        "{} not found: run scripts/setup-venv.sh (./run test does)",
        python.display()
    );
    let dir = tempfile::tempdir().unwrap();
    let status = Command::new(&python)
        .arg(repo_root().join("scripts/fixtures/write_raw_episodes.py"))
        .arg(dir.path())
        .status()
        .unwrap();
    assert!(status.success(), "write_raw_episodes.py failed");
    let expected: Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("expected.json")).unwrap())
            .unwrap();
    let size = |k: &str| expected[k].as_u64().unwrap() as usize;
    let (w, h, states) = (size("width"), size("height"), size("frames"));
    let root = dir.path().join("agibot");
    let video = root.join("observations/327/648642/videos/head_color.mp4");

    // Two more frames than states, the first two hidden by the edit list
    // (15 fps, 1000 ticks a frame: the edit starts at the third frame).
    const HIDDEN: usize = 2;
    write_test_pattern(&video, (w, h), states + HIDDEN, 15).unwrap();
    let coded = decode_mp4(&video).unwrap().frames;
    let bytes = with_edit_list(&std::fs::read(&video).unwrap(), 1000 * HIDDEN as u32);
    std::fs::write(&video, bytes).unwrap();
    let info = VideoStream::open(&video).unwrap().info().clone();
    assert_eq!(info.frames, states + HIDDEN);
    assert_eq!(
        info.hidden_by_edit_list(),
        HIDDEN,
        "{:?}",
        info.timestamps_s
    );
    assert_eq!(info.timestamps_s[HIDDEN], 0.0);

    let out = dir.path().join("converted");
    let embodiment = Embodiment::builtin("agibot-g1").unwrap();
    let source = RawSource::Agibot {
        root,
        options: AgibotOptions::default(),
    };
    let report = convert_source(
        &source,
        None,
        &embodiment,
        &out,
        &options("agibot"),
        &|_| {},
    )
    .unwrap();
    assert_eq!(report.views_written, 1, "{report:?}");
    let skipped: Vec<&Note> = report
        .notes
        .iter()
        .map(|n| &n.note)
        .filter(|n| n.kind() == "edit_list_skipped")
        .collect();
    assert_eq!(
        skipped,
        [&Note::EditListSkipped {
            video: video.clone(),
            video_frames: states + HIDDEN,
            hidden: HIDDEN,
        }]
    );
    assert!(
        report
            .notes
            .iter()
            .all(|n| n.note.kind() != "frames_aligned"),
        "the shown frames match the states one for one: {:?}",
        report.notes
    );

    // Each converted frame is the shown frame of its state: coded frame
    // t + HIDDEN (the pattern brightens by 10 levels a frame).
    let ds = LeRobotDataset::open(&out).unwrap();
    let frames = ds.read_video(0, &ds.video_keys[0]).unwrap();
    assert_eq!(frames.len(), states);
    let resized: Vec<Vec<u8>> = coded
        .iter()
        .map(|f| bridgev2w_data::raw::convert::resize_rgb(f, (w, h), (32, 24)))
        .collect();
    for (t, f) in frames.iter().enumerate() {
        let best = (0..resized.len())
            .max_by(|&a, &b| psnr_db(f, &resized[a]).total_cmp(&psnr_db(f, &resized[b])))
            .unwrap();
        assert_eq!(best, t + HIDDEN, "converted frame {t}");
    }
}
