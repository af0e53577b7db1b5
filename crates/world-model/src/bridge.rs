//! The BridgeV2W model: a CogVideoX image-to-video backbone (VAE + transformer,
//! frozen), LoRA adapters on its attention, and the mask [`ControlNet`] branch;
//! it implements [`crate::pipeline::Denoiser`] and [`crate::pipeline::WorldModel`]
//! (in `bridge/predict.rs`, with batch prediction).
//!
//! Files: the backbone is a diffusers pipeline folder (loaded unchanged); BridgeV2W's
//! own weights (ControlNet + LoRA) are one safetensors file with keys
//! `controlnet.*` and `transformer.transformer_blocks.{i}.attn1.{to_q,to_k,to_v,to_out.0}.lora_{A,B}.weight`
//! and its [`BridgeV2WConfig`] as JSON in the header's `__metadata__["bridgev2w_config"]`.

use crate::checkpoint::{PipelineFolder, PromptEmbedding};
use crate::controlnet::{ControlNet, ControlNetConfig};
use crate::device::{move_to_device, ComputeDevice, Precision};
use crate::error::{Result, WorldModelError};
use crate::lora::LoraConfig;
use crate::pipeline::BatchNoise;
use crate::scheduler::SchedulerConfig;
use crate::transformer::{CheckpointedForward, LoadedTransformer, Rotary, TransformerConfig};
use crate::vae::{AutoencoderKLCogVideoX, Posterior, VaeConfig};
use crate::weights::{
    load_weights, read_safetensors_metadata, save_safetensors, save_safetensors_with_metadata,
    DIFFUSERS_WEIGHTS_STEM,
};
use std::collections::BTreeMap;
use std::path::Path;
use tch::nn::VarStore;
use tch::{Device, Kind, Tensor};

mod memory;
mod predict;

pub use memory::{check_predict_batch, MAX_PREDICT_BATCH};

/// The metadata key of the config in a BridgeV2W weights file.
pub const CONFIG_METADATA_KEY: &str = "bridgev2w_config";

/// The most pixel frames of a clip (a config's or a weights file's
/// `frames`, `plan --clip-frames`): 40 times the paper's 25.
pub const MAX_CLIP_FRAMES: usize = 1024;
/// The largest side of a clip (pixels; a config's or a weights file's
/// `height` and `width`): more than 10 times the paper's 720.
pub const MAX_CLIP_SIDE: usize = 8192;

/// BridgeV2W's own settings (the backbone's are in its diffusers configs).
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct BridgeV2WConfig {
    /// Pixel frames per clip (`4k + 1`; the paper: 25).
    pub frames: usize,
    /// Pixel height (the paper: 480).
    pub height: usize,
    /// Pixel width (the paper: 720).
    pub width: usize,
    /// The mask branch.
    pub controlnet: ControlNetConfig,
    /// LoRA on the backbone's attention (none: the backbone is used as is).
    pub lora: Option<LoraConfig>,
    /// Where the image latent enters the conditioning channels.
    pub image_conditioning: ImageConditioning,
    /// How the masks fill the mask branch's three channels (weights files
    /// from before this setting read as the paper's binary masks).
    pub mask_coding: MaskCoding,
}

pub use crate::conditioning::ImageConditioning;
pub use crate::mask_coding::MaskCoding;

impl Default for BridgeV2WConfig {
    fn default() -> Self {
        Self::paper()
    }
}

impl BridgeV2WConfig {
    /// The paper's setting: 25 frames at 480x720, 8 branch blocks, LoRA 64/64.
    pub fn paper() -> Self {
        Self {
            frames: 25,
            height: 480,
            width: 720,
            controlnet: ControlNetConfig::default(),
            lora: Some(LoraConfig::paper()),
            image_conditioning: ImageConditioning::FirstFrame,
            mask_coding: MaskCoding::Binary,
        }
    }

    /// Test size (for the `tiny` VAE and transformer presets): 9 frames at
    /// 64x96, one branch block, LoRA rank 4.
    pub fn tiny() -> Self {
        Self {
            frames: 9,
            height: 64,
            width: 96,
            controlnet: ControlNetConfig::with_layers(1),
            lora: Some(LoraConfig {
                rank: 4,
                alpha: 4.0,
            }),
            image_conditioning: ImageConditioning::FirstFrame,
            mask_coding: MaskCoding::Binary,
        }
    }

