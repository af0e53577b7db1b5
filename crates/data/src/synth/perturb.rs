//! Perturbed demonstrations: training episodes whose expert actions are
//! shifted, so that a world model also sees what off-target actions do
//! (a grasp that closes beside the object, a push that misses), not only
//! successful demonstrations. The paper notes that a model trained on
//! successes alone "recovers" small action errors and so overestimates a
//! policy's success; training on perturbed and failed episodes is its
//! suggested remedy.
//!
//! A perturbed episode is the expert episode with one offset added to every
//! action's position after the first frame (drawn per episode, per axis,
//! normal with `offset_mm`), the same error model as the scripted policies
//! of `bridgev2w eval-policy-rollout` (their constant offset); the world
//! then executes it with its contact rules. Whether it still accomplishes
//! the task is judged as the planners judge success: the TCP (reach) or the
//! task object (push, pick_place: horizontally, and released) within
//! [`SUCCESS_TOLERANCE_M`] of where the expert's ended.

use super::world::{MAX_IK_RESIDUAL_M, MAX_IK_RESIDUAL_RAD};
use super::{Contact, Episode, Split, SynthError, Task, World};
use rand::Rng;
use serde::{Deserialize, Serialize};

/// Success tolerance: TCP (reach) or object (push, pick-and-place) within
/// this distance of the expert's final one (metres, horizontal for objects).
pub const SUCCESS_TOLERANCE_M: f64 = 0.03;

/// The object push and pick_place move: the scene's first (the scripted
/// expert's choice).
pub const TASK_OBJECT: usize = 0;

/// Offsets drawn for an episode before it is left unperturbed (an offset
/// whose targets the arm cannot reach is drawn again).
const ATTEMPTS: usize = 4;

/// Which training episodes are perturbed, and how much.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Perturbation {
    /// Fraction of the `train` split's goal-task episodes (reach, push,
    /// pick_place; not play) whose actions are perturbed: 0 none, 1 all.
    pub fraction: f64,
    /// Standard deviation of the per-episode position offset (millimetres,
    /// per axis).
    pub offset_mm: f64,
}

impl Default for Perturbation {
    /// None (fraction 0); 30 mm when a fraction is given.
    fn default() -> Self {
        Self {
            fraction: 0.0,
            offset_mm: 30.0,
        }
    }
}

impl Perturbation {
    /// Checks the settings: fraction in [0, 1], offset in (0, 500] mm.
    pub fn validate(&self) -> Result<(), SynthError> {
        if !(self.fraction.is_finite() && (0.0..=1.0).contains(&self.fraction)) {
            return Err(SynthError::Config(format!(
                "--perturbed-fraction {}: expected a fraction of the training episodes in [0, 1]",
                self.fraction
            )));
        }
        if !(self.offset_mm.is_finite() && self.offset_mm > 0.0 && self.offset_mm <= 500.0) {
            return Err(SynthError::Config(format!(
                "--perturb-mm {}: expected a standard deviation in (0, 500] millimetres",
                self.offset_mm
            )));
        }
        Ok(())
    }

    /// Whether the episode `(split, task)` drawing `u` (uniform in [0, 1))
    /// is perturbed.
    fn applies(&self, split: Split, task: Task, u: f64) -> bool {
        split == Split::Train && task != Task::Play && u < self.fraction
    }
}

/// What became of a perturbed episode (in `meta/synth.json`'s episodes).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PerturbedOutcome {
    /// The offset added to every action's position after the first frame
    /// (metres, world frame).
    pub offset_m: [f64; 3],
    /// The task error against the expert's outcome (metres; see the module).
    pub error_m: f64,
    /// Whether the perturbed episode still accomplishes the task.
    pub success: bool,
}

impl World {
    /// The task error of `episode` against the `expert`'s outcome (metres):
    /// final TCP distance (reach, play), the task object's final horizontal
    /// distance (push, pick_place); infinite when the object is still held
    /// at the end of a pick_place.
    pub fn task_error_m(&self, expert: &Episode, episode: &Episode) -> f64 {
        let last = |e: &Episode| e.joints.len().checked_sub(1);
        match expert.meta.task {
            Task::Reach | Task::Play => match (last(expert), last(episode)) {
                (Some(a), Some(b)) => {
                    let want = self.world_from_tcp(&expert.meta, &expert.joints[a]);
                    let got = self.world_from_tcp(&episode.meta, &episode.joints[b]);
                    (want.translation.vector - got.translation.vector).norm()
                }
                _ => f64::INFINITY,
            },
            Task::Push | Task::PickPlace => {
                let object = |e: &Episode| {
                    e.object_poses
                        .last()
                        .and_then(|p| p.get(TASK_OBJECT))
                        .map(|p| p.position_m)
                };
                let held = episode
                    .contacts
                    .last()
                    .and_then(|c| c.get(TASK_OBJECT))
                    .is_some_and(|c| matches!(c, Contact::Grasped | Contact::Carried));
                match (object(expert), object(episode)) {
                    (Some(_), Some(_)) if held && expert.meta.task == Task::PickPlace => {
                        f64::INFINITY
                    }
                    (Some(w), Some(g)) => (w[0] - g[0]).hypot(w[1] - g[1]),
                    _ => f64::INFINITY,
                }
            }
        }
    }

    /// The expert episode perturbed as `p` says, when it applies to the
    /// episode (else `expert` unchanged). Draws from `rng`; an offset whose
    /// targets the arm cannot reach (IK residual over 1 cm or 5 degrees) is
    /// drawn again,
    /// [`ATTEMPTS`] times, then the expert episode is kept.
    pub(super) fn perturbed(
        &self,
        expert: Episode,
        p: &Perturbation,
        rng: &mut impl Rng,
    ) -> Result<Episode, SynthError> {
        if !p.applies(expert.meta.split, expert.meta.task, rng.gen::<f64>()) {
            return Ok(expert);
        }
        let arm = expert.meta.arm;
        for attempt in 0..ATTEMPTS {
            let offset_m: [f64; 3] = std::array::from_fn(|_| {
                bridgev2w_io::seed::standard_normal(rng) * p.offset_mm * 1e-3
            });
            let mut actions = expert.actions.clone();
            for row in actions.iter_mut().skip(1) {
                for (k, o) in offset_m.iter().enumerate() {
                    row[7 * arm + k] += o;
                }
            }
            let seed = expert.meta.seed.wrapping_add(attempt as u64);
            let (joints, worst, worst_rot) =
                self.episode_joints("perturbed demonstration", &actions, seed)?;
            if worst > MAX_IK_RESIDUAL_M || worst_rot > MAX_IK_RESIDUAL_RAD {
                continue;
            }
            let mut meta = expert.meta.clone();
            meta.max_ik_residual_m = worst;
            let mut episode = self.finish(meta, expert.camera.clone(), actions, joints);
            let error_m = self.task_error_m(&expert, &episode);
            episode.meta.perturbation = Some(PerturbedOutcome {
                offset_m,
                error_m,
                success: error_m < SUCCESS_TOLERANCE_M,
            });
            return Ok(episode);
        }
        Ok(expert)
    }
}
