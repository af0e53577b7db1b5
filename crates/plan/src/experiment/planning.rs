//! Goal-image CEM-MPC on the task instances of a split, and the random-action
//! baseline on the same instances (`bridgev2w plan`).

use super::{trial_seed, LoadedModel, ModelOptions};
use crate::cem::{CemConfig, RotationSearch};
use crate::model::ViewLimit;
use crate::mpc::{run_mpc, run_random, GripperChoice, GripperPolicy, MpcConfig, MpcTraceStep};
use crate::synthetic::{SyntheticEnv, TaskInstance, WaypointSpacing};
use crate::{PlanError, Result};
use bridgev2w_data::synth::mujoco::{find_python, MujocoEngine};
use bridgev2w_data::synth::Engine;
use bridgev2w_data::synth::{Split, Task};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_io::frame::RgbFrame;
use bridgev2w_io::output::{check_no_overlap, OutputDir};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The CEM sizes of an experiment (flags of `plan` and `plan-report`).
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct CemSizes {
    /// CEM samples S per iteration.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = CemSizes::default().samples))]
    pub samples: usize,
    /// CEM elites k.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = CemSizes::default().elites))]
    pub elites: usize,
    /// CEM iterations T.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = CemSizes::default().iters))]
    pub iters: usize,
    /// Planning horizon H (actions). With H > 1 only the terminal frame is
    /// scored, so the executed first action of the best sequence is
    /// unconstrained; H = 1 scores exactly the executed action's outcome.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = CemSizes::default().horizon))]
    pub horizon: usize,
    /// Carry each CEM iteration's elites into the next selection (iCEM; off
    /// in the paper's algorithm).
    #[cfg_attr(feature = "clap", arg(long))]
    pub keep_elites: bool,
    /// Execute the best evaluated candidate's first action instead of the
    /// refined mean's (the paper executes the mean).
    #[cfg_attr(feature = "clap", arg(long))]
    pub execute_best: bool,
    /// Actions of the chosen plan executed before planning again, 1 to the
    /// horizon (the paper: 1). With `--horizon N --execute-actions N` one
    /// search pays for N actions, each chunk judged by its terminal frame
    /// (beyond the paper).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = CemSizes::default().execute_actions))]
    pub execute_actions: usize,
    /// Evaluate the sampling distribution's mean as one of the S samples
    /// (iCEM): in a step's first iteration that is staying put, so a step
    /// that no sample improves on holds the pose (beyond the paper).
    #[cfg_attr(feature = "clap", arg(long))]
    pub include_mean: bool,
    /// After each stalled step (no 1% progress) multiply the next search's
    /// standard deviations by this factor in (0, 1]; progress or a new goal
    /// restores them. 1: off (beyond the paper; `MpcConfig::stall_std_factor`).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = CemSizes::default().shrink_on_stall, value_name = "FACTOR"))]
    pub shrink_on_stall: f64,
}

impl Default for CemSizes {
    /// The paper's search: S 64, k 8, T 3, H 1.
    fn default() -> Self {
        Self {
            samples: 64,
            elites: 8,
            iters: 3,
            horizon: 1,
            keep_elites: false,
            execute_best: false,
            execute_actions: 1,
            include_mean: false,
            shrink_on_stall: 1.0,
        }
    }
}

/// The goal sequence and its switching.
#[derive(Debug, Clone, PartialEq)]
pub struct GoalOptions {
    /// Waypoint goals: expert frames inserted before each key goal.
    pub waypoints: WaypointSpacing,
    /// Stalled steps (no 1% progress) after which the final goal counts as
    /// reached as far as the model can tell.
    pub patience: usize,
    /// The same for subgoals and waypoints: then switch to the next goal.
    pub subgoal_patience: usize,
    /// Keep the TCP inside the camera's view, this fraction of the image's
    /// smaller side from its edges ([`ViewLimit`]); `None`: no limit.
    pub view_margin: Option<f64>,
    /// pick_place: release the object on leaving the goal before the final
    /// one and pursue the final goal open ([`MpcConfig::release_before_final`]).
    pub release_before_final: bool,
}

