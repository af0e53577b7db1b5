//! The training configuration (`bridgev2w train CONFIG.toml`), with the
//! paper's hyper-parameters as defaults (appendix table).
//!
//! ```toml
//! [model]
//! backbone = "random:tiny"          # or a diffusers CogVideoX I2V folder
//! [data]
//! dataset = "synth-data"            # `bridgev2w synth` / LeRobot v3.0 folder
//! split = "train"
//! [train]
//! out = "runs/tiny"
//! max_steps = 100
//! ```

use crate::data::{MaskKind, SourceSpec};
use crate::{Result, TrainError};
use bridgev2w_world_model::bridge::{ImageConditioning, MaskCoding};
use bridgev2w_world_model::spec::ModelSpec;
use bridgev2w_world_model::transformer::TransformerConfig;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// The whole configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(default, deny_unknown_fields)]
pub struct TrainConfig {
    /// The model to train.
    pub model: ModelSection,
    /// The clips it is trained on.
    pub data: DataSection,
    /// Optimisation and losses.
    pub train: TrainSection,
    /// The paper's ablation switches.
    pub ablation: AblationSection,
}

/// `[model]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelSection {
    /// A diffusers CogVideoX image-to-video folder, or `random:tiny` /
    /// `random:small` / `random:small2x` / `random:small2x-wide` (the tiny,
    /// small or 2x-spatial small VAE/transformer presets with random
    /// weights, 9 frames at 64x96; `-wide`: a transformer of 256, not 128).
    pub backbone: String,
    /// The fixed prompt's embedding (safetensors, see `bridgev2w predict`); zeros when absent.
    pub prompt_embeds: Option<PathBuf>,
    /// BridgeV2W weights (ControlNet + LoRA) to start from instead of a fresh branch.
    pub init_weights: Option<PathBuf>,
    /// LoRA rank on the backbone's attention (paper: 64; 0 = no LoRA).
    pub lora_rank: usize,
    /// LoRA alpha (paper: 64).
    pub lora_alpha: f64,
    /// ControlNet branch blocks (copies of the backbone's first N). Unset:
    /// the paper's 8, or all the backbone's blocks when it has fewer; a
    /// value above the backbone's block count is an error.
    pub controlnet_layers: Option<usize>,
    /// Also train the backbone transformer's own weights (training a video
    /// prior from scratch; implied by `ablation.pretrained = false`).
    pub train_backbone: bool,
    /// `cpu`, `cuda`, `cuda:N` or `auto`.
    pub device: bridgev2w_world_model::DeviceSpec,
    /// Hidden width of the action MLP (`ablation.mask_action = false`).
    pub action_hidden: i64,
    /// Where the image latent enters the backbone's conditioning channels:
    /// `first_frame` (CogVideoX-I2V) or `every_frame` (for backbones trained
    /// here from scratch; the prior and the fine-tuning must agree).
    pub image_conditioning: ImageConditioning,
    /// How the masks fill the mask branch's three channels: `binary` (the
    /// paper's) or `links` (link-coded, beyond the paper: needs the
    /// datasets' link labels, `labels/episode_*.npy` of `bridgev2w synth`).
    pub mask_coding: MaskCoding,
    /// A transformer preset (`small2x-wide`, `small2x`, `small`, `tiny`, ...)
    /// with fresh random weights in place of the backbone folder's
    /// transformer; the VAE and scheduler still come from the folder. For a
    /// `prior` stage of another width than the autoencoder stages' backbone.
    pub transformer: Option<String>,
    /// The VAE's spatial tiles in training, `"HxW"` pixels (e.g.
    /// `"144x200"`): the clips' encoding and the flow loss's decode run tile
    /// by tile. Unset: the VAE's default tiles (half its sample size, 240x360
    /// for CogVideoX) above 256x256 pixels, whole frames below. Smaller tiles
    /// lower the flow loss's memory (its backward replays one tile at a
    /// time) for more overlap to compute; they must join exactly (a multiple
    /// of 8 px whose latent size is a multiple of 6 high and 5 wide).
    pub vae_tile: Option<bridgev2w_world_model::vae::TileSize>,
}

