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
pub mod layers;

use crate::device::{ComputeDevice, Precision};
use crate::error::{read_json, Result, WorldModelError};
use crate::parity::FixtureIo;
use coder::{Decoder3D, Encoder3D};
use layers::{Activation, SafeConv3d};
use std::path::{Path, PathBuf};
use tch::nn::{self, VarStore};
use tch::{Kind, Tensor};

pub use coder::{DecoderCache, EncoderCache};

/// The only block type of the encoder.
pub const DOWN_BLOCK_TYPE: &str = "CogVideoXDownBlock3D";
/// The only block type of the decoder.
pub const UP_BLOCK_TYPE: &str = "CogVideoXUpBlock3D";

/// Largest deviation from `[-1, 1]` that [`AutoencoderKLCogVideoX::encode`] accepts in a
/// video (rounding of converted pixel values).
pub const VIDEO_RANGE_SLACK: f64 = 1e-3;

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
        if !(self.scaling_factor.is_finite() && self.scaling_factor != 0.0) {
            return err(
                "scaling_factor",
                format!("{}: must be finite and non-zero", self.scaling_factor),
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

/// Spatial tiling parameters (diffusers' `tile_sample_min_*`, `tile_latent_min_*`,
/// `tile_overlap_factor_*`). Inputs larger than a tile in either direction are split
/// into overlapping tiles, each encoded/decoded on its own, and blended linearly.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tiling {
    /// Tile height in pixels.
    pub tile_sample_min_height: i64,
    /// Tile width in pixels.
    pub tile_sample_min_width: i64,
    /// Tile height in latent pixels.
    pub tile_latent_min_height: i64,
    /// Tile width in latent pixels.
    pub tile_latent_min_width: i64,
    /// Fraction of a tile's height shared with the next tile.
    pub tile_overlap_factor_height: f64,
    /// Fraction of a tile's width shared with the next tile.
    pub tile_overlap_factor_width: f64,
}

/// Overrides for [`AutoencoderKLCogVideoX::enable_tiling`]; `None` keeps the current value.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct TilingOptions {
    /// Tile height in pixels.
    pub tile_sample_min_height: Option<i64>,
    /// Tile width in pixels.
    pub tile_sample_min_width: Option<i64>,
    /// Fraction of a tile's height shared with the next tile, in `[0, 1)`.
    pub tile_overlap_factor_height: Option<f64>,
    /// Fraction of a tile's width shared with the next tile, in `[0, 1)`.
    pub tile_overlap_factor_width: Option<f64>,
}

/// Pixel tile -> latent tile: `int(sample / 2^(blocks - 1))` as in diffusers.
fn latent_tile(sample: i64, cfg: &VaeConfig) -> i64 {
    (sample as f64 / cfg.spatial_compression() as f64) as i64
}

impl Tiling {
    /// diffusers' defaults: half the config's sample size, overlaps 1/6 (height) and
    /// 1/5 (width).
    pub fn for_config(cfg: &VaeConfig) -> Self {
        let h = cfg.sample_height / 2;
        let w = cfg.sample_width / 2;
        Self {
            tile_sample_min_height: h,
            tile_sample_min_width: w,
            tile_latent_min_height: latent_tile(h, cfg),
            tile_latent_min_width: latent_tile(w, cfg),
            tile_overlap_factor_height: 1.0 / 6.0,
            tile_overlap_factor_width: 1.0 / 5.0,
        }
    }
}

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

/// The diagonal Gaussian posterior of an encoded video (diffusers'
/// `DiagonalGaussianDistribution`): `mean` and `logvar` (clamped to `[-30, 20]`),
/// each `[B, latent_channels, t, h, w]`, unscaled.
#[derive(Debug)]
pub struct Posterior {
    mean: Tensor,
    logvar: Tensor,
}

impl Posterior {
    /// Splits the encoder's moments `[B, 2C, t, h, w]` into mean and log-variance.
    pub fn from_moments(moments: &Tensor) -> Result<Self> {
        let parts = moments.f_chunk(2, 1)?;
        let [mean, logvar] = <[Tensor; 2]>::try_from(parts).map_err(|p| {
            WorldModelError::input(
                "moments",
                format!("expected 2 chunks along channels, got {}", p.len()),
            )
        })?;
        Ok(Self {
            mean,
            logvar: logvar.clamp(-30.0, 20.0),
        })
    }

