//! The trainer: builds the model and data from a [`TrainConfig`], runs the
//! paper's objective (v-prediction diffusion + `lambda_dyn` dynamics
//! consistency + `lambda_flow` flow loss after `e_switch` epochs) with AdamW
//! over the adapters, and writes atomic, exactly resumable checkpoints.
//!
//! Determinism: every random draw of step `s` (data order, clip starts,
//! timesteps, noise, VAE posterior samples, image-noise sigma, condition
//! dropout) comes from `(seed, s)`, so the RNG state of a checkpoint is its
//! step, and a resumed run repeats an uninterrupted run's loss curve.
//!
//! Stages (`train.stage`): `bridgev2w` (the above), `vae` and `prior` (a
//! video prior trained here, see [`Trainer::save_trained_backbone`]).
//!
//! Per-block gradient checkpointing of the backbone: `train.gradient_checkpointing`.
//!
//! Mixed precision: `train.autocast` (bf16 autocast around the loss's
//! forward passes, by default on CUDA only; see [`Trainer::autocast_dtype`]).
//!
//! Data-parallel training: [`Trainer::new_distributed`] with a
//! [`DistEnv`] (torchrun-style environment, see [`crate::distributed`]):
//! each rank trains on the items `rank, rank + world, ...` of every step's
//! global batch, with the random draws of the whole batch (so the ranks
//! together compute what one process computes on the whole batch), and the
//! gradients are averaged over the ranks before clipping and AdamW. Rank 0
//! writes the metrics and checkpoints.

use crate::action::ActionEncoder;
use crate::augment::{recolor, ColorDraw};
use crate::config::{Autocast, Stage, TrainConfig};
use crate::data::{rng_for, seed_for, Batch, ClipDataset};
use crate::distributed::{Collective, DistEnv};
use crate::ema::Ema;
use crate::flow::{flow_loss, flow_weight, FlowEstimator, FlowLossConfig, LucasKanade, RaftFlow};
use crate::losses::{diffusion_loss, dynamics_loss, predicted_x0};
use crate::optim::{AdamW, AdamWConfig};
use crate::run_dir::{self, ExistingRun};
use crate::{Result, TrainError};
use bridgev2w_torch_ext::{autocast, AutocastDevice, AutocastDtype, AutocastGuard};
use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
use bridgev2w_world_model::controlnet::ControlNetConfig;
use bridgev2w_world_model::device::{ComputeDevice, Precision};
use bridgev2w_world_model::lora::LoraConfig;
use bridgev2w_world_model::pipeline::{sample_latents, Denoiser, Guidance, SampleOptions};
use bridgev2w_world_model::scheduler::{Scheduler, SchedulerConfig};
use bridgev2w_world_model::spec::ModelSpec;
use bridgev2w_world_model::transformer::{CheckpointedForward, TransformerConfig};
use bridgev2w_world_model::vae::VaeConfig;
use rand::Rng;
use rand_distr_free::normal;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tch::nn::VarStore;
use tch::{Kind, Tensor};

/// Box-Muller normal draws from a `rand` RNG (no extra dependency).
mod rand_distr_free {
    use rand::Rng;

    /// One draw of `N(mean, std^2)`.
    pub fn normal(rng: &mut impl Rng, mean: f64, std: f64) -> f64 {
        let u1: f64 = rng.gen_range(f64::MIN_POSITIVE..1.0);
        let u2: f64 = rng.gen();
        mean + std * (-2.0 * u1.ln()).sqrt() * (2.0 * std::f64::consts::PI * u2).cos()
    }
}

/// What one step measured.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct StepMetrics {
    /// Step index (0-based; the update it made is the `step + 1`-th).
    pub step: usize,
    /// Epoch of the step.
    pub epoch: usize,
    /// The total loss.
    pub loss: f64,
    /// The diffusion loss.
    pub diffusion: f64,
    /// The dynamics-consistency loss (unweighted).
    pub dynamics: f64,
    /// The flow loss (unweighted; 0 when off).
    pub flow: f64,
    /// The flow weight of this step (0 before `e_switch`).
    pub flow_weight: f64,
    /// Learning rate.
    pub lr: f64,
    /// Gradient norm before clipping.
    pub grad_norm: f64,
    /// Whether the condition was dropped (unconditional step).
    pub dropped: bool,
    /// Wall time of the step, seconds.
    pub secs: f64,
    /// `vae` stage: L1 reconstruction loss (0 in other stages).
    #[serde(default)]
    pub recon: f64,
    /// `vae` stage: KL divergence of the posterior from N(0, I), per element.
    #[serde(default)]
    pub kl: f64,
}

/// The losses of one forward pass.
#[derive(Debug)]
pub struct Losses {
    /// The weighted total (differentiable).
    pub total: Tensor,
    /// Diffusion loss value.
    pub diffusion: f64,
    /// Dynamics loss value.
    pub dynamics: f64,
    /// Flow loss value (0 when off).
    pub flow: f64,
    /// Flow weight used.
    pub flow_weight: f64,
    /// Whether the condition was dropped.
    pub dropped: bool,
    /// `vae` stage: reconstruction loss.
    pub recon: f64,
    /// `vae` stage: KL term.
    pub kl: f64,
    /// With gradient checkpointing: the record whose
    /// [`CheckpointedForward::backward`] must follow `total.backward()`.
    pub checkpointed: Option<CheckpointedForward>,
}

/// The trainer.
#[derive(Debug)]
pub struct Trainer {
    /// The configuration.
    pub cfg: TrainConfig,
    /// The model.
    pub model: BridgeV2W,
    /// The training clips.
    pub data: ClipDataset,
    /// The action MLP's variables (`mask_action = false`).
    pub action_vs: Option<VarStore>,
    action: Option<ActionEncoder>,
    estimator: Box<dyn FlowEstimator>,
    flow_cfg: FlowLossConfig,
    scheduler: Scheduler,
    /// The optimizer over the trainable variables.
    pub opt: AdamW,
    /// The moving average of the trainable variables (`train.ema_decay > 0`).
    ema: Option<Ema>,
    /// Completed optimizer steps.
    pub step: usize,
    /// The autocast dtype of the loss's forward passes (`None`: f32).
    autocast: Option<AutocastDtype>,
    /// Data-parallel training: the gradient all-reduce (`None`: one process).
    collective: Option<Box<dyn Collective>>,
    /// What [`Self::run`] does when `train.out` already holds a run.
    existing_run: ExistingRun,
}

