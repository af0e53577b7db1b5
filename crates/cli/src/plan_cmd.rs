//! `bridgev2w plan`, `bridgev2w eval-policy-rollout` and `bridgev2w plan-report`:
//! goal-image CEM-MPC and world-model policy evaluation, executed in the
//! synthetic tabletop world.

use anyhow::{bail, Context, Result};
use bridgev2w_data::synth::{Split, SynthConfig, Task, World};
use bridgev2w_plan::cem::{standard_normal, CemConfig, RotationSearch};
use bridgev2w_plan::choice::PlanModel;
use bridgev2w_plan::fidelity::{rank_fidelity, RankFidelity};
use bridgev2w_plan::model::{ActionWorldModel, MaskConditioned};
use bridgev2w_plan::mpc::{run_mpc, run_random, GripperChoice, MpcConfig};
use bridgev2w_plan::policy::{
    evaluate_trial, report_from_tallies, GoalDistanceJudge, LabelJudge, Policy, PolicyEvalReport,
    PolicyTally, ScriptedPolicy, SuccessJudge,
};
use bridgev2w_plan::synthetic::{PerfectWorldModel, SyntheticEnv, TaskInstance};
use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
use bridgev2w_world_model::pipeline::{PredictOptions, SampleOptions};
use bridgev2w_world_model::scheduler::SchedulerConfig;
use bridgev2w_world_model::spec::{ModelSpec, RandomPreset};

use bridgev2w_world_model::video::Image;
use bridgev2w_world_model::{ComputeDevice, Precision};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::path::PathBuf;
use std::time::Instant;

fn parse_task(s: &str) -> Result<Task, String> {
    Task::parse(s)
        .filter(|t| Task::ALL.contains(t))
        .ok_or_else(|| format!("unknown task {s:?}: expected reach, push or pick_place"))
}

fn parse_split(s: &str) -> Result<Split, String> {
    Split::parse(s).ok_or_else(|| {
        format!("unknown split {s:?}: expected train, test, unseen_camera or unseen_scene")
    })
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
    /// Denoising steps of a diffusion model.
    #[arg(long, default_value_t = 4)]
    pub denoise_steps: usize,
    /// cpu, cuda, cuda:N or auto.
    #[arg(long, default_value = "auto")]
    pub device: ComputeDevice,
    /// Image width of the synthetic world with the perfect model (pixels, even).
    #[arg(long, default_value_t = 96)]
    pub width: u32,
    /// Image height of the synthetic world with the perfect model (pixels, even).
    #[arg(long, default_value_t = 64)]
    pub height: u32,
    /// Clip frames of the perfect model.
    #[arg(long, default_value_t = 9)]
    pub clip_frames: usize,
}

/// A loaded model.
enum Loaded {
    Perfect,
    Diffusion(Box<BridgeV2W>),
}

fn load(a: &ModelArgs) -> Result<Loaded> {
    Ok(match &a.model {
        PlanModel::Perfect => Loaded::Perfect,
        PlanModel::World(ModelSpec::Random(preset)) => {
            let (vae, tf) = preset.configs();
            Loaded::Diffusion(Box::new(BridgeV2W::random(
                BridgeV2WConfig::tiny(),
                &vae,
                &tf,
                SchedulerConfig::cogvideox_5b_i2v(),
                a.device,
                0,
            )?))
        }
        PlanModel::World(ModelSpec::Folder(dir)) => {
            if !dir.is_dir() {
                bail!(
                    "--model {}: no such folder (expected perfect, random or a model folder)",
                    dir.display()
                );
            }
            Loaded::Diffusion(Box::new(
                BridgeV2W::load(
                    dir,
                    a.weights.as_deref(),
                    a.prompt_embeds.as_deref(),
                    BridgeV2WConfig::paper(),
                    a.device,
                    Precision::F32,
                )
                .with_context(|| format!("loading the model from {}", dir.display()))?,
            ))
        }
    })
}