    /// Checks the clip's size against [`MAX_CLIP_FRAMES`] and
    /// [`MAX_CLIP_SIDE`] (before anything of that size is allocated): the
    /// field at fault and its value, or `None`.
    pub fn size_error(&self) -> Option<(&'static str, String)> {
        for (field, v, max, unit) in [
            ("frames", self.frames, MAX_CLIP_FRAMES, "frames"),
            ("height", self.height, MAX_CLIP_SIDE, "pixels"),
            ("width", self.width, MAX_CLIP_SIDE, "pixels"),
        ] {
            if v > max {
                return Some((field, format!("{v}: at most {max} {unit} is supported")));
            }
        }
        None
    }

    /// Checks the clip shape against the VAE and transformer.
    pub fn validate(&self, vae: &VaeConfig, tf: &TransformerConfig) -> Result<()> {
        if let Some((field, message)) = self.size_error() {
            return Err(WorldModelError::input(field, message));
        }
        if let Some(message) = vae.frames_error(self.frames) {
            return Err(WorldModelError::input("frames", message));
        }
        let m = (vae.spatial_compression() * tf.patch_size) as usize;
        if self.height == 0 || self.width == 0 || self.height % m != 0 || self.width % m != 0 {
            return Err(WorldModelError::input(
                "resolution",
                format!(
                    "{}x{} (HxW): expected multiples of {m} (VAE downsampling x patch size)",
                    self.height, self.width
                ),
            ));
        }
        // Checked here, not first in a forward pass: a learned positional
        // embedding holds one latent size.
        let s = vae.spatial_compression() as usize;
        let (sh, sw) = (tf.sample_height as usize, tf.sample_width as usize);
        if tf.use_learned_positional_embeddings && (self.height / s, self.width / s) != (sh, sw) {
            return Err(WorldModelError::input(
                "resolution",
                format!(
                    "{}x{} (HxW) gives latents of {}x{}, but the transformer's learned positional embedding is for {sh}x{sw} latents ({}x{} pixels)",
                    self.height,
                    self.width,
                    self.height / s,
                    self.width / s,
                    sh * s,
                    sw * s
                ),
            ));
        }
        if tf.in_channels != 2 * vae.latent_channels {
            return Err(WorldModelError::input(
                "transformer.in_channels",
                format!(
                    "{}: an image-to-video backbone takes 2 x {} latent channels",
                    tf.in_channels, vae.latent_channels
                ),
            ));
        }
        self.controlnet.validate(tf)
    }

    /// Latent frames of a clip.
    pub fn latent_frames(&self, vae: &VaeConfig) -> usize {
        (self.frames - 1) / vae.temporal_compression_ratio as usize + 1
    }
}

/// The BridgeV2W model.
#[derive(Debug)]
pub struct BridgeV2W {
    cfg: BridgeV2WConfig,
    /// The VAE's variables.
    pub vae_vs: VarStore,
    /// The 3D causal VAE.
    pub vae: AutoencoderKLCogVideoX,
    /// The backbone (variables frozen).
    pub transformer: LoadedTransformer,
    /// BridgeV2W's trainable variables: `controlnet.*` and the LoRA adapters.
    pub adapters: VarStore,
    /// The mask branch.
    pub controlnet: ControlNet,
    /// The sampler's configuration.
    pub scheduler: SchedulerConfig,
    /// The fixed prompt's embedding `[L, text_dim]`.
    pub prompt: Tensor,
    device: Device,
    kind: Kind,
}

