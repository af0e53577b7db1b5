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

use bridgev2w_data::raw::h5::H5;
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

/// Ignored: it finds a real fault not fixed yet (issue 20). With the default
/// seed, case 262, a 12,664-byte mutation of the seed, makes the HDF5 path
/// allocate 2,147,511,275 bytes (`hdf5-reader` trusts a size field of the
/// file). Run it with `cargo test -p bridgev2w-data --test fuzz_h5 -- --ignored`.
#[test]
#[ignore = "issue 20: a 12 KB mutated HDF5 file makes the reader allocate 2 GB (not fixed yet)"]
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
        let result = fuzz::guarded(&ALLOCATOR, "h5", case, data, || read_all(&path));
        if let Err(e) = result {
            assert!(
                e.contains("case.h5"),
                "h5 case {case}: the error does not name the file: {e}"
            );
        }
    });
}
