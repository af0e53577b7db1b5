//! BridgeV2W's mask ControlNet branch (paper "ControlNet-Based Video
//! Generation"): the embodiment-mask video, encoded by the same VAE, is
//! concatenated on channels with the (zero-padded) first-frame image latents,
//! patch-embedded by the branch's own `patch_embed`, and run through `N`
//! trainable [`CogVideoXBlock`]s initialised as copies of the backbone's first
//! `N` blocks. After branch block `i`, a zero-initialised linear projection
//! (`out_projectors.{i}`) maps the branch's video tokens to a residual that is
//! added, times `conditioning_scale[i]`, to the backbone's video tokens after
//! backbone block `i`. With zero projections the model is exactly the backbone.
//!
//! Keys (relative to the branch's root, `controlnet.` in BridgeV2W weight
//! files): `patch_embed.{proj,text_proj}.*`, `transformer_blocks.{i}.*` (the
//! backbone's block key names), `out_projectors.{i}.{weight,bias}`.

use crate::error::{Result, WorldModelError};
use crate::transformer::layers::PatchEmbed;
use crate::transformer::{CogVideoXBlock, Rotary, TransformerConfig};
use tch::nn::{self, Module, VarStore};
use tch::Tensor;

/// The largest `conditioning_scale` magnitude accepted: a residual weight
/// far beyond 1 (the paper's) overflows the backbone's tokens.
pub const MAX_CONDITIONING_SCALE: f64 = 1000.0;

/// The branch's hyper-parameters.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct ControlNetConfig {
    /// Branch blocks `N` (copies of the backbone's first `N`).
    pub num_layers: usize,
    /// Per-block residual weights (length `N`; empty = all 1).
    pub conditioning_scale: Vec<f64>,
    /// Zero-initialised output projections (the ControlNet design). `false`
    /// is the paper's "w/o ControlNet" ablation: a branch whose projections
    /// start from the default (non-zero) initialisation.
    pub zero_init: bool,
}

impl Default for ControlNetConfig {
    fn default() -> Self {
        Self {
            num_layers: 8,
            conditioning_scale: Vec::new(),
            zero_init: true,
        }
    }
}

impl ControlNetConfig {
    /// A branch of `num_layers` blocks with unit weights.
    pub fn with_layers(num_layers: usize) -> Self {
        Self {
            num_layers,
            ..Self::default()
        }
    }

    /// The weight of block `i`'s residual.
    pub fn scale(&self, i: usize) -> f64 {
        self.conditioning_scale.get(i).copied().unwrap_or(1.0)
    }

    /// Checks the branch against the backbone it is attached to.
    pub fn validate(&self, backbone: &TransformerConfig) -> Result<()> {
        if self.num_layers == 0 || self.num_layers as i64 > backbone.num_layers {
            return Err(WorldModelError::input(
                "controlnet.num_layers",
                format!(
                    "{}: expected 1..={} (the backbone's blocks)",
                    self.num_layers, backbone.num_layers
                ),
            ));
        }
        if !self.conditioning_scale.is_empty() && self.conditioning_scale.len() != self.num_layers {
            return Err(WorldModelError::input(
                "controlnet.conditioning_scale",
                format!(
                    "{} weights for {} blocks (give one per block, or none for all 1)",
                    self.conditioning_scale.len(),
                    self.num_layers
                ),
            ));
        }
        if let Some(message) = self.scale_error() {
            return Err(WorldModelError::input(
                "controlnet.conditioning_scale",
                message,
            ));
        }
        Ok(())
    }

    /// A `conditioning_scale` weight that is not finite or beyond
    /// [`MAX_CONDITIONING_SCALE`] in magnitude: which one, its value and the
    /// range; `None` when all are fine.
    pub fn scale_error(&self) -> Option<String> {
        let (i, w) = self
            .conditioning_scale
            .iter()
            .enumerate()
            .find(|(_, w)| !(w.is_finite() && w.abs() <= MAX_CONDITIONING_SCALE))?;
        Some(format!(
            "weight {i} is {w}: expected a finite weight in [-{MAX_CONDITIONING_SCALE}, {MAX_CONDITIONING_SCALE}] (1 = the paper's)"
        ))
    }
}

/// The mask ControlNet branch.
#[derive(Debug)]
pub struct ControlNet {
    cfg: ControlNetConfig,
    /// The branch's patch embedding (`in_channels` of the backbone: mask
    /// latents ++ image latents).
    pub patch_embed: PatchEmbed,
    blocks: Vec<CogVideoXBlock>,
    out_projectors: Vec<crate::cpu_linear::Linear>,
}

