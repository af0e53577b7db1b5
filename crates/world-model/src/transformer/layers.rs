//! The layers of `CogVideoXTransformer3DModel`, with diffusers' key names.

use super::config::TransformerConfig;
use super::positions::{apply_rotary, joint_sincos, Rotary};
use crate::cpu_linear::Linear;
use crate::error::{Result, WorldModelError};
use crate::lora::{LoraConfig, LoraLinear};
use bridgev2w_torch_ext::onednn::PostOp;
use tch::nn::{self, Module};
use tch::{Kind, Tensor};

/// `nn.LayerNorm(dim, eps, elementwise_affine)` (`weight`, `bias` when affine).
#[derive(Debug)]
pub struct LayerNorm {
    weight: Option<Tensor>,
    bias: Option<Tensor>,
    dim: i64,
    eps: f64,
}

impl LayerNorm {
    /// Under `p`.
    pub fn new(p: nn::Path, dim: i64, eps: f64, affine: bool) -> Self {
        let (weight, bias) = if affine {
            (
                Some(p.var("weight", &[dim], nn::Init::Const(1.0))),
                Some(p.var("bias", &[dim], nn::Init::Const(0.0))),
            )
        } else {
            (None, None)
        };
        Self {
            weight,
            bias,
            dim,
            eps,
        }
    }

    /// Normalises the last dimension.
    pub fn forward(&self, x: &Tensor) -> Tensor {
        x.layer_norm(
            [self.dim],
            self.weight.as_ref(),
            self.bias.as_ref(),
            self.eps,
            true,
        )
    }
}

/// A plain linear layer in diffusers' layout (`weight` `[out, in]`, `bias`).
fn linear(p: nn::Path, i: i64, o: i64, bias: bool) -> Linear {
    let bound = 1.0 / (i as f64).sqrt();
    Linear::new(nn::linear(
        p,
        i,
        o,
        nn::LinearConfig {
            ws_init: nn::Init::Uniform {
                lo: -bound,
                up: bound,
            },
            bs_init: bias.then_some(nn::Init::Uniform {
                lo: -bound,
                up: bound,
            }),
            bias,
        },
    ))
}

/// diffusers' `get_timestep_embedding` (f32): `[B, dim]`.
pub fn timestep_embedding(
    timesteps: &Tensor,
    dim: i64,
    flip_sin_to_cos: bool,
    shift: f64,
) -> Tensor {
    let device = timesteps.device();
    let half = dim / 2;
    let exponent =
        Tensor::arange(half, (Kind::Float, device)) * (-(10000f64.ln())) / (half as f64 - shift);
    let freqs = exponent.exp(); // [half]
    let args = timesteps.to_kind(Kind::Float).unsqueeze(1) * freqs.unsqueeze(0); // [B, half]
    let (sin, cos) = (args.sin(), args.cos());
    let emb = if flip_sin_to_cos {
        Tensor::cat(&[cos, sin], -1)
    } else {
        Tensor::cat(&[sin, cos], -1)
    };
    if dim % 2 == 1 {
        emb.pad([0, 1, 0, 0], "constant", 0.0)
    } else {
        emb
    }
}

/// `TimestepEmbedding`: `linear_1`, SiLU, `linear_2`.
#[derive(Debug)]
pub struct TimestepMlp {
    linear_1: Linear,
    linear_2: Linear,
}

impl TimestepMlp {
    /// `in_dim -> out_dim -> out_dim` under `p`.
    pub fn new(p: nn::Path, in_dim: i64, out_dim: i64) -> Self {
        Self {
            linear_1: linear(&p / "linear_1", in_dim, out_dim, true),
            linear_2: linear(&p / "linear_2", out_dim, out_dim, true),
        }
    }

    /// `[B, in] -> [B, out]`.
    pub fn forward(&self, x: &Tensor) -> Tensor {
        self.linear_2.forward(&self.linear_1.forward(x).silu())
    }
}

/// `CogVideoXPatchEmbed`: video latents to patch tokens, text embeddings
/// projected, positions added (sin-cos, or learned `pos_embedding`).
#[derive(Debug)]
pub struct PatchEmbed {
    proj_conv: Option<nn::Conv2D>,
    proj_linear: Option<Linear>,
    text_proj: Linear,
    learned_pos: Option<Tensor>,
    cfg: TransformerConfig,
    in_channels: i64,
}

