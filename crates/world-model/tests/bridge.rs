//! The BridgeV2W model: the ControlNet identity with zero projections, the branch
//! initialised from the backbone, weights files, pipeline folders, gradients and
//! the `WorldModel` contract.

#![allow(clippy::unwrap_used)]

mod common;

use bridgev2w_io::frame::RgbFrame;
use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig, ImageConditioning, MaskCoding};
use bridgev2w_world_model::controlnet::ControlNetConfig;
use bridgev2w_world_model::pipeline::{
    BatchNoise, DecodeFrames, PredictOptions, SampleOptions, WorldModel,
};
use bridgev2w_world_model::scheduler::SchedulerConfig;
use bridgev2w_world_model::transformer::TransformerConfig;
use bridgev2w_world_model::vae::VaeConfig;
use bridgev2w_world_model::video::MaskVideo;
use bridgev2w_world_model::{ComputeDevice, Precision};
use tch::{Device, Kind, Tensor};

fn tiny(cfg: BridgeV2WConfig, seed: i64) -> BridgeV2W {
    BridgeV2W::random(
        cfg,
        &VaeConfig::tiny(),
        &TransformerConfig::tiny(),
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        seed,
    )
    .unwrap()
}

/// Random `(latent_in [1, 3, 8, 8, 12], control [1, 3, 8, 8, 12], timestep [1])`.
fn inputs(seed: i64) -> (Tensor, Tensor, Tensor) {
    tch::manual_seed(seed);
    let opts = (Kind::Float, Device::Cpu);
    (
        Tensor::randn([1, 3, 8, 8, 12], opts),
        Tensor::randn([1, 3, 8, 8, 12], opts),
        Tensor::from_slice(&[500i64]),
    )
}

fn max_abs(a: &Tensor, b: &Tensor) -> f64 {
    (a - b).abs().max().double_value(&[])
}

/// Fills every `out_projectors` variable with small random values.
fn perturb_projections(m: &BridgeV2W) {
    tch::no_grad(|| {
        for (name, mut v) in m.adapters.variables() {
            if name.contains("out_projectors") {
                v.copy_(&(Tensor::randn_like(&v) * 0.05));
            }
        }
    });
}

#[test]
fn zero_projections_and_fresh_lora_leave_the_backbone_exactly() {
    let m = tiny(BridgeV2WConfig::tiny(), 1);
    let (x, c, t) = inputs(2);
    let with_branch = m.velocity_with(&x, &t, Some(&c)).unwrap();
    let without = m.velocity_with(&x, &t, None).unwrap();
    assert_eq!(with_branch.size(), [1, 3, 4, 8, 12]);
    assert_eq!(max_abs(&with_branch, &without), 0.0);
    // And equal to a plain backbone without adapters (same seed, same init order).
    let text = Tensor::zeros([1, 8, 24], (Kind::Float, Device::Cpu));
    let plain = bridgev2w_world_model::transformer::LoadedTransformer::random(
        &TransformerConfig::tiny(),
        ComputeDevice::Cpu,
        Precision::F32,
    )
    .unwrap();
    tch::no_grad(|| {
        let src = m.transformer.vs.variables();
        for (name, mut v) in plain.vs.variables() {
            v.copy_(&src[&name]);
        }
    });
    let rotary = plain.model.rotary_for(&x).unwrap();
    let base = plain
        .model
        .forward(&x, &text, &t, rotary.as_ref(), None)
        .unwrap();
    assert_eq!(max_abs(&with_branch, &base), 0.0);
}

#[test]
fn branch_starts_as_a_copy_of_the_backbone_and_changes_the_output_when_trained() {
    let m = tiny(BridgeV2WConfig::tiny(), 3);
    let base = m.transformer.vs.variables();
    let branch = m.adapters.variables();
    let mut copied = 0;
    for (name, v) in &branch {
        let Some(rest) = name.strip_prefix("controlnet.") else {
            continue;
        };
        if rest.starts_with("out_projectors") {
            assert_eq!(v.abs().sum(Kind::Double).double_value(&[]), 0.0, "{name}");
            continue;
        }
        assert_eq!(max_abs(v, &base[rest]), 0.0, "{name}");
        copied += 1;
    }
    // patch_embed (proj w+b, text_proj w+b, pos_embedding) + one block's tensors.
    assert!(copied > 10, "{copied}");
    assert!(!branch
        .keys()
        .any(|k| k.starts_with("controlnet.transformer_blocks.1.")));
    perturb_projections(&m);
    let (x, c, t) = inputs(4);
    let a = m.velocity_with(&x, &t, Some(&c)).unwrap();
    let b = m.velocity_with(&x, &t, None).unwrap();
    assert!(max_abs(&a, &b) > 1e-4);
    // Another control input gives another prediction.
    let c2 = Tensor::randn_like(&c);
    let a2 = m.velocity_with(&x, &t, Some(&c2)).unwrap();
    assert!(max_abs(&a, &a2) > 1e-5);
}

