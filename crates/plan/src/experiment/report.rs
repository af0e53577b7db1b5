//! `plan-report`: planning on every task and the policy evaluation, with
//! each named model, as one section of the results file.

use super::planning::{plan_with, CemSizes, GoalOptions, PlanOptions};
use super::rollout::{rollout_with, RolloutOptions};
use super::{LoadedModel, ModelOptions, Sampling};
use crate::choice::PlanModel;
use crate::goal_latent::GoalLatent;
use crate::policy::PolicyEvalReport;
use crate::{PlanError, Result};
use bridgev2w_data::synth::{Engine, Task};
use bridgev2w_world_model::pipeline::DecodeFrames;
use bridgev2w_world_model::spec::{ModelSpec, RandomPreset};
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::PathBuf;

/// A model of the report: `perfect`, `random`, or a trained folder
/// (`backbone/` + `bridgev2w.safetensors`).
#[derive(Debug, Clone, PartialEq)]
pub enum ReportModel {
    /// The synthetic renderer.
    Perfect,
    /// Random tiny weights (policy evaluation only).
    Random,
    /// A trained folder, as `assets/demo-model`.
    Trained(PathBuf),
}

impl ReportModel {
    /// The model's name in the tables.
    pub fn label(&self) -> String {
        match self {
            Self::Perfect => "perfect".into(),
            Self::Random => "random".into(),
            Self::Trained(dir) => format!("trained (`{}`)", dir.display()),
        }
    }

    /// How to load it.
    fn options(&self, o: &PlanReportOptions) -> Result<ModelOptions> {
        let (model, weights) = match self {
            Self::Perfect => (PlanModel::Perfect, None),
            Self::Random => (
                PlanModel::World(ModelSpec::Random(RandomPreset::Tiny)),
                None,
            ),
            Self::Trained(dir) => {
                let (backbone, weights) = (dir.join("backbone"), dir.join("bridgev2w.safetensors"));
                if !backbone.is_dir() || !weights.is_file() {
                    return Err(PlanError::input(
                        format!("--trained {}", dir.display()),
                        "expected backbone/ (a diffusers CogVideoX I2V folder) and bridgev2w.safetensors, as assets/demo-model",
                    ));
                }
                (PlanModel::World(ModelSpec::Folder(backbone)), Some(weights))
            }
        };
        Ok(ModelOptions {
            model,
            weights,
            prompt_embeds: None,
            sampling: o.sampling,
            device: o.device,
            precision: o.precision,
            decode_frames: o.decode_frames,
            width: 96,
            height: 64,
            robot: o.robot.clone(),
            ..ModelOptions::default()
        })
    }
}

/// The settings of `plan-report`.
#[derive(Debug, Clone)]
pub struct PlanReportOptions {
    /// Planning trials per task (0: no planning, only the policy evaluation).
    pub trials: usize,
    /// Policy-evaluation trials per policy (0: no policy evaluation, only
    /// the planning).
    pub eval_trials: usize,
    /// The CEM sizes.
    pub cem: CemSizes,
    /// Executed actions at most.
    pub max_steps: usize,
    /// Initial translational standard deviation per step (metres).
    pub translation_std_m: f64,
    /// The goals.
    pub goals: GoalOptions,
    /// Tasks to plan.
    pub tasks: Vec<Task>,
    /// The world models of the tables, in order.
    pub models: Vec<ReportModel>,
    /// The results file's section the tables replace: its name decides the
    /// heading (the default `planning` names no models).
    pub section: String,
    /// How the diffusion models sample and where goal distances are measured.
    pub sampling: Sampling,
    /// The device of the diffusion models.
    pub device: ComputeDevice,
    /// Precision of the diffusion models.
    pub precision: Precision,
    /// BridgeV2W weights the trained model plans with instead of its
    /// folder's `bridgev2w.safetensors` (e.g. `bridgev2w-plan.safetensors`,
    /// trained on the clips planning predicts); the policy evaluation keeps
    /// the folder's.
    pub plan_weights: Option<PathBuf>,
    /// Frames of each clip the planning models predict (`None`: the
    /// model's own); policy evaluation keeps the model's own.
    pub plan_clip_frames: Option<usize>,
    /// Which frames of the diffusion models' predictions are decoded
    /// (planning and policy evaluation alike).
    pub decode_frames: DecodeFrames,
    /// Seed.
    pub seed: u64,
    /// The results file the section goes to: its figures are written next
    /// to it (`<results without .md>/figures/<section>-*.png`) and linked
    /// from the section; `None`: no figures.
    pub results: Option<PathBuf>,
    /// What executes the plans and the policies ([`PlanOptions::engine`]).
    pub engine: Engine,
    /// The synthetic world's robot ([`ModelOptions::robot`]).
    pub robot: String,
}

