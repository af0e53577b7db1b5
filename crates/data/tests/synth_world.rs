//! The synthetic world: determinism, split separation, GT masks, contacts.
#![allow(clippy::unwrap_used)]

use bridgev2w_data::synth::{Contact, Split, SynthConfig, Task, World};
use bridgev2w_embodiment::masks::render_trajectory;

fn config(robot: &str) -> SynthConfig {
    SynthConfig {
        robot: robot.into(),
        frames: 12,
        width: 48,
        height: 32,
        seed: 7,
        episodes_per_split: [3, 1, 1, 1],
        ..SynthConfig::default()
    }
}

#[test]
fn same_seed_same_episode_other_seed_differs() {
    let w = World::new(&config("franka")).unwrap();
    let a = w.generate(Split::Train, 1, Task::Push).unwrap();
    let b = w.generate(Split::Train, 1, Task::Push).unwrap();
    assert_eq!(a.rgb, b.rgb);
    assert_eq!(a.masks, b.masks);
    assert_eq!(a.actions, b.actions);
    assert_eq!(a.joints, b.joints);
    let c = w.generate(Split::Train, 2, Task::Push).unwrap();
    assert_ne!(a.actions, c.actions);
    assert_ne!(a.rgb, c.rgb);
    let w2 = World::new(&SynthConfig {
        seed: 8,
        ..config("franka")
    })
    .unwrap();
    let d = w2.generate(Split::Train, 1, Task::Push).unwrap();
    assert_ne!(a.actions, d.actions);
}

#[test]
fn thread_count_does_not_change_output() {
    let w = World::new(&config("franka")).unwrap();
    let one = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| w.generate_all(&|| {}).unwrap());
    let many = rayon::ThreadPoolBuilder::new()
        .num_threads(4)
        .build()
        .unwrap()
        .install(|| w.generate_all(&|| {}).unwrap());
    assert_eq!(one.len(), 6);
    for (a, b) in one.iter().zip(&many) {
        assert_eq!(a.rgb, b.rgb);
        assert_eq!(a.masks, b.masks);
        assert_eq!(a.joints, b.joints);
    }
}

#[test]
fn splits_are_separated() {
    let w = World::new(&config("franka")).unwrap();
    let train = w.spec(Split::Train);
    let test = w.spec(Split::Test);
    let cam = w.spec(Split::UnseenCamera);
    let scene = w.spec(Split::UnseenScene);
    assert_eq!(
        train,
        &bridgev2w_data::synth::SplitSpec {
            split: Split::Train,
            ..test.clone()
        }
    );
    // Camera regions disjoint.
    for r in &cam.camera.azimuth_deg {
        for t in &train.camera.azimuth_deg {
            assert!(r[0] > t[1] || r[1] < t[0], "{r:?} overlaps {t:?}");
        }
    }
    // Palettes disjoint: colours, patterns, layout regions.
    let (a, b) = (&train.scene, &scene.scene);
    for c in &b.table_colors {
        assert!(!a.table_colors.contains(c));
    }
    for c in &b.background_colors {
        assert!(!a.background_colors.contains(c));
    }
    for c in &b.object_colors {
        assert!(!a.object_colors.contains(c));
    }
    for p in &b.table_patterns {
        assert!(!a.table_patterns.contains(p), "table pattern {p} shared");
    }
    for p in &b.background_patterns {
        assert!(
            !a.background_patterns.contains(p),
            "background pattern {p} shared"
        );
    }
    assert!(b.layout_dy_m[0] > a.layout_dy_m[1] || b.layout_dy_m[1] < a.layout_dy_m[0]);
    // Generated episodes respect them.
    let center = w.frame.workspace_center_m;
    for i in 0..4 {
        let e = w.generate(Split::UnseenCamera, i, Task::Reach).unwrap();
        assert!(!train.camera.contains_azimuth(e.meta.camera_azimuth_deg));
        assert!(cam.camera.contains_azimuth(e.meta.camera_azimuth_deg));
        let t = w.generate(Split::Train, i, Task::Reach).unwrap();
        assert!(train.camera.contains_azimuth(t.meta.camera_azimuth_deg));
        let s = w.generate(Split::UnseenScene, i, Task::Reach).unwrap();
        for o in &s.meta.objects {
            let dy = o.initial.position_m[1] - center[1];
            assert!(dy >= b.layout_dy_m[0] - 1e-9 && dy <= b.layout_dy_m[1] + 1e-9);
            assert!(!(a.layout_dy_m[0]..=a.layout_dy_m[1]).contains(&dy));
        }
        for o in &t.meta.objects {
            let dy = o.initial.position_m[1] - center[1];
            assert!((a.layout_dy_m[0]..=a.layout_dy_m[1]).contains(&dy));
        }
        assert!(!s.meta.look.table_pattern.family().is_empty());
        assert!(b
            .table_patterns
            .iter()
            .any(|p| p == s.meta.look.table_pattern.family()));
        assert!(a
            .table_patterns
            .iter()
            .any(|p| p == t.meta.look.table_pattern.family()));
    }
}

