//! The world of one robot: generating whole episodes (sample, IK, contact
//! simulation, rendering, masks) and stepping a scene from a state.

use super::{episode_seed, plan, Contact, ObjectPose, SceneFrame, SceneLook, SceneObject};
use super::{split_specs, Split, SplitSpec, SynthConfig, SynthError, Task};
use bridgev2w_embodiment::actions::{actions_to_joints, Trajectory};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_embodiment::embodiment::{Embodiment, BUILTIN_ROBOTS};
use bridgev2w_embodiment::kinematics::IkOptions;
use bridgev2w_embodiment::masks::render_trajectory_labels;
use bridgev2w_embodiment::mesh::TriMesh;
use nalgebra::{Isometry3, Point3};
use rand::SeedableRng;
use rand_chacha::ChaCha8Rng;

/// The worst IK position residual an episode may have (metres).
pub(super) const MAX_IK_RESIDUAL_M: f64 = 0.01;
/// The worst IK rotation residual an episode may have (radians; 5 degrees).
pub(super) const MAX_IK_RESIDUAL_RAD: f64 = 5.0 * (std::f64::consts::PI / 180.0);

/// The seed stream of the perturbation draws (`derive_seed` with the
/// episode's seed).
const PERTURB_STREAM: u64 = 0x5045_5254_5552_4221;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};

/// Everything about one generated episode.
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct EpisodeMeta {
    /// Split.
    pub split: Split,
    /// Index within the split.
    pub index_in_split: usize,
    /// Task.
    pub task: Task,
    /// The episode's RNG seed.
    pub seed: u64,
    /// Acting arm (index into the embodiment's end effectors).
    pub arm: usize,
    /// Camera azimuth (degrees) around the workspace centre.
    pub camera_azimuth_deg: f64,
    /// Camera elevation (degrees).
    pub camera_elevation_deg: f64,
    /// Camera distance (metres).
    pub camera_distance_m: f64,
    /// Scene look.
    pub look: SceneLook,
    /// Objects with initial poses.
    pub objects: Vec<SceneObject>,
    /// Worst IK position residual over frames and arms (metres).
    pub max_ik_residual_m: f64,
    /// A perturbed demonstration's offset and outcome
    /// ([`super::Perturbation`]); `None` for the expert's own actions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub perturbation: Option<super::PerturbedOutcome>,
    /// MuJoCo's run of the episode (`synth --engine mujoco`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mujoco: Option<super::mujoco::MujocoCheck>,
}

/// One rendered clip.
#[derive(Debug, Clone)]
pub struct Episode {
    /// Metadata.
    pub meta: EpisodeMeta,
    /// The camera (intrinsics + `world_from_camera`).
    pub camera: Camera,
    /// Per frame: interleaved RGB8, `height * width * 3`.
    pub rgb: Vec<Vec<u8>>,
    /// Per frame: embodiment mask (0/1), `height * width`.
    pub masks: Vec<Vec<u8>>,
    /// Per frame: link labels (0 = background, else the link's label,
    /// `bridgev2w_embodiment::masks::label_of_link`, at most 255), `height * width`.
    pub labels: Vec<Vec<u8>>,
    /// Per frame: end-effector actions, 7 per arm.
    pub actions: Vec<Vec<f64>>,
    /// Per frame: joint positions (URDF actuated order).
    pub joints: Vec<Vec<f64>>,
    /// Per frame, per object: pose.
    pub object_poses: Vec<Vec<ObjectPose>>,
    /// Per frame, per object: contact event.
    pub contacts: Vec<Vec<Contact>>,
    /// `--engine mujoco`: per frame, MuJoCo's segmentation of the robot
    /// (0/1, `height * width`), an independent renderer's robot pixels.
    pub mujoco_masks: Option<Vec<Vec<u8>>>,
}

/// The dynamic state of a scene between frames: what [`World::step`]
/// continues from.
#[derive(Debug, Clone, PartialEq)]
pub struct SceneState {
    /// Robot joints (URDF actuated order).
    pub joints: Vec<f64>,
    /// Per object: pose.
    pub object_poses: Vec<ObjectPose>,
    /// Held object: `(index, tcp_from_object_center)`.
    pub(super) held: Option<(usize, Isometry3<f64>)>,
    /// Contact points (fingertips, hand) of the previous frame (world frame).
    pub(super) prev_points: Option<[Point3<f64>; 3]>,
    /// Gripper command of the previous frame (0 open, 1 closed).
    pub prev_gripper: f64,
}

impl SceneState {
    /// The index of the object held in the gripper, if any.
    pub fn held_object(&self) -> Option<usize> {
        self.held.map(|(i, _)| i)
    }
}

/// Which frames [`World::step`] renders.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RenderFrames {
    /// None (state only).
    None,
    /// The last frame only.
    Last,
    /// Every frame.
    All,
}