impl PatchEmbed {
    /// Under `p` (`proj`, `text_proj`, `pos_embedding`), for latents of
    /// `in_channels` channels (the ControlNet branch builds its own).
    pub fn new(cfg: &TransformerConfig, p: nn::Path, in_channels: i64) -> Self {
        let d = cfg.inner_dim();
        let ps = cfg.patch_size;
        let (proj_conv, proj_linear) = match cfg.patch_size_t {
            None => (
                Some(nn::conv2d(
                    &p / "proj",
                    in_channels,
                    d,
                    ps,
                    nn::ConvConfig {
                        stride: ps,
                        bias: cfg.patch_bias,
                        ..Default::default()
                    },
                )),
                None,
            ),
            Some(pt) => (
                None,
                Some(linear(&p / "proj", in_channels * ps * ps * pt, d, true)),
            ),
        };
        let text_proj = linear(&p / "text_proj", cfg.text_embed_dim, d, true);
        let learned_pos = cfg.use_learned_positional_embeddings.then(|| {
            let (h, w) = (cfg.sample_height / ps, cfg.sample_width / ps);
            let n = cfg.max_text_seq_length + cfg.sample_latent_frames() * h * w;
            // A persistent buffer in diffusers (in the checkpoint, not a parameter).
            p.zeros_no_train("pos_embedding", &[1, n, d])
        });
        Self {
            proj_conv,
            proj_linear,
            text_proj,
            learned_pos,
            cfg: cfg.clone(),
            in_channels,
        }
    }

    /// Tokens `[B, L + N, D]` of text `[B, L, text_dim]` and video latents
    /// `[B, F, C, H, W]`.
    pub fn forward(&self, text: &Tensor, video: &Tensor) -> Result<Tensor> {
        let size = video.size();
        let [b, f, c, h, w] = size[..] else {
            return Err(WorldModelError::input(
                "hidden_states",
                format!("shape {size:?}: expected [B, F, C, H, W]"),
            ));
        };
        if c != self.in_channels {
            return Err(WorldModelError::input(
                "hidden_states",
                format!(
                    "{c} channels: this patch embedding expects {}",
                    self.in_channels
                ),
            ));
        }
        let ps = self.cfg.patch_size;
        if h % ps != 0 || w % ps != 0 {
            return Err(WorldModelError::input(
                "hidden_states",
                format!(
                    "latents of {h}x{w}: height and width must be multiples of the patch size {ps}"
                ),
            ));
        }
        let text = self.text_proj.forward(text); // [B, L, D]
        let tokens = match (&self.proj_conv, &self.proj_linear, self.cfg.patch_size_t) {
            (Some(conv), _, _) => {
                let x = conv.forward(&video.reshape([b * f, c, h, w])); // [B*F, D, h, w]
                let d = x.size()[1];
                x.view([b, f, d, h / ps, w / ps]) // [B, F, D, h, w]
                    .flatten(3, 4) // [B, F, D, h*w]
                    .transpose(2, 3) // [B, F, h*w, D]
                    .flatten(1, 2) // [B, F*h*w, D]
            }
            (_, Some(lin), Some(pt)) => {
                if f % pt != 0 {
                    return Err(WorldModelError::input(
                        "hidden_states",
                        format!("{f} latent frames: must be a multiple of patch_size_t {pt}"),
                    ));
                }
                let x = video
                    .permute([0, 1, 3, 4, 2]) // [B, F, H, W, C]
                    .reshape([b, f / pt, pt, h / ps, ps, w / ps, ps, c].as_slice()) // [B, F/pt, pt, h, ps, w, ps, C]
                    .permute([0, 1, 3, 5, 7, 2, 4, 6].as_slice()) // [B, F/pt, h, w, C, pt, ps, ps]
                    .flatten(4, 7) // [B, F/pt, h, w, C*pt*ps*ps]
                    .flatten(1, 3); // [B, F/pt*h*w, C*pt*ps*ps]
                lin.forward(&x)
            }
            _ => {
                return Err(WorldModelError::input(
                    "patch embedding",
                    "no projection configured",
                ))
            }
        };
        let embeds = Tensor::cat(&[&text, &tokens], 1); // [B, L + N, D]
        if !self.cfg.use_rotary_positional_embeddings || self.cfg.use_learned_positional_embeddings
        {
            // Positions are added (sin-cos, or learned at the training size).
            let (sh, sw) = (self.cfg.sample_height, self.cfg.sample_width);
            if self.learned_pos.is_some() && (sh != h || sw != w) {
                return Err(WorldModelError::input(
                    "hidden_states",
                    format!(
                        "latents of {h}x{w}: a learned positional embedding only supports the training size {sh}x{sw} (as diffusers)"
                    ),
                ));
            }
            if text.size()[1] != self.cfg.max_text_seq_length {
                return Err(WorldModelError::input(
                    "encoder_hidden_states",
                    format!(
                        "{} text tokens: positional embeddings need exactly max_text_seq_length = {}",
                        text.size()[1],
                        self.cfg.max_text_seq_length
                    ),
                ));
            }
            let pixel_frames = (f - 1) * self.cfg.temporal_compression_ratio + 1;
            let pos = match &self.learned_pos {
                Some(learned) if sh == h && sw == w && self.cfg.sample_frames == pixel_frames => {
                    learned.shallow_clone()
                }
                // Other sizes / frame counts: sin-cos positions, as diffusers does.
                _ => joint_sincos(&self.cfg, f, h / ps, w / ps, video.device()),
            };
            let kind = embeds.kind();
            return Ok(embeds + pos.to_kind(kind));
        }
        Ok(embeds)
    }
}

