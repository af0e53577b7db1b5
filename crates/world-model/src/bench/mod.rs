//! Timing of the model's main operations on random weights, for `bridgev2w bench
//! model`, which runs diffusers on the same configs and shapes in the same run:
//!
//! * here: [`time_model`], one transformer forward and one VAE encode/decode;
//! * [`diffusers`]: the same operations timed by diffusers (a Python peer);
//! * [`gpu_memory`]: each side's peak GPU memory, polled from `nvidia-smi`;
//! * [`compare`]: both sides from one options struct to one report;
//! * [`precisions`]: that report at several precisions in one run.

pub mod compare;
pub mod diffusers;
pub mod gpu_memory;
pub mod precisions;

pub use compare::{
    bench_configs, bench_model, speed_up, GpuPeakMib, ModelBenchOptions, ModelBenchReport,
    ModelStyle,
};
pub use diffusers::DiffusersPeer;
pub use precisions::{bench_model_precisions, ModelBenchSeries};

use crate::device::{ComputeDevice, Precision};
use crate::error::{Result, WorldModelError};
use crate::transformer::{LoadedTransformer, TransformerConfig};
use crate::vae::{AutoencoderKLCogVideoX, VaeConfig};
use std::time::Instant;
use tch::nn::VarStore;
use tch::{Kind, Tensor};

/// Why `bench model` could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The options do not fit together: says which and what is expected.
    #[error("{0}")]
    Invalid(String),
    /// This crate's model failed.
    #[error(transparent)]
    Model(#[from] WorldModelError),
    /// diffusers could not be found, run or understood.
    #[error(transparent)]
    Peer(#[from] bridgev2w_io::peer::PeerError),
    /// A config file for the peer could not be written.
    #[error(transparent)]
    File(#[from] bridgev2w_io::FileError),
}

impl BenchError {
    /// An option's bad value: `field` names it, `message` says what was
    /// given and what is expected.
    pub(crate) fn input(field: &str, message: impl std::fmt::Display) -> Self {
        Self::Invalid(format!("{field}: {message}"))
    }
}

/// What is timed: one clip of `frames` pixel frames at `height` x `width`.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelBenchShape {
    /// Pixel frames (`4k + 1`).
    pub frames: i64,
    /// Pixel height (a multiple of 8 x patch size).
    pub height: i64,
    /// Pixel width (a multiple of 8 x patch size).
    pub width: i64,
    /// Text tokens.
    pub text_len: i64,
    /// Transformer batch: 2 is one denoising step with classifier-free
    /// guidance (conditional and unconditional halves in one forward).
    pub batch: i64,
    /// The VAE runs with spatial tiling (diffusers' `enable_tiling()`, default
    /// tile sizes), as `predict` does above 256x256.
    pub vae_tiling: bool,
}

/// Seconds (best of `repeat`, after a warm-up) of each operation.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelTimings {
    /// One transformer forward at the shape's batch.
    pub transformer_forward_s: f64,
    /// VAE encode of the clip (posterior mean).
    pub vae_encode_s: f64,
    /// VAE decode of the clip's latents.
    pub vae_decode_s: f64,
}

fn best_of(repeat: usize, device: tch::Device, f: &mut dyn FnMut() -> Result<()>) -> Result<f64> {
    f()?; // warm-up
    let mut best = f64::INFINITY;
    for _ in 0..repeat.max(1) {
        if let tch::Device::Cuda(i) = device {
            tch::Cuda::synchronize(i as i64);
        }
        let t0 = Instant::now();
        f()?;
        if let tch::Device::Cuda(i) = device {
            tch::Cuda::synchronize(i as i64);
        }
        best = best.min(t0.elapsed().as_secs_f64());
    }
    Ok(best)
}