impl BridgeV2W {
    /// Assembles the model around a VAE and a backbone: creates the branch
    /// (blocks copied from the backbone's first `N`) and the LoRA adapters.
    pub fn assemble(
        cfg: BridgeV2WConfig,
        mut vae_vs: VarStore,
        vae: AutoencoderKLCogVideoX,
        mut transformer: LoadedTransformer,
        scheduler: SchedulerConfig,
        prompt: PromptEmbedding,
    ) -> Result<Self> {
        let tf_cfg = transformer.model.config().clone();
        cfg.validate(vae.config(), &tf_cfg)?;
        let device = transformer.vs.device();
        let kind = transformer
            .vs
            .variables()
            .values()
            .next()
            .map(|t| t.kind())
            .unwrap_or(Kind::Float);
        // Built on the host, then moved (see `move_to_device`).
        let mut adapters = VarStore::new(tch::Device::Cpu);
        let controlnet =
            ControlNet::new(&tf_cfg, &cfg.controlnet, &(adapters.root() / "controlnet"))?;
        if let Some(lora) = cfg.lora {
            transformer
                .model
                .attach_lora(&(adapters.root() / "transformer"), lora)?;
        }
        controlnet.copy_from_backbone(&transformer.vs, &adapters, "controlnet")?;
        if kind != Kind::Float {
            adapters.set_kind(kind);
        }
        move_to_device(&mut adapters, device);
        transformer.vs.freeze();
        vae_vs.freeze();
        let prompt = prompt.embeds.to_device(device).to_kind(kind);
        Ok(Self {
            cfg,
            vae_vs,
            vae,
            transformer,
            adapters,
            controlnet,
            scheduler,
            prompt,
            device,
            kind,
        })
    }

    /// A model with random backbone weights (tests, and training a prior from scratch).
    pub fn random(
        cfg: BridgeV2WConfig,
        vae_cfg: &VaeConfig,
        tf_cfg: &TransformerConfig,
        scheduler: SchedulerConfig,
        device: ComputeDevice,
        seed: i64,
    ) -> Result<Self> {
        Self::random_in(
            cfg,
            vae_cfg,
            tf_cfg,
            scheduler,
            device,
            Precision::F32,
            seed,
        )
    }

    /// [`Self::random`] in `precision`: the same weights (drawn in f32 from
    /// `seed`), then, for bf16, the transformer in bf16 and the VAE too unless
    /// its config says `force_upcast`, as [`Self::load`] does for a folder.
    pub fn random_in(
        cfg: BridgeV2WConfig,
        vae_cfg: &VaeConfig,
        tf_cfg: &TransformerConfig,
        scheduler: SchedulerConfig,
        device: ComputeDevice,
        precision: Precision,
        seed: i64,
    ) -> Result<Self> {
        tch::manual_seed(seed);
        let device = device.check_available()?;
        let mut vae_vs = VarStore::new(tch::Device::Cpu);
        let vae = AutoencoderKLCogVideoX::new(vae_cfg, vae_vs.root())?;
        crate::vae::init_like_pytorch(&vae_vs);
        if precision == Precision::Bf16 && !vae_cfg.force_upcast {
            vae_vs.bfloat16();
        }
        move_to_device(&mut vae_vs, device.to_tch());
        let transformer = LoadedTransformer::random(tf_cfg, device, precision)?;
        let prompt = PromptEmbedding::zeros(tf_cfg.max_text_seq_length, tf_cfg.text_embed_dim);
        Self::assemble(cfg, vae_vs, vae, transformer, scheduler, prompt)
    }