/// The frames of one [`World::step`].
#[derive(Debug, Clone)]
pub struct StepOutput {
    /// Rendered frames (interleaved RGB8), as [`RenderFrames`] asked.
    pub rgb: Vec<Vec<u8>>,
    /// Per frame: achieved joints.
    pub joints: Vec<Vec<f64>>,
    /// Per frame, per object: pose.
    pub object_poses: Vec<Vec<ObjectPose>>,
    /// Per frame, per object: contact event.
    pub contacts: Vec<Vec<Contact>>,
}

/// The synthetic world of one robot.
#[derive(Debug)]
pub struct World {
    /// The robot.
    pub embodiment: Embodiment,
    /// Table and workspace placement.
    pub frame: SceneFrame,
    /// Split definitions.
    pub specs: Vec<SplitSpec>,
    /// Configuration.
    pub config: SynthConfig,
    /// Home end-effector poses (world frame), per arm.
    pub(super) home_tcp: Vec<Isometry3<f64>>,
}

impl World {
    /// The world for `config.robot`.
    pub fn new(config: &SynthConfig) -> Result<World, SynthError> {
        config.validate()?;
        let embodiment = Embodiment::builtin(&config.robot)?;
        let usable: Vec<&str> = BUILTIN_ROBOTS
            .iter()
            .filter(|b| b.synthetic_world)
            .map(|b| b.name)
            .collect();
        if !usable.contains(&config.robot.as_str()) {
            return Err(SynthError::Config(format!(
                "robot \"{}\": the synthetic world's tables are laid out for {}",
                config.robot,
                usable.join(", ")
            )));
        }
        let frame = SceneFrame::for_embodiment(&embodiment);
        let poses = embodiment.robot.link_poses(&embodiment.home);
        let home_tcp = embodiment
            .end_effectors
            .iter()
            .map(|ee| poses[ee.link])
            .collect();
        Ok(World {
            embodiment,
            frame,
            specs: split_specs(),
            config: config.clone(),
            home_tcp,
        })
    }

    /// The definition of `split`.
    pub fn spec(&self, split: Split) -> &SplitSpec {
        let i = Split::ALL.iter().position(|s| *s == split).unwrap_or(0);
        &self.specs[i]
    }

    /// Generates all planned episodes in parallel (output independent of
    /// thread count). `on_episode` is called after each.
    pub fn generate_all(&self, on_episode: &(dyn Fn() + Sync)) -> Result<Vec<Episode>, SynthError> {
        plan(&self.config)
            .par_iter()
            .map(|&(split, i, task)| {
                let e = self.generate(split, i, task);
                on_episode();
                e
            })
            .collect()
    }

    /// Generates one episode (retrying layouts until the IK reaches the
    /// scripted targets within 1 cm).
    pub fn generate(&self, split: Split, index: usize, task: Task) -> Result<Episode, SynthError> {
        let base_seed = episode_seed(self.config.seed, split, index);
        let mut last_residual = f64::INFINITY;
        const ATTEMPTS: usize = 8;
        for attempt in 0..ATTEMPTS {
            let seed = base_seed.wrapping_add(attempt as u64);
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let (meta, camera, actions) = self.sample(split, index, task, seed, &mut rng)?;
            let (joints, worst, worst_rot) = self.episode_joints("synth", &actions, seed)?;
            last_residual = worst;
            if worst > MAX_IK_RESIDUAL_M || worst_rot > MAX_IK_RESIDUAL_RAD {
                continue;
            }
            let mut meta = meta;
            meta.max_ik_residual_m = worst;
            let expert = self.finish(meta, camera, actions, joints);
            if self.config.perturb.fraction <= 0.0 {
                return Ok(expert);
            }
            // Its own stream: the expert episodes stay as without perturbation.
            let mut rng = ChaCha8Rng::seed_from_u64(bridgev2w_io::seed::derive_seed(&[
                base_seed,
                PERTURB_STREAM,
            ]));
            return self.perturbed(expert, &self.config.perturb, &mut rng);
        }
        Err(SynthError::Unreachable {
            split: split.name().into(),
            episode: index,
            task: task.name().into(),
            attempts: ATTEMPTS,
            residual_mm: last_residual * 1e3,
        })
    }

    /// The joints of an episode's end-effector `actions` by IK from the
    /// home pose (8 restarts, `seed`), with the worst position (metres) and
    /// rotation (radians) residuals over its frames and arms.
    pub(super) fn episode_joints(
        &self,
        what: &str,
        actions: &[Vec<f64>],
        seed: u64,
    ) -> Result<(Vec<Vec<f64>>, f64, f64), SynthError> {
        let traj = Trajectory::new(what, actions.to_vec())?;
        let opts = IkOptions {
            restarts: 8,
            seed,
            ..IkOptions::default()
        };
        let (joints, residuals) = actions_to_joints(
            &self.embodiment.robot,
            &self.embodiment.end_effectors,
            &traj,
            &self.embodiment.home,
            &opts,
            true,
        )?;
        let worst = |f: fn(&_) -> f64| residuals.iter().map(f).fold(0.0, f64::max);
        let (position_m, rotation_rad) = (
            worst(|r| r.position_error_m),
            worst(|r| r.rotation_error_rad),
        );
        Ok((joints, position_m, rotation_rad))
    }