/// The models of the report from a comma-separated list (or, without one,
/// the default: perfect, random with `with_random`, trained with
/// `trained`).
pub fn report_models(
    list: Option<&str>,
    with_random: bool,
    trained: Option<&std::path::Path>,
) -> Result<Vec<ReportModel>> {
    let Some(list) = list else {
        let mut out = vec![ReportModel::Perfect];
        if with_random {
            out.push(ReportModel::Random);
        }
        out.extend(trained.map(|d| ReportModel::Trained(d.to_path_buf())));
        return Ok(out);
    };
    let bad = |m: String| PlanError::input(format!("--models {list}"), m);
    let mut out = Vec::new();
    for name in list.split(',').map(str::trim) {
        let m = match name {
            "perfect" => ReportModel::Perfect,
            "random" => ReportModel::Random,
            "trained" => match trained {
                Some(dir) => ReportModel::Trained(dir.to_path_buf()),
                None => return Err(bad("`trained` needs --trained DIR".into())),
            },
            other => {
                return Err(bad(format!(
                    "unknown model {other:?}; expected perfect, trained or random"
                )))
            }
        };
        if out.contains(&m) {
            return Err(bad(format!("{name} named twice")));
        }
        out.push(m);
    }
    if with_random && !out.contains(&ReportModel::Random) {
        out.push(ReportModel::Random);
    }
    if trained.is_some() && !out.iter().any(|m| matches!(m, ReportModel::Trained(_))) {
        return Err(bad(
            "--trained is given but `trained` is not among the models".into(),
        ));
    }
    Ok(out)
}