impl Default for ModelSection {
    fn default() -> Self {
        Self {
            backbone: "random:tiny".into(),
            prompt_embeds: None,
            init_weights: None,
            lora_rank: 64,
            lora_alpha: 64.0,
            controlnet_layers: None,
            train_backbone: false,
            device: bridgev2w_world_model::DeviceSpec::Cpu,
            action_hidden: 256,
            image_conditioning: ImageConditioning::FirstFrame,
            mask_coding: MaskCoding::Binary,
            transformer: None,
            vae_tile: None,
        }
    }
}

/// `[data]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DataSection {
    /// A `bridgev2w synth` (LeRobot v3.0 + `masks/`) dataset folder.
    pub dataset: PathBuf,
    /// The split to train on (episodes whose `split` column matches; all
    /// episodes when the dataset has no split column).
    pub split: String,
    /// The video key (default: the dataset's first).
    pub video_key: Option<String>,
    /// Frames per clip (`4k + 1`); 0 = the backbone's default (9 for `random:*`, else 25).
    pub frames: usize,
    /// Clip width, pixels; 0 = the backbone's default. Frames of another size are resized.
    pub width: usize,
    /// Clip height, pixels; 0 = the backbone's default.
    pub height: usize,
    /// Random clips per video and epoch (the paper: 20).
    pub clips_per_video: usize,
    /// Mask source: `calc` (rendered from URDF + calibration: the dataset's
    /// `masks/`, else rendered for `robot` and cached) or `seg` (PNG folders
    /// under `seg_masks`).
    pub masks: MaskSource,
    /// `seg` masks: root of `episode_XXXXXX/*.png` folders (default
    /// `<dataset>/seg_masks`).
    pub seg_masks: Option<PathBuf>,
    /// `calc` masks for datasets without `masks/`: the robot (built-in name
    /// or URDF) whose joint states `observation.state` holds.
    pub robot: Option<String>,
    /// Cache of rendered `calc` masks (default `<dataset>/.bridgev2w-mask-cache`).
    pub mask_cache: Option<PathBuf>,
    /// Mixing weight of this dataset against the `[[data.mix]]` sources.
    pub weight: f64,
    /// More datasets mixed in (paper Table "segmix": calc and seg sources).
    pub mix: Vec<MixSource>,
}

impl Default for DataSection {
    fn default() -> Self {
        Self {
            dataset: PathBuf::new(),
            split: "train".into(),
            video_key: None,
            frames: 0,
            width: 0,
            height: 0,
            clips_per_video: 20,
            masks: MaskSource::Calc,
            seg_masks: None,
            robot: None,
            mask_cache: None,
            weight: 1.0,
            mix: Vec::new(),
        }
    }
}

/// `[[data.mix]]`: another dataset of the mixture (fields as in `[data]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MixSource {
    /// Dataset folder.
    pub dataset: PathBuf,
    /// Split.
    pub split: String,
    /// Video key (default: the dataset's first).
    pub video_key: Option<String>,
    /// `calc` or `seg`.
    pub masks: MaskSource,
    /// `seg` masks root (default `<dataset>/seg_masks`).
    pub seg_masks: Option<PathBuf>,
    /// Robot for rendering `calc` masks.
    pub robot: Option<String>,
    /// Mask cache (default `<dataset>/.bridgev2w-mask-cache`).
    pub mask_cache: Option<PathBuf>,
    /// Mixing weight.
    pub weight: f64,
}

impl Default for MixSource {
    fn default() -> Self {
        Self {
            dataset: PathBuf::new(),
            split: "train".into(),
            video_key: None,
            masks: MaskSource::Calc,
            seg_masks: None,
            robot: None,
            mask_cache: None,
            weight: 1.0,
        }
    }
}

