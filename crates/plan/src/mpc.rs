//! Receding-horizon planning: CEM over the world model's predictions toward
//! a goal image, execute the first action, observe, re-plan; two goal images
//! (subgoal, then final) with the gripper heuristic; and VLA-proposal
//! selection.

use crate::cem::{optimize, CemConfig, GripperMode};
use crate::error::{check_finite, PlanError, Result};
use crate::model::{
    apply_increment, check_image_size, expand_waypoints, latent_l1, ActionWorldModel, ViewLimit,
    Workspace,
};
use crate::{EeAction, Observation};
use bridgev2w_data::synth::Task;
use bridgev2w_io::frame::RgbFrame;
use rand_chacha::ChaCha8Rng;

/// How the gripper is commanded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum GripperPolicy {
    /// Searched by CEM (the Bernoulli of the algorithm).
    Search,
    /// The paper's heuristic: `approach` while pursuing the first goal;
    /// with two goals, close (grasp) on switching to the final goal and
    /// keep it closed; with `release_at_end`, open once the final goal is
    /// pursued to its end.
    Heuristic {
        /// Command while approaching (0 open, 1 closed).
        approach: f64,
        /// Command after the switch to the final goal.
        after_switch: f64,
        /// Open the gripper at the end (release at the target).
        release_at_end: bool,
    },
}

/// The gripper as chosen by name (`--gripper`): searched, the task's
/// heuristic, or `auto` (searched for `reach`, whose goal says nothing of
/// the gripper; the heuristic for the tasks that grasp or push).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GripperChoice {
    /// Searched for reach, the heuristic otherwise.
    Auto,
    /// Always searched.
    Search,
    /// Always the task's heuristic.
    Heuristic,
}
bridgev2w_world_model::named_enum!(GripperChoice, crate::PlanError, crate::PlanError::input, "gripper", {
    Auto => "auto",
    Search => "search",
    Heuristic => "heuristic",
});

impl GripperChoice {
    /// The gripper policy for `task`.
    pub fn policy(self, task: Task) -> GripperPolicy {
        let heuristic = match task {
            Task::Reach | Task::Play => GripperPolicy::Heuristic {
                approach: 0.0,
                after_switch: 0.0,
                release_at_end: false,
            },
            Task::Push => GripperPolicy::Heuristic {
                approach: 1.0,
                after_switch: 1.0,
                release_at_end: false,
            },
            Task::PickPlace => GripperPolicy::Heuristic {
                approach: 0.0,
                after_switch: 1.0,
                release_at_end: true,
            },
        };
        match (self, task) {
            (Self::Auto, Task::Reach) | (Self::Search, _) => GripperPolicy::Search,
            (Self::Auto, _) | (Self::Heuristic, _) => heuristic,
        }
    }
}

/// MPC settings.
#[derive(Debug, Clone, PartialEq)]
pub struct MpcConfig {
    /// CEM settings.
    pub cem: CemConfig,
    /// Clip frames per planned action (the action's motion is interpolated).
    pub frames_per_action: usize,
    /// Executed actions at most (the time limit).
    pub max_steps: usize,
    /// Gripper.
    pub gripper: GripperPolicy,
    /// A step stalls when the observed latent distance to the current goal
    /// does not improve by this fraction.
    pub stall_fraction: f64,
    /// After this many consecutive stalled steps the final goal counts as
    /// reached as far as the model can tell: stop.
    pub patience: usize,
    /// The same for the goals before the final one: switch to the next.
    pub subgoal_patience: usize,
    /// Planned (and random-baseline) positions are clamped into this box.
    pub workspace: Option<Workspace>,
    /// Planned (and random-baseline) moves stop where the TCP would leave
    /// the camera's view.
    pub view: Option<ViewLimit>,
    /// Execute the best evaluated candidate instead of the refined mean
    /// (the paper executes the mean). Near the goal the mean of spread
    /// elites can step away from a goal the best sample already holds.
    pub execute_best: bool,
    /// Actions of the chosen plan executed before planning again, 1 to the
    /// horizon (the paper executes 1). With a horizon of `n` actions and
    /// `n` executed, one search pays for `n` actions and the whole executed
    /// chunk is what its terminal frame was scored on.
    pub execute_actions: usize,
    /// Index of the goal whose end triggers the gripper heuristic's
    /// switch (the grasp): goals up to it are pursued with `approach`,
    /// later ones with `after_switch`. 0 without waypoint goals.
    pub switch_after_goal: usize,
    /// After each consecutive stalled step the next search's standard
    /// deviations are multiplied by this factor in (0, 1] (1: off); a step
    /// with progress or a new goal restores them. Near a goal the initial
    /// spread overshoots: a stall is the sign to search finer.
    pub stall_std_factor: f64,
    /// With the heuristic's release at the end (pick_place): open the
    /// gripper in place on leaving the goal before the final one, when that
    /// goal comes after the grasp (the place waypoint), and pursue the
    /// final goal open: the expert's final frame shows the object released
    /// and the gripper lifted away from it, which a closed gripper can only
    /// approach by lifting the object with it.
    pub release_before_final: bool,
}