/// Runs planning on every task and the policy evaluation with every model,
/// and returns the section's markdown; `command` is the command line that
/// produced it, `progress` gets a line per trial.
pub fn plan_report(
    o: &PlanReportOptions,
    command: &str,
    progress: &mut dyn FnMut(&str),
) -> Result<String> {
    if !bridgev2w_io::sections::is_section_name(&o.section) {
        return Err(PlanError::input(
            format!("--section {:?}", o.section),
            bridgev2w_io::sections::SECTION_NAME_EXPECTED,
        ));
    }
    if o.trials == 0 && o.eval_trials == 0 {
        return Err(PlanError::input(
            "--trials 0 --eval-trials 0",
            "nothing to report: expected planning trials, policy-evaluation trials or both",
        ));
    }
    // Resolved once, up front: a bad folder fails before hours of planning.
    let models = o
        .models
        .iter()
        .map(|m| Ok((m.clone(), m.options(o)?)))
        .collect::<Result<Vec<(ReportModel, ModelOptions)>>>()?;
    for (_, options) in &models {
        options.check_sizes()?;
    }
    super::sizes::check_trials("--trials", o.trials)?;
    super::sizes::check_trials("--eval-trials", o.eval_trials)?;
    super::sizes::check_candidates("--samples", o.cem.samples)?;
    if let Some(frames) = o.plan_clip_frames {
        bridgev2w_io::memory::at_most(
            "--plan-clip-frames",
            frames as u64,
            bridgev2w_world_model::bridge::MAX_CLIP_FRAMES as u64,
            "frames",
        )?;
    }
    let planners: Vec<&(ReportModel, ModelOptions)> = models
        .iter()
        .filter(|(m, _)| *m != ReportModel::Random)
        .collect();
    if planners.is_empty() && o.trials > 0 {
        return Err(PlanError::input(
            "--models",
            "expected perfect or trained among them (random only evaluates policies; --trials 0 plans nothing)",
        ));
    }
    if let Some(w) = &o.plan_weights {
        let what = format!("--plan-weights {}", w.display());
        if !planners
            .iter()
            .any(|(m, _)| matches!(m, ReportModel::Trained(_)))
            || o.trials == 0
        {
            return Err(PlanError::input(
                what,
                "only a trained model that plans takes planning weights (name `trained` in --models, with --trials of at least 1)",
            ));
        }
        if !w.is_file() {
            return Err(PlanError::input(
                what,
                "expected a BridgeV2W weights file (ControlNet + LoRA safetensors), as assets/demo-model/bridgev2w-plan.safetensors",
            ));
        }
    }
    let world = super::rollout::world_name(o.engine).replace('-', " ");
    let mut md = match (o.trials > 0, o.eval_trials > 0) {
        (true, true) => format!("## Goal-image planning and policy evaluation in the {world}"),
        (true, false) => format!("## Goal-image planning in the {world}"),
        (false, _) => format!("## Policy evaluation in the {world}"),
    };
    if o.section != "planning" {
        // A trained model that plans with other weights is named with them,
        // as in the planning table.
        let names: Vec<String> = models
            .iter()
            .map(|(m, _)| match o.trials {
                0 => m.label(),
                _ => planner_label(m, o.plan_weights.as_deref()),
            })
            .collect();
        md += &format!(": {}", names.join(", "));
    }
    md += "\n\n";
    md += &format!(
        "Produced by `{command}` (diffusion models on `{}`{}). {} is the real robot; each table names the world model that plans or rolls policies out.\n\n",
        o.device,
        match o.precision {
            Precision::F32 => "",
            Precision::Bf16 => " in bfloat16",
        },
        match o.engine {
            Engine::Builtin => format!("The synthetic tabletop world (robot `{}`, 96x64 images, split `test`)", o.robot),
            Engine::Mujoco => format!("MuJoCo (the synthetic world's scenes, robot `{}`, split `test`, simulated with physics: position-controlled arm, free objects with contact and friction; 96x64 images)", o.robot) + ": every plan and policy is executed there and judged on MuJoCo's object poses against MuJoCo's run of the scripted expert, whose states the goal images show (the perfect model, the built-in world stepped kinematically, sees them drawn by the built-in renderer; a diffusion model sees MuJoCo's frames)",
        },
    );
    let mut plans = Vec::new();
    if o.trials > 0 {
        md += &plan_tables(o, &planners, progress, &mut plans)?;
    }
    let mut evals = Vec::new();
    if o.eval_trials > 0 {
        md += &policy_evaluation(o, &models, progress, &mut evals)?;
    }
    if let Some(results) = &o.results {
        md += &super::report_figures::figures_section(results, &o.section, &plans, &evals)?;
    }
    Ok(md)
}