impl Loaded {
    /// `(height, width)` the synthetic world must render at.
    fn resolution(&self, a: &ModelArgs) -> (u32, u32) {
        match self {
            Loaded::Perfect => (a.height, a.width),
            Loaded::Diffusion(m) => (m.config().height as u32, m.config().width as u32),
        }
    }

    /// Runs `f` with the world model of a task instance.
    fn with_model<T>(
        &self,
        a: &ModelArgs,
        world: &World,
        inst: &TaskInstance,
        f: &mut dyn FnMut(&dyn ActionWorldModel) -> Result<T>,
    ) -> Result<T> {
        match self {
            Loaded::Perfect => f(&PerfectWorldModel {
                world,
                instance: inst.clone(),
                clip_frames: a.clip_frames,
            }),
            Loaded::Diffusion(m) => {
                let predict = PredictOptions {
                    sample: SampleOptions {
                        steps: a.denoise_steps,
                        guidance_scale: 1.0,
                        ..SampleOptions::default()
                    },
                };
                let wrapped = MaskConditioned::new(
                    m.as_ref(),
                    world.embodiment.clone(),
                    inst.expert.meta.arm,
                    inst.expert.camera.clone(),
                    inst.expert.actions[0].clone(),
                    predict,
                )?;
                f(&wrapped)
            }
        }
    }
}

fn world_for(loaded: &Loaded, a: &ModelArgs, episode_frames: usize, seed: u64) -> Result<World> {
    let (h, w) = loaded.resolution(a);
    Ok(World::new(&SynthConfig {
        frames: episode_frames,
        width: w,
        height: h,
        seed,
        ..SynthConfig::default()
    })?)
}

/// The goal sequence and its switching, shared by `plan` and `plan-report`.
#[derive(Debug, Clone, clap::Args)]
pub struct GoalArgs {
    /// Waypoint goals: expert frames inserted evenly before each key goal
    /// image (a goal image says little about a gripper far from it).
    #[arg(long, default_value_t = 2)]
    pub waypoints: usize,
    /// Stalled steps (no 1% progress) after which the final goal counts as
    /// reached as far as the model can tell.
    #[arg(long, default_value_t = 4)]
    pub patience: usize,
    /// The same for subgoals and waypoints: then switch to the next goal.
    #[arg(long, default_value_t = 1)]
    pub subgoal_patience: usize,
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
}

