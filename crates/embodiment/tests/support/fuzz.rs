//! Shared by the fuzz targets of several crates (included with `#[path]`):
//! the case loop with its environment knobs, the no-panic and
//! bounded-allocation contract, and a mutator for text formats.
//!
//! `FUZZ_CASES` cases per target (default 1500), or `FUZZ_SECONDS` of
//! wall-clock time (`scripts/fuzz.sh`); every case is derived from
//! `FUZZ_SEED` (default 0) and its index, so a failure names the case to
//! replay.

// Each test binary that includes this module uses a part of it.
#![allow(dead_code)]

use peak_alloc::PeakAlloc;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use std::sync::Mutex;

/// The allocator's peak is process-wide: one target at a time.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

/// The most a parser may allocate per input byte: an `.npy` of `u8` values
/// becomes `f64`s (8x), a JSON number of two bytes a `serde_json::Value`
/// (32 bytes) and then an `f64`.
pub const ALLOC_FACTOR: usize = 64;
/// Fixed allowance: error strings, small tables.
pub const ALLOC_SLACK: usize = 1 << 20;

fn env_usize(name: &str, default: usize) -> usize {
    std::env::var(name)
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}

/// Number strings that break parsers and the arithmetic behind them.
pub const WEIRD_NUMBERS: [&str; 18] = [
    "0",
    "-0",
    "1e308",
    "1e309",
    "-1e309",
    "1e-320",
    "nan",
    "NaN",
    "inf",
    "-inf",
    "18446744073709551615",
    "18446744073709551616",
    "4294967296",
    "99999999999999999999999",
    "-1",
    "",
    "1.5.5",
    "0x10",
];

/// Runs the cases of one target: each case mutates one of `seeds` with
/// `mutate` and hands the result to `check`; the seeds themselves are
/// checked first (as case `usize::MAX`).
pub fn run_target(
    name: &str,
    seeds: &[Vec<u8>],
    mutate: impl Fn(&[u8], &mut ChaCha8Rng) -> Vec<u8>,
    check: impl Fn(usize, &[u8]),
) {
    // One target at a time: the allocator's peak is process-wide, and a
    // failing target's backtrace would count against another's parse.
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    for s in seeds {
        check(usize::MAX, s);
    }
    let cases = env_usize("FUZZ_CASES", 1500);
    let seconds = env_usize("FUZZ_SECONDS", 0);
    let base_seed = env_usize("FUZZ_SEED", 0) as u64;
    let start = std::time::Instant::now();
    let mut n = 0;
    while (seconds == 0 && n < cases) || (seconds > 0 && start.elapsed().as_secs() < seconds as u64)
    {
        check(n, &case_input(seeds, &mutate, base_seed, n));
        n += 1;
    }
    eprintln!(
        "fuzz {name}: {n} cases in {:.1} s",
        start.elapsed().as_secs_f64()
    );
}

/// Case `n` of the series `base_seed`: a seed file picked and mutated by a
/// generator derived from both.
pub fn case_input(
    seeds: &[Vec<u8>],
    mutate: impl Fn(&[u8], &mut ChaCha8Rng) -> Vec<u8>,
    base_seed: u64,
    n: usize,
) -> Vec<u8> {
    let mut rng = ChaCha8Rng::seed_from_u64(base_seed.wrapping_mul(1_000_003) ^ n as u64);
    let seed = &seeds[rng.gen_range(0..seeds.len())];
    mutate(seed, &mut rng)
}

/// Reruns the given cases of series 0 (faults a longer run found, beyond
/// the suite's `FUZZ_CASES`), whatever the environment says.
pub fn replay(
    seeds: &[Vec<u8>],
    mutate: impl Fn(&[u8], &mut ChaCha8Rng) -> Vec<u8>,
    cases: &[usize],
    check: impl Fn(usize, &[u8]),
) {
    let _one = ONE_AT_A_TIME.lock().unwrap_or_else(|p| p.into_inner());
    for &n in cases {
        check(n, &case_input(seeds, &mutate, 0, n));
    }
}

/// Runs `parse` on the input `data` under the contract: no panic, and at
/// most `ALLOC_FACTOR * data.len() + ALLOC_SLACK` bytes at the peak of the
/// Rust heap (`allocator`, the test binary's global allocator).
pub fn guarded<T>(
    allocator: &PeakAlloc,
    target: &str,
    case: usize,
    data: &[u8],
    parse: impl FnOnce() -> T,
) -> T {
    guarded_within(allocator, target, case, data, data.len(), parse)
}

