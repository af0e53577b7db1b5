//! Fuzzing the MP4 demuxer and the H.264 decoding path: structure-aware
//! mutations of a valid file (box fields overwritten with extreme values,
//! truncations, byte flips, spliced boxes) must give `Ok` or a typed error,
//! never a panic, and never allocate more than `ALLOC_FACTOR` times the
//! input (plus a fixed `ALLOC_SLACK`) on the Rust heap.
//!
//! In the test suite it runs `FUZZ_CASES` cases (default 1500);
//! `scripts/fuzz.sh mp4 SECONDS` runs it for a wall-clock budget instead
//! (the case loop of `embodiment/tests/support/fuzz.rs`; its own allocation
//! bound, with room for the decoder's tables).

#[path = "../../embodiment/tests/support/fuzz.rs"]
mod fuzz;

use bridgev2w_data::mp4::demux;
use bridgev2w_data::video::{decode_track, Mp4VideoWriter};
use peak_alloc::PeakAlloc;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use std::path::Path;

/// Counts the bytes the Rust heap holds and their peak.
#[global_allocator]
static ALLOCATOR: PeakAlloc = PeakAlloc;

/// The most the parser may allocate per input byte (the decoded frames of a
/// valid file are `W x H x 3` per frame, bounded by the container's sizes).
const ALLOC_FACTOR: usize = 64;
/// Fixed allowance: decoder tables, error strings, one decoded frame.
const ALLOC_SLACK: usize = 4 << 20;

/// A valid 3-frame 32x32 H.264 MP4.
fn seed_file() -> Vec<u8> {
    let (w, h) = (32, 32);
    let mut writer = Mp4VideoWriter::new(Path::new("seed.mp4"), w, h, 10).expect("writer");
    for f in 0..3 {
        let rgb: Vec<u8> = (0..w * h * 3)
            .map(|i| ((i / 3 % w) * 7 + (i / 3 / w) * 3 + f * 20) as u8)
            .collect();
        writer.push(&rgb, f == 0).expect("push");
    }
    writer.to_bytes().expect("bytes")
}

/// The offsets of every box header (size, type) the file's nesting holds.
fn box_offsets(data: &[u8]) -> Vec<usize> {
    const CONTAINERS: [&[u8; 4]; 6] = [b"moov", b"trak", b"mdia", b"minf", b"stbl", b"dinf"];
    let mut out = Vec::new();
    let mut stack = vec![(0usize, data.len())];
    while let Some((mut at, end)) = stack.pop() {
        while at + 8 <= end {
            let size =
                u32::from_be_bytes([data[at], data[at + 1], data[at + 2], data[at + 3]]) as usize;
            if size < 8 || at + size > end {
                break;
            }
            out.push(at);
            let kind = &data[at + 4..at + 8];
            if CONTAINERS.iter().any(|c| c.as_slice() == kind) {
                stack.push((at + 8, at + size));
            }
            at += size;
        }
    }
    out
}

/// Values that break size arithmetic.
const WEIRD_U32: [u32; 8] = [0, 1, 7, 8, 0x7FFF_FFFF, 0x8000_0000, 0xFFFF_FFF0, u32::MAX];

/// One mutation of `seed` (structure-aware: box sizes, box fields, tables).
fn mutate(seed: &[u8], boxes: &[usize], rng: &mut ChaCha8Rng) -> Vec<u8> {
    let mut d = seed.to_vec();
    for _ in 0..rng.gen_range(1..=3) {
        match rng.gen_range(0..6) {
            // A box's size field.
            0 => {
                let at = boxes[rng.gen_range(0..boxes.len())];
                let v = WEIRD_U32[rng.gen_range(0..WEIRD_U32.len())];
                if at + 4 <= d.len() {
                    d[at..at + 4].copy_from_slice(&v.to_be_bytes());
                }
            }
            // A field inside a box (counts, sizes, offsets, dimensions).
            1 => {
                let at = boxes[rng.gen_range(0..boxes.len())] + 8 + 4 * rng.gen_range(0..8);
                if at + 4 <= d.len() {
                    let v = if rng.gen_bool(0.5) {
                        WEIRD_U32[rng.gen_range(0..WEIRD_U32.len())]
                    } else {
                        rng.gen()
                    };
                    d[at..at + 4].copy_from_slice(&v.to_be_bytes());
                }
            }
            // Truncation.
            2 => {
                let n = rng.gen_range(0..d.len().max(1));
                d.truncate(n);
            }
            // Byte flips anywhere (the H.264 payload included).
            3 => {
                for _ in 0..rng.gen_range(1..=8) {
                    if !d.is_empty() {
                        let i = rng.gen_range(0..d.len());
                        d[i] ^= 1 << rng.gen_range(0..8);
                    }
                }
            }
            // A box duplicated or removed.
            4 => {
                let at = boxes[rng.gen_range(0..boxes.len())];
                if at + 8 <= d.len() {
                    let size =
                        u32::from_be_bytes([d[at], d[at + 1], d[at + 2], d[at + 3]]) as usize;
                    if size >= 8 && at + size <= d.len() {
                        let b: Vec<u8> = d[at..at + size].to_vec();
                        if rng.gen_bool(0.5) {
                            d.splice(at..at, b);
                        } else {
                            d.drain(at..at + size);
                        }
                    }
                }
            }
            // Random bytes appended.
            _ => {
                let n = rng.gen_range(1..64);
                d.extend((0..n).map(|_| rng.gen::<u8>()));
            }
        }
    }
    d
}

/// The contract on one input.
fn check(case: usize, data: &[u8]) {
    let path = Path::new("fuzz.mp4");
    let base = ALLOCATOR.current_usage();
    ALLOCATOR.reset_peak_usage();
    let result = std::panic::catch_unwind(|| match demux(path, data) {
        Ok(track) => decode_track(path, data, &track)
            .map(|_| ())
            .map_err(|e| e.to_string()),
        Err(e) => Err(e.to_string()),
    });
    let peak = ALLOCATOR.peak_usage().saturating_sub(base);
    match result {
        Ok(Ok(())) => {}
        Ok(Err(message)) => assert!(
            message.contains("fuzz.mp4"),
            "case {case}: the error does not name the file: {message}"
        ),
        Err(_) => panic!("case {case}: the MP4 path panicked on {} bytes", data.len()),
    }
    assert!(
        peak <= ALLOC_FACTOR * data.len() + ALLOC_SLACK,
        "case {case}: {peak} bytes allocated for a {}-byte input",
        data.len()
    );
}

#[test]
fn mutated_mp4_files_never_panic_nor_over_allocate() {
    let seed = seed_file();
    let boxes = box_offsets(&seed);
    assert!(boxes.len() > 10, "{} boxes", boxes.len());
    fuzz::run_target(
        "mp4",
        std::slice::from_ref(&seed),
        |s, rng| mutate(s, &boxes, rng),
        check,
    );
}
