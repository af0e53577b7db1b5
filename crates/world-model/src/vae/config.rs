//! The VAE's configuration: diffusers' `vae/config.json`, its presets and its checks.

use super::layers::Activation;
use crate::error::{Result, WorldModelError};
use bridgev2w_io::json::read_json;
use std::path::Path;

/// The only block type of the encoder.
pub const DOWN_BLOCK_TYPE: &str = "CogVideoXDownBlock3D";
/// The only block type of the decoder.
pub const UP_BLOCK_TYPE: &str = "CogVideoXUpBlock3D";
/// The smallest `scaling_factor` accepted (latents are multiplied by it
/// or by its inverse).
pub const MIN_SCALING_FACTOR: f64 = 1e-6;
/// The largest `scaling_factor` accepted (a `vae` stage writes at most
/// 1e6: one over its latents' standard deviation, floored at 1e-6).
pub const MAX_SCALING_FACTOR: f64 = 1e6;

/// diffusers' `vae/config.json` of `AutoencoderKLCogVideoX`. Unknown fields
/// (`_class_name`, `_diffusers_version`, ...) are ignored; missing fields take diffusers'
/// defaults (those of CogVideoX-2b).
#[derive(Debug, Clone, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(default)]
pub struct VaeConfig {
    /// Channels of the input video.
    pub in_channels: i64,
    /// Channels of the decoded video.
    pub out_channels: i64,
    /// One `CogVideoXDownBlock3D` per entry of `block_out_channels`.
    pub down_block_types: Vec<String>,
    /// One `CogVideoXUpBlock3D` per entry of `block_out_channels`.
    pub up_block_types: Vec<String>,
    /// Channels of each encoder block (reversed in the decoder).
    pub block_out_channels: Vec<i64>,
    /// Channels of the latent.
    pub latent_channels: i64,
    /// Resnets per encoder block (the decoder has one more).
    pub layers_per_block: i64,
    /// The resnets' activation (`silu`, `swish`, `mish`, `gelu`, `relu`).
    pub act_fn: String,
    /// Epsilon of the encoder resnets' group norms.
    pub norm_eps: f64,
    /// Groups of every group norm.
    pub norm_num_groups: i64,
    /// Time compression; `log2` of it is the number of blocks that halve time.
    pub temporal_compression_ratio: f64,
    /// Sample height the model was made for (tiling uses tiles of half of it).
    pub sample_height: i64,
    /// Sample width the model was made for (tiling uses tiles of half of it).
    pub sample_width: i64,
    /// Latent scale of the diffusion model: `z_model = scaling_factor * z_vae`.
    pub scaling_factor: f64,
    /// Latent shift (unused by CogVideoX; kept for the config's round trip).
    pub shift_factor: Option<f64>,
    /// Per-channel latent means (unused by CogVideoX).
    pub latents_mean: Option<Vec<f64>>,
    /// Per-channel latent stds (unused by CogVideoX).
    pub latents_std: Option<Vec<f64>>,
    /// Whether pipelines should run the VAE in f32.
    pub force_upcast: bool,
    /// Whether a 1×1×1 `quant_conv` follows the encoder.
    pub use_quant_conv: bool,
    /// Whether a 1×1×1 `post_quant_conv` precedes the decoder.
    pub use_post_quant_conv: bool,
    /// Whether pipelines divide (instead of multiply) encoded latents by the scale.
    pub invert_scale_latents: bool,
}

impl Default for VaeConfig {
    /// diffusers' defaults (== CogVideoX-2b's VAE).
    fn default() -> Self {
        Self {
            in_channels: 3,
            out_channels: 3,
            down_block_types: vec![DOWN_BLOCK_TYPE.to_owned(); 4],
            up_block_types: vec![UP_BLOCK_TYPE.to_owned(); 4],
            block_out_channels: vec![128, 256, 256, 512],
            latent_channels: 16,
            layers_per_block: 3,
            act_fn: "silu".to_owned(),
            norm_eps: 1e-6,
            norm_num_groups: 32,
            temporal_compression_ratio: 4.0,
            sample_height: 480,
            sample_width: 720,
            scaling_factor: 1.152_584_26,
            shift_factor: None,
            latents_mean: None,
            latents_std: None,
            force_upcast: true,
            use_quant_conv: false,
            use_post_quant_conv: false,
            invert_scale_latents: false,
        }
    }
}

impl VaeConfig {
    /// THUDM/CogVideoX-5b-I2V's `vae/config.json` (as CogVideoX-5b's: scaling 0.7).
    pub fn cogvideox_5b_i2v() -> Self {
        Self {
            scaling_factor: 0.7,
            ..Self::default()
        }
    }

    /// THUDM/CogVideoX-2b's `vae/config.json` (scaling 1.15258426).
    pub fn cogvideox_2b() -> Self {
        Self::default()
    }

