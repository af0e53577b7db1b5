//! The planning commands (`plan`, `plan-fidelity`, `eval-policy-rollout`,
//! `plan-report`): their arguments, turned into `bridgev2w_plan::experiment`
//! options, one library call each.

pub mod drift;
pub mod fidelity;
pub mod plan;
pub mod report;
pub mod rollout;

use bridgev2w_data::synth::{Split, Task};
use bridgev2w_plan::choice::PlanModel;
use bridgev2w_plan::experiment::planning::{CemSizes, GoalOptions};
use bridgev2w_plan::experiment::ModelOptions;
use bridgev2w_plan::goal_latent::GoalLatent;
use bridgev2w_plan::synthetic::WaypointSpacing;
use bridgev2w_world_model::pipeline::{BatchNoise, DecodeFrames};
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::PathBuf;

pub(crate) fn parse_task(s: &str) -> Result<Task, String> {
    Task::parse(s)
        .filter(|t| Task::ALL.contains(t))
        .ok_or_else(|| format!("unknown task {s:?}: expected reach, push or pick_place"))
}

pub(crate) fn parse_split(s: &str) -> Result<Split, String> {
    Split::parse(s).ok_or_else(|| {
        format!("unknown split {s:?}: expected train, test, unseen_camera or unseen_scene")
    })
}

/// Prints a progress line to stderr.
pub(crate) fn progress(line: &str) {
    eprintln!("{line}");
}

/// Which world model to plan or evaluate with.
#[derive(Debug, Clone, clap::Args)]
pub struct ModelArgs {
    /// `perfect` (the synthetic world's own renderer), `random` (BridgeV2W
    /// with random tiny weights at 64x96, 9 frames: a smoke test), or a
    /// CogVideoX image-to-video diffusers folder (with --weights).
    #[arg(long, default_value = "perfect")]
    pub model: PlanModel,
    /// BridgeV2W weights (ControlNet + LoRA safetensors) for a model folder.
    #[arg(long)]
    pub weights: Option<PathBuf>,
    /// The fixed prompt's T5 embedding for a model folder.
    #[arg(long)]
    pub prompt_embeds: Option<PathBuf>,
    #[command(flatten)]
    pub sampling: SamplingArgs,
    /// cpu, cuda, cuda:N or auto.
    #[arg(long, default_value = "auto")]
    pub device: ComputeDevice,
    /// Precision of a diffusion model: f32 or bf16 (bf16 halves the memory
    /// of a GPU run).
    #[arg(long, default_value = "f32")]
    pub precision: Precision,
    /// At most this many candidates through a diffusion model at once (all
    /// of a CEM iteration's by default): a smaller batch bounds the device
    /// memory; with shared batch noise the plan is the same.
    #[arg(long, value_name = "N")]
    pub max_batch: Option<usize>,
    /// Image width of the synthetic world with the perfect model (pixels, even).
    #[arg(long, default_value_t = 96)]
    pub width: u32,
    /// Image height of the synthetic world with the perfect model (pixels, even).
    #[arg(long, default_value_t = 64)]
    pub height: u32,
    /// Frames of each predicted clip (default: the model's own, 9 for the
    /// perfect model, a diffusion model's training clip). A planned action
    /// needs one more than its frames; a shorter clip is cheaper (beyond
    /// the paper).
    #[arg(long, value_name = "N")]
    pub clip_frames: Option<usize>,
    /// Which frames of a diffusion model's predictions are decoded: `all`,
    /// or `last` (only the VAE decoder's last batch of latent frames: the
    /// planner scores the clip's last frame; without the earlier frames'
    /// conv cache, an approximation; beyond the paper).
    #[arg(long, default_value = "all")]
    pub decode_frames: DecodeFrames,
}

/// How a diffusion model samples and how goal distances are measured,
/// shared by the planning commands.
#[derive(Debug, Clone, clap::Args)]
pub struct SamplingArgs {
    /// Denoising steps of a diffusion model.
    #[arg(long, default_value_t = 4)]
    pub denoise_steps: usize,
    /// How a diffusion model draws the noise of a batch of candidates:
    /// `shared` (common random numbers: candidates differ by their actions
    /// alone) or `independent`.
    #[arg(long, default_value = "shared")]
    pub batch_noise: BatchNoise,
    /// Where a diffusion model's sampling starts, in (0, 1]: 1 from pure
    /// noise; s < 1 from the first frame's latent in every frame, noised to
    /// the level a fraction s from the end (only the last ceil(s * steps)
    /// denoising steps run).
    #[arg(long, default_value_t = 1.0)]
    pub strength: f64,
    /// Keep the static scene of a diffusion model's predictions (beyond the
    /// paper): outside the region the candidate's masks have swept so far,
    /// dilated by this many pixels, each frame is the first frame.
    #[arg(long, value_name = "MARGIN_PX")]
    pub keep_static: Option<u32>,
    /// Where goal distances are measured: `model` (a diffusion model's VAE
    /// latent, the paper) or `pyramid` (a Gaussian pyramid of the image, the
    /// perfect model's latent: it keeps growing with the arm's displacement
    /// where a fine latent is flat; beyond the paper).
    #[arg(long, default_value = "model")]
    pub goal_latent: GoalLatent,
}