impl DataSection {
    /// Every source of the mixture: `[data]` itself, then `[[data.mix]]`.
    pub fn sources(&self) -> Result<Vec<SourceSpec>> {
        let primary = MixSource {
            dataset: self.dataset.clone(),
            split: self.split.clone(),
            video_key: self.video_key.clone(),
            masks: self.masks,
            seg_masks: self.seg_masks.clone(),
            robot: self.robot.clone(),
            mask_cache: self.mask_cache.clone(),
            weight: self.weight,
        };
        std::iter::once(&primary)
            .chain(&self.mix)
            .enumerate()
            .map(|(i, m)| {
                let what = if i == 0 {
                    "data".to_string()
                } else {
                    format!("data.mix[{}]", i - 1)
                };
                let masks = match m.masks {
                    MaskSource::Calc => MaskKind::Calc {
                        robot: m.robot.clone(),
                        cache: m
                            .mask_cache
                            .clone()
                            .unwrap_or_else(|| m.dataset.join(".bridgev2w-mask-cache")),
                    },
                    MaskSource::Seg => MaskKind::Seg {
                        dir: m
                            .seg_masks
                            .clone()
                            .unwrap_or_else(|| m.dataset.join("seg_masks")),
                    },
                };
                if !(m.weight.is_finite() && m.weight > 0.0) {
                    return Err(TrainError::input(
                        format!("config {what}.weight"),
                        format!("{}: expected a finite mixing weight > 0", m.weight),
                    ));
                }
                Ok(SourceSpec {
                    root: m.dataset.clone(),
                    split: m.split.clone(),
                    video_key: m.video_key.clone(),
                    masks,
                    weight: m.weight,
                })
            })
            .collect()
    }
}