impl Default for MpcConfig {
    fn default() -> Self {
        Self {
            cem: CemConfig::default(),
            frames_per_action: 2,
            max_steps: 12,
            gripper: GripperPolicy::Search,
            stall_fraction: 0.01,
            patience: 2,
            subgoal_patience: 2,
            workspace: None,
            view: None,
            execute_best: false,
            execute_actions: 1,
            switch_after_goal: 0,
            stall_std_factor: 1.0,
            release_before_final: false,
        }
    }
}

impl MpcConfig {
    /// Checks the settings against a model's clip length.
    pub fn validate(&self, clip_frames: usize) -> Result<()> {
        self.cem.validate()?;
        if let Some(w) = &self.workspace {
            w.validate()?;
        }
        if let Some(v) = &self.view {
            v.validate()?;
        }
        if self.frames_per_action == 0 || self.max_steps == 0 {
            return Err(PlanError::Invalid(
                "frames per action and max steps must be at least 1".into(),
            ));
        }
        self.check_execute_actions()?;
        self.check_stall_std_factor()?;
        if self.cem.horizon * self.frames_per_action > clip_frames.saturating_sub(1) {
            return Err(PlanError::ClipTooShort {
                actions: self.cem.horizon,
                frames_per_action: self.frames_per_action,
                clip_frames,
            });
        }
        Ok(())
    }

    /// Checks that 1 to the horizon's actions are executed per search.
    pub fn check_execute_actions(&self) -> Result<()> {
        if (1..=self.cem.horizon).contains(&self.execute_actions) {
            return Ok(());
        }
        Err(PlanError::input(
            "--execute-actions",
            format!(
                "{}: expected 1 to the horizon (--horizon {})",
                self.execute_actions, self.cem.horizon
            ),
        ))
    }

    /// Checks that the stall factor is in (0, 1].
    pub fn check_stall_std_factor(&self) -> Result<()> {
        let f = self.stall_std_factor;
        if f.is_finite() && f > 0.0 && f <= 1.0 {
            return Ok(());
        }
        Err(PlanError::input(
            "--shrink-on-stall",
            format!("{f}: expected a factor in (0, 1] (1: off)"),
        ))
    }

    /// These settings with the search's standard deviations shrunk for
    /// `stalls` consecutive stalled steps ([`Self::stall_std_factor`]).
    fn after_stalls(&self, stalls: usize) -> std::borrow::Cow<'_, Self> {
        if stalls == 0 || self.stall_std_factor == 1.0 {
            return std::borrow::Cow::Borrowed(self);
        }
        let scale = self
            .stall_std_factor
            .powi(i32::try_from(stalls).unwrap_or(i32::MAX));
        let mut cfg = self.clone();
        cfg.cem.init_translation_std_m *= scale;
        cfg.cem.init_rotation_std_rad *= scale;
        std::borrow::Cow::Owned(cfg)
    }

    /// The move from `from` toward `to` as the limits allow: `to` clamped
    /// into the workspace, if one is set, then stopped where the TCP would
    /// leave the view, if that is limited.
    pub fn constrain(&self, from: &EeAction, to: &EeAction) -> EeAction {
        let a = self.workspace.as_ref().map_or(*to, |w| w.clamp(to));
        self.view.as_ref().map_or(a, |v| v.constrain(from, &a))
    }
}