impl Default for GoalOptions {
    fn default() -> Self {
        Self {
            waypoints: WaypointSpacing::Frames(2),
            patience: 4,
            subgoal_patience: 1,
            view_margin: None,
            release_before_final: false,
        }
    }
}

impl GoalOptions {
    /// The view limit of `view_margin` for observations by `camera`.
    pub fn view_limit(&self, camera: &Camera) -> Option<ViewLimit> {
        self.view_margin.map(|f| {
            let k = &camera.intrinsics;
            ViewLimit {
                camera: camera.clone(),
                margin_px: f * f64::from(k.width.min(k.height)),
            }
        })
    }

    /// Checks the settings.
    pub fn validate(&self) -> Result<()> {
        self.waypoints.validate()?;
        match self.view_margin {
            Some(f) if !(f.is_finite() && (0.0..0.5).contains(&f)) => Err(PlanError::input(
                "--view-margin",
                format!("{f}: expected a fraction of the image's smaller side in [0, 0.5)"),
            )),
            _ => Ok(()),
        }
    }
}

/// One planning experiment: a task, its instances, the model and the search.
#[derive(Debug, Clone)]
pub struct PlanOptions {
    /// The task.
    pub task: Task,
    /// Trials (task instances of the split).
    pub trials: usize,
    /// The world model.
    pub model: ModelOptions,
    /// The CEM sizes.
    pub cem: CemSizes,
    /// Clip frames per planned action.
    pub frames_per_action: usize,
    /// Executed actions at most.
    pub max_steps: usize,
    /// Initial translational standard deviation per step (metres).
    pub translation_std_m: f64,
    /// Search rotation too (default: translation only).
    pub search_rotation: bool,
    /// Rotation refinement.
    pub rotation: RotationSearch,
    /// Fraction of samples that perturb rotation only.
    pub rotation_sample_fraction: f64,
    /// Discretise increments (0.05 m, 20 degrees).
    pub discretize: bool,
    /// How the gripper command is chosen.
    pub gripper: GripperChoice,
    /// Plan toward the final goal image only (no subgoal, no waypoints).
    pub single_goal: bool,
    /// The goals.
    pub goals: GoalOptions,
    /// Do not keep planned positions inside the table's workspace box.
    pub no_workspace: bool,
    /// Split of the task instances.
    pub split: Split,
    /// Frames of the scripted expert episodes (start, goals).
    pub episode_frames: usize,
    /// Seed of the world and the planner.
    pub seed: u64,
    /// What executes the planned actions ("the real robot"): the built-in
    /// world, or MuJoCo (issue 72: success judged on MuJoCo's state against
    /// MuJoCo's run of the expert, whose states the goal images show; the
    /// perfect model stays the built-in world stepped kinematically and sees
    /// them drawn by the built-in renderer, a diffusion model sees MuJoCo's
    /// frames and should have been trained on `synth --engine mujoco`).
    pub engine: Engine,
    /// Write the planner's trace into this new folder: `trials.jsonl`, one
    /// JSON line per trial ([`TrialTrace`]), and `trial-N.png` per trial, a
    /// row per executed step: the goal image pursued, the model's
    /// prediction of the lowest-cost candidate, the observed frame.
    pub trace: Option<PathBuf>,
}

/// One planned trial, step by step (`bridgev2w plan --trace FILE`).
#[derive(Debug, Clone, serde::Serialize)]
pub struct TrialTrace {
    /// Task.
    pub task: Task,
    /// Trial (task instance index of the split).
    pub trial: usize,
    /// The task succeeded.
    pub success: bool,
    /// Final task error (metres).
    pub error_m: f64,
    /// The task object was held in the gripper after some executed step
    /// (a pick_place success without it pushed the object into place).
    pub carried: bool,
    /// World positions (metres) of the expert's TCP at each goal image.
    pub goal_tcp_m: Vec<[f64; 3]>,
    /// The executed steps.
    pub steps: Vec<MpcTraceStep>,
}

