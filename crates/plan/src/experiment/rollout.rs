//! Policy evaluation by world-model rollouts in the synthetic world
//! (`bridgev2w eval-policy-rollout`): scripted policies of growing offset
//! and policies served over openpi's websocket protocol
//! ([`crate::served`]), each rolled out in the world model and in the
//! synthetic world, and their success rates compared (MMRV, Pearson r). A
//! served policy that fails (unreachable, closed, slow, a bad chunk) is
//! reported by name with its error; the others' results are kept.

use super::judge_calibration::{calibrate_ratio, CalibrationRun};
use super::{LoadedModel, ModelOptions};
use crate::policy::{
    evaluate_trial, report_from_tallies, Execution, GoalDistanceJudge, LabelJudge, Policy,
    PolicyEvalReport, PolicyTally, ScriptedPolicy, SuccessJudge,
};
use crate::served::{ServedPolicy, ServedPolicyConfig, TcpKinematics};
use crate::synthetic::TaskInstance;
use crate::{EeAction, Observation};
use crate::{PlanError, Result};
use bridgev2w_data::synth::mujoco::{find_python, MujocoEngine};
use bridgev2w_data::synth::Engine;
use bridgev2w_data::synth::{Split, Task};
use bridgev2w_io::frame::RgbFrame;
use std::path::PathBuf;

/// One policy evaluation.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct RolloutOptions {
    /// reach, push or pick_place.
    #[cfg_attr(feature = "clap", arg(long, value_parser = Task::parse_goal_task))]
    pub task: Task,
    /// Trials per policy (task instances of the split).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = RolloutOptions::new(Task::Reach).trials))]
    pub trials: usize,
    /// The world model.
    #[cfg_attr(feature = "clap", command(flatten))]
    pub model: ModelOptions,
    /// Offset standard deviations of the scripted policies (mm), one policy
    /// each (with the served ones, at least two policies in all).
    #[cfg_attr(feature = "clap", arg(skip))]
    pub offsets_mm: Vec<f64>,
    /// A policy served over openpi's websocket protocol, [NAME=]ws://HOST:PORT
    /// (repeatable): it gets the rollout's frame, joints and pose and returns
    /// end-effector action chunks, as --policy-config maps them.
    #[cfg_attr(feature = "clap", arg(long = "policy", value_name = "[NAME=]URL"))]
    pub served: Vec<ServedSpec>,
    /// How observations and actions map to the served policies' keys (TOML;
    /// default openpi's DROID example keys, absolute end-effector actions,
    /// `ServedPolicyConfig::default`; see docs/guide/planning.md).
    #[cfg_attr(
        feature = "clap",
        arg(long = "policy-config", value_name = "TOML", requires = "served")
    )]
    pub served_config: Option<PathBuf>,
    /// Per-action jitter of the scripted policies (mm).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = RolloutOptions::new(Task::Reach).jitter_mm))]
    pub jitter_mm: f64,
    /// Actions per policy chunk (at most the model's clip frames - 1).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = RolloutOptions::new(Task::Reach).chunk))]
    pub chunk: usize,
    /// Goal-distance judge: success when d(last, goal) <= ratio * d(start, goal).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = RolloutOptions::new(Task::Reach).ratio))]
    pub ratio: f64,
    /// Calibrate the goal-distance judge on the model's own rollouts of the
    /// expert's actions in this many episodes of the train split: their
    /// --calibration-quantile of d_last / d_start is a floor f, and success
    /// is d_last / d_start <= f + ratio (1 - f), for models whose blurred
    /// predictions never come within a fixed --ratio of the sharp goal image
    /// (0: the fixed --ratio; beyond the paper).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = RolloutOptions::new(Task::Reach).calibrate_judge, value_name = "N"))]
    pub calibrate_judge: usize,
    /// The quantile of the expert rollouts' d_last / d_start that
    /// --calibrate-judge takes as the ratio, in (0, 1].
    #[cfg_attr(feature = "clap", arg(long, default_value_t = RolloutOptions::new(Task::Reach).calibration_quantile))]
    pub calibration_quantile: f64,
    /// Judge by labels instead (CSV policy,trial,success).
    #[cfg_attr(feature = "clap", arg(long))]
    pub labels: Option<PathBuf>,
    /// Split of the task instances.
    #[cfg_attr(feature = "clap", arg(long, default_value = "test", value_parser = Split::parse_named))]
    pub split: Split,
    /// Frames of the scripted expert episodes (the rollout horizon is this minus one).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = RolloutOptions::new(Task::Reach).episode_frames))]
    pub episode_frames: usize,
    /// Seed of the world and the policies.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = RolloutOptions::new(Task::Reach).seed))]
    pub seed: u64,
    /// What executes the policies for their true success: `builtin` (the
    /// synthetic world's contact rules) or `mujoco` (MuJoCo's physics, judged
    /// on its state against its run of the expert; the model's rollouts
    /// unchanged; needs scripts/setup-mujoco-venv.sh).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = Engine::Builtin))]
    pub engine: Engine,
}