/// The "real world" the plan is executed in.
pub trait Environment {
    /// The current observation.
    fn observe(&self) -> Result<Observation>;
    /// Executes end-effector actions (one per frame) and observes.
    fn execute(&mut self, actions: &[EeAction]) -> Result<Observation>;
    /// Whether the goal is reached (ends the episode early).
    fn goal_reached(&self) -> bool;
    /// The task's error in metres where the environment knows it (a
    /// simulator; a real robot does not): recorded in the planner's trace.
    fn task_error_m(&self) -> Option<f64> {
        None
    }
}

impl Environment for crate::synthetic::SyntheticEnv<'_> {
    fn observe(&self) -> Result<Observation> {
        Ok(crate::synthetic::SyntheticEnv::observe(self))
    }
    fn execute(&mut self, actions: &[EeAction]) -> Result<Observation> {
        crate::synthetic::SyntheticEnv::execute(self, actions)
    }
    fn goal_reached(&self) -> bool {
        self.success()
    }
    fn task_error_m(&self) -> Option<f64> {
        Some(self.instance.error_m(self.world, &self.state))
    }
}

/// One planning cycle's result.
#[derive(Debug, Clone, PartialEq)]
pub struct PlanStep {
    /// The planned waypoints `A*_{1..H}` (absolute end-effector actions).
    pub waypoints: Vec<EeAction>,
    /// Best predicted cost per CEM iteration.
    pub best_cost_per_iteration: Vec<f64>,
    /// The model's predicted frame of the lowest-cost candidate.
    pub best_prediction: Option<RgbFrame>,
}

/// Scores action sequences: the latent mean L1 distance of each predicted
/// terminal frame to `goal_latent` (one batched model call).
pub fn score_sequences<M: ActionWorldModel + ?Sized>(
    model: &M,
    start: &Observation,
    sequences: &[Vec<EeAction>],
    goal_latent: &[f32],
) -> Result<Vec<f64>> {
    Ok(predict_and_score(model, start, sequences, goal_latent)?.1)
}

/// [`score_sequences`] with the predicted observations it scored.
fn predict_and_score<M: ActionWorldModel + ?Sized>(
    model: &M,
    start: &Observation,
    sequences: &[Vec<EeAction>],
    goal_latent: &[f32],
) -> Result<(Vec<Observation>, Vec<f64>)> {
    let predicted = model.rollout_batch(start, sequences)?;
    let costs = predicted
        .iter()
        .map(|o| latent_l1(&model.encode(&o.image)?, goal_latent))
        .collect::<Result<_>>()?;
    Ok((predicted, costs))
}