impl PlanOptions {
    /// The defaults of `bridgev2w plan` for `task`.
    pub fn new(task: Task) -> Self {
        Self {
            task,
            trials: 20,
            model: ModelOptions::default(),
            cem: CemSizes::default(),
            frames_per_action: 2,
            max_steps: 25,
            translation_std_m: 0.1,
            search_rotation: false,
            rotation: RotationSearch::Joint,
            rotation_sample_fraction: 0.0,
            discretize: false,
            gripper: GripperChoice::Auto,
            single_goal: false,
            goals: GoalOptions::default(),
            no_workspace: false,
            split: Split::Test,
            episode_frames: 25,
            seed: 0,
            engine: Engine::Builtin,
            trace: None,
        }
    }

    /// The MPC settings, checked.
    pub fn mpc_config(&self) -> Result<MpcConfig> {
        let cfg = MpcConfig {
            cem: CemConfig {
                samples: self.cem.samples,
                elites: self.cem.elites,
                iterations: self.cem.iters,
                horizon: self.cem.horizon,
                init_translation_std_m: self.translation_std_m,
                translation_only: !self.search_rotation,
                discretize: self.discretize,
                rotation_search: self.rotation,
                rotation_sample_fraction: self.rotation_sample_fraction,
                keep_elites: self.cem.keep_elites,
                include_mean: self.cem.include_mean,
                ..CemConfig::default()
            },
            frames_per_action: self.frames_per_action,
            max_steps: self.max_steps,
            gripper: self.gripper.policy(self.task),
            execute_best: self.cem.execute_best,
            execute_actions: self.cem.execute_actions,
            patience: self.goals.patience,
            subgoal_patience: self.goals.subgoal_patience,
            stall_std_factor: self.cem.shrink_on_stall,
            release_before_final: self.goals.release_before_final,
            ..MpcConfig::default()
        };
        cfg.cem.validate()?;
        cfg.check_stall_std_factor()?;
        self.goals.validate()?;
        cfg.check_execute_actions()?;
        Ok(cfg)
    }
}

/// Success counts of the planner and the random baseline on one task.
#[derive(Debug, Clone)]
pub struct PlanSummary {
    /// Task.
    pub task: Task,
    /// Trials.
    pub trials: usize,
    /// Planner successes.
    pub planned: usize,
    /// Planner successes in which the task object was held in the gripper
    /// after some executed step (for pick_place: grasped and carried, not
    /// pushed into place).
    pub planned_carried: usize,
    /// Random-action successes.
    pub random: usize,
    /// Mean final task error of the planner (metres).
    pub planned_error_m: f64,
    /// Mean final task error of the random baseline (metres).
    pub random_error_m: f64,
    /// Mean final TCP orientation error of the planner (radians; judged by
    /// no task, see [`TaskInstance::tcp_rotation_error_rad`]).
    pub planned_rotation_error_rad: f64,
    /// The same for the random baseline.
    pub random_rotation_error_rad: f64,
    /// Mean executed actions of the planner.
    pub planned_steps: f64,
    /// Wall time (seconds).
    pub seconds: f64,
}

impl PlanSummary {
    /// One line: the planner's and the random baseline's successes and errors.
    pub fn line(&self, model: &str) -> String {
        let carried = if self.task == Task::PickPlace {
            format!(", {} carried in the gripper", self.planned_carried)
        } else {
            String::new()
        };
        format!(
            "{}: planner ({model}) {}/{} successes{carried} (mean error {:.1} cm, TCP orientation {:.1} deg off, {:.1} actions), random actions {}/{} (mean error {:.1} cm, {:.1} deg); {:.0} s",
            self.task.name(),
            self.planned,
            self.trials,
            self.planned_error_m * 100.0,
            self.planned_rotation_error_rad.to_degrees(),
            self.planned_steps,
            self.random,
            self.trials,
            self.random_error_m * 100.0,
            self.random_rotation_error_rad.to_degrees(),
            self.seconds
        )
    }
}

