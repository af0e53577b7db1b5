//! Does a model's goal distance order candidate actions as the world does?
//! (`bridgev2w plan-fidelity`): per trial, candidate actions drawn as CEM's
//! first iteration draws them, scored by the model and by the synthetic
//! world, compared by Spearman's rank correlation.

use super::planning::GoalOptions;
use super::{mean_std, trial_seed, LoadedModel, ModelOptions};
use crate::cem::standard_normal;
use crate::fidelity::{rank_fidelity, RankFidelity};
use crate::model::{apply_increment, ActionWorldModel};
use crate::synthetic::{GoalLook, PerfectWorldModel, SyntheticEnv, TaskInstance, WaypointSpacing};
use crate::{EeAction, PlanError, Result};
use bridgev2w_data::synth::{Split, Task};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::time::Instant;

/// One fidelity study.
#[derive(Debug, Clone)]
pub struct FidelityOptions {
    /// The task.
    pub task: Task,
    /// Trials (task instances of the split), each one start/goal pair.
    pub trials: usize,
    /// The world model.
    pub model: ModelOptions,
    /// Candidate actions per trial (translation only, kept in the workspace).
    pub candidates: usize,
    /// Standard deviation of the candidates' translation (metres).
    pub translation_std_m: f64,
    /// Waypoint goals before the first key goal (as the planner); the trial's
    /// goal is the first goal image, as the planner's first one.
    pub waypoints: WaypointSpacing,
    /// Clip frames per action.
    pub frames_per_action: usize,
    /// Split of the task instances.
    pub split: Split,
    /// Seed of the world and the candidates.
    pub seed: u64,
    /// Keep the candidates' TCP in the camera's view, as the planner does
    /// with the same setting ([`super::planning::GoalOptions::view_margin`]).
    pub view_margin: Option<f64>,
}

impl Default for FidelityOptions {
    /// The defaults of `bridgev2w plan-fidelity`.
    fn default() -> Self {
        Self {
            task: Task::Reach,
            trials: 6,
            model: ModelOptions::default(),
            candidates: 24,
            translation_std_m: 0.1,
            waypoints: WaypointSpacing::Frames(2),
            frames_per_action: 2,
            split: Split::Test,
            seed: 0,
            view_margin: None,
        }
    }
}

/// The rank correlations of every trial.
#[derive(Debug, Clone)]
pub struct FidelityStudy {
    /// The settings it ran with.
    pub options: FidelityOptions,
    /// Per trial, the studied model.
    pub rows: Vec<RankFidelity>,
    /// Per trial, the perfect model on the same candidates (the reference
    /// row; empty when the studied model is the perfect one).
    pub perfect_rows: Vec<RankFidelity>,
    /// Wall time (seconds).
    pub seconds: f64,
}