/// One CEM planning cycle from `obs` toward `goal_latent`.
pub fn plan_once<M: ActionWorldModel + ?Sized>(
    model: &M,
    obs: &Observation,
    goal_latent: &[f32],
    cfg: &MpcConfig,
    gripper: GripperMode,
    rng: &mut ChaCha8Rng,
) -> Result<PlanStep> {
    cfg.validate(model.clip_frames())?;
    let to_waypoints = |c: &crate::cem::Candidate| {
        let mut cur = obs.ee;
        c.increments
            .iter()
            .zip(&c.gripper)
            .map(|(inc, &g)| {
                cur = cfg.constrain(&cur, &apply_increment(&cur, inc, g));
                cur
            })
            .collect::<Vec<_>>()
    };
    // The lowest-cost prediction seen (the executed one with `execute_best`).
    let mut best_prediction: Option<(f64, RgbFrame)> = None;
    let mut evaluate = |cands: &[crate::cem::Candidate]| {
        let seqs: Vec<Vec<EeAction>> = cands
            .iter()
            .map(|c| expand_waypoints(&obs.ee, &to_waypoints(c), cfg.frames_per_action))
            .collect();
        let (predicted, costs) = predict_and_score(model, obs, &seqs, goal_latent)?;
        for (o, &c) in predicted.into_iter().zip(&costs) {
            if best_prediction.as_ref().is_none_or(|(b, _)| c < *b) {
                best_prediction = Some((c, o.image));
            }
        }
        Ok(costs)
    };
    let r = optimize(&cfg.cem, gripper, rng, &mut evaluate)?;
    let chosen = if cfg.execute_best { &r.best.0 } else { &r.plan };
    Ok(PlanStep {
        waypoints: to_waypoints(chosen),
        best_cost_per_iteration: r.best_cost_per_iteration,
        best_prediction: best_prediction.map(|(_, image)| image),
    })
}

/// What one MPC episode did.
#[derive(Debug, Clone, PartialEq)]
pub struct MpcOutcome {
    /// Actions executed.
    pub steps: usize,
    /// The environment reported the goal reached.
    pub reached: bool,
    /// Observed latent distance to the final goal after each step.
    pub final_goal_distance: Vec<f64>,
    /// What each executed step did, in order.
    pub trace: Vec<MpcTraceStep>,
}

/// One executed MPC step, as the planner saw it.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct MpcTraceStep {
    /// Index of the goal image pursued (0: the first waypoint or subgoal).
    pub goal: usize,
    /// The executed waypoint (absolute end-effector action; the last of
    /// the step's, when a step executes several).
    pub action: EeAction,
    /// The observed end-effector pose after the step (xyz metres, rpy
    /// radians, gripper).
    pub ee: EeAction,
    /// The model's predicted cost of the best candidate (last CEM iteration).
    pub predicted_cost: f64,
    /// The observed latent distance to the pursued goal after the step.
    pub observed_cost: f64,
    /// Consecutive stalled steps after this one (0: it made progress).
    pub stalls: usize,
    /// The task's error after the step, where the environment knows it.
    pub task_error_m: Option<f64>,
    /// The model's predicted frame of the lowest-cost candidate.
    #[serde(skip)]
    pub predicted: Option<RgbFrame>,
    /// The observed frame after the step.
    #[serde(skip)]
    pub observed: RgbFrame,
}

