//! The planning commands (`plan`, `plan-fidelity`, `eval-policy-rollout`,
//! `plan-report`): their arguments, turned into `bridgev2w_plan::experiment`
//! options, one library call each.

pub mod drift;
pub mod fidelity;
pub mod plan;
pub mod report;
pub mod rollout;

use bridgev2w_plan::experiment::planning::GoalOptions;
use bridgev2w_plan::synthetic::WaypointSpacing;

/// Prints a progress line to stderr.
pub(crate) fn progress(line: &str) {
    eprintln!("{line}");
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