    /// The architecture of the real VAE (4 blocks, 2 compressing time, 8× space) with a
    /// few channels, for tests (== `fixture_vae.py --preset tiny`).
    pub fn tiny() -> Self {
        Self {
            block_out_channels: vec![8, 16, 16, 24],
            latent_channels: 4,
            layers_per_block: 1,
            norm_num_groups: 4,
            sample_height: 32,
            sample_width: 32,
            scaling_factor: 0.7,
            ..Self::default()
        }
    }

    /// The CPU-trainable autoencoder of the synthetic proof run: 3 blocks
    /// (4x space, 4x time), 16 latent channels as the real VAE.
    pub fn small() -> Self {
        Self {
            down_block_types: vec![DOWN_BLOCK_TYPE.to_owned(); 3],
            up_block_types: vec![UP_BLOCK_TYPE.to_owned(); 3],
            block_out_channels: vec![16, 32, 64],
            latent_channels: 16,
            layers_per_block: 1,
            norm_num_groups: 8,
            sample_height: 64,
            sample_width: 96,
            scaling_factor: 1.0,
            ..Self::default()
        }
    }

    /// The 2x-spatial variant of [`VaeConfig::small`]: 2 blocks of 16 and 32
    /// channels, 4 latent channels. Its one resampling block halves space
    /// only: 2x space, no time compression (one latent frame per frame, 9
    /// for 9). Each latent pixel holds 4 numbers for 2x2 RGB pixels, so the
    /// autoencoder can reconstruct the synthetic world's 2-3 pixel objects
    /// and textures, and it costs less per frame than `small` (no
    /// quarter-resolution block). 4 latent channels, not 16: a transformer
    /// token of 4x4 latent pixels then holds 64 noise values, which its 128
    /// dimensions can carry (with 16 channels, 256 noise values through 128
    /// dimensions: the sampler cannot see, so cannot remove, most of the
    /// noise, and the predictions stay noisy). Without time compression, an
    /// autoencoder trained on single frames starts on clips as itself applied
    /// frame by frame (`train.inflate_image_vae`).
    pub fn small_2x() -> Self {
        Self {
            down_block_types: vec![DOWN_BLOCK_TYPE.to_owned(); 2],
            up_block_types: vec![UP_BLOCK_TYPE.to_owned(); 2],
            block_out_channels: vec![16, 32],
            latent_channels: 4,
            temporal_compression_ratio: 1.0,
            ..Self::small()
        }
    }

    /// Reads `path` (a diffusers `config.json`) and validates it.
    pub fn from_file(path: &Path) -> Result<Self> {
        let cfg: Self = read_json(path)?;
        cfg.validate(path)?;
        Ok(cfg)
    }

    /// Number of blocks that halve (encoder) / double (decoder) time:
    /// `int(log2(temporal_compression_ratio))` as in diffusers.
    pub fn temporal_compress_level(&self) -> i64 {
        self.temporal_compression_ratio.log2().floor() as i64
    }

    /// Why `frames` pixel frames do not round-trip through this VAE, or
    /// `None`: a count must be `tk + 1` (the temporal compression `t`), and
    /// with more than one latent frame their count must be odd, since the
    /// causal upsampler keeps the first latent frame apart only for odd counts
    /// (5 frames, 2 latent frames, would decode to 8).
    pub fn frames_error(&self, frames: usize) -> Option<String> {
        let t = (self.temporal_compression_ratio as usize).max(1);
        if frames == 0 || (frames - 1) % t != 0 {
            return Some(format!(
                "{frames}: expected {t}k + 1 (the VAE's temporal compression)"
            ));
        }
        let latents = (frames - 1) / t + 1;
        (t > 1 && latents > 1 && latents % 2 == 0).then(|| {
            format!(
                "{frames}: {latents} latent frames, an even count, which the causal VAE decodes to {} frames (its upsampler keeps the first latent frame apart only for odd counts); expected {}k + 1 frames, e.g. 9, 17, 25 or 49",
                latents * t,
                2 * t
            )
        })
    }

    /// Spatial compression: `2^(blocks - 1)` (8 for CogVideoX).
    pub fn spatial_compression(&self) -> i64 {
        1 << (self.block_out_channels.len().saturating_sub(1))
    }

    /// The resnets' activation.
    pub fn activation(&self) -> Option<Activation> {
        Activation::from_name(&self.act_fn)
    }