impl ControlNet {
    /// Creates the branch's variables under `p` for a backbone of `backbone`'s
    /// configuration. Blocks and patch embedding start randomly initialised:
    /// call [`Self::copy_from_backbone`] to start from the backbone's weights.
    pub fn new(backbone: &TransformerConfig, cfg: &ControlNetConfig, p: &nn::Path) -> Result<Self> {
        cfg.validate(backbone)?;
        let d = backbone.inner_dim();
        let patch_embed = PatchEmbed::new(backbone, p / "patch_embed", backbone.in_channels);
        let blocks = (0..cfg.num_layers)
            .map(|i| CogVideoXBlock::new(backbone, p / "transformer_blocks" / i))
            .collect();
        let proj_cfg = if cfg.zero_init {
            nn::LinearConfig {
                ws_init: nn::Init::Const(0.0),
                bs_init: Some(nn::Init::Const(0.0)),
                bias: true,
            }
        } else {
            nn::LinearConfig::default()
        };
        let out_projectors = (0..cfg.num_layers)
            .map(|i| {
                crate::cpu_linear::Linear::new(nn::linear(p / "out_projectors" / i, d, d, proj_cfg))
            })
            .collect();
        Ok(Self {
            cfg: cfg.clone(),
            patch_embed,
            blocks,
            out_projectors,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &ControlNetConfig {
        &self.cfg
    }

    /// Copies the backbone's `patch_embed.*` and `transformer_blocks.{i}.*`
    /// (`i < N`) into the branch: `backbone` holds the backbone's variables at
    /// its root, `branch` the branch's under `prefix` (e.g. `controlnet`).
    /// Returns the number of tensors copied; every branch variable other
    /// than the output projections must have a backbone counterpart.
    pub fn copy_from_backbone(
        &self,
        backbone: &VarStore,
        branch: &VarStore,
        prefix: &str,
    ) -> Result<usize> {
        let src = backbone.variables();
        let lead = format!("{prefix}.");
        let mut copied = 0;
        for (name, dst) in branch.variables() {
            let Some(rest) = name.strip_prefix(&lead) else {
                continue;
            };
            if rest.starts_with("out_projectors.") || rest.contains(".lora_") {
                continue;
            }
            let s = src.get(rest).ok_or_else(|| {
                WorldModelError::input(
                    "controlnet",
                    format!("branch variable `{name}` has no backbone variable `{rest}`"),
                )
            })?;
            if s.size() != dst.size() {
                return Err(WorldModelError::input(
                    "controlnet",
                    format!(
                        "`{name}` {:?} but backbone `{rest}` {:?}",
                        dst.size(),
                        s.size()
                    ),
                ));
            }
            tch::no_grad(|| {
                let mut dst = dst.shallow_clone();
                dst.f_copy_(&s.to_kind(dst.kind()).to_device(dst.device()))
            })?;
            copied += 1;
        }
        Ok(copied)
    }

    /// The weighted residuals `[B, N_tokens, D]`, one per branch block, for
    /// `control` latents `[B, F, C_in, H, W]` (mask latents ++ image
    /// latents), text `[B, L, text_dim]`, and the backbone's timestep
    /// embedding `temb` `[B, time_embed_dim]`.
    pub fn residuals(
        &self,
        control: &Tensor,
        text: &Tensor,
        temb: &Tensor,
        rotary: Option<&Rotary>,
    ) -> Result<Vec<Tensor>> {
        let l = text.size().get(1).copied().unwrap_or(0);
        let tokens = self.patch_embed.forward(text, control)?; // [B, L + N, D]
        let n = tokens.size()[1] - l;
        let (mut video, mut text) = (tokens.narrow(1, l, n), tokens.narrow(1, 0, l));
        let mut out = Vec::with_capacity(self.blocks.len());
        let last = self.blocks.len().saturating_sub(1);
        for (i, (block, proj)) in self.blocks.iter().zip(&self.out_projectors).enumerate() {
            if i == last {
                // Nothing reads the last block's text output: not computed.
                let v = block.forward_video(&video, &text, temb, rotary);
                out.push(proj.forward(&v) * self.cfg.scale(i));
                break;
            }
            let (v, t) = block.forward(&video, &text, temb, rotary);
            out.push(proj.forward(&v) * self.cfg.scale(i));
            video = v;
            text = t;
        }
        Ok(out)
    }
}
