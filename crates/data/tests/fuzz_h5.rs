//! Fuzzing the HDF5 path of the DROID and AgiBot World readers: a small file
//! written by h5py (libhdf5, in the project venv: contiguous, chunked and
//! compressed datasets, groups, f32/f64/integer types) is mutated (words of
//! the superblock and object headers overwritten with extreme values, byte
//! flips, truncation); opening it, listing its groups and reading every
//! dataset must give values or an error naming the file, never a panic, and
//! the Rust heap stays within `ALLOC_FACTOR` times the file.
//!
//! In the test suite it runs `FUZZ_CASES` cases (default 1500);
//! `scripts/fuzz.sh h5 SECONDS` runs it for a wall-clock budget.

#[path = "../../embodiment/tests/support/fuzz.rs"]
mod fuzz;

use bridgev2w_data::raw::h5::{H5, MAX_DECODED_RATIO};
use fuzz::run_target;
use peak_alloc::PeakAlloc;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use std::path::Path;
use std::process::Command;

/// Counts the bytes the Rust heap holds and their peak.
#[global_allocator]
static ALLOCATOR: PeakAlloc = PeakAlloc;

const WRITER: &str = r#"
import sys, h5py, numpy as np
with h5py.File(sys.argv[1], "w") as f:
    f["observation/joint_position"] = np.linspace(-1, 1, 5 * 7, dtype=np.float32).reshape(5, 7)
    f.create_dataset("action/gripper", data=np.arange(5, dtype=np.int64))
    f.create_dataset("state/pose", data=np.random.default_rng(0).normal(size=(6, 4)),
                     chunks=(2, 4), compression="gzip")
    f.create_dataset("state/u8", data=np.arange(12, dtype=np.uint8).reshape(3, 4), chunks=(1, 4))
"#;

fn seed(dir: &Path) -> Vec<u8> {
    let python = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../.venv/bin/python");
    assert!(
        python.is_file(),
        "{} is missing: run scripts/setup-venv.sh (h5py writes the seed)",
        python.display()
    );
    let path = dir.join("seed.h5");
    let status = Command::new(&python)
        .args(["-c", WRITER])
        .arg(&path)
        .status()
        .expect("run python");
    assert!(status.success(), "h5py could not write the seed");
    std::fs::read(&path).expect("seed")
}

/// Word-aware mutation: HDF5 keeps sizes, addresses and counts in 2-, 4-
/// and 8-byte little-endian fields.
fn mutate_h5(seed: &[u8], rng: &mut ChaCha8Rng) -> Vec<u8> {
    let mut d = seed.to_vec();
    for _ in 0..rng.gen_range(1..=4) {
        match rng.gen_range(0..5) {
            0 | 1 => {
                let w = [2usize, 4, 8][rng.gen_range(0..3)];
                if d.len() > w {
                    let at = rng.gen_range(0..d.len() - w);
                    let v: u64 =
                        [0, 1, 0xFF, 0xFFFF, 0x7FFF_FFFF, u64::MAX, rng.gen()][rng.gen_range(0..7)];
                    d[at..at + w].copy_from_slice(&v.to_le_bytes()[..w]);
                }
            }
            2 => {
                for _ in 0..rng.gen_range(1..=8) {
                    let i = rng.gen_range(0..d.len());
                    d[i] ^= 1 << rng.gen_range(0..8);
                }
            }
            3 => {
                let n = rng.gen_range(0..d.len());
                d.truncate(n.max(1));
            }
            _ => {
                let n = rng.gen_range(1..64);
                d.extend((0..n).map(|_| rng.gen::<u8>()));
            }
        }
    }
    d
}