    /// Checks the fields the model is built from; `source` names the file (or preset)
    /// in errors.
    pub fn validate(&self, source: &Path) -> Result<()> {
        let err = |field: &str, msg: String| Err(WorldModelError::config(source, field, msg));
        let n = self.block_out_channels.len();
        if n == 0 {
            return err("block_out_channels", "is empty".into());
        }
        if self.down_block_types.len() != n {
            return err(
                "down_block_types",
                format!(
                    "has {} entries, block_out_channels {n}",
                    self.down_block_types.len()
                ),
            );
        }
        if self.up_block_types.len() != n {
            return err(
                "up_block_types",
                format!(
                    "has {} entries, block_out_channels {n}",
                    self.up_block_types.len()
                ),
            );
        }
        if let Some(t) = self.down_block_types.iter().find(|t| *t != DOWN_BLOCK_TYPE) {
            return err(
                "down_block_types",
                format!("`{t}`: only {DOWN_BLOCK_TYPE} is supported"),
            );
        }
        if let Some(t) = self.up_block_types.iter().find(|t| *t != UP_BLOCK_TYPE) {
            return err(
                "up_block_types",
                format!("`{t}`: only {UP_BLOCK_TYPE} is supported"),
            );
        }
        if self.norm_num_groups < 1 {
            return err(
                "norm_num_groups",
                format!("{}: must be >= 1", self.norm_num_groups),
            );
        }
        for (field, value) in [
            ("in_channels", self.in_channels),
            ("out_channels", self.out_channels),
            ("latent_channels", self.latent_channels),
        ] {
            if value < 1 {
                return err(field, format!("{value}: must be >= 1"));
            }
        }
        if let Some(c) = self
            .block_out_channels
            .iter()
            .find(|c| **c < 1 || **c % self.norm_num_groups != 0)
        {
            return err(
                "block_out_channels",
                format!(
                    "{c} is not a positive multiple of norm_num_groups {}",
                    self.norm_num_groups
                ),
            );
        }
        // Upper bounds before anything is allocated: far above every
        // CogVideoX VAE (4 blocks up to 512 channels, 16 latent channels).
        if n > 16 {
            return err(
                "block_out_channels",
                format!("{n} blocks: at most 16 are supported (a corrupt config?)"),
            );
        }
        for (field, value, max) in [
            ("in_channels", self.in_channels, 1024),
            ("out_channels", self.out_channels, 1024),
            ("latent_channels", self.latent_channels, 1024),
            ("norm_num_groups", self.norm_num_groups, 1024),
            (
                "block_out_channels",
                self.block_out_channels.iter().copied().max().unwrap_or(1),
                8192,
            ),
            ("layers_per_block", self.layers_per_block, 64),
            ("sample_height", self.sample_height, 16_384),
            ("sample_width", self.sample_width, 16_384),
        ] {
            if value > max {
                return err(
                    field,
                    format!("{value}: at most {max} is supported (a corrupt config?)"),
                );
            }
        }
        if self.temporal_compression_ratio > 64.0 {
            return err(
                "temporal_compression_ratio",
                format!(
                    "{}: at most 64 is supported",
                    self.temporal_compression_ratio
                ),
            );
        }
        if self.layers_per_block < 0 {
            return err(
                "layers_per_block",
                format!("{}: must be >= 0", self.layers_per_block),
            );
        }
        if self.activation().is_none() {
            return err(
                "act_fn",
                format!(
                    "`{}`: expected silu, swish, mish, gelu or relu",
                    self.act_fn
                ),
            );
        }
        if self.temporal_compression_ratio.is_nan() || self.temporal_compression_ratio < 1.0 {
            return err(
                "temporal_compression_ratio",
                format!("{}: must be >= 1", self.temporal_compression_ratio),
            );
        }
        // Only the blocks with a down/upsampler (all but the last) can halve
        // time: more levels than that would leave the latent longer than
        // `latent_frames` expects.
        let resamplers = n as i64 - 1;
        if self.temporal_compress_level() > resamplers {
            return err(
                "temporal_compression_ratio",
                format!(
                    "{} needs {} time-halving blocks, but {n} blocks have only {resamplers} resamplers",
                    self.temporal_compression_ratio,
                    self.temporal_compress_level()
                ),
            );
        }
        if self.norm_eps.is_nan() || self.norm_eps <= 0.0 {
            return err("norm_eps", format!("{}: must be > 0", self.norm_eps));
        }
        // Latents are multiplied by it or by its inverse: both must stay
        // far from float32's range, or the latents become 0 or infinite.
        if !(MIN_SCALING_FACTOR..=MAX_SCALING_FACTOR).contains(&self.scaling_factor) {
            return err(
                "scaling_factor",
                format!(
                    "{}: expected a number in [{MIN_SCALING_FACTOR:e}, {MAX_SCALING_FACTOR:e}] (CogVideoX: 0.7 or 1.15258426)",
                    self.scaling_factor
                ),
            );
        }
        if self.sample_height < 2 || self.sample_width < 2 {
            return err(
                "sample_height",
                format!(
                    "{}x{}: sample size must be at least 2x2",
                    self.sample_height, self.sample_width
                ),
            );
        }
        Ok(())
    }
}