impl RolloutOptions {
    /// The defaults of `bridgev2w eval-policy-rollout` for `task`.
    pub fn new(task: Task) -> Self {
        Self {
            task,
            trials: 10,
            model: ModelOptions::default(),
            offsets_mm: vec![0.0, 10.0, 20.0, 30.0, 50.0],
            served: Vec::new(),
            served_config: None,
            jitter_mm: 2.0,
            chunk: 8,
            ratio: 0.5,
            calibrate_judge: 0,
            calibration_quantile: 0.8,
            labels: None,
            split: Split::Test,
            episode_frames: 25,
            seed: 0,
            engine: Engine::Builtin,
        }
    }
}

/// A served policy: its name in the report and its URL.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ServedSpec {
    /// The name in the report.
    pub name: String,
    /// `ws://HOST:PORT`.
    pub url: String,
}

impl std::str::FromStr for ServedSpec {
    type Err = String;
    /// `[NAME=]ws://HOST:PORT` (the name defaults to the URL).
    fn from_str(s: &str) -> std::result::Result<Self, String> {
        let (name, url) = match s.split_once('=') {
            Some((n, u)) if !n.contains("://") => (n.trim(), u.trim()),
            _ => (s.trim(), s.trim()),
        };
        if !url.contains("://") || name.is_empty() {
            return Err(format!(
                "{s:?}: expected [NAME=]ws://HOST:PORT (a policy served over openpi's websocket protocol)"
            ));
        }
        Ok(Self {
            name: name.to_string(),
            url: url.to_string(),
        })
    }
}

