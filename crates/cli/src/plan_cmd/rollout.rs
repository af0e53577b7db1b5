//! `bridgev2w eval-policy-rollout`: policy evaluation by world-model
//! rollouts vs synthetic-world success.

use super::{parse_split, parse_task, progress, ModelArgs};
use anyhow::Result;
use bridgev2w_data::synth::{Split, Task};
use bridgev2w_io::json::write_json_atomic;
use bridgev2w_io::output::check_new_file;
use bridgev2w_plan::experiment::rollout::{parse_offsets_mm, ServedSpec};
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
    /// Offset standard deviations of the scripted policies (mm,
    /// comma-separated; default 0,10,20,30,50, none with --policy unless given).
    #[arg(long)]
    pub offsets_mm: Option<String>,
    /// A policy served over openpi's websocket protocol, [NAME=]ws://HOST:PORT
    /// (repeatable): it gets the rollout's frame, joints and pose and returns
    /// end-effector action chunks, as --policy-config maps them.
    #[arg(long = "policy", value_name = "[NAME=]URL", value_parser = parse_served)]
    pub policies: Vec<ServedSpec>,
    /// How observations and actions map to the served policies' keys (TOML;
    /// default openpi's DROID example keys, absolute end-effector actions;
    /// see docs/guide/planning.md).
    #[arg(long, value_name = "TOML", requires = "policies")]
    pub policy_config: Option<PathBuf>,
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
    /// Also write the report as JSON (rates, agreement, the policies not
    /// evaluated and why).
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
    /// Replace an existing --json file.
    #[arg(long, requires = "json")]
    pub overwrite: bool,
}

fn parse_served(s: &str) -> Result<ServedSpec, String> {
    s.parse()
}

/// `bridgev2w eval-policy-rollout`.
pub fn run(a: &EvalRolloutArgs) -> Result<()> {
    if let Some(path) = &a.json {
        check_new_file(path, a.overwrite).map_err(|e| anyhow::anyhow!("--json {e}"))?;
    }
    let o = RolloutOptions {
        task: a.task,
        trials: a.trials,
        model: (&a.model).into(),
        offsets_mm: match (&a.offsets_mm, a.policies.is_empty()) {
            (Some(text), _) => parse_offsets_mm(text)?,
            (None, true) => RolloutOptions::new(a.task).offsets_mm,
            (None, false) => Vec::new(),
        },
        served: a.policies.clone(),
        served_config: a.policy_config.clone(),
        jitter_mm: a.jitter_mm,
        chunk: a.chunk,
        ratio: a.ratio,
        labels: a.labels.clone(),
        split: a.split,
        episode_frames: a.episode_frames,
        seed: a.seed,
    };
    let r = rollout_report(&o, &mut progress)?;
    if let Some(path) = &a.json {
        write_json_atomic(path, &r.to_json())?;
    }
    crate::print_stdout(&r.markdown())
}
