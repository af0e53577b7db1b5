//! Fuzzing the training configuration (TOML): mutated configs must give a
//! validated `TrainConfig` or an error naming the field or the TOML
//! position, never a panic; an accepted config must survive its own
//! round trip (`to_toml` then `from_toml` gives it back) and stay within the
//! validator's bounds; the Rust heap stays within `ALLOC_FACTOR` times the
//! input.
//!
//! In the test suite it runs `FUZZ_CASES` cases (default 1500);
//! `scripts/fuzz.sh train-config SECONDS` runs it for a wall-clock budget.

#[path = "../../embodiment/tests/support/fuzz.rs"]
mod fuzz;

use bridgev2w_train::config::TrainConfig;
use fuzz::{mutate_text, run_target};
use peak_alloc::PeakAlloc;

/// Counts the bytes the Rust heap holds and their peak.
#[global_allocator]
static ALLOCATOR: PeakAlloc = PeakAlloc;

/// The configs of `scripts/reproduce-synthetic.sh` (fine-tuning, prior, VAE)
/// and the full default config as `to_toml` writes it.
fn seeds() -> Vec<Vec<u8>> {
    let finetune = r#"[model]
backbone = "runs/r/prior/final/backbone"
lora_rank = 64
lora_alpha = 64
controlnet_layers = 2
action_hidden = 128
image_conditioning = "every_frame"
[data]
dataset = "runs/r/synth"
frames = 9
width = 96
height = 64
clips_per_video = 2
[train]
out = "runs/r/bridgev2w"
batch_size = 4
max_steps = 2000
lr = 5e-4
warmup_steps = 100
e_switch = 5
checkpoint_every = 250
[ablation]
mask_action = true
"#;
    let vae = r#"[model]
backbone = "random:small2x"
lora_rank = 0
[data]
dataset = "runs/r/synth"
frames = 1
width = 96
height = 64
[train]
stage = "vae"
out = "runs/r/vae-image"
batch_size = 16
max_steps = 2500
lr = 1e-3
color_augment = true
"#;
    let full = TrainConfig::from_toml(finetune)
        .expect("the seed parses")
        .to_toml()
        .expect("toml");
    vec![
        finetune.as_bytes().to_vec(),
        vae.as_bytes().to_vec(),
        full.into_bytes(),
    ]
}

#[test]
fn mutated_training_configs_never_panic_nor_accept_garbage() {
    let check = |case: usize, data: &[u8]| {
        let text = String::from_utf8_lossy(data);
        let parsed = fuzz::guarded(&ALLOCATOR, "train-config", case, data, || {
            TrainConfig::from_toml(&text)
        });
        match parsed {
            Ok(c) => {
                let again = c
                    .to_toml()
                    .and_then(|t| TrainConfig::from_toml(&t))
                    .unwrap_or_else(|e| panic!("train-config case {case}: no round trip: {e}"));
                assert_eq!(again, c, "train-config case {case}: the round trip differs");
                assert!(
                    c.train.lr.is_finite() && c.train.lr > 0.0,
                    "train-config case {case}: lr {}",
                    c.train.lr
                );
            }
            Err(e) => assert!(
                e.to_string().contains("config") || e.to_string().contains("train."),
                "train-config case {case}: the error names neither the config nor a field: {e}"
            ),
        }
    };
    run_target("train-config", &seeds(), mutate_text, check);
    // Found by `scripts/fuzz.sh train-config 60`: `lora_alpha = nan` passed
    // validation (NaN != NaN, so the round trip "differed"), with LoRA on
    // (4049) and, after the first fix, with `lora_rank = 0` (117776).
    fuzz::replay(&seeds(), mutate_text, &[4049, 117776], check);
}