/// Runs CEM-MPC: per cycle plan toward the current goal, execute the first
/// action, observe; switch from the subgoal to the final goal when progress
/// toward the subgoal stalls; stop when the environment reports the goal
/// reached, the final goal stalls, or at `max_steps`.
pub fn run_mpc<M: ActionWorldModel + ?Sized, E: Environment>(
    model: &M,
    env: &mut E,
    goals: &[RgbFrame],
    cfg: &MpcConfig,
    rng: &mut ChaCha8Rng,
) -> Result<MpcOutcome> {
    cfg.validate(model.clip_frames())?;
    if goals.is_empty() {
        return Err(PlanError::Invalid(
            "at least one goal image is needed".into(),
        ));
    }
    for g in goals {
        check_image_size(g, model.resolution())?;
    }
    if cfg.switch_after_goal >= goals.len() {
        return Err(PlanError::Invalid(format!(
            "the gripper switch after goal {} needs more than {} goal images",
            cfg.switch_after_goal,
            goals.len()
        )));
    }
    let latents: Vec<Vec<f32>> = goals
        .iter()
        .map(|g| model.encode(g))
        .collect::<Result<_>>()?;
    let mut obs = env.observe()?;
    let mut stage = 0;
    let mut prev_dist = latent_l1(&model.encode(&obs.image)?, &latents[stage])?;
    let mut final_goal_distance = Vec::new();
    let mut trace = Vec::new();
    let mut steps = 0;
    let mut stalls = 0;
    let last = latents.len() - 1;
    // Release in place on switching to the final goal (see
    // `MpcConfig::release_before_final`): only with the heuristic's release
    // and a goal between the grasp and the final one.
    let release_before_final = cfg.release_before_final
        && last > cfg.switch_after_goal + 1
        && matches!(
            cfg.gripper,
            GripperPolicy::Heuristic {
                release_at_end: true,
                ..
            }
        );
    let gripper_for = |stage: usize| match cfg.gripper {
        GripperPolicy::Search => GripperMode::Search,
        GripperPolicy::Heuristic {
            approach,
            after_switch,
            ..
        } => GripperMode::Fixed(if stage <= cfg.switch_after_goal {
            approach
        } else if release_before_final && stage == last {
            0.0
        } else {
            after_switch
        }),
    };
    while steps < cfg.max_steps && !env.goal_reached() {
        let search = cfg.after_stalls(stalls);
        let plan = plan_once(
            model,
            &obs,
            &latents[stage],
            &search,
            gripper_for(stage),
            rng,
        )?;
        // The first `execute_actions` of the plan, as many as the steps left.
        let n = cfg
            .execute_actions
            .min(plan.waypoints.len())
            .min(cfg.max_steps - steps)
            .max(1);
        let executed = &plan.waypoints[..n];
        let last_executed = executed[n - 1];
        let frames = expand_waypoints(&obs.ee, executed, cfg.frames_per_action);
        obs = env.execute(&frames)?;
        steps += n;
        let z = model.encode(&obs.image)?;
        let dist = latent_l1(&z, &latents[stage])?;
        final_goal_distance.push(latent_l1(&z, &latents[last])?);
        if dist > prev_dist * (1.0 - cfg.stall_fraction) {
            stalls += 1;
        } else {
            stalls = 0;
        }
        trace.push(MpcTraceStep {
            goal: stage,
            action: last_executed,
            ee: obs.ee,
            predicted_cost: plan
                .best_cost_per_iteration
                .last()
                .copied()
                .unwrap_or(f64::NAN),
            observed_cost: dist,
            stalls,
            task_error_m: env.task_error_m(),
            predicted: plan.best_prediction.clone(),
            observed: obs.image.clone(),
        });
        prev_dist = prev_dist.min(dist);
        let patience = if stage < last {
            cfg.subgoal_patience
        } else {
            cfg.patience
        };
        let stalled = stalls >= patience.max(1);
        if stalled && stage < last {
            stage += 1;
            // Grasp in place before pursuing the goals after the switch.
            if let (GripperPolicy::Heuristic { after_switch, .. }, true) =
                (cfg.gripper, stage == cfg.switch_after_goal + 1)
            {
                obs = gripper_in_place(env, &obs, after_switch, cfg.frames_per_action)?;
            }
            // Release in place before pursuing the final goal open.
            if release_before_final && stage == last {
                obs = gripper_in_place(env, &obs, 0.0, cfg.frames_per_action)?;
            }
            prev_dist = latent_l1(&model.encode(&obs.image)?, &latents[stage])?;
            stalls = 0;
        } else if stalled && stage == last {
            break;
        }
    }
    if let GripperPolicy::Heuristic {
        release_at_end: true,
        ..
    } = cfg.gripper
    {
        obs = gripper_in_place(env, &obs, 0.0, cfg.frames_per_action)?;
        final_goal_distance.push(latent_l1(&model.encode(&obs.image)?, &latents[last])?);
    }
    Ok(MpcOutcome {
        steps,
        reached: env.goal_reached(),
        final_goal_distance,
        trace,
    })
}

/// Commands the gripper to `command` (0 open, 1 closed) with the arm held
/// at its observed pose, for `frames` frames.
fn gripper_in_place<E: Environment>(
    env: &mut E,
    obs: &Observation,
    command: f64,
    frames: usize,
) -> Result<Observation> {
    let mut a = obs.ee;
    a[6] = command;
    env.execute(&vec![a; frames])
}

