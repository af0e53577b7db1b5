//! Policy evaluation with world-model rollouts (the paper's appendix
//! "Policy Evaluation"): query the policy on the current image, pad its
//! action chunk to the model's clip, predict, feed the last predicted frame
//! back, until the horizon; judge success; compare success rates with the
//! real ones (MMRV, Pearson r).

use crate::error::{check_finite, PlanError, Result};
use crate::model::ActionWorldModel;
use crate::synthetic::{GoalLook, SyntheticEnv, TaskInstance};
use crate::{EeAction, Observation};
use bridgev2w_data::synth::mujoco::MujocoEngine;
use bridgev2w_data::synth::Engine;
use bridgev2w_io::frame::RgbFrame;
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;

mod judge;

pub use judge::{goal_progress, GoalDistanceJudge, JudgeInput, LabelJudge, SuccessJudge, Verdict};

/// A policy: observation (image, proprioception) -> action chunk.
pub trait Policy {
    /// The policy's name in reports.
    fn name(&self) -> String;
    /// Starts a new trial.
    fn reset(&mut self, trial: usize);
    /// The next action chunk (absolute end-effector actions, one per frame).
    fn act(&mut self, obs: &Observation) -> Result<Vec<EeAction>>;
}

/// The policy's next chunk, checked: finite and non-empty.
fn next_chunk(policy: &mut dyn Policy, obs: &Observation) -> Result<Vec<EeAction>> {
    let chunk = policy.act(obs)?;
    check_finite(&format!("policy {}", policy.name()), &chunk)?;
    if chunk.is_empty() {
        return Err(PlanError::Invalid(format!(
            "policy {} returned no actions",
            policy.name()
        )));
    }
    Ok(chunk)
}

/// An autoregressive world-model rollout.
#[derive(Debug, Clone)]
pub struct RolloutResult {
    /// The last predicted frame of every chunk.
    pub chunk_last_frames: Vec<RgbFrame>,
    /// The final observation.
    pub last: Observation,
    /// Policy actions executed (without padding).
    pub actions: usize,
}

/// Rolls a policy out in the world model: each chunk (at most
/// `clip_frames - 1` actions are used) is padded to the clip by repeating
/// its last action, predicted from the current frame, and the clip's last
/// frame becomes the next policy input, until `horizon` actions are done.
pub fn rollout_in_model<M: ActionWorldModel + ?Sized>(
    model: &M,
    policy: &mut dyn Policy,
    start: Observation,
    horizon: usize,
) -> Result<RolloutResult> {
    if horizon == 0 {
        return Err(PlanError::ZeroHorizon);
    }
    let max_chunk = model.clip_frames().saturating_sub(1).max(1);
    let mut obs = start;
    let mut done = 0;
    let mut chunk_last_frames = Vec::new();
    while done < horizon {
        let mut chunk = next_chunk(policy, &obs)?;
        chunk.truncate(max_chunk.min(horizon - done));
        done += chunk.len();
        // The model pads the chunk by repeating its last action.
        obs = model
            .rollout_batch(&obs, std::slice::from_ref(&chunk))?
            .pop()
            .ok_or_else(|| PlanError::Invalid("the model returned no rollout".into()))?;
        chunk_last_frames.push(obs.image.clone());
    }
    Ok(RolloutResult {
        chunk_last_frames,
        last: obs,
        actions: done,
    })
}

/// Executes a policy in the synthetic world for `horizon` actions (chunks
/// of at most `max_chunk` actions); returns the final observation.
pub fn rollout_in_world(
    env: &mut SyntheticEnv<'_>,
    policy: &mut dyn Policy,
    horizon: usize,
    max_chunk: usize,
) -> Result<Observation> {
    if horizon == 0 {
        return Err(PlanError::ZeroHorizon);
    }
    let mut obs = env.observe();
    let mut done = 0;
    while done < horizon {
        let mut chunk = next_chunk(policy, &obs)?;
        chunk.truncate(max_chunk.max(1).min(horizon - done));
        done += chunk.len();
        obs = env.execute(&chunk)?;
    }
    Ok(obs)
}

