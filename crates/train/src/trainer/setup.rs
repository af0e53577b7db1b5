//! Building a [`Trainer`] from a [`TrainConfig`]: the device and the data-parallel
//! rendezvous, the data, the model, the action MLP, the trainable parameters and their
//! optimizer, the flow estimator.

use super::Trainer;
use crate::action::ActionEncoder;
use crate::config::{Autocast, Stage, TrainConfig};
use crate::data::{seed_for, ClipDataset};
use crate::distributed::{Collective, DistEnv};
use crate::ema::Ema;
use crate::flow::{FlowEstimator, FlowLossConfig, LucasKanade, RaftFlow};
use crate::optim::{AdamW, AdamWConfig};
use crate::run_dir::ExistingRun;
use crate::{Result, TrainError};
use bridgev2w_torch_ext::AutocastDtype;
use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
use bridgev2w_world_model::controlnet::ControlNetConfig;
use bridgev2w_world_model::device::{ComputeDevice, Precision};
use bridgev2w_world_model::lora::LoraConfig;
use bridgev2w_world_model::scheduler::{Scheduler, SchedulerConfig};
use bridgev2w_world_model::spec::ModelSpec;
use bridgev2w_world_model::transformer::TransformerConfig;
use bridgev2w_world_model::vae::{VaeConfig, VaeTiling};
use std::path::{Path, PathBuf};
use tch::nn::VarStore;
use tch::Tensor;

/// The VAE and transformer presets of a `random:PRESET` backbone; `None`
/// for a diffusers folder.
pub(super) fn random_preset(backbone: &str) -> Result<Option<(VaeConfig, TransformerConfig)>> {
    match backbone.parse::<ModelSpec>() {
        Ok(ModelSpec::Random(preset)) => Ok(Some(preset.configs())),
        Ok(ModelSpec::Folder(_)) => Ok(None),
        Err(e) => Err(TrainError::input("config model.backbone", e.to_string())),
    }
}

/// A backbone folder's weight files that the run loads, checked before the
/// data is read and before a model is built (whose clip size might not fit
/// it): the VAE's always, the transformer's when it is pretrained
/// (`ablation.pretrained` without `model.transformer`).
fn check_backbone_weights(cfg: &TrainConfig) -> Result<()> {
    if random_preset(&cfg.model.backbone)?.is_some() {
        return Ok(());
    }
    let dir = bridgev2w_world_model::hub::resolve_model_dir(Path::new(&cfg.model.backbone))?;
    let pretrained = cfg.ablation.pretrained && cfg.model.transformer.is_none();
    let components: &[&str] = if pretrained {
        &["vae", "transformer"]
    } else {
        &["vae"]
    };
    for c in components {
        bridgev2w_world_model::weights::resolve_weight_files(
            &dir.join(c),
            bridgev2w_world_model::weights::DIFFUSERS_WEIGHTS_STEM,
        )
        .map_err(|e| TrainError::input("config model.backbone", format!("{e}")))?;
    }
    Ok(())
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
        let mut device = cfg.model.device.resolve();
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
        random_preset(&cfg.model.backbone)?; // an unknown preset fails before the data is read
        check_backbone_weights(&cfg)?; // as do a folder's missing weights
        let (frames, height, width) = {
            let d = &cfg.data;
            // A random preset's own size (9 frames at 64x96, or the
            // paper's for the full-size preset); a folder: the paper's.
            let (f, h, w) = match cfg.model.backbone.parse::<ModelSpec>() {
                Ok(ModelSpec::Random(preset)) => {
                    let b = preset.bridge_config();
                    (b.frames, b.height, b.width)
                }
                _ => (25, 480, 720),
            };
            (
                if d.frames == 0 { f } else { d.frames },
                if d.height == 0 { h } else { d.height },
                if d.width == 0 { w } else { d.width },
            )
        };
        check_batch_memory(
            &cfg,
            env.as_ref().map_or(1, |e| e.world),
            (frames, height, width),
        )?;
        let mut data = ClipDataset::open_sources(
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
        if cfg.ablation.mask_action && cfg.train.stage == Stage::Bridgev2w {
            data.set_mask_coding(cfg.model.mask_coding)?;
        }
        let mut model = build_model(&cfg, device, frames, height, width)?;
        // As `predict` runs the VAE at these sizes: the clips' encoding and
        // the flow loss's decode in tiles above 256x256 (memory), or in the
        // configured ones; the vae stage trains on whole frames (`validate`
        // refuses model.vae_tile there).
        let tiling = match (cfg.model.vae_tile, cfg.train.stage) {
            (_, Stage::Vae) => VaeTiling::Off,
            (Some(size), _) => VaeTiling::Tiles(size),
            (None, _) => VaeTiling::Auto,
        };
        model
            .vae
            .set_tiling(tiling, (height, width), "config model.vae_tile")?;
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
                if cfg.train.vae_parts.trains(&name) {
                    params.push((format!("vae.{name}"), t));
                } else {
                    let _ = t.set_requires_grad(false);
                }
            }
        }
        if let Some(vs) = &action_vs {
            for (name, t) in vs.variables() {
                if t.requires_grad() {
                    params.push((format!("action.{name}"), t));
                }
            }
        }
        let backbone_trained =
            (train_backbone && stage == Stage::Bridgev2w) || stage == Stage::Prior;
        if backbone_trained {
            model.transformer.vs.unfreeze();
            for (name, t) in model.transformer.vs.variables() {
                params.push((format!("backbone.{name}"), t));
            }
        } else if let Some(dtype) = autocast {
            // The frozen backbone kept in the autocast dtype, as diffusers'
            // training scripts keep it in their weight dtype: its products
            // run in that dtype anyway, and its weights take half the memory
            // (11 GB less at 5B). The trained adapters stay f32.
            let _guard = tch::no_grad_guard();
            model.transformer.vs.set_kind(dtype.kind());
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
                    RaftConfig::of(cfg.train.raft_model),
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
}

/// Bytes per pixel of every frame of every clip of a step's batch at the
/// least: the video as floats (3 channels) and the masks as floats.
const BATCH_BYTES_PER_PIXEL: u64 = 12 + 4;

/// Refuses a run whose batch (`train.batch_size` clips among `ranks`
/// processes, of `frames` frames at `height` x `width`) alone exceeds the
/// machine's memory ([`BATCH_BYTES_PER_PIXEL`] a pixel: a floor, the model,
/// its activations and gradients come on top), before the data is read.
fn check_batch_memory(
    cfg: &TrainConfig,
    ranks: usize,
    (frames, height, width): (usize, usize, usize),
) -> Result<()> {
    let clips = cfg.train.batch_size.div_ceil(ranks.max(1));
    let estimate = bridgev2w_io::memory::bytes(&[
        clips as u64,
        frames as u64,
        height as u64,
        width as u64,
        BATCH_BYTES_PER_PIXEL,
    ]);
    bridgev2w_io::memory::check_fits(
        &format!(
            "a training batch of {clips} clip(s) of {frames} frames at {height}x{width} (train.batch_size, data.frames, data.height x data.width)"
        ),
        estimate,
        crate::TRAIN_MEMORY_ADVICE,
    )?;
    Ok(())
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
            mask_coding: cfg.model.mask_coding,
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
        let dir = bridgev2w_world_model::hub::resolve_model_dir(Path::new(&cfg.model.backbone))?;
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