#[derive(Debug, Clone, clap::Args)]
pub struct PlanArgs {
    /// reach, push or pick_place.
    #[arg(long, value_parser = parse_task)]
    pub task: Task,
    /// Trials (task instances of the split).
    #[arg(long, default_value_t = 20)]
    pub trials: usize,
    #[command(flatten)]
    pub model: ModelArgs,
    #[command(flatten)]
    pub cem: CemArgs,
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
    #[arg(long, default_value = "test", value_parser = parse_split)]
    pub split: Split,
    /// Frames of the scripted expert episodes (start, goals).
    #[arg(long, default_value_t = 25)]
    pub episode_frames: usize,
    /// Seed of the world and the planner.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
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

fn mpc_config(a: &PlanArgs) -> Result<MpcConfig> {
    let rotation_search = a.rotation;
    let gripper = a.gripper.policy(a.task);
    let cfg = MpcConfig {
        cem: CemConfig {
            samples: a.cem.samples,
            elites: a.cem.elites,
            iterations: a.cem.iters,
            horizon: a.cem.horizon,
            init_translation_std_m: a.translation_std_m,
            translation_only: !a.search_rotation,
            discretize: a.discretize,
            rotation_search,
            rotation_sample_fraction: a.rotation_sample_fraction,
            keep_elites: a.cem.keep_elites,
            ..CemConfig::default()
        },
        frames_per_action: a.frames_per_action,
        max_steps: a.max_steps,
        gripper,
        execute_best: a.cem.execute_best,
        patience: a.goals.patience,
        subgoal_patience: a.goals.subgoal_patience,
        ..MpcConfig::default()
    };
    cfg.cem.validate()?;
    Ok(cfg)
}

/// Plans every trial of `a.task` and runs the random baseline on the same instances.
pub fn plan_summary(a: &PlanArgs) -> Result<PlanSummary> {
    if a.trials == 0 {
        bail!("--trials must be at least 1");
    }
    let cfg = mpc_config(a)?;
    let loaded = load(&a.model)?;
    let world = world_for(&loaded, &a.model, a.episode_frames, a.seed)?;
    let t0 = Instant::now();
    let (mut planned, mut random) = (0, 0);
    let (mut planned_err, mut random_err, mut steps) = (0.0, 0.0, 0.0);
    let (mut planned_rot, mut random_rot) = (0.0, 0.0);
    for trial in 0..a.trials {
        let mut inst = TaskInstance::new(&world, a.split, trial, a.task)?;
        if !a.single_goal {
            inst = inst.with_waypoints(a.goals.waypoints);
        }
        let mut goals: Vec<Image> = inst.goal_images();
        if a.single_goal {
            goals.drain(..goals.len() - 1);
        }
        let seed = a.seed ^ (trial as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15);
        let mut cfg = cfg.clone();
        cfg.switch_after_goal = if a.single_goal {
            0
        } else {
            inst.first_key_goal
        };
        if !a.no_workspace {
            cfg.workspace = Some(inst.workspace(&world));
        }
        let mut env = SyntheticEnv::new(&world, inst.clone());
        let out = loaded.with_model(&a.model, &world, &inst, &mut |m| {
            Ok(run_mpc(
                m,
                &mut env,
                &goals,
                &cfg,
                &mut ChaCha8Rng::seed_from_u64(seed),
            )?)
        })?;
        let ok = env.success();
        let err = inst.error_m(&world, &env.state);
        let rot = inst.tcp_rotation_error_rad(&world, &env.state);
        let mut base = SyntheticEnv::new(&world, inst.clone());
        run_random(&mut base, &cfg, &mut ChaCha8Rng::seed_from_u64(seed))?;
        let rok = base.success();
        let rerr = inst.error_m(&world, &base.state);
        let rrot = inst.tcp_rotation_error_rad(&world, &base.state);
        eprintln!(
            "{} trial {trial}: planner {} ({:.1} cm, TCP {:.1} deg off, {} steps), random {} ({:.1} cm, {:.1} deg)",
            a.task.name(),
            if ok { "success" } else { "failure" },
            err * 100.0,
            rot.to_degrees(),
            out.steps,
            if rok { "success" } else { "failure" },
            rerr * 100.0,
            rrot.to_degrees()
        );
        planned += usize::from(ok);
        random += usize::from(rok);
        planned_err += err;
        random_err += rerr;
        planned_rot += rot;
        random_rot += rrot;
        steps += out.steps as f64;
    }
    let n = a.trials as f64;
    Ok(PlanSummary {
        task: a.task,
        trials: a.trials,
        planned,
        random,
        planned_error_m: planned_err / n,
        random_error_m: random_err / n,
        planned_rotation_error_rad: planned_rot / n,
        random_rotation_error_rad: random_rot / n,
        planned_steps: steps / n,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

/// `bridgev2w plan`.
pub fn run_plan(a: &PlanArgs) -> Result<()> {
    let s = plan_summary(a)?;
    crate::print_stdout(&format!(
        "{}: planner ({}) {}/{} successes (mean error {:.1} cm, TCP orientation {:.1} deg off, {:.1} actions), random actions {}/{} (mean error {:.1} cm, {:.1} deg); {:.0} s\n",
        s.task.name(),
        a.model.model,
        s.planned,
        s.trials,
        s.planned_error_m * 100.0,
        s.planned_rotation_error_rad.to_degrees(),
        s.planned_steps,
        s.random,
        s.trials,
        s.random_error_m * 100.0,
        s.random_rotation_error_rad.to_degrees(),
        s.seconds
    ))
}

/// `bridgev2w eval-policy-rollout`.
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

/// Runs the policy evaluation.
pub fn eval_rollout_report(a: &EvalRolloutArgs) -> Result<PolicyEvalReport> {
    if a.trials == 0 {
        bail!("--trials must be at least 1");
    }
    let offsets: Vec<f64> = a
        .offsets_mm
        .split(',')
        .map(|s| {
            s.trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite() && *v >= 0.0)
                .with_context(|| format!("--offsets-mm: {s:?} is not a non-negative number"))
        })
        .collect::<Result<_>>()?;
    if offsets.len() < 2 {
        bail!("--offsets-mm: at least two policies are needed for a correlation");
    }
    let loaded = load(&a.model)?;
    let world = world_for(&loaded, &a.model, a.episode_frames, a.seed)?;
    let instances: Vec<TaskInstance> = (0..a.trials)
        .map(|i| TaskInstance::new(&world, a.split, i, a.task))
        .collect::<std::result::Result<_, _>>()?;
    let labels = a.labels.as_deref().map(LabelJudge::read).transpose()?;
    let horizon = a.episode_frames - 1;
    let mut names = Vec::new();
    let mut tallies = Vec::new();
    // One instance at a time so each gets its own model (camera, scene).
    for (pi, off) in offsets.iter().enumerate() {
        let mut policy = ScriptedPolicy::new(
            Vec::new(),
            a.chunk,
            off / 1e3,
            a.jitter_mm / 1e3,
            a.seed ^ (pi as u64 + 1).wrapping_mul(0xA076_1D64_78BD_642F),
        );
        let name = policy.name();
        let mut tally = PolicyTally::default();
        for (trial, inst) in instances.iter().enumerate() {
            policy.expert = inst.expert_actions();
            let outcome = loaded.with_model(&a.model, &world, inst, &mut |m| {
                let encode = |img: &Image| m.encode(img);
                let goal_judge = GoalDistanceJudge {
                    encode: &encode,
                    ratio: a.ratio,
                };
                let judge: &dyn SuccessJudge = match &labels {
                    Some(l) => l,
                    None => &goal_judge,
                };
                Ok(evaluate_trial(
                    &world,
                    inst,
                    trial,
                    &mut policy,
                    m,
                    judge,
                    horizon,
                )?)
            })?;
            tally.add(&outcome);
        }
        eprintln!(
            "{name}: world model {:.2}{}, synthetic world {:.2}",
            tally.model_rate(),
            tally
                .mean_progress()
                .map(|p| format!(" (goal progress {p:+.3})"))
                .unwrap_or_default(),
            tally.real_rate()
        );
        names.push(name);
        tallies.push(tally);
    }
    Ok(report_from_tallies(names, &tallies)?)
}

/// `bridgev2w eval-policy-rollout`.
pub fn run_eval_rollout(a: &EvalRolloutArgs) -> Result<()> {
    let r = eval_rollout_report(a)?;
    crate::print_stdout(&eval_table(&r))
}

fn eval_table(r: &PolicyEvalReport) -> String {
    let progress = r.progress.as_ref();
    let mut s = String::from("| policy | world-model success |");
    if progress.is_some() {
        s += " world-model goal progress |";
    }
    s += " synthetic-world success |\n|---|---|---|";
    if progress.is_some() {
        s += "---|";
    }
    s += "\n";
    for (i, ((p, w), g)) in r.policies.iter().zip(&r.predicted).zip(&r.real).enumerate() {
        s += &format!("| {p} | {w:.2} |");
        if let Some(pr) = progress {
            s += &format!(" {:+.3} |", pr.mean[i]);
        }
        s += &format!(" {g:.2} |\n");
    }
    s += &format!(
        "\nSuccess rates: MMRV {:.3} (lower is better), Pearson r {:.3}\n",
        r.mmrv, r.pearson
    );
    if let Some(pr) = progress {
        s += &format!(
            "Goal progress vs synthetic-world success: MMRV {:.3}, Pearson r {:.3}\n",
            pr.mmrv, pr.pearson
        );
    }
    s
}

/// `bridgev2w plan-report`.
#[derive(Debug, Clone, clap::Args)]
pub struct PlanReportArgs {
    /// Output markdown file.
    #[arg(long, default_value = "docs/results.md")]
    pub out: PathBuf,
    /// Planning trials per task (0: no planning, only the policy evaluation).
    #[arg(long, default_value_t = 20)]
    pub trials: usize,
    /// Policy-evaluation trials per policy.
    #[arg(long, default_value_t = 10)]
    pub eval_trials: usize,
    #[command(flatten)]
    pub cem: CemArgs,
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
    /// Denoising steps of the diffusion models' predictions.
    #[arg(long, default_value_t = 4)]
    pub denoise_steps: usize,
    /// cpu, cuda, cuda:N or auto: the device of the diffusion models.
    #[arg(long, default_value = "cpu")]
    pub device: ComputeDevice,
    /// Seed.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
}

/// A model of the report: `perfect`, `random`, or a trained folder
/// (`backbone/` + `bridgev2w.safetensors`).
#[derive(Debug, Clone, PartialEq)]
enum ReportModel {
    Perfect,
    Random,
    Trained(PathBuf),
}

impl ReportModel {
    fn label(&self) -> String {
        match self {
            Self::Perfect => "perfect".into(),
            Self::Random => "random".into(),
            Self::Trained(dir) => format!("trained (`{}`)", dir.display()),
        }
    }

    fn args(&self, a: &PlanReportArgs) -> Result<ModelArgs> {
        let (model, weights) = match self {
            Self::Perfect => (PlanModel::Perfect, None),
            Self::Random => (
                PlanModel::World(ModelSpec::Random(RandomPreset::Tiny)),
                None,
            ),
            Self::Trained(dir) => {
                let (backbone, weights) = (dir.join("backbone"), dir.join("bridgev2w.safetensors"));
                if !backbone.is_dir() || !weights.is_file() {
                    bail!(
                        "--trained {}: expected backbone/ (a diffusers CogVideoX I2V folder) and bridgev2w.safetensors, as assets/demo-model",
                        dir.display()
                    );
                }
                (PlanModel::World(ModelSpec::Folder(backbone)), Some(weights))
            }
        };
        Ok(ModelArgs {
            model,
            weights,
            prompt_embeds: None,
            denoise_steps: a.denoise_steps,
            device: a.device,
            width: 96,
            height: 64,
            clip_frames: 9,
        })
    }
}

/// The models of `plan-report`'s tables, in order, from `--models` (or the
/// default: perfect, random with `--with-random-model`, trained with
/// `--trained`).
fn report_models(a: &PlanReportArgs) -> Result<Vec<ReportModel>> {
    let Some(list) = &a.models else {
        let mut out = vec![ReportModel::Perfect];
        if a.with_random_model {
            out.push(ReportModel::Random);
        }
        out.extend(a.trained.clone().map(ReportModel::Trained));
        return Ok(out);
    };
    let mut out = Vec::new();
    for name in list.split(',').map(str::trim) {
        let m = match name {
            "perfect" => ReportModel::Perfect,
            "random" => ReportModel::Random,
            "trained" => match &a.trained {
                Some(dir) => ReportModel::Trained(dir.clone()),
                None => bail!("--models {list}: `trained` needs --trained DIR"),
            },
            other => bail!(
                "--models {list}: unknown model {other:?}; expected perfect, trained or random"
            ),
        };
        if out.contains(&m) {
            bail!("--models {list}: {name} named twice");
        }
        out.push(m);
    }
    if a.with_random_model && !out.contains(&ReportModel::Random) {
        out.push(ReportModel::Random);
    }
    if a.trained.is_some() && !out.iter().any(|m| matches!(m, ReportModel::Trained(_))) {
        bail!("--models {list}: --trained is given but `trained` is not among the models");
    }
    Ok(out)
}

/// `bridgev2w plan-report`: runs planning on all tasks and the policy
/// evaluation, and writes the tables with the command that produced them.
pub fn run_plan_report(a: &PlanReportArgs) -> Result<()> {
    let command: Vec<String> = std::env::args().collect();
    if a.section.is_empty()
        || !a
            .section
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
    {
        bail!(
            "--section {:?}: expected a name of letters, digits, - and _",
            a.section
        );
    }
    let tasks = a
        .tasks
        .split(',')
        .map(|t| parse_task(t.trim()).map_err(anyhow::Error::msg))
        .collect::<Result<Vec<Task>>>()?;
    // Resolved once, up front: a bad folder fails before hours of planning.
    let models = report_models(a)?
        .into_iter()
        .map(|m| {
            let args = m.args(a)?;
            Ok((m, args))
        })
        .collect::<Result<Vec<(ReportModel, ModelArgs)>>>()?;
    let planners: Vec<&(ReportModel, ModelArgs)> = models
        .iter()
        .filter(|(m, _)| *m != ReportModel::Random)
        .collect();
    if planners.is_empty() && a.trials > 0 {
        bail!("--models: expected perfect or trained among them (random only evaluates policies; --trials 0 plans nothing)");
    }
    let mut md = String::from(if a.trials > 0 {
        "## Goal-image planning and policy evaluation in the synthetic world"
    } else {
        "## Policy evaluation in the synthetic world"
    });
    if a.section != "planning" {
        let names: Vec<String> = models.iter().map(|(m, _)| m.label()).collect();
        md += &format!(": {}", names.join(", "));
    }
    md += "\n\n";
    md += &format!(
        "Produced by `{}` (diffusion models on `{}`). The synthetic tabletop world (Franka, {}x{} images, split `test`) is the real robot; each table names the world model that plans or rolls policies out.\n\n",
        command.join(" "),
        a.device,
        96,
        64
    );
    if a.trials > 0 {
        md += &plan_tables(a, &tasks, &planners)?;
    }
    md += &format!(
        "\n### Policy evaluation by world-model rollouts ({} trials per policy, pick_place)\n\nScripted policies replay the expert with a per-trial offset of the given standard deviation (z: half) plus 2 mm jitter, in chunks of 8 actions padded to the 9-frame clip. World-model success: goal-distance judge (final predicted frame at most 0.5x the start's latent distance to the goal). World-model goal progress: the mean over trials of (d_start - d_last) / max(d_start, d_last) for those latent distances (1: at the goal, 0: no nearer, negative: farther); it ranks policies even when no rollout succeeds. Synthetic-world success: the task's state check.\n",
        a.eval_trials
    );
    for (model, args) in &models {
        let ea = EvalRolloutArgs {
            task: Task::PickPlace,
            trials: a.eval_trials,
            model: args.clone(),
            offsets_mm: "0,10,20,30,50".into(),
            jitter_mm: 2.0,
            chunk: 8,
            ratio: 0.5,
            labels: None,
            split: Split::Test,
            episode_frames: 25,
            seed: a.seed,
        };
        let r = eval_rollout_report(&ea)?;
        md += &format!(
            "\n#### Model: {}{}\n\n{}",
            model.label(),
            match model {
                ReportModel::Perfect => String::new(),
                _ => format!(" ({} denoising steps)", a.denoise_steps),
            },
            eval_table(&r)
        );
    }
    crate::report::write_section(&a.out, &a.section, &md)?;
    crate::print_stdout(&md)
}

/// The planning part of `plan-report`: the CEM settings and a row per task
/// and planning model.
fn plan_tables(
    a: &PlanReportArgs,
    tasks: &[Task],
    planners: &[&(ReportModel, ModelArgs)],
) -> Result<String> {
    let mut md = format!(
        "### Goal-image CEM-MPC ({} trials per task)\n\nCEM: S = {}, k = {}, T = {}, H = {}, initial translation std {} m per step, 2 clip frames per action, at most {} actions, translation-only search{}{}; gripper searched for reach, heuristic for push/pick_place. Goals: two key goal images per task (reach: the half-way pose, then the final one; push: the end of the push, then the final frame; pick_place: the grasp, then the final frame), each preceded by {} waypoint images (evenly spaced expert frames); a goal ends after {} stalled step(s) (no 1% latent progress), the final one after {}. Success: TCP (reach) or object (push, pick_place; released) within 3 cm of the scripted expert's final one. Random baseline: the same number of actions drawn from CEM's initial distribution.\n\n| task | model | planner success | random-action success | planner mean error (cm) | random mean error (cm) | mean actions | time (s) |\n|---|---|---|---|---|---|---|---|\n",
        a.trials,
        a.cem.samples,
        a.cem.elites,
        a.cem.iters,
        a.cem.horizon,
        a.translation_std_m,
        a.max_steps,
        if a.cem.keep_elites { ", elites carried over (iCEM)" } else { "" },
        if a.cem.execute_best { ", the best candidate executed" } else { ", the refined mean executed" },
        a.goals.waypoints,
        a.goals.subgoal_patience,
        a.goals.patience
    );
    for &task in tasks {
        for &(planner, args) in planners {
            let pa = PlanArgs {
                task,
                trials: a.trials,
                model: args.clone(),
                cem: a.cem.clone(),
                frames_per_action: 2,
                max_steps: a.max_steps,
                translation_std_m: a.translation_std_m,
                search_rotation: false,
                rotation: RotationSearch::Joint,
                rotation_sample_fraction: 0.0,
                discretize: false,
                gripper: GripperChoice::Auto,
                single_goal: false,
                goals: a.goals.clone(),
                no_workspace: false,
                split: Split::Test,
                episode_frames: 25,
                seed: a.seed,
            };
            let s = plan_summary(&pa)?;
            md += &format!(
                "| {} | {} | {}/{} | {}/{} | {:.1} | {:.1} | {:.1} | {:.0} |\n",
                task.name(),
                planner.label(),
                s.planned,
                s.trials,
                s.random,
                s.trials,
                s.planned_error_m * 100.0,
                s.random_error_m * 100.0,
                s.planned_steps,
                s.seconds
            );
        }
    }
    Ok(md)
}

/// `bridgev2w plan-fidelity`.
#[derive(Debug, Clone, clap::Args)]
pub struct PlanFidelityArgs {
    /// reach, push or pick_place.
    #[arg(long, value_parser = parse_task, default_value = "reach")]
    pub task: Task,
    /// Trials (task instances of the split), each one start/goal pair.
    #[arg(long, default_value_t = 6)]
    pub trials: usize,
    #[command(flatten)]
    pub model: ModelArgs,
    /// Candidate actions per trial, drawn as CEM's first iteration draws
    /// them (translation only, kept in the workspace).
    #[arg(long, default_value_t = 24)]
    pub candidates: usize,
    /// Standard deviation of the candidates' translation (metres).
    #[arg(long, default_value_t = 0.1)]
    pub translation_std_m: f64,
    /// Waypoint goals before the first key goal (as `plan`); the trial's
    /// goal is the first goal image, as the planner's first one.
    #[arg(long, default_value_t = 2)]
    pub waypoints: usize,
    /// Clip frames per action.
    #[arg(long, default_value_t = 2)]
    pub frames_per_action: usize,
    /// Split of the task instances.
    #[arg(long, default_value = "test", value_parser = parse_split)]
    pub split: Split,
    /// Seed of the world and the candidates.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Also write the table to this markdown file (its `planning-fidelity`
    /// section), e.g. docs/results.md.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Mean and sample standard deviation.
fn mean_std(v: &[f64]) -> (f64, f64) {
    let n = v.len() as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = if v.len() > 1 {
        v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0)
    } else {
        0.0
    };
    (m, var.sqrt())
}

/// `bridgev2w plan-fidelity`: does the model's goal distance order
/// candidate actions as the synthetic world does?
pub fn run_plan_fidelity(a: &PlanFidelityArgs) -> Result<()> {
    if a.trials == 0 || a.candidates < 2 {
        bail!(
            "--trials {} / --candidates {}: expected at least 1 trial and 2 candidates",
            a.trials,
            a.candidates
        );
    }
    if !(a.translation_std_m.is_finite() && a.translation_std_m > 0.0) {
        bail!(
            "--translation-std-m {}: expected a positive number of metres",
            a.translation_std_m
        );
    }
    let loaded = load(&a.model)?;
    let world = world_for(&loaded, &a.model, 25, a.seed)?;
    let t0 = Instant::now();
    let reference = matches!(loaded, Loaded::Diffusion(_));
    let (mut rows, mut perfect_rows): (Vec<RankFidelity>, Vec<RankFidelity>) = (vec![], vec![]);
    for trial in 0..a.trials {
        let inst = TaskInstance::new(&world, a.split, trial, a.task)?.with_waypoints(a.waypoints);
        let goal = inst
            .goal_images()
            .into_iter()
            .next()
            .context("the task instance has no goal image")?;
        let goal_ee = inst.expert_actions()[inst.goal_frames[0]];
        let obs = SyntheticEnv::new(&world, inst.clone()).observe();
        let workspace = inst.workspace(&world);
        let mut rng =
            ChaCha8Rng::seed_from_u64(a.seed ^ (trial as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15));
        let std = a.translation_std_m;
        let normal = |rng: &mut ChaCha8Rng| std * standard_normal(rng);
        let candidates: Vec<[f64; 7]> = (0..a.candidates)
            .map(|_| {
                let inc = [
                    normal(&mut rng),
                    normal(&mut rng),
                    normal(&mut rng),
                    0.0,
                    0.0,
                    0.0,
                ];
                workspace.clamp(&bridgev2w_plan::model::apply_increment(
                    &obs.ee, &inc, obs.ee[6],
                ))
            })
            .collect();
        let real = PerfectWorldModel {
            world: &world,
            instance: inst.clone(),
            clip_frames: 9,
        };
        let rank = |m: &dyn ActionWorldModel| {
            rank_fidelity(
                m,
                &real,
                &obs,
                &goal,
                &goal_ee,
                &candidates,
                a.frames_per_action,
            )
        };
        let f = loaded.with_model(&a.model, &world, &inst, &mut |m| Ok(rank(m)?))?;
        eprintln!(
            "{} trial {trial}: Spearman model vs real {:.2}, real vs distance {:.2}, model vs distance {:.2}",
            a.task.name(),
            f.model_vs_real,
            f.real_vs_distance,
            f.model_vs_distance
        );
        rows.push(f);
        if reference {
            // The same candidates through the perfect model (the renderer
            // with its pyramid latent): the reference row.
            perfect_rows.push(rank(&real)?);
        }
    }
    let row = |name: &str, rows: &[RankFidelity]| {
        let col = |g: fn(&RankFidelity) -> f64| {
            let v: Vec<f64> = rows.iter().map(g).collect();
            let (m, s) = mean_std(&v);
            format!("{m:.2} ± {s:.2}")
        };
        format!(
            "| {name} | {} | {} | {} |\n",
            col(|f| f.model_vs_real),
            col(|f| f.real_vs_distance),
            col(|f| f.model_vs_distance)
        )
    };
    let mut table = row(&a.model.model.to_string(), &rows);
    if reference {
        table += &row("perfect (the same candidates)", &perfect_rows);
    }
    let command: Vec<String> = std::env::args().collect();
    let md = format!(
        "## Does the model's goal distance order actions as the world does?\n\nProduced by `{}` ({:.0} s). Per trial (a `{}` task instance of split `{}`, its first goal image), {} candidate actions (translation ~ N(0, {} m) per axis from the start pose, in the workspace, {} clip frames each) are scored by the model (latent L1 of its predicted terminal frame to the goal, as the planner does) and by the synthetic world (the same latent L1 of the frame the world renders), and compared by Spearman's rank correlation, mean ± std over {} trials. CEM keeps the lowest-cost candidates, so it can only plan as well as *model vs distance* allows. The latent is the model's own: a diffusion model's VAE posterior mean, the perfect model's Gaussian image pyramid.\n\n| model | model vs real cost | real cost vs TCP distance | model cost vs TCP distance |\n|---|---|---|---|\n{table}",
        command.join(" "),
        t0.elapsed().as_secs_f64(),
        a.task.name(),
        a.split.name(),
        a.candidates,
        a.translation_std_m,
        a.frames_per_action,
        a.trials,
    );
    if let Some(out) = &a.out {
        crate::report::write_section(out, "planning-fidelity", &md)?;
    }
    crate::print_stdout(&md)
}
