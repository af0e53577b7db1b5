//! `TransformerConfig`: diffusers' `transformer/config.json` of
//! `CogVideoXTransformer3DModel`, with named presets.

use crate::error::{Result, WorldModelError};
use bridgev2w_io::json::read_json;
use std::path::{Path, PathBuf};

/// The transformer's configuration. Unknown JSON fields (`_class_name`, ...)
/// are ignored; missing ones take diffusers' defaults (those of CogVideoX-2b).
#[derive(Debug, Clone, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(default)]
pub struct TransformerConfig {
    /// Attention heads.
    pub num_attention_heads: i64,
    /// Channels per head.
    pub attention_head_dim: i64,
    /// Input latent channels (32 for image-to-video: noisy ++ image latents).
    pub in_channels: i64,
    /// Output latent channels (defaults to 16).
    pub out_channels: Option<i64>,
    /// Cosine half first in the timestep embedding.
    pub flip_sin_to_cos: bool,
    /// Frequency shift of the timestep embedding.
    pub freq_shift: i64,
    /// Timestep embedding width.
    pub time_embed_dim: i64,
    /// "ofs" embedding width (CogVideoX 1.5 I2V), none otherwise.
    pub ofs_embed_dim: Option<i64>,
    /// Text embedding width (T5-XXL: 4096).
    pub text_embed_dim: i64,
    /// Transformer blocks.
    pub num_layers: i64,
    /// Dropout probability (training only).
    pub dropout: f64,
    /// Biases on to_q / to_k / to_v.
    pub attention_bias: bool,
    /// Latent width the model was trained at.
    pub sample_width: i64,
    /// Latent height the model was trained at.
    pub sample_height: i64,
    /// Pixel frames the model was trained at (latent frames = (F - 1) / 4 + 1).
    pub sample_frames: i64,
    /// Spatial patch size.
    pub patch_size: i64,
    /// Temporal patch size (CogVideoX 1.5), none for 1.0.
    pub patch_size_t: Option<i64>,
    /// The VAE's temporal compression.
    pub temporal_compression_ratio: i64,
    /// Text tokens.
    pub max_text_seq_length: i64,
    /// Feed-forward activation (only `gelu-approximate`).
    pub activation_fn: String,
    /// Timestep embedding activation (only `silu`).
    pub timestep_activation_fn: String,
    /// LayerNorm affine parameters.
    pub norm_elementwise_affine: bool,
    /// LayerNorm epsilon.
    pub norm_eps: f64,
    /// Spatial scale of the sin-cos positions.
    pub spatial_interpolation_scale: f64,
    /// Temporal scale of the sin-cos positions.
    pub temporal_interpolation_scale: f64,
    /// 3D rotary embeddings on the video tokens (5B models).
    pub use_rotary_positional_embeddings: bool,
    /// A learned positional embedding (5B-I2V).
    pub use_learned_positional_embeddings: bool,
    /// Bias of the patch projection.
    pub patch_bias: bool,
}

impl Default for TransformerConfig {
    fn default() -> Self {
        Self::cogvideox_2b()
    }
}

impl TransformerConfig {
    /// THUDM/CogVideoX-2b: 30 layers of 30 heads x 64, sin-cos positions.
    pub fn cogvideox_2b() -> Self {
        Self {
            num_attention_heads: 30,
            attention_head_dim: 64,
            in_channels: 16,
            out_channels: Some(16),
            flip_sin_to_cos: true,
            freq_shift: 0,
            time_embed_dim: 512,
            ofs_embed_dim: None,
            text_embed_dim: 4096,
            num_layers: 30,
            dropout: 0.0,
            attention_bias: true,
            sample_width: 90,
            sample_height: 60,
            sample_frames: 49,
            patch_size: 2,
            patch_size_t: None,
            temporal_compression_ratio: 4,
            max_text_seq_length: 226,
            activation_fn: "gelu-approximate".into(),
            timestep_activation_fn: "silu".into(),
            norm_elementwise_affine: true,
            norm_eps: 1e-5,
            spatial_interpolation_scale: 1.875,
            temporal_interpolation_scale: 1.0,
            use_rotary_positional_embeddings: false,
            use_learned_positional_embeddings: false,
            patch_bias: true,
        }
    }

