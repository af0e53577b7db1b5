//! Does a world model's goal distance rank actions as the real world does?
//!
//! CEM only needs the model to *order* candidate actions correctly: the
//! elites are the candidates with the lowest cost. For one start and one
//! goal image, [`rank_fidelity`] scores the same candidate actions three
//! ways and compares the orders by Spearman's rank correlation:
//!
//! * the model's cost: the latent distance of the model's predicted
//!   terminal frame to the goal (what the planner uses);
//! * the real cost: the same latent distance (the model's own encoder) of
//!   the frame the real world renders for that action;
//! * the true distance: the candidate's end-effector position to the goal's.
//!
//! `model vs real` measures the model's fidelity (1 for a perfect model),
//! `real vs distance` how well the latent distance itself guides the arm
//! (no model error), `model vs distance` what the planner gets.

use crate::error::{PlanError, Result};
use crate::model::{check_image_size, expand_waypoints, latent_l1, ActionWorldModel};
use crate::{EeAction, Observation};
use bridgev2w_io::frame::RgbFrame;

/// Spearman rank correlations of one start/goal pair (see the module docs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RankFidelity {
    /// Model cost vs the real world's cost.
    pub model_vs_real: f64,
    /// Real cost vs the true end-effector distance to the goal pose.
    pub real_vs_distance: f64,
    /// Model cost vs the true end-effector distance.
    pub model_vs_distance: f64,
}

/// Spearman's rank correlation (see [`bridgev2w_eval::ranking::spearman`]).
fn spearman(a: &[f64], b: &[f64]) -> Result<f64> {
    bridgev2w_eval::ranking::spearman(a, b)
        .map_err(|e| PlanError::Invalid(format!("rank correlation: {e}")))
}

/// Scores `candidates` (one end-effector action each, reached from
/// `start.ee` over `frames_per_action` clip frames) with `model` and with
/// `real` (the real world as a model, e.g. the synthetic renderer), toward
/// `goal` (whose end-effector action is `goal_ee`), and compares the
/// orders. Both models are called once, with all candidates as one batch.
pub fn rank_fidelity<M, R>(
    model: &M,
    real: &R,
    start: &Observation,
    goal: &RgbFrame,
    goal_ee: &EeAction,
    candidates: &[EeAction],
    frames_per_action: usize,
) -> Result<RankFidelity>
where
    M: ActionWorldModel + ?Sized,
    R: ActionWorldModel + ?Sized,
{
    check_image_size(goal, model.resolution())?;
    if candidates.len() < 2 {
        return Err(PlanError::Invalid(format!(
            "{} candidate actions: expected at least 2 to rank",
            candidates.len()
        )));
    }
    crate::error::check_finite("candidate actions", candidates)?;
    let sequences: Vec<Vec<EeAction>> = candidates
        .iter()
        .map(|c| expand_waypoints(&start.ee, std::slice::from_ref(c), frames_per_action))
        .collect();
    let goal_latent = model.encode(goal)?;
    let cost = |frames: Vec<Observation>| -> Result<Vec<f64>> {
        frames
            .iter()
            .map(|o| latent_l1(&model.encode(&o.image)?, &goal_latent))
            .collect()
    };
    let model_cost = cost(model.rollout_batch(start, &sequences)?)?;
    let real_cost = cost(real.rollout_batch(start, &sequences)?)?;
    let distance_m: Vec<f64> = candidates
        .iter()
        .map(|c| {
            (0..3)
                .map(|i| (c[i] - goal_ee[i]).powi(2))
                .sum::<f64>()
                .sqrt()
        })
        .collect();
    Ok(RankFidelity {
        model_vs_real: spearman(&model_cost, &real_cost)?,
        real_vs_distance: spearman(&real_cost, &distance_m)?,
        model_vs_distance: spearman(&model_cost, &distance_m)?,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    /// A model that "predicts" the image whose every pixel is the
    /// candidate's x (in [0, 1]); `flip` mirrors it, a model that moves the
    /// arm the wrong way.
    struct Toy {
        flip: bool,
    }

    impl ActionWorldModel for Toy {
        fn clip_frames(&self) -> usize {
            9
        }
        fn resolution(&self) -> (usize, usize) {
            (2, 2)
        }
        fn rollout_batch(
            &self,
            start: &Observation,
            sequences: &[Vec<EeAction>],
        ) -> Result<Vec<Observation>> {
            Ok(sequences
                .iter()
                .map(|s| {
                    let x = s.last().unwrap()[0] as f32;
                    let v = if self.flip { 1.0 - x } else { x };
                    Observation {
                        image: RgbFrame {
                            height: 2,
                            width: 2,
                            rgb: vec![v; 12],
                        },
                        ..start.clone()
                    }
                })
                .collect())
        }
        fn encode(&self, image: &RgbFrame) -> Result<Vec<f32>> {
            Ok(image.rgb.clone())
        }
    }

    #[test]
    fn a_faithful_model_ranks_like_the_world_and_a_mirrored_one_does_not() {
        let start = Observation {
            image: RgbFrame {
                height: 2,
                width: 2,
                rgb: vec![0.0; 12],
            },
            joints: vec![],
            ee: [0.0; 7],
            scene: None,
        };
        let goal = RgbFrame {
            height: 2,
            width: 2,
            rgb: vec![0.2; 12],
        };
        let goal_ee = [0.2, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0];
        let cands: Vec<EeAction> = [0.0, 0.15, 0.3, 0.5, 0.9]
            .iter()
            .map(|&x| [x, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
            .collect();
        let world = Toy { flip: false };
        let f = rank_fidelity(&world, &world, &start, &goal, &goal_ee, &cands, 2).unwrap();
        assert!((f.model_vs_real - 1.0).abs() < 1e-6, "{f:?}");
        assert!((f.real_vs_distance - 1.0).abs() < 1e-6, "{f:?}");
        let bad = Toy { flip: true };
        let f = rank_fidelity(&bad, &world, &start, &goal, &goal_ee, &cands, 2).unwrap();
        assert!(f.model_vs_real < 0.5, "{f:?}");
        assert!(f.model_vs_distance < 0.5, "{f:?}");
        // Bad input: one candidate, a wrong-size goal.
        assert!(rank_fidelity(&world, &world, &start, &goal, &goal_ee, &cands[..1], 2).is_err());
        let small = RgbFrame {
            height: 1,
            width: 1,
            rgb: vec![0.0; 3],
        };
        assert!(matches!(
            rank_fidelity(&world, &world, &start, &small, &goal_ee, &cands, 2),
            Err(PlanError::GoalImageSize { .. })
        ));
    }
}