/// The policy-evaluation part of the report: every model rolls the
/// scripted policies out (each model's report also pushed to `evals`, with
/// its label).
fn policy_evaluation(
    o: &PlanReportOptions,
    models: &[(ReportModel, ModelOptions)],
    progress: &mut dyn FnMut(&str),
    evals: &mut Vec<(String, PolicyEvalReport)>,
) -> Result<String> {
    let mut md = format!(
        "\n### Policy evaluation by world-model rollouts ({} trials per policy, pick_place)\n\nScripted policies replay the expert with a per-trial offset of the given standard deviation (z: half) plus 2 mm jitter, in chunks of 8 actions padded to the 9-frame clip. World-model success: goal-distance judge (final predicted frame at most 0.5x the start's latent distance to the goal). World-model goal progress: the mean over trials of (d_start - d_last) / max(d_start, d_last) for those latent distances (1: at the goal, 0: no nearer, negative: farther); it ranks policies even when no rollout succeeds. {}: the task's state check{}.\n",
        o.eval_trials,
        match o.engine {
            Engine::Builtin => "Synthetic-world success",
            Engine::Mujoco => "MuJoCo-world success",
        },
        match o.engine {
            Engine::Builtin => "",
            Engine::Mujoco => " on MuJoCo's state, against MuJoCo's run of the expert",
        }
    );
    for (model, options) in models {
        let ro = RolloutOptions {
            engine: o.engine,
            trials: o.eval_trials,
            model: options.clone(),
            seed: o.seed,
            ..RolloutOptions::new(Task::PickPlace)
        };
        let loaded = LoadedModel::load(options)?;
        let r = rollout_with(&loaded, &ro, Vec::new(), progress)?;
        evals.push((model.label(), r.clone()));
        md += &format!(
            "\n#### Model: {}{}\n\n{}",
            model.label(),
            match model {
                ReportModel::Perfect => String::new(),
                _ => format!(
                    " ({} denoising steps, {} noise{})",
                    o.sampling.denoise_steps,
                    o.sampling.batch_noise,
                    sampling_note(&o.sampling, o.decode_frames)
                ),
            },
            r.markdown()
        );
    }
    Ok(md)
}

/// The planning part of the report: the CEM settings and a row per task
/// and planning model (each row's summary also pushed to `summaries`, with
/// its model's label).
fn plan_tables(
    o: &PlanReportOptions,
    planners: &[&(ReportModel, ModelOptions)],
    progress: &mut dyn FnMut(&str),
    summaries: &mut Vec<(String, super::PlanSummary)>,
) -> Result<String> {
    let mut md = format!(
        "### Goal-image CEM-MPC ({} trials per task)\n\nCEM: S = {}, k = {}, T = {}, H = {}, initial translation std {} m per step, 2 clip frames per action, at most {} actions, translation-only search{}{}{}; gripper searched for reach, heuristic for push/pick_place{}. Goals: two key goal images per task (reach: the half-way pose, then the final one; push: the end of the push, then the final frame; pick_place: the grasp, then the final frame), {}; a goal ends after {} stalled step(s) (no 1% latent progress), the final one after {}{}. Success: TCP (reach) or object (push, pick_place; released) within 3 cm of the scripted expert's final one. Random baseline: the same number of actions drawn from CEM's initial distribution.\n\n| task | model | planner success | random-action success | planner mean error (cm) | random mean error (cm) | mean actions | time (s) |\n|---|---|---|---|---|---|---|---|\n",
        o.trials,
        o.cem.samples,
        o.cem.elites,
        o.cem.iters,
        o.cem.horizon,
        o.translation_std_m,
        o.max_steps,
        search_extras(&o.cem),
        match (o.cem.execute_best, o.cem.execute_actions) {
            (true, 1) => ", the best candidate executed".to_string(),
            (false, 1) => ", the refined mean executed".to_string(),
            (true, n) => format!(", the best candidate's first {n} actions executed per search"),
            (false, n) => format!(", the refined mean's first {n} actions executed per search"),
        },
        o.plan_clip_frames.map_or(String::new(), |n| format!(
            ", each candidate predicted as a clip of {n} frames"
        )),
        if o.goals.release_before_final {
            " (pick_place released on leaving the goal before the final one, which is pursued open)"
        } else {
            ""
        },
        o.goals.waypoints.describe(),
        o.goals.subgoal_patience,
        o.goals.patience,
        o.goals.view_margin.map_or(String::new(), |f| format!(
            "; planned and random moves stop where the TCP would come within {f} of the image's smaller side of its edges (kept in the camera's view)"
        ))
    );
    // The planners' model options: the report's, with the planning clip
    // and, for a trained model, the planning weights.
    let planning: Vec<ModelOptions> = planners
        .iter()
        .map(|(model, options)| ModelOptions {
            clip_frames: o.plan_clip_frames,
            weights: match (model, &o.plan_weights) {
                (ReportModel::Trained(_), Some(w)) => Some(w.clone()),
                _ => options.weights.clone(),
            },
            ..options.clone()
        })
        .collect();
    let loaded = planning
        .iter()
        .map(LoadedModel::load)
        .collect::<Result<Vec<_>>>()?;
    for l in &loaded {
        super::sizes::check_candidates_memory(l, "--samples", o.cem.samples)?;
    }
    for &task in &o.tasks {
        for ((&(planner, _), options), loaded) in planners.iter().zip(&planning).zip(&loaded) {
            let po = PlanOptions {
                engine: o.engine,
                trials: o.trials,
                model: options.clone(),
                cem: o.cem.clone(),
                max_steps: o.max_steps,
                translation_std_m: o.translation_std_m,
                goals: o.goals.clone(),
                seed: o.seed,
                ..PlanOptions::new(task)
            };
            let cfg = po.mpc_config()?;
            let s = plan_with(loaded, &po, &cfg, progress)?;
            let label = planner_label(planner, o.plan_weights.as_deref());
            md += &format!(
                "| {} | {} | {}/{} | {}/{} | {:.1} | {:.1} | {:.1} | {:.0} |\n",
                task.name(),
                label,
                s.planned,
                s.trials,
                s.random,
                s.trials,
                s.planned_error_m * 100.0,
                s.random_error_m * 100.0,
                s.planned_steps,
                s.seconds
            );
            summaries.push((label, s));
        }
    }
    Ok(md)
}