    /// THUDM/CogVideoX-5b-I2V: 42 layers of 48 heads x 64, image latents
    /// concatenated (in_channels 32), 3D RoPE and a learned positional embedding.
    pub fn cogvideox_5b_i2v() -> Self {
        Self {
            num_attention_heads: 48,
            in_channels: 32,
            num_layers: 42,
            use_rotary_positional_embeddings: true,
            use_learned_positional_embeddings: true,
            ..Self::cogvideox_2b()
        }
    }

    /// A test-size image-to-video model in the 5B-I2V style (RoPE + learned
    /// positions): 2 layers of 2 heads x 16, latents 8x12 of 4 channels.
    pub fn tiny() -> Self {
        Self {
            num_attention_heads: 2,
            attention_head_dim: 16,
            in_channels: 8,
            out_channels: Some(4),
            time_embed_dim: 32,
            text_embed_dim: 24,
            num_layers: 2,
            sample_width: 12,
            sample_height: 8,
            sample_frames: 9,
            max_text_seq_length: 8,
            use_rotary_positional_embeddings: true,
            use_learned_positional_embeddings: true,
            ..Self::cogvideox_2b()
        }
    }

    /// The CPU-trainable model of the synthetic proof run (`VaeConfig::small`
    /// latents: 16 channels, 4x spatial compression): 4 layers of 4 heads x 32
    /// on 64x96 clips of 9 frames (latents 3x16x24, 288 tokens).
    pub fn small() -> Self {
        Self {
            num_attention_heads: 4,
            attention_head_dim: 32,
            in_channels: 32,
            out_channels: Some(16),
            time_embed_dim: 128,
            text_embed_dim: 24,
            num_layers: 4,
            sample_width: 24,
            sample_height: 16,
            sample_frames: 9,
            max_text_seq_length: 8,
            use_rotary_positional_embeddings: true,
            use_learned_positional_embeddings: true,
            ..Self::cogvideox_2b()
        }
    }

    /// The transformer of [`crate::vae::VaeConfig::small_2x`]'s latents
    /// (4 channels, 48x32 at 96x64 pixels, one latent frame per frame):
    /// [`TransformerConfig::small`] with patches of 4x4 latent pixels, so a
    /// token covers 8x8 pixels (96 tokens a frame, 864 for 9 frames) and
    /// holds 64 noise + 64 image values in its 128 dimensions.
    pub fn small_2x() -> Self {
        Self {
            patch_size: 4,
            in_channels: 8,
            out_channels: Some(4),
            temporal_compression_ratio: 1,
            sample_width: 48,
            sample_height: 32,
            ..Self::small()
        }
    }

    /// [`Self::small_2x`] twice as wide: 8 heads of 32 (256), for CPU runs
    /// where width buys more per second than steps do (`docs/results.md`,
    /// section `levers`).
    pub fn small_2x_wide() -> Self {
        Self {
            num_attention_heads: 8,
            time_embed_dim: 256,
            ..Self::small_2x()
        }
    }

    /// A preset by name: `cogvideox-5b-i2v`, `cogvideox-2b`, `small`,
    /// `small2x`, `small2x-wide` or `tiny`.
    pub fn preset(name: &str) -> Result<Self> {
        match name {
            "cogvideox-5b-i2v" | "cogvideox_5b_i2v" => Ok(Self::cogvideox_5b_i2v()),
            "cogvideox-2b" | "cogvideox_2b" => Ok(Self::cogvideox_2b()),
            "tiny" => Ok(Self::tiny()),
            "small" => Ok(Self::small()),
            "small2x" => Ok(Self::small_2x()),
            "small2x-wide" => Ok(Self::small_2x_wide()),
            other => Err(WorldModelError::config(
                PathBuf::from("<preset>"),
                "name",
                format!("unknown transformer preset `{other}`: expected cogvideox-5b-i2v, cogvideox-2b, small, small2x, small2x-wide or tiny"),
            )),
        }
    }

    /// Reads and validates a diffusers `config.json`.
    pub fn from_file(path: &Path) -> Result<Self> {
        let cfg: Self = read_json(path)?;
        cfg.validate(path)?;
        Ok(cfg)
    }

    /// Heads x head width.
    pub fn inner_dim(&self) -> i64 {
        self.num_attention_heads * self.attention_head_dim
    }

    /// Output latent channels.
    pub fn out_channels(&self) -> i64 {
        self.out_channels.unwrap_or(16)
    }

    /// Latent frames the config's `sample_frames` correspond to.
    pub fn sample_latent_frames(&self) -> i64 {
        (self.sample_frames - 1) / self.temporal_compression_ratio + 1
    }