/// Where a policy of the evaluation comes from.
enum Source<'o, 'p> {
    /// The scripted policy of `offsets_mm[i]`.
    Scripted(usize),
    /// A served policy.
    Served(&'o ServedSpec),
    /// The caller's.
    External(Box<dyn Policy + 'p>),
}

/// A scripted policy whose expert follows the trial (instance `i` is trial `i`).
struct PerTrialExpert {
    inner: ScriptedPolicy,
    experts: Vec<Vec<EeAction>>,
}

impl Policy for PerTrialExpert {
    fn name(&self) -> String {
        self.inner.name()
    }
    fn reset(&mut self, trial: usize) {
        self.inner.expert = self.experts.get(trial).cloned().unwrap_or_default();
        self.inner.reset(trial);
    }
    fn act(&mut self, obs: &Observation) -> Result<Vec<EeAction>> {
        self.inner.act(obs)
    }
}

/// A served policy whose joint-space chunks go through the forward
/// kinematics of the trial's acting arm.
struct ServedInWorld {
    inner: ServedPolicy,
    kinematics: Vec<TcpKinematics>,
}

impl Policy for ServedInWorld {
    fn name(&self) -> String {
        self.inner.name()
    }
    fn reset(&mut self, trial: usize) {
        self.inner
            .set_kinematics(self.kinematics.get(trial).cloned());
        self.inner.reset(trial);
    }
    fn act(&mut self, obs: &Observation) -> Result<Vec<EeAction>> {
        self.inner.act(obs)
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
    rollout_report_with(o, Vec::new(), progress)
}

/// [`rollout_report`] with policies of the caller's after the options'
/// (e.g. the Python package's callables); one that fails with
/// [`PlanError::Policy`] is reported like a served one.
pub fn rollout_report_with(
    o: &RolloutOptions,
    external: Vec<Box<dyn Policy + '_>>,
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
    if o.offsets_mm.len() + o.served.len() + external.len() < 2 {
        return Err(PlanError::input(
            "--offsets-mm",
            "at least two policies (scripted offsets and served policies) are needed for a correlation",
        ));
    }
    if let Some(p) = &o.served_config {
        ServedPolicyConfig::read(p).map_err(|e| PlanError::input("--policy-config", e))?;
    }
    o.model.check_sizes()?;
    super::sizes::check_trials("--trials", o.trials)?;
    super::sizes::check_trials("--calibrate-judge", o.calibrate_judge)?;
    super::judge_calibration::check(
        o.calibrate_judge,
        o.calibration_quantile,
        o.labels.is_some(),
    )?;
    super::sizes::check_episode_frames(o.episode_frames)?;
    let loaded = LoadedModel::load(&o.model)?;
    // One clip per model call.
    super::sizes::check_candidates_memory(&loaded, "a rollout", 1)?;
    rollout_with(&loaded, o, external, progress)
}

/// [`rollout_report`] with a model already loaded.
pub(crate) fn rollout_with<'p>(
    loaded: &LoadedModel,
    o: &RolloutOptions,
    external: Vec<Box<dyn Policy + 'p>>,
    progress: &mut dyn FnMut(&str),
) -> Result<PolicyEvalReport> {
    let world = loaded.world(o.episode_frames, o.seed)?;
    let engine = match o.engine {
        Engine::Builtin => None,
        Engine::Mujoco => Some(MujocoEngine::new(&world.config.robot, find_python()?)?),
    };
    let instances: Vec<TaskInstance> = (0..o.trials)
        .map(|i| {
            let inst = TaskInstance::new(&world, o.split, i, o.task)?;
            match &engine {
                None => Ok(inst),
                Some(e) => inst.in_mujoco(&world, e),
            }
        })
        .collect::<Result<_>>()?;
    let labels = o.labels.as_deref().map(LabelJudge::read).transpose()?;
    let horizon = o.episode_frames - 1;
    let look = loaded.look();
    let calibration = match o.calibrate_judge {
        0 => None,
        n => {
            progress(&format!(
                "judge: calibrating on the model's rollouts of the expert in {n} train episodes"
            ));
            let run = CalibrationRun {
                task: o.task,
                episodes: n,
                quantile: o.calibration_quantile,
                ratio: o.ratio,
                chunk: o.chunk,
                horizon,
                seed: o.seed,
            };
            let c = calibrate_ratio(loaded, &world, &run)?;
            progress(&format!(
                "judge: floor {:.3} (the {} quantile of the expert rollouts' d_last / d_start), ratio {:.3}",
                c.floor, c.quantile, c.ratio
            ));
            Some(c)
        }
    };
    let ratio = calibration.as_ref().map_or(o.ratio, |c| c.ratio);
    let served_config = match &o.served_config {
        Some(p) => {
            ServedPolicyConfig::read(p).map_err(|e| PlanError::input("--policy-config", e))?
        }
        None => ServedPolicyConfig::default(),
    };
    let experts: Vec<Vec<EeAction>> = instances.iter().map(TaskInstance::expert_actions).collect();
    let robot = std::sync::Arc::new(world.embodiment.robot.clone());
    let kinematics: Vec<TcpKinematics> = instances
        .iter()
        .map(|inst| TcpKinematics {
            robot: robot.clone(),
            link: world.embodiment.end_effectors[inst.expert.meta.arm].link,
        })
        .collect();
    let mut names = Vec::new();
    let mut tallies = Vec::new();
    let mut failed = Vec::new();
    // The scripted policies, the served ones, the caller's.
    let mut sources: Vec<Source<'_, 'p>> = (0..o.offsets_mm.len()).map(Source::Scripted).collect();
    sources.extend(o.served.iter().map(Source::Served));
    sources.extend(external.into_iter().map(Source::External));
    for source in sources {
        let mut policy: Box<dyn Policy + 'p> = match source {
            Source::Scripted(pi) => Box::new(PerTrialExpert {
                inner: ScriptedPolicy::new(
                    Vec::new(),
                    o.chunk,
                    o.offsets_mm[pi] / 1e3,
                    o.jitter_mm / 1e3,
                    o.seed ^ (pi as u64 + 1).wrapping_mul(0xA076_1D64_78BD_642F),
                ),
                experts: experts.clone(),
            }),
            Source::Served(s) => {
                match ServedPolicy::connect(&s.name, &s.url, served_config.clone()) {
                    Ok(p) => {
                        let mut meta = p.metadata().to_string();
                        if meta.chars().count() > 200 {
                            meta = meta.chars().take(200).collect::<String>() + "...";
                        }
                        progress(&format!(
                            "{}: connected to {} (server metadata {meta})",
                            s.name, s.url
                        ));
                        Box::new(ServedInWorld {
                            inner: p,
                            kinematics: kinematics.clone(),
                        })
                    }
                    Err(e) => {
                        progress(&format!("{}: not evaluated: {e}", s.name));
                        failed.push((s.name.clone(), e.to_string()));
                        continue;
                    }
                }
            }
            Source::External(p) => p,
        };
        let name = policy.name();
        let mut tally = PolicyTally::default();
        let mut run = || -> Result<()> {
            // One instance at a time so each gets its own model (camera, scene).
            for (trial, inst) in instances.iter().enumerate() {
                let outcome = loaded.with_model(&world, inst, &mut |m| {
                    let encode = |img: &RgbFrame| m.encode(img);
                    let goal_judge = GoalDistanceJudge {
                        encode: &encode,
                        ratio,
                    };
                    let judge: &dyn SuccessJudge = match &labels {
                        Some(l) => l,
                        None => &goal_judge,
                    };
                    evaluate_trial(
                        &world,
                        inst,
                        trial,
                        policy.as_mut(),
                        m,
                        judge,
                        horizon,
                        Execution {
                            mujoco: engine.as_ref(),
                            look,
                        },
                    )
                })?;
                tally.add(&outcome);
            }
            Ok(())
        };
        match run() {
            Ok(()) => {}
            Err(e @ PlanError::Policy { .. }) => {
                progress(&format!("{name}: stopped: {e}"));
                failed.push((name, e.to_string()));
                continue;
            }
            Err(e) => return Err(e),
        }
        progress(&format!(
            "{name}: world model {:.2}{}, {} {:.2}",
            tally.model_rate(),
            tally
                .mean_progress()
                .map(|p| format!(" (goal progress {p:+.3})"))
                .unwrap_or_default(),
            world_name(o.engine).replace('-', " "),
            tally.real_rate()
        ));
        names.push(name);
        tallies.push(tally);
    }
    if names.len() < 2 {
        let why: Vec<String> = failed.iter().map(|(_, e)| e.clone()).collect();
        return Err(PlanError::Invalid(format!(
            "{} of the policies finished: a correlation needs two; {}",
            names.len(),
            why.join("; ")
        )));
    }
    let mut report = report_from_tallies(names, &tallies)?;
    report.failed = failed;
    report.calibration = calibration;
    report.executed_in = o.engine;
    Ok(report)
}

/// The world the policies were executed in, as the reports name it (as
/// an adjective: "synthetic-world success").
pub(crate) fn world_name(engine: Engine) -> &'static str {
    match engine {
        Engine::Builtin => "synthetic-world",
        Engine::Mujoco => "MuJoCo-world",
    }
}