#[test]
fn per_block_weights_scale_the_residuals() {
    let mut cfg = BridgeV2WConfig::tiny();
    cfg.controlnet = ControlNetConfig {
        num_layers: 2,
        conditioning_scale: vec![0.0, 0.0],
        zero_init: true,
    };
    let m = tiny(cfg.clone(), 5);
    perturb_projections(&m);
    let (x, c, t) = inputs(6);
    let off = m.velocity_with(&x, &t, Some(&c)).unwrap();
    let base = m.velocity_with(&x, &t, None).unwrap();
    assert_eq!(max_abs(&off, &base), 0.0, "weights 0 switch the branch off");
    cfg.controlnet.conditioning_scale = vec![1.0, 0.0];
    let bad = BridgeV2W::random(
        BridgeV2WConfig {
            controlnet: ControlNetConfig {
                conditioning_scale: vec![1.0],
                ..cfg.controlnet.clone()
            },
            ..cfg.clone()
        },
        &VaeConfig::tiny(),
        &TransformerConfig::tiny(),
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        0,
    )
    .unwrap_err()
    .to_string();
    assert!(
        bad.contains("conditioning_scale") && bad.contains("1 weights for 2 blocks"),
        "{bad}"
    );
    let too_many = BridgeV2W::random(
        BridgeV2WConfig {
            controlnet: ControlNetConfig::with_layers(3),
            ..cfg
        },
        &VaeConfig::tiny(),
        &TransformerConfig::tiny(),
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        0,
    )
    .unwrap_err()
    .to_string();
    assert!(too_many.contains("expected 1..=2"), "{too_many}");
    // 5 frames = 2 latent frames: the causal VAE would decode 8.
    for (frames, ok) in [(5, false), (13, false), (9, true), (17, true), (6, false)] {
        let r = BridgeV2WConfig {
            frames,
            ..cfg.clone()
        }
        .validate(&VaeConfig::tiny(), &TransformerConfig::tiny());
        assert_eq!(r.is_ok(), ok, "{frames} frames: {r:?}");
        if frames == 5 {
            let e = r.unwrap_err().to_string();
            assert!(
                e.contains("decodes to 8 frames") && e.contains("8k + 1"),
                "{e}"
            );
        }
    }
}

#[test]
fn non_zero_initialised_branch_is_the_ablation() {
    let mut cfg = BridgeV2WConfig::tiny();
    cfg.controlnet.zero_init = false;
    let m = tiny(cfg, 7);
    let (x, c, t) = inputs(8);
    let a = m.velocity_with(&x, &t, Some(&c)).unwrap();
    let b = m.velocity_with(&x, &t, None).unwrap();
    assert!(max_abs(&a, &b) > 1e-4);
}

#[test]
fn gradients_reach_the_branch_and_lora_only() {
    let m = tiny(BridgeV2WConfig::tiny(), 9);
    let (x, c, t) = inputs(10);
    let v = m.velocity_with(&x, &t, Some(&c)).unwrap();
    v.square().mean(Kind::Float).backward();
    let vars = m.adapters.variables();
    let grad_norm = |k: &str| vars[k].grad().abs().sum(Kind::Double).double_value(&[]);
    // Zero projections get gradients (their inputs are non-zero) ...
    assert!(grad_norm("controlnet.out_projectors.0.weight") > 0.0);
    // ... and LoRA B does (A is random), while the frozen backbone has none.
    assert!(grad_norm("transformer.transformer_blocks.0.attn1.to_q.lora_B.weight") > 0.0);
    for (name, v) in m.transformer.vs.variables() {
        assert!(!v.requires_grad(), "{name} should be frozen");
    }
}