/// The VAE and transformer presets of a `random:PRESET` backbone; `None`
/// for a diffusers folder.
fn random_preset(backbone: &str) -> Result<Option<(VaeConfig, TransformerConfig)>> {
    match backbone.parse::<ModelSpec>() {
        Ok(ModelSpec::Random(preset)) => Ok(Some(preset.configs())),
        Ok(ModelSpec::Folder(_)) => Ok(None),
        Err(e) => Err(TrainError::input("config model.backbone", e.to_string())),
    }
}

/// `train.autocast` on `device`: `auto` is bf16 on CUDA, off on the CPU.
fn resolve_autocast(setting: Autocast, device: ComputeDevice) -> Option<AutocastDtype> {
    match (setting, device) {
        (Autocast::Bf16, _) | (Autocast::Auto, ComputeDevice::Cuda(_)) => {
            Some(AutocastDtype::BFloat16)
        }
        (Autocast::Off, _) | (Autocast::Auto, ComputeDevice::Cpu) => None,
    }
}

/// A hash of the configuration as every rank must share it (the output
/// folder aside), compared at the data-parallel rendezvous.
fn config_fingerprint(cfg: &TrainConfig) -> Result<u64> {
    use std::hash::{Hash, Hasher};
    let mut c = cfg.clone();
    c.train.out = PathBuf::new();
    let text = c.to_toml()?;
    // SipHash with fixed keys: the same value in every process of this build.
    let mut h = std::collections::hash_map::DefaultHasher::new();
    text.hash(&mut h);
    Ok(h.finish())
}

/// Checks that `rank` is one of `world` ranks and that `train.batch_size`
/// divides among them (every rank takes `batch_size / world` items a step).
fn check_ranks(cfg: &TrainConfig, rank: usize, world: usize) -> Result<()> {
    if rank >= world {
        return Err(TrainError::input(
            "RANK",
            format!("{rank}: expected 0..WORLD_SIZE={world}"),
        ));
    }
    if cfg.train.batch_size % world != 0 {
        return Err(TrainError::input(
            "config train.batch_size",
            format!(
                "{} is not divisible by WORLD_SIZE={world}: every rank takes batch_size / WORLD_SIZE items of a step",
                cfg.train.batch_size
            ),
        ));
    }
    Ok(())
}

/// The items `rank, rank + world, ...` of a global batch's per-item list
/// (`(0, 1)`: all of them).
fn rank_items<T>(items: Vec<T>, (rank, world): (usize, usize)) -> Vec<T> {
    items.into_iter().skip(rank).step_by(world).collect()
}

fn parse_device(s: &str) -> Result<ComputeDevice> {
    s.parse::<ComputeDevice>()
        .map_err(|e| TrainError::input("config model.device", e.to_string()))
}

impl Trainer {
    /// Builds the model, reads the data, creates the optimizer (step 0).
    pub fn new(cfg: TrainConfig) -> Result<Self> {
        Self::new_distributed(cfg, None)
    }

    /// [`Self::new`] as one rank of a data-parallel run (`env`; `None`: a
    /// single process): checks that `train.batch_size` divides among the
    /// ranks, on CUDA uses device `LOCAL_RANK` (default `RANK`), and meets
    /// the other ranks (rank 0 at `MASTER_ADDR:MASTER_PORT`) before building
    /// the model: NCCL on CUDA, the TCP backend on the CPU.
    pub fn new_distributed(cfg: TrainConfig, env: Option<DistEnv>) -> Result<Self> {
        cfg.validate()?;
        let mut device = parse_device(&cfg.model.device)?;
        let collective = match &env {
            None => None,
            Some(env) => {
                check_ranks(&cfg, env.rank, env.world)?;
                if let ComputeDevice::Cuda(_) = device {
                    device = ComputeDevice::Cuda(env.local_rank.unwrap_or(env.rank));
                }
                device = device
                    .check_available()
                    .map_err(|e| TrainError::input("LOCAL_RANK / model.device", e.to_string()))?;
                Some(crate::distributed::connect(
                    env,
                    device.to_tch(),
                    config_fingerprint(&cfg)?,
                )?)
            }
        };
        let autocast = resolve_autocast(cfg.train.autocast, device);
        let random = random_preset(&cfg.model.backbone)?;
        let (frames, height, width) = {
            let d = &cfg.data;
            let (f, h, w) = if random.is_some() {
                (9, 64, 96)
            } else {
                (25, 480, 720)
            };
            (
                if d.frames == 0 { f } else { d.frames },
                if d.height == 0 { h } else { d.height },
                if d.width == 0 { w } else { d.width },
            )
        };
        let data = ClipDataset::open_sources(
            &cfg.data.sources()?,
            frames,
            height,
            width,
            cfg.data.clips_per_video,
        )?;
        if cfg.ablation.mask_action && cfg.train.stage == Stage::Bridgev2w && !data.has_masks() {
            return Err(TrainError::input(
                format!("dataset {}", cfg.data.dataset.display()),
                "mask conditioning needs masks for every episode: masks/episode_*.npy, data.robot to render calc masks, or data.masks = \"seg\"",
            ));
        }
        let mut model = build_model(&cfg, device, frames, height, width)?;
        let tf_cfg = model.transformer.model.config().clone();
        let train_backbone =
            cfg.model.train_backbone || !cfg.ablation.pretrained || cfg.model.transformer.is_some();
        let (action_vs, action) = if cfg.ablation.mask_action || cfg.train.stage != Stage::Bridgev2w
        {
            (None, None)
        } else {
            tch::manual_seed(seed_for(cfg.train.seed, u64::MAX, 7) as i64);
            let vs = VarStore::new(model.device());
            let enc = ActionEncoder::new(
                &(vs.root() / "action_encoder"),
                data.action_dim as i64,
                model.vae.config().temporal_compression_ratio as i64,
                cfg.model.action_hidden,
                tf_cfg.inner_dim(),
                cfg.controlnet_blocks(tf_cfg.num_layers as usize)?,
            );
            let (mean, std) = data.action_stats();
            enc.set_stats(&mean, &std)?;
            (Some(vs), Some(enc))
        };
        // Trainable: LoRA (+ the ControlNet when masks condition), the action
        // MLP, the backbone when trained from scratch.
        let stage = cfg.train.stage;
        let mut params: Vec<(String, Tensor)> = Vec::new();
        for (name, t) in model.adapters.variables() {
            if stage != Stage::Bridgev2w || !t.requires_grad() {
                continue;
            }
            if !cfg.ablation.mask_action && name.starts_with("controlnet.") {
                continue;
            }
            params.push((format!("adapters.{name}"), t));
        }
        if stage == Stage::Vae {
            if cfg.train.inflate_image_vae {
                bridgev2w_world_model::vae::inflate_image_weights(&model.vae_vs);
            }
            model.vae_vs.unfreeze();
            for (name, t) in model.vae_vs.variables() {
                params.push((format!("vae.{name}"), t));
            }
        }
        if let Some(vs) = &action_vs {
            for (name, t) in vs.variables() {
                if t.requires_grad() {
                    params.push((format!("action.{name}"), t));
                }
            }
        }
        if (train_backbone && stage == Stage::Bridgev2w) || stage == Stage::Prior {
            model.transformer.vs.unfreeze();
            for (name, t) in model.transformer.vs.variables() {
                params.push((format!("backbone.{name}"), t));
            }
        }
        let opt = AdamW::new(
            params,
            AdamWConfig {
                beta1: cfg.train.beta1,
                beta2: cfg.train.beta2,
                eps: cfg.train.eps,
                weight_decay: cfg.train.weight_decay,
            },
        );
        let ema = (cfg.train.ema_decay > 0.0).then(|| Ema::new(cfg.train.ema_decay, opt.params()));
        let estimator: Box<dyn FlowEstimator> = match &cfg.train.raft_weights {
            Some(path) => {
                use bridgev2w_world_model::nets::raft::{Raft, RaftConfig};
                let raft = Raft::load(
                    RaftConfig::by_name(&cfg.train.raft_model)?,
                    std::slice::from_ref(path),
                    device,
                )?;
                Box::new(RaftFlow {
                    raft,
                    iterations: cfg.train.raft_iterations,
                })
            }
            None => Box::new(LucasKanade::default()),
        };
        let scheduler = Scheduler::new(model.scheduler.clone())?;
        Ok(Self {
            cfg,
            model,
            data,
            action_vs,
            action,
            estimator,
            flow_cfg: FlowLossConfig::default(),
            scheduler,
            opt,
            ema,
            step: 0,
            autocast,
            collective,
            existing_run: ExistingRun::Refuse,
        })
    }

