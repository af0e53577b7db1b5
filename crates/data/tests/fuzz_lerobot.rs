//! Fuzzing the LeRobot dataset reader: one file of a small valid dataset
//! (`meta/info.json`, the episode index, the frames or tasks parquet, a
//! calibration JSON) is mutated per case, then the dataset is opened and
//! episode 0 read (frames, masks, calibration, video). Every outcome must be
//! `Ok` or an error naming a file or field, never a panic, and the Rust heap
//! stays within `ALLOC_FACTOR` times the dataset's bytes.
//!
//! In the test suite it runs `FUZZ_CASES` cases (default 1500, spread over
//! the files); `scripts/fuzz.sh lerobot SECONDS` runs it for a wall-clock
//! budget.

#[path = "../../embodiment/tests/support/fuzz.rs"]
mod fuzz;

use bridgev2w_data::lerobot::LeRobotDataset;
use bridgev2w_data::synth::{write_dataset, SynthConfig, VIDEO_KEY};
use fuzz::{mutate_text, run_target};
use peak_alloc::PeakAlloc;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use std::path::Path;

/// Counts the bytes the Rust heap holds and their peak.
#[global_allocator]
static ALLOCATOR: PeakAlloc = PeakAlloc;

/// The dataset's files that a case may mutate (relative paths).
const FILES: [&str; 5] = [
    "meta/info.json",
    "meta/episodes/chunk-000/file-000.parquet",
    "data/chunk-000/file-000.parquet",
    "meta/tasks.parquet",
    "meta/calibration/episode_000000.json",
];

/// Bytes of every file under `root`.
fn dataset_bytes(root: &Path) -> usize {
    let mut total = 0;
    let mut stack = vec![root.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).expect("ls").flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                total += e.metadata().map_or(0, |m| m.len() as usize);
            }
        }
    }
    total
}

/// Opens the dataset and reads everything of episode 0; the first error.
fn read_all(root: &Path) -> Result<(), String> {
    let ds = LeRobotDataset::open(root).map_err(|e| e.to_string())?;
    let ep = ds.read_episode(0).map_err(|e| e.to_string())?;
    let values = ep
        .frames
        .iter()
        .flat_map(|f| f.state.iter().chain(&f.action));
    if values.clone().any(|v| !v.is_finite()) {
        return Err("accepted a non-finite state".into());
    }
    ds.read_masks(0).map_err(|e| e.to_string())?;
    ds.read_calibration(0, VIDEO_KEY)
        .map_err(|e| e.to_string())?;
    ds.read_video(0, VIDEO_KEY).map_err(|e| e.to_string())?;
    Ok(())
}

#[test]
fn mutated_lerobot_datasets_never_panic_nor_over_allocate() {
    let dir = tempfile::tempdir().expect("tempdir");
    let root = dir.path().join("ds");
    let cfg = SynthConfig {
        frames: 6,
        width: 32,
        height: 24,
        seed: 5,
        episodes_per_split: [1, 1, 0, 0],
        ..SynthConfig::default()
    };
    write_dataset(&cfg, &root, &|| {}).expect("dataset");
    read_all(&root).expect("the valid dataset reads");
    let total = dataset_bytes(&root);
    let originals: Vec<Vec<u8>> = FILES
        .iter()
        .map(|f| std::fs::read(root.join(f)).expect("dataset file"))
        .collect();
    // A seed is (file index, its bytes): the mutator keeps the index byte.
    let seeds: Vec<Vec<u8>> = originals
        .iter()
        .enumerate()
        .map(|(i, b)| {
            let mut s = vec![i as u8];
            s.extend_from_slice(b);
            s
        })
        .collect();
    let mutate = |seed: &[u8], rng: &mut ChaCha8Rng| {
        let mut out = vec![seed[0]];
        let body = &seed[1..];
        if seed[0] == 0 || seed[0] == 4 || rng.gen_bool(0.5) {
            out.extend(mutate_text(body, rng));
        } else {
            // Binary files: flips and overwritten words in the footer, where
            // parquet keeps its metadata, as often as anywhere else.
            let mut b = body.to_vec();
            for _ in 0..rng.gen_range(1..=6) {
                if b.is_empty() {
                    break;
                }
                let i = if rng.gen_bool(0.5) {
                    b.len() - 1 - rng.gen_range(0..b.len().min(400))
                } else {
                    rng.gen_range(0..b.len())
                };
                b[i] = [0u8, 0xFF, 0x7F, 0x80, rng.gen()][rng.gen_range(0..5)];
            }
            out.extend(b);
        }
        out
    };
    let check = |case: usize, data: &[u8]| {
        let i = data[0] as usize;
        let path = root.join(FILES[i]);
        std::fs::write(&path, &data[1..]).expect("write case");
        let result =
            fuzz::guarded_within(&ALLOCATOR, "lerobot", case, data, total, || read_all(&root));
        std::fs::write(&path, &originals[i]).expect("restore");
        if let Err(e) = result {
            assert!(
                !e.contains("accepted a non-finite"),
                "lerobot case {case} ({}): {e}",
                FILES[i]
            );
            assert!(
                e.contains(dir.path().to_str().expect("utf-8 path")) || e.contains("episode"),
                "lerobot case {case} ({}): the error names no file or episode: {e}",
                FILES[i]
            );
        }
    };
    run_target("lerobot", &seeds, mutate, check);
    // Found by `scripts/fuzz.sh lerobot 60`: parquet footers whose column
    // chunk has a negative offset (4816) and a dictionary-encoded page
    // without a dictionary (97784) panicked the parquet reader.
    fuzz::replay(&seeds, mutate, &[4816, 97784], check);
}
