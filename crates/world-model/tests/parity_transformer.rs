//! The CogVideoX transformer against diffusers, LoRA identities, loading and
//! configuration errors, and parameter counts of the full-size presets.

#![allow(clippy::unwrap_used)]

use crate::common;

use bridgev2w_world_model::lora::LoraConfig;
use bridgev2w_world_model::parity::{
    run_fixture, run_fixture_bf16, BF16_EPSILON, BF16_FACTOR, DEFAULT_TOLERANCE,
};
use bridgev2w_world_model::transformer::{
    CogVideoXTransformer3DModel, LoadedTransformer, TransformerConfig,
};
use bridgev2w_world_model::weights::learnable_parameter_count;
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::Path;
use tch::nn::VarStore;
use tch::{Device, Kind, Tensor};

fn check(name: &str, args: &[&str], outputs: usize) {
    let dir = common::fixture(name, args);
    let report = run_fixture(&dir).unwrap();
    assert_eq!(report.outputs.len(), outputs, "{name}: outputs compared");
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

/// A 2-block 5B-I2V-style transformer (RoPE, learned positions), with
/// diffusers' output in f32 and in bf16.
const I2V: (&str, &[&str]) = (
    "tf-5b-i2v",
    &[
        "transformer",
        "--style",
        "5b-i2v",
        "--shape",
        "2,3,8,8,12",
        "--bf16",
    ],
);

#[test]
fn i2v_rope_learned_positions_at_training_size() {
    check(I2V.0, I2V.1, 3);
}

#[test]
fn i2v_in_bf16_is_as_accurate_as_diffusers_in_bf16() {
    // Weights and inputs in bf16 on the CPU: the error against diffusers'
    // f32 output at most 1.5 times diffusers' own bf16 error + 1e-3.
    let dir = common::fixture(I2V.0, I2V.1);
    let report = run_fixture_bf16(&dir).unwrap();
    assert_eq!(report.outputs.len(), 1, "sample");
    let o = &report.outputs[0];
    assert!(
        o.ours.rms_rel > 1e-4 && o.diffusers.rms_rel > 1e-4,
        "both ran in bf16: {o:?}"
    );
    assert!(o.within(BF16_FACTOR, BF16_EPSILON), "{o:?}");
}

#[test]
fn i2v_other_frame_count_falls_back_to_sincos_and_loads_shards() {
    // 4 latent frames against sample_frames 9 (3 latent frames); sharded weights.
    check(
        "tf-5b-i2v-frames",
        &[
            "transformer",
            "--style",
            "5b-i2v",
            "--shape",
            "2,4,8,8,12",
            "--sample-frames",
            "9",
            "--shard",
        ],
        3,
    );
}

#[test]
fn sincos_2b_style_other_grid_and_odd_frames() {
    check(
        "tf-2b-grid",
        &[
            "transformer",
            "--style",
            "2b",
            "--shape",
            "1,3,16,8,12",
            "--sample-size",
            "6,10",
            "--sample-frames",
            "13",
        ],
        1,
    );
}

#[test]
fn cogvideox_1_5_temporal_patches_and_ofs() {
    check(
        "tf-1.5",
        &[
            "transformer",
            "--style",
            "5b-i2v",
            "--shape",
            "1,4,8,8,12",
            "--config-json",
            r#"{"ofs_embed_dim": 32, "patch_size_t": 2, "use_learned_positional_embeddings": false}"#,
        ],
        3,
    );
}

fn tiny_inputs(cfg: &TransformerConfig, b: i64, f: i64) -> (Tensor, Tensor, Tensor) {
    tch::manual_seed(7);
    let opts = (Kind::Float, Device::Cpu);
    (
        Tensor::randn(
            [b, f, cfg.in_channels, cfg.sample_height, cfg.sample_width],
            opts,
        ),
        Tensor::randn([b, cfg.max_text_seq_length, cfg.text_embed_dim], opts),
        Tensor::from_slice(&[3i64, 977][..b as usize]),
    )
}

#[test]
fn lora_with_zero_b_is_the_base_model_and_merging_is_exact() {
    let cfg = TransformerConfig::tiny();
    let vs = VarStore::new(Device::Cpu);
    let mut model = CogVideoXTransformer3DModel::new(&cfg, &vs.root()).unwrap();
    let (x, text, t) = tiny_inputs(&cfg, 2, 3);
    let rot = model.rotary_for(&x).unwrap();
    let base = model.forward(&x, &text, &t, rot.as_ref(), None).unwrap();
    let adapters = VarStore::new(Device::Cpu);
    model
        .attach_lora(
            &adapters.root(),
            LoraConfig {
                rank: 4,
                alpha: 8.0,
            },
        )
        .unwrap();
    // PEFT key names.
    let keys = adapters.variables();
    assert!(
        keys.contains_key("transformer_blocks.1.attn1.to_out.0.lora_B.weight"),
        "{:?}",
        keys.keys()
    );
    assert_eq!(keys.len(), 2 * 4 * cfg.num_layers as usize);
    let with_zero_b = model.forward(&x, &text, &t, rot.as_ref(), None).unwrap();
    assert_eq!(
        f64::try_from((&with_zero_b - &base).abs().max()).unwrap(),
        0.0
    );
    // Non-zero B changes the output; merging gives the same output.
    tch::no_grad(|| {
        for (k, v) in adapters.variables() {
            if k.ends_with("lora_B.weight") {
                let mut v = v;
                v.copy_(&(Tensor::randn_like(&v) * 0.05));
            }
        }
    });
    let adapted = model.forward(&x, &text, &t, rot.as_ref(), None).unwrap();
    assert!(f64::try_from((&adapted - &base).abs().max()).unwrap() > 1e-4);
    model.set_lora_merged(true);
    let merged = model.forward(&x, &text, &t, rot.as_ref(), None).unwrap();
    assert!(f64::try_from((&merged - &adapted).abs().max()).unwrap() < 1e-5);
    model.set_lora_merged(false);
    let unmerged = model.forward(&x, &text, &t, rot.as_ref(), None).unwrap();
    assert!(f64::try_from((&unmerged - &adapted).abs().max()).unwrap() < 1e-5);
}

#[test]
fn residual_hook_sees_every_block_and_zero_residuals_change_nothing() {
    let cfg = TransformerConfig::tiny();
    let vs = VarStore::new(Device::Cpu);
    let model = CogVideoXTransformer3DModel::new(&cfg, &vs.root()).unwrap();
    let (x, text, t) = tiny_inputs(&cfg, 1, 3);
    let rot = model.rotary_for(&x).unwrap();
    let base = model.forward(&x, &text, &t, rot.as_ref(), None).unwrap();
    let mut seen = vec![];
    let zero = model
        .forward_with_residuals(&x, &text, &t, rot.as_ref(), None, &mut |i, v| {
            seen.push(i);
            Some(v.zeros_like())
        })
        .unwrap();
    assert_eq!(seen, (0..cfg.num_layers as usize).collect::<Vec<_>>());
    assert_eq!(f64::try_from((&zero - &base).abs().max()).unwrap(), 0.0);
    let pushed = model
        .forward_with_residuals(&x, &text, &t, rot.as_ref(), None, &mut |i, v| {
            (i == 0).then(|| v.randn_like())
        })
        .unwrap();
    assert!(f64::try_from((&pushed - &base).abs().max()).unwrap() > 1e-3);
}

#[test]
fn last_block_video_output_alone_equals_the_full_block() {
    // The model runs its last block without the text tokens' queries and
    // feed-forward (nothing reads that block's text output): the video
    // output must be the full block's, with RoPE and with sin-cos positions.
    for rope in [true, false] {
        let mut cfg = TransformerConfig::tiny();
        cfg.use_rotary_positional_embeddings = rope;
        cfg.use_learned_positional_embeddings = false;
        let vs = VarStore::new(Device::Cpu);
        let model = CogVideoXTransformer3DModel::new(&cfg, &vs.root()).unwrap();
        let (x, text, t) = tiny_inputs(&cfg, 2, 3);
        let rot = model.rotary_for(&x).unwrap();
        // Inputs of the last block, from the model's own hook.
        let mut last_in = None;
        let _ = model
            .forward_with_residuals(&x, &text, &t, rot.as_ref(), None, &mut |i, v| {
                if i == 0 {
                    last_in = Some(v.shallow_clone());
                }
                None
            })
            .unwrap();
        let video = last_in.unwrap();
        let words = Tensor::randn(
            [2, cfg.max_text_seq_length, cfg.inner_dim()],
            (Kind::Float, Device::Cpu),
        );
        let temb = Tensor::randn([2, cfg.time_embed_dim], (Kind::Float, Device::Cpu));
        let block = model.blocks().last().unwrap();
        let (full, _) = block.forward(&video, &words, &temb, rot.as_ref());
        let alone = block.forward_video(&video, &words, &temb, rot.as_ref());
        let diff = f64::try_from((&full - &alone).abs().max()).unwrap();
        let scale = f64::try_from(full.abs().max()).unwrap();
        assert!(diff <= 1e-6 * scale, "rope {rope}: {diff} of {scale}");
        assert_eq!(full.size(), alone.size());
    }
}

#[test]
fn errors_name_the_problem() {
    let cfg = TransformerConfig::tiny();
    let vs = VarStore::new(Device::Cpu);
    let model = CogVideoXTransformer3DModel::new(&cfg, &vs.root()).unwrap();
    let (x, text, t) = tiny_inputs(&cfg, 1, 3);
    // Learned positions at another resolution: diffusers refuses too.
    let wide = Tensor::randn([1, 3, cfg.in_channels, 8, 16], (Kind::Float, Device::Cpu));
    let rot = model.rotary_for(&wide).unwrap();
    let e = model
        .forward(&wide, &text, &t, rot.as_ref(), None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("training size 8x12"), "{e}");
    // RoPE model without rotary tables.
    let e = model
        .forward(&x, &text, &t, None, None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("rotary"), "{e}");
    // Wrong channel count.
    let bad = x.narrow(2, 0, 4);
    let e = model
        .forward(
            &bad,
            &text,
            &t,
            model.rotary_for(&bad).unwrap().as_ref(),
            None,
        )
        .unwrap_err()
        .to_string();
    assert!(e.contains("4 channels"), "{e}");
    // Config validation names the field.
    let mut bad_cfg = TransformerConfig::tiny();
    bad_cfg.attention_head_dim = 12;
    let e = bad_cfg
        .validate(Path::new("cfg.json"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("attention_head_dim") && e.contains("cfg.json"),
        "{e}"
    );
    // An absurd size is refused before any allocation (it panicked in tch).
    bad_cfg.attention_head_dim = 1 << 40;
    let e = bad_cfg
        .validate(Path::new("cfg.json"))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("attention_head_dim") && e.contains("at most"),
        "{e}"
    );
    let mut wide = TransformerConfig::tiny();
    (wide.num_attention_heads, wide.attention_head_dim) = (1024, 1024);
    let e = wide
        .validate(Path::new("cfg.json"))
        .unwrap_err()
        .to_string();
    assert!(e.contains("1048576 dims"), "{e}");
    // Strict loading: a weight missing from the file is named.
    let dir = common::fixture(
        "tf-5b-i2v",
        &["transformer", "--style", "5b-i2v", "--shape", "2,3,8,8,12"],
    )
    .join("model");
    let tmp = common::component_without(&dir, "proj_out.bias");
    let e = LoadedTransformer::load(tmp.path(), ComputeDevice::Cpu, Precision::F32)
        .unwrap_err()
        .to_string();
    assert!(e.contains("proj_out.bias"), "{e}");
}

fn diffusers_count(cfg: &TransformerConfig) -> i64 {
    common::diffusers_param_count("transformer", cfg)
}

fn rust_count(cfg: &TransformerConfig) -> i64 {
    let vs = VarStore::new(Device::Cpu);
    let _model = CogVideoXTransformer3DModel::new(cfg, &vs.root()).unwrap();
    learnable_parameter_count(&vs)
}

/// The full-size presets: one- and two-block models at full width are built
/// (a few hundred million parameters each), the per-block count extrapolated
/// to all blocks; each is checked against diffusers.
fn check_full_size(full: TransformerConfig) {
    let with_layers = |n| TransformerConfig {
        num_layers: n,
        ..full.clone()
    };
    let (one, two) = (rust_count(&with_layers(1)), rust_count(&with_layers(2)));
    assert_eq!(one, diffusers_count(&with_layers(1)));
    assert_eq!(two, diffusers_count(&with_layers(2)));
    let extrapolated = one + (full.num_layers - 1) * (two - one);
    assert_eq!(extrapolated, diffusers_count(&full));
}

#[test]
fn parameter_count_of_cogvideox_5b_i2v_matches_diffusers() {
    check_full_size(TransformerConfig::cogvideox_5b_i2v());
}

#[test]
fn parameter_count_of_cogvideox_2b_matches_diffusers() {
    check_full_size(TransformerConfig::cogvideox_2b());
}
