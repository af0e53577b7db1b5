//! Fuzzing the checkpoint readers: safetensors files (the header checked in
//! words before libtorch reads a byte) and diffusers `config.json` of the
//! transformer and the VAE. Mutated files must give `Ok` or an error naming
//! the file, never a panic or an abort; a safetensors file that passes
//! `check_safetensors` must then be read by libtorch; an accepted config
//! must pass its own validation; and the Rust heap stays within
//! `ALLOC_FACTOR` times the input (libtorch's own allocations are not
//! counted).
//!
//! In the test suite each target runs `FUZZ_CASES` cases (default 1500);
//! `scripts/fuzz.sh safetensors|model-config SECONDS` runs one for a
//! wall-clock budget.

#[path = "../../embodiment/tests/support/fuzz.rs"]
mod fuzz;

use bridgev2w_world_model::transformer::TransformerConfig;
use bridgev2w_world_model::vae::VaeConfig;
use bridgev2w_world_model::weights::{check_safetensors, read_safetensors, save_safetensors};
use fuzz::{mutate_text, run_target};
use peak_alloc::PeakAlloc;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use std::path::Path;
use tch::{Kind, Tensor};

/// Counts the bytes the Rust heap holds and their peak.
#[global_allocator]
static ALLOCATOR: PeakAlloc = PeakAlloc;

/// Writes `data` to `dir/name` and returns the path.
fn write(dir: &Path, name: &str, data: &[u8]) -> std::path::PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, data).expect("write case");
    p
}

fn safetensors_seeds(dir: &Path) -> Vec<Vec<u8>> {
    let p = dir.join("seed.safetensors");
    let named = vec![
        (
            "controlnet.a.weight".to_owned(),
            Tensor::arange(12, (Kind::Float, tch::Device::Cpu)).view([3, 4]),
        ),
        (
            "b.bias".to_owned(),
            Tensor::arange(5, (Kind::Int64, tch::Device::Cpu)),
        ),
        (
            "c".to_owned(),
            Tensor::ones([2, 2, 2], (Kind::BFloat16, tch::Device::Cpu)),
        ),
    ];
    save_safetensors(&named, &p).expect("seed");
    vec![std::fs::read(&p).expect("seed")]
}

/// Header-aware mutation: the JSON header's text (dtypes, shapes, offsets)
/// with its length kept consistent or not, the length field itself, or the
/// raw bytes.
fn mutate_safetensors(seed: &[u8], rng: &mut ChaCha8Rng) -> Vec<u8> {
    let n = u64::from_le_bytes(seed[..8].try_into().expect("8 bytes")) as usize;
    let (header, data) = (&seed[8..8 + n], &seed[8 + n..]);
    match rng.gen_range(0..5) {
        0..=2 => {
            let mut h = mutate_text(header, rng);
            if rng.gen_bool(0.3) {
                const DTYPES: [&str; 6] = ["\"F64\"", "\"U8\"", "\"X9\"", "\"BF16\"", "7", "\"\""];
                // By bytes: a lossy UTF-8 view of a mutated header has other offsets.
                if let Some(at) = h.windows(5).position(|w| w == b"\"F32\"") {
                    let w = DTYPES[rng.gen_range(0..DTYPES.len())];
                    h.splice(at..at + 5, w.bytes());
                }
            }
            let mut out = (h.len() as u64).to_le_bytes().to_vec();
            out.extend_from_slice(&h);
            out.extend_from_slice(data);
            out
        }
        3 => {
            let mut out = seed.to_vec();
            let v: u64 = [0, 1, 7, n as u64 + 1, 1 << 40, u64::MAX][rng.gen_range(0..6)];
            out[..8].copy_from_slice(&v.to_le_bytes());
            out
        }
        _ => mutate_text(seed, rng),
    }
}

#[test]
fn mutated_safetensors_never_panic_nor_reach_libtorch_broken() {
    let dir = tempfile::tempdir().expect("tempdir");
    let seeds = safetensors_seeds(dir.path());
    run_target("safetensors", &seeds, mutate_safetensors, |case, data| {
        let p = write(dir.path(), "case.safetensors", data);
        let checked = fuzz::guarded(&ALLOCATOR, "safetensors", case, data, || {
            check_safetensors(&p)
        });
        match checked {
            // Passed the checks in words: libtorch must read it.
            Ok(()) => {
                let read = std::panic::catch_unwind(|| read_safetensors(&p));
                match read {
                    Ok(Ok(_)) => {}
                    Ok(Err(e)) => panic!("safetensors case {case}: checked, then refused: {e}"),
                    Err(_) => panic!("safetensors case {case}: checked, then libtorch panicked"),
                }
            }
            Err(e) => assert!(
                e.to_string().contains("case.safetensors"),
                "safetensors case {case}: the error does not name the file: {e}"
            ),
        }
    });
}

fn config_seeds() -> Vec<Vec<u8>> {
    let tf = serde_json::to_vec_pretty(&TransformerConfig::small_2x()).expect("json");
    let vae = serde_json::to_vec_pretty(&VaeConfig::small_2x()).expect("json");
    vec![tf, vae]
}

#[test]
fn mutated_model_configs_never_panic_nor_accept_garbage() {
    let dir = tempfile::tempdir().expect("tempdir");
    run_target(
        "model-config",
        &config_seeds(),
        mutate_text,
        |case, data| {
            let p = write(dir.path(), "config.json", data);
            let (tf, vae) = fuzz::guarded(&ALLOCATOR, "model-config", case, data, || {
                (TransformerConfig::from_file(&p), VaeConfig::from_file(&p))
            });
            if let Ok(c) = &tf {
                assert!(c.validate(&p).is_ok(), "model-config case {case}");
            }
            if let Ok(c) = &vae {
                assert!(c.validate(&p).is_ok(), "model-config case {case}");
            }
            for e in [tf.err(), vae.err()].into_iter().flatten() {
                assert!(
                    e.to_string().contains("config.json"),
                    "model-config case {case}: the error does not name the file: {e}"
                );
            }
        },
    );
}
