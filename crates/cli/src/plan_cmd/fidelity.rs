//! `bridgev2w plan-fidelity`: does a model's goal distance order candidate
//! actions as the synthetic world does (Spearman)?

use super::progress;
use anyhow::Result;
use bridgev2w_data::synth::{Split, Task};
use bridgev2w_plan::experiment::ModelOptions;
use bridgev2w_plan::experiment::{fidelity_study, FidelityOptions};
use std::path::PathBuf;

#[derive(Debug, Clone, clap::Args)]
pub struct PlanFidelityArgs {
    /// reach, push or pick_place.
    #[arg(long, value_parser = Task::parse_goal_task, default_value = "reach")]
    pub task: Task,
    /// Trials (task instances of the split), each one start/goal pair.
    #[arg(long, default_value_t = 6)]
    pub trials: usize,
    #[command(flatten)]
    pub model: ModelOptions,
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
    /// Instead of `--waypoints`: a waypoint goal about every this many
    /// metres of the expert's TCP path (as `plan`).
    #[arg(long, conflicts_with = "waypoints")]
    pub waypoint_every_m: Option<f64>,
    /// Clip frames per action.
    #[arg(long, default_value_t = 2)]
    pub frames_per_action: usize,
    /// Split of the task instances.
    #[arg(long, default_value = "test", value_parser = Split::parse_named)]
    pub split: Split,
    /// Seed of the world and the candidates.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Keep the candidates' TCP in the camera's view, this fraction of the
    /// image's smaller side from its edges (as `plan --view-margin`).
    #[arg(long)]
    pub view_margin: Option<f64>,
    /// Also write the table to this markdown file (its `planning-fidelity`
    /// section), e.g. docs/results.md.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// `bridgev2w plan-fidelity`.
pub fn run(a: &PlanFidelityArgs) -> Result<()> {
    let o = FidelityOptions {
        task: a.task,
        trials: a.trials,
        model: a.model.clone(),
        candidates: a.candidates,
        translation_std_m: a.translation_std_m,
        waypoints: super::waypoint_spacing(a.waypoints, a.waypoint_every_m),
        frames_per_action: a.frames_per_action,
        split: a.split,
        seed: a.seed,
        view_margin: a.view_margin,
    };
    let study = fidelity_study(&o, &mut progress)?;
    let md = study.markdown(&std::env::args().collect::<Vec<_>>().join(" "));
    if let Some(out) = &a.out {
        bridgev2w_io::sections::write_section(out, "planning-fidelity", &md)?;
    }
    crate::print_stdout(&md)
}
