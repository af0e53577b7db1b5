//! The CogVideoX 3D causal VAE: diffusers' `AutoencoderKLCogVideoX` (0.42.1), numerically
//! identical in f32 and loading `vae/` checkpoints unchanged.
//!
//! A video `[B, 3, T, H, W]` in `[-1, 1]` encodes to a diagonal Gaussian posterior over
//! latents `[B, 16, t, H/8, W/8]` with `t = 1 + (T - 1) / 4` for `T = 4k + 1` (time
//! compression 4, the first frame kept on its own). Like diffusers, the encoder runs on
//! frame batches of 8 (the first batch taking the remainder, e.g. 9 + 8 + 8 ... for
//! 8k + 1 frames) and the decoder on latent-frame batches of 2 (3 + 2 + 2 ...), each batch
//! continuing the causal convolutions of the previous one through a conv cache. Optional
//! spatial tiling (overlapping tiles blended linearly) and batch slicing bound memory.
//!
//! [`AutoencoderKLCogVideoX::encode`] returns the *unscaled* posterior; the diffusion
//! model works on latents scaled by [`VaeConfig::scaling_factor`]
//! ([`AutoencoderKLCogVideoX::scale_latents`] / [`AutoencoderKLCogVideoX::unscale_latents`]).

mod coder;
mod config;
mod decode_backward;
mod init;
pub mod layers;
mod posterior;
mod tiling;

use crate::device::{ComputeDevice, Precision};
use crate::error::{Result, WorldModelError};
use coder::{Decoder3D, Encoder3D};
use layers::SafeConv3d;
use std::path::Path;
use tch::nn::{self, VarStore};
use tch::{Kind, Tensor};

pub use coder::{DecoderCache, EncoderCache};
pub use config::{
    VaeConfig, DOWN_BLOCK_TYPE, MAX_SCALING_FACTOR, MIN_SCALING_FACTOR, UP_BLOCK_TYPE,
};
pub use decode_backward::{BatchReplay, DecodeRecord};

/// Frames with more pixels than this are run through the VAE in tiles by
/// `predict` and training (memory; diffusers' CogVideoX examples tile above
/// 256x256).
pub const TILING_MIN_PIXELS: usize = 256 * 256;
pub use init::{inflate_image_weights, init_like_pytorch};
pub use posterior::Posterior;
pub use tiling::{TileSize, Tiling, TilingOptions, VaeTiling};

/// Largest deviation from `[-1, 1]` that [`AutoencoderKLCogVideoX::encode`] accepts in a
/// video (rounding of converted pixel values).
pub const VIDEO_RANGE_SLACK: f64 = 1e-3;

/// The frame ranges `[start, end)` of diffusers' frame batching: `max(T / batch, 1)`
/// batches of `batch` frames, the first one also taking the `T % batch` remainder.
pub fn frame_batches(num_frames: i64, batch: i64) -> Vec<(i64, i64)> {
    let num_batches = (num_frames / batch).max(1);
    let remaining = num_frames % batch;
    (0..num_batches)
        .map(|i| {
            let start = batch * i + if i == 0 { 0 } else { remaining };
            let end = (batch * (i + 1) + remaining).min(num_frames);
            (start, end)
        })
        .collect()
}

/// diffusers' `AutoencoderKLCogVideoX`: encoder, decoder, optional quant convs, frame
/// batching with conv caches, optional tiling and slicing.
#[derive(Debug)]
pub struct AutoencoderKLCogVideoX {
    cfg: VaeConfig,
    encoder: Encoder3D,
    decoder: Decoder3D,
    quant_conv: Option<SafeConv3d>,
    post_quant_conv: Option<SafeConv3d>,
    /// A parameter, whose device and kind inputs are converted to.
    probe: Tensor,
    use_slicing: bool,
    use_tiling: bool,
    tiling: Tiling,
    num_latent_frames_batch_size: i64,
    num_sample_frames_batch_size: i64,
}