/// `[train]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TrainSection {
    /// Output folder: `checkpoints/`, `metrics.jsonl`, `config.toml`, `final/`.
    pub out: PathBuf,
    /// Seed of everything (model init, data order, noise, dropout).
    pub seed: u64,
    /// Clips per step.
    pub batch_size: usize,
    /// Optimizer steps; 0 = `epochs` x steps per epoch.
    pub max_steps: usize,
    /// Epochs (`data.clips_per_video` clips of every video each) when `max_steps` is 0.
    pub epochs: usize,
    /// AdamW learning rate (paper: 2e-5).
    pub lr: f64,
    /// AdamW beta1 (paper: 0.9).
    pub beta1: f64,
    /// AdamW beta2 (paper: 0.95).
    pub beta2: f64,
    /// AdamW epsilon (paper: 1e-8).
    pub eps: f64,
    /// AdamW decoupled weight decay (paper: 1e-4).
    pub weight_decay: f64,
    /// Global gradient-norm clip (paper: 1.0; 0 = off).
    pub grad_clip: f64,
    /// Linear warm-up steps of the otherwise constant learning rate (paper: 100).
    pub warmup_steps: usize,
    /// Weight of the dynamics-consistency loss (paper: 0.1).
    pub lambda_dyn: f64,
    /// Offsets of the dynamics loss (paper: K = 4).
    pub dyn_k: usize,
    /// Weight of the flow loss once on (paper: 0.05).
    pub lambda_flow: f64,
    /// Epoch from which the flow loss is on (paper: 5).
    pub e_switch: usize,
    /// RAFT weights (safetensors, torchvision key names) for the flow loss;
    /// absent: the differentiable Lucas-Kanade stand-in.
    pub raft_weights: Option<PathBuf>,
    /// `raft_large` or `raft_small` (with `raft_weights`).
    pub raft_model: bridgev2w_world_model::nets::raft::RaftVariant,
    /// RAFT refinement iterations.
    pub raft_iterations: usize,
    /// Image-noise augmentation of the first frame (CogVideoX I2V): sigma =
    /// exp(N(mean, std)) per clip; off when false.
    pub image_noise: bool,
    /// Mean of log sigma (CogVideoX: -3.0).
    pub image_noise_log_mean: f64,
    /// Std of log sigma (CogVideoX: 0.5).
    pub image_noise_log_std: f64,
    /// Probability of dropping the mask branch for a step (unconditional
    /// training for classifier-free guidance).
    pub condition_dropout: f64,
    /// Exponential moving average of the trained parameters
    /// ([`crate::ema`]): the decay per step, 0 = off (e.g. 0.999). The run's
    /// final weights (and a trained backbone) are the averages; `eval-run`
    /// scores them unless told `--weights raw`.
    pub ema_decay: f64,
    /// Extra weight of the diffusion loss where the robot is
    /// ([`crate::losses::motion_weights`]): each latent pixel counts
    /// `1 + w` times where the robot's silhouette in that frame or in the
    /// first frame covers it (dilated by one latent pixel), once elsewhere.
    /// 0 = the paper's plain mean (the default).
    pub motion_loss_weight: f64,
    /// Checkpoint every N steps (0 = only at the end).
    pub checkpoint_every: usize,
    /// Denoising steps of the preview clip written to the TensorBoard log at
    /// every checkpoint (prior and BridgeV2W stages; 0 = no preview).
    pub preview_steps: usize,
    /// Checkpoints kept (older ones deleted; 0 = keep all).
    pub keep_checkpoints: usize,
    /// Testing aid: from this step on, the diffusion loss is multiplied by NaN
    /// (exercises the NaN/inf guard).
    pub inject_nan_at_step: Option<usize>,
    /// What the run trains: `bridgev2w` (ControlNet + LoRA on a video prior,
    /// the paper's fine-tuning), `vae` (the backbone's VAE as an autoencoder:
    /// L1 reconstruction + `kl_weight` KL), or `prior` (the backbone
    /// transformer as an action-free image-to-video model: the diffusion and
    /// dynamics losses, no condition). `vae` and `prior` write the trained
    /// backbone as a diffusers folder to `OUT/final/backbone`, the next stage's
    /// `model.backbone`.
    pub stage: Stage,
    /// KL weight of the `vae` stage.
    pub kl_weight: f64,
    /// `vae` stage: permute each clip's RGB channels and invert half of the
    /// clips at random ([`crate::augment`]), so the autoencoder learns to
    /// reconstruct colours beyond the training palettes.
    pub color_augment: bool,
    /// `vae` stage, fresh start: the backbone's VAE was trained on single
    /// frames, so its causal convolutions' temporal taps are summed into the
    /// current frame's ([`bridgev2w_world_model::vae::inflate_image_weights`])
    /// and clip training starts from the image autoencoder applied frame by
    /// frame. Useful only without time compression (e.g. `small2x`).
    pub inflate_image_vae: bool,
    /// `vae` stage: which parts train. `all` (encoder and decoder) or
    /// `decoder` (the encoder frozen: its latents, and so every model trained
    /// on them, stay valid while the reconstruction improves; Stable
    /// Diffusion's fine-tuned decoders were made this way).
    pub vae_parts: VaeParts,
    /// Per-block gradient checkpointing of the backbone transformer
    /// (`bridgev2w` and `prior` stages): blocks run without autograd graphs
    /// and are recomputed one at a time in the backward pass. Same
    /// gradients, less activation memory, about one more forward pass of
    /// compute.
    pub gradient_checkpointing: bool,
    /// Mixed precision of the loss's forward passes: `bf16` (libtorch
    /// autocast in bfloat16: matmuls, linears and convolutions run in bf16,
    /// reductions, norms and the losses in f32; parameters, gradients and
    /// the AdamW state stay f32; the backward and the optimizer run outside
    /// the region), `off` (f32), or `auto` (the default: `bf16` on CUDA,
    /// `off` on the CPU, where bf16 matmuls are slower than f32 on most
    /// processors).
    pub autocast: Autocast,
}

impl Default for TrainSection {
    fn default() -> Self {
        Self {
            out: PathBuf::from("runs/bridgev2w"),
            seed: 0,
            batch_size: 1,
            max_steps: 0,
            epochs: 10,
            lr: 2e-5,
            beta1: 0.9,
            beta2: 0.95,
            eps: 1e-8,
            weight_decay: 1e-4,
            grad_clip: 1.0,
            warmup_steps: 100,
            lambda_dyn: 0.1,
            dyn_k: 4,
            lambda_flow: 0.05,
            e_switch: 5,
            raft_weights: None,
            raft_model: bridgev2w_world_model::nets::raft::RaftVariant::RaftLarge,
            raft_iterations: 12,
            image_noise: true,
            image_noise_log_mean: -3.0,
            image_noise_log_std: 0.5,
            condition_dropout: 0.1,
            ema_decay: 0.0,
            motion_loss_weight: 0.0,
            checkpoint_every: 100,
            preview_steps: 10,
            keep_checkpoints: 3,
            inject_nan_at_step: None,
            stage: Stage::Bridgev2w,
            kl_weight: 1e-4,
            color_augment: false,
            inflate_image_vae: false,
            vae_parts: VaeParts::All,
            gradient_checkpointing: false,
            autocast: Autocast::Auto,
        }
    }
}

