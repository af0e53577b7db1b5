//! Helpers of the BridgeV2W tests (`bridge.rs`, `bridge_predict.rs`): tiny
//! random models, inputs, and the prediction inputs of the `WorldModel` contract.

#![allow(dead_code)] // each test file uses its own part

use bridgev2w_io::frame::RgbFrame;
use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
use bridgev2w_world_model::pipeline::{BatchNoise, PredictOptions, SampleOptions};
use bridgev2w_world_model::scheduler::SchedulerConfig;
use bridgev2w_world_model::transformer::TransformerConfig;
use bridgev2w_world_model::vae::VaeConfig;
use bridgev2w_world_model::video::MaskVideo;
use bridgev2w_world_model::ComputeDevice;
use tch::{Device, Kind, Tensor};

/// Serialises the tests of a test binary that draw from libtorch's global
/// random generator: `BridgeV2W::random` seeds it and then initialises the
/// weights from it, so a test running beside another that draws from it
/// gets other weights for the same seed (two `tiny(cfg, 21)` differ). Every
/// test of `bridge.rs` and `bridge_predict.rs` holds this for its duration.
pub fn rng_lock() -> std::sync::MutexGuard<'static, ()> {
    static RNG: std::sync::Mutex<()> = std::sync::Mutex::new(());
    // A failed test poisons the lock; the others still run.
    RNG.lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

pub fn tiny(cfg: BridgeV2WConfig, seed: i64) -> BridgeV2W {
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
pub fn inputs(seed: i64) -> (Tensor, Tensor, Tensor) {
    tch::manual_seed(seed);
    let opts = (Kind::Float, Device::Cpu);
    (
        Tensor::randn([1, 3, 8, 8, 12], opts),
        Tensor::randn([1, 3, 8, 8, 12], opts),
        Tensor::from_slice(&[500i64]),
    )
}

pub fn max_abs(a: &Tensor, b: &Tensor) -> f64 {
    (a - b).abs().max().double_value(&[])
}

/// Fills every `out_projectors` variable with small random values.
pub fn perturb_projections(m: &BridgeV2W) {
    tch::no_grad(|| {
        for (name, mut v) in m.adapters.variables() {
            if name.contains("out_projectors") {
                v.copy_(&(Tensor::randn_like(&v) * 0.05));
            }
        }
    });
}

pub fn image(seed: u64) -> RgbFrame {
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

pub fn masks(offset: usize) -> MaskVideo {
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

pub fn opts(seed: u64, guidance_scale: f64) -> PredictOptions {
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