/// `CogVideoXLayerNormZero`: SiLU + `linear` to six modulations, shared `norm`.
#[derive(Debug)]
pub struct LayerNormZero {
    linear: Linear,
    norm: LayerNorm,
}

/// Output of [`LayerNormZero::forward`].
#[derive(Debug)]
pub struct Modulated {
    /// Modulated video tokens `[B, N, D]`.
    pub video: Tensor,
    /// Modulated text tokens `[B, L, D]`.
    pub text: Tensor,
    /// Video gate `[B, 1, D]`.
    pub gate: Tensor,
    /// Text gate `[B, 1, D]`.
    pub text_gate: Tensor,
}

impl LayerNormZero {
    fn new(cfg: &TransformerConfig, p: nn::Path) -> Self {
        let d = cfg.inner_dim();
        Self {
            linear: linear(&p / "linear", cfg.time_embed_dim, 6 * d, true),
            norm: LayerNorm::new(&p / "norm", d, cfg.norm_eps, cfg.norm_elementwise_affine),
        }
    }

    /// Shift, scale, gate, text shift, text scale, text gate: `[B, 1, D]`
    /// each, from `temb` `[B, time_embed_dim]`.
    fn modulation(&self, temb: &Tensor) -> Vec<Tensor> {
        // [B, 6D] -> 6 x [B, 1, D]
        self.linear
            .forward(&temb.silu())
            .chunk(6, 1)
            .iter()
            .map(|t| t.unsqueeze(1))
            .collect()
    }

    fn forward(&self, video: &Tensor, text: &Tensor, temb: &Tensor) -> Modulated {
        let m = self.modulation(temb);
        Modulated {
            video: self.norm.forward(video) * (&m[1] + 1.0) + &m[0],
            text: self.norm.forward(text) * (&m[4] + 1.0) + &m[3],
            gate: m[2].shallow_clone(),
            text_gate: m[5].shallow_clone(),
        }
    }

    /// The modulated video tokens and the video gate alone.
    fn forward_video(&self, video: &Tensor, temb: &Tensor) -> (Tensor, Tensor) {
        let m = self.modulation(temb);
        (
            self.norm.forward(video) * (&m[1] + 1.0) + &m[0],
            m[2].shallow_clone(),
        )
    }
}

/// Joint text-video self-attention with per-head q/k LayerNorms and RoPE on
/// the video tokens (`CogVideoXAttnProcessor2_0`).
#[derive(Debug)]
pub struct Attention {
    /// Query projection.
    pub to_q: LoraLinear,
    /// Key projection.
    pub to_k: LoraLinear,
    /// Value projection.
    pub to_v: LoraLinear,
    /// Output projection (`to_out.0`).
    pub to_out: LoraLinear,
    norm_q: LayerNorm,
    norm_k: LayerNorm,
    heads: i64,
}

impl Attention {
    fn new(cfg: &TransformerConfig, p: nn::Path) -> Self {
        let d = cfg.inner_dim();
        let hd = cfg.attention_head_dim;
        Self {
            to_q: LoraLinear::new(&p / "to_q", d, d, cfg.attention_bias),
            to_k: LoraLinear::new(&p / "to_k", d, d, cfg.attention_bias),
            to_v: LoraLinear::new(&p / "to_v", d, d, cfg.attention_bias),
            to_out: LoraLinear::new(&p / "to_out" / "0", d, d, true),
            norm_q: LayerNorm::new(&p / "norm_q", hd, 1e-6, true),
            norm_k: LayerNorm::new(&p / "norm_k", hd, 1e-6, true),
            heads: cfg.num_attention_heads,
        }
    }