#[test]
fn gt_masks_equal_the_masks_renderer() {
    for robot in ["franka", "dual-arm"] {
        let w = World::new(&config(robot)).unwrap();
        let e = w.generate(Split::Test, 0, Task::PickPlace).unwrap();
        let frames = render_trajectory(&w.embodiment.robot, &e.camera, &e.joints, &|| {});
        assert_eq!(frames.len(), e.masks.len());
        let mut covered = 0;
        for ((f, m), l) in frames.iter().zip(&e.masks).zip(&e.labels) {
            assert_eq!(&f.mask(), m);
            let want: Vec<u8> = f.labels.iter().map(|&v| v as u8).collect();
            assert_eq!(&want, l, "{robot}: the link labels are the renderer's");
            covered += f.coverage();
        }
        let links: std::collections::BTreeSet<u8> = e.labels.iter().flatten().copied().collect();
        assert!(links.len() > 3, "{robot}: several links in view: {links:?}");
        assert!(covered > 0, "{robot}: the robot is never visible");
    }
}

fn moved(a: &bridgev2w_data::synth::ObjectPose, b: &bridgev2w_data::synth::ObjectPose) -> f64 {
    let d: f64 = (0..3)
        .map(|k| (a.position_m[k] - b.position_m[k]).powi(2))
        .sum();
    d.sqrt() + (a.yaw_rad - b.yaw_rad).abs()
}

#[test]
fn objects_move_only_when_contacted_and_tasks_move_them() {
    let w = World::new(&SynthConfig {
        frames: 25,
        ..config("franka")
    })
    .unwrap();
    for task in [Task::Push, Task::PickPlace, Task::Reach, Task::Play] {
        let mut displaced_episodes = 0;
        for i in 0..4 {
            let e = w.generate(Split::Train, i, task).unwrap();
            for f in 1..e.object_poses.len() {
                for (k, (a, b)) in e.object_poses[f - 1]
                    .iter()
                    .zip(&e.object_poses[f])
                    .enumerate()
                {
                    if moved(a, b) > 1e-12 {
                        assert_ne!(
                            e.contacts[f][k],
                            Contact::None,
                            "{task:?} ep {i}: object {k} moved at frame {f} without contact"
                        );
                    }
                }
            }
            let first = &e.object_poses[0][0];
            let last = e.object_poses.last().unwrap();
            let d = ((first.position_m[0] - last[0].position_m[0]).powi(2)
                + (first.position_m[1] - last[0].position_m[1]).powi(2))
            .sqrt();
            if d > 0.03 {
                displaced_episodes += 1;
            }
            if task == Task::PickPlace && d > 0.03 {
                assert!(e.contacts.iter().any(|c| c[0] == Contact::Grasped));
                assert!(e.contacts.iter().any(|c| c[0] == Contact::Released));
                // Released onto the table.
                assert!((last[0].position_m[2] - w.frame.table_z_m).abs() < 1e-9);
            }
            if task == Task::Push && d > 0.03 {
                assert!(e.contacts.iter().any(|c| c[0] == Contact::Pushed));
            }
        }
        match task {
            Task::Push | Task::PickPlace => {
                assert!(
                    displaced_episodes >= 3,
                    "{task:?}: only {displaced_episodes}/4 episodes moved the object"
                )
            }
            Task::Reach | Task::Play => {}
        }
    }
}