    /// Loads a diffusers CogVideoX image-to-video folder, then BridgeV2W's weights
    /// file when given (its config then overrides `cfg`), and the prompt embedding
    /// (zeros of `[max_text_seq_length, text_embed_dim]` when absent).
    pub fn load(
        pipeline_dir: &Path,
        weights: Option<&Path>,
        prompt: Option<&Path>,
        cfg: BridgeV2WConfig,
        device: ComputeDevice,
        precision: Precision,
    ) -> Result<Self> {
        let pipeline_dir = &crate::hub::resolve_model_dir(pipeline_dir)?;
        let folder = PipelineFolder::open(pipeline_dir)?;
        folder.check_weights(&["vae", "transformer"])?;
        let device = device.check_available()?;
        let vae_dir = folder.component_dir("vae");
        let vae_cfg = VaeConfig::from_file(&vae_dir.join("config.json"))?;
        let mut vae_vs = VarStore::new(tch::Device::Cpu);
        let vae = AutoencoderKLCogVideoX::new(&vae_cfg, vae_vs.root())?;
        crate::weights::load_component(&vae_vs, &vae_dir)?;
        if precision == Precision::Bf16 && !vae_cfg.force_upcast {
            vae_vs.bfloat16();
        }
        move_to_device(&mut vae_vs, device.to_tch());
        let transformer =
            LoadedTransformer::load(&folder.component_dir("transformer"), device, precision)?;
        let tf_cfg = transformer.model.config().clone();
        let scheduler = SchedulerConfig::load(
            &folder
                .component_dir("scheduler")
                .join("scheduler_config.json"),
        )?;
        let prompt = match prompt {
            Some(p) => PromptEmbedding::load(p, tf_cfg.text_embed_dim)?,
            None => PromptEmbedding::zeros(tf_cfg.max_text_seq_length, tf_cfg.text_embed_dim),
        };
        let mut cfg = match weights {
            Some(w) => Self::weights_config(w)?.unwrap_or(cfg),
            None => cfg,
        };
        match (folder.image_conditioning, weights) {
            (Some(rec), Some(w)) if rec != cfg.image_conditioning => {
                return Err(WorldModelError::config(
                    w,
                    "image_conditioning",
                    format!(
                        "{}, but the backbone {} was trained with {rec} ({})",
                        cfg.image_conditioning,
                        pipeline_dir.display(),
                        crate::checkpoint::IMAGE_CONDITIONING_KEY
                    ),
                ))
            }
            (Some(rec), None) => cfg.image_conditioning = rec,
            _ => {}
        }
        let me = Self::assemble(cfg, vae_vs, vae, transformer, scheduler, prompt)?;
        if let Some(w) = weights {
            me.load_weights(w)?;
        }
        Ok(me)
    }

    /// The configuration.
    pub fn config(&self) -> &BridgeV2WConfig {
        &self.cfg
    }

    /// Predicts clips of `frames` frames from now on instead of the frames
    /// the model was trained on (beyond the paper: a planner that scores one
    /// action of 2 frames needs a clip of 3, a third of the tokens of 9).
    /// The transformer's rotary or sin-cos positions follow the clip;
    /// `frames` must suit the VAE's time compression as a config's must.
    pub fn set_clip_frames(&mut self, frames: usize) -> Result<()> {
        let cfg = BridgeV2WConfig {
            frames,
            ..self.cfg.clone()
        };
        cfg.validate(self.vae.config(), self.transformer.model.config())?;
        self.cfg = cfg;
        Ok(())
    }

    /// The tch device the model runs on.
    pub fn device(&self) -> Device {
        self.device
    }

    /// The BridgeV2W config stored in a weights file, if any.
    /// Its frame count and resolution are checked against
    /// [`MAX_CLIP_FRAMES`] and [`MAX_CLIP_SIDE`] here, naming the file.
    pub fn weights_config(path: &Path) -> Result<Option<BridgeV2WConfig>> {
        let meta = read_safetensors_metadata(path)?;
        let Some(text) = meta.get(CONFIG_METADATA_KEY) else {
            return Ok(None);
        };
        let cfg: BridgeV2WConfig = serde_json::from_str(text).map_err(|e| {
            WorldModelError::config(
                path,
                CONFIG_METADATA_KEY,
                format!("not a BridgeV2W config: {e}"),
            )
        })?;
        if let Some((field, message)) = cfg.size_error() {
            return Err(WorldModelError::config(
                path,
                format!("{CONFIG_METADATA_KEY}.{field}"),
                message,
            ));
        }
        Ok(Some(cfg))
    }

    /// Writes the ControlNet + LoRA weights and the config, atomically.
    pub fn save_weights(&self, path: &Path) -> Result<()> {
        let mut named: Vec<(String, Tensor)> = self.adapters.variables().into_iter().collect();
        named.sort_by(|a, b| a.0.cmp(&b.0));
        let mut meta = BTreeMap::new();
        meta.insert(
            CONFIG_METADATA_KEY.to_owned(),
            serde_json::to_string(&self.cfg).map_err(|e| WorldModelError::Json {
                path: path.to_path_buf(),
                error: e,
            })?,
        );
        meta.insert("format".to_owned(), "bridgev2w".to_owned());
        save_safetensors_with_metadata(&named, &meta, path)
    }

