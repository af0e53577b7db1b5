//! `bridgev2w plan`: goal-image CEM-MPC executed in the synthetic world, vs
//! random actions.

use super::{progress, GoalArgs};
use anyhow::Result;
use bridgev2w_data::synth::{Split, Task};
use bridgev2w_plan::cem::RotationSearch;
use bridgev2w_plan::experiment::planning::CemSizes;
use bridgev2w_plan::experiment::ModelOptions;
use bridgev2w_plan::experiment::{plan_summary, PlanOptions};
use bridgev2w_plan::mpc::GripperChoice;

#[derive(Debug, Clone, clap::Args)]
pub struct PlanArgs {
    /// reach, push or pick_place.
    #[arg(long, value_parser = Task::parse_goal_task)]
    pub task: Task,
    /// Trials (task instances of the split).
    #[arg(long, default_value_t = 20)]
    pub trials: usize,
    #[command(flatten)]
    pub model: ModelOptions,
    #[command(flatten)]
    pub cem: CemSizes,
    /// Clip frames per planned action.
    #[arg(long, default_value_t = 2)]
    pub frames_per_action: usize,
    /// Executed actions at most.
    #[arg(long, default_value_t = 25)]
    pub max_steps: usize,
    /// Initial translational standard deviation per step (metres).
    #[arg(long, default_value_t = 0.1)]
    pub translation_std_m: f64,
    /// Search rotation too (default: translation only, as the paper for pick-and-place).
    #[arg(long)]
    pub search_rotation: bool,
    /// Rotation refinement: joint, rotation-first or axis-wise.
    #[arg(long, default_value = "joint")]
    pub rotation: RotationSearch,
    /// Sample reallocation: fraction of samples that perturb rotation only.
    #[arg(long, default_value_t = 0.0)]
    pub rotation_sample_fraction: f64,
    /// Discretise increments (0.05 m, 20 degrees).
    #[arg(long)]
    pub discretize: bool,
    /// Gripper: auto (heuristic for push/pick_place, searched for reach), search, heuristic.
    #[arg(long, default_value = "auto")]
    pub gripper: GripperChoice,
    /// Plan toward the final goal image only (no subgoal, no waypoints).
    #[arg(long)]
    pub single_goal: bool,
    #[command(flatten)]
    pub goals: GoalArgs,
    /// Do not keep planned positions inside the table's workspace box
    /// (above the table, inside its edges, at most 5 cm above the start).
    #[arg(long)]
    pub no_workspace: bool,
    /// Split of the task instances.
    #[arg(long, default_value = "test", value_parser = Split::parse_named)]
    pub split: Split,
    /// Frames of the scripted expert episodes (start, goals).
    #[arg(long, default_value_t = 25)]
    pub episode_frames: usize,
    /// Seed of the world and the planner.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Write the planner's trace into this new folder: trials.jsonl (per
    /// trial and executed step: goal pursued, action, observed pose,
    /// predicted and observed cost, stalls, task error; the goals' expert
    /// TCP positions; whether the task object was carried in the gripper)
    /// and trial-N.png (a row per step: goal, the model's
    /// prediction of the best candidate, the observed frame).
    #[arg(long)]
    pub trace: Option<std::path::PathBuf>,
    /// What executes the planned actions: `builtin` (the synthetic world's
    /// contact rules) or `mujoco` (MuJoCo's physics, the success judged on
    /// its object poses; the perfect model stays the built-in world's, a
    /// diffusion model sees MuJoCo's frames: train it on `synth --engine
    /// mujoco`; needs scripts/setup-mujoco-venv.sh).
    #[arg(long, default_value_t = bridgev2w_data::synth::Engine::Builtin)]
    pub engine: bridgev2w_data::synth::Engine,
}

impl From<&PlanArgs> for PlanOptions {
    fn from(a: &PlanArgs) -> Self {
        Self {
            task: a.task,
            trials: a.trials,
            model: a.model.clone(),
            cem: a.cem.clone(),
            frames_per_action: a.frames_per_action,
            max_steps: a.max_steps,
            translation_std_m: a.translation_std_m,
            search_rotation: a.search_rotation,
            rotation: a.rotation,
            rotation_sample_fraction: a.rotation_sample_fraction,
            discretize: a.discretize,
            gripper: a.gripper,
            single_goal: a.single_goal,
            goals: (&a.goals).into(),
            no_workspace: a.no_workspace,
            split: a.split,
            episode_frames: a.episode_frames,
            seed: a.seed,
            engine: a.engine,
            trace: a.trace.clone(),
        }
    }
}

/// `bridgev2w plan`.
pub fn run(a: &PlanArgs) -> Result<()> {
    let s = plan_summary(&a.into(), &mut progress)?;
    crate::print_stdout(&format!("{}\n", s.line(&a.model.model.to_string())))
}