#[test]
fn weights_file_round_trip_with_config_and_strict_loading() {
    let mut cfg = BridgeV2WConfig::tiny();
    cfg.controlnet.conditioning_scale = vec![0.5];
    let m = tiny(cfg.clone(), 11);
    perturb_projections(&m);
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("bridgev2w.safetensors");
    m.save_weights(&path).unwrap();
    assert_eq!(BridgeV2W::weights_config(&path).unwrap(), Some(cfg.clone()));
    let other = tiny(cfg.clone(), 12);
    other.load_weights(&path).unwrap();
    for (name, v) in m.adapters.variables() {
        assert_eq!(
            max_abs(&v, &other.adapters.variables()[&name]),
            0.0,
            "{name}"
        );
    }
    // A file from a model with another branch depth is rejected, naming a key.
    let mut deeper = cfg;
    deeper.controlnet = ControlNetConfig::with_layers(2);
    let err = tiny(deeper, 13)
        .load_weights(&path)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("missing weight `controlnet.") && err.contains(".1."),
        "{err}"
    );
    // Not a safetensors file.
    std::fs::write(dir.path().join("bad.safetensors"), b"\x05\0\0\0\0\0\0\0{").unwrap();
    let err = BridgeV2W::weights_config(&dir.path().join("bad.safetensors"))
        .unwrap_err()
        .to_string();
    assert!(err.contains("bad.safetensors"), "{err}");
    // A truncated file: the tensor and the byte range in words, no library code.
    let bytes = std::fs::read(&path).unwrap();
    let cut = dir.path().join("cut.safetensors");
    std::fs::write(&cut, &bytes[..bytes.len() - 16]).unwrap();
    let err = other.load_weights(&cut).unwrap_err().to_string();
    assert!(
        err.contains("cut.safetensors")
            && err.contains("lie outside")
            && !err.contains("InvalidOffset"),
        "{err}"
    );
    // NaN weights are refused when loaded, naming the file and the tensor.
    let (name, v) = m.adapters.variables().into_iter().next().unwrap();
    let _ = tch::no_grad(|| v.shallow_clone().fill_(f64::NAN));
    let nan = dir.path().join("nan.safetensors");
    m.save_weights(&nan).unwrap();
    let err = other.load_weights(&nan).unwrap_err().to_string();
    assert!(
        err.contains("nan.safetensors")
            && err.contains(&format!("`{name}`"))
            && err.contains("NaN"),
        "{err}"
    );
}

fn image(seed: u64) -> RgbFrame {
    let (h, w) = (64, 96);
    let data = (0..h * w * 3)
        .map(|i| (((i as u64 * 2654435761 + seed) % 1000) as f32) / 1000.0)
        .collect();
    RgbFrame {
        height: h,
        width: w,
        rgb: data,
    }
}

fn masks(offset: usize) -> MaskVideo {
    let (t, h, w) = (9, 64, 96);
    let mut data = vec![0u8; t * h * w];
    for f in 0..t {
        for y in 20..40 {
            for x in (10 + 4 * f + offset)..(30 + 4 * f + offset) {
                data[(f * h + y) * w + x] = 1;
            }
        }
    }
    MaskVideo {
        frames: t,
        height: h,
        width: w,
        data,
    }
}

fn opts(seed: u64, guidance_scale: f64) -> PredictOptions {
    PredictOptions {
        sample: SampleOptions {
            steps: 3,
            guidance_scale,
            dynamic_cfg: false,
            seed,
            first_frame: Default::default(),
            batch_noise: BatchNoise::Independent,
            ..SampleOptions::default()
        },
        max_batch: None,
        ..PredictOptions::default()
    }
}