    /// Loads ControlNet + LoRA weights (strict: every variable, no extras).
    pub fn load_weights(&self, path: &Path) -> Result<()> {
        load_weights(&self.adapters, &[path.to_path_buf()], |_| false, |_| false)?;
        Ok(())
    }

    /// Writes the backbone as a diffusers pipeline folder (`model_index.json`,
    /// `vae/`, `transformer/`, `scheduler/`), loadable by [`Self::load`] and by
    /// diffusers' `CogVideoXImageToVideoPipeline` components.
    pub fn save_backbone(&self, dir: &Path) -> Result<()> {
        let write_json = |path: &Path, value: &serde_json::Value| -> Result<()> {
            let text = serde_json::to_string_pretty(value).map_err(|e| WorldModelError::Json {
                path: path.to_path_buf(),
                error: e,
            })?;
            Ok(bridgev2w_io::atomic::write_atomic(path, text.as_bytes())?)
        };
        let with_class = |value: serde_json::Value, class: &str| {
            let mut v = value;
            if let Some(o) = v.as_object_mut() {
                o.insert("_class_name".into(), class.into());
                o.insert("_diffusers_version".into(), "0.42.1".into());
            }
            v
        };
        let to_value = |v: Result<serde_json::Value, serde_json::Error>, path: &Path| {
            v.map_err(|e| WorldModelError::Json {
                path: path.to_path_buf(),
                error: e,
            })
        };
        for sub in ["vae", "transformer", "scheduler"] {
            std::fs::create_dir_all(dir.join(sub)).map_err(|e| WorldModelError::io(dir, e))?;
        }
        let p = dir.join("vae/config.json");
        write_json(
            &p,
            &with_class(
                to_value(serde_json::to_value(self.vae.config()), &p)?,
                "AutoencoderKLCogVideoX",
            ),
        )?;
        save_vars(&self.vae_vs, &dir.join("vae"))?;
        let p = dir.join("transformer/config.json");
        write_json(
            &p,
            &with_class(
                to_value(serde_json::to_value(self.transformer.model.config()), &p)?,
                "CogVideoXTransformer3DModel",
            ),
        )?;
        save_vars(&self.transformer.vs, &dir.join("transformer"))?;
        let p = dir.join("scheduler/scheduler_config.json");
        write_json(&p, &to_value(serde_json::to_value(&self.scheduler), &p)?)?;
        let sched_class = self
            .scheduler
            .class_name
            .clone()
            .unwrap_or_else(|| "CogVideoXDDIMScheduler".to_owned());
        let mut index = serde_json::json!({
            "_class_name": "CogVideoXImageToVideoPipeline",
            "_diffusers_version": "0.42.1",
            "scheduler": ["diffusers", sched_class],
            "transformer": ["diffusers", "CogVideoXTransformer3DModel"],
            "vae": ["diffusers", "AutoencoderKLCogVideoX"],
            "text_encoder": [null, null],
            "tokenizer": [null, null],
        });
        if self.cfg.image_conditioning != ImageConditioning::FirstFrame {
            // Only the deviation is recorded: a folder without it is CogVideoX's.
            index[crate::checkpoint::IMAGE_CONDITIONING_KEY] =
                self.cfg.image_conditioning.to_string().into();
        }
        write_json(&dir.join("model_index.json"), &index)
    }

    fn latent_geometry(&self) -> (i64, i64, i64) {
        let s = self.vae.config().spatial_compression() as usize;
        (
            self.cfg.latent_frames(self.vae.config()) as i64,
            (self.cfg.height / s) as i64,
            (self.cfg.width / s) as i64,
        )
    }

    /// Scaled VAE latents `[B, t, C, h, w]` of a video `[B, 3, T, H, W]` in
    /// [-1, 1]: the posterior mean, or a sample with `seed`.
    pub fn encode_latents(&self, video: &Tensor, seed: Option<u64>) -> Result<Tensor> {
        self.posterior_latents(&self.vae.encode(video)?, seed, BatchNoise::Independent)
    }