    /// Checks the fields this implementation relies on; `source` names the
    /// config in errors.
    pub fn validate(&self, source: &Path) -> Result<()> {
        let bad =
            |field: &str, message: String| Err(WorldModelError::config(source, field, message));
        let positive = [
            ("num_attention_heads", self.num_attention_heads),
            ("attention_head_dim", self.attention_head_dim),
            ("in_channels", self.in_channels),
            ("time_embed_dim", self.time_embed_dim),
            ("text_embed_dim", self.text_embed_dim),
            ("num_layers", self.num_layers),
            ("sample_width", self.sample_width),
            ("sample_height", self.sample_height),
            ("sample_frames", self.sample_frames),
            ("patch_size", self.patch_size),
            (
                "temporal_compression_ratio",
                self.temporal_compression_ratio,
            ),
            ("max_text_seq_length", self.max_text_seq_length),
        ];
        for (field, v) in positive {
            if v <= 0 {
                return bad(field, format!("{v}: expected a positive integer"));
            }
        }
        // Upper bounds, checked before anything is allocated: far above every
        // CogVideoX release (5B: 48 heads x 64, 42 layers, 60x90x49 samples),
        // far below what would exhaust memory or overflow a tensor's size.
        let bounded = [
            ("num_attention_heads", self.num_attention_heads, 1024),
            ("attention_head_dim", self.attention_head_dim, 1024),
            ("in_channels", self.in_channels, 4096),
            ("out_channels", self.out_channels.unwrap_or(1), 4096),
            ("time_embed_dim", self.time_embed_dim, 65_536),
            ("text_embed_dim", self.text_embed_dim, 65_536),
            ("num_layers", self.num_layers, 1024),
            ("sample_width", self.sample_width, 16_384),
            ("sample_height", self.sample_height, 16_384),
            ("sample_frames", self.sample_frames, 16_384),
            ("patch_size", self.patch_size, 64),
            ("patch_size_t", self.patch_size_t.unwrap_or(1), 64),
            (
                "temporal_compression_ratio",
                self.temporal_compression_ratio,
                64,
            ),
            ("max_text_seq_length", self.max_text_seq_length, 65_536),
        ];
        for (field, v, max) in bounded {
            if v > max {
                return bad(
                    field,
                    format!("{v}: at most {max} is supported (a corrupt config?)"),
                );
            }
        }
        if self.inner_dim() > 65_536 {
            return bad(
                "attention_head_dim",
                format!(
                    "{} heads x {} = {} dims: at most 65536 are supported (a corrupt config?)",
                    self.num_attention_heads,
                    self.attention_head_dim,
                    self.inner_dim()
                ),
            );
        }
        if self.out_channels.is_some_and(|c| c <= 0) {
            return bad(
                "out_channels",
                format!("{:?}: expected a positive integer", self.out_channels),
            );
        }
        if self.activation_fn != "gelu-approximate" {
            return bad(
                "activation_fn",
                format!(
                    "`{}`: only `gelu-approximate` is supported",
                    self.activation_fn
                ),
            );
        }
        if self.timestep_activation_fn != "silu" {
            return bad(
                "timestep_activation_fn",
                format!(
                    "`{}`: only `silu` is supported",
                    self.timestep_activation_fn
                ),
            );
        }
        if !self.use_rotary_positional_embeddings && self.use_learned_positional_embeddings {
            return bad(
                "use_learned_positional_embeddings",
                "true without rotary embeddings: no CogVideoX model has this combination".into(),
            );
        }
        if !self.use_rotary_positional_embeddings && self.inner_dim() % 4 != 0 {
            return bad(
                "num_attention_heads",
                format!(
                    "inner dim {} must be divisible by 4 for sin-cos positions",
                    self.inner_dim()
                ),
            );
        }
        if self.use_rotary_positional_embeddings && self.attention_head_dim % 8 != 0 {
            return bad(
                "attention_head_dim",
                format!(
                    "{}: must be divisible by 8 for 3D rotary embeddings",
                    self.attention_head_dim
                ),
            );
        }
        if self.patch_size_t.is_some_and(|p| p <= 0) {
            return bad(
                "patch_size_t",
                format!("{:?}: expected a positive integer", self.patch_size_t),
            );
        }
        if !(self.norm_eps > 0.0 && self.norm_eps.is_finite()) {
            return bad(
                "norm_eps",
                format!("{}: expected a positive number", self.norm_eps),
            );
        }
        Ok(())
    }
}