    /// [`Self::new`] with a ready data-parallel backend (e.g. a custom
    /// [`Collective`]); `train.batch_size` must divide by its world size.
    pub fn with_collective(cfg: TrainConfig, collective: Box<dyn Collective>) -> Result<Self> {
        check_ranks(&cfg, collective.rank(), collective.world())?;
        let mut t = Self::new(cfg)?;
        t.collective = Some(collective);
        Ok(t)
    }

    /// `(rank, world size)` of a data-parallel run; `(0, 1)` for one process.
    pub fn rank_and_world(&self) -> (usize, usize) {
        self.collective
            .as_ref()
            .map_or((0, 1), |c| (c.rank(), c.world()))
    }

    /// The data-parallel backend's name (`None`: one process).
    pub fn collective_name(&self) -> Option<&'static str> {
        self.collective.as_ref().map(|c| c.name())
    }

    /// Whether this process writes metrics and checkpoints (rank 0).
    pub fn is_primary(&self) -> bool {
        self.rank_and_world().0 == 0
    }

    /// This rank's items of a global batch (`rank, rank + world, ...`) as an
    /// index tensor; `None` for one process.
    fn shard_index(&self, global: i64, device: tch::Device) -> Option<Tensor> {
        let (rank, world) = self.rank_and_world();
        (world > 1).then(|| {
            let idx = rank_items((0..global).collect(), (rank, world));
            Tensor::from_slice(&idx).to_device(device)
        })
    }

    /// Standard normal noise for this rank's rows `local` `[b, ...]`: the
    /// rows of the global batch's draw (`[b * world, ...]` from libtorch's
    /// generator), so the ranks together use the single process's noise.
    fn shard_randn(&self, local: &Tensor) -> Tensor {
        let mut size = local.size();
        let (_, world) = self.rank_and_world();
        size[0] *= world as i64;
        match self.shard_index(size[0], local.device()) {
            None => local.randn_like(),
            Some(idx) => {
                // `randn_like` is `empty_like` (which keeps the strides of a
                // permuted tensor such as the latents) then `normal_`, whose
                // CPU kernel differs for contiguous and strided tensors: make
                // the global tensor with the same layout and fill it the same way.
                let strides = local.stride();
                let mut order: Vec<usize> = (0..size.len()).collect();
                order.sort_by(|&a, &b| strides[b].cmp(&strides[a]));
                let mem_size: Vec<i64> = order.iter().map(|&d| size[d]).collect();
                let mut inverse = vec![0i64; order.len()];
                for (pos, &d) in order.iter().enumerate() {
                    inverse[d] = pos as i64;
                }
                let mut global = Tensor::empty(mem_size.as_slice(), (local.kind(), local.device()))
                    .permute(inverse.as_slice());
                let _ = global.normal_(0.0, 1.0);
                global.index_select(0, &idx)
            }
        }
    }

    /// `post.sample(seed)` for this rank's rows of the global batch.
    fn shard_sample(
        &self,
        post: &bridgev2w_world_model::vae::Posterior,
        seed: u64,
    ) -> Result<Tensor> {
        let mean = post.mean();
        let mut size = mean.size();
        let (_, world) = self.rank_and_world();
        size[0] *= world as i64;
        match self.shard_index(size[0], tch::Device::Cpu) {
            None => Ok(post.sample(seed)?),
            Some(idx) => {
                // As `sample`: the generators seeded with `seed`, CPU noise.
                tch::manual_seed(seed as i64);
                let noise = Tensor::f_randn(size.as_slice(), (mean.kind(), tch::Device::Cpu))?
                    .index_select(0, &idx);
                Ok(post.sample_with_noise(&noise)?)
            }
        }
    }

    /// `model.encode_latents(video, Some(seed))` with this rank's rows of
    /// the global batch's posterior noise.
    fn encode_sampled(&self, video: &Tensor, seed: u64) -> Result<Tensor> {
        let model = &self.model;
        if self.collective.is_none() {
            return Ok(model.encode_latents(video, Some(seed))?);
        }
        let post = model.vae.encode(video)?;
        let z = self.shard_sample(&post, seed)?;
        Ok(model
            .vae
            .scale_latents(&z)
            .permute([0, 2, 1, 3, 4])
            .to_device(model.device())
            .to_kind(model.kind()))
    }

    /// `model.image_latents(first, Some(seed))` with this rank's noise rows.
    fn image_latents_sampled(&self, first: &Tensor, seed: u64, frames: i64) -> Result<Tensor> {
        let model = &self.model;
        if self.collective.is_none() {
            return Ok(model.image_latents(first, Some(seed))?);
        }
        let z = self.encode_sampled(&first.unsqueeze(2), seed)?; // [B, 1, C, h, w]
        Ok(model.config().image_conditioning.expand(&z, frames)) // [B, t, C, h, w]
    }

    /// The dtype the loss's forward passes autocast to (`None`: f32), from
    /// `train.autocast` and the device.
    pub fn autocast_dtype(&self) -> Option<AutocastDtype> {
        self.autocast
    }

    /// The flow estimator's name (for reports).
    pub fn flow_estimator_name(&self) -> String {
        self.estimator.name()
    }

    /// Steps per epoch.
    pub fn steps_per_epoch(&self) -> usize {
        self.data.steps_per_epoch(self.cfg.train.batch_size)
    }

    /// The total number of steps of the run.
    pub fn total_steps(&self) -> usize {
        if self.cfg.train.max_steps > 0 {
            self.cfg.train.max_steps
        } else {
            self.cfg.train.epochs * self.steps_per_epoch()
        }
    }

    /// This process's batch of step `step`: the whole batch, or in a
    /// data-parallel run this rank's items (`rank, rank + world, ...`).
    pub fn batch(&self, step: usize) -> Result<Batch> {
        let clips = self
            .data
            .batch_clips(self.cfg.train.seed, step, self.cfg.train.batch_size);
        let mine = rank_items(clips, self.rank_and_world());
        self.data.clips(&mine, self.model.device())
    }

    /// The whole batch of step `step` (every rank's items).
    pub fn global_batch(&self, step: usize) -> Result<Batch> {
        self.data.batch(
            self.cfg.train.seed,
            step,
            self.cfg.train.batch_size,
            self.model.device(),
        )
    }

    /// The model's prediction `[B, 3, T, H, W]` in [-1, 1] for `batch`: from
    /// the first frames (posterior mode) and the run's condition (mask
    /// branch, action MLP, or none for a prior), sampled with `opts`.
    pub fn predict(&self, batch: &Batch, opts: &SampleOptions) -> Result<Tensor> {
        let model = &self.model;
        tch::no_grad(|| -> Result<Tensor> {
            let img = model.image_latents(&batch.first_frames, None)?;
            let bridge = self.cfg.train.stage == Stage::Bridgev2w;
            let control = if bridge && self.cfg.ablation.mask_action {
                Some(model.control_latents(&batch.masks, &img)?)
            } else {
                None
            };
            let extra = match (&self.action, bridge) {
                (Some(enc), true) => {
                    let zs = img.size(); // [B, t, C, h, w]
                    let p = model.transformer.model.config().patch_size;
                    enc.residuals(
                        &batch.actions.to_device(model.device()),
                        (zs[3] / p) * (zs[4] / p),
                    )?
                }
                _ => Vec::new(),
            };
            let denoiser = RunDenoiser {
                model,
                control: control.as_ref(),
                extra: &extra,
            };
            let mut scheduler = Scheduler::new(model.scheduler.clone())?;
            let z = sample_latents(&denoiser, &mut scheduler, &img, opts)?;
            Ok(model.decode_latents(&z)?.clamp(-1.0, 1.0))
        })
    }

    /// The `vae` stage's objective: L1 reconstruction of the clip through a
    /// posterior sample plus `kl_weight` times the per-element KL from N(0, I).
    fn vae_losses(&self, batch: &Batch, step: usize) -> Result<Losses> {
        let t = &self.cfg.train;
        let vae = &self.model.vae;
        let video = if t.color_augment {
            // Per-item draws for the whole batch; this rank keeps its own.
            let rank_world = self.rank_and_world();
            let global_b = batch.video.size()[0] as usize * rank_world.1;
            let mut rng = rng_for(t.seed, step as u64, 7);
            let all: Vec<ColorDraw> = (0..global_b).map(|_| ColorDraw::sample(&mut rng)).collect();
            recolor(&batch.video, &rank_items(all, rank_world))?
        } else {
            batch.video.shallow_clone()
        };
        let post = vae.encode_with_grad(&video)?;
        let z = self.shard_sample(&post, seed_for(t.seed, step as u64, 5))?;
        let recon = vae.decode_with_grad(&z)?;
        let l1 = (recon - video.to_device(z.device()))
            .abs()
            .mean(Kind::Float);
        let (mean, logvar) = (post.mean(), post.logvar());
        let kl = ((mean * mean) + logvar.exp() - 1.0 - logvar).mean(Kind::Float) * 0.5;
        let l1 = if t.inject_nan_at_step.is_some_and(|n| step >= n) {
            l1 * f64::NAN
        } else {
            l1
        };
        let (rv, kv) = (l1.double_value(&[]), kl.double_value(&[]));
        check_finite(step, "reconstruction", rv)?;
        check_finite(step, "kl", kv)?;
        Ok(Losses {
            total: l1 + kl * t.kl_weight,
            diffusion: 0.0,
            dynamics: 0.0,
            flow: 0.0,
            flow_weight: 0.0,
            dropped: false,
            recon: rv,
            kl: kv,
            checkpointed: None,
        })
    }

    /// The objective on `batch` with the random draws of step `step`.
    pub fn losses(&self, batch: &Batch, step: usize) -> Result<Losses> {
        if self.cfg.train.stage == Stage::Vae {
            return self.vae_losses(batch, step);
        }
        let prior = self.cfg.train.stage == Stage::Prior;
        let t = &self.cfg.train;
        let seed = t.seed;
        let s = step as u64;
        tch::manual_seed(seed_for(seed, s, 3) as i64);
        let mut rng = rng_for(seed, s, 4);
        let b = batch.video.size()[0];
        let rank_world = self.rank_and_world();
        // Per-item draws are made for the whole batch; this rank keeps its own.
        let global_b = b * rank_world.1 as i64;
        let model = &self.model;
        // The frozen encoders make the targets and conditions: in f32 even
        // inside an autocast region (a guard with autocast off), so mixed
        // precision changes only the trained networks' forward passes.
        let f32_island = match (self.autocast, AutocastDevice::of(model.device())) {
            (Some(dtype), Some(dev)) => Some(AutocastGuard::new(dev, dtype, false)?),
            _ => None,
        };
        let (z0, image_latents, control) = tch::no_grad(|| -> Result<_> {
            let z0 = self.encode_sampled(&batch.video, seed_for(seed, s, 5))?;
            let mut first = batch.first_frames.shallow_clone();
            if t.image_noise {
                let all: Vec<f32> = (0..global_b)
                    .map(|_| {
                        normal(&mut rng, t.image_noise_log_mean, t.image_noise_log_std).exp() as f32
                    })
                    .collect();
                let sig = rank_items(all, rank_world);
                let sig = Tensor::from_slice(&sig)
                    .view([b, 1, 1, 1])
                    .to_device(first.device());
                first = (&first + self.shard_randn(&first) * sig).clamp(-1.0, 1.0);
            }
            let img = self.image_latents_sampled(&first, seed_for(seed, s, 6), z0.size()[1])?;
            let control = if self.cfg.ablation.mask_action && !prior {
                Some(model.control_latents(&batch.masks, &img)?)
            } else {
                None
            };
            Ok((z0, img, control))
        })?;
        drop(f32_island);
        // The prior is action-free: never conditioned.
        let dropped = rng.gen::<f64>() < t.condition_dropout || prior;
        let n_train = model.scheduler.num_train_timesteps as i64;
        let all: Vec<i64> = (0..global_b).map(|_| rng.gen_range(0..n_train)).collect();
        let ts = rank_items(all, rank_world);
        let timesteps = Tensor::from_slice(&ts).to_device(model.device());
        let noise = self.shard_randn(&z0);
        let x_t = self.scheduler.add_noise(&z0, &noise, &timesteps)?;
        let latent_in = Tensor::cat(&[&x_t, &image_latents], 2);
        let extra = match (&self.action, dropped) {
            (Some(enc), false) => {
                let zs = z0.size(); // [B, t, C, h, w]
                let p = model.transformer.model.config().patch_size;
                enc.residuals(&batch.actions, (zs[3] / p) * (zs[4] / p))?
            }
            _ => Vec::new(),
        };
        let ctrl = if dropped { None } else { control.as_ref() };
        let (v, checkpointed) = if t.gradient_checkpointing {
            let (v, record) = model.velocity_checkpointed(&latent_in, &timesteps, ctrl, &extra)?;
            (v, Some(record))
        } else {
            (
                model.velocity_with_extra(&latent_in, &timesteps, ctrl, &extra)?,
                None,
            )
        };
        let v = v.to_kind(Kind::Float);
        let alpha = self.scheduler.alpha_bar_like(&timesteps, &z0)?;
        let diff = diffusion_loss(&z0, &x_t, &v, &alpha)?;
        let diff = if t.inject_nan_at_step.is_some_and(|n| step >= n) {
            diff * f64::NAN
        } else {
            diff
        };
        let diffusion = diff.double_value(&[]);
        check_finite(step, "diffusion", diffusion)?;
        let x0 = predicted_x0(&x_t, &v, &alpha);
        let dynl = dynamics_loss(&x0, &z0, t.dyn_k)?;
        let dynamics = dynl.double_value(&[]);
        check_finite(step, "dynamics", dynamics)?;
        let total = diff + &dynl * t.lambda_dyn;
        let epoch = step / self.steps_per_epoch();
        let fw = if self.cfg.ablation.flow_loss && !prior {
            flow_weight(epoch, t.e_switch, t.lambda_flow)
        } else {
            0.0
        };
        let mut flow = 0.0;
        let total = if fw > 0.0 {
            let decoded = model.decode_latents_with_grad(&x0)?.clamp(-1.0, 1.0);
            let gt = batch.video.to_device(decoded.device());
            let fl = flow_loss(self.estimator.as_ref(), &decoded, &gt, &self.flow_cfg)?;
            flow = fl.double_value(&[]);
            check_finite(step, "flow", flow)?;
            total + fl * fw
        } else {
            total
        };
        Ok(Losses {
            total,
            diffusion,
            dynamics,
            flow,
            flow_weight: fw,
            dropped,
            recon: 0.0,
            kl: 0.0,
            checkpointed,
        })
    }

    /// One optimizer step on the next batch; the NaN/inf guard runs before
    /// any parameter changes.
    pub fn train_step(&mut self) -> Result<StepMetrics> {
        let step = self.step;
        let batch = self.batch(step)?;
        self.update(&batch, step)
    }

    /// One optimizer update on `batch` with the random draws (and learning
    /// rate, epoch) of step `step`; counts as a completed step. Tests use it
    /// to overfit one fixed batch.
    pub fn update(&mut self, batch: &Batch, step: usize) -> Result<StepMetrics> {
        let start = Instant::now();
        self.opt.zero_grad();
        let device = self.model.device();
        // The forward passes under autocast; the backward outside it (as
        // PyTorch recommends), except the checkpointed blocks' replay, which
        // must recompute them in the forward's precision.
        let l = autocast(device, self.autocast, || self.losses(batch, step))??;
        let loss = l.total.double_value(&[]);
        check_finite(step, "total", loss)?;
        l.total.backward();
        if let Some(record) = l.checkpointed {
            let model = &self.model.transformer.model;
            autocast(device, self.autocast, || record.backward(model))??;
        }
        let mut scalars = [loss, l.diffusion, l.dynamics, l.flow, l.recon, l.kl];
        self.average_gradients(&mut scalars)?;
        let [loss, diffusion, dynamics, flow, recon, kl] = scalars;
        check_finite(step, "total (all ranks)", loss)?;
        let grad_norm = self.opt.clip_grad_norm(self.cfg.train.grad_clip);
        check_finite(step, "gradient norm", grad_norm)?;
        let lr = self.cfg.lr_at(step);
        self.opt.step(lr);
        if let Some(ema) = &mut self.ema {
            ema.update(self.opt.params(), step);
        }
        self.step += 1;
        Ok(StepMetrics {
            step,
            epoch: step / self.steps_per_epoch(),
            loss,
            diffusion,
            dynamics,
            flow,
            flow_weight: l.flow_weight,
            lr,
            grad_norm,
            dropped: l.dropped,
            secs: start.elapsed().as_secs_f64(),
            recon,
            kl,
        })
    }

    /// Data-parallel runs: replaces every gradient (and the loss values in
    /// `scalars`) by its mean over the ranks: one flattened f32 buffer,
    /// scaled by `1 / world` and sum-all-reduced. Every rank holds
    /// `batch_size / world` items, so this is the gradient of the global
    /// batch's mean loss. A no-op for one process.
    fn average_gradients(&mut self, scalars: &mut [f64]) -> Result<()> {
        let Some(collective) = self.collective.as_mut() else {
            return Ok(());
        };
        let world = collective.world() as f64;
        let grads: Vec<Tensor> = self
            .opt
            .params()
            .iter()
            .map(|(_, p)| p.grad())
            .filter(|g| g.defined())
            .collect();
        let device = self.model.device();
        let mut parts: Vec<Tensor> = grads
            .iter()
            .map(|g| g.to_kind(Kind::Float).reshape(-1).to_device(device))
            .collect();
        let sc: Vec<f32> = scalars.iter().map(|&v| v as f32).collect();
        parts.push(Tensor::from_slice(&sc).to_device(device));
        let mut flat = tch::no_grad(|| Tensor::cat(&parts, 0) * (1.0 / world)).contiguous();
        collective.all_reduce_sum(&mut flat)?;
        tch::no_grad(|| {
            let mut offset = 0i64;
            for g in &grads {
                let n = g.numel() as i64;
                let chunk = flat.narrow(0, offset, n).view(g.size().as_slice());
                g.shallow_clone().copy_(&chunk.to_kind(g.kind()));
                offset += n;
            }
            let tail = Vec::<f32>::try_from(
                &flat
                    .narrow(0, offset, sc.len() as i64)
                    .to_device(tch::Device::Cpu),
            )?;
            for (v, t) in scalars.iter_mut().zip(tail) {
                *v = f64::from(t);
            }
            Ok::<(), TrainError>(())
        })
    }

    /// Lets [`Self::run`] replace a run that `train.out` already holds (its
    /// config, metrics, checkpoints and final weights; other files stay).
    /// Without it (and without [`Self::resume`]) such a folder is refused.
    pub fn overwrite_existing_run(&mut self) {
        if self.existing_run == ExistingRun::Refuse {
            self.existing_run = ExistingRun::Overwrite;
        }
    }

    /// Trains to [`Self::total_steps`], appending to `OUT/metrics.jsonl`,
    /// checkpointing every `checkpoint_every` steps and at the end
    /// (`OUT/checkpoints/step-NNNNNNNN`, `OUT/checkpoints/latest`), and
    /// writing `OUT/final/weights.safetensors`. `on_step` sees every step's metrics.
    /// A non-finite loss or gradient stops the run with an error naming the
    /// step and the term; the checkpoints written before stay as they were.
    pub fn run(&mut self, on_step: &mut dyn FnMut(&StepMetrics)) -> Result<Vec<StepMetrics>> {
        if !self.is_primary() {
            // Other ranks: the same steps (their all-reduce is rank 0's), no files.
            let total = self.total_steps();
            let mut all = Vec::new();
            while self.step < total {
                let m = self.train_step()?;
                on_step(&m);
                all.push(m);
            }
            return Ok(all);
        }
        let out = self.cfg.train.out.clone();
        run_dir::claim(&out, &self.cfg, self.existing_run)?;
        // From here on the folder is this run's own.
        self.existing_run = ExistingRun::Continue;
        std::fs::create_dir_all(&out).map_err(|e| io_err(&out, e))?;
        let cfg_text = self.cfg.to_toml()?;
        write_atomic(&out.join("config.toml"), cfg_text.as_bytes())?;
        let metrics_path = out.join("metrics.jsonl");
        truncate_metrics(&metrics_path, self.step)?;
        let mut metrics_file = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&metrics_path)
            .map_err(|e| io_err(&metrics_path, e))?;
        let total = self.total_steps();
        let every = self.cfg.train.checkpoint_every;
        let mut all = Vec::new();
        while self.step < total {
            let m = self.train_step()?;
            let line = serde_json::to_string(&m)
                .map_err(|e| TrainError::input("metrics", e.to_string()))?;
            writeln!(metrics_file, "{line}").map_err(|e| io_err(&metrics_path, e))?;
            on_step(&m);
            all.push(m);
            if (every > 0 && self.step % every == 0) || self.step == total {
                self.save_checkpoint()?;
            }
        }
        // The final weights (and backbone) are the averages, if any; the
        // last checkpoint keeps the raw parameters.
        self.use_averaged_weights();
        let fin = out.join("final");
        std::fs::create_dir_all(&fin).map_err(|e| io_err(&fin, e))?;
        self.model.save_weights(&fin.join("weights.safetensors"))?;
        if self.cfg.train.stage != Stage::Bridgev2w {
            self.save_trained_backbone(&fin.join("backbone"))?;
        }
        if let Some(vs) = &self.action_vs {
            save_named(
                vs.variables().into_iter().collect(),
                &fin.join("action_encoder.safetensors"),
            )?;
        }
        Ok(all)
    }

    /// Writes the backbone (diffusers folder) after a `vae` or `prior` stage.
    /// After `vae`, the latent `scaling_factor` is re-estimated as
    /// `1 / std` of posterior means over up to 8 training batches, so the
    /// diffusion stages see latents of unit scale (as Stable Diffusion and
    /// CogVideoX set it). Written to a temporary folder, then renamed.
    pub fn save_trained_backbone(&self, dir: &Path) -> Result<()> {
        let tmp = PathBuf::from(format!("{}.tmp", dir.display()));
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).map_err(|e| io_err(&tmp, e))?;
        }
        self.model.save_backbone(&tmp)?;
        if self.cfg.train.stage == Stage::Vae {
            let mut sum = 0f64;
            let mut sq = 0f64;
            let mut n = 0f64;
            for step in 0..self.steps_per_epoch().min(8) {
                let b = self.global_batch(step)?;
                let z = tch::no_grad(|| self.model.vae.encode(&b.video))?
                    .mode()
                    .to_kind(Kind::Double);
                sum += z.sum(Kind::Double).double_value(&[]);
                sq += (&z * &z).sum(Kind::Double).double_value(&[]);
                n += z.numel() as f64;
            }
            let std = (sq / n - (sum / n).powi(2)).max(1e-12).sqrt();
            let path = tmp.join("vae/config.json");
            let text = std::fs::read_to_string(&path).map_err(|e| io_err(&path, e))?;
            let mut v: serde_json::Value = serde_json::from_str(&text)
                .map_err(|e| TrainError::input(path.display().to_string(), e.to_string()))?;
            v["scaling_factor"] = serde_json::json!(1.0 / std);
            write_atomic(&path, v.to_string().as_bytes())?;
        }
        if dir.exists() {
            std::fs::remove_dir_all(dir).map_err(|e| io_err(dir, e))?;
        }
        std::fs::rename(&tmp, dir).map_err(|e| io_err(dir, e))
    }

    /// The checkpoint folder of `step` under the run's output.
    pub fn checkpoint_dir(&self, step: usize) -> PathBuf {
        self.cfg
            .train
            .out
            .join("checkpoints")
            .join(format!("step-{step:08}"))
    }

    /// Writes `checkpoints/step-NNNNNNNN/` (weights, trainable state, optimizer,
    /// `state.json`) into a temporary folder, renames it into place, then
    /// updates `checkpoints/latest`; prunes old checkpoints.
    pub fn save_checkpoint(&self) -> Result<PathBuf> {
        let root = self.cfg.train.out.join("checkpoints");
        std::fs::create_dir_all(&root).map_err(|e| io_err(&root, e))?;
        let name = format!("step-{:08}", self.step);
        let final_dir = root.join(&name);
        let tmp = root.join(format!(".{name}.tmp"));
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).map_err(|e| io_err(&tmp, e))?;
        }
        std::fs::create_dir_all(&tmp).map_err(|e| io_err(&tmp, e))?;
        self.model.save_weights(&tmp.join("weights.safetensors"))?;
        save_named(self.trainable_state(), &tmp.join("trainable.safetensors"))?;
        save_named(self.opt.state(), &tmp.join("optimizer.safetensors"))?;
        if let Some(ema) = &self.ema {
            save_named(ema.state(), &tmp.join("ema.safetensors"))?;
        }
        let state = serde_json::json!({
            "step": self.step,
            "seed": self.cfg.train.seed,
            "epoch": self.step / self.steps_per_epoch(),
            "rng": "derived from (seed, step): no generator state to store",
            "flow_estimator": self.estimator.name(),
        });
        write_atomic(&tmp.join("state.json"), state.to_string().as_bytes())?;
        if final_dir.exists() {
            std::fs::remove_dir_all(&final_dir).map_err(|e| io_err(&final_dir, e))?;
        }
        std::fs::rename(&tmp, &final_dir).map_err(|e| io_err(&final_dir, e))?;
        write_atomic(&root.join("latest"), name.as_bytes())?;
        self.prune_checkpoints(&root)?;
        Ok(final_dir)
    }

    /// Keeps the newest `keep_checkpoints` checkpoints up to the current step
    /// (the one just written among them); checkpoints of later steps (a run
    /// resumed from an earlier one) are left for the run to replace.
    fn prune_checkpoints(&self, root: &Path) -> Result<()> {
        let keep = self.cfg.train.keep_checkpoints;
        if keep == 0 {
            return Ok(());
        }
        let current = format!("step-{:08}", self.step);
        let mut dirs: Vec<PathBuf> = std::fs::read_dir(root)
            .map_err(|e| io_err(root, e))?
            .filter_map(|e| e.ok().map(|e| e.path()))
            .filter(|p| {
                p.is_dir()
                    && p.file_name()
                        .and_then(|n| n.to_str())
                        .is_some_and(|n| n.starts_with("step-") && *n <= *current)
            })
            .collect();
        dirs.sort();
        while dirs.len() > keep {
            let d = dirs.remove(0);
            std::fs::remove_dir_all(&d).map_err(|e| io_err(&d, e))?;
        }
        Ok(())
    }

    /// Everything the run changes: trainable parameters and the action
    /// MLP's normalisation, by prefixed name.
    fn trainable_state(&self) -> Vec<(String, Tensor)> {
        let mut named: Vec<(String, Tensor)> = self
            .opt
            .params()
            .iter()
            .map(|(n, t)| (n.clone(), t.shallow_clone()))
            .collect();
        if let Some(vs) = &self.action_vs {
            for (name, t) in vs.variables() {
                if !t.requires_grad() {
                    named.push((format!("action.{name}"), t));
                }
            }
        }
        named
    }

    /// Puts the moving averages (`train.ema_decay > 0`) into the trainable
    /// variables, for evaluating or exporting them; `false` (nothing done)
    /// for a run without averages. Training on afterwards would continue
    /// from the averages, not from the raw parameters.
    pub fn use_averaged_weights(&mut self) -> bool {
        match &self.ema {
            Some(ema) => {
                ema.copy_into(self.opt.params());
                true
            }
            None => false,
        }
    }

    /// Resumes from a checkpoint folder, or from a run folder's latest checkpoint.
    pub fn resume(&mut self, dir: &Path) -> Result<()> {
        let dir = resolve_checkpoint(dir)?;
        let state_path = dir.join("state.json");
        let text = std::fs::read_to_string(&state_path).map_err(|e| io_err(&state_path, e))?;
        let state: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| TrainError::input(state_path.display().to_string(), e.to_string()))?;
        let step = state["step"].as_u64().ok_or_else(|| {
            TrainError::input(state_path.display().to_string(), "no integer `step`")
        })?;
        // A checkpoint may lie beyond this config's steps (evaluating a run
        // that was extended with --max-steps), but not beyond any run.
        if step > crate::config::MAX_STEPS as u64 {
            return Err(TrainError::input(
                state_path.display().to_string(),
                format!(
                    "step {step} is beyond any run (at most {} steps): a corrupt state.json?",
                    crate::config::MAX_STEPS
                ),
            ));
        }
        let step = step as usize;
        if state["seed"].as_u64() != Some(self.cfg.train.seed) {
            return Err(TrainError::input(
                state_path.display().to_string(),
                format!(
                    "seed {} but the config says {}: resuming would not repeat the run",
                    state["seed"], self.cfg.train.seed
                ),
            ));
        }
        let path = dir.join("trainable.safetensors");
        let saved = bridgev2w_world_model::weights::read_safetensors(&path)?;
        crate::checkpoint::copy_named_into(&self.trainable_state(), saved, &path)?;
        // The adapters' untrained variables (e.g. the unused branch of the
        // action ablation) come from the weights file.
        self.model.load_weights(&dir.join("weights.safetensors"))?;
        let opt_path = dir.join("optimizer.safetensors");
        self.opt
            .load_state(bridgev2w_world_model::weights::read_safetensors(&opt_path)?)?;
        if let Some(ema) = &mut self.ema {
            let path = dir.join("ema.safetensors");
            if !path.is_file() {
                return Err(TrainError::input(
                    path.display().to_string(),
                    format!(
                        "missing: the config averages the weights (train.ema_decay = {}) but \
                         this checkpoint has no averages",
                        self.cfg.train.ema_decay
                    ),
                ));
            }
            ema.load(
                bridgev2w_world_model::weights::read_safetensors(&path)?,
                &path,
            )?;
        }
        self.step = step;
        self.existing_run = ExistingRun::Continue;
        Ok(())
    }
}