impl AutoencoderKLCogVideoX {
    /// Creates the model's parameters under `p` (diffusers' names: `encoder.*`,
    /// `decoder.*`, `quant_conv.*`, `post_quant_conv.*`) with placeholder values;
    /// load weights into the var store afterwards ([`crate::weights::load_component`]).
    pub fn new(cfg: &VaeConfig, p: nn::Path) -> Result<Self> {
        cfg.validate(Path::new("<VaeConfig>"))?;
        let act = cfg
            .activation()
            .ok_or_else(|| WorldModelError::config("<VaeConfig>", "act_fn", cfg.act_fn.clone()))?;
        let encoder = Encoder3D::new(cfg, &p / "encoder", act);
        let decoder = Decoder3D::new(cfg, &p / "decoder", act);
        // As diffusers: sized by `out_channels` (usable only when it equals
        // `latent_channels`; CogVideoX has neither conv).
        let oc = cfg.out_channels;
        let quant_conv = cfg.use_quant_conv.then(|| {
            SafeConv3d::new(
                &p / "quant_conv",
                2 * oc,
                2 * oc,
                [1, 1, 1],
                [1, 1, 1],
                [0, 0, 0],
            )
        });
        let post_quant_conv = cfg.use_post_quant_conv.then(|| {
            SafeConv3d::new(
                &p / "post_quant_conv",
                oc,
                oc,
                [1, 1, 1],
                [1, 1, 1],
                [0, 0, 0],
            )
        });
        let probe = (&p / "encoder" / "conv_in" / "conv")
            .get("weight")
            .ok_or_else(|| WorldModelError::input("vae", "encoder.conv_in.conv.weight missing"))?;
        Ok(Self {
            cfg: cfg.clone(),
            encoder,
            decoder,
            quant_conv,
            post_quant_conv,
            probe,
            use_slicing: false,
            use_tiling: false,
            tiling: Tiling::for_config(cfg),
            num_latent_frames_batch_size: 2,
            num_sample_frames_batch_size: 8,
        })
    }

    /// Loads a diffusers `vae/` folder (`config.json` and
    /// `diffusion_pytorch_model.safetensors` or shards) strictly onto `device` in
    /// `precision`. The parameters are frozen.
    pub fn load(dir: &Path, device: ComputeDevice, precision: Precision) -> Result<Self> {
        let device = device.check_available()?;
        let cfg = VaeConfig::from_file(&dir.join("config.json"))?;
        // Missing weights are named before the model is allocated.
        crate::weights::resolve_weight_files(dir, crate::weights::DIFFUSERS_WEIGHTS_STEM)?;
        let mut vs = VarStore::new(tch::Device::Cpu);
        let model = Self::new(&cfg, vs.root())?;
        vs.set_kind(precision.kind());
        crate::weights::load_component(&vs, dir)?;
        crate::device::move_to_device(&mut vs, device.to_tch());
        vs.freeze();
        Ok(model)
    }

    /// The config.
    pub fn config(&self) -> &VaeConfig {
        &self.cfg
    }

    /// Encodes/decodes each batch element separately (diffusers' `enable_slicing`).
    pub fn enable_slicing(&mut self) {
        self.use_slicing = true;
    }

    /// Encodes/decodes the batch at once (the default).
    pub fn disable_slicing(&mut self) {
        self.use_slicing = false;
    }

    /// Whether slicing is enabled.
    pub fn uses_slicing(&self) -> bool {
        self.use_slicing
    }

    /// Latents of the VAE -> latents of the diffusion model: `scaling_factor * z` (or
    /// `z / scaling_factor` with `invert_scale_latents`), as CogVideoX's pipelines.
    pub fn scale_latents(&self, z: &Tensor) -> Tensor {
        if self.cfg.invert_scale_latents {
            z * (1.0 / self.cfg.scaling_factor)
        } else {
            z * self.cfg.scaling_factor
        }
    }

    /// Latents of the diffusion model -> latents of the VAE: `1 / scaling_factor * z`,
    /// as CogVideoX's pipelines before decoding.
    pub fn unscale_latents(&self, z: &Tensor) -> Tensor {
        z * (1.0 / self.cfg.scaling_factor)
    }

    fn to_model(&self, x: &Tensor) -> Tensor {
        x.to_device(self.probe.device()).to_kind(self.probe.kind())
    }