#[test]
fn play_episodes_roam_the_table_and_toggle_the_gripper() {
    let w = World::new(&SynthConfig {
        frames: 17,
        ..config("franka")
    })
    .unwrap();
    assert_eq!(Task::parse("play"), Some(Task::Play));
    assert!(!Task::ALL.contains(&Task::Play));
    let (mut toggled, mut touched) = (0, 0);
    for i in 0..8 {
        let e = w.generate(Split::Train, i, Task::Play).unwrap();
        // Deterministic, like every task.
        assert_eq!(
            e.actions,
            w.generate(Split::Train, i, Task::Play).unwrap().actions
        );
        let xyz = |r: &Vec<f64>| nalgebra::Vector3::new(r[0], r[1], r[2]);
        let path: f64 = e
            .actions
            .windows(2)
            .map(|p| (xyz(&p[1]) - xyz(&p[0])).norm())
            .sum();
        // Several waypoints: a longer path than the straight line home -> end.
        let line = (xyz(e.actions.last().unwrap()) - xyz(&e.actions[0])).norm();
        assert!(
            path > line + 0.05,
            "episode {i}: path {path:.3} m, line {line:.3} m"
        );
        let g: Vec<f64> = e.actions.iter().map(|r| r[6]).collect();
        if g.windows(2).any(|p| (p[1] - p[0]).abs() > 0.05) {
            toggled += 1;
        }
        if e.contacts.iter().flatten().any(|c| *c != Contact::None) {
            touched += 1;
        }
    }
    assert!(
        toggled >= 4,
        "the gripper moved in only {toggled}/8 play episodes"
    );
    assert!(touched >= 1, "no play episode touched an object");
}

#[test]
fn agibot_generates_all_tasks() {
    let w = World::new(&config("dual-arm")).unwrap();
    for task in Task::ALL {
        let e = w.generate(Split::Train, 0, task).unwrap();
        assert_eq!(e.actions[0].len(), 14);
        assert_eq!(e.rgb[0].len(), 48 * 32 * 3);
    }
}

#[test]
fn stepping_from_the_initial_state_replays_an_episode() {
    use bridgev2w_data::synth::RenderFrames;
    let w = World::new(&config("franka")).unwrap();
    for task in [Task::Push, Task::PickPlace] {
        let e = w.generate(Split::Train, 0, task).unwrap();
        let s0 = w.initial_state(&e);
        assert_eq!(w.render_state(&e.meta, &e.camera, &s0), e.rgb[0]);
        // In two halves, so the state carries over between steps.
        let mid = e.actions.len() / 2;
        let (a, s1) = w
            .step(
                &e.meta,
                &e.camera,
                &s0,
                &e.actions[1..mid],
                RenderFrames::None,
            )
            .unwrap();
        assert!(a.rgb.is_empty());
        let (b, s2) = w
            .step(
                &e.meta,
                &e.camera,
                &s1,
                &e.actions[mid..],
                RenderFrames::Last,
            )
            .unwrap();
        assert_eq!(b.rgb.len(), 1);
        assert_eq!(b.rgb[0].len(), 48 * 32 * 3);
        let last = e.object_poses.last().unwrap();
        for (p, q) in s2.object_poses.iter().zip(last) {
            assert!(
                moved(p, q) < 0.005,
                "{task:?}: replay drifted {} m",
                moved(p, q)
            );
        }
        // The task moved an object, so the replay is not trivially the start.
        let first = &e.object_poses[0];
        assert!(s2
            .object_poses
            .iter()
            .zip(first)
            .any(|(p, q)| moved(p, q) > 0.02));
    }
}