impl From<&ModelArgs> for ModelOptions {
    fn from(a: &ModelArgs) -> Self {
        Self {
            model: a.model.clone(),
            weights: a.weights.clone(),
            prompt_embeds: a.prompt_embeds.clone(),
            denoise_steps: a.sampling.denoise_steps,
            batch_noise: a.sampling.batch_noise,
            strength: a.sampling.strength,
            keep_static_margin_px: a.sampling.keep_static,
            goal_latent: a.sampling.goal_latent,
            device: a.device,
            precision: a.precision,
            max_batch: a.max_batch,
            width: a.width,
            height: a.height,
            clip_frames: a.clip_frames,
            decode_frames: a.decode_frames,
        }
    }
}

/// The goal sequence and its switching, shared by `plan` and `plan-report`.
#[derive(Debug, Clone, clap::Args)]
pub struct GoalArgs {
    /// Waypoint goals: expert frames inserted evenly before each key goal
    /// image (a goal image says little about a gripper far from it).
    #[arg(long, default_value_t = 2)]
    pub waypoints: usize,
    /// Instead of `--waypoints`: a waypoint goal about every this many
    /// metres of the expert's TCP path, evenly along it (a long approach
    /// gets several, a short segment none; beyond the paper).
    #[arg(long, conflicts_with = "waypoints")]
    pub waypoint_every_m: Option<f64>,
    /// Stalled steps (no 1% progress) after which the final goal counts as
    /// reached as far as the model can tell.
    #[arg(long, default_value_t = 4)]
    pub patience: usize,
    /// The same for subgoals and waypoints: then switch to the next goal.
    #[arg(long, default_value_t = 1)]
    pub subgoal_patience: usize,
    /// Keep the TCP inside the camera's view, this fraction of the image's
    /// smaller side from its edges (a goal image says nothing about a
    /// gripper out of view). Not given: no limit.
    #[arg(long)]
    pub view_margin: Option<f64>,
    /// pick_place: open the gripper on leaving the goal before the final
    /// one (the place) and pursue the final goal, the gripper lifted from
    /// the released object, open; without it the object is released after
    /// the final goal (beyond the paper).
    #[arg(long)]
    pub release_before_final: bool,
}

impl From<&GoalArgs> for GoalOptions {
    fn from(a: &GoalArgs) -> Self {
        Self {
            waypoints: waypoint_spacing(a.waypoints, a.waypoint_every_m),
            patience: a.patience,
            subgoal_patience: a.subgoal_patience,
            view_margin: a.view_margin,
            release_before_final: a.release_before_final,
        }
    }
}

/// `--waypoints N` or `--waypoint-every-m M` as a spacing.
pub fn waypoint_spacing(per_segment: usize, every_m: Option<f64>) -> WaypointSpacing {
    every_m.map_or(WaypointSpacing::Frames(per_segment), WaypointSpacing::PathM)
}

/// The CEM sizes shared by `plan` and `plan-report`.
#[derive(Debug, Clone, clap::Args)]
pub struct CemArgs {
    /// CEM samples S per iteration.
    #[arg(long, default_value_t = 64)]
    pub samples: usize,
    /// CEM elites k.
    #[arg(long, default_value_t = 8)]
    pub elites: usize,
    /// CEM iterations T.
    #[arg(long, default_value_t = 3)]
    pub iters: usize,
    /// Planning horizon H (actions). With H > 1 only the terminal frame is
    /// scored, so the executed first action of the best sequence is
    /// unconstrained; H = 1 scores exactly the executed action's outcome.
    #[arg(long, default_value_t = 1)]
    pub horizon: usize,
    /// Carry each CEM iteration's elites into the next selection (iCEM; off
    /// in the paper's algorithm).
    #[arg(long)]
    pub keep_elites: bool,
    /// Execute the best evaluated candidate's first action instead of the
    /// refined mean's (the paper executes the mean).
    #[arg(long)]
    pub execute_best: bool,
    /// Actions of the chosen plan executed before planning again, 1 to the
    /// horizon (the paper: 1). With `--horizon N --execute-actions N` one
    /// search pays for N actions, each chunk judged by its terminal frame
    /// (beyond the paper).
    #[arg(long, default_value_t = 1)]
    pub execute_actions: usize,
    /// Evaluate the sampling distribution's mean as one of the S samples
    /// (iCEM): in a step's first iteration that is staying put, so a step
    /// that no sample improves on holds the pose (beyond the paper).
    #[arg(long)]
    pub include_mean: bool,
    /// After each stalled step (no 1% progress) multiply the next search's
    /// standard deviations by this factor in (0, 1]; progress or a new goal
    /// restores them. 1: off (beyond the paper).
    #[arg(long, default_value_t = 1.0, value_name = "FACTOR")]
    pub shrink_on_stall: f64,
}

impl From<&CemArgs> for CemSizes {
    fn from(a: &CemArgs) -> Self {
        Self {
            samples: a.samples,
            elites: a.elites,
            iters: a.iters,
            horizon: a.horizon,
            keep_elites: a.keep_elites,
            execute_best: a.execute_best,
            execute_actions: a.execute_actions,
            include_mean: a.include_mean,
            shrink_on_stall: a.shrink_on_stall,
        }
    }
}