impl PolicyEvalReport {
    /// The report as JSON: per policy its rates (and goal progress), the
    /// agreement metrics, and the policies not evaluated with their errors.
    pub fn to_json(&self) -> serde_json::Value {
        let progress = self.progress.as_ref();
        let over = self.overestimate();
        let rows: Vec<serde_json::Value> = (0..self.policies.len())
            .map(|i| {
                serde_json::json!({
                    "policy": self.policies[i],
                    "world_model_success": self.predicted[i],
                    "synthetic_world_success": self.real[i],
                    "overestimate": over[i],
                    "world_model_goal_progress": progress.map(|p| p.mean[i]),
                })
            })
            .collect();
        let failed: Vec<serde_json::Value> = self
            .failed
            .iter()
            .map(|(policy, error)| serde_json::json!({"policy": policy, "error": error}))
            .collect();
        serde_json::json!({
            "policies": rows,
            "mmrv": self.mmrv,
            "pearson": self.pearson,
            "executed_in": self.executed_in.name(),
            "mean_overestimate": self.mean_overestimate(),
            "judge_calibration": self.calibration,
            "progress_mmrv": progress.map(|p| p.mmrv),
            "progress_pearson": progress.map(|p| p.pearson),
            "not_evaluated": failed,
        })
    }

    /// The report as a markdown table with its agreement metrics.
    pub fn markdown(&self) -> String {
        let progress = self.progress.as_ref();
        let mut s = String::from("| policy | world-model success |");
        if progress.is_some() {
            s += " world-model goal progress |";
        }
        let world = world_name(self.executed_in);
        s += &format!(" {world} success | overestimate |\n|---|---|---|---|");
        if progress.is_some() {
            s += "---|";
        }
        s += "\n";
        let over = self.overestimate();
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
            s += &format!(" {g:.2} | {:+.2} |\n", over[i]);
        }
        s += &format!(
            "\nSuccess rates: MMRV {:.3} (lower is better), Pearson r {:.3}; overestimate (world model minus {}) {:+.3} on average\n",
            self.mmrv,
            self.pearson,
            world.replace('-', " "),
            self.mean_overestimate()
        );
        if let Some(pr) = progress {
            s += &format!(
                "Goal progress vs {world} success: MMRV {:.3}, Pearson r {:.3}\n",
                pr.mmrv, pr.pearson
            );
        }
        if let Some(c) = &self.calibration {
            s += &format!(
                "World-model success judged above a floor of {:.3} (the {} quantile of d_last / d_start over the model's rollouts of the expert's actions in {} train episodes): ratio {:.3}\n",
                c.floor, c.quantile, c.episodes, c.ratio
            );
        }
        for (name, error) in &self.failed {
            s += &format!("\nNot evaluated: {name}: {error}\n");
        }
        s
    }
}