/// A checkpoint folder (holding `state.json`), or a run folder whose
/// `checkpoints/latest` names one.
pub fn resolve_checkpoint(dir: &Path) -> Result<PathBuf> {
    if dir.join("state.json").is_file() {
        return Ok(dir.to_path_buf());
    }
    let latest = dir.join("checkpoints").join("latest");
    let name = std::fs::read_to_string(&latest).map_err(|e| {
        TrainError::input(
            format!("--resume {}", dir.display()),
            format!(
                "neither a checkpoint (state.json) nor a run folder with checkpoints/latest: {e}"
            ),
        )
    })?;
    Ok(dir.join("checkpoints").join(name.trim()))
}

fn build_model(
    cfg: &TrainConfig,
    device: ComputeDevice,
    frames: usize,
    height: usize,
    width: usize,
) -> Result<BridgeV2W> {
    let lora = (cfg.model.lora_rank > 0).then_some(LoraConfig {
        rank: cfg.model.lora_rank as i64,
        alpha: cfg.model.lora_alpha,
    });
    let seed = seed_for(cfg.train.seed, u64::MAX, 8) as i64;
    let make_cfg = |tf: &TransformerConfig| -> Result<BridgeV2WConfig> {
        Ok(BridgeV2WConfig {
            frames,
            height,
            width,
            controlnet: ControlNetConfig {
                num_layers: cfg.controlnet_blocks(tf.num_layers as usize)?,
                conditioning_scale: Vec::new(),
                zero_init: cfg.ablation.controlnet,
            },
            lora,
            image_conditioning: cfg.model.image_conditioning,
        })
    };
    let model = if let Some((vae, tf)) = random_preset(&cfg.model.backbone)? {
        BridgeV2W::random(
            make_cfg(&tf)?,
            &vae,
            &tf,
            SchedulerConfig::cogvideox_5b_i2v(),
            device,
            seed,
        )?
    } else {
        let dir = PathBuf::from(&cfg.model.backbone);
        // model.transformer: a fresh transformer of that preset, not the folder's.
        let tf = match &cfg.model.transformer {
            Some(preset) => TransformerConfig::preset(preset)?,
            None => TransformerConfig::from_file(&dir.join("transformer").join("config.json"))?,
        };
        if cfg.ablation.pretrained && cfg.model.transformer.is_none() {
            tch::manual_seed(seed);
            BridgeV2W::load(
                &dir,
                None,
                cfg.model.prompt_embeds.as_deref(),
                make_cfg(&tf)?,
                device,
                Precision::F32,
            )?
        } else {
            // A random transformer (the folder's shapes or model.transformer's
            // preset); the pretrained VAE.
            let vae_cfg = VaeConfig::from_file(&dir.join("vae").join("config.json"))?;
            let sched =
                SchedulerConfig::load(&dir.join("scheduler").join("scheduler_config.json"))?;
            let m = BridgeV2W::random(make_cfg(&tf)?, &vae_cfg, &tf, sched, device, seed)?;
            bridgev2w_world_model::weights::load_component(&m.vae_vs, &dir.join("vae"))?;
            m
        }
    };
    if let Some(w) = &cfg.model.init_weights {
        model.load_weights(w)?;
    }
    let loaded = model.config().image_conditioning;
    if loaded != cfg.model.image_conditioning {
        return Err(TrainError::input(
            "model.image_conditioning",
            format!(
                "{}, but the backbone {} was trained with {loaded}: set model.image_conditioning = \"{loaded}\"",
                cfg.model.image_conditioning, cfg.model.backbone
            ),
        ));
    }
    Ok(model)
}