/// Times a transformer forward and a VAE encode/decode with random weights.
/// An out-of-memory (libtorch's error, or an op's panic, caught) is
/// [`WorldModelError::OutOfMemory`] naming the shapes.
pub fn time_model(
    tf_cfg: &TransformerConfig,
    vae_cfg: &VaeConfig,
    shape: &ModelBenchShape,
    device: ComputeDevice,
    precision: Precision,
    repeat: usize,
) -> Result<ModelTimings> {
    let timed = || -> Result<ModelTimings> {
        let _guard = tch::no_grad_guard();
        let dev = device.check_available()?.to_tch();
        let kind = precision.kind();
        let t = vae_cfg.temporal_compression_ratio as i64;
        let s = vae_cfg.spatial_compression();
        if (shape.frames - 1) % t != 0
            || shape.height % (s * tf_cfg.patch_size) != 0
            || shape.width % (s * tf_cfg.patch_size) != 0
        {
            return Err(WorldModelError::input(
                "bench shape",
                format!(
                    "{} frames at {}x{}: expected {t}k + 1 frames and sides divisible by {}",
                    shape.frames,
                    shape.height,
                    shape.width,
                    s * tf_cfg.patch_size
                ),
            ));
        }
        if shape.batch < 1 {
            return Err(WorldModelError::input(
                "bench batch",
                format!("{}: expected >= 1", shape.batch),
            ));
        }
        check_shape_memory(tf_cfg, shape, precision, device)?;
        let (lf, lh, lw) = (
            (shape.frames - 1) / t + 1,
            shape.height / s,
            shape.width / s,
        );
        tch::manual_seed(0);
        let tf = LoadedTransformer::random(tf_cfg, device, precision)?;
        let b = shape.batch;
        // [B, F, C, H, W] latents, [B, L, D] text, [B] timesteps.
        let x = Tensor::randn([b, lf, tf_cfg.in_channels, lh, lw], (kind, dev));
        let text = Tensor::randn([b, shape.text_len, tf_cfg.text_embed_dim], (kind, dev));
        let ts = Tensor::full([b], 500i64, (Kind::Int64, dev));
        let rotary = tf.model.rotary_for(&x)?;
        let ofs = tf_cfg
            .ofs_embed_dim
            .map(|_| Tensor::full([b], 2.0, (Kind::Float, dev)));
        let transformer_forward_s = best_of(repeat, dev, &mut || {
            tf.model
                .forward(&x, &text, &ts, rotary.as_ref(), ofs.as_ref())
                .map(|_| ())
        })?;
        drop(tf);
        let mut vs = VarStore::new(tch::Device::Cpu);
        let mut vae = AutoencoderKLCogVideoX::new(vae_cfg, vs.root())?;
        if shape.vae_tiling {
            vae.enable_tiling(crate::vae::TilingOptions::default())?;
        }
        vs.set_kind(kind);
        crate::device::move_to_device(&mut vs, dev);
        let video =
            Tensor::rand([1, 3, shape.frames, shape.height, shape.width], (kind, dev)) * 2.0 - 1.0;
        let latents = Tensor::randn([1, vae_cfg.latent_channels, lf, lh, lw], (kind, dev));
        let vae_encode_s = best_of(repeat, dev, &mut || vae.encode(&video).map(|_| ()))?;
        let vae_decode_s = best_of(repeat, dev, &mut || vae.decode(&latents).map(|_| ()))?;
        Ok(ModelTimings {
            transformer_forward_s,
            vae_encode_s,
            vae_decode_s,
        })
    };
    crate::error::guarded(timed)
        .map_err(|e| {
            e.on_out_of_memory(
                || {
                    format!(
                        "timing the model: batch {} of {} frames at {}x{} ({} layers of {}, {precision:?} on {device:?})",
                        shape.batch,
                        shape.frames,
                        shape.height,
                        shape.width,
                        tf_cfg.num_layers,
                        tf_cfg.inner_dim()
                    )
                },
                crate::error::BENCH_MEMORY_ADVICE,
            )
        })
}

/// The bench's sizes against their maximum (`--frames` within
/// [`crate::bridge::MAX_CLIP_FRAMES`], `--height`/`--width` within
/// [`crate::bridge::MAX_CLIP_SIDE`], `--batch` within
/// [`crate::bridge::MAX_PREDICT_BATCH`]) and, on a CPU, a floor of its
/// memory against the machine's: the video `[1, 3, F, H, W]` and one
/// transformer block's activations (8 x batch x tokens x width) at the
/// bench's precision.
fn check_shape_memory(
    tf_cfg: &TransformerConfig,
    shape: &ModelBenchShape,
    precision: Precision,
    device: ComputeDevice,
) -> Result<()> {
    use crate::bridge::{MAX_CLIP_FRAMES, MAX_CLIP_SIDE, MAX_PREDICT_BATCH};
    use bridgev2w_io::memory::{at_most, bytes, check_fits};
    let size = |v: i64| v.max(0) as u64;
    at_most(
        "--frames",
        size(shape.frames),
        MAX_CLIP_FRAMES as u64,
        "frames",
    )?;
    at_most(
        "--height",
        size(shape.height),
        MAX_CLIP_SIDE as u64,
        "pixels",
    )?;
    at_most("--width", size(shape.width), MAX_CLIP_SIDE as u64, "pixels")?;
    at_most(
        "--batch",
        size(shape.batch),
        MAX_PREDICT_BATCH as u64,
        "clips",
    )?;
    if device != ComputeDevice::Cpu {
        return Ok(());
    }
    let element = match precision {
        Precision::F32 => 4,
        Precision::Bf16 => 2,
    };
    let video = bytes(&[
        3,
        size(shape.frames),
        size(shape.height),
        size(shape.width),
        element,
    ]);
    // CogVideoX's tokens: 4x in time, 8x in space and 2x2 patches.
    let tokens = bytes(&[
        size(shape.frames) / 4 + 1,
        size(shape.height) / 16,
        size(shape.width) / 16,
    ])
    .saturating_add(size(shape.text_len));
    let block = bytes(&[
        size(shape.batch),
        tokens,
        size(tf_cfg.inner_dim()),
        element,
        8,
    ]);
    check_fits(
        &format!(
            "timing the model at batch {} of {} frames at {}x{}",
            shape.batch, shape.frames, shape.height, shape.width
        ),
        video.saturating_add(block),
        crate::error::BENCH_MEMORY_ADVICE,
    )?;
    Ok(())
}

/// libtorch's intra-op threads (what the peer should use too).
pub fn torch_threads() -> usize {
    tch::get_num_threads().max(1) as usize
}
