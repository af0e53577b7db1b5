//! The streaming video decoder: frames come one at a time in presentation
//! order, with the right content, while the memory held stays a few frames'
//! worth, not the video's (`peak_alloc` counts the Rust heap: the streaming
//! state, the frames and rav1d's pictures; openh264's own buffers are C
//! allocations and the resident-set check covers them where `/proc` has it).

#![allow(clippy::unwrap_used, clippy::expect_used)]

use bridgev2w_data::video::{decode_mp4, decode_track, Mp4VideoWriter, VideoError, VideoStream};
use peak_alloc::PeakAlloc;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::sync::Mutex;

/// Counts the bytes the Rust heap holds and their peak.
#[global_allocator]
static ALLOCATOR: PeakAlloc = PeakAlloc;

/// The heap is one counter for the whole process: one test at a time.
static SERIAL: Mutex<()> = Mutex::new(());

/// The test pattern's value at pixel (`x`, `y`) of frame `f` (every channel).
fn pattern(x: usize, y: usize, f: usize) -> u8 {
    ((x * 2 + y + f * 3) % 200 + 20) as u8
}

/// Writes a `frames`-frame `w` x `h` H.264 video of [`pattern`] (no frame
/// of it held beyond the one being encoded; the encoded samples are).
fn write_pattern(path: &Path, (w, h): (usize, usize), frames: usize) {
    let mut writer = Mp4VideoWriter::new(path, w, h, 30).unwrap();
    let mut rgb = vec![0u8; w * h * 3];
    for f in 0..frames {
        for y in 0..h {
            for x in 0..w {
                let v = pattern(x, y, f);
                rgb[(y * w + x) * 3..(y * w + x) * 3 + 3].fill(v);
            }
        }
        writer.push(&rgb, f == 0).unwrap();
    }
    std::fs::write(path, writer.to_bytes().unwrap()).unwrap();
}

/// Resets this process's peak resident set (`VmHWM`); `None` without `/proc`.
fn reset_peak_rss() -> Option<()> {
    std::fs::write("/proc/self/clear_refs", "5").ok()
}

fn rss_kb(field: &str) -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with(field))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

#[test]
fn a_long_video_streams_in_the_memory_of_a_few_frames() {
    let _one = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("long.mp4");
    let (w, h, frames) = (320, 240, 480);
    write_pattern(&path, (w, h), frames);
    let frame_bytes = w * h * 3;
    let whole = frame_bytes * frames;

    let base = ALLOCATOR.current_usage();
    ALLOCATOR.reset_peak_usage();
    let rss_reset = reset_peak_rss().is_some();
    let rss_base = rss_kb("VmRSS:");
    let mut stream = VideoStream::open(&path).unwrap();
    let info = stream.info().clone();
    assert_eq!((info.width, info.height, info.frames), (w, h, frames));
    assert_eq!(info.codec, "H.264");
    assert!((info.timestamps_s[frames - 1] - (frames - 1) as f64 / 30.0).abs() < 1e-9);
    let mut checksum = 0u64;
    let mut count = 0;
    let mut worst = 0.0f64;
    while let Some(frame) = stream.next_frame().unwrap() {
        assert_eq!(frame.index, count);
        assert_eq!(frame.rgb.len(), frame_bytes);
        assert_eq!(frame.timestamp_s, info.timestamps_s[count]);
        // The content is this frame's pattern (so the order is right).
        let mut err = 0u64;
        for y in (0..h).step_by(7) {
            for x in (0..w).step_by(5) {
                let got = frame.rgb[(y * w + x) * 3 + 1];
                err += u64::from(got.abs_diff(pattern(x, y, count)));
            }
        }
        let mean = err as f64 / (h.div_ceil(7) * w.div_ceil(5)) as f64;
        worst = worst.max(mean);
        checksum = checksum
            .wrapping_mul(31)
            .wrapping_add(frame.rgb.iter().map(|&v| u64::from(v)).sum::<u64>());
        count += 1;
    }
    let peak = ALLOCATOR.peak_usage().saturating_sub(base);
    let rss_peak = rss_kb("VmHWM:");
    assert_eq!(count, frames);
    assert!(stream.next_frame().unwrap().is_none(), "the stream ended");
    let held = stream.peak_frames_held();
    drop(stream);
    eprintln!(
        "{frames} frames of {w}x{h}: the whole video is {:.1} MB; streaming peak Rust heap {:.2} MB \
         ({:.1} frames), at most {held} decoded frames held; worst frame's mean error vs the pattern {worst:.2}; \
         resident set base {rss_base:?} kB, peak {rss_peak:?} kB (reset: {rss_reset}); checksum {checksum:x}",
        whole as f64 / 1e6,
        peak as f64 / 1e6,
        peak as f64 / frame_bytes as f64,
    );
    assert!(
        worst < 3.0,
        "frames differ from the pattern: mean error {worst}"
    );
    // A few frames (the one returned, the one being converted, the sample
    // table and reading buffers), never the video.
    assert!(
        peak < 4 * frame_bytes && peak * 50 < whole,
        "streaming peak {peak} bytes for {whole} bytes of frames"
    );
    if let (true, Some(base), Some(high)) = (rss_reset, rss_base, rss_peak) {
        let grown = high.saturating_sub(base) * 1024;
        assert!(
            (grown as usize) * 4 < whole,
            "resident set grew {grown} bytes streaming {whole} bytes of frames"
        );
    }

    // Collecting the stream gives the same frames.
    let all = decode_mp4(&path).unwrap();
    let sum: u64 = all.frames.iter().fold(0u64, |c, f| {
        c.wrapping_mul(31)
            .wrapping_add(f.iter().map(|&v| u64::from(v)).sum::<u64>())
    });
    assert_eq!(sum, checksum);
    assert_eq!(all.timestamps_s, info.timestamps_s);
}

