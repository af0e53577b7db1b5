//! The gripper heuristic of the MPC loop: the grasp in place after the key
//! goal, and the release (at the end, or before the final goal).
#![allow(clippy::unwrap_used)]

use crate::common;

use bridgev2w_io::frame::RgbFrame;
use bridgev2w_plan::cem::CemConfig;
use bridgev2w_plan::mpc::{run_mpc, GripperPolicy, MpcConfig};
use common::*;
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

#[test]
fn waypoint_goals_and_the_gripper_switch_after_the_key_goal() {
    let model = position_model();
    let at = |x: f64, g: f64| position_image(&[x, 0.0, 0.0, 0.0, 0.0, 0.0, g]);
    // A waypoint, the key (grasp) goal, the final goal.
    let goals = [at(0.1, 0.0), at(0.2, 0.0), at(0.3, 1.0)];
    // The pick_place search (below) without a release.
    let cfg = MpcConfig {
        gripper: GripperPolicy::Heuristic {
            approach: 0.0,
            after_switch: 1.0,
            release_at_end: false,
        },
        max_steps: 30,
        ..pick_place_config(false)
    };
    let mut env = RecordingEnv {
        inner: PositionEnv {
            ee: [0.0; 7],
            target: [0.3, 0.0, 0.0],
        },
        executed: vec![],
    };
    let out = run_mpc(
        &model,
        &mut env,
        &goals,
        &cfg,
        &mut ChaCha8Rng::seed_from_u64(3),
    )
    .unwrap();
    assert!(out.reached, "{:?}", env.executed);
    // The gripper closes once, in place, after the key goal (not after the
    // waypoint), and stays closed.
    let first_closed = env.executed.iter().position(|e| e.1 == 1.0).unwrap();
    assert!(env.executed[first_closed..].iter().all(|e| e.1 == 1.0));
    let x = env.executed[first_closed].0;
    assert!((x - 0.2).abs() < 0.03, "grasped at x = {x}");
    // Too few goals for the switch: a clear error.
    let e = run_mpc(
        &model,
        &mut env,
        &goals[..1],
        &cfg,
        &mut ChaCha8Rng::seed_from_u64(3),
    )
    .unwrap_err()
    .to_string();
    assert!(
        e.contains("switch after goal 1") && e.contains("1 goal"),
        "{e}"
    );
}

/// pick_place's goals: a waypoint, the grasp (key) goal, the place
/// waypoint, the final goal lifted from the place (gripper open).
fn pick_place_goals() -> Vec<RgbFrame> {
    let at = |x: f64, z: f64, g: f64| position_image(&[x, 0.0, z, 0.0, 0.0, 0.0, g]);
    vec![
        at(0.1, 0.0, 0.0),
        at(0.2, 0.0, 1.0),
        at(0.3, 0.0, 1.0),
        at(0.3, 0.1, 0.0),
    ]
}

fn pick_place_config(release_before_final: bool) -> MpcConfig {
    MpcConfig {
        cem: CemConfig {
            samples: 32,
            elites: 4,
            iterations: 3,
            horizon: 1,
            init_translation_std_m: 0.05,
            translation_only: true,
            keep_elites: true,
            ..CemConfig::default()
        },
        gripper: GripperPolicy::Heuristic {
            approach: 0.0,
            after_switch: 1.0,
            release_at_end: true,
        },
        max_steps: 40,
        patience: 2,
        subgoal_patience: 1,
        execute_best: true,
        switch_after_goal: 1,
        release_before_final,
        ..MpcConfig::default()
    }
}

fn run_recorded(goals: &[RgbFrame], cfg: &MpcConfig, target: [f64; 3]) -> Vec<(f64, f64)> {
    let model = position_model();
    let mut env = RecordingEnv {
        inner: PositionEnv {
            ee: [0.0; 7],
            target,
        },
        executed: vec![],
    };
    run_mpc(
        &model,
        &mut env,
        goals,
        cfg,
        &mut ChaCha8Rng::seed_from_u64(5),
    )
    .unwrap();
    env.executed
}

#[test]
fn releasing_before_the_final_goal_opens_at_the_place_and_lifts_open() {
    let goals = pick_place_goals();
    // The target is out of reach of the goal check, so every goal is
    // pursued to its patience.
    let never = [9.0, 9.0, 9.0];
    // (x, gripper) of each executed frame; the z of the frames is not
    // recorded, so the release's place is told by x and by order.
    let released = run_recorded(&goals, &pick_place_config(true), never);
    let closed = released.iter().position(|e| e.1 == 1.0).unwrap();
    let reopened = closed + released[closed..].iter().position(|e| e.1 == 0.0).unwrap();
    let x_grasp = released[closed].0;
    let x_release = released[reopened].0;
    assert!((x_grasp - 0.2).abs() < 0.03, "grasped at x = {x_grasp}");
    assert!(
        (x_release - 0.3).abs() < 0.03,
        "released at x = {x_release}"
    );
    // Released in place (the frame before it is at the same x), and open
    // from there on: the final goal is pursued with the gripper open, so
    // more than the release frames follow it.
    assert_eq!(released[reopened - 1].0, x_release);
    assert!(released[reopened..].iter().all(|e| e.1 == 0.0));
    let n_open = released.len() - reopened;
    assert!(
        n_open > 2 * MpcConfig::default().frames_per_action,
        "{released:?}"
    );

    // Without the option the gripper stays closed until the release after
    // the final goal: only the last frames are open again.
    let at_end = run_recorded(&goals, &pick_place_config(false), never);
    let closed = at_end.iter().position(|e| e.1 == 1.0).unwrap();
    let reopened = closed + at_end[closed..].iter().position(|e| e.1 == 0.0).unwrap();
    assert_eq!(
        at_end.len() - reopened,
        MpcConfig::default().frames_per_action
    );

    // With no goal between the grasp and the final one there is no place to
    // release at: the option changes nothing.
    let no_place = [goals[0].clone(), goals[1].clone(), goals[3].clone()];
    assert_eq!(
        run_recorded(&no_place, &pick_place_config(true), never),
        run_recorded(&no_place, &pick_place_config(false), never)
    );
}

#[test]
fn releasing_before_the_final_goal_is_refused_where_nothing_is_released() {
    use bridgev2w_data::synth::Task;
    use bridgev2w_plan::experiment::{plan_summary, PlanOptions};
    use bridgev2w_plan::mpc::GripperChoice;
    for (task, gripper) in [
        (Task::Push, GripperChoice::Auto),
        (Task::Reach, GripperChoice::Auto),
        (Task::PickPlace, GripperChoice::Search),
    ] {
        let mut o = PlanOptions::new(task);
        o.gripper = gripper;
        o.goals.release_before_final = true;
        let e = plan_summary(&o, &mut |_| {}).unwrap_err().to_string();
        assert!(
            e.contains("--release-before-final") && e.contains(task.name()),
            "{e}"
        );
    }
}