#[test]
fn predict_follows_the_world_model_contract() {
    let m = tiny(BridgeV2WConfig::tiny(), 14);
    perturb_projections(&m);
    assert_eq!(m.clip_frames(), 9);
    assert_eq!(m.resolution(), (64, 96));
    let v1 = m.predict(&image(1), &masks(0), &opts(3, 2.0)).unwrap();
    assert_eq!((v1.frames, v1.height, v1.width), (9, 64, 96));
    assert!(v1.data.iter().all(|v| (0.0..=1.0).contains(v)));
    let again = m.predict(&image(1), &masks(0), &opts(3, 2.0)).unwrap();
    assert!(v1 == again, "same seed, same video");
    let moved = m.predict(&image(1), &masks(20), &opts(3, 2.0)).unwrap();
    assert!(v1 != moved, "other masks, other video");
    let spread = v1.data.iter().fold(0f32, |a, v| a.max((v - 0.5).abs()));
    assert!(spread > 1e-3, "a random VAE decodes to non-constant frames");
    let batch = m
        .predict_batch(&[image(1), image(1)], &[masks(0), masks(20)], &opts(3, 2.0))
        .unwrap();
    let close = |a: &[f32], b: &[f32]| {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0f32, f32::max)
    };
    assert!(close(&batch[0].data, &v1.data) < 1e-4);
    // Later batch items draw later noise (as diffusers with one generator).
    assert!(close(&batch[1].data, &batch[0].data) > 1e-4);
    // Shared noise (common random numbers): every item gets the noise of a
    // batch of one, so it equals its own single prediction, and the same
    // inputs give the same video.
    let shared = |seed| PredictOptions {
        sample: SampleOptions {
            batch_noise: BatchNoise::Shared,
            ..opts(seed, 2.0).sample
        },
        max_batch: None,
        ..PredictOptions::default()
    };
    let moved_alone = m.predict(&image(1), &masks(20), &shared(3)).unwrap();
    assert!(
        close(&moved_alone.data, &moved.data) == 0.0,
        "a batch of one"
    );
    let batch = m
        .predict_batch(
            &[image(1), image(1), image(1)],
            &[masks(0), masks(20), masks(0)],
            &shared(3),
        )
        .unwrap();
    assert!(close(&batch[0].data, &v1.data) < 1e-4);
    assert!(close(&batch[1].data, &moved.data) < 1e-4);
    assert!(close(&batch[2].data, &batch[0].data) < 1e-5);
    // In chunks of at most two clips (a planner's memory bound): with shared
    // noise, the same videos as one call.
    let chunked = m
        .predict_batch(
            &[image(1), image(1), image(1)],
            &[masks(0), masks(20), masks(0)],
            &PredictOptions {
                max_batch: Some(2),
                ..shared(3)
            },
        )
        .unwrap();
    assert_eq!(chunked.len(), 3);
    for (c, b) in chunked.iter().zip(&batch) {
        assert!(close(&c.data, &b.data) < 1e-5, "chunked vs one call");
    }
    let e = m
        .predict_batch(
            &[image(1)],
            &[masks(0)],
            &PredictOptions {
                max_batch: Some(0),
                ..shared(3)
            },
        )
        .unwrap_err()
        .to_string();
    assert!(e.contains("max_batch") && e.contains("at least 1"), "{e}");
    // Only the last latent-frame batch decoded (a planner's last frame; the
    // VAE's own test covers a clip of several batches): this model's 3
    // latent frames are one decode batch, so the whole clip, the same
    // videos. Not with keep_static, which needs every frame.
    let last = |o: PredictOptions| PredictOptions {
        decode_frames: DecodeFrames::Last,
        ..o
    };
    let tails = m
        .predict_batch(
            &[image(1), image(1)],
            &[masks(0), masks(20)],
            &last(shared(3)),
        )
        .unwrap();
    for (tail, full) in tails.iter().zip(&batch) {
        assert_eq!(tail.frames, full.frames);
        assert!(close(&tail.data, &full.data) < 1e-5);
    }
    let e = m
        .predict_batch(
            &[image(1)],
            &[masks(0)],
            &last(PredictOptions {
                sample: SampleOptions {
                    keep_static_margin_px: Some(2),
                    ..shared(3).sample
                },
                ..shared(3)
            }),
        )
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("decode_frames") && e.contains("keep_static"),
        "{e}"
    );
    assert!("last".parse::<DecodeFrames>().unwrap() == DecodeFrames::Last);
    assert!("shared".parse::<BatchNoise>().unwrap() == BatchNoise::Shared);
    let e = "common".parse::<BatchNoise>().unwrap_err().to_string();
    assert!(e.contains("batch_noise") && e.contains("shared"), "{e}");
    let latent = m.encode_image(&image(1)).unwrap();
    assert_eq!(latent.len(), 4 * 8 * 12);
    // Bad input.
    let small = RgbFrame {
        height: 32,
        width: 48,
        rgb: vec![0.5; 32 * 48 * 3],
    };
    let e = m
        .predict(&small, &masks(0), &opts(3, 1.0))
        .unwrap_err()
        .to_string();
    assert!(e.contains("32x48") && e.contains("64x96"), "{e}");
    let mut short = masks(0);
    short.frames = 5;
    short.data.truncate(5 * 64 * 96);
    let e = m
        .predict(&image(1), &short, &opts(3, 1.0))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("[5, 64, 96]") && e.contains("[9, 64, 96]"),
        "{e}"
    );
    let e = m
        .predict(&image(1), &masks(0), &opts(3, 0.5))
        .unwrap_err()
        .to_string();
    assert!(e.contains("guidance_scale"), "{e}");
}

