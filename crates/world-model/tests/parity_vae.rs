//! The CogVideoX VAE against diffusers (frame batching, odd and even frame
//! counts, slicing, tiling, the full-size architecture, in f32 and in bf16),
//! loading and configuration errors, and parameter counts of the presets.

#![allow(clippy::unwrap_used)]

use crate::common;

use bridgev2w_world_model::parity::{
    run_fixture, run_fixture_bf16, BF16_EPSILON, BF16_FACTOR, DEFAULT_TOLERANCE,
};
use bridgev2w_world_model::vae::{AutoencoderKLCogVideoX, VaeConfig};
use bridgev2w_world_model::weights::learnable_parameter_count;
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::Path;
use tch::nn::VarStore;
use tch::Device;

fn check(name: &str, args: &[&str]) {
    let dir = common::fixture(name, args);
    let report = run_fixture(&dir).unwrap();
    assert_eq!(
        report.outputs.len(),
        3,
        "{name}: latent_sample, latent_mean, decoded"
    );
    for o in &report.outputs {
        assert!(
            o.max_rel <= DEFAULT_TOLERANCE,
            "{name}: {} rel {:e} abs {:e}",
            o.name,
            o.max_rel,
            o.max_abs
        );
    }
}

#[test]
fn nine_frames_one_encoder_batch() {
    check("vae-9", &["vae", "--frames", "9"]);
}

#[test]
fn seventeen_frames_two_batches_with_slicing() {
    // Encoder batches 9 + 8 frames, decoder 3 + 2 latent frames; batch 2 sliced.
    check(
        "vae-17-sliced",
        &[
            "vae",
            "--frames",
            "17",
            "--batch",
            "2",
            "--slicing",
            "--height",
            "24",
            "--width",
            "16",
        ],
    );
}

#[test]
fn even_frame_count_and_other_latent_length() {
    check("vae-8", &["vae", "--frames", "8"]);
    check(
        "vae-13-dec4",
        &["vae", "--frames", "13", "--latent-frames", "4"],
    );
}

#[test]
fn spatial_tiling_with_blending() {
    check(
        "vae-tiled",
        &[
            "vae",
            "--frames",
            "9",
            "--height",
            "96",
            "--width",
            "80",
            "--tiling",
            "--tile-sample-height",
            "64",
            "--tile-sample-width",
            "48",
            "--tile-overlap-height",
            "0.25",
            "--tile-overlap-width",
            "0.25",
        ],
    );
}

/// The full-size (CogVideoX 5B) VAE on a 9-frame 16x16 clip, with diffusers'
/// outputs in f32 and in bf16.
const FULL_SIZE: (&str, &[&str]) = (
    "vae-5b-i2v",
    &[
        "vae",
        "--preset",
        "cogvideox-5b-i2v",
        "--frames",
        "9",
        "--height",
        "16",
        "--width",
        "16",
        "--bf16",
    ],
);

#[test]
fn full_size_cogvideox_architecture_on_a_small_clip() {
    check(FULL_SIZE.0, FULL_SIZE.1);
}

#[test]
fn full_size_architecture_in_bf16_is_as_accurate_as_diffusers_in_bf16() {
    // Encode (the time pooling included) and decode with the weights in bf16
    // on the CPU: each error against diffusers' f32 output at most 1.5 times
    // diffusers' own bf16 error + 1e-3 (measured: the same errors).
    let dir = common::fixture(FULL_SIZE.0, FULL_SIZE.1);
    let report = run_fixture_bf16(&dir).unwrap();
    let names: Vec<&str> = report.outputs.iter().map(|o| o.name.as_str()).collect();
    assert_eq!(names, ["latent_mean", "decoded"]);
    for o in &report.outputs {
        // Both sides really ran in bf16 (8 significant bits: errors near 1e-2).
        assert!(
            o.ours.rms_rel > 1e-4 && o.diffusers.rms_rel > 1e-4,
            "{}: {o:?}",
            o.name
        );
        assert!(o.within(BF16_FACTOR, BF16_EPSILON), "{}: {o:?}", o.name);
    }
}

#[test]
fn loading_and_config_errors_name_the_problem() {
    let dir = common::fixture("vae-9", &["vae", "--frames", "9"]).join("model");
    let tmp = common::component_without(&dir, "decoder.conv_out.conv.bias");
    let e = AutoencoderKLCogVideoX::load(tmp.path(), ComputeDevice::Cpu, Precision::F32)
        .unwrap_err()
        .to_string();
    assert!(e.contains("decoder.conv_out.conv.bias"), "{e}");
    let mut cfg = VaeConfig::tiny();
    cfg.norm_num_groups = 5;
    let e = cfg
        .validate(Path::new("vae/config.json"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("vae/config.json") && e.contains("norm_num_groups"),
        "{e}"
    );
    let mut huge = VaeConfig::tiny();
    huge.block_out_channels = vec![huge.norm_num_groups << 30; huge.block_out_channels.len()];
    let e = huge
        .validate(Path::new("vae/config.json"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("block_out_channels") && e.contains("at most"),
        "{e}"
    );
}

fn diffusers_count(cfg: &VaeConfig) -> i64 {
    common::diffusers_param_count("vae", cfg)
}

#[test]
fn parameter_counts_match_diffusers() {
    for cfg in [
        VaeConfig::cogvideox_5b_i2v(),
        VaeConfig::cogvideox_2b(),
        VaeConfig::tiny(),
    ] {
        let vs = VarStore::new(Device::Cpu);
        let _vae = AutoencoderKLCogVideoX::new(&cfg, vs.root()).unwrap();
        assert_eq!(
            learnable_parameter_count(&vs),
            diffusers_count(&cfg),
            "{cfg:?}"
        );
    }
}