    /// The four LoRA-capable projections with their key suffixes.
    pub fn projections_mut(&mut self) -> [(&'static str, &mut LoraLinear); 4] {
        [
            ("to_q", &mut self.to_q),
            ("to_k", &mut self.to_k),
            ("to_v", &mut self.to_v),
            ("to_out.0", &mut self.to_out),
        ]
    }

    /// `(video, text)` outputs for `video` `[B, N, D]`, `text` `[B, L, D]`.
    fn forward(&self, video: &Tensor, text: &Tensor, rotary: Option<&Rotary>) -> (Tensor, Tensor) {
        let l = text.size()[1];
        let x = Tensor::cat(&[text, video], 1); // [B, L + N, D]
        let s = x.size()[1];
        let q = self.heads(&self.to_q, Some(&self.norm_q), &x, l, rotary);
        let (k, v) = self.keys_values(&x, l, rotary);
        let out = self.to_out.forward(&attend(&q, &k, &v)); // [B, S, D]
        (out.narrow(1, l, s - l), out.narrow(1, 0, l))
    }

    /// [`Self::forward`]'s video output alone: the text tokens give keys
    /// and values, but no queries (their outputs are not computed).
    fn forward_video(&self, video: &Tensor, text: &Tensor, rotary: Option<&Rotary>) -> Tensor {
        let l = text.size()[1];
        let x = Tensor::cat(&[text, video], 1); // [B, L + N, D]
        let q = self.heads(&self.to_q, Some(&self.norm_q), video, 0, rotary);
        let (k, v) = self.keys_values(&x, l, rotary);
        self.to_out.forward(&attend(&q, &k, &v)) // [B, N, D]
    }

    /// Keys and values `[B, heads, S, hd]` of the tokens `x` `[B, S, D]`,
    /// whose first `text` are the text tokens.
    fn keys_values(&self, x: &Tensor, text: i64, rotary: Option<&Rotary>) -> (Tensor, Tensor) {
        (
            self.heads(&self.to_k, Some(&self.norm_k), x, text, rotary),
            self.heads(&self.to_v, None, x, text, None),
        )
    }

    /// The tokens `t` `[B, T, D]` through `proj`, split into heads, then
    /// normalised by `norm` and rotated by `rotary` after the first `text`
    /// tokens (RoPE turns the video tokens only): `[B, heads, T, hd]`.
    fn heads(
        &self,
        proj: &LoraLinear,
        norm: Option<&LayerNorm>,
        t: &Tensor,
        text: i64,
        rotary: Option<&Rotary>,
    ) -> Tensor {
        let y = proj.forward(t);
        let (b, n, d) = (y.size()[0], y.size()[1], y.size()[2]);
        // [B, T, D] -> [B, heads, T, hd]
        let h = y.view([b, n, self.heads, d / self.heads]).transpose(1, 2);
        let h = match norm {
            Some(norm) => norm.forward(&h),
            None => h,
        };
        match rotary {
            Some(rot) if text == 0 => apply_rotary(&h, rot),
            Some(rot) => {
                let video_part = apply_rotary(&h.narrow(2, text, n - text), rot);
                Tensor::cat(&[h.narrow(2, 0, text), video_part], 2)
            }
            None => h,
        }
    }
}

/// Softmax attention of queries `q` `[B, heads, T, hd]` over keys `k` and
/// values `v` `[B, heads, S, hd]`: `[B, T, heads * hd]`.
fn attend(q: &Tensor, k: &Tensor, v: &Tensor) -> Tensor {
    let s = q.size();
    let (b, heads, t, hd) = (s[0], s[1], s[2], s[3]);
    crate::cpu_attention::attention(q, k, v)
        .transpose(1, 2) // [B, T, heads, hd]
        .reshape([b, t, heads * hd]) // [B, T, D]
}

/// The tanh-GELU feed-forward (`ff.net.0.proj`, `ff.net.2`).
#[derive(Debug)]
pub struct FeedForward {
    proj: Linear,
    out: Linear,
}

impl FeedForward {
    fn new(cfg: &TransformerConfig, p: nn::Path) -> Self {
        let d = cfg.inner_dim();
        Self {
            proj: linear(&p / "net" / "0" / "proj", d, 4 * d, true),
            out: linear(&p / "net" / "2", 4 * d, d, true),
        }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        // The tanh GELU runs inside the first product where oneDNN runs it.
        self.out
            .forward(&self.proj.forward_then(x, PostOp::GeluTanh))
    }
}

/// `CogVideoXBlock`: gated attention and feed-forward over text and video tokens.
#[derive(Debug)]
pub struct CogVideoXBlock {
    norm1: LayerNormZero,
    /// The joint attention.
    pub attn1: Attention,
    norm2: LayerNormZero,
    ff: FeedForward,
}

impl CogVideoXBlock {
    /// Under `p` (e.g. `transformer_blocks.3`).
    pub fn new(cfg: &TransformerConfig, p: nn::Path) -> Self {
        Self {
            norm1: LayerNormZero::new(cfg, &p / "norm1"),
            attn1: Attention::new(cfg, &p / "attn1"),
            norm2: LayerNormZero::new(cfg, &p / "norm2"),
            ff: FeedForward::new(cfg, &p / "ff"),
        }
    }

