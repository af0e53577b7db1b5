//! BridgeV2W predictions: the `WorldModel` contract, pipeline folders that
//! diffusers loads, bf16, link-coded masks, clip lengths and decoding the last
//! frames. The model itself: `bridge.rs`.

#![allow(clippy::unwrap_used)]

mod bridge_common;
mod common;

use bridge_common::*;
use bridgev2w_io::frame::RgbFrame;
use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig, MaskCoding};
use bridgev2w_world_model::pipeline::{
    BatchNoise, DecodeFrames, PredictOptions, SampleOptions, WorldModel,
};
use bridgev2w_world_model::scheduler::SchedulerConfig;
use bridgev2w_world_model::transformer::TransformerConfig;
use bridgev2w_world_model::vae::VaeConfig;
use bridgev2w_world_model::video::MaskVideo;
use bridgev2w_world_model::{ComputeDevice, Precision};
use tch::Kind;

#[test]
fn predict_follows_the_world_model_contract() {
    let _rng = rng_lock();
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
    let _rng = rng_lock();
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
    let _rng = rng_lock();
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
    let _rng = rng_lock();
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
fn link_coded_masks_travel_with_the_weights_and_refuse_binary_masks() {
    let _rng = rng_lock();
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
    let _rng = rng_lock();
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
    let _rng = rng_lock();
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
