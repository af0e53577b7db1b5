//! A success judge calibrated on the world model's own predictions
//! (`eval-policy-rollout --calibrate-judge N`, beyond the paper).
//!
//! The goal-distance judge calls a rollout a success when its last
//! predicted frame is at most `ratio` times as far from the goal image as
//! the start is (latent L1). A fixed ratio suits a model whose predictions
//! are as sharp as the goal image; a small trained model's predicted last
//! frame is blurred, so it stays far from the sharp goal even when the
//! actions reached it, and a fixed 0.5 calls every rollout a failure (the
//! shipped model's r 0 in docs/results.md). Calibrated, the judge first
//! measures how near the goal the model's own rollouts of the *expert's*
//! actions end: the floor `f`, the given quantile of `d_last / d_start` over
//! N episodes of the `train` split (never the evaluated ones), rolled out in
//! the model chunk by chunk as the policies are. The fixed judge is then
//! applied above that floor: success when `d_last / d_start <= f + ratio *
//! (1 - f)`. A model whose expert rollouts end on the goal (`f = 0`, the
//! perfect model) keeps the fixed judge; a blurred one is no longer asked
//! to come nearer the goal than the expert's own actions take it (its
//! floor may exceed 1: its rollouts of the expert end farther from the
//! sharp goal image than the sharp start is; the judge then accepts a
//! rollout ending between 1 and `f`, the nearer to 1 the smaller `ratio`).

use super::LoadedModel;
use crate::model::latent_l1;
use crate::policy::{rollout_in_model, JudgeCalibration, Policy, ScriptedPolicy};
use crate::synthetic::{GoalLook, SyntheticEnv, TaskInstance};
use crate::{PlanError, Result};
use bridgev2w_data::synth::{Split, Task, World};

/// What to calibrate on: the task's training episodes and how the
/// policies are rolled out.
#[derive(Debug, Clone, Copy)]
pub(super) struct CalibrationRun {
    /// The task.
    pub task: Task,
    /// Training episodes whose expert actions are rolled out.
    pub episodes: usize,
    /// The quantile of their `d_last / d_start` taken as the floor.
    pub quantile: f64,
    /// The fixed judge's ratio, applied above the floor.
    pub ratio: f64,
    /// Actions per policy chunk.
    pub chunk: usize,
    /// Actions per rollout.
    pub horizon: usize,
    /// Seed of the scripted replay.
    pub seed: u64,
}

/// The `q` quantile of `values` (linear between order statistics).
fn quantile(values: &[f64], q: f64) -> Option<f64> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let pos = q.clamp(0.0, 1.0) * (v.len() - 1) as f64;
    let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
    Some(v[lo] + (v[hi] - v[lo]) * (pos - lo as f64))
}

/// Checks the quantile, and that the judge calibrated is the one used (no
/// `labels`); the episode count is checked by the trials' size check.
pub(super) fn check(episodes: usize, quantile: f64, labels: bool) -> Result<()> {
    let q = quantile;
    if !(q.is_finite() && q > 0.0 && q <= 1.0) {
        return Err(PlanError::input(
            "--calibration-quantile",
            format!("{q}: expected a quantile in (0, 1]"),
        ));
    }
    if episodes > 0 && labels {
        return Err(PlanError::input(
            "--calibrate-judge",
            "calibrates the goal-distance judge, which --labels replaces: give one of them",
        ));
    }
    Ok(())
}

/// Rolls the expert's actions of `c.episodes` training episodes out in
/// `loaded` and returns the judge's floor (the `c.quantile` quantile of
/// their `d_last / d_start`) and its ratio above it.
pub(super) fn calibrate_ratio(
    loaded: &LoadedModel,
    world: &World,
    c: &CalibrationRun,
) -> Result<JudgeCalibration> {
    let mut expert_ratios = Vec::with_capacity(c.episodes);
    for i in 0..c.episodes {
        let inst = TaskInstance::new(world, Split::Train, i, c.task)?;
        let goal = inst
            .goal_images(world, GoalLook::Builtin)
            .pop()
            .ok_or_else(|| PlanError::Invalid("a task instance without a goal image".into()))?;
        let start = SyntheticEnv::new(world, inst.clone()).observe();
        // The expert's own actions, without offset or jitter.
        let mut expert = ScriptedPolicy::new(inst.expert_actions(), c.chunk, 0.0, 0.0, c.seed);
        let (d_start, d_last) = loaded.with_model(world, &inst, &mut |m| {
            expert.reset(i);
            let rolled = rollout_in_model(m, &mut expert, start.clone(), c.horizon)?;
            let g = m.encode(&goal)?;
            Ok((
                latent_l1(&m.encode(&start.image)?, &g)?,
                latent_l1(&m.encode(&rolled.last.image)?, &g)?,
            ))
        })?;
        expert_ratios.push(if d_start > 0.0 {
            d_last / d_start
        } else {
            f64::NAN
        });
    }
    let floor = quantile(&expert_ratios, c.quantile).ok_or_else(|| {
        PlanError::Invalid(format!(
            "--calibrate-judge {}: no expert rollout started away from its goal",
            c.episodes
        ))
    })?;
    // At least 0; above 1 where the model's rollouts of the expert end
    // farther from the goal image than the start is (a blurred last frame
    // against a sharp goal in the model's latent).
    let floor = floor.max(0.0);
    Ok(JudgeCalibration {
        floor,
        ratio: floor + c.ratio * (1.0 - floor),
        episodes: c.episodes,
        quantile: c.quantile,
        expert_ratios,
    })
}

#[cfg(test)]
mod tests {
    use super::quantile;

    #[test]
    fn quantiles_interpolate_between_order_statistics() {
        let v = [0.9, 0.1, 0.5, f64::NAN, 0.3];
        assert_eq!(quantile(&v, 0.0), Some(0.1));
        assert_eq!(quantile(&v, 1.0), Some(0.9));
        assert_eq!(quantile(&v, 0.5), Some(0.4));
        assert!((quantile(&v, 0.8).unwrap_or(0.0) - 0.66).abs() < 1e-12);
        assert_eq!(quantile(&[f64::NAN], 0.5), None);
    }
}
