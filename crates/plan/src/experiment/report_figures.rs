//! The figures of `plan-report`: planner success next to random actions per
//! task ([`planning_figure`]) and the policy evaluation's world-model
//! success against synthetic-world success, with the least-squares line
//! and Pearson r per model ([`policy_figure`]); [`figures_section`] writes
//! them next to the results file and returns the markdown that links them.

use super::planning::PlanSummary;
use crate::policy::PolicyEvalReport;
use crate::Result;
use bridgev2w_io::plot::bars::{BarFigure, Bars};
use bridgev2w_io::plot::scatter::{PointSet, ScatterFigure};
use bridgev2w_io::plot::{write_png, FigureDir};
use std::path::Path;

/// The planner's and the random baseline's success per task, a pair of
/// bars per planning model; `None` without planning.
pub fn planning_figure(rows: &[(String, PlanSummary)]) -> Option<BarFigure> {
    let mut tasks: Vec<String> = Vec::new();
    let mut models: Vec<String> = Vec::new();
    for (model, s) in rows {
        let task = s.task.name().to_string();
        if !tasks.contains(&task) {
            tasks.push(task);
        }
        if !models.contains(model) {
            models.push(model.clone());
        }
    }
    if rows.is_empty() {
        return None;
    }
    let rate = |model: &str, task: &str, random: bool| {
        rows.iter()
            .find(|(m, s)| m == model && s.task.name() == task)
            .map_or(f64::NAN, |(_, s)| {
                (if random { s.random } else { s.planned }) as f64 / s.trials.max(1) as f64
            })
    };
    let one = models.len() == 1;
    let mut series = Vec::new();
    for (k, model) in models.iter().enumerate() {
        for random in [false, true] {
            series.push(Bars {
                label: match (one, random) {
                    (true, false) => format!("planner ({model})"),
                    (true, true) => "random actions".into(),
                    (false, false) => format!("{model}: planner"),
                    (false, true) => format!("{model}: random actions"),
                },
                values: tasks.iter().map(|t| rate(model, t, random)).collect(),
                color: if random { 7 } else { k },
            });
        }
    }
    Some(BarFigure {
        title: "Goal-image planning: success per task".into(),
        y_desc: "success rate".into(),
        categories: tasks,
        series,
        y_range: (0.0, 1.05),
        size: (640, 400),
    })
}

/// Each model's policies as points (world-model success, synthetic-world
/// success), with its least-squares line; `None` without models.
pub fn policy_figure(evals: &[(String, PolicyEvalReport)]) -> Option<ScatterFigure> {
    if evals.is_empty() {
        return None;
    }
    let sets = evals
        .iter()
        .enumerate()
        .map(|(k, (model, r))| PointSet {
            label: format!("{model}: Pearson r = {:.2}", r.pearson),
            points: r
                .predicted
                .iter()
                .copied()
                .zip(r.real.iter().copied())
                .collect(),
            color: k,
        })
        .collect();
    Some(ScatterFigure {
        title: "Policy evaluation: a point per policy".into(),
        x_desc: "world-model success rate".into(),
        y_desc: "synthetic-world success rate".into(),
        sets,
        range: (-0.05, 1.05),
        size: (520, 480),
    })
}

/// Writes the figures of section `section` next to `results` and returns
/// the markdown that links them (empty when there is nothing to draw).
pub fn figures_section(
    results: &Path,
    section: &str,
    plans: &[(String, PlanSummary)],
    evals: &[(String, PolicyEvalReport)],
) -> Result<String> {
    let fig = FigureDir::next_to(results);
    let mut images = Vec::new();
    if let Some(f) = planning_figure(plans) {
        let name = format!("{section}-planner-vs-random.png");
        write_png(&fig.path(&name), &f)?;
        images.push(format!(
            "Planner and random-action success per task:\n\n{}",
            fig.image(&name, "Planner vs random-action success per task")
        ));
    }
    if let Some(f) = policy_figure(evals) {
        let name = format!("{section}-policy-evaluation.png");
        write_png(&fig.path(&name), &f)?;
        images.push(format!(
            "Policy evaluation: world-model against synthetic-world success rate per policy, with each model's least-squares line (dashed: y = x, perfect agreement):\n\n{}",
            fig.image(&name, "World-model vs synthetic-world success per policy")
        ));
    }
    Ok(if images.is_empty() {
        String::new()
    } else {
        format!("\n### Figures\n\n{}\n", images.join("\n\n"))
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use bridgev2w_data::synth::Task;

    fn summary(task: Task, planned: usize, random: usize) -> PlanSummary {
        PlanSummary {
            task,
            trials: 4,
            planned,
            planned_carried: 0,
            random,
            planned_error_m: 0.01,
            random_error_m: 0.1,
            planned_rotation_error_rad: 0.0,
            random_rotation_error_rad: 0.0,
            planned_steps: 3.0,
            seconds: 1.0,
        }
    }

    #[test]
    fn the_section_draws_and_links_both_figures() {
        let tmp = tempfile::tempdir().unwrap();
        let results = tmp.path().join("docs/results.md");
        let plans = vec![
            ("perfect".to_string(), summary(Task::Reach, 4, 1)),
            ("perfect".to_string(), summary(Task::Push, 2, 0)),
        ];
        let evals = vec![(
            "perfect".to_string(),
            PolicyEvalReport {
                policies: vec!["a".into(), "b".into(), "c".into()],
                predicted: vec![0.9, 0.5, 0.1],
                real: vec![1.0, 0.4, 0.2],
                mmrv: 0.0,
                pearson: 0.97,
                progress: None,
                failed: Vec::new(),
                calibration: None,
                executed_in: bridgev2w_data::synth::Engine::Builtin,
            },
        )];
        let md = figures_section(&results, "planning", &plans, &evals).unwrap();
        let dir = tmp.path().join("docs/results/figures");
        for (name, size) in [
            ("planning-planner-vs-random.png", (640, 400)),
            ("planning-policy-evaluation.png", (520, 480)),
        ] {
            let (got, share) = bridgev2w_io::plot::ink_share(&dir.join(name)).unwrap();
            assert_eq!(got, size, "{name}");
            assert!(share > 0.01, "{name}: {share}");
            assert!(md.contains(&format!("(results/figures/{name})")), "{md}");
        }
        let bars = planning_figure(&plans).unwrap();
        assert_eq!(bars.categories, ["reach", "push"]);
        assert_eq!(bars.series[0].values, [1.0, 0.5]);
        assert_eq!(bars.series[1].values, [0.25, 0.0]);
        // Nothing planned or evaluated: no figure, no heading.
        assert_eq!(figures_section(&results, "x", &[], &[]).unwrap(), "");
    }
}