    /// The mean `[B, C, t, h, w]` (diffusers' `latent_dist.mean`, also the mode).
    pub fn mean(&self) -> &Tensor {
        &self.mean
    }

    /// The clamped log-variance.
    pub fn logvar(&self) -> &Tensor {
        &self.logvar
    }

    /// `exp(0.5 * logvar)`.
    pub fn std(&self) -> Tensor {
        (&self.logvar * 0.5).exp()
    }

    /// The mode (== mean).
    pub fn mode(&self) -> Tensor {
        self.mean.shallow_clone()
    }

    /// `mean + std * noise` for a caller-supplied standard normal `noise` of the
    /// mean's shape.
    pub fn sample_with_noise(&self, noise: &Tensor) -> Result<Tensor> {
        if noise.size() != self.mean.size() {
            return Err(WorldModelError::input(
                "noise",
                format!(
                    "shape {:?}, the posterior's is {:?}",
                    noise.size(),
                    self.mean.size()
                ),
            ));
        }
        let noise = noise
            .to_device(self.mean.device())
            .to_kind(self.mean.kind());
        Ok(&self.mean + self.std() * noise)
    }

    /// A sample with the noise of diffusers'
    /// `sample(generator=torch.Generator().manual_seed(seed))`: standard normal noise
    /// drawn on the CPU after seeding libtorch's global generators with `seed` (which
    /// they keep afterwards).
    pub fn sample(&self, seed: u64) -> Result<Tensor> {
        tch::manual_seed(seed as i64);
        let noise = Tensor::f_randn(self.mean.size(), (self.mean.kind(), tch::Device::Cpu))?;
        self.sample_with_noise(&noise)
    }
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
        let mut vs = VarStore::new(device.to_tch());
        let model = Self::new(&cfg, vs.root())?;
        vs.set_kind(precision.kind());
        crate::weights::load_component(&vs, dir)?;
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

    /// Splits large inputs into overlapping spatial tiles (diffusers' `enable_tiling`);
    /// the options override the current tile sizes and overlaps.
    pub fn enable_tiling(&mut self, options: TilingOptions) -> Result<()> {
        let mut t = self.tiling;
        if let Some(h) = options.tile_sample_min_height {
            t.tile_sample_min_height = h;
        }
        if let Some(w) = options.tile_sample_min_width {
            t.tile_sample_min_width = w;
        }
        if let Some(f) = options.tile_overlap_factor_height {
            t.tile_overlap_factor_height = f;
        }
        if let Some(f) = options.tile_overlap_factor_width {
            t.tile_overlap_factor_width = f;
        }
        t.tile_latent_min_height = latent_tile(t.tile_sample_min_height, &self.cfg);
        t.tile_latent_min_width = latent_tile(t.tile_sample_min_width, &self.cfg);
        for (name, f) in [
            ("tile_overlap_factor_height", t.tile_overlap_factor_height),
            ("tile_overlap_factor_width", t.tile_overlap_factor_width),
        ] {
            if !(0.0..1.0).contains(&f) {
                return Err(WorldModelError::input(
                    name,
                    format!("{f}: must be in [0, 1)"),
                ));
            }
        }
        // The tile strides (overlap_*) of encode and decode must be positive.
        let strides = [
            (
                "tile_sample_min_height",
                t.tile_sample_min_height,
                t.tile_overlap_factor_height,
            ),
            (
                "tile_sample_min_width",
                t.tile_sample_min_width,
                t.tile_overlap_factor_width,
            ),
            (
                "tile_sample_min_height",
                t.tile_latent_min_height,
                t.tile_overlap_factor_height,
            ),
            (
                "tile_sample_min_width",
                t.tile_latent_min_width,
                t.tile_overlap_factor_width,
            ),
        ];
        for (name, size, factor) in strides {
            if tile_stride(size, factor) < 1 {
                return Err(WorldModelError::input(
                    name,
                    format!(
                        "tiles of {}x{} px ({}x{} latent) with overlaps {} / {} leave no stride: use larger tiles",
                        t.tile_sample_min_height,
                        t.tile_sample_min_width,
                        t.tile_latent_min_height,
                        t.tile_latent_min_width,
                        t.tile_overlap_factor_height,
                        t.tile_overlap_factor_width
                    ),
                ));
            }
        }
        self.tiling = t;
        self.use_tiling = true;
        Ok(())
    }

