//! `bridgev2w eval-policy-rollout`: policy evaluation by world-model
//! rollouts vs synthetic-world success.

use super::{parse_split, parse_task, progress, ModelArgs};
use anyhow::Result;
use bridgev2w_data::synth::{Split, Task};
use bridgev2w_plan::experiment::rollout::parse_offsets_mm;
use bridgev2w_plan::experiment::{rollout_report, RolloutOptions};
use std::path::PathBuf;

#[derive(Debug, Clone, clap::Args)]
pub struct EvalRolloutArgs {
    /// reach, push or pick_place.
    #[arg(long, value_parser = parse_task)]
    pub task: Task,
    /// Trials per policy (task instances of the split).
    #[arg(long, default_value_t = 10)]
    pub trials: usize,
    #[command(flatten)]
    pub model: ModelArgs,
    /// Offset standard deviations of the scripted policies (mm, comma-separated).
    #[arg(long, default_value = "0,10,20,30,50")]
    pub offsets_mm: String,
    /// Per-action jitter of the scripted policies (mm).
    #[arg(long, default_value_t = 2.0)]
    pub jitter_mm: f64,
    /// Actions per policy chunk (at most the model's clip frames - 1).
    #[arg(long, default_value_t = 8)]
    pub chunk: usize,
    /// Goal-distance judge: success when d(last, goal) <= ratio * d(start, goal).
    #[arg(long, default_value_t = 0.5)]
    pub ratio: f64,
    /// Judge by labels instead (CSV policy,trial,success).
    #[arg(long)]
    pub labels: Option<PathBuf>,
    /// Split of the task instances.
    #[arg(long, default_value = "test", value_parser = parse_split)]
    pub split: Split,
    /// Frames of the scripted expert episodes (the rollout horizon is this minus one).
    #[arg(long, default_value_t = 25)]
    pub episode_frames: usize,
    /// Seed of the world and the policies.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// `bridgev2w eval-policy-rollout`.
pub fn run(a: &EvalRolloutArgs) -> Result<()> {
    let o = RolloutOptions {
        task: a.task,
        trials: a.trials,
        model: (&a.model).into(),
        offsets_mm: parse_offsets_mm(&a.offsets_mm)?,
        jitter_mm: a.jitter_mm,
        chunk: a.chunk,
        ratio: a.ratio,
        labels: a.labels.clone(),
        split: a.split,
        episode_frames: a.episode_frames,
        seed: a.seed,
    };
    let r = rollout_report(&o, &mut progress)?;
    crate::print_stdout(&r.markdown())
}
