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
//!
//! [`DistEnv`]: crate::distributed::DistEnv

mod checkpoint_io;
mod objective;
mod predict;
mod setup;
mod shard;
mod step;
#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests;

use crate::action::ActionEncoder;
use crate::config::TrainConfig;
use crate::data::ClipDataset;
use crate::distributed::Collective;
use crate::ema::Ema;
use crate::flow::{FlowEstimator, FlowLossConfig};
use crate::optim::AdamW;
use crate::run_dir::ExistingRun;
use crate::{Result, TrainError};
use bridgev2w_torch_ext::AutocastDtype;
use bridgev2w_world_model::bridge::BridgeV2W;
use bridgev2w_world_model::scheduler::Scheduler;
use bridgev2w_world_model::transformer::CheckpointedForward;
use std::path::Path;
use tch::nn::VarStore;
use tch::Tensor;

pub use checkpoint_io::resolve_checkpoint;

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
    /// On CUDA: the most memory tensors held at once during the step, MiB
    /// (the caching allocator's `max_memory_allocated`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cuda_peak_allocated_mib: Option<f64>,
    /// On CUDA: the most memory the caching allocator reserved at once during
    /// the step, MiB (`max_memory_reserved`: what the device must have,
    /// besides the CUDA context).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cuda_peak_reserved_mib: Option<f64>,
}

impl StepMetrics {
    /// The step's losses, learning rate and gradient norm on one line (the
    /// `vae` stage's reconstruction and KL, else the diffusion, dynamics
    /// and flow losses).
    pub fn summary(&self) -> String {
        if self.diffusion == 0.0 && (self.recon > 0.0 || self.kl > 0.0) {
            format!(
                "loss {:.4} (L1 {:.4} KL {:.3}) lr {:.2e} |g| {:.3}",
                self.loss, self.recon, self.kl, self.lr, self.grad_norm
            )
        } else {
            format!(
                "loss {:.4} (diff {:.4} dyn {:.4} flow {:.4}) lr {:.2e} |g| {:.3}",
                self.loss, self.diffusion, self.dynamics, self.flow, self.lr, self.grad_norm
            )
        }
    }
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

impl Trainer {
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

    /// What the run is about to do, for its log: the steps, the flow
    /// estimator, the precision, the output and, data-parallel, this rank's
    /// share of each batch.
    pub fn describe(&self) -> Vec<String> {
        let mut lines = vec![format!(
            "training {} step(s) ({} per epoch), flow estimator {}, {}, output {}",
            self.total_steps(),
            self.steps_per_epoch(),
            self.flow_estimator_name(),
            match self.autocast_dtype() {
                Some(d) => format!("{:?} autocast", d.kind()),
                None => "f32".to_string(),
            },
            self.cfg.train.out.display()
        )];
        if let Some(name) = self.collective_name() {
            let (rank, world) = self.rank_and_world();
            let batch = self.cfg.train.batch_size;
            let writer = if self.is_primary() {
                ""
            } else {
                " (rank 0 writes the outputs)"
            };
            lines.push(format!(
                "rank {rank} of {world}: {} of {batch} batch items per step, {name} all-reduce{writer}",
                batch / world
            ));
        }
        lines
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