/// Runs the study; `progress` gets a line per trial.
pub fn fidelity_study(
    o: &FidelityOptions,
    progress: &mut dyn FnMut(&str),
) -> Result<FidelityStudy> {
    if o.trials == 0 || o.candidates < 2 {
        return Err(PlanError::input(
            format!("--trials {} / --candidates {}", o.trials, o.candidates),
            "expected at least 1 trial and 2 candidates",
        ));
    }
    if !(o.translation_std_m.is_finite() && o.translation_std_m > 0.0) {
        return Err(PlanError::input(
            format!("--translation-std-m {}", o.translation_std_m),
            "expected a positive number of metres",
        ));
    }
    let view_options = GoalOptions {
        view_margin: o.view_margin,
        waypoints: o.waypoints,
        ..GoalOptions::default()
    };
    view_options.validate()?;
    o.model.check_sizes()?;
    super::sizes::check_trials("--trials", o.trials)?;
    super::sizes::check_candidates("--candidates", o.candidates)?;
    let loaded = LoadedModel::load(&o.model)?;
    super::sizes::check_candidates_memory(&loaded, "--candidates", o.candidates)?;
    let world = loaded.world(25, o.seed)?;
    let t0 = Instant::now();
    let reference = loaded.is_diffusion();
    let (mut rows, mut perfect_rows) = (vec![], vec![]);
    for trial in 0..o.trials {
        let inst =
            TaskInstance::new(&world, o.split, trial, o.task)?.with_waypoints(o.waypoints)?;
        let goal = inst
            .goal_images(&world, GoalLook::Builtin)
            .into_iter()
            .next()
            .ok_or_else(|| PlanError::Invalid("the task instance has no goal image".into()))?;
        let goal_ee = inst.expert_actions()[inst.goal_frames[0]];
        let obs = SyntheticEnv::new(&world, inst.clone()).observe();
        let workspace = inst.workspace(&world);
        let view = view_options.view_limit(&inst.expert.camera);
        let mut rng = ChaCha8Rng::seed_from_u64(trial_seed(o.seed, trial as u64));
        let std = o.translation_std_m;
        let normal = |rng: &mut ChaCha8Rng| std * standard_normal(rng);
        let candidates: Vec<EeAction> = (0..o.candidates)
            .map(|_| {
                let inc = [
                    normal(&mut rng),
                    normal(&mut rng),
                    normal(&mut rng),
                    0.0,
                    0.0,
                    0.0,
                ];
                let a = workspace.clamp(&apply_increment(&obs.ee, &inc, obs.ee[6]));
                view.as_ref().map_or(a, |v| v.constrain(&obs.ee, &a))
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
                o.frames_per_action,
            )
        };
        let f = loaded.with_model(&world, &inst, &mut |m| rank(m))?;
        progress(&format!(
            "{} trial {trial}: Spearman model vs real {:.2}, real vs distance {:.2}, model vs distance {:.2}",
            o.task.name(),
            f.model_vs_real,
            f.real_vs_distance,
            f.model_vs_distance
        ));
        rows.push(f);
        if reference {
            // The same candidates through the perfect model (the renderer
            // with its pyramid latent): the reference row.
            perfect_rows.push(rank(&real)?);
        }
    }
    Ok(FidelityStudy {
        options: o.clone(),
        rows,
        perfect_rows,
        seconds: t0.elapsed().as_secs_f64(),
    })
}

impl FidelityStudy {
    /// The `planning-fidelity` section of the results file; `command` is the
    /// command line that produced it.
    pub fn markdown(&self, command: &str) -> String {
        let o = &self.options;
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
        let mut table = row(&o.model.model.to_string(), &self.rows);
        if !self.perfect_rows.is_empty() {
            table += &row("perfect (the same candidates)", &self.perfect_rows);
        }
        format!(
            "## Does the model's goal distance order actions as the world does?\n\nProduced by `{command}` ({:.0} s). Per trial (a `{}` task instance of split `{}`, its first goal image), {} candidate actions (translation ~ N(0, {} m) per axis from the start pose, in the workspace{}, {} clip frames each) are scored by the model (latent L1 of its predicted terminal frame to the goal, as the planner does; a diffusion model samples with {} denoising steps and {} noise across the candidates{}) and by the synthetic world (the same latent L1 of the frame the world renders), and compared by Spearman's rank correlation, mean ± std over {} trials. CEM keeps the lowest-cost candidates, so it can only plan as well as *model vs distance* allows. The latent is a diffusion model's VAE posterior mean unless said otherwise, the perfect model's Gaussian image pyramid.\n\n| model | model vs real cost | real cost vs TCP distance | model cost vs TCP distance |\n|---|---|---|---|\n{table}",
            self.seconds,
            o.task.name(),
            o.split.name(),
            o.candidates,
            o.translation_std_m,
            o.view_margin.map_or(String::new(), |f| format!(
                ", the TCP kept in the camera's view ({f} of the image's smaller side from its edges, as `plan --view-margin {f}`)"
            )),
            o.frames_per_action,
            o.model.sampling.denoise_steps,
            o.model.sampling.batch_noise,
            crate::experiment::report::sampling_note(&o.model.sampling, o.model.decode_frames),
            o.trials,
        )
    }
}