/// A scripted policy with graded noise: it replays the expert's actions in
/// chunks, displaced by a per-trial offset drawn with standard deviation
/// `offset_std_m` per axis (half on z) plus per-action jitter.
#[derive(Debug, Clone)]
pub struct ScriptedPolicy {
    /// The expert actions.
    pub expert: Vec<EeAction>,
    /// Actions per chunk.
    pub chunk: usize,
    /// Offset standard deviation (metres).
    pub offset_std_m: f64,
    /// Per-action jitter (metres, uniform +-).
    pub jitter_m: f64,
    /// Seed.
    pub seed: u64,
    cursor: usize,
    offset_m: [f64; 3],
    rng: ChaCha8Rng,
}

impl ScriptedPolicy {
    /// A policy replaying `expert` (from its second action on).
    pub fn new(
        expert: Vec<EeAction>,
        chunk: usize,
        offset_std_m: f64,
        jitter_m: f64,
        seed: u64,
    ) -> Self {
        Self {
            expert,
            chunk: chunk.max(1),
            offset_std_m,
            jitter_m,
            seed,
            cursor: 1,
            offset_m: [0.0; 3],
            rng: ChaCha8Rng::seed_from_u64(seed),
        }
    }
}

use bridgev2w_io::seed::{standard_normal as gauss, trial_seed};

impl Policy for ScriptedPolicy {
    fn name(&self) -> String {
        format!("scripted(offset {:.0} mm)", self.offset_std_m * 1e3)
    }

    fn reset(&mut self, trial: usize) {
        self.rng = ChaCha8Rng::seed_from_u64(trial_seed(self.seed, trial as u64));
        self.cursor = 1;
        let s = self.offset_std_m;
        self.offset_m = [
            s * gauss(&mut self.rng),
            s * gauss(&mut self.rng),
            0.5 * s * gauss(&mut self.rng),
        ];
    }

    fn act(&mut self, _obs: &Observation) -> Result<Vec<EeAction>> {
        let n = self.expert.len();
        let mut out = Vec::with_capacity(self.chunk);
        for _ in 0..self.chunk {
            let i = self.cursor.min(n.saturating_sub(1));
            let Some(mut a) = self.expert.get(i).copied() else {
                return Err(PlanError::Invalid(
                    "a scripted policy without actions".into(),
                ));
            };
            for (k, v) in a.iter_mut().take(3).enumerate() {
                let j = if self.jitter_m > 0.0 {
                    self.rng.gen_range(-self.jitter_m..=self.jitter_m)
                } else {
                    0.0
                };
                *v += self.offset_m[k] + j;
            }
            out.push(a);
            self.cursor += 1;
        }
        Ok(out)
    }
}

/// Success rates per policy, world model vs real, and the agreement metrics.
#[derive(Debug, Clone, PartialEq)]
pub struct PolicyEvalReport {
    /// Policy names.
    pub policies: Vec<String>,
    /// World-model success rate per policy.
    pub predicted: Vec<f64>,
    /// Real (synthetic-world) success rate per policy.
    pub real: Vec<f64>,
    /// MMRV (lower is better).
    pub mmrv: f64,
    /// Pearson r.
    pub pearson: f64,
    /// The graded alternative, when the judge grades (see [`Verdict`]).
    pub progress: Option<ProgressAgreement>,
    /// Policies whose evaluation stopped (a served policy unreachable,
    /// closed, slow or answering badly): name and error.
    pub failed: Vec<(String, String)>,
    /// The goal-distance judge's ratio when it was calibrated on the
    /// model's own expert rollouts (`--calibrate-judge`).
    pub calibration: Option<JudgeCalibration>,
    /// What executed the policies for their true success.
    pub executed_in: Engine,
}