    /// Scaled latents `[B, t, C, h, w]` of a VAE posterior: its mean, or a
    /// sample with `seed` (a batch's noise drawn as `batch_noise` says).
    fn posterior_latents(
        &self,
        post: &Posterior,
        seed: Option<u64>,
        batch_noise: BatchNoise,
    ) -> Result<Tensor> {
        let z = match seed {
            Some(s) => post.sample_batch(s, batch_noise)?,
            None => post.mode(),
        };
        Ok(self
            .vae
            .scale_latents(&z)
            .permute([0, 2, 1, 3, 4]) // [B, C, t, h, w] -> [B, t, C, h, w]
            .to_device(self.device)
            .to_kind(self.kind))
    }

    /// The pipeline's image latents `[B, t, C, h, w]`: the first frame's latents
    /// (`first_frames` `[B, 3, H, W]` in [-1, 1]) followed by zeros, or repeated
    /// in every latent frame ([`BridgeV2WConfig::image_conditioning`]).
    pub fn image_latents(&self, first_frames: &Tensor, seed: Option<u64>) -> Result<Tensor> {
        // [B, 3, H, W] -> [B, 3, 1, H, W] -> [B, 1, C, h, w]
        let z = self.encode_latents(&first_frames.unsqueeze(2), seed)?;
        let (t, _, _) = self.latent_geometry();
        Ok(self.cfg.image_conditioning.expand(&z, t)) // [B, t, C, h, w]
    }

    /// The branch input `[B, t, 2C, h, w]`: mask latents (`masks` `[B, 3, T, H, W]`
    /// in {-1, 1}) ++ image latents.
    pub fn control_latents(&self, masks: &Tensor, image_latents: &Tensor) -> Result<Tensor> {
        let zm = self.encode_latents(masks, None)?;
        if zm.size() != image_latents.size() {
            return Err(WorldModelError::input(
                "masks",
                format!(
                    "mask latents {:?} but image latents {:?} (same frames and size needed)",
                    zm.size(),
                    image_latents.size()
                ),
            ));
        }
        Ok(Tensor::cat(&[&zm, image_latents], 2))
    }

    /// The predicted velocity `[B, t, C, h, w]` for `latent_in` `[B, t, 2C, h, w]`
    /// (noisy latents ++ image latents) at `timestep` `[B]`, with the mask branch
    /// when `control` (`[B, t, 2C, h, w]`) is given. Differentiable in the
    /// adapters' variables.
    pub fn velocity_with(
        &self,
        latent_in: &Tensor,
        timestep: &Tensor,
        control: Option<&Tensor>,
    ) -> Result<Tensor> {
        self.velocity_with_extra(latent_in, timestep, control, &[])
    }

    /// [`Self::velocity_with`] plus `extra` residuals: `extra[i]` (`[B, N_tokens, D]`
    /// or broadcastable to it) is added to the backbone's video tokens after block
    /// `i`, on top of the branch's residual (training's action-MLP ablation injects
    /// its action tokens this way). Blocks beyond `extra.len()` get none.
    pub fn velocity_with_extra(
        &self,
        latent_in: &Tensor,
        timestep: &Tensor,
        control: Option<&Tensor>,
        extra: &[Tensor],
    ) -> Result<Tensor> {
        let p = self.prepare(latent_in, timestep, control, extra)?;
        let residuals = p.residuals;
        self.transformer.model.forward_with_residuals(
            &p.latent_in,
            &p.text,
            &p.timestep,
            p.rotary.as_ref(),
            p.ofs.as_ref(),
            &mut |i, _| {
                residuals
                    .get(i)
                    .and_then(|r| r.as_ref().map(Tensor::shallow_clone))
            },
        )
    }

    /// [`Self::velocity_with_extra`] with per-block gradient checkpointing
    /// of the backbone: the velocity comes back as a leaf that requires
    /// grad; after the loss's `backward()`, call
    /// [`CheckpointedForward::backward`] with the backbone
    /// (`&self.transformer.model`) to recompute each block and carry the
    /// gradients into the adapters, the ControlNet branch and `extra`'s
    /// sources. Memory: one `(video, text)` token pair per block instead of
    /// every block's activations.
    pub fn velocity_checkpointed(
        &self,
        latent_in: &Tensor,
        timestep: &Tensor,
        control: Option<&Tensor>,
        extra: &[Tensor],
    ) -> Result<(Tensor, CheckpointedForward)> {
        let p = self.prepare(latent_in, timestep, control, extra)?;
        self.transformer.model.forward_checkpointed(
            &p.latent_in,
            &p.text,
            &p.timestep,
            p.rotary.as_ref(),
            p.ofs.as_ref(),
            p.residuals,
        )
    }

