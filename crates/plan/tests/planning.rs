//! Planning and policy evaluation against cheap models with known optima
//! and a counting world model (the synthetic world: `synthetic_world.rs`).
#![allow(clippy::unwrap_used)]

use bridgev2w_embodiment::camera::{Camera, Intrinsics};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::xyz_rpy_from_pose;
use bridgev2w_io::frame::RgbFrame;
use bridgev2w_plan::cem::{CemConfig, GripperMode};
use bridgev2w_plan::goal_latent::{pyramid_latent, GoalLatent};
use bridgev2w_plan::model::{expand_waypoints, ActionWorldModel, MaskConditioned, Workspace};
use bridgev2w_plan::mpc::{
    plan_once, run_mpc, run_random, score_sequences, select_proposal, Environment, MpcConfig,
};
use bridgev2w_plan::policy::{rollout_in_model, Policy};
use bridgev2w_plan::{EeAction, Observation, PlanError, Result};
use bridgev2w_world_model::pipeline::{PredictOptions, SampleOptions, WorldModel};
use bridgev2w_world_model::video::{MaskVideo, Video};
use nalgebra::{Point3, Vector3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;
use std::sync::Mutex;

use crate::common;
use common::*;

#[test]
fn executing_the_best_candidate_and_the_workspace_box() {
    let model = position_model();
    let start = [0.0, 0.0, 0.0, std::f64::consts::PI, 0.0, 0.0, 0.0];
    let obs = position_obs(start);
    let goal = model
        .encode(&position_image(&[0.3, -0.1, 0.05, 0.0, 0.0, 0.0, 0.0]))
        .unwrap();
    let base = MpcConfig {
        cem: CemConfig {
            samples: 24,
            elites: 4,
            iterations: 3,
            horizon: 2,
            init_translation_std_m: 0.1,
            ..CemConfig::default()
        },
        ..MpcConfig::default()
    };
    // The executed plan is the best candidate: its predicted cost is the
    // lowest of the trace (the model is deterministic).
    let best = MpcConfig {
        execute_best: true,
        ..base.clone()
    };
    let step = plan_once(
        &model,
        &obs,
        &goal,
        &best,
        GripperMode::Fixed(0.0),
        &mut ChaCha8Rng::seed_from_u64(5),
    )
    .unwrap();
    let seq = expand_waypoints(&start, &step.waypoints, best.frames_per_action);
    let cost = score_sequences(&model, &obs, &[seq], &goal).unwrap()[0];
    let lowest = step
        .best_cost_per_iteration
        .iter()
        .copied()
        .fold(f64::INFINITY, f64::min);
    assert!((cost - lowest).abs() < 1e-12, "{cost} vs {lowest}");
    // Every planned waypoint stays inside the workspace box, even though the
    // goal lies outside it.
    let boxed = MpcConfig {
        workspace: Some(Workspace {
            min_m: [-0.05, -0.05, -0.05],
            max_m: [0.1, 0.05, 0.02],
        }),
        ..base
    };
    let step = plan_once(
        &model,
        &obs,
        &goal,
        &boxed,
        GripperMode::Fixed(0.0),
        &mut ChaCha8Rng::seed_from_u64(6),
    )
    .unwrap();
    for w in &step.waypoints {
        assert!((-0.05..=0.1).contains(&w[0]) && (-0.05..=0.05).contains(&w[1]));
        assert!((-0.05..=0.02).contains(&w[2]), "{w:?}");
    }
    // The box's far corner toward the goal is where the plan ends.
    let last = step.waypoints.last().unwrap();
    assert!((last[0] - 0.1).abs() < 0.02, "{last:?}");
    let bad = MpcConfig {
        workspace: Some(Workspace {
            min_m: [0.0; 3],
            max_m: [-1.0, 0.0, 0.0],
        }),
        ..MpcConfig::default()
    };
    assert!(bad.validate(9).is_err());
}

#[test]
fn cem_mpc_on_an_analytic_model_converges_to_the_goal() {
    let target = [0.15, -0.1, 0.08];
    let model = position_model();
    let start = [0.0, 0.0, 0.0, std::f64::consts::PI, 0.0, 0.0, 0.0];
    let mut env = PositionEnv { ee: start, target };
    let goal = position_image(&[target[0], target[1], target[2], 0.0, 0.0, 0.0, 1.0]);
    let cfg = MpcConfig {
        cem: CemConfig {
            samples: 48,
            elites: 6,
            iterations: 4,
            horizon: 1,
            ..CemConfig::default()
        },
        max_steps: 30,
        patience: 100,
        ..MpcConfig::default()
    };
    let out = run_mpc(
        &model,
        &mut env,
        &[goal],
        &cfg,
        &mut ChaCha8Rng::seed_from_u64(0),
    )
    .unwrap();
    assert!(
        out.reached,
        "ended at {:?} after {} steps",
        env.ee, out.steps
    );
    assert!(out.steps < 30);
    // A random walk with the same budget does not get there.
    let mut env = PositionEnv { ee: start, target };
    let r = run_random(&mut env, &cfg, &mut ChaCha8Rng::seed_from_u64(0)).unwrap();
    assert!(!r.reached);
}

/// An environment that records every executed chunk of frames.
struct ChunkEnv {
    inner: PositionEnv,
    chunks: Vec<Vec<EeAction>>,
}

impl Environment for ChunkEnv {
    fn observe(&self) -> Result<Observation> {
        self.inner.observe()
    }
    fn execute(&mut self, a: &[EeAction]) -> Result<Observation> {
        self.chunks.push(a.to_vec());
        self.inner.execute(a)
    }
    fn goal_reached(&self) -> bool {
        self.inner.goal_reached()
    }
}

#[test]
fn executing_several_planned_actions_per_search() {
    let target = [0.3, -0.2, 0.1];
    let model = position_model();
    let start = [0.0, 0.0, 0.0, std::f64::consts::PI, 0.0, 0.0, 0.0];
    let goal = position_image(&[target[0], target[1], target[2], 0.0, 0.0, 0.0, 0.0]);
    let cfg = MpcConfig {
        cem: CemConfig {
            samples: 32,
            elites: 4,
            iterations: 3,
            horizon: 3,
            init_translation_std_m: 0.05,
            ..CemConfig::default()
        },
        execute_best: true,
        execute_actions: 3,
        max_steps: 7,
        patience: 100,
        ..MpcConfig::default()
    };
    let mut env = ChunkEnv {
        inner: PositionEnv { ee: start, target },
        chunks: vec![],
    };
    let out = run_mpc(
        &model,
        &mut env,
        &[goal],
        &cfg,
        &mut ChaCha8Rng::seed_from_u64(1),
    )
    .unwrap();
    // 3 + 3 + 1 actions (the last search executes the one step left), each
    // of `frames_per_action` frames; one trace step per search.
    let lens: Vec<usize> = env.chunks.iter().map(Vec::len).collect();
    let fpa = cfg.frames_per_action;
    assert_eq!(lens, vec![3 * fpa, 3 * fpa, fpa], "{lens:?}");
    assert_eq!(out.steps, 7);
    assert_eq!(out.trace.len(), 3);
    // A chunk ends at the last action it executed, and the next search
    // starts there.
    for (step, chunk) in out.trace.iter().zip(&env.chunks) {
        assert_eq!(step.action, *chunk.last().unwrap());
        assert_eq!(step.ee, *chunk.last().unwrap());
    }
    // Chunks of the plan make progress toward the goal like single steps.
    let dist = |a: &EeAction| {
        (0..3)
            .map(|i| (a[i] - target[i]).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    assert!(
        dist(&env.inner.ee) < 0.5 * dist(&start),
        "{:?}",
        env.inner.ee
    );
    // 0 or more than the horizon: a clear error naming the setting.
    for bad in [0, 4] {
        let e = run_mpc(
            &model,
            &mut PositionEnv { ee: start, target },
            &[position_image(&start)],
            &MpcConfig {
                execute_actions: bad,
                ..cfg.clone()
            },
            &mut ChaCha8Rng::seed_from_u64(1),
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("--execute-actions") && e.contains("(--horizon 3)"),
            "{e}"
        );
    }
}

#[test]
fn a_stalled_step_holds_the_pose_and_the_next_search_is_finer() {
    // The goal's gripper pixel differs from the fixed gripper: no move can
    // lower the cost below staying put, so every step stalls.
    let start = [0.0, 0.0, 0.0, std::f64::consts::PI, 0.0, 0.0, 0.0];
    let goal = position_image(&[0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]);
    let (samples, steps) = (64, 4);
    let run = |factor: f64, include_mean: bool| {
        let model = position_model();
        let mut env = PositionEnv {
            ee: start,
            target: [1.0; 3],
        };
        let cfg = MpcConfig {
            cem: CemConfig {
                samples,
                elites: 4,
                iterations: 1,
                horizon: 1,
                init_translation_std_m: 0.04,
                include_mean,
                ..CemConfig::default()
            },
            execute_best: true,
            max_steps: steps,
            patience: 100,
            stall_std_factor: factor,
            gripper: bridgev2w_plan::mpc::GripperPolicy::Heuristic {
                approach: 0.0,
                after_switch: 0.0,
                release_at_end: false,
            },
            ..MpcConfig::default()
        };
        let out = run_mpc(
            &model,
            &mut env,
            std::slice::from_ref(&goal),
            &cfg,
            &mut ChaCha8Rng::seed_from_u64(2),
        )
        .unwrap();
        // The RMS of each step's sampled translation (the zero move left
        // out), from where that step started.
        let padded = model.padded.into_inner().unwrap();
        assert_eq!(padded.len(), samples * steps);
        let mut from = start;
        let rms: Vec<f64> = padded
            .chunks(samples)
            .zip(&out.trace)
            .map(|(cands, step)| {
                let sq: Vec<f64> = cands
                    .iter()
                    .map(|p| *p.last().unwrap())
                    .filter(|a| a[..3] != from[..3])
                    .flat_map(|a| (0..3).map(move |i| a[i] - from[i]))
                    .map(|d| d * d)
                    .collect();
                from = step.ee;
                (sq.iter().sum::<f64>() / sq.len() as f64).sqrt()
            })
            .collect();
        (out, env.ee, rms)
    };
    let (out, ee, rms) = run(0.5, true);
    // Staying put is a candidate and the best one: the pose is held.
    assert_eq!(ee, start);
    assert_eq!(
        out.trace.iter().map(|s| s.stalls).collect::<Vec<_>>(),
        vec![1, 2, 3, 4]
    );
    // Each stall halves the spread (64 samples x 3 axes: about 5% noise).
    assert!((rms[0] / 0.04 - 1.0).abs() < 0.2, "{rms:?}");
    for w in rms.windows(2) {
        assert!((w[1] / w[0] - 0.5).abs() < 0.12, "{rms:?}");
    }
    // Off (factor 1) the spread stays; without the mean the arm moves.
    let (_, ee, rms) = run(1.0, false);
    assert_ne!(ee, start);
    for w in rms.windows(2) {
        assert!((w[1] / w[0] - 1.0).abs() < 0.25, "{rms:?}");
    }
    // A factor outside (0, 1] is a clear error naming the option.
    for bad in [0.0, 1.5, f64::NAN] {
        let cfg = MpcConfig {
            stall_std_factor: bad,
            ..MpcConfig::default()
        };
        let e = cfg.validate(9).unwrap_err().to_string();
        assert!(
            e.contains("--shrink-on-stall") && e.contains("(0, 1]"),
            "{e}"
        );
    }
}

/// A world model that records the batch size of every call.
struct CountingModel {
    calls: Mutex<Vec<usize>>,
}

impl WorldModel for CountingModel {
    fn clip_frames(&self) -> usize {
        9
    }
    fn resolution(&self) -> (usize, usize) {
        (24, 32)
    }
    fn predict(
        &self,
        f: &RgbFrame,
        m: &MaskVideo,
        _: &PredictOptions,
    ) -> bridgev2w_world_model::Result<Video> {
        // The frame's brightness is the mask coverage of the last frame.
        let n = m.height * m.width;
        let cover = m.data[(m.frames - 1) * n..]
            .iter()
            .filter(|&&v| v != 0)
            .count() as f32
            / n as f32;
        Ok(Video {
            frames: m.frames,
            height: f.height,
            width: f.width,
            data: vec![cover; m.frames * f.height * f.width * 3],
        })
    }
    fn predict_batch(
        &self,
        f: &[RgbFrame],
        m: &[MaskVideo],
        o: &PredictOptions,
    ) -> bridgev2w_world_model::Result<Vec<Video>> {
        self.calls.lock().unwrap().push(f.len());
        f.iter()
            .zip(m)
            .map(|(f, m)| self.predict(f, m, o))
            .collect()
    }
    fn encode_image(&self, image: &RgbFrame) -> bridgev2w_world_model::Result<Vec<f32>> {
        Ok(image.rgb.clone())
    }
}

fn franka_model(counting: &CountingModel) -> (MaskConditioned<'_, CountingModel>, Observation) {
    let e = Embodiment::builtin("franka").unwrap();
    let cam = Camera::look_at(
        Intrinsics::centered(30.0, 32, 24),
        Point3::new(1.6, 0.0, 0.8),
        Point3::new(0.4, 0.0, 0.2),
        Vector3::z(),
    )
    .unwrap();
    let tcp = e.robot.link_pose(e.end_effectors[0].link, &e.home);
    let v = xyz_rpy_from_pose(&tcp);
    let obs = Observation {
        image: RgbFrame {
            height: 24,
            width: 32,
            rgb: vec![0.5; 24 * 32 * 3],
        },
        joints: e.home.clone(),
        ee: [v[0], v[1], v[2], v[3], v[4], v[5], 0.0],
        scene: None,
    };
    let hold = obs.ee.to_vec();
    let predict = PredictOptions {
        sample: SampleOptions::default(),
        max_batch: None,
        ..PredictOptions::default()
    };
    let m = MaskConditioned::new(counting, e, 0, cam, hold, predict).unwrap();
    (m, obs)
}

#[test]
fn each_cem_iteration_is_one_predict_batch_of_s_candidates() {
    let counting = CountingModel {
        calls: Mutex::new(vec![]),
    };
    let (m, obs) = franka_model(&counting);
    let cfg = MpcConfig {
        cem: CemConfig {
            samples: 5,
            elites: 2,
            iterations: 3,
            horizon: 2,
            ..CemConfig::default()
        },
        frames_per_action: 2,
        ..MpcConfig::default()
    };
    let goal = m.encode(&obs.image).unwrap();
    let r = plan_once(
        &m,
        &obs,
        &goal,
        &cfg,
        GripperMode::Fixed(0.0),
        &mut ChaCha8Rng::seed_from_u64(1),
    )
    .unwrap();
    assert_eq!(*counting.calls.lock().unwrap(), vec![5, 5, 5]);
    assert_eq!(r.waypoints.len(), 2);
    assert_eq!(r.best_cost_per_iteration.len(), 3);
    // The masks cover the robot: a rendered arm is visible from this camera.
    let (masks, _) = m.masks(&obs.joints, &[obs.ee; 8]).unwrap();
    assert_eq!(masks.frames, 9);
    assert!(masks.data.iter().any(|&v| v != 0));
}

#[test]
fn bad_inputs_are_clear_errors() {
    let model = position_model();
    let start = [0.0; 7];
    let good_goal = position_image(&start);
    let run = |goal: &RgbFrame, cem: CemConfig| {
        let mut env = PositionEnv {
            ee: start,
            target: [1.0; 3],
        };
        let cfg = MpcConfig {
            cem,
            max_steps: 1,
            ..MpcConfig::default()
        };
        run_mpc(
            &model,
            &mut env,
            std::slice::from_ref(goal),
            &cfg,
            &mut ChaCha8Rng::seed_from_u64(0),
        )
    };
    let wrong = RgbFrame {
        height: 2,
        width: 2,
        rgb: vec![0.0; 12],
    };
    let e = run(&wrong, CemConfig::default()).unwrap_err();
    assert!(
        matches!(
            e,
            PlanError::GoalImageSize {
                got_h: 2,
                got_w: 2,
                want_h: 1,
                want_w: 2
            }
        ),
        "{e}"
    );
    let e = run(
        &good_goal,
        CemConfig {
            horizon: 0,
            ..CemConfig::default()
        },
    )
    .unwrap_err();
    assert!(matches!(e, PlanError::ZeroHorizon), "{e}");
    let e = run(
        &good_goal,
        CemConfig {
            samples: 3,
            elites: 4,
            ..CemConfig::default()
        },
    )
    .unwrap_err();
    assert!(
        e.to_string().contains("k = 4") && e.to_string().contains("S = 3"),
        "{e}"
    );
    // Horizon x frames per action beyond the clip.
    let e = run(
        &good_goal,
        CemConfig {
            horizon: 5,
            ..CemConfig::default()
        },
    )
    .unwrap_err();
    assert!(matches!(e, PlanError::ClipTooShort { .. }), "{e}");
    // NaN in a proposed chunk.
    let mut bad = [0.1; 7];
    bad[2] = f64::NAN;
    let e = select_proposal(
        &model,
        &position_obs(start),
        &good_goal,
        &[vec![[0.1; 7]], vec![[0.1; 7], bad]],
    )
    .unwrap_err();
    assert!(
        matches!(
            e,
            PlanError::NonFinite {
                index: 1,
                column: 2,
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("proposal 1"));
}

#[test]
fn vla_proposal_mode_picks_the_chunk_nearest_the_goal() {
    let model = position_model();
    let start = [0.0; 7];
    let goal = position_image(&[0.1, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]);
    let props: Vec<Vec<EeAction>> = [-0.1, 0.3, 0.09, 0.0]
        .iter()
        .map(|&x| {
            vec![
                [x / 2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
                [x, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
            ]
        })
        .collect();
    let (best, costs) = select_proposal(&model, &position_obs(start), &goal, &props).unwrap();
    assert_eq!(best, 2);
    assert_eq!(costs.len(), 4);
}

/// Returns chunks of 3 actions stepping x by 0.01 and records its inputs.
struct StepPolicy {
    next_x: f64,
    seen_x: Vec<f64>,
}

impl Policy for StepPolicy {
    fn name(&self) -> String {
        "step".into()
    }
    fn reset(&mut self, _: usize) {}
    fn act(&mut self, obs: &Observation) -> Result<Vec<EeAction>> {
        self.seen_x.push(f64::from(obs.image.rgb[0]) - 0.5);
        Ok((0..3)
            .map(|_| {
                self.next_x += 0.01;
                [self.next_x, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]
            })
            .collect())
    }
}

#[test]
fn policy_rollout_pads_chunks_and_feeds_the_last_frame_back() {
    let model = PositionModel {
        clip: 5,
        padded: Mutex::new(vec![]),
    };
    let mut p = StepPolicy {
        next_x: 0.0,
        seen_x: vec![],
    };
    let r = rollout_in_model(&model, &mut p, position_obs([0.0; 7]), 7).unwrap();
    assert_eq!(r.actions, 7);
    assert_eq!(r.chunk_last_frames.len(), 3);
    let padded = model.padded.lock().unwrap();
    assert_eq!(padded.len(), 3);
    // Chunks of 3 (then the 1 left of the horizon) padded to 4 by repeating the last.
    let xs: Vec<Vec<f64>> = padded
        .iter()
        .map(|s| s.iter().map(|a| (a[0] * 100.0).round()).collect())
        .collect();
    assert_eq!(
        xs,
        vec![
            vec![1.0, 2.0, 3.0, 3.0],
            vec![4.0, 5.0, 6.0, 6.0],
            vec![7.0, 7.0, 7.0, 7.0]
        ]
    );
    // The policy saw the start, then each chunk's last predicted frame.
    let seen: Vec<f64> = p.seen_x.iter().map(|x| (x * 100.0).round()).collect();
    assert_eq!(seen, vec![0.0, 3.0, 6.0]);
    assert!(rollout_in_model(&model, &mut p, position_obs([0.0; 7]), 0).is_err());
}

/// A 48x32 synthetic world (seed 1) with episodes of `frames` frames.
#[test]
fn the_goal_latent_is_the_models_encoder_or_the_image_pyramid() {
    let counting = CountingModel {
        calls: Mutex::new(vec![]),
    };
    let (mut m, obs) = franka_model(&counting);
    // The default is the model's own encoder (the paper's VAE latent).
    assert_eq!(m.goal_latent, GoalLatent::Model);
    assert_eq!(m.encode(&obs.image).unwrap(), obs.image.rgb);
    m.goal_latent = GoalLatent::Pyramid;
    let pyramid = m.encode(&obs.image).unwrap();
    assert_eq!(pyramid, pyramid_latent(&obs.image));
    assert_ne!(pyramid.len(), obs.image.rgb.len());
    // An image of another size is refused, not measured.
    let small = RgbFrame {
        height: 12,
        width: 16,
        rgb: vec![0.5; 12 * 16 * 3],
    };
    assert!(m.encode(&small).is_err());
}