#[test]
fn sizes_beyond_the_limits_are_refused_before_anything_is_allocated() {
    let base = SynthConfig::default();
    for (cfg, needle) in [
        (
            SynthConfig {
                frames: 4_000_000_000,
                ..base.clone()
            },
            "at most 10000 frames",
        ),
        (
            SynthConfig {
                width: 100_000,
                ..base.clone()
            },
            "at most 4096 pixels",
        ),
        (
            SynthConfig {
                episodes_per_split: [4_000_000_000, 1, 1, 1],
                ..base.clone()
            },
            "at most 100000 episodes",
        ),
    ] {
        let e = cfg.validate().unwrap_err().to_string();
        assert!(e.contains(needle), "{e}");
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("ds");
        assert!(bridgev2w_data::synth::write_dataset(&cfg, &out, &|| {}).is_err());
        assert!(
            !out.exists()
                && std::fs::read_dir(dir.path()).expect("read_dir").all(|e| !e
                    .expect("entry")
                    .file_name()
                    .to_string_lossy()
                    .contains("bridgev2w-tmp"))
        );
    }
}

/// Perturbed demonstrations (issue 71, item 4): with fraction 1 every
/// goal-task training episode is the expert's with one offset on every
/// action's position after the first frame, its outcome judged against the
/// expert's; other splits, play episodes and fraction 0 are the expert's
/// own; large offsets make grasps fail; bad settings are refused.
#[test]
fn perturbed_demonstrations_shift_the_expert_and_record_their_outcome() {
    use bridgev2w_data::synth::{Perturbation, SUCCESS_TOLERANCE_M};
    let plain = World::new(&config("franka")).unwrap();
    let with = |fraction: f64, offset_mm: f64| {
        World::new(&SynthConfig {
            perturb: Perturbation {
                fraction,
                offset_mm,
            },
            ..config("franka")
        })
        .unwrap()
    };
    let perturbed = with(1.0, 30.0);
    let expert = plain.generate(Split::Train, 0, Task::PickPlace).unwrap();
    let e = perturbed
        .generate(Split::Train, 0, Task::PickPlace)
        .unwrap();
    let outcome = e.meta.perturbation.clone().expect("perturbed");
    assert!(expert.meta.perturbation.is_none());
    assert_eq!(e.actions[0], expert.actions[0]);
    for (a, b) in e.actions.iter().zip(&expert.actions).skip(1) {
        for k in 0..3 {
            assert!((a[k] - b[k] - outcome.offset_m[k]).abs() < 1e-12);
        }
        assert_eq!(a[3..], b[3..]);
    }
    let norm = outcome.offset_m.iter().map(|v| v * v).sum::<f64>().sqrt();
    assert!(norm > 1e-4 && norm < 0.2, "{outcome:?}");
    assert_eq!(outcome.error_m, perturbed.task_error_m(&expert, &e));
    assert_eq!(outcome.success, outcome.error_m < SUCCESS_TOLERANCE_M);
    assert_eq!(perturbed.task_error_m(&expert, &expert), 0.0);
    assert_ne!(e.rgb, expert.rgb);
    // The test split, play episodes and fraction 0: the expert's own.
    let t = perturbed.generate(Split::Test, 0, Task::PickPlace).unwrap();
    assert_eq!(
        t.actions,
        plain
            .generate(Split::Test, 0, Task::PickPlace)
            .unwrap()
            .actions
    );
    assert!(t.meta.perturbation.is_none());
    let p = perturbed.generate(Split::Train, 1, Task::Play).unwrap();
    assert!(p.meta.perturbation.is_none());
    let zero = with(0.0, 30.0)
        .generate(Split::Train, 0, Task::PickPlace)
        .unwrap();
    assert_eq!(zero.actions, expert.actions);
    // 15 cm offsets: most pick-and-places miss the object.
    let far = with(1.0, 150.0);
    let outcomes: Vec<bool> = (0..4)
        .filter_map(|i| {
            far.generate(Split::Train, i, Task::PickPlace)
                .unwrap()
                .meta
                .perturbation
        })
        .map(|o| o.success)
        .collect();
    assert!(
        outcomes.iter().filter(|s| !**s).count() >= 2,
        "{outcomes:?}"
    );
    for (fraction, offset_mm, flag) in [
        (1.5, 30.0, "--perturbed-fraction"),
        (f64::NAN, 30.0, "--perturbed-fraction"),
        (0.5, 0.0, "--perturb-mm"),
        (0.5, 600.0, "--perturb-mm"),
    ] {
        let e = World::new(&SynthConfig {
            perturb: Perturbation {
                fraction,
                offset_mm,
            },
            ..config("franka")
        })
        .unwrap_err()
        .to_string();
        assert!(e.contains(flag), "{e}");
    }
}