/// The run's model as a denoiser: the mask branch and/or action residuals
/// when conditioned, neither when unconditioned (classifier-free guidance).
struct RunDenoiser<'a> {
    model: &'a BridgeV2W,
    control: Option<&'a Tensor>,
    extra: &'a [Tensor],
}

impl Denoiser for RunDenoiser<'_> {
    fn velocity(
        &self,
        latent_in: &Tensor,
        timestep: &Tensor,
        guidance: Guidance,
    ) -> bridgev2w_world_model::Result<Tensor> {
        match guidance {
            Guidance::Conditional => {
                self.model
                    .velocity_with_extra(latent_in, timestep, self.control, self.extra)
            }
            Guidance::Unconditional => {
                self.model
                    .velocity_with_extra(latent_in, timestep, None, &[])
            }
        }
    }
}

fn check_finite(step: usize, term: &str, value: f64) -> Result<()> {
    if value.is_finite() {
        Ok(())
    } else {
        Err(TrainError::NonFinite {
            step,
            term: term.into(),
            value,
        })
    }
}

fn io_err(path: &Path, e: std::io::Error) -> TrainError {
    TrainError::Io {
        path: path.to_path_buf(),
        error: e,
    }
}

/// Writes `bytes` to `path` through a temporary file and a rename.
fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    let mut tmp = path.as_os_str().to_owned();
    tmp.push(".tmp");
    let tmp = PathBuf::from(tmp);
    {
        let mut f = std::fs::File::create(&tmp).map_err(|e| io_err(&tmp, e))?;
        f.write_all(bytes).map_err(|e| io_err(&tmp, e))?;
        f.sync_all().map_err(|e| io_err(&tmp, e))?;
    }
    std::fs::rename(&tmp, path).map_err(|e| io_err(path, e))
}