/// Opens the file and reads everything in it; the first error.
fn read_all(path: &Path) -> Result<usize, String> {
    let h5 = H5::open(path).map_err(|e| e.to_string())?;
    let mut values = 0;
    let mut groups = vec![String::new()];
    let mut visited = 0;
    while let Some(g) = groups.pop() {
        visited += 1;
        if visited > 64 {
            break; // a mutated file may link groups in a cycle
        }
        let (subgroups, datasets) = h5.members(&g).map_err(|e| e.to_string())?;
        for d in datasets {
            let a = h5.read(&format!("{g}/{d}")).map_err(|e| e.to_string())?;
            assert_eq!(
                a.values.len(),
                a.shape.iter().product::<usize>(),
                "{g}/{d}: shape and values disagree"
            );
            assert!(a.values.iter().all(|v| v.is_finite()));
            values += a.values.len();
        }
        groups.extend(subgroups.into_iter().map(|s| format!("{g}/{s}")));
    }
    Ok(values)
}

/// A format that compresses: the heap may hold twice
/// [`MAX_DECODED_RATIO`] per byte of file (the decoded dataset and its `f64`
/// copy), plus 16 MiB whatever the size: `hdf5-reader` reserves room for as
/// many entries as a version-1 B-tree node claims (a 16-bit count, at most
/// about 9.5 MB; a 2,811-byte file reached it). It found (seed 0, case 262) a 12,664-byte
/// file whose dataspace claimed 33,554,438 rows beyond its maximum of 6, read
/// into 2,147,511,275 bytes before `H5` bounded both.
#[test]
fn mutated_hdf5_files_never_panic_nor_over_allocate() {
    let dir = tempfile::tempdir().expect("tempdir");
    let seeds = vec![seed(dir.path())];
    assert_eq!(
        read_all(&dir.path().join("seed.h5")),
        Ok(35 + 5 + 24 + 12),
        "the seed reads"
    );
    let path = dir.path().join("case.h5");
    run_target("h5", &seeds, mutate_h5, |case, data| {
        std::fs::write(&path, data).expect("write case");
        let limit = fuzz::AllocLimit {
            per_byte: 2 * MAX_DECODED_RATIO,
            fixed: 16 << 20,
        };
        let result = fuzz::guarded_by(&ALLOCATOR, "h5", case, data, data.len(), limit, || {
            read_all(&path)
        });
        if let Err(e) = result {
            assert!(
                e.contains("case.h5"),
                "h5 case {case}: the error does not name the file: {e}"
            );
        }
    });
}

/// The case the fuzzer found, built here: `state/pose` (6 x 4, at most
/// 6 x 4) told it has 33,554,438 rows, and a 1-row dataset told it has
/// 2^40 rows with an unlimited maximum; both are refused by name before any
/// value is read.
#[test]
fn a_dataspace_beyond_its_maximum_or_the_file_is_refused() {
    let dir = tempfile::tempdir().expect("tempdir");
    let mut data = seed(dir.path());
    let pose_dims: Vec<u8> = [6u64, 4, 6, 4]
        .iter()
        .flat_map(|v| v.to_le_bytes())
        .collect();
    let at = data
        .windows(pose_dims.len())
        .position(|w| w == pose_dims.as_slice())
        .expect("the dataspace of state/pose (6 x 4, max 6 x 4) is in the seed");
    data[at..at + 8].copy_from_slice(&33_554_438u64.to_le_bytes());
    let path = dir.path().join("rows.h5");
    std::fs::write(&path, &data).expect("write");
    let h5 = H5::open(&path).expect("the file opens");
    let e = h5.read("state/pose").expect_err("refused").to_string();
    assert!(
        e.contains("rows.h5") && e.contains("state/pose") && e.contains("maximum shape"),
        "{e}"
    );
    // Within the maximum but beyond what the file can hold.
    data[at + 16..at + 24].copy_from_slice(&u64::MAX.to_le_bytes());
    data[at..at + 8].copy_from_slice(&(1u64 << 40).to_le_bytes());
    std::fs::write(&path, &data).expect("write");
    let h5 = H5::open(&path).expect("the file opens");
    let e = h5.read("state/pose").expect_err("refused").to_string();
    assert!(
        e.contains("state/pose") && e.contains(&format!("{MAX_DECODED_RATIO} times")),
        "{e}"
    );
}