/// The MuJoCo venv's Python (`./run test` makes it).
fn mujoco_python() -> std::path::PathBuf {
    let repo = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let python = repo.join(".venv-mujoco/bin/python");
    assert!(
        python.is_file(),
        "{}: no MuJoCo venv (./run test makes it: scripts/setup-mujoco-venv.sh)",
        python.display()
    );
    python
}

/// The MuJoCo session a planner executes chunks in (issue 72): stepping a
/// plan in two chunks ends where stepping it at once does (the physics is
/// deterministic), only asked frames are rendered, and a worker that stops
/// is an error carrying what it said.
#[test]
fn a_mujoco_session_steps_in_chunks_as_at_once_and_names_a_worker_that_stops() {
    use bridgev2w_data::synth::mujoco::{MujocoEngine, Render};
    let python = mujoco_python();
    let world = World::new(&config("franka-robotiq")).unwrap();
    let e = world.generate(Split::Test, 0, Task::Push).unwrap();
    let engine = MujocoEngine::new("franka-robotiq", python).unwrap();
    let scene = engine.scene_json(&world, &e, "chunks").unwrap();
    let size = (32, 48);
    let run = |chunks: &[(usize, usize)]| {
        let mut s = engine.session("chunks").unwrap();
        let start = s.reset(&scene, size).unwrap();
        assert_eq!(start.frames.len(), 1);
        assert_eq!(
            start.frames[0].rgb.as_ref().map(Vec::len),
            Some(32 * 48 * 3)
        );
        let mut last = None;
        for &(from, to) in chunks {
            let c = from..to;
            let r = s.step(&e.joints[c.clone()], Render::Last).unwrap();
            assert!(r.unstable.is_none(), "{:?}", r.unstable);
            assert_eq!(r.frames.len(), c.len());
            let rendered: Vec<bool> = r.frames.iter().map(|f| f.rgb.is_some()).collect();
            assert_eq!(rendered.iter().filter(|&&x| x).count(), 1);
            assert!(rendered[c.len() - 1]);
            last = r.frames.last().cloned();
        }
        last.unwrap()
    };
    let n = e.joints.len();
    let (whole, halves) = (run(&[(1, n)]), run(&[(1, n / 2), (n / 2, n)]));
    assert_eq!(whole.joints, halves.joints);
    assert_eq!(whole.objects, halves.objects);
    assert_eq!(whole.rgb, halves.rgb);
    // The arm follows its plan (radians, the arm's seven joints).
    for (a, b) in whole.joints.iter().zip(&e.joints[n - 1]).take(7) {
        assert!((a - b).abs() < 0.1, "{a} against {b}");
    }
    // Rollouts of candidates from a saved state (a perfect model of the
    // MuJoCo world): each ends where stepping it does, and the scene is
    // left at the saved state.
    let mut s = engine.session("rollouts").unwrap();
    s.reset(&scene, size).unwrap();
    let saved = s.save("start").unwrap();
    let candidates = vec![e.joints[1..n].to_vec(), e.joints[1..n / 2].to_vec()];
    let ends = s.rollouts("start", &candidates, true).unwrap();
    let first = ends[0].as_ref().unwrap();
    assert_eq!(first.joints, whole.joints);
    assert_eq!(first.objects, whole.objects);
    assert_eq!(first.rgb, whole.rgb);
    assert_ne!(ends[1].as_ref().unwrap().joints, whole.joints);
    let back = s.restore("start").unwrap();
    assert_eq!(back.frames[0].joints, saved.frames[0].joints);
    let err = s
        .rollouts("nowhere", &candidates, false)
        .unwrap_err()
        .to_string();
    assert!(err.contains("nothing saved there"), "{err}");
    // A step before any reset: the worker refuses and stops; the error says why.
    let mut s = engine.session("early").unwrap();
    let err = s
        .step(&e.joints[1..2], Render::None)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("MuJoCo's worker stopped") && err.contains("expected reset"),
        "{err}"
    );
}