    /// The transformer inputs of a velocity call and the per-block
    /// residuals (branch + `extra`).
    fn prepare(
        &self,
        latent_in: &Tensor,
        timestep: &Tensor,
        control: Option<&Tensor>,
        extra: &[Tensor],
    ) -> Result<Prepared> {
        if extra.len() > self.transformer.model.config().num_layers as usize {
            return Err(WorldModelError::input(
                "extra residuals",
                format!(
                    "{} residuals for {} backbone blocks",
                    extra.len(),
                    self.transformer.model.config().num_layers
                ),
            ));
        }
        let model = &self.transformer.model;
        let latent_in = latent_in.to_device(self.device).to_kind(self.kind);
        let b = latent_in.size()[0];
        let l = self.prompt.size()[0];
        let text = self
            .prompt
            .unsqueeze(0)
            .expand([b, l, self.prompt.size()[1]], false); // [B, L, D_text]
        let rotary = model.rotary_for(&latent_in)?;
        let ofs = model
            .config()
            .ofs_embed_dim
            .map(|_| Tensor::full([b], 2.0, (Kind::Float, self.device)));
        let timestep = timestep.to_device(self.device);
        let branch = match control {
            Some(c) => {
                let temb = model.time_embed(&timestep, ofs.as_ref(), self.kind)?;
                let c = c.to_device(self.device).to_kind(self.kind);
                self.controlnet
                    .residuals(&c, &text, &temb, rotary.as_ref())?
            }
            None => Vec::new(),
        };
        let n = branch.len().max(extra.len());
        let residuals = (0..n)
            .map(|i| match (branch.get(i), extra.get(i)) {
                (Some(r), Some(e)) => Some(r + e.to_kind(self.kind)),
                (Some(r), None) => Some(r.shallow_clone()),
                (None, Some(e)) => Some(e.to_kind(self.kind)),
                (None, None) => None,
            })
            .collect();
        Ok(Prepared {
            latent_in,
            text,
            timestep,
            rotary,
            ofs,
            residuals,
        })
    }

    /// Decodes scaled latents `[B, t, C, h, w]` into videos `[B, 3, T, H, W]` in [-1, 1].
    pub fn decode_latents(&self, latents: &Tensor) -> Result<Tensor> {
        self.vae.decode(&self.vae_latents(latents))
    }

    /// [`Self::decode_latents`] of the VAE's last latent-frame batch only
    /// ([`crate::vae::AutoencoderKLCogVideoX::decode_last_batch`]): the
    /// clip's last frames `[B, 3, T', H, W]`.
    pub fn decode_latents_last(&self, latents: &Tensor) -> Result<Tensor> {
        self.vae.decode_last_batch(&self.vae_latents(latents))
    }

    /// The transformer's scaled latents `[B, t, C, h, w]` as the VAE
    /// decoder takes them: unscaled, float32, `[B, C, t, h, w]`.
    fn vae_latents(&self, latents: &Tensor) -> Tensor {
        let z = self.vae.unscale_latents(&latents.permute([0, 2, 1, 3, 4])); // [B, C, t, h, w]
        z.to_kind(Kind::Float)
    }

    /// The compute dtype of the backbone.
    pub fn kind(&self) -> Kind {
        self.kind
    }
}

/// Inputs of one transformer call (see [`BridgeV2W::velocity_with_extra`]).
struct Prepared {
    latent_in: Tensor,
    text: Tensor,
    timestep: Tensor,
    rotary: Option<Rotary>,
    ofs: Option<Tensor>,
    residuals: Vec<Option<Tensor>>,
}

fn save_vars(vs: &VarStore, dir: &Path) -> Result<()> {
    let mut named: Vec<(String, Tensor)> = vs.variables().into_iter().collect();
    named.sort_by(|a, b| a.0.cmp(&b.0));
    save_safetensors(
        &named,
        &dir.join(format!("{DIFFUSERS_WEIGHTS_STEM}.safetensors")),
    )
}