    /// Encodes a video `[B, in_channels, T, H, W]` with values in `[-1, 1]` into the
    /// posterior over unscaled latents `[B, latent_channels, t, h, w]`.
    pub fn encode(&self, video: &Tensor) -> Result<Posterior> {
        let _guard = tch::no_grad_guard();
        self.encode_with_grad(video)
    }

    /// [`Self::encode`] with autograd on: gradients reach the encoder's
    /// parameters when they are trainable (training the VAE itself).
    pub fn encode_with_grad(&self, video: &Tensor) -> Result<Posterior> {
        self.check_video(video)?;
        let x = self.to_model(video);
        let b = x.size()[0];
        let h = if self.use_slicing && b > 1 {
            let slices = x
                .f_split(1, 0)?
                .iter()
                .map(|s| self.encode_one(s))
                .collect::<Result<Vec<_>>>()?;
            Tensor::f_cat(&slices, 0)?
        } else {
            self.encode_one(&x)?
        };
        Posterior::from_moments(&h)
    }

    /// Decodes unscaled latents `[B, latent_channels, t, h, w]` into a video
    /// `[B, out_channels, T, 8h, 8w]` (values roughly in `[-1, 1]`, not clamped).
    pub fn decode(&self, latents: &Tensor) -> Result<Tensor> {
        let _guard = tch::no_grad_guard();
        self.decode_with_grad(latents)
    }

    /// Decodes only the last of the decoder's latent-frame batches of
    /// `latents` `[B, latent_channels, t, h, w]` (the frames of
    /// [`frame_batches`]' last batch: 2 latent frames when `t` > 2), without
    /// the earlier batches' conv cache: the causal convolutions repeat the
    /// batch's first frame where they would have seen the frames before it.
    /// The last frames of [`Self::decode`] exactly for a still clip, an
    /// approximation otherwise (the earlier frames reach the last ones only
    /// through the caches), at the cost of the last batch alone.
    pub fn decode_last_batch(&self, latents: &Tensor) -> Result<Tensor> {
        self.check_latents(latents)?;
        let t = latents.size()[2];
        let (start, end) = frame_batches(t, self.num_latent_frames_batch_size)
            .last()
            .copied()
            .unwrap_or((0, t));
        self.decode(&latents.narrow(2, start, end - start)) // [B, C, T', H, W]
    }

    /// [`Self::decode`] with autograd on: gradients flow from the decoded
    /// video back into `latents` (and into the decoder's parameters when they
    /// are trainable; frozen otherwise). The `vae` stage's reconstruction
    /// loss decodes through this; the flow loss through
    /// [`Self::decode_recorded`] (bounded memory).
    pub fn decode_with_grad(&self, latents: &Tensor) -> Result<Tensor> {
        self.check_latents(latents)?;
        let z = self.to_model(latents);
        let b = z.size()[0];
        if self.use_slicing && b > 1 {
            let slices = z
                .f_split(1, 0)?
                .iter()
                .map(|s| self.decode_one(s))
                .collect::<Result<Vec<_>>>()?;
            Ok(Tensor::f_cat(&slices, 0)?)
        } else {
            self.decode_one(&z)
        }
    }

    fn check_video(&self, video: &Tensor) -> Result<()> {
        check_rank5(video, "video", self.cfg.in_channels, "in_channels")?;
        let s = video.size();
        // Each non-final encoder block maps a side s to (s - 2) / 2 + 1 (needs s >= 2).
        for (name, side) in [("height", s[3]), ("width", s[4])] {
            let mut v = side;
            for _ in 1..self.cfg.block_out_channels.len() {
                if v < 2 {
                    return Err(WorldModelError::input(
                        "video",
                        format!(
                            "{name} {side} is too small for {} downsamplings (use a multiple of {})",
                            self.cfg.block_out_channels.len() - 1,
                            self.cfg.spatial_compression()
                        ),
                    ));
                }
                v = (v - 2) / 2 + 1;
            }
        }
        check_finite(video, "video", "expected pixel values in [-1, 1]")?;
        if video.numel() > 0 {
            let v = video.to_kind(Kind::Float);
            let (lo, hi) = (v.min().double_value(&[]), v.max().double_value(&[]));
            if lo < -1.0 - VIDEO_RANGE_SLACK || hi > 1.0 + VIDEO_RANGE_SLACK {
                return Err(WorldModelError::input(
                    "video",
                    format!("values in [{lo}, {hi}]: expected [-1, 1] (pixels / 127.5 - 1)"),
                ));
            }
        }
        Ok(())
    }