fn save_named(mut named: Vec<(String, Tensor)>, path: &Path) -> Result<()> {
    named.sort_by(|a, b| a.0.cmp(&b.0));
    let named: Vec<(String, Tensor)> = named
        .into_iter()
        .map(|(n, t)| (n, t.detach().to_device(tch::Device::Cpu).contiguous()))
        .collect();
    Tensor::write_safetensors(&named, path)?;
    Ok(())
}

/// Keeps the metrics lines of steps before `step` (a resumed run rewrites the rest).
fn truncate_metrics(path: &Path, step: usize) -> Result<()> {
    if !path.is_file() {
        return Ok(());
    }
    let text = std::fs::read_to_string(path).map_err(|e| io_err(path, e))?;
    let kept: String = text
        .lines()
        .filter(|l| {
            serde_json::from_str::<serde_json::Value>(l)
                .ok()
                .and_then(|v| v["step"].as_u64())
                .is_some_and(|s| (s as usize) < step)
        })
        .map(|l| format!("{l}\n"))
        .collect();
    write_atomic(path, kept.as_bytes())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn random_presets_by_name_and_an_unknown_one_lists_them() {
        let (vae, tf) = random_preset("random:small2x-wide").unwrap().unwrap();
        assert_eq!(vae, VaeConfig::small_2x());
        assert_eq!(
            tf.inner_dim(),
            2 * TransformerConfig::small_2x().inner_dim()
        );
        assert!(random_preset("some/folder").unwrap().is_none());
        let e = random_preset("random:huge").unwrap_err().to_string();
        assert!(
            e.contains("random:small2x-wide") && e.contains("random:huge"),
            "{e}"
        );
    }
}
