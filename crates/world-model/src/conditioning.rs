//! How the first frame's latent conditions an image-to-video backbone
//! (`model.image_conditioning`), a setting both the model and the folders
//! it is saved in record.

use crate::error::WorldModelError;
use tch::Tensor;

/// Where the first frame's latent goes in the `C` conditioning channels that an
/// image-to-video backbone concatenates to its noisy latents.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImageConditioning {
    /// Latent frame 0 only, the later frames zero (CogVideoX-I2V; the only
    /// choice for its pretrained weights).
    #[default]
    FirstFrame,
    /// Repeated in every latent frame, so that each token sees the image at
    /// its own place and copying the static scene is a local map. A measured
    /// deviation for backbones trained from scratch (the synthetic presets).
    EveryFrame,
}

crate::named_enum!(ImageConditioning, WorldModelError, WorldModelError::input, "image_conditioning", {
    FirstFrame => "first_frame",
    EveryFrame => "every_frame",
});

impl ImageConditioning {
    /// `[B, t, C, h, w]` conditioning latents from the image latent `z`
    /// `[B, 1, C, h, w]`.
    pub fn expand(self, z: &Tensor, t: i64) -> Tensor {
        let s = z.size();
        match self {
            Self::FirstFrame => {
                let pad = Tensor::zeros([s[0], t - 1, s[2], s[3], s[4]], (z.kind(), z.device()));
                Tensor::cat(&[z, &pad], 1) // [B, t, C, h, w]
            }
            Self::EveryFrame => z.expand([s[0], t, s[2], s[3], s[4]], false).contiguous(),
        }
    }
}