    /// Encodes/decodes whole frames (the default).
    pub fn disable_tiling(&mut self) {
        self.use_tiling = false;
    }

    /// The tiling parameters (used when tiling is enabled).
    pub fn tiling(&self) -> Tiling {
        self.tiling
    }

    /// Whether tiling is enabled.
    pub fn uses_tiling(&self) -> bool {
        self.use_tiling
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

    /// [`Self::decode`] with autograd on: gradients flow from the decoded
    /// video back into `latents` (and into the decoder's parameters when they
    /// are trainable; frozen otherwise).
    /// Training's flow loss decodes predicted latents through this.
    pub fn decode_with_grad(&self, latents: &Tensor) -> Result<Tensor> {
        check_rank5(
            latents,
            "latents",
            self.cfg.latent_channels,
            "latent_channels",
        )?;
        check_finite(latents, "latents")?;
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
        check_finite(video, "video")?;
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
        if self.use_tiling
            && (s[4] > self.tiling.tile_latent_min_width
                || s[3] > self.tiling.tile_latent_min_height)
        {
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
            let chunk = z.narrow(2, start, end - start);
            let chunk = match &self.post_quant_conv {
                Some(conv) => conv.forward(&chunk)?,
                None => chunk,
            };
            let (h, c) = self.decoder.forward(&chunk, cache.as_ref())?;
            cache = Some(c);
            parts.push(h);
        }
        Ok(Tensor::f_cat(&parts, 2)?)
    }

    /// diffusers' `tiled_encode`.
    fn tiled_encode(&self, x: &Tensor) -> Result<Tensor> {
        let t = &self.tiling;
        let geometry = TileGeometry {
            tile_h: t.tile_sample_min_height,
            tile_w: t.tile_sample_min_width,
            stride_h: tile_stride(t.tile_sample_min_height, t.tile_overlap_factor_height),
            stride_w: tile_stride(t.tile_sample_min_width, t.tile_overlap_factor_width),
            blend_h: (t.tile_latent_min_height as f64 * t.tile_overlap_factor_height) as i64,
            blend_w: (t.tile_latent_min_width as f64 * t.tile_overlap_factor_width) as i64,
            out_tile_h: t.tile_latent_min_height,
            out_tile_w: t.tile_latent_min_width,
        };
        tiled(x, &geometry, |tile| self.encode_frames(tile))
    }

    /// diffusers' `tiled_decode`.
    fn tiled_decode(&self, z: &Tensor) -> Result<Tensor> {
        let t = &self.tiling;
        let geometry = TileGeometry {
            tile_h: t.tile_latent_min_height,
            tile_w: t.tile_latent_min_width,
            stride_h: tile_stride(t.tile_latent_min_height, t.tile_overlap_factor_height),
            stride_w: tile_stride(t.tile_latent_min_width, t.tile_overlap_factor_width),
            blend_h: (t.tile_sample_min_height as f64 * t.tile_overlap_factor_height) as i64,
            blend_w: (t.tile_sample_min_width as f64 * t.tile_overlap_factor_width) as i64,
            out_tile_h: t.tile_sample_min_height,
            out_tile_w: t.tile_sample_min_width,
        };
        tiled(z, &geometry, |tile| self.decode_frames(tile))
    }
}

/// `int(size * (1 - overlap))`: the step between tile origins.
fn tile_stride(size: i64, overlap: f64) -> i64 {
    (size as f64 * (1.0 - overlap)) as i64
}

/// Tile sizes of the input and output side of a tiled encode or decode.
struct TileGeometry {
    /// Input tile size.
    tile_h: i64,
    tile_w: i64,
    /// Step between input tile origins.
    stride_h: i64,
    stride_w: i64,
    /// Output rows/columns blended with the previous tile.
    blend_h: i64,
    blend_w: i64,
    /// Nominal output tile size (the kept part is this minus the blend).
    out_tile_h: i64,
    out_tile_w: i64,
}

/// Runs `f` on overlapping tiles of `x [B, C, T, H, W]`, blends each output tile with
/// its upper and left neighbours (already blended, as diffusers modifies its tiles in
/// place), keeps the first `out_tile - blend` rows/columns of each and concatenates.
fn tiled(x: &Tensor, g: &TileGeometry, f: impl Fn(&Tensor) -> Result<Tensor>) -> Result<Tensor> {
    let s = x.size();
    let (height, width) = (s[3], s[4]);
    let mut rows: Vec<Vec<Tensor>> = Vec::new();
    let mut i = 0;
    while i < height {
        let mut row = Vec::new();
        let mut j = 0;
        while j < width {
            // [B, C, T, <= tile_h, <= tile_w]
            let tile =
                x.narrow(3, i, g.tile_h.min(height - i))
                    .narrow(4, j, g.tile_w.min(width - j));
            row.push(f(&tile)?);
            j += g.stride_w;
        }
        rows.push(row);
        i += g.stride_h;
    }
    let row_limit_h = g.out_tile_h - g.blend_h;
    let row_limit_w = g.out_tile_w - g.blend_w;
    let mut result_rows = Vec::with_capacity(rows.len());
    for i in 0..rows.len() {
        let mut result_row = Vec::with_capacity(rows[i].len());
        for j in 0..rows[i].len() {
            let mut tile = rows[i][j].shallow_clone();
            if i > 0 {
                tile = blend_v(&rows[i - 1][j], &tile, g.blend_h)?;
            }
            if j > 0 {
                tile = blend_h(&rows[i][j - 1], &tile, g.blend_w)?;
            }
            let ts = tile.size();
            result_row.push(tile.narrow(3, 0, row_limit_h.min(ts[3])).narrow(
                4,
                0,
                row_limit_w.min(ts[4]),
            ));
            rows[i][j] = tile;
        }
        result_rows.push(Tensor::f_cat(&result_row, 4)?);
    }
    Ok(Tensor::f_cat(&result_rows, 3)?)
}

/// Blends the last rows of `a` into the first rows of `b` along `dim`:
/// `b[y] = a[-e + y] * (1 - y / e) + b[y] * (y / e)` for `y < e`,
/// `e = min(a.len, b.len, extent)`; returns the blended copy of `b`.
fn blend(a: &Tensor, b: &Tensor, extent: i64, dim: i64) -> Result<Tensor> {
    let (la, lb) = (a.size()[dim as usize], b.size()[dim as usize]);
    let e = la.min(lb).min(extent);
    if e <= 0 {
        return Ok(b.shallow_clone());
    }
    let out = b.copy();
    for y in 0..e {
        let wb = y as f64 / e as f64;
        let row = a.narrow(dim, la - e + y, 1) * (1.0 - wb) + b.narrow(dim, y, 1) * wb;
        out.narrow(dim, y, 1).f_copy_(&row)?;
    }
    Ok(out)
}

/// diffusers' `blend_v` (height).
fn blend_v(a: &Tensor, b: &Tensor, extent: i64) -> Result<Tensor> {
    blend(a, b, extent, 3)
}

/// diffusers' `blend_h` (width).
fn blend_h(a: &Tensor, b: &Tensor, extent: i64) -> Result<Tensor> {
    blend(a, b, extent, 4)
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

fn check_finite(x: &Tensor, name: &str) -> Result<()> {
    let finite = x.f_isfinite()?.f_all()?.int64_value(&[]) != 0;
    if finite {
        Ok(())
    } else {
        Err(WorldModelError::input(
            name,
            "contains NaN or infinite values",
        ))
    }
}

/// Options of a VAE parity fixture (`meta.json` `options`).
#[derive(Debug, serde::Deserialize)]
struct FixtureOptions {
    #[serde(default)]
    tiling: Option<FixtureTiling>,
    #[serde(default)]
    slicing: bool,
    #[serde(default)]
    sample_seed: Option<u64>,
}

#[derive(Debug, serde::Deserialize)]
struct FixtureTiling {
    tile_sample_min_height: i64,
    tile_sample_min_width: i64,
    tile_overlap_factor_height: f64,
    tile_overlap_factor_width: f64,
}

/// The `"vae"` arm of [`crate::parity::run_fixture`]: loads `model_dir`, applies the
/// fixture's tiling/slicing and computes `latent_mean` (and `latent_sample`) from
/// `video`, `decoded` from `latents`.
pub(crate) fn parity_outputs(
    model_dir: &Path,
    meta: &serde_json::Value,
    meta_path: &Path,
    io: &FixtureIo,
) -> Result<Vec<(String, Tensor)>> {
    let options: FixtureOptions = match meta.get("options") {
        Some(o) => serde_json::from_value(o.clone()).map_err(|error| WorldModelError::Json {
            path: PathBuf::from(meta_path),
            error,
        })?,
        None => FixtureOptions {
            tiling: None,
            slicing: false,
            sample_seed: None,
        },
    };
    let mut vae = AutoencoderKLCogVideoX::load(model_dir, ComputeDevice::Cpu, Precision::F32)?;
    if let Some(t) = &options.tiling {
        vae.enable_tiling(TilingOptions {
            tile_sample_min_height: Some(t.tile_sample_min_height),
            tile_sample_min_width: Some(t.tile_sample_min_width),
            tile_overlap_factor_height: Some(t.tile_overlap_factor_height),
            tile_overlap_factor_width: Some(t.tile_overlap_factor_width),
        })?;
    }
    if options.slicing {
        vae.enable_slicing();
    }
    let mut out = Vec::new();
    if io.contains("video") {
        let posterior = vae.encode(io.get("video")?)?;
        if io.contains("latent_sample") {
            if let Some(seed) = options.sample_seed {
                out.push(("latent_sample".to_owned(), posterior.sample(seed)?));
            }
        }
        out.push(("latent_mean".to_owned(), posterior.mode()));
    }
    if io.contains("latents") {
        out.push(("decoded".to_owned(), vae.decode(io.get("latents")?)?));
    }
    Ok(out)
}

/// Re-initialises a VAE's convolutions as PyTorch does (`kaiming_uniform_(a=sqrt(5))`
/// for weights and the same bound for biases: uniform in `±1/sqrt(fan_in)`), from the
/// global seed; norm scales and shifts keep 1 and 0. For training from scratch.
pub fn init_like_pytorch(vs: &VarStore) {
    let vars = vs.variables();
    tch::no_grad(|| {
        let mut names: Vec<&String> = vars.keys().collect();
        names.sort();
        for name in names {
            let w = &vars[name];
            if w.dim() < 4 || !name.ends_with(".weight") {
                continue;
            }
            let fan_in: i64 = w.size()[1..].iter().product();
            let bound = 1.0 / (fan_in.max(1) as f64).sqrt();
            let _ = w.shallow_clone().uniform_(-bound, bound);
            if let Some(b) = vars.get(&format!("{}.bias", name.trim_end_matches(".weight"))) {
                let _ = b.shallow_clone().uniform_(-bound, bound);
            }
        }
    });
}

/// Turns an autoencoder trained on single frames into the same autoencoder
/// applied frame by frame: every causal convolution's temporal taps
/// (`[Cout, Cin, kt, kh, kw]`, `kt > 1`, the last tap the current frame) are
/// summed into the current frame's tap and the earlier taps zeroed. A single
/// frame sees all `kt` taps on copies of itself, so its output is unchanged;
/// a clip's frames then no longer mix in the convolutions (only the group
/// norms still pool over time). The start of clip training after image
/// training (3-D "inflation" of 2-D weights). Returns the number of weights changed.
pub fn inflate_image_weights(vs: &VarStore) -> usize {
    let vars = vs.variables();
    let mut changed = 0;
    tch::no_grad(|| {
        for (name, w) in &vars {
            if w.dim() != 5 || !name.ends_with(".weight") || w.size()[2] < 2 {
                continue;
            }
            let kt = w.size()[2];
            // [Cout, Cin, kt, kh, kw] -> [Cout, Cin, 1, kh, kw]
            let summed = w.sum_dim_intlist(2, true, w.kind());
            let mut dst = w.shallow_clone();
            let _ = dst.zero_();
            dst.narrow(2, kt - 1, 1).copy_(&summed);
            changed += 1;
        }
    });
    changed
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_batches_match_diffusers() {
        assert_eq!(frame_batches(1, 8), vec![(0, 1)]);
        assert_eq!(frame_batches(5, 8), vec![(0, 5)]);
        assert_eq!(frame_batches(9, 8), vec![(0, 9)]);
        assert_eq!(frame_batches(13, 8), vec![(0, 13)]);
        assert_eq!(frame_batches(16, 8), vec![(0, 8), (8, 16)]);
        assert_eq!(frame_batches(17, 8), vec![(0, 9), (9, 17)]);
        assert_eq!(frame_batches(49, 8).len(), 6);
        assert_eq!(frame_batches(49, 8)[0], (0, 9));
        assert_eq!(
            frame_batches(13, 2),
            vec![(0, 3), (3, 5), (5, 7), (7, 9), (9, 11), (11, 13)]
        );
        assert_eq!(frame_batches(1, 2), vec![(0, 1)]);
    }

    #[test]
    fn presets_validate() {
        for cfg in [
            VaeConfig::cogvideox_5b_i2v(),
            VaeConfig::cogvideox_2b(),
            VaeConfig::tiny(),
        ] {
            cfg.validate(Path::new("preset"))
                .unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(cfg.spatial_compression(), 8);
            assert_eq!(cfg.temporal_compress_level(), 2);
        }
        use crate::transformer::TransformerConfig;
        for (small, tf, space, time_levels) in [
            (VaeConfig::small(), TransformerConfig::small(), 4, 2),
            (VaeConfig::small_2x(), TransformerConfig::small_2x(), 2, 0),
            (
                VaeConfig::small_2x(),
                TransformerConfig::small_2x_wide(),
                2,
                0,
            ),
        ] {
            tf.validate(Path::new("transformer preset"))
                .unwrap_or_else(|e| panic!("{e}"));
            small
                .validate(Path::new("small"))
                .unwrap_or_else(|e| panic!("{e}"));
            assert_eq!(
                (small.spatial_compression(), small.temporal_compress_level()),
                (space, time_levels)
            );
            // The small transformer denoises the small VAE's latents (noisy ++ image).
            assert_eq!(
                (tf.in_channels, tf.out_channels()),
                (2 * small.latent_channels, small.latent_channels)
            );
            assert_eq!(
                (tf.sample_height, tf.sample_width),
                (
                    small.sample_height / small.spatial_compression(),
                    small.sample_width / small.spatial_compression()
                )
            );
            // Every token covers 8x8 pixels in both presets.
            assert_eq!(tf.patch_size * small.spatial_compression(), 8);
            // A token's noise and image values fit its width, so the
            // sampler can see all the noise it has to remove.
            assert!(tf.patch_size.pow(2) * tf.in_channels <= tf.inner_dim());
            // Its learned positions are sized for the VAE's latent frames.
            assert_eq!(
                tf.temporal_compression_ratio,
                small.temporal_compression_ratio as i64
            );
        }
        let t = Tiling::for_config(&VaeConfig::cogvideox_5b_i2v());
        assert_eq!(
            (t.tile_sample_min_height, t.tile_sample_min_width),
            (240, 360)
        );
        assert_eq!(
            (t.tile_latent_min_height, t.tile_latent_min_width),
            (30, 45)
        );
    }

    #[test]
    fn time_compression_beyond_the_resampling_blocks_is_refused() {
        let cfg = VaeConfig {
            temporal_compression_ratio: 4.0,
            ..VaeConfig::small_2x()
        };
        let e = cfg
            .validate(Path::new("vae/config.json"))
            .expect_err("4x time with one resampling block")
            .to_string();
        assert!(
            e.contains("temporal_compression_ratio") && e.contains("only 1 resamplers"),
            "{e}"
        );
    }

    #[test]
    fn config_parses_diffusers_json() {
        let json = r#"{"_class_name": "AutoencoderKLCogVideoX", "_diffusers_version": "0.30.0",
            "scaling_factor": 0.7, "block_out_channels": [128, 256, 256, 512]}"#;
        let cfg: VaeConfig = serde_json::from_str(json).unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(cfg, VaeConfig::cogvideox_5b_i2v());
    }
}