/// A task's scene executed in MuJoCo a chunk of end-effector actions at a
/// time (what a planner acts on in the MuJoCo world): the expert's actions
/// end where MuJoCo's run of the expert's plan ends.
#[test]
fn a_mujoco_scene_executes_the_experts_actions_as_the_engine_runs_its_plan() {
    use bridgev2w_data::synth::mujoco::{MujocoEngine, MujocoScene, Simulated};
    let python = mujoco_python();
    let world = World::new(&config("franka-robotiq")).unwrap();
    let e = world.generate(Split::Test, 0, Task::Reach).unwrap();
    let engine = MujocoEngine::new("franka-robotiq", python).unwrap();
    let Simulated::Stable(run) = engine.simulate(&world, e.clone()).unwrap() else {
        panic!("unstable")
    };
    let mut scene = MujocoScene::start(&engine, &world, &e, "scene").unwrap();
    assert_eq!(scene.rgb().len(), 32 * 48 * 3);
    assert_eq!(scene.state().object_poses, run.object_poses[0]);
    for chunk in e.actions[1..].chunks(4) {
        let out = scene.step(&world, chunk).unwrap();
        assert_eq!((out.joints.len(), out.rgb.len()), (chunk.len(), 1));
        assert_eq!(scene.state().joints, *out.joints.last().unwrap());
    }
    let tcp = |q: &[f64]| world.world_from_tcp(&e.meta, q).translation.vector;
    let gap = (tcp(&scene.state().joints) - tcp(run.joints.last().unwrap())).norm();
    assert!(
        gap < 0.01,
        "{gap} m between the executed and the simulated plan"
    );
    assert!(scene.state().held_object().is_none());
}

/// The MuJoCo engine draws the built-in world's backdrop (its pattern and
/// colours, new ones in unseen_scene) where MuJoCo's rays meet nothing:
/// the built-in frame's backdrop pixels are the same bytes in MuJoCo's.
#[test]
fn mujoco_frames_show_the_built_in_backdrop() {
    use bridgev2w_data::synth::mujoco::{MujocoEngine, Simulated};
    let python = mujoco_python();
    let world = World::new(&SynthConfig {
        frames: 5,
        width: 96,
        height: 64,
        ..config("franka-robotiq")
    })
    .unwrap();
    let engine = MujocoEngine::new("franka-robotiq", python).unwrap();
    for split in [Split::Test, Split::UnseenScene] {
        let e = world.generate(split, 0, Task::Reach).unwrap();
        let Simulated::Stable(run) = engine.simulate(&world, e.clone()).unwrap() else {
            panic!("unstable")
        };
        let back = world.backdrop(&e.meta, &e.camera);
        let px = |f: &[u8], i: usize| [f[3 * i], f[3 * i + 1], f[3 * i + 2]];
        let n = back.len() / 3;
        let seen: Vec<usize> = (0..n)
            .filter(|&i| px(&e.rgb[0], i) == px(&back, i))
            .collect();
        let same = seen
            .iter()
            .filter(|&&i| px(&run.rgb[0], i) == px(&back, i))
            .count();
        assert!(
            seen.len() > n / 20,
            "{split:?}: {} backdrop pixels of {n}",
            seen.len()
        );
        assert!(
            same as f64 > 0.95 * seen.len() as f64,
            "{split:?}: {same} of the built-in frame's {} backdrop pixels in MuJoCo's",
            seen.len()
        );
    }
}