    /// `(video [B, N, D], text [B, L, D])` after the block, with the
    /// timestep embedding `temb` `[B, time_embed_dim]`.
    pub fn forward(
        &self,
        video: &Tensor,
        text: &Tensor,
        temb: &Tensor,
        rotary: Option<&Rotary>,
    ) -> (Tensor, Tensor) {
        let l = text.size()[1];
        let m = self.norm1.forward(video, text, temb);
        let (attn_video, attn_text) = self.attn1.forward(&m.video, &m.text, rotary);
        let video = video + &m.gate * attn_video;
        let text = text + &m.text_gate * attn_text;
        let m = self.norm2.forward(&video, &text, temb);
        let ff = self.ff.forward(&Tensor::cat(&[&m.text, &m.video], 1)); // [B, L + N, D]
        let n = ff.size()[1] - l;
        let video = video + &m.gate * ff.narrow(1, l, n);
        let text = text + &m.text_gate * ff.narrow(1, 0, l);
        (video, text)
    }

    /// [`Self::forward`]'s video output alone, for a block whose text
    /// output nothing reads (the last): the text tokens still give keys and
    /// values, but their queries, attention outputs and feed-forward are
    /// skipped (at 226 text and 288 video tokens, 37% of the block's
    /// products). The same values up to the order of summation.
    pub fn forward_video(
        &self,
        video: &Tensor,
        text: &Tensor,
        temb: &Tensor,
        rotary: Option<&Rotary>,
    ) -> Tensor {
        let m = self.norm1.forward(video, text, temb);
        let attn_video = self.attn1.forward_video(&m.video, &m.text, rotary);
        let video = video + &m.gate * attn_video;
        let (modulated, gate) = self.norm2.forward_video(&video, temb);
        video + gate * self.ff.forward(&modulated)
    }

    /// Attaches LoRA adapters to `attn1.to_q/to_k/to_v/to_out.0`, their
    /// variables under `p` (the block's path in the adapters' store).
    pub fn attach_lora(&mut self, p: &nn::Path, cfg: LoraConfig) -> Result<()> {
        let attn = p / "attn1";
        for (name, layer) in self.attn1.projections_mut() {
            let lp = name.split('.').fold(attn.clone(), |acc, part| &acc / part);
            layer.attach_lora(lp, cfg)?;
        }
        Ok(())
    }
}

/// The output head: `norm_out` (AdaLayerNorm, shift then scale) and `proj_out`.
#[derive(Debug)]
pub struct OutputHead {
    norm_final: LayerNorm,
    norm_out_linear: Linear,
    norm_out_norm: LayerNorm,
    proj_out: Linear,
}

impl OutputHead {
    /// `norm_final`, `norm_out`, `proj_out` under the model root `p`.
    pub fn new(cfg: &TransformerConfig, p: &nn::Path) -> Self {
        let d = cfg.inner_dim();
        let per_token = match cfg.patch_size_t {
            None => cfg.patch_size * cfg.patch_size * cfg.out_channels(),
            Some(pt) => cfg.patch_size * cfg.patch_size * pt * cfg.out_channels(),
        };
        Self {
            norm_final: LayerNorm::new(
                p / "norm_final",
                d,
                cfg.norm_eps,
                cfg.norm_elementwise_affine,
            ),
            norm_out_linear: linear(p / "norm_out" / "linear", cfg.time_embed_dim, 2 * d, true),
            norm_out_norm: LayerNorm::new(
                p / "norm_out" / "norm",
                d,
                cfg.norm_eps,
                cfg.norm_elementwise_affine,
            ),
            proj_out: linear(p / "proj_out", d, per_token, true),
        }
    }

    /// `[B, N, D] -> [B, N, p*p*C_out]`.
    pub fn forward(&self, video: &Tensor, temb: &Tensor) -> Tensor {
        let x = self.norm_final.forward(video);
        let m = self.norm_out_linear.forward(&temb.silu()).chunk(2, 1); // shift, scale: [B, D]
        let x = self.norm_out_norm.forward(&x) * (m[1].unsqueeze(1) + 1.0) + m[0].unsqueeze(1);
        self.proj_out.forward(&x)
    }
}