/// Where a dataset's embodiment masks come from (`data.masks`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum MaskSource {
    /// Rendered from the URDF and the calibration: the dataset's `masks/`,
    /// else rendered for `data.robot` and cached.
    #[default]
    Calc,
    /// Segmentation PNG folders under `seg_masks`.
    Seg,
}

bridgev2w_world_model::named_enum!(MaskSource, TrainError, TrainError::input, "data.masks", {
    Calc => "calc",
    Seg => "seg",
});

/// Mixed precision of the loss's forward passes (`train.autocast`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Autocast {
    /// bf16 on CUDA, off on the CPU.
    #[default]
    Auto,
    /// bf16 autocast.
    Bf16,
    /// f32.
    Off,
}

bridgev2w_world_model::named_enum!(Autocast, TrainError, TrainError::input, "train.autocast", {
    Auto => "auto",
    Bf16 => "bf16",
    Off => "off",
});

/// Which parts of the VAE a `vae` stage trains (`train.vae_parts`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VaeParts {
    /// Encoder and decoder.
    #[default]
    All,
    /// The decoder (and `post_quant_conv`); the encoder frozen.
    Decoder,
}

bridgev2w_world_model::named_enum!(VaeParts, TrainError, TrainError::input, "train.vae_parts", {
    All => "all",
    Decoder => "decoder",
});

impl VaeParts {
    /// Whether the VAE variable `name` (its checkpoint key, e.g.
    /// `decoder.conv_in.conv.weight`) trains.
    pub fn trains(self, name: &str) -> bool {
        match self {
            Self::All => true,
            Self::Decoder => name.starts_with("decoder.") || name.starts_with("post_quant_conv."),
        }
    }
}

/// What a run trains (`train.stage`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Stage {
    /// ControlNet + LoRA on a video prior: the paper's fine-tuning.
    #[default]
    Bridgev2w,
    /// The backbone's VAE as an autoencoder (L1 reconstruction + KL).
    Vae,
    /// The backbone transformer as an action-free image-to-video model.
    Prior,
}

bridgev2w_world_model::named_enum!(Stage, TrainError, TrainError::input, "train.stage", {
    Bridgev2w => "bridgev2w",
    Vae => "vae",
    Prior => "prior",
});

/// `[ablation]`: the paper's switches (all `true` = full BridgeV2W).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AblationSection {
    /// Condition on embodiment masks through the ControlNet (false: the
    /// end-effector actions through an MLP instead).
    pub mask_action: bool,
    /// Zero-initialised ControlNet projections (false: default-initialised branch).
    pub controlnet: bool,
    /// Use the flow loss (after `e_switch`).
    pub flow_loss: bool,
    /// Start from the pretrained backbone (false: random transformer weights,
    /// trained with the adapters; the VAE is still loaded).
    pub pretrained: bool,
}

impl Default for AblationSection {
    fn default() -> Self {
        Self {
            mask_action: true,
            controlnet: true,
            flow_loss: true,
            pretrained: true,
        }
    }
}

/// The most steps (`train.max_steps`) a run may have.
pub const MAX_STEPS: usize = 1_000_000_000;

/// The largest `train.lr` accepted: AdamW moves each weight by about the
/// learning rate a step, and a weight moved by 1 a step diverges.
pub const MAX_LR: f64 = 1.0;