/// A planning model's name in the tables: its label, with the planning
/// weights of a trained model when they are not its folder's.
fn planner_label(model: &ReportModel, plan_weights: Option<&std::path::Path>) -> String {
    match (model, plan_weights) {
        (ReportModel::Trained(dir), Some(w)) => format!(
            "trained (`{}`, planning weights `{}`)",
            dir.display(),
            w.display()
        ),
        _ => model.label(),
    }
}

/// A diffusion model's departures from the defaults: `, strength S` when
/// sampling starts from the noised first frame,
/// `, the static scene kept outside the swept region (+N px)` when
/// predictions keep it, and `, goal distances on a Gaussian pyramid of the
/// image` when they are not measured in the VAE's latent, and `, only the
/// last latent-frame batch decoded` with [`DecodeFrames::Last`]; else
/// nothing.
pub(crate) fn sampling_note(sampling: &Sampling, decode_frames: DecodeFrames) -> String {
    let mut note = String::new();
    if sampling.strength < 1.0 {
        note += &format!(", strength {}", sampling.strength);
    }
    if let Some(m) = sampling.keep_static_margin_px {
        note += &format!(", the static scene kept outside the swept region (+{m} px)");
    }
    if sampling.goal_latent == GoalLatent::Pyramid {
        note += ", goal distances on a Gaussian pyramid of the image";
    }
    if decode_frames == DecodeFrames::Last {
        note += ", only the last latent-frame batch decoded";
    }
    note
}

/// The search options beyond S / k / T / H, as the section's text says them.
fn search_extras(cem: &super::planning::CemSizes) -> String {
    let mut text = String::new();
    if cem.keep_elites {
        text.push_str(", elites carried over (iCEM)");
    }
    if cem.include_mean {
        text.push_str(", the distribution's mean among the samples (staying put a candidate)");
    }
    if cem.shrink_on_stall < 1.0 {
        text.push_str(&format!(
            ", the spread times {} after each stalled step",
            cem.shrink_on_stall
        ));
    }
    text
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::experiment::planning::CemSizes;

    #[test]
    fn the_section_text_names_the_search_options_in_use() {
        let plain = CemSizes::default();
        assert_eq!(search_extras(&plain), "");
        let all = CemSizes {
            keep_elites: true,
            include_mean: true,
            shrink_on_stall: 0.5,
            ..plain
        };
        assert_eq!(
            search_extras(&all),
            ", elites carried over (iCEM), the distribution's mean among the samples (staying put a candidate), the spread times 0.5 after each stalled step"
        );
    }
}