/// The goal-distance judge calibrated on the model's own rollouts of the
/// expert (`crate::experiment::judge_calibration`).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct JudgeCalibration {
    /// The floor: the quantile of the expert rollouts' `d_last / d_start`.
    pub floor: f64,
    /// The judge's ratio above the floor: success when `d_last <= ratio *
    /// d_start` with `ratio = floor + fixed * (1 - floor)`.
    pub ratio: f64,
    /// Expert rollouts it was measured on (`train` split episodes).
    pub episodes: usize,
    /// The quantile of their `d_last / d_start` taken.
    pub quantile: f64,
    /// Each expert rollout's `d_last / d_start`, in episode order.
    pub expert_ratios: Vec<f64>,
}

/// Mean world-model goal progress per policy and its agreement with the
/// real success rates: a weak model whose rollouts never succeed (every
/// predicted rate 0, Pearson 0) can still rank policies by progress.
#[derive(Debug, Clone, PartialEq)]
pub struct ProgressAgreement {
    /// Mean [`goal_progress`] of the world-model rollouts, per policy.
    pub mean: Vec<f64>,
    /// MMRV of the means against the real success rates.
    pub mmrv: f64,
    /// Pearson r of the means against the real success rates.
    pub pearson: f64,
}

impl PolicyEvalReport {
    /// From success rates.
    pub fn new(policies: Vec<String>, predicted: Vec<f64>, real: Vec<f64>) -> Result<Self> {
        let mmrv = bridgev2w_eval::ranking::mmrv(&predicted, &real)?;
        let pearson = bridgev2w_eval::ranking::pearson(&predicted, &real)?;
        Ok(Self {
            policies,
            predicted,
            real,
            mmrv,
            pearson,
            progress: None,
            failed: Vec::new(),
            calibration: None,
            executed_in: Engine::Builtin,
        })
    }

    /// World-model minus synthetic-world success rate per policy: the
    /// paper's bias of a model trained on successful demonstrations (it
    /// "recovers" small errors) shows as a positive overestimate.
    pub fn overestimate(&self) -> Vec<f64> {
        self.predicted
            .iter()
            .zip(&self.real)
            .map(|(p, r)| p - r)
            .collect()
    }

    /// The mean of [`Self::overestimate`] over the policies (0 for none).
    pub fn mean_overestimate(&self) -> f64 {
        let o = self.overestimate();
        o.iter().sum::<f64>() / o.len().max(1) as f64
    }

    /// Adds the mean goal progress per policy (same order as the rates).
    pub fn with_progress(mut self, mean: Vec<f64>) -> Result<Self> {
        let mmrv = bridgev2w_eval::ranking::mmrv(&mean, &self.real)?;
        let pearson = bridgev2w_eval::ranking::pearson(&mean, &self.real)?;
        self.progress = Some(ProgressAgreement {
            mean,
            mmrv,
            pearson,
        });
        Ok(self)
    }
}

/// Success and progress tallies of one policy's trials.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PolicyTally {
    trials: usize,
    model_wins: usize,
    real_wins: usize,
    progress_sum: f64,
    graded: usize,
}

impl PolicyTally {
    /// Counts one trial.
    pub fn add(&mut self, t: &TrialOutcome) {
        self.trials += 1;
        self.model_wins += usize::from(t.model.success);
        self.real_wins += usize::from(t.real_success);
        if let Some(p) = t.model.progress {
            self.progress_sum += p;
            self.graded += 1;
        }
    }

    /// World-model success rate.
    pub fn model_rate(&self) -> f64 {
        self.model_wins as f64 / self.trials.max(1) as f64
    }

    /// Synthetic-world success rate.
    pub fn real_rate(&self) -> f64 {
        self.real_wins as f64 / self.trials.max(1) as f64
    }

    /// Mean goal progress, when every trial was graded.
    pub fn mean_progress(&self) -> Option<f64> {
        (self.trials > 0 && self.graded == self.trials)
            .then(|| self.progress_sum / self.trials as f64)
    }
}

