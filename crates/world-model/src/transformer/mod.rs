//! The CogVideoX diffusion transformer: diffusers' `CogVideoXTransformer3DModel`
//! (0.42.1), numerically identical in f32 and loading `transformer/`
//! checkpoints (single file or shards) unchanged.
//!
//! Latents `[B, F, C, H, W]` (for image-to-video, `C = 32`: the noisy latents
//! and the first-frame image latents concatenated) become `F * H/p * W/p`
//! patch tokens, joined by the projected text tokens; every
//! [`CogVideoXBlock`] attends over text and video jointly (RoPE on video
//! tokens for 5B models) with adaptive LayerNorm modulation from the
//! timestep embedding; the head predicts `[B, F, C_out, H, W]`.
//!
//! The forward pass is split for the ControlNet branch: [`CogVideoXTransformer3DModel::embed`],
//! the [`CogVideoXTransformer3DModel::blocks`], [`CogVideoXTransformer3DModel::finish`],
//! and [`CogVideoXTransformer3DModel::forward_with_residuals`] which adds a
//! residual to the video tokens after each block. Dropout is not applied
//! (CogVideoX uses none).

pub mod config;
pub mod layers;
pub mod positions;

pub use config::TransformerConfig;
pub use layers::{CogVideoXBlock, PatchEmbed};
pub use positions::{rotary_for_latents, Rotary};

use crate::device::{ComputeDevice, Precision};
use crate::error::{Result, WorldModelError};
use crate::lora::LoraConfig;
use crate::weights::{load_component, parameter_count};
use layers::{timestep_embedding, OutputHead, TimestepMlp};
use std::path::Path;
use tch::nn::{self, VarStore};
use tch::{Kind, Tensor};

/// The embedded inputs: what every block receives.
#[derive(Debug)]
pub struct Embedded {
    /// Video tokens `[B, N, D]`.
    pub video: Tensor,
    /// Text tokens `[B, L, D]`.
    pub text: Tensor,
    /// Timestep (+ ofs) embedding `[B, time_embed_dim]`.
    pub temb: Tensor,
    /// `(B, F, H, W)` of the input latents.
    pub latent_shape: (i64, i64, i64, i64),
}

/// `CogVideoXTransformer3DModel`.
#[derive(Debug)]
pub struct CogVideoXTransformer3DModel {
    cfg: TransformerConfig,
    /// The patch embedding (`patch_embed`).
    pub patch_embed: PatchEmbed,
    time_embedding: TimestepMlp,
    ofs_embedding: Option<TimestepMlp>,
    blocks: Vec<CogVideoXBlock>,
    head: OutputHead,
}

