//! Policy evaluation by world-model rollouts in the synthetic world
//! (`bridgev2w eval-policy-rollout`): scripted policies of growing offset,
//! each rolled out in the world model and in the synthetic world, and their
//! success rates compared (MMRV, Pearson r).

use super::{LoadedModel, ModelOptions};
use crate::policy::{
    evaluate_trial, report_from_tallies, GoalDistanceJudge, LabelJudge, Policy, PolicyEvalReport,
    PolicyTally, ScriptedPolicy, SuccessJudge,
};
use crate::synthetic::TaskInstance;
use crate::{PlanError, Result};
use bridgev2w_data::synth::{Split, Task};
use bridgev2w_io::frame::RgbFrame;
use std::path::PathBuf;

/// One policy evaluation.
#[derive(Debug, Clone)]
pub struct RolloutOptions {
    /// The task.
    pub task: Task,
    /// Trials per policy (task instances of the split).
    pub trials: usize,
    /// The world model.
    pub model: ModelOptions,
    /// Offset standard deviations of the scripted policies (mm), one policy
    /// each; at least two.
    pub offsets_mm: Vec<f64>,
    /// Per-action jitter of the scripted policies (mm).
    pub jitter_mm: f64,
    /// Actions per policy chunk (at most the model's clip frames - 1).
    pub chunk: usize,
    /// Goal-distance judge: success when d(last, goal) <= ratio * d(start, goal).
    pub ratio: f64,
    /// Judge by labels instead (CSV policy,trial,success).
    pub labels: Option<PathBuf>,
    /// Split of the task instances.
    pub split: Split,
    /// Frames of the scripted expert episodes (the rollout horizon is this minus one).
    pub episode_frames: usize,
    /// Seed of the world and the policies.
    pub seed: u64,
}

impl RolloutOptions {
    /// The defaults of `bridgev2w eval-policy-rollout` for `task`.
    pub fn new(task: Task) -> Self {
        Self {
            task,
            trials: 10,
            model: ModelOptions::default(),
            offsets_mm: vec![0.0, 10.0, 20.0, 30.0, 50.0],
            jitter_mm: 2.0,
            chunk: 8,
            ratio: 0.5,
            labels: None,
            split: Split::Test,
            episode_frames: 25,
            seed: 0,
        }
    }
}

/// Parses comma-separated non-negative offsets (mm).
pub fn parse_offsets_mm(text: &str) -> Result<Vec<f64>> {
    text.split(',')
        .map(|s| {
            s.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite() && *v >= 0.0)
                .ok_or_else(|| {
                    PlanError::input(
                        "--offsets-mm",
                        format!("{s:?} is not a non-negative number"),
                    )
                })
        })
        .collect()
}

/// Runs the policy evaluation; `progress` gets a line per policy.
pub fn rollout_report(
    o: &RolloutOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<PolicyEvalReport> {
    if o.trials == 0 {
        return Err(PlanError::input("--trials", "must be at least 1"));
    }
    if let Some(bad) = o.offsets_mm.iter().find(|v| !(v.is_finite() && **v >= 0.0)) {
        return Err(PlanError::input(
            "--offsets-mm",
            format!("{bad} is not a non-negative number"),
        ));
    }
    if o.offsets_mm.len() < 2 {
        return Err(PlanError::input(
            "--offsets-mm",
            "at least two policies are needed for a correlation",
        ));
    }
    o.model.check_sizes()?;
    super::sizes::check_trials("--trials", o.trials)?;
    super::sizes::check_episode_frames(o.episode_frames)?;
    let loaded = LoadedModel::load(&o.model)?;
    // One clip per model call.
    super::sizes::check_candidates_memory(&loaded, "a rollout", 1)?;
    rollout_with(&loaded, o, progress)
}

/// [`rollout_report`] with a model already loaded.
pub(crate) fn rollout_with(
    loaded: &LoadedModel,
    o: &RolloutOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<PolicyEvalReport> {
    let world = loaded.world(o.episode_frames, o.seed)?;
    let instances: Vec<TaskInstance> = (0..o.trials)
        .map(|i| TaskInstance::new(&world, o.split, i, o.task))
        .collect::<Result<_>>()?;
    let labels = o.labels.as_deref().map(LabelJudge::read).transpose()?;
    let horizon = o.episode_frames - 1;
    let mut names = Vec::new();
    let mut tallies = Vec::new();
    // One instance at a time so each gets its own model (camera, scene).
    for (pi, off) in o.offsets_mm.iter().enumerate() {
        let mut policy = ScriptedPolicy::new(
            Vec::new(),
            o.chunk,
            off / 1e3,
            o.jitter_mm / 1e3,
            o.seed ^ (pi as u64 + 1).wrapping_mul(0xA076_1D64_78BD_642F),
        );
        let name = policy.name();
        let mut tally = PolicyTally::default();
        for (trial, inst) in instances.iter().enumerate() {
            policy.expert = inst.expert_actions();
            let outcome = loaded.with_model(&world, inst, &mut |m| {
                let encode = |img: &RgbFrame| m.encode(img);
                let goal_judge = GoalDistanceJudge {
                    encode: &encode,
                    ratio: o.ratio,
                };
                let judge: &dyn SuccessJudge = match &labels {
                    Some(l) => l,
                    None => &goal_judge,
                };
                evaluate_trial(&world, inst, trial, &mut policy, m, judge, horizon)
            })?;
            tally.add(&outcome);
        }
        progress(&format!(
            "{name}: world model {:.2}{}, synthetic world {:.2}",
            tally.model_rate(),
            tally
                .mean_progress()
                .map(|p| format!(" (goal progress {p:+.3})"))
                .unwrap_or_default(),
            tally.real_rate()
        ));
        names.push(name);
        tallies.push(tally);
    }
    report_from_tallies(names, &tallies)
}

impl PolicyEvalReport {
    /// The report as a markdown table with its agreement metrics.
    pub fn markdown(&self) -> String {
        let progress = self.progress.as_ref();
        let mut s = String::from("| policy | world-model success |");
        if progress.is_some() {
            s += " world-model goal progress |";
        }
        s += " synthetic-world success |\n|---|---|---|";
        if progress.is_some() {
            s += "---|";
        }
        s += "\n";
        for (i, ((p, w), g)) in self
            .policies
            .iter()
            .zip(&self.predicted)
            .zip(&self.real)
            .enumerate()
        {
            s += &format!("| {p} | {w:.2} |");
            if let Some(pr) = progress {
                s += &format!(" {:+.3} |", pr.mean[i]);
            }
            s += &format!(" {g:.2} |\n");
        }
        s += &format!(
            "\nSuccess rates: MMRV {:.3} (lower is better), Pearson r {:.3}\n",
            self.mmrv, self.pearson
        );
        if let Some(pr) = progress {
            s += &format!(
                "Goal progress vs synthetic-world success: MMRV {:.3}, Pearson r {:.3}\n",
                pr.mmrv, pr.pearson
            );
        }
        s
    }
}