#[test]
fn backbone_folder_round_trips_and_loads_in_diffusers() {
    let m = tiny(BridgeV2WConfig::tiny(), 15);
    perturb_projections(&m);
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("prior");
    m.save_backbone(&folder).unwrap();
    let weights = dir.path().join("bridgev2w.safetensors");
    m.save_weights(&weights).unwrap();
    let loaded = BridgeV2W::load(
        &folder,
        Some(&weights),
        None,
        BridgeV2WConfig::paper(), // overridden by the file's config
        ComputeDevice::Cpu,
        Precision::F32,
    )
    .unwrap();
    assert_eq!(loaded.config(), m.config());
    let (x, c, t) = inputs(16);
    let a = m.velocity_with(&x, &t, Some(&c)).unwrap();
    let b = loaded.velocity_with(&x, &t, Some(&c)).unwrap();
    assert_eq!(max_abs(&a, &b), 0.0);
    // diffusers reads the folder's configs and weights (strictly).
    let script = r#"
import sys, torch
from diffusers import AutoencoderKLCogVideoX, CogVideoXTransformer3DModel, CogVideoXDDIMScheduler
root = sys.argv[1]
vae = AutoencoderKLCogVideoX.from_pretrained(root, subfolder="vae", low_cpu_mem_usage=False)
tf = CogVideoXTransformer3DModel.from_pretrained(root, subfolder="transformer", low_cpu_mem_usage=False)
sc = CogVideoXDDIMScheduler.from_pretrained(root, subfolder="scheduler")
assert tf.config.num_layers == 2 and vae.config.latent_channels == 4, (tf.config, vae.config)
assert sc.config.prediction_type == "v_prediction"
print("ok")
"#;
    let out = std::process::Command::new(common::venv_python())
        .arg("-c")
        .arg(script)
        .arg(&folder)
        .output()
        .unwrap();
    assert!(
        out.status.success() && String::from_utf8_lossy(&out.stdout).contains("ok"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn bf16_model_predicts_close_to_f32() {
    let m = tiny(BridgeV2WConfig::tiny(), 17);
    perturb_projections(&m);
    let dir = tempfile::tempdir().unwrap();
    m.save_backbone(&dir.path().join("prior")).unwrap();
    let w = dir.path().join("w.safetensors");
    m.save_weights(&w).unwrap();
    let load = |p| {
        BridgeV2W::load(
            &dir.path().join("prior"),
            Some(&w),
            None,
            BridgeV2WConfig::tiny(),
            ComputeDevice::Cpu,
            p,
        )
        .unwrap()
    };
    let (f32m, bf16m) = (load(Precision::F32), load(Precision::Bf16));
    let (x, c, t) = inputs(18);
    let a = f32m.velocity_with(&x, &t, Some(&c)).unwrap();
    let b = bf16m.velocity_with(&x, &t, Some(&c)).unwrap();
    assert_eq!(b.kind(), Kind::BFloat16);
    let rel = max_abs(&a, &b.to_kind(Kind::Float)) / a.abs().max().double_value(&[]);
    assert!(rel < 0.05, "bf16 vs f32 relative error {rel}");
    let v = bf16m.predict(&image(2), &masks(0), &opts(1, 2.0)).unwrap();
    assert!(v.data.iter().all(|x| x.is_finite()));
}

#[test]
fn random_spec_honours_bf16_with_the_same_weights() {
    use bridgev2w_world_model::spec::{ModelSpec, RandomPreset};
    let spec = ModelSpec::Random(RandomPreset::Tiny);
    let load = |p| {
        spec.load_bridge(None, None, ComputeDevice::Cpu, p, 0)
            .unwrap()
    };
    let (f32m, bf16m) = (load(Precision::F32), load(Precision::Bf16));
    // F32 is `BridgeV2W::random`, bit for bit.
    let direct = BridgeV2W::random(
        RandomPreset::Tiny.bridge_config(),
        &VaeConfig::tiny(),
        &TransformerConfig::tiny(),
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        0,
    )
    .unwrap();
    assert_eq!(f32m.kind(), Kind::Float);
    let v32 = f32m.predict(&image(3), &masks(0), &opts(1, 2.0)).unwrap();
    let vd = direct.predict(&image(3), &masks(0), &opts(1, 2.0)).unwrap();
    assert!(v32 == vd, "f32 random:tiny unchanged");
    // bf16: the same weights, rounded; the VAE (force_upcast) stays f32.
    assert_eq!(bf16m.kind(), Kind::BFloat16);
    let (w32, w16) = (
        f32m.transformer.vs.variables(),
        bf16m.transformer.vs.variables(),
    );
    assert_eq!(w32.len(), w16.len());
    for (name, v) in &w16 {
        assert_eq!(v.kind(), Kind::BFloat16, "{name}");
        assert!(v.equal(&w32[name].to_kind(Kind::BFloat16)), "{name}");
    }
    assert!(bf16m
        .adapters
        .variables()
        .values()
        .all(|v| v.kind() == Kind::BFloat16));
    let vae32 = f32m.vae_vs.variables();
    for (name, v) in bf16m.vae_vs.variables() {
        assert!(v.kind() == Kind::Float && v.equal(&vae32[&name]), "{name}");
    }
    let v16 = bf16m.predict(&image(3), &masks(0), &opts(1, 2.0)).unwrap();
    assert_eq!(v16.data.len(), v32.data.len());
    assert!(v16.data.iter().all(|x| x.is_finite()));
    let mean = v16
        .data
        .iter()
        .zip(&v32.data)
        .map(|(a, b)| f64::from((a - b).abs()))
        .sum::<f64>()
        / v32.data.len() as f64;
    assert!(v16 != v32 && mean < 0.05, "bf16 vs f32 mean |diff| {mean}");
    // Without force_upcast the VAE goes to bf16 too.
    let vae_cfg = VaeConfig {
        force_upcast: false,
        ..VaeConfig::tiny()
    };
    let m = BridgeV2W::random_in(
        BridgeV2WConfig::tiny(),
        &vae_cfg,
        &TransformerConfig::tiny(),
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        Precision::Bf16,
        0,
    )
    .unwrap();
    assert!(m
        .vae_vs
        .variables()
        .values()
        .all(|v| v.kind() == Kind::BFloat16));
    let v = m.predict(&image(3), &masks(0), &opts(1, 2.0)).unwrap();
    assert!(v.data.iter().all(|x| x.is_finite()));
}

#[test]
fn per_block_gradient_checkpointing_gives_the_same_gradients() {
    let m = tiny(BridgeV2WConfig::tiny(), 21);
    // Non-zero projections and LoRA B, so every path carries gradient.
    tch::no_grad(|| {
        for (name, mut v) in m.adapters.variables() {
            if name.contains("out_projectors") || name.contains("lora_B") {
                v.copy_(&(Tensor::randn_like(&v) * 0.05));
            }
        }
    });
    let (x, c, t) = inputs(22);
    let d = TransformerConfig::tiny().inner_dim();
    let extra = Tensor::randn([1, 1, d], (Kind::Float, Device::Cpu)) * 0.1;
    let weight = Tensor::randn([1, 3, 4, 8, 12], (Kind::Float, Device::Cpu));
    let loss = |v: &Tensor| (v * &weight).square().mean(Kind::Float);
    let vars = m.adapters.variables();
    let copy = |g: Tensor| g.defined().then(|| g.copy());
    let grads = |e: &Tensor| -> Vec<(String, Option<Tensor>)> {
        let mut g: Vec<(String, Option<Tensor>)> = vars
            .iter()
            .map(|(k, v)| (k.clone(), copy(v.grad())))
            .collect();
        g.push(("extra".into(), copy(e.grad())));
        g
    };
    let zero = || {
        tch::no_grad(|| {
            for v in vars.values() {
                let mut g = v.grad();
                if g.defined() {
                    let _ = g.zero_();
                }
            }
        })
    };
    // Plain backward.
    zero();
    let e1 = extra.detach().set_requires_grad(true);
    let v1 = m
        .velocity_with_extra(&x, &t, Some(&c), std::slice::from_ref(&e1))
        .unwrap();
    loss(&v1).backward();
    let plain = grads(&e1);
    // Checkpointed.
    zero();
    let e2 = extra.detach().set_requires_grad(true);
    let (v2, record) = m
        .velocity_checkpointed(&x, &t, Some(&c), std::slice::from_ref(&e2))
        .unwrap();
    assert!(max_abs(&v1, &v2) < 1e-6, "outputs differ");
    assert!(v2.requires_grad() && v2.is_leaf());
    loss(&v2).backward();
    record.backward(&m.transformer.model).unwrap();
    let checkpointed = grads(&e2);
    let mut nonzero = 0;
    for ((name, a), (_, b)) in plain.iter().zip(&checkpointed) {
        let (a, b) = match (a, b) {
            (Some(a), Some(b)) => (a, b),
            (None, None) => continue,
            _ => panic!("{name}: gradient defined in one run only"),
        };
        let scale = a.abs().max().double_value(&[]);
        nonzero += usize::from(scale > 0.0);
        let diff = max_abs(a, b);
        assert!(
            diff <= 1e-5 * (1.0 + scale),
            "{name}: {diff} (scale {scale})"
        );
    }
    // Branch, LoRA A and B of every block, and the extra residual.
    assert!(nonzero >= 4, "{nonzero} non-zero gradients");
    assert!(checkpointed.iter().any(|(n, g)| n.contains("lora_A")
        && g.as_ref()
            .is_some_and(|g| g.abs().max().double_value(&[]) > 0.0)));
    assert!(checkpointed
        .iter()
        .any(|(n, g)| n == "extra" && g.is_some()));
    // More extra residuals than backbone blocks: the same clear error on both paths.
    let layers = TransformerConfig::tiny().num_layers as usize;
    let too_many: Vec<Tensor> = (0..=layers).map(|_| extra.shallow_clone()).collect();
    let e = m
        .velocity_with_extra(&x, &t, Some(&c), &too_many)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&format!(
            "{} residuals for {layers} backbone blocks",
            layers + 1
        )),
        "{e}"
    );
    let e = m
        .velocity_checkpointed(&x, &t, Some(&c), &too_many)
        .unwrap_err()
        .to_string();
    assert!(e.contains("backbone blocks"), "{e}");
    // A RoPE backbone without its rotary table: the same error as the plain forward.
    let text = Tensor::zeros([1, 3, 24], (Kind::Float, Device::Cpu));
    let tf = &m.transformer.model;
    let e = tf
        .forward_checkpointed(&x, &text, &t, None, None, vec![])
        .unwrap_err()
        .to_string();
    assert!(e.contains("rotary embeddings"), "{e}");
    let plain = tf
        .forward(&x, &text, &t, None, None)
        .unwrap_err()
        .to_string();
    assert_eq!(e, plain);
}

#[test]
fn image_conditioning_pads_or_repeats_and_travels_with_the_backbone() {
    let every = BridgeV2WConfig {
        image_conditioning: ImageConditioning::EveryFrame,
        ..BridgeV2WConfig::tiny()
    };
    let first = tiny(BridgeV2WConfig::tiny(), 21);
    let m = tiny(every.clone(), 21);
    tch::manual_seed(22);
    let img = Tensor::rand([2, 3, 64, 96], (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
    let a = first.image_latents(&img, None).unwrap(); // [2, 3, 8, 8, 12]
    let b = m.image_latents(&img, None).unwrap();
    assert_eq!(a.size(), b.size());
    let t = a.size()[1];
    assert!(a.narrow(1, 0, 1).abs().max().double_value(&[]) > 0.0);
    assert_eq!(a.narrow(1, 1, t - 1).abs().max().double_value(&[]), 0.0);
    for i in 0..t {
        assert_eq!(
            max_abs(&b.narrow(1, i, 1), &a.narrow(1, 0, 1)),
            0.0,
            "frame {i}"
        );
    }
    // The folder records the deviation; loading it alone adopts it, and a
    // weights file that disagrees is refused by name.
    let dir = tempfile::tempdir().unwrap();
    let folder = dir.path().join("prior");
    m.save_backbone(&folder).unwrap();
    let index = std::fs::read_to_string(folder.join("model_index.json")).unwrap();
    assert!(
        index.contains("\"_bridgev2w_image_conditioning\": \"every_frame\""),
        "{index}"
    );
    let load = |w: Option<&std::path::Path>| {
        BridgeV2W::load(
            &folder,
            w,
            None,
            BridgeV2WConfig::tiny(),
            ComputeDevice::Cpu,
            Precision::F32,
        )
    };
    let loaded = load(None).unwrap();
    assert_eq!(
        loaded.config().image_conditioning,
        ImageConditioning::EveryFrame
    );
    let weights = dir.path().join("first.safetensors");
    first.save_weights(&weights).unwrap();
    let e = load(Some(&weights)).unwrap_err().to_string();
    assert!(
        e.contains("image_conditioning") && e.contains("every_frame") && e.contains("first_frame"),
        "{e}"
    );
    // A first-frame backbone records nothing (diffusers' own folders).
    first.save_backbone(&dir.path().join("cog")).unwrap();
    let index = std::fs::read_to_string(dir.path().join("cog/model_index.json")).unwrap();
    assert!(!index.contains("image_conditioning"), "{index}");
    assert_eq!(
        "every_frame".parse::<ImageConditioning>().unwrap(),
        ImageConditioning::EveryFrame
    );
    let e = "repeat"
        .parse::<ImageConditioning>()
        .unwrap_err()
        .to_string();
    assert!(e.contains("first_frame, every_frame"), "{e}");
}

#[test]
fn link_coded_masks_travel_with_the_weights_and_refuse_binary_masks() {
    let links = BridgeV2WConfig {
        mask_coding: MaskCoding::Links,
        ..BridgeV2WConfig::tiny()
    };
    let m = tiny(links, 31);
    let dir = tempfile::tempdir().unwrap();
    let weights = dir.path().join("links.safetensors");
    m.save_weights(&weights).unwrap();
    let read = BridgeV2W::weights_config(&weights)
        .unwrap()
        .expect("config");
    assert_eq!(read.mask_coding, MaskCoding::Links);
    // Binary masks are refused by name; labels (two links) predict.
    let binary = masks(0);
    let e = m
        .predict(&image(1), &binary, &opts(1, 1.0))
        .unwrap_err()
        .to_string();
    assert!(e.contains("mask_coding") && e.contains("labels.npy"), "{e}");
    let mut labelled = binary.clone();
    for (i, v) in labelled.data.iter_mut().enumerate() {
        if *v != 0 {
            *v = 2 + (i % 96 >= 30) as u8;
        }
    }
    let a = m.predict(&image(1), &labelled, &opts(1, 1.0)).unwrap();
    assert_eq!(a.frames, 9);
    // The binary model reads the same labels as their silhouette.
    let b = tiny(BridgeV2WConfig::tiny(), 31);
    let from_labels = b.predict(&image(1), &labelled, &opts(1, 1.0)).unwrap();
    let from_masks = b.predict(&image(1), &binary, &opts(1, 1.0)).unwrap();
    assert_eq!(from_labels, from_masks);
}

#[test]
fn the_clip_length_can_change_where_the_vae_allows_it() {
    let mut m = tiny(BridgeV2WConfig::tiny(), 21);
    perturb_projections(&m);
    // The tiny VAE compresses time 4x: 5 frames are 2 latent frames (an even
    // count its decoder cannot return), 4 frames no 4k + 1; both refused by
    // name, the model left as it was.
    for bad in [0, 4, 5] {
        let e = m.set_clip_frames(bad).unwrap_err().to_string();
        assert!(e.contains("frames") && e.contains(&bad.to_string()), "{e}");
        assert_eq!(m.clip_frames(), 9);
    }
    m.set_clip_frames(17).unwrap();
    assert_eq!(m.clip_frames(), 17);
    let long = |offset| {
        let short = masks(offset);
        let mut data = short.data.clone();
        data.extend_from_slice(&short.data[..8 * 64 * 96]);
        MaskVideo {
            frames: 17,
            data,
            ..short
        }
    };
    let v = m.predict(&image(1), &long(0), &opts(3, 1.0)).unwrap();
    assert_eq!((v.frames, v.height, v.width), (17, 64, 96));
    assert!(v.data.iter().all(|x| x.is_finite()));
    let moved = m.predict(&image(1), &long(20), &opts(3, 1.0)).unwrap();
    assert!(v != moved, "the masks still steer the longer clip");
    // A clip of the old length is now refused, naming both shapes.
    let e = m
        .predict(&image(1), &masks(0), &opts(3, 1.0))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("[9, 64, 96]") && e.contains("[17, 64, 96]"),
        "{e}"
    );
}

#[test]
fn decoding_the_last_batch_gives_the_clips_last_frames() {
    // A VAE that does not compress time: 9 latent frames, decode batches
    // (0..3), (3..5), (5..7), (7..9).
    let m = BridgeV2W::random(
        BridgeV2WConfig::tiny(),
        &VaeConfig {
            temporal_compression_ratio: 1.0,
            ..VaeConfig::tiny()
        },
        &TransformerConfig::tiny(),
        SchedulerConfig::cogvideox_5b_i2v(),
        ComputeDevice::Cpu,
        21,
    )
    .unwrap();
    perturb_projections(&m);
    let o = PredictOptions {
        sample: SampleOptions {
            batch_noise: BatchNoise::Shared,
            ..opts(4, 1.0).sample
        },
        ..PredictOptions::default()
    };
    let frames = [image(1), image(1)];
    let masks = [masks(0), masks(20)];
    let full = m.predict_batch(&frames, &masks, &o).unwrap();
    let last = m
        .predict_batch(
            &frames,
            &masks,
            &PredictOptions {
                decode_frames: DecodeFrames::Last,
                ..o.clone()
            },
        )
        .unwrap();
    // The decode's last two frames, approximated (the VAE's own test:
    // exact for a still clip); a random model's clips are anything but.
    for (l, f) in last.iter().zip(&full) {
        assert_eq!((f.frames, l.frames), (9, 2));
        assert_eq!((l.height, l.width), (f.height, f.width));
        assert!(l.data.iter().all(|v| (0.0..=1.0).contains(v)));
    }
    assert!(last[0] != last[1], "other masks, other frames");
}