/// VLA-proposal mode: rolls out each proposed action chunk (absolute
/// end-effector actions) with the model from `obs` in one batch and returns
/// the index of the one whose predicted outcome is nearest the goal, with
/// all costs.
pub fn select_proposal<M: ActionWorldModel + ?Sized>(
    model: &M,
    obs: &Observation,
    goal: &RgbFrame,
    proposals: &[Vec<EeAction>],
) -> Result<(usize, Vec<f64>)> {
    check_image_size(goal, model.resolution())?;
    if proposals.is_empty() {
        return Err(PlanError::Invalid("no proposals to choose from".into()));
    }
    for (i, p) in proposals.iter().enumerate() {
        check_finite(&format!("proposal {i}"), p)?;
    }
    let goal_latent = model.encode(goal)?;
    let costs = score_sequences(model, obs, proposals, &goal_latent)?;
    let best = crate::cem::elite_indices(&costs, 1)[0];
    Ok((best, costs))
}

/// The random-action baseline: `max_steps` actions whose increments are
/// drawn from CEM's initial distribution (translation only if the config
/// says so), gripper as the config's policy would set it on approach (or a
/// fair coin when searched).
pub fn run_random<E: Environment>(
    env: &mut E,
    cfg: &MpcConfig,
    rng: &mut ChaCha8Rng,
) -> Result<MpcOutcome> {
    cfg.cem.validate()?;
    if let Some(w) = &cfg.workspace {
        w.validate()?;
    }
    if let Some(v) = &cfg.view {
        v.validate()?;
    }
    let dist = vec![crate::cem::StepDistribution::initial(&cfg.cem)];
    let active = if cfg.cem.translation_only {
        [true, true, true, false, false, false]
    } else {
        [true; 6]
    };
    let gripper = match cfg.gripper {
        GripperPolicy::Search => GripperMode::Search,
        GripperPolicy::Heuristic { approach, .. } => GripperMode::Fixed(approach),
    };
    let mut obs = env.observe()?;
    let mut steps = 0;
    while steps < cfg.max_steps && !env.goal_reached() {
        let c = crate::cem::sample_candidate(&dist, &active, &cfg.cem, gripper, rng);
        let next = cfg.constrain(
            &obs.ee,
            &apply_increment(&obs.ee, &c.increments[0], c.gripper[0]),
        );
        obs = env.execute(&expand_waypoints(&obs.ee, &[next], cfg.frames_per_action))?;
        steps += 1;
    }
    Ok(MpcOutcome {
        steps,
        reached: env.goal_reached(),
        final_goal_distance: Vec::new(),
        trace: Vec::new(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `--gripper` by name: auto searches only for reach; the heuristic
    /// closes to push, grasps and releases to pick and place.
    #[test]
    fn gripper_choices_by_name_and_task() {
        let auto: GripperChoice = "auto".parse().expect("auto");
        assert_eq!(auto.policy(Task::Reach), GripperPolicy::Search);
        assert!(matches!(
            auto.policy(Task::PickPlace),
            GripperPolicy::Heuristic {
                after_switch: 1.0,
                release_at_end: true,
                ..
            }
        ));
        assert!(matches!(
            GripperChoice::Heuristic.policy(Task::Push),
            GripperPolicy::Heuristic { approach: 1.0, .. }
        ));
        assert_eq!(
            GripperChoice::Search.policy(Task::Push),
            GripperPolicy::Search
        );
        let e = "closed"
            .parse::<GripperChoice>()
            .expect_err("not a choice")
            .to_string();
        assert!(
            e.contains("gripper") && e.contains("auto, search, heuristic"),
            "{e}"
        );
        let e = "spiral"
            .parse::<RotationSearchName>()
            .expect_err("not a search")
            .to_string();
        assert!(e.contains("joint, rotation-first, axis-wise"), "{e}");
    }

    type RotationSearchName = crate::cem::RotationSearch;
}