/// As [`guarded`] for a parse that reads `input_bytes` in all (a dataset of
/// several files, `data` the one mutated).
pub fn guarded_within<T>(
    allocator: &PeakAlloc,
    target: &str,
    case: usize,
    data: &[u8],
    input_bytes: usize,
    parse: impl FnOnce() -> T,
) -> T {
    let limit = AllocLimit {
        per_byte: ALLOC_FACTOR,
        fixed: ALLOC_SLACK,
    };
    guarded_by(allocator, target, case, data, input_bytes, limit, parse)
}

/// The most a parse may hold at its peak: `per_byte * input + fixed`.
#[derive(Debug, Clone, Copy)]
pub struct AllocLimit {
    /// Bytes per input byte.
    pub per_byte: usize,
    /// Bytes whatever the input's size.
    pub fixed: usize,
}

/// As [`guarded_within`] with the format's own `limit` (a compressed format
/// decodes to more than [`ALLOC_FACTOR`] per byte).
pub fn guarded_by<T>(
    allocator: &PeakAlloc,
    target: &str,
    case: usize,
    data: &[u8],
    input_bytes: usize,
    limit: AllocLimit,
    parse: impl FnOnce() -> T,
) -> T {
    let base = allocator.current_usage();
    allocator.reset_peak_usage();
    let result = std::panic::catch_unwind(std::panic::AssertUnwindSafe(parse));
    let peak = allocator.peak_usage().saturating_sub(base);
    let shown = String::from_utf8_lossy(&data[..data.len().min(400)]).into_owned();
    let Ok(value) = result else {
        panic!(
            "{target} case {case}: the parser panicked on {} bytes: {shown:?}",
            data.len()
        );
    };
    assert!(
        peak <= limit.per_byte * input_bytes + limit.fixed,
        "{target} case {case}: {peak} bytes allocated for {input_bytes} bytes of input \
         (at most {limit:?}): {shown:?}"
    );
    value
}

/// The spans of `text` that are numbers (digits, signs, dots, exponents).
fn number_spans(text: &[u8]) -> Vec<(usize, usize)> {
    let is_num = |c: u8| c.is_ascii_digit() || matches!(c, b'-' | b'+' | b'.' | b'e' | b'E');
    let mut spans = Vec::new();
    let mut i = 0;
    while i < text.len() {
        if text[i].is_ascii_digit() || (text[i] == b'-' && i + 1 < text.len()) {
            let start = i;
            while i < text.len() && is_num(text[i]) {
                i += 1;
            }
            spans.push((start, i.max(start + 1)));
        } else {
            i += 1;
        }
    }
    spans
}

/// One mutation of a text file: numbers replaced by extreme or malformed
/// ones, truncation, spans duplicated (up to 50 times) or deleted,
/// structural characters inserted, bytes flipped.
pub fn mutate_text(seed: &[u8], rng: &mut ChaCha8Rng) -> Vec<u8> {
    let mut d = seed.to_vec();
    for _ in 0..rng.gen_range(1..=3) {
        let spans = number_spans(&d);
        match rng.gen_range(0..7) {
            0 | 1 if !spans.is_empty() => {
                let (a, b) = spans[rng.gen_range(0..spans.len())];
                let w = WEIRD_NUMBERS[rng.gen_range(0..WEIRD_NUMBERS.len())];
                d.splice(a..b.min(d.len()), w.bytes());
            }
            2 => {
                let n = rng.gen_range(0..d.len().max(1));
                d.truncate(n);
            }
            3 if d.len() > 2 => {
                let a = rng.gen_range(0..d.len() - 1);
                let b = rng.gen_range(a + 1..=d.len().min(a + 200));
                let span: Vec<u8> = d[a..b].to_vec();
                let times = if rng.gen_bool(0.1) { 50 } else { 1 };
                for _ in 0..times {
                    d.splice(b..b, span.iter().copied());
                }
            }
            4 if d.len() > 2 => {
                let a = rng.gen_range(0..d.len() - 1);
                let b = rng.gen_range(a + 1..=d.len().min(a + 40));
                d.drain(a..b);
            }
            5 => {
                const CH: &[u8] = b"[]{},:\"\n\r\t ;\\\0=#'";
                let at = rng.gen_range(0..=d.len());
                d.insert(at, CH[rng.gen_range(0..CH.len())]);
            }
            _ => {
                for _ in 0..rng.gen_range(1..=4) {
                    if !d.is_empty() {
                        let i = rng.gen_range(0..d.len());
                        d[i] ^= 1 << rng.gen_range(0..8);
                    }
                }
            }
        }
    }
    d
}
