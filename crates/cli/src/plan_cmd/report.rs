//! `bridgev2w plan-report`: planning on all tasks and the policy
//! evaluation, written as one section of docs/results.md.

use super::{progress, GoalArgs};
use anyhow::Result;
use bridgev2w_data::synth::Task;
use bridgev2w_plan::experiment::planning::CemSizes;
use bridgev2w_plan::experiment::report::report_models;
use bridgev2w_plan::experiment::{plan_report, PlanReportOptions, Sampling};
use bridgev2w_world_model::pipeline::DecodeFrames;
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::PathBuf;

#[derive(Debug, Clone, clap::Args)]
pub struct PlanReportArgs {
    /// Output markdown file (only `--section` is replaced). The figures go
    /// to the folder named after it: OUT_WITHOUT_.md/figures/SECTION-*.png.
    #[arg(long, default_value = "docs/results.md")]
    pub out: PathBuf,
    /// Planning trials per task (0: no planning, only the policy evaluation).
    #[arg(long, default_value_t = 20)]
    pub trials: usize,
    /// Policy-evaluation trials per policy (0: no policy evaluation, only
    /// the planning).
    #[arg(long, default_value_t = 10)]
    pub eval_trials: usize,
    #[command(flatten)]
    pub cem: CemSizes,
    /// Executed actions at most.
    #[arg(long, default_value_t = 25)]
    pub max_steps: usize,
    /// Initial translational standard deviation per step (metres).
    #[arg(long, default_value_t = 0.1)]
    pub translation_std_m: f64,
    #[command(flatten)]
    pub goals: GoalArgs,
    /// Tasks to plan (comma-separated).
    #[arg(long, default_value = "reach,push,pick_place")]
    pub tasks: String,
    /// Also evaluate policies with the random-weight BridgeV2W (slow on CPU);
    /// the same as naming `random` in `--models`.
    #[arg(long)]
    pub with_random_model: bool,
    /// The world models of the tables, comma-separated, in order: `perfect`
    /// (the synthetic renderer), `trained` (the folder of `--trained`),
    /// `random` (random weights; policy evaluation only). Default: perfect,
    /// then random with `--with-random-model`, then trained with `--trained`.
    #[arg(long)]
    pub models: Option<String>,
    /// The section of `--out` the tables replace (`<!-- section: NAME -->`):
    /// runs with other settings (e.g. a smaller search for the slow trained
    /// model) keep their own section.
    #[arg(long, default_value = "planning")]
    pub section: String,
    /// Also plan and evaluate policies with a trained BridgeV2W: a folder
    /// with `backbone/` (a diffusers CogVideoX image-to-video folder) and
    /// `bridgev2w.safetensors`, as `assets/demo-model` or what
    /// `scripts/reproduce-synthetic.sh` exports (minutes per trial on CPU).
    #[arg(long)]
    pub trained: Option<PathBuf>,
    /// BridgeV2W weights the trained model plans with, instead of its
    /// folder's `bridgev2w.safetensors`: e.g.
    /// `assets/demo-model/bridgev2w-plan.safetensors`, the planning model
    /// trained on 3-frame clips (with `--plan-clip-frames 3`). The policy
    /// evaluation keeps the folder's weights.
    #[arg(long, value_name = "FILE")]
    pub plan_weights: Option<PathBuf>,
    #[command(flatten)]
    pub sampling: Sampling,
    /// cpu, cuda, cuda:N or auto: the device of the diffusion models.
    #[arg(long, default_value = "cpu")]
    pub device: ComputeDevice,
    /// Precision of the diffusion models: f32 or bf16.
    #[arg(long, default_value = "f32")]
    pub precision: Precision,
    /// Frames of each clip the planning models predict (default: the
    /// model's own; a planned action needs one more than its frames, and a
    /// shorter clip is cheaper; beyond the paper). Policy evaluation keeps
    /// the model's own clip.
    #[arg(long, value_name = "N")]
    pub plan_clip_frames: Option<usize>,
    /// Which frames of the diffusion models' predictions are decoded: `all`,
    /// or `last` (only the VAE decoder's last batch of latent frames, for
    /// planning and policy evaluation, which score the last frame; an
    /// approximation; beyond the paper).
    #[arg(long, default_value = "all")]
    pub decode_frames: DecodeFrames,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// What executes the plans and the policies: `builtin` or `mujoco`
    /// (as `plan --engine`).
    #[arg(long, default_value_t = bridgev2w_data::synth::Engine::Builtin)]
    pub engine: bridgev2w_data::synth::Engine,
    /// The synthetic world's robot (as `plan --robot`).
    #[arg(long, default_value = "franka")]
    pub robot: String,
}

/// `bridgev2w plan-report`: runs planning on all tasks and the policy
/// evaluation, and writes the tables with the command that produced them.
pub fn run(a: &PlanReportArgs) -> Result<()> {
    let o = PlanReportOptions {
        trials: a.trials,
        eval_trials: a.eval_trials,
        cem: a.cem.clone(),
        max_steps: a.max_steps,
        translation_std_m: a.translation_std_m,
        goals: (&a.goals).into(),
        tasks: a
            .tasks
            .split(',')
            .map(|t| Task::parse_goal_task(t.trim()).map_err(anyhow::Error::msg))
            .collect::<Result<Vec<Task>>>()?,
        models: report_models(
            a.models.as_deref(),
            a.with_random_model,
            a.trained.as_deref(),
        )?,
        section: a.section.clone(),
        sampling: a.sampling,
        device: a.device,
        precision: a.precision,
        plan_weights: a.plan_weights.clone(),
        plan_clip_frames: a.plan_clip_frames,
        decode_frames: a.decode_frames,
        seed: a.seed,
        results: Some(a.out.clone()),
        engine: a.engine,
        robot: a.robot.clone(),
    };
    let command = std::env::args().collect::<Vec<_>>().join(" ");
    let md = plan_report(&o, &command, &mut progress)?;
    bridgev2w_io::sections::write_section(&a.out, &a.section, &md)?;
    if let Some(w) = bridgev2w_io::plot::missing_font_warning() {
        eprintln!("{w}");
    }
    crate::print_stdout(&md)
}