    /// Simulates the objects and renders the clip.
    pub(super) fn finish(
        &self,
        meta: EpisodeMeta,
        camera: Camera,
        actions: Vec<Vec<f64>>,
        joints: Vec<Vec<f64>>,
    ) -> Episode {
        let robot = &self.embodiment.robot;
        let ee = &self.embodiment.end_effectors[meta.arm];
        let (object_poses, contacts) = self.simulate(&meta, &actions, &joints);
        let labels = render_trajectory_labels(robot, &camera, &joints, &|| {});
        let masks = labels
            .iter()
            .map(|l| l.iter().map(|&v| u8::from(v != 0)).collect())
            .collect();
        let labels = labels
            .iter()
            .map(|l| l.iter().map(|&v| v.min(255) as u8).collect())
            .collect();
        let meshes: Vec<TriMesh> = meta.objects.iter().map(|o| o.shape.mesh()).collect();
        let _ = ee;
        let rgb = joints
            .iter()
            .zip(&object_poses)
            .map(|(q, poses)| self.render_rgb(&meta, &camera, &meshes, q, poses))
            .collect();
        Episode {
            meta,
            camera,
            rgb,
            masks,
            labels,
            actions,
            joints,
            object_poses,
            contacts,
            mujoco_masks: None,
        }
    }

    /// The state of an episode's scene at its first frame: the robot at the
    /// episode's first joints, the objects at their initial poses.
    pub fn initial_state(&self, episode: &Episode) -> SceneState {
        let g0 = episode
            .actions
            .first()
            .map_or(0.0, |row| row[7 * episode.meta.arm + 6]);
        SceneState {
            joints: episode
                .joints
                .first()
                .cloned()
                .unwrap_or_else(|| self.embodiment.home.clone()),
            object_poses: episode.meta.objects.iter().map(|o| o.initial).collect(),
            held: None,
            prev_points: None,
            prev_gripper: g0,
        }
    }

    /// The end-effector pose of the acting arm at joints `q` (world frame).
    pub fn world_from_tcp(&self, meta: &EpisodeMeta, q: &[f64]) -> Isometry3<f64> {
        let ee = &self.embodiment.end_effectors[meta.arm];
        self.embodiment.robot.link_pose(ee.link, q)
    }

    /// The joints of a step's end-effector `actions` (full rows, 7 per
    /// arm), by IK warm-started from `from` (2 restarts, the episode's seed):
    /// what [`World::step`] executes, and a MuJoCo scene's targets.
    pub fn step_joints(
        &self,
        meta: &EpisodeMeta,
        from: &[f64],
        actions: &[Vec<f64>],
    ) -> Result<Vec<Vec<f64>>, SynthError> {
        let traj = Trajectory::new("scene step", actions.to_vec())?;
        let opts = IkOptions {
            restarts: 2,
            seed: meta.seed,
            ..IkOptions::default()
        };
        let (joints, _) = actions_to_joints(
            &self.embodiment.robot,
            &self.embodiment.end_effectors,
            &traj,
            from,
            &opts,
            true,
        )?;
        Ok(joints)
    }

    /// Steps a scene from `state` through end-effector `actions` (one row
    /// per frame, 7 values per arm as in [`Episode::actions`]): IK warm-started
    /// from the state's joints (targets out of reach leave a residual rather
    /// than an error), the contact rules per frame, and RGB frames as
    /// `render` asks. Returns the step's frames and the state after the
    /// last action.
    pub fn step(
        &self,
        meta: &EpisodeMeta,
        camera: &Camera,
        state: &SceneState,
        actions: &[Vec<f64>],
        render: RenderFrames,
    ) -> Result<(StepOutput, SceneState), SynthError> {
        let joints = self.step_joints(meta, &state.joints, actions)?;
        let mut next = state.clone();
        let meshes: Vec<TriMesh> = meta.objects.iter().map(|o| o.shape.mesh()).collect();
        let mut out = StepOutput {
            rgb: Vec::new(),
            joints: Vec::with_capacity(joints.len()),
            object_poses: Vec::with_capacity(joints.len()),
            contacts: Vec::with_capacity(joints.len()),
        };
        let last = joints.len().saturating_sub(1);
        for (f, q) in joints.iter().enumerate() {
            let g = actions[f][7 * meta.arm + 6];
            let contacts = self.contact_step(meta, &mut next, q, g);
            if render == RenderFrames::All || (render == RenderFrames::Last && f == last) {
                out.rgb
                    .push(self.render_rgb(meta, camera, &meshes, q, &next.object_poses));
            }
            out.joints.push(q.clone());
            out.object_poses.push(next.object_poses.clone());
            out.contacts.push(contacts);
        }
        Ok((out, next))
    }
}