/// Plans every trial of `o.task` and runs the random baseline on the same
/// instances; `progress` gets a line per trial.
pub fn plan_summary(o: &PlanOptions, progress: &mut dyn FnMut(&str)) -> Result<PlanSummary> {
    if o.trials == 0 {
        return Err(PlanError::input("--trials", "must be at least 1"));
    }
    o.check_sizes()?;
    let cfg = o.mpc_config()?;
    if o.goals.release_before_final
        && !matches!(
            cfg.gripper,
            GripperPolicy::Heuristic {
                release_at_end: true,
                ..
            }
        )
    {
        return Err(PlanError::input(
            "--release-before-final",
            format!(
                "task {}: only pick_place with the gripper heuristic releases an object",
                o.task.name()
            ),
        ));
    }
    if let Some(trace) = &o.trace {
        // Before the model loads: a trace folder overlapping the model's
        // files is refused.
        check_no_overlap(trace, &model_inputs(&o.model))
            .map_err(|e| PlanError::input("--trace", e.to_string()))?;
    }
    let loaded = LoadedModel::load(&o.model)?;
    super::sizes::check_candidates_memory(&loaded, "--samples", o.cem.samples)?;
    plan_with(&loaded, o, &cfg, progress)
}

/// The files of a world model (its folder, weights, prompt embedding): an
/// output must not overlap them.
fn model_inputs(m: &ModelOptions) -> Vec<&Path> {
    let folder = match &m.model {
        crate::choice::PlanModel::World(bridgev2w_world_model::spec::ModelSpec::Folder(p)) => {
            Some(p.as_path())
        }
        _ => None,
    };
    folder
        .into_iter()
        .chain(m.weights.as_deref())
        .chain(m.prompt_embeds.as_deref())
        .collect()
}