fn pyav_fixtures(frames: usize) -> tempfile::TempDir {
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
        .args(["--frames", &frames.to_string()])
        .output()
        .unwrap();
    assert!(
        o.status.success(),
        "write_pyav_videos.py: {}",
        String::from_utf8_lossy(&o.stderr)
    );
    dir
}

/// x264 with 3 B-frames and SVT-AV1 (PyAV's encoders): the stream holds
/// the reorder depth's frames, and gives what decoding the file whole does.
#[test]
fn b_frames_and_av1_stream_with_a_bounded_reorder_buffer() {
    let frames = 240;
    let dir = pyav_fixtures(frames);
    let _one = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    for name in ["h264-bframes", "av1-svt"] {
        let path = dir.path().join(format!("{name}.mp4"));
        let base = ALLOCATOR.current_usage();
        ALLOCATOR.reset_peak_usage();
        let mut stream = VideoStream::open(&path).unwrap();
        let info = stream.info().clone();
        let frame_bytes = info.frame_bytes();
        let mut sums = Vec::new();
        for frame in &mut stream {
            let frame = frame.unwrap();
            sums.push(frame.rgb.iter().map(|&v| u64::from(v)).sum::<u64>());
        }
        let peak = ALLOCATOR.peak_usage().saturating_sub(base);
        let held = stream.peak_frames_held();
        eprintln!(
            "{name}: {frames} frames of {}x{}, whole video {:.1} MB; streaming peak Rust heap {:.2} MB \
             ({:.1} frames); at most {held} decoded frames held",
            info.width,
            info.height,
            (frame_bytes * frames) as f64 / 1e6,
            peak as f64 / 1e6,
            peak as f64 / frame_bytes as f64
        );
        assert_eq!(sums.len(), frames, "{name}");
        assert!(held <= 16, "{name}: {held} frames held");
        // rav1d's reference pictures count here (Rust), openh264's do not.
        assert!(
            peak * 8 < frame_bytes * frames,
            "{name}: streaming peak {peak} bytes for {} bytes of frames",
            frame_bytes * frames
        );
        // Decoding the file's bytes whole gives the same frames in order.
        let data = std::fs::read(&path).unwrap();
        let track = bridgev2w_data::mp4::demux(&path, &data).unwrap();
        // Reading the sample table from the file (only `moov` read whole)
        // gives what demuxing its bytes does.
        assert_eq!(bridgev2w_data::mp4::demux_file(&path).unwrap(), track);
        let whole = decode_track(&path, &data, &track).unwrap();
        let whole_sums: Vec<u64> = whole
            .frames
            .iter()
            .map(|f| f.iter().map(|&v| u64::from(v)).sum())
            .collect();
        assert_eq!(whole_sums, sums, "{name}");
        assert_eq!(whole.timestamps_s, info.timestamps_s, "{name}");
    }
}

/// Errors name the file: a missing one, and samples cut off after the
/// sample table was read (the stream reads them only when it gets there).
#[test]
fn a_file_cut_while_streaming_is_an_error_naming_it() {
    let _one = SERIAL.lock().unwrap_or_else(|e| e.into_inner());
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("missing.mp4");
    let e = VideoStream::open(&missing).unwrap_err().to_string();
    assert!(e.contains("missing.mp4"), "{e}");

    let path = dir.path().join("cut.mp4");
    write_pattern(&path, (64, 48), 20);
    let mut stream = VideoStream::open(&path).unwrap();
    assert_eq!(stream.info().frames, 20);
    stream.next_frame().unwrap().unwrap();
    // The writer puts `mdat` before `moov`: cutting the file's samples away
    // (keeping its length) leaves a table pointing at nothing.
    let bytes = std::fs::read(&path).unwrap();
    let mdat = bytes.windows(4).position(|w| w == b"mdat").unwrap();
    std::fs::write(&path, &bytes[..mdat + 100]).unwrap();
    let mut err = None;
    for frame in &mut stream {
        if let Err(e) = frame {
            err = Some(e);
        }
    }
    let e = err.expect("an error");
    assert!(matches!(e, VideoError::Frame { .. }), "{e:?}");
    let e = e.to_string();
    assert!(
        e.contains("cut.mp4") && e.contains("cannot read sample"),
        "{e}"
    );
    assert!(stream.next().is_none(), "the stream is over after an error");
}