/// The report of tallied policies: rates, and progress when every policy's
/// trials were all graded.
pub fn report_from_tallies(
    policies: Vec<String>,
    tallies: &[PolicyTally],
) -> Result<PolicyEvalReport> {
    let report = PolicyEvalReport::new(
        policies,
        tallies.iter().map(PolicyTally::model_rate).collect(),
        tallies.iter().map(PolicyTally::real_rate).collect(),
    )?;
    match tallies
        .iter()
        .map(PolicyTally::mean_progress)
        .collect::<Option<Vec<f64>>>()
    {
        Some(mean) => report.with_progress(mean),
        None => Ok(report),
    }
}

/// One trial's outcome: the judge's verdict on the world-model rollout and
/// the synthetic world's success.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TrialOutcome {
    /// The verdict on the world-model rollout.
    pub model: Verdict,
    /// The task's state check after executing the policy in the world.
    pub real_success: bool,
}

/// One trial of one policy on one task instance: rolled out in the model
/// (judged by `judge` on the images, against the instance's final goal
/// image) and executed in the synthetic world (judged by the task's state
/// check).
/// With `exec.mujoco`, the policy is executed in MuJoCo instead
/// ([`SyntheticEnv::in_mujoco`]; the instance's success reference should be
/// MuJoCo's run, [`TaskInstance::in_mujoco`]); the model's start frame and
/// goal image are drawn in `exec.look`.
#[allow(clippy::too_many_arguments)]
pub fn evaluate_trial<M: ActionWorldModel + ?Sized>(
    world: &bridgev2w_data::synth::World,
    instance: &TaskInstance,
    trial: usize,
    policy: &mut dyn Policy,
    model: &M,
    judge: &dyn SuccessJudge,
    horizon: usize,
    exec: Execution<'_>,
) -> Result<TrialOutcome> {
    let name = policy.name();
    let goal = instance
        .goal_images(world, exec.look)
        .pop()
        .ok_or_else(|| PlanError::Invalid("a task instance without a goal image".into()))?;
    let builtin = SyntheticEnv::new(world, instance.clone());
    let (mut env, start) = match exec.mujoco {
        None => {
            let start = builtin.observe();
            (builtin, start)
        }
        Some(engine) => {
            let env = SyntheticEnv::in_mujoco(world, instance.clone(), engine)?;
            let start = match exec.look {
                GoalLook::Builtin => builtin.observe(),
                GoalLook::Executed => env.observe(),
            };
            (env, start)
        }
    };
    policy.reset(trial);
    let r = rollout_in_model(model, policy, start.clone(), horizon)?;
    let model_verdict = judge.judge(&JudgeInput {
        policy: &name,
        trial,
        start: &start.image,
        last: &r.last.image,
        goal: &goal,
    })?;
    policy.reset(trial);
    rollout_in_world(
        &mut env,
        policy,
        horizon,
        model.clip_frames().saturating_sub(1),
    )?;
    Ok(TrialOutcome {
        model: model_verdict,
        real_success: env.success(),
    })
}

/// Where a trial's policy is executed and how its model sees the scene
/// ([`evaluate_trial`]).
#[derive(Debug, Clone, Copy)]
pub struct Execution<'a> {
    /// MuJoCo executes the policy; `None`: the built-in world.
    pub mujoco: Option<&'a MujocoEngine>,
    /// How the model's start frame and goal image are drawn.
    pub look: GoalLook,
}

impl Execution<'static> {
    /// The built-in world executes; the model sees its frames.
    pub const BUILTIN: Self = Self {
        mujoco: None,
        look: GoalLook::Builtin,
    };
}