/// [`plan_summary`] with a model already loaded.
pub(crate) fn plan_with(
    loaded: &LoadedModel,
    o: &PlanOptions,
    cfg: &MpcConfig,
    progress: &mut dyn FnMut(&str),
) -> Result<PlanSummary> {
    let world = loaded.world(o.episode_frames, o.seed)?;
    let engine = match o.engine {
        Engine::Builtin => None,
        Engine::Mujoco => Some(MujocoEngine::new(&world.config.robot, find_python()?)?),
    };
    let look = loaded.look();
    let t0 = Instant::now();
    let (mut planned, mut planned_carried, mut random) = (0, 0, 0);
    let (mut planned_err, mut random_err, mut steps) = (0.0, 0.0, 0.0);
    let (mut planned_rot, mut random_rot) = (0.0, 0.0);
    let mut traces = Vec::new();
    let trace_dir = o
        .trace
        .as_deref()
        .map(|p| {
            OutputDir::create_for(p, false, &model_inputs(&o.model))
                .map_err(|e| PlanError::input("--trace", e.to_string()))
        })
        .transpose()?;
    for trial in 0..o.trials {
        let mut inst = TaskInstance::new(&world, o.split, trial, o.task)?;
        if !o.single_goal {
            inst = inst.with_waypoints(o.goals.waypoints)?;
        }
        if let Some(engine) = &engine {
            inst = inst.in_mujoco(&world, engine)?;
        }
        let mut goals: Vec<RgbFrame> = inst.goal_images(&world, look);
        if o.single_goal {
            goals.drain(..goals.len() - 1);
        }
        let seed = trial_seed(o.seed, trial as u64);
        let mut cfg = cfg.clone();
        cfg.switch_after_goal = if o.single_goal {
            0
        } else {
            inst.first_key_goal
        };
        if !o.no_workspace {
            cfg.workspace = Some(inst.workspace(&world));
        }
        cfg.view = o.goals.view_limit(&inst.expert.camera);
        let start_env = |inst: &TaskInstance| match &engine {
            None => Ok(SyntheticEnv::new(&world, inst.clone())),
            Some(engine) => SyntheticEnv::in_mujoco(&world, inst.clone(), engine),
        };
        let mut env = start_env(&inst)?;
        let out = loaded.with_model(&world, &inst, &mut |m| {
            run_mpc(
                m,
                &mut env,
                &goals,
                &cfg,
                &mut ChaCha8Rng::seed_from_u64(seed),
            )
        })?;
        let ok = env.success();
        let carried = env.carried_task_object;
        let err = inst.error_m(&world, &env.state);
        if let Some(dir) = &trace_dir {
            let png = filmstrip(&goals, &out.trace);
            let path = dir.path().join(format!("trial-{trial}.png"));
            bridgev2w_io::atomic::write_atomic(&path, &png)?;
            traces.push(TrialTrace {
                task: o.task,
                trial,
                success: ok,
                error_m: err,
                carried,
                goal_tcp_m: inst.goal_tcp_m(&world),
                steps: out.trace.clone(),
            });
        }
        let rot = inst.tcp_rotation_error_rad(&world, &env.state);
        let mut base = start_env(&inst)?;
        run_random(&mut base, &cfg, &mut ChaCha8Rng::seed_from_u64(seed))?;
        let rok = base.success();
        let rerr = inst.error_m(&world, &base.state);
        let rrot = inst.tcp_rotation_error_rad(&world, &base.state);
        progress(&format!(
            "{} trial {trial}: planner {} ({:.1} cm, TCP {:.1} deg off, {} steps), random {} ({:.1} cm, {:.1} deg)",
            o.task.name(),
            match (ok, o.task == Task::PickPlace, carried) {
                (false, ..) => "failure",
                (true, false, _) => "success",
                (true, true, true) => "success, carried",
                (true, true, false) => "success, not carried",
            },
            err * 100.0,
            rot.to_degrees(),
            out.steps,
            if rok { "success" } else { "failure" },
            rerr * 100.0,
            rrot.to_degrees()
        ));
        planned += usize::from(ok);
        planned_carried += usize::from(ok && carried);
        random += usize::from(rok);
        planned_err += err;
        random_err += rerr;
        planned_rot += rot;
        random_rot += rrot;
        steps += out.steps as f64;
    }
    if let Some(dir) = trace_dir {
        write_traces(&dir.path().join("trials.jsonl"), &traces)?;
        dir.commit()
            .map_err(|e| PlanError::input("--trace", e.to_string()))?;
    }
    let n = o.trials as f64;
    Ok(PlanSummary {
        task: o.task,
        trials: o.trials,
        planned,
        planned_carried,
        random,
        planned_error_m: planned_err / n,
        random_error_m: random_err / n,
        planned_rotation_error_rad: planned_rot / n,
        random_rotation_error_rad: random_rot / n,
        planned_steps: steps / n,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// Writes one JSON line per trial (atomically).
fn write_traces(path: &std::path::Path, traces: &[TrialTrace]) -> Result<()> {
    let mut text = String::new();
    for t in traces {
        let line = serde_json::to_string(t)
            .map_err(|e| PlanError::Invalid(format!("trace of trial {}: {e}", t.trial)))?;
        text.push_str(&line);
        text.push('\n');
    }
    bridgev2w_io::atomic::write_atomic(path, text.as_bytes())?;
    Ok(())
}

/// A PNG with a row per executed step: the goal image pursued, the model's
/// prediction of the lowest-cost candidate (grey where there is none), the
/// observed frame; 2-pixel white gaps.
fn filmstrip(goals: &[RgbFrame], steps: &[MpcTraceStep]) -> Vec<u8> {
    const GAP: usize = 2;
    let (h, w) = goals.first().map_or((1, 1), |g| (g.height, g.width));
    let rows = steps.len().max(1);
    let (width, height) = (3 * w + 2 * GAP, rows * h + (rows - 1) * GAP);
    let mut px = vec![255u8; width * height * 3];
    let mut blit = |row: usize, col: usize, frame: Option<&RgbFrame>| {
        let rgb = frame
            .filter(|f| f.height == h && f.width == w)
            .map_or_else(|| vec![128u8; h * w * 3], RgbFrame::to_rgb8);
        for y in 0..h {
            let dst = ((row * (h + GAP) + y) * width + col * (w + GAP)) * 3;
            px[dst..dst + w * 3].copy_from_slice(&rgb[y * w * 3..(y + 1) * w * 3]);
        }
    };
    for (row, s) in steps.iter().enumerate() {
        blit(row, 0, goals.get(s.goal));
        blit(row, 1, s.predicted.as_ref());
        blit(row, 2, Some(&s.observed));
    }
    bridgev2w_io::png::encode_rgb8(width as u32, height as u32, &px)
}