impl TrainConfig {
    /// Parses a TOML file.
    pub fn from_file(path: &Path) -> Result<Self> {
        let text = std::fs::read_to_string(path)
            .map_err(|e| TrainError::input(format!("config {}", path.display()), e.to_string()))?;
        Self::from_toml(&text)
            .map_err(|e| TrainError::input(format!("config {}", path.display()), e.to_string()))
    }

    /// Parses TOML text and validates it.
    pub fn from_toml(text: &str) -> Result<Self> {
        let cfg: Self =
            toml::from_str(text).map_err(|e| TrainError::input("config", e.to_string()))?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// The configuration as TOML.
    pub fn to_toml(&self) -> Result<String> {
        toml::to_string_pretty(self).map_err(|e| TrainError::input("config", e.to_string()))
    }

    /// The ControlNet's block count for a backbone of `backbone_layers`
    /// blocks (see [`ModelSection::controlnet_layers`]).
    pub fn controlnet_blocks(&self, backbone_layers: usize) -> Result<usize> {
        match self.model.controlnet_layers {
            None => Ok(backbone_layers.min(8)),
            Some(n) if (1..=backbone_layers).contains(&n) => Ok(n),
            Some(n) => Err(TrainError::input(
                "config model.controlnet_layers",
                format!("{n}: expected 1..={backbone_layers} (the backbone's blocks)"),
            )),
        }
    }

    /// Checks value ranges.
    pub fn validate(&self) -> Result<()> {
        let t = &self.train;
        let bad = |what: &str, msg: String| Err(TrainError::input(format!("config {what}"), msg));
        if t.batch_size == 0 {
            return bad("train.batch_size", "0: expected at least 1".into());
        }
        if t.max_steps == 0 && t.epochs == 0 {
            return bad(
                "train.max_steps/epochs",
                "both 0: give a number of steps or epochs".into(),
            );
        }
        if !(t.lr > 0.0 && t.lr <= MAX_LR) {
            return bad(
                "train.lr",
                format!(
                    "{}: expected a finite learning rate > 0 and at most {MAX_LR} (MAX_LR; the paper's: 2e-5)",
                    t.lr
                ),
            );
        }
        // AdamW divides by sqrt(v) + eps: a parameter whose gradient is 0
        // (LoRA's A while B is still 0) would get 0 / 0.
        if !(t.eps.is_finite() && t.eps > 0.0) {
            return bad(
                "train.eps",
                format!("{}: expected a finite value > 0 (the paper's: 1e-8)", t.eps),
            );
        }
        if !(0.0..1.0).contains(&t.ema_decay) {
            return bad(
                "train.ema_decay",
                format!(
                    "{}: expected a decay in [0, 1) (0 = no average, e.g. 0.999)",
                    t.ema_decay
                ),
            );
        }
        for (name, v) in [
            ("train.weight_decay", t.weight_decay),
            ("train.grad_clip", t.grad_clip),
            ("train.lambda_dyn", t.lambda_dyn),
            ("train.lambda_flow", t.lambda_flow),
            ("train.motion_loss_weight", t.motion_loss_weight),
        ] {
            if !v.is_finite() || v < 0.0 {
                return bad(name, format!("{v}: expected a finite value >= 0"));
            }
        }
        for (name, v) in [("train.beta1", t.beta1), ("train.beta2", t.beta2)] {
            if !(0.0..1.0).contains(&v) {
                return bad(name, format!("{v}: expected [0, 1)"));
            }
        }
        if !(0.0..=1.0).contains(&t.condition_dropout) {
            return bad(
                "train.condition_dropout",
                format!("{}: expected a probability", t.condition_dropout),
            );
        }
        if !(t.image_noise_log_mean.is_finite()
            && t.image_noise_log_std.is_finite()
            && t.image_noise_log_std >= 0.0)
        {
            return bad(
                "train.image_noise_log_mean/std",
                format!(
                    "{} / {}: expected a finite mean and a finite std >= 0",
                    t.image_noise_log_mean, t.image_noise_log_std
                ),
            );
        }
        if !(t.kl_weight.is_finite() && t.kl_weight >= 0.0) {
            return bad(
                "train.kl_weight",
                format!("{}: expected a finite value >= 0", t.kl_weight),
            );
        }
        if t.inflate_image_vae && t.stage != Stage::Vae {
            return bad(
                "train.inflate_image_vae",
                format!(
                    "true with stage \"{}\": it starts a \"vae\" stage from an image autoencoder",
                    t.stage
                ),
            );
        }
        if t.vae_parts != VaeParts::All && t.stage != Stage::Vae {
            return bad(
                "train.vae_parts",
                format!(
                    "\"{}\" with stage \"{}\": it chooses what a \"vae\" stage trains",
                    t.vae_parts, t.stage
                ),
            );
        }
        if t.vae_parts == VaeParts::Decoder && t.inflate_image_vae {
            return bad(
                "train.vae_parts",
                "\"decoder\" with inflate_image_vae = true: inflating rewrites the encoder that \"decoder\" keeps".into(),
            );
        }
        if self.data.clips_per_video == 0 {
            return bad("data.clips_per_video", "0: expected at least 1".into());
        }
        self.data.sources()?;
        if t.dyn_k == 0 {
            return bad("train.dyn_k", "0: expected K >= 1".into());
        }
        // Checked whatever the rank: a run without LoRA still records it.
        if !(self.model.lora_alpha.is_finite() && self.model.lora_alpha > 0.0) {
            return bad(
                "model.lora_alpha",
                format!("{}: expected a finite value > 0", self.model.lora_alpha),
            );
        }
        let backbone = self
            .model
            .backbone
            .parse::<ModelSpec>()
            .map_err(|e| TrainError::input("config model.backbone", e.to_string()))?;
        if let Some(preset) = &self.model.transformer {
            if matches!(backbone, ModelSpec::Random(_)) {
                return bad(
                    "model.transformer",
                    format!(
                        "`{preset}` with model.backbone = `{}`: a random backbone already names its transformer; use model.backbone = \"random:{preset}\" or a backbone folder",
                        self.model.backbone
                    ),
                );
            }
            if let Err(e) = TransformerConfig::preset(preset) {
                return bad("model.transformer", e.to_string());
            }
        }
        if let (Some(size), Stage::Vae) = (self.model.vae_tile, t.stage) {
            return bad(
                "model.vae_tile",
                format!(
                    "{size}: the vae stage trains the autoencoder on whole frames; remove \
                     model.vae_tile (it tiles the VAE in the prior and bridgev2w stages)"
                ),
            );
        }
        if self.model.controlnet_layers == Some(0) {
            return bad("model.controlnet_layers", "0: expected at least 1".into());
        }
        if self.model.action_hidden <= 0 {
            return bad(
                "model.action_hidden",
                format!("{}: expected > 0", self.model.action_hidden),
            );
        }
        // Upper bounds, checked before anything is allocated: far above any
        // real run, far below what would exhaust memory at the first step.
        for (name, v, max) in [
            ("data.frames", self.data.frames, 1024),
            ("data.width", self.data.width, 8192),
            ("data.height", self.data.height, 8192),
            ("data.clips_per_video", self.data.clips_per_video, 10_000),
            ("train.batch_size", t.batch_size, 65_536),
            ("train.dyn_k", t.dyn_k, 1024),
            ("model.lora_rank", self.model.lora_rank, 65_536),
            (
                "model.controlnet_layers",
                self.model.controlnet_layers.unwrap_or(1),
                1024,
            ),
            (
                "model.action_hidden",
                self.model.action_hidden.max(0) as usize,
                1 << 20,
            ),
            ("train.max_steps", t.max_steps, MAX_STEPS),
            ("train.epochs", t.epochs, 1_000_000_000),
        ] {
            if v > max {
                return bad(name, format!("{v}: at most {max} is supported"));
            }
        }
        Ok(())
    }

    /// The learning rate at `step` (0-based): linear warm-up over
    /// `warmup_steps` (`lr * (step + 1) / warmup`), then constant.
    pub fn lr_at(&self, step: usize) -> f64 {
        let w = self.train.warmup_steps;
        if w == 0 || step + 1 >= w {
            self.train.lr
        } else {
            self.train.lr * (step + 1) as f64 / w as f64
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests;