    /// diffusers' `_encode`: one sample (or the whole batch), tiled or in frame batches.
    fn encode_one(&self, x: &Tensor) -> Result<Tensor> {
        let s = x.size();
        if self.use_tiling
            && (s[4] > self.tiling.tile_sample_min_width
                || s[3] > self.tiling.tile_sample_min_height)
        {
            return self.tiled_encode(x);
        }
        self.encode_frames(x)
    }

    /// The encoder over frame batches of 8 with the conv cache, then `quant_conv`.
    fn encode_frames(&self, x: &Tensor) -> Result<Tensor> {
        let mut cache: Option<EncoderCache> = None;
        let mut parts = Vec::new();
        for (start, end) in frame_batches(x.size()[2], self.num_sample_frames_batch_size) {
            let chunk = x.narrow(2, start, end - start);
            let (h, c) = self.encoder.forward(&chunk, cache.as_ref())?;
            cache = Some(c);
            let h = match &self.quant_conv {
                Some(conv) => conv.forward(&h)?,
                None => h,
            };
            parts.push(h);
        }
        Ok(Tensor::f_cat(&parts, 2)?)
    }

    /// diffusers' `_decode`: one sample (or the whole batch), tiled or in frame batches.
    fn decode_one(&self, z: &Tensor) -> Result<Tensor> {
        let s = z.size();
        if self.tiles_latents(s[3], s[4]) {
            return self.tiled_decode(z);
        }
        self.decode_frames(z)
    }

    /// `post_quant_conv`, then the decoder over latent-frame batches of 2 with the
    /// conv cache.
    fn decode_frames(&self, z: &Tensor) -> Result<Tensor> {
        let mut cache: Option<DecoderCache> = None;
        let mut parts = Vec::new();
        for (start, end) in frame_batches(z.size()[2], self.num_latent_frames_batch_size) {
            let (h, c) = self.decode_batch(&z.narrow(2, start, end - start), cache.as_ref())?;
            cache = Some(c);
            parts.push(h);
        }
        Ok(Tensor::f_cat(&parts, 2)?)
    }
}

impl AutoencoderKLCogVideoX {
    /// Latents to decode: `[B, latent_channels, t, h, w]`, finite.
    fn check_latents(&self, latents: &Tensor) -> Result<()> {
        check_rank5(
            latents,
            "latents",
            self.cfg.latent_channels,
            "latent_channels",
        )?;
        check_finite(
            latents,
            "latents",
            "a diverged denoising run, or latents scaled by a bad scaling_factor",
        )
    }
}

fn check_rank5(x: &Tensor, name: &str, channels: i64, field: &str) -> Result<()> {
    let s = x.size();
    if s.len() != 5 {
        return Err(WorldModelError::input(
            name,
            format!("shape {s:?}: expected 5 dimensions [batch, channels, frames, height, width]"),
        ));
    }
    if s[1] != channels {
        return Err(WorldModelError::input(
            name,
            format!("shape {s:?}: expected {channels} channels (config {field}) in dimension 1"),
        ));
    }
    if s.contains(&0) {
        return Err(WorldModelError::input(
            name,
            format!("shape {s:?} is empty"),
        ));
    }
    if !matches!(
        x.kind(),
        Kind::Float | Kind::Double | Kind::Half | Kind::BFloat16
    ) {
        return Err(WorldModelError::input(
            name,
            format!("dtype {:?}: expected a floating-point tensor", x.kind()),
        ));
    }
    Ok(())
}

/// Refuses NaN or infinite values in `x` (the input `name`), saying where
/// they may come from (`hint`).
fn check_finite(x: &Tensor, name: &str, hint: &str) -> Result<()> {
    let bad = x
        .f_isfinite()?
        .f_logical_not()?
        .f_sum(Kind::Int64)?
        .int64_value(&[]);
    if bad == 0 {
        Ok(())
    } else {
        Err(WorldModelError::input(
            name,
            format!("{bad} of {} values are NaN or infinite ({hint})", x.numel()),
        ))
    }
}

#[cfg(test)]
mod tests;