impl CogVideoXTransformer3DModel {
    /// Creates the variables under `p` (the model root: keys `patch_embed.*`,
    /// `transformer_blocks.{i}.*`, ...).
    pub fn new(cfg: &TransformerConfig, p: &nn::Path) -> Result<Self> {
        cfg.validate(Path::new("<transformer config>"))?;
        let patch_embed = PatchEmbed::new(cfg, p / "patch_embed", cfg.in_channels);
        let time_embedding =
            TimestepMlp::new(p / "time_embedding", cfg.inner_dim(), cfg.time_embed_dim);
        let ofs_embedding = cfg
            .ofs_embed_dim
            .map(|d| TimestepMlp::new(p / "ofs_embedding", d, d));
        let blocks = (0..cfg.num_layers)
            .map(|i| CogVideoXBlock::new(cfg, p / "transformer_blocks" / i))
            .collect();
        let head = OutputHead::new(cfg, p);
        Ok(Self {
            cfg: cfg.clone(),
            patch_embed,
            time_embedding,
            ofs_embedding,
            blocks,
            head,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &TransformerConfig {
        &self.cfg
    }

    /// The blocks, in order.
    pub fn blocks(&self) -> &[CogVideoXBlock] {
        &self.blocks
    }

    /// The timestep (+ ofs) embedding `[B, time_embed_dim]` of `timestep` `[B]`.
    pub fn time_embed(
        &self,
        timestep: &Tensor,
        ofs: Option<&Tensor>,
        kind: Kind,
    ) -> Result<Tensor> {
        let t = timestep_embedding(
            timestep,
            self.cfg.inner_dim(),
            self.cfg.flip_sin_to_cos,
            self.cfg.freq_shift as f64,
        )
        .to_kind(kind);
        let mut emb = self.time_embedding.forward(&t);
        if let (Some(mlp), Some(d)) = (&self.ofs_embedding, self.cfg.ofs_embed_dim) {
            let ofs = ofs.ok_or_else(|| {
                WorldModelError::input(
                    "ofs",
                    "this model has an ofs embedding: pass the ofs value (2.0 in the I2V pipeline)",
                )
            })?;
            let o =
                timestep_embedding(ofs, d, self.cfg.flip_sin_to_cos, self.cfg.freq_shift as f64)
                    .to_kind(kind);
            emb = &emb + mlp.forward(&o);
        }
        Ok(emb)
    }

    /// Embeds latents `[B, F, C, H, W]`, text `[B, L, text_dim]` and timesteps `[B]`.
    pub fn embed(
        &self,
        hidden_states: &Tensor,
        encoder_hidden_states: &Tensor,
        timestep: &Tensor,
        ofs: Option<&Tensor>,
    ) -> Result<Embedded> {
        let size = hidden_states.size();
        let [b, f, _c, h, w] = size[..] else {
            return Err(WorldModelError::input(
                "hidden_states",
                format!("shape {size:?}: expected [B, F, C, H, W]"),
            ));
        };
        let es = encoder_hidden_states.size();
        if es.len() != 3 || es[0] != b || es[2] != self.cfg.text_embed_dim {
            return Err(WorldModelError::input(
                "encoder_hidden_states",
                format!(
                    "shape {es:?}: expected [{b}, L, {}]",
                    self.cfg.text_embed_dim
                ),
            ));
        }
        if timestep.size() != [b] {
            return Err(WorldModelError::input(
                "timestep",
                format!("shape {:?}: expected [{b}]", timestep.size()),
            ));
        }
        let temb = self.time_embed(timestep, ofs, hidden_states.kind())?;
        let tokens = self
            .patch_embed
            .forward(encoder_hidden_states, hidden_states)?; // [B, L + N, D]
        let l = es[1];
        let n = tokens.size()[1] - l;
        Ok(Embedded {
            video: tokens.narrow(1, l, n),
            text: tokens.narrow(1, 0, l),
            temb,
            latent_shape: (b, f, h, w),
        })
    }

    /// The head and unpatchify: `[B, F, C_out, H, W]` from the final video tokens.
    pub fn finish(&self, emb: &Embedded, video: &Tensor) -> Tensor {
        let (b, f, h, w) = emb.latent_shape;
        let p = self.cfg.patch_size;
        let x = self.head.forward(video, &emb.temb); // [B, N, per-token]
        match self.cfg.patch_size_t {
            None => x
                .reshape([b, f, h / p, w / p, -1, p, p].as_slice()) // [B, F, h, w, C, p, p]
                .permute([0, 1, 4, 2, 5, 3, 6].as_slice()) // [B, F, C, h, p, w, p]
                .flatten(5, 6) // [B, F, C, h, p, W]
                .flatten(3, 4), // [B, F, C, H, W]
            Some(pt) => x
                .reshape([b, (f + pt - 1) / pt, h / p, w / p, -1, pt, p, p].as_slice()) // [B, F/pt, h, w, C, pt, p, p]
                .permute([0, 1, 5, 4, 2, 6, 3, 7].as_slice()) // [B, F/pt, pt, C, h, p, w, p]
                .flatten(6, 7) // [..., h, p, W]
                .flatten(4, 5) // [B, F/pt, pt, C, H, W]
                .flatten(1, 2), // [B, F, C, H, W]
        }
    }

    /// The rotary embedding for latents of this shape (the pipeline's), if the
    /// model uses RoPE.
    pub fn rotary_for(&self, hidden_states: &Tensor) -> Result<Option<Rotary>> {
        let s = hidden_states.size();
        if s.len() != 5 {
            return Err(WorldModelError::input(
                "hidden_states",
                format!("shape {s:?}: expected [B, F, C, H, W]"),
            ));
        }
        Ok(
            rotary_for_latents(&self.cfg, s[1], s[3], s[4], hidden_states.device())?
                .map(|r| r.to(hidden_states.device(), Kind::Float)),
        )
    }

    /// The predicted `[B, F, C_out, H, W]` (velocity for v-prediction models).
    /// `rotary`: the pipeline's rotary embedding (see [`Self::rotary_for`]);
    /// required for RoPE models.
    pub fn forward(
        &self,
        hidden_states: &Tensor,
        encoder_hidden_states: &Tensor,
        timestep: &Tensor,
        rotary: Option<&Rotary>,
        ofs: Option<&Tensor>,
    ) -> Result<Tensor> {
        self.forward_with_residuals(
            hidden_states,
            encoder_hidden_states,
            timestep,
            rotary,
            ofs,
            &mut |_, _| None,
        )
    }

    /// As [`Self::forward`], adding `residual(i, video)` (when `Some`,
    /// `[B, N, D]`) to the video tokens after block `i`: the ControlNet
    /// injection point.
    pub fn forward_with_residuals(
        &self,
        hidden_states: &Tensor,
        encoder_hidden_states: &Tensor,
        timestep: &Tensor,
        rotary: Option<&Rotary>,
        ofs: Option<&Tensor>,
        residual: &mut dyn FnMut(usize, &Tensor) -> Option<Tensor>,
    ) -> Result<Tensor> {
        let emb =
            self.embed_checked(hidden_states, encoder_hidden_states, timestep, rotary, ofs)?;
        let (mut video, mut text) = (emb.video.shallow_clone(), emb.text.shallow_clone());
        for i in 0..self.blocks.len() {
            let (v, t) = self.run_block(i, &video, &text, &emb.temb, rotary);
            video = match residual(i, &v) {
                Some(r) => v + r,
                None => v,
            };
            text = t;
        }
        Ok(self.finish(&emb, &video))
    }

    /// Block `i`'s `(video, text)` outputs; the last block's text output,
    /// which nothing reads, is not computed (an empty tensor stands for
    /// it; see [`CogVideoXBlock::forward_video`]).
    fn run_block(
        &self,
        i: usize,
        video: &Tensor,
        text: &Tensor,
        temb: &Tensor,
        rotary: Option<&Rotary>,
    ) -> (Tensor, Tensor) {
        let block = &self.blocks[i];
        if i + 1 == self.blocks.len() {
            (
                block.forward_video(video, text, temb, rotary),
                Tensor::new(),
            )
        } else {
            block.forward(video, text, temb, rotary)
        }
    }

    /// [`Self::embed`] after checking the rotary embedding: required for
    /// RoPE models, one position per video token.
    fn embed_checked(
        &self,
        hidden_states: &Tensor,
        encoder_hidden_states: &Tensor,
        timestep: &Tensor,
        rotary: Option<&Rotary>,
        ofs: Option<&Tensor>,
    ) -> Result<Embedded> {
        if self.cfg.use_rotary_positional_embeddings && rotary.is_none() {
            return Err(WorldModelError::input(
                "image_rotary_emb",
                "this model uses rotary embeddings: pass them (rotary_for computes the pipeline's)",
            ));
        }
        let emb = self.embed(hidden_states, encoder_hidden_states, timestep, ofs)?;
        if let Some(r) = rotary {
            if r.tokens() != emb.video.size()[1] {
                return Err(WorldModelError::input(
                    "image_rotary_emb",
                    format!(
                        "{} positions for {} video tokens",
                        r.tokens(),
                        emb.video.size()[1]
                    ),
                ));
            }
        }
        Ok(emb)
    }

    /// Per-block gradient checkpointing: [`Self::forward_with_residuals`]
    /// with `residuals[i]` (when `Some`) added after block `i`, but the
    /// blocks run without recording autograd graphs; only each block's
    /// inputs are kept. Returns the output `[B, F, C_out, H, W]` as a leaf
    /// that requires grad, and the record that
    /// [`CheckpointedForward::backward`] replays block by block (from the
    /// last) once the loss's backward pass has filled that leaf's gradient.
    /// Gradients reach the same variables as with the plain forward: the
    /// blocks' (LoRA adapters), the embeddings', the head's, and through
    /// `residuals` whatever produced them (the ControlNet branch).
    pub fn forward_checkpointed(
        &self,
        hidden_states: &Tensor,
        encoder_hidden_states: &Tensor,
        timestep: &Tensor,
        rotary: Option<&Rotary>,
        ofs: Option<&Tensor>,
        residuals: Vec<Option<Tensor>>,
    ) -> Result<(Tensor, CheckpointedForward)> {
        if residuals.len() > self.blocks.len() {
            return Err(WorldModelError::input(
                "residuals",
                format!(
                    "{} residuals for {} blocks",
                    residuals.len(),
                    self.blocks.len()
                ),
            ));
        }
        let mut block_inputs = Vec::with_capacity(self.blocks.len());
        let (output, final_video) = tch::no_grad(|| -> Result<(Tensor, Tensor)> {
            let emb =
                self.embed_checked(hidden_states, encoder_hidden_states, timestep, rotary, ofs)?;
            let (mut video, mut text) = (emb.video.shallow_clone(), emb.text.shallow_clone());
            for i in 0..self.blocks.len() {
                let (v, t) = self.run_block(i, &video, &text, &emb.temb, rotary);
                block_inputs.push((video, text));
                video = match residuals.get(i) {
                    Some(Some(r)) => v + r.detach(),
                    _ => v,
                };
                text = t;
            }
            Ok((self.finish(&emb, &video), video))
        })?;
        let output = output.detach().set_requires_grad(true);
        let record = CheckpointedForward {
            hidden_states: hidden_states.shallow_clone(),
            encoder_hidden_states: encoder_hidden_states.shallow_clone(),
            timestep: timestep.shallow_clone(),
            ofs: ofs.map(Tensor::shallow_clone),
            rotary: rotary.map(Rotary::shallow_clone),
            block_inputs,
            final_video,
            residuals,
            output: output.shallow_clone(),
        };
        Ok((output, record))
    }

    /// Attaches LoRA adapters (rank, alpha) to every block's attention
    /// projections, their variables under `p` with PEFT key names
    /// (`transformer_blocks.{i}.attn1.to_q.lora_A.weight`, ...).
    pub fn attach_lora(&mut self, p: &nn::Path, cfg: LoraConfig) -> Result<()> {
        for (i, block) in self.blocks.iter_mut().enumerate() {
            block.attach_lora(&(p / "transformer_blocks" / i), cfg)?;
        }
        Ok(())
    }

    /// Merges (or unmerges) every LoRA adapter into its base weight.
    pub fn set_lora_merged(&mut self, merged: bool) {
        for block in &mut self.blocks {
            for (_, layer) in block.attn1.projections_mut() {
                if merged {
                    layer.merge();
                } else {
                    layer.unmerge();
                }
            }
        }
    }
}

/// A transformer with its own variable store, loaded from a diffusers folder.
#[derive(Debug)]
pub struct LoadedTransformer {
    /// The variables (frozen after loading).
    pub vs: VarStore,
    /// The model.
    pub model: CogVideoXTransformer3DModel,
}

impl LoadedTransformer {
    /// Random weights for `cfg` on `device` in `precision`.
    pub fn random(
        cfg: &TransformerConfig,
        device: ComputeDevice,
        precision: Precision,
    ) -> Result<Self> {
        let device = device.check_available()?.to_tch();
        let mut vs = VarStore::new(tch::Device::Cpu);
        let model = CogVideoXTransformer3DModel::new(cfg, &vs.root())?;
        if precision == Precision::Bf16 {
            vs.bfloat16();
        }
        crate::device::move_to_device(&mut vs, device);
        Ok(Self { vs, model })
    }

    /// Loads `dir/config.json` and the weights (strict key match).
    pub fn load(dir: &Path, device: ComputeDevice, precision: Precision) -> Result<Self> {
        let cfg = TransformerConfig::from_file(&dir.join("config.json"))?;
        let device = device.check_available()?;
        // Missing weights are named before the model is allocated.
        crate::weights::resolve_weight_files(dir, crate::weights::DIFFUSERS_WEIGHTS_STEM)?;
        let mut me = Self::random(&cfg, ComputeDevice::Cpu, Precision::F32)?;
        load_component(&me.vs, dir)?;
        if precision == Precision::Bf16 {
            me.vs.bfloat16();
        }
        crate::device::move_to_device(&mut me.vs, device.to_tch());
        me.vs.freeze();
        Ok(me)
    }

    /// Parameters.
    pub fn parameter_count(&self) -> i64 {
        parameter_count(&self.vs)
    }
}

/// What [`CogVideoXTransformer3DModel::forward_checkpointed`] keeps for the
/// backward pass: the inputs, every block's `(video, text)` input and the
/// residuals (with their autograd graphs).
#[derive(Debug)]
pub struct CheckpointedForward {
    hidden_states: Tensor,
    encoder_hidden_states: Tensor,
    timestep: Tensor,
    ofs: Option<Tensor>,
    rotary: Option<Rotary>,
    block_inputs: Vec<(Tensor, Tensor)>,
    final_video: Tensor,
    residuals: Vec<Option<Tensor>>,
    output: Tensor,
}

/// `sum(a * g)`: the scalar whose gradient pushes `g` back through `a`.
fn dot(a: &Tensor, g: &Tensor) -> Tensor {
    (a * g.to_kind(a.kind())).sum(Kind::Float)
}

/// A leaf copy of `t` that requires grad.
fn leaf(t: &Tensor) -> Tensor {
    t.detach().set_requires_grad(true)
}

impl CheckpointedForward {
    /// Back-propagates the gradient the loss left on the output leaf:
    /// the head, then each block from the last (recomputed with autograd
    /// on, one at a time), then the embeddings and the residuals' sources.
    /// Gradients accumulate into the variables as `backward()` would have.
    /// Nothing happens when the output received no gradient.
    pub fn backward(self, model: &CogVideoXTransformer3DModel) -> Result<()> {
        let grad_output = self.output.grad();
        if !grad_output.defined() {
            return Ok(());
        }
        // The embeddings, recomputed with autograd on (cheap); the blocks
        // see a leaf of the timestep embedding whose gradient sums over
        // all blocks and the head.
        let emb = model.embed(
            &self.hidden_states,
            &self.encoder_hidden_states,
            &self.timestep,
            self.ofs.as_ref(),
        )?;
        let temb = leaf(&emb.temb);
        let emb_leaf = Embedded {
            video: emb.video.shallow_clone(),
            text: emb.text.shallow_clone(),
            temb: temb.shallow_clone(),
            latent_shape: emb.latent_shape,
        };
        let video = leaf(&self.final_video);
        dot(&model.finish(&emb_leaf, &video), &grad_output).backward();
        let mut grad_video = video.grad();
        let mut grad_text: Option<Tensor> = None;
        let mut residual_terms = Vec::new();
        for (i, (video_in, text_in)) in self.block_inputs.iter().enumerate().rev() {
            // After block i: video_{i+1} = v + r_i, text_{i+1} = t.
            if let Some(Some(r)) = self.residuals.get(i) {
                if r.requires_grad() {
                    residual_terms.push(dot(r, &grad_video));
                }
            }
            let (v_in, t_in) = (leaf(video_in), leaf(text_in));
            let (v, t) = model.run_block(i, &v_in, &t_in, &temb, self.rotary.as_ref());
            let mut scalar = dot(&v, &grad_video);
            if let (Some(g), true) = (&grad_text, t.defined()) {
                scalar += dot(&t, g);
            }
            scalar.backward();
            grad_video = v_in.grad();
            let g = t_in.grad();
            grad_text = g.defined().then_some(g);
        }
        // Into the embeddings (trainable only in some setups).
        let mut scalar: Option<Tensor> = None;
        let mut add = |term: Tensor| {
            scalar = Some(match scalar.take() {
                Some(s) => s + term,
                None => term,
            });
        };
        if emb.video.requires_grad() && grad_video.defined() {
            add(dot(&emb.video, &grad_video));
        }
        if let (true, Some(g)) = (emb.text.requires_grad(), &grad_text) {
            add(dot(&emb.text, g));
        }
        let grad_temb = temb.grad();
        if emb.temb.requires_grad() && grad_temb.defined() {
            add(dot(&emb.temb, &grad_temb));
        }
        for term in residual_terms {
            add(term);
        }
        if let Some(s) = scalar {
            s.backward();
        }
        Ok(())
    }
}