/// Evaluates policies on task instances (instance `i` is trial `i`) with
/// the model `model_for` gives for each instance; success rates and the
/// agreement metrics.
pub fn evaluate_policies<M: ActionWorldModel>(
    world: &bridgev2w_data::synth::World,
    instances: &[TaskInstance],
    policies: &mut [Box<dyn Policy + '_>],
    model_for: &dyn Fn(&TaskInstance) -> Result<M>,
    judge: &dyn SuccessJudge,
    horizon: usize,
) -> Result<PolicyEvalReport> {
    let mut names = Vec::new();
    let mut tallies = Vec::new();
    for p in policies.iter_mut() {
        let mut tally = PolicyTally::default();
        for (trial, inst) in instances.iter().enumerate() {
            let model = model_for(inst)?;
            tally.add(&evaluate_trial(
                world,
                inst,
                trial,
                p.as_mut(),
                &model,
                judge,
                horizon,
                Execution::BUILTIN,
            )?);
        }
        names.push(p.name());
        tallies.push(tally);
    }
    report_from_tallies(names, &tallies)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn labels_parse_and_bad_lines_are_errors() {
        let j = LabelJudge::parse("policy,trial,success\n# c\na,0,1\na,1,false\n", "x").unwrap();
        let img = RgbFrame {
            height: 1,
            width: 1,
            rgb: vec![0.0; 3],
        };
        let inp = |trial| JudgeInput {
            policy: "a",
            trial,
            start: &img,
            last: &img,
            goal: &img,
        };
        assert_eq!(
            j.judge(&inp(0)).unwrap(),
            Verdict {
                success: true,
                progress: None
            }
        );
        assert!(!j.judge(&inp(1)).unwrap().success);
        assert!(j.judge(&inp(2)).is_err());
        assert!(LabelJudge::parse("a,x,1", "f")
            .unwrap_err()
            .to_string()
            .contains("line 1"));
        assert!(LabelJudge::parse("a,0,maybe", "f").is_err());
    }

    #[test]
    fn goal_progress_closed_forms_and_the_ratio_rule() {
        assert_eq!(goal_progress(2.0, 1.0), 0.5);
        assert_eq!(goal_progress(1.0, 2.0), -0.5);
        assert_eq!(goal_progress(1.0, 0.0), 1.0);
        assert_eq!(goal_progress(3.0, 3.0), 0.0);
        assert_eq!(goal_progress(0.0, 0.0), 0.0);
        assert_eq!(goal_progress(0.0, 4.0), -1.0);
        // Success with ratio r  <=>  progress >= 1 - r (away from the boundary).
        for r in [0.25, 0.5, 0.9] {
            for (ds, dl) in [(1.0, 0.1), (1.0, 0.6), (2.0, 1.9), (0.5, 3.0), (4.0, 0.3)] {
                assert_eq!(
                    dl <= r * ds,
                    goal_progress(ds, dl) >= 1.0 - r,
                    "{r} {ds} {dl}"
                );
            }
        }
    }

    #[test]
    fn goal_distance_judge_grades_with_latent_distances() {
        let img = |v: f32| RgbFrame {
            height: 1,
            width: 2,
            rgb: vec![v; 6],
        };
        // The "latent" is the image itself: d = mean |a - b|.
        let encode = |i: &RgbFrame| Ok(i.rgb.clone());
        let judge = GoalDistanceJudge {
            encode: &encode,
            ratio: 0.5,
        };
        let (start, goal) = (img(0.0), img(1.0));
        let verdict = |last: &RgbFrame| {
            judge
                .judge(&JudgeInput {
                    policy: "p",
                    trial: 0,
                    start: &start,
                    last,
                    goal: &goal,
                })
                .unwrap()
        };
        // d_start 1, d_last 0.25: success, progress 0.75.
        let v = verdict(&img(0.75));
        assert!(v.success);
        assert!((v.progress.unwrap() - 0.75).abs() < 1e-6);
        // d_last 0.6: not half-way, progress 0.4.
        let v = verdict(&img(0.4));
        assert!(!v.success);
        assert!((v.progress.unwrap() - 0.4).abs() < 1e-6);
        // Away from the goal: d_last 1.5, progress (1 - 1.5) / 1.5.
        let v = verdict(&img(-0.5));
        assert!(!v.success);
        assert!((v.progress.unwrap() + 1.0 / 3.0).abs() < 1e-6);
    }

    fn outcome(model: bool, progress: Option<f64>, real: bool) -> TrialOutcome {
        TrialOutcome {
            model: Verdict {
                success: model,
                progress,
            },
            real_success: real,
        }
    }

    #[test]
    fn progress_ranks_policies_a_weak_model_never_succeeds_with() {
        // Three policies, real success 1, 1/2, 0; the model succeeds never,
        // but its rollouts get less near the goal for the worse policies.
        let trials = [
            [(0.4, true), (0.3, true)],
            [(0.2, true), (0.1, false)],
            [(-0.1, false), (0.0, false)],
        ];
        let tallies: Vec<PolicyTally> = trials
            .iter()
            .map(|t| {
                let mut tally = PolicyTally::default();
                for &(p, real) in t {
                    tally.add(&outcome(false, Some(p), real));
                }
                tally
            })
            .collect();
        assert_eq!(tallies[1].real_rate(), 0.5);
        assert!((tallies[0].mean_progress().unwrap() - 0.35).abs() < 1e-12);
        let r = report_from_tallies(vec!["a".into(), "b".into(), "c".into()], &tallies).unwrap();
        assert_eq!(r.predicted, vec![0.0; 3]);
        assert_eq!(r.pearson, 0.0);
        let p = r.progress.unwrap();
        assert_eq!(p.mmrv, 0.0);
        assert!(p.pearson > 0.95, "{}", p.pearson);
        // One ungraded trial (a label judge): no progress for the report.
        let mut partial = tallies.clone();
        partial[2].add(&outcome(true, None, true));
        assert_eq!(partial[2].mean_progress(), None);
        let r = report_from_tallies(vec!["a".into(), "b".into(), "c".into()], &partial).unwrap();
        assert!(r.progress.is_none());
        assert_eq!(r.predicted[2], 1.0 / 3.0);
    }

    #[test]
    fn report_wires_mmrv_and_pearson() {
        let r = PolicyEvalReport::new(
            vec!["a".into(), "b".into(), "c".into()],
            vec![0.9, 0.5, 0.1],
            vec![0.8, 0.6, 0.2],
        )
        .unwrap();
        assert_eq!(r.mmrv, 0.0);
        assert!(r.pearson > 0.95);
        // Swapped order: a rank violation of |0.8 - 0.6| for a and b.
        let s = PolicyEvalReport::new(
            vec!["a".into(), "b".into(), "c".into()],
            vec![0.5, 0.9, 0.1],
            vec![0.8, 0.6, 0.2],
        )
        .unwrap();
        assert!((s.mmrv - (0.2 + 0.2) / 3.0).abs() < 1e-12, "{}", s.mmrv);
        assert!(PolicyEvalReport::new(vec![], vec![0.1], vec![]).is_err());
    }

    #[test]
    fn overestimate_is_world_model_minus_real_success() {
        let r = PolicyEvalReport::new(
            vec!["a".into(), "b".into(), "c".into()],
            vec![0.9, 0.5, 0.1],
            vec![0.8, 0.6, 0.1],
        )
        .unwrap();
        let o = r.overestimate();
        for (got, want) in o.iter().zip([0.1, -0.1, 0.0]) {
            assert!((got - want).abs() < 1e-12, "{o:?}");
        }
        assert!(r.mean_overestimate().abs() < 1e-12);
        let md = r.markdown();
        assert!(md.contains("| a | 0.90 | 0.80 | +0.10 |"), "{md}");
        assert!(md.contains("| b | 0.50 | 0.60 | -0.10 |"), "{md}");
        assert!(md.contains("+0.000 on average"), "{md}");
        let json = r.to_json();
        assert_eq!(json["policies"][1]["policy"], "b");
        assert!((json["policies"][1]["overestimate"].as_f64().unwrap() + 0.1).abs() < 1e-12);
    }
}
