//! The synthetic tabletop world as the "real robot" ([`SyntheticEnv`]) and
//! as a perfect world model ([`PerfectWorldModel`]: it steps the true scene
//! state through the actions and renders what really happens, which
//! separates planner quality from model quality).
//!
//! A task instance is a scripted expert episode of the world: its first
//! frame is the start, its frames at the task's key moments are the goal
//! images (pick-and-place: the grasp, then the final frame; push: the end
//! of the push, then the final frame; reach: the final frame), and its final
//! state defines success.

use crate::error::{PlanError, Result};
use crate::goal_latent::pyramid_latent;
use crate::model::{check_image_size, full_rows, pad_to_clip, ActionWorldModel, Workspace};
use crate::{EeAction, Observation};
use bridgev2w_data::synth::mujoco::{MujocoEngine, MujocoScene, Simulated};
use bridgev2w_data::synth::{Episode, RenderFrames, SceneState, Split, Task, World};
use bridgev2w_embodiment::kinematics::xyz_rpy_from_pose;
use bridgev2w_io::frame::{unit_from_u8, RgbFrame};
use nalgebra::Isometry3;
use rayon::prelude::*;

/// Success tolerance and the task object: the synthetic world's (the
/// perturbed demonstrations of `synth` are judged by them too).
pub use bridgev2w_data::synth::{SUCCESS_TOLERANCE_M, TASK_OBJECT};

/// Lowest planned TCP height above the table top (metres).
pub const WORKSPACE_CLEARANCE_M: f64 = 0.02;
/// Highest planned TCP height above the start pose's (metres).
pub const WORKSPACE_HEADROOM_M: f64 = 0.05;

/// RGB8 to an [`RgbFrame`] ([`unit_from_u8`]: `value / 255`).
pub fn image_from_rgb8(rgb: &[u8], height: usize, width: usize) -> RgbFrame {
    RgbFrame {
        height,
        width,
        rgb: rgb.iter().map(|&v| unit_from_u8(v)).collect(),
    }
}

/// Where waypoint goal images go between the key goals
/// ([`TaskInstance::with_waypoints`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum WaypointSpacing {
    /// This many per segment, evenly spaced in time (expert frames).
    Frames(usize),
    /// About one every this many metres of the expert's commanded TCP path,
    /// evenly along the path (beyond the paper): a long, fast motion (the
    /// approach from the home pose) gets several, a short one none, and
    /// none is farther from the next than about this.
    PathM(f64),
}

impl WaypointSpacing {
    /// Checks that a path spacing is a positive, finite length.
    pub fn validate(&self) -> Result<()> {
        match *self {
            Self::PathM(m) if !(m.is_finite() && m > 0.0) => Err(PlanError::input(
                "--waypoint-every-m",
                format!("{m}: expected a positive length in metres"),
            )),
            _ => Ok(()),
        }
    }

    /// The spacing in words, for reports.
    pub fn describe(&self) -> String {
        match *self {
            Self::Frames(n) => {
                format!("each preceded by {n} waypoint images (evenly spaced expert frames)")
            }
            Self::PathM(m) => format!(
                "each preceded by waypoint images about every {m} m of the expert's TCP path"
            ),
        }
    }
}

/// How a world model sees the scene: the start frame it is given and the
/// goal images it is asked to reach are drawn in its own look.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GoalLook {
    /// Drawn by the built-in world's renderer: its kinematic model
    /// ([`PerfectWorldModel`]) and models trained on its data. In MuJoCo
    /// the goals are the states MuJoCo's run of the expert reached, drawn
    /// by the built-in renderer.
    Builtin,
    /// As the executing world rendered them: MuJoCo's own frames when the
    /// instance runs in MuJoCo (models trained on `synth --engine mujoco`),
    /// the built-in world's otherwise.
    Executed,
}

/// One task instance: the scripted expert episode and its goals.
#[derive(Debug, Clone)]
pub struct TaskInstance {
    /// The task.
    pub task: Task,
    /// The expert episode (start, goals, success reference).
    pub expert: Episode,
    /// Expert frame indices of the goal images, in order (subgoal first).
    pub goal_frames: Vec<usize>,
    /// Index into `goal_frames` of the task's first key goal (the grasp of
    /// pick-and-place, the end of the push, the half-way pose of reach);
    /// goals before it are waypoints ([`TaskInstance::with_waypoints`]).
    pub first_key_goal: usize,
    /// The expert's episode as the executing world ran it, when that is
    /// not the built-in world ([`TaskInstance::in_mujoco`]): the success
    /// reference (its final TCP and object poses) and the states the goal
    /// images show ([`TaskInstance::goal_images`]).
    pub executed_expert: Option<Episode>,
}

impl TaskInstance {
    /// The instance `index` of `task` in `split` of `world`.
    pub fn new(world: &World, split: Split, index: usize, task: Task) -> Result<Self> {
        // The fraction of the expert episode at the first key goal.
        let key_frac = match task {
            Task::Reach => 0.5,
            Task::Push => 0.85,
            Task::PickPlace => 0.52,
            Task::Play => {
                return Err(PlanError::Invalid(
                    "task play has no goal: plan reach, push or pick_place".into(),
                ))
            }
        };
        let expert = world.generate(split, index, task)?;
        let n = expert.rgb.len();
        let at = |frac: f64| ((frac * (n - 1) as f64).round() as usize).min(n - 1);
        let goal_frames = vec![at(key_frac), n - 1];
        Ok(Self {
            task,
            expert,
            goal_frames,
            first_key_goal: 0,
            executed_expert: None,
        })
    }

    /// The instance with MuJoCo executing it (issue 72): the expert's plan
    /// run in MuJoCo becomes the success reference (where the expert's
    /// pushes and grasps end with real contact).
    pub fn in_mujoco(mut self, world: &World, engine: &MujocoEngine) -> Result<Self> {
        match engine.simulate(world, self.expert.clone())? {
            Simulated::Stable(run) => self.executed_expert = Some(*run),
            Simulated::Unstable { reason } => {
                return Err(PlanError::Invalid(format!(
                "{} instance {} of split {}: MuJoCo's run of the expert went unstable ({reason})",
                self.task.name(),
                self.expert.meta.index_in_split,
                self.expert.meta.split.name()
            )))
            }
        }
        Ok(self)
    }

    /// The success reference: the expert as the executing world ran it.
    fn reference(&self) -> &Episode {
        self.executed_expert.as_ref().unwrap_or(&self.expert)
    }

    /// Inserts waypoint goals (expert frames) before every key goal,
    /// between the start (or the previous key goal) and it, placed as
    /// `spacing` says. A goal image says little about a gripper far from it
    /// (out of view, or no overlap with its goal pose even at coarse blur),
    /// so a long motion is planned through nearer waypoints. Idempotent only
    /// on a fresh instance: the key goals are the current `goal_frames`.
    pub fn with_waypoints(mut self, spacing: WaypointSpacing) -> Result<Self> {
        spacing.validate()?;
        // Cumulative length (metres) of the expert's commanded TCP path.
        let xyz: Vec<[f64; 3]> = self
            .expert_actions()
            .iter()
            .map(|a| [a[0], a[1], a[2]])
            .collect();
        let mut path_m = vec![0.0];
        for w in xyz.windows(2) {
            let step = (0..3).map(|i| (w[1][i] - w[0][i]).powi(2)).sum::<f64>();
            path_m.push(path_m[path_m.len() - 1] + step.sqrt());
        }
        // The path length at a frame (the last action's beyond the actions).
        let along_m = |f: usize| path_m[f.min(path_m.len() - 1)];
        let mut frames = Vec::new();
        let mut first_key = None;
        let mut prev = 0usize;
        for &key in &self.goal_frames {
            let inner: Vec<usize> = match spacing {
                WaypointSpacing::Frames(n) => {
                    let span = key.saturating_sub(prev);
                    (1..=n)
                        .map(|j| prev + (span * j + n.div_ceil(2)) / (n + 1))
                        .collect()
                }
                WaypointSpacing::PathM(every_m) => {
                    let (p0, p1) = (along_m(prev), along_m(key));
                    // At most one waypoint per frame between the goals.
                    let most = key.saturating_sub(prev).max(1) as f64;
                    let n = ((p1 - p0) / every_m).ceil().clamp(1.0, most) as usize - 1;
                    (1..=n)
                        .filter_map(|j| {
                            let want_m = p0 + (p1 - p0) * j as f64 / (n + 1) as f64;
                            (prev..=key).min_by(|&a, &b| {
                                (along_m(a) - want_m)
                                    .abs()
                                    .total_cmp(&(along_m(b) - want_m).abs())
                            })
                        })
                        .collect()
                }
            };
            for f in inner {
                if f > prev && f < key && frames.last() != Some(&f) {
                    frames.push(f);
                }
            }
            first_key.get_or_insert(frames.len());
            frames.push(key);
            prev = key;
        }
        self.first_key_goal = first_key.unwrap_or(0);
        self.goal_frames = frames;
        Ok(self)
    }

    /// `(height, width)` of the episode's images.
    pub fn resolution(&self) -> (usize, usize) {
        (
            self.expert.camera.intrinsics.height as usize,
            self.expert.camera.intrinsics.width as usize,
        )
    }

    /// The goal images, subgoal first: the success reference's frames
    /// ([`TaskInstance::in_mujoco`]: MuJoCo's run of the expert, else the
    /// expert), drawn in `look`.
    pub fn goal_images(&self, world: &World, look: GoalLook) -> Vec<RgbFrame> {
        let (h, w) = self.resolution();
        let reference = self.reference();
        self.goal_frames
            .iter()
            .map(|&f| match (look, &self.executed_expert) {
                (GoalLook::Builtin, Some(run)) => image_from_rgb8(
                    &world.render_poses(
                        &run.meta,
                        &run.camera,
                        &run.joints[f],
                        &run.object_poses[f],
                    ),
                    h,
                    w,
                ),
                _ => image_from_rgb8(&reference.rgb[f], h, w),
            })
            .collect()
    }

    /// World positions (metres) of the reference's TCP at each goal image.
    pub fn goal_tcp_m(&self, world: &World) -> Vec<[f64; 3]> {
        self.goal_frames
            .iter()
            .filter_map(|&f| self.reference().joints.get(f))
            .map(|q| {
                let t = world
                    .world_from_tcp(&self.expert.meta, q)
                    .translation
                    .vector;
                [t.x, t.y, t.z]
            })
            .collect()
    }

    /// The acting arm's expert actions.
    pub fn expert_actions(&self) -> Vec<EeAction> {
        let arm = self.expert.meta.arm;
        self.expert
            .actions
            .iter()
            .map(|r| {
                let mut a = [0.0; 7];
                a.copy_from_slice(&r[7 * arm..7 * arm + 7]);
                a
            })
            .collect()
    }

    /// The planning workspace of the instance: above the table top (by
    /// [`WORKSPACE_CLEARANCE_M`]), inside its edges, and no higher than the
    /// start pose's TCP plus [`WORKSPACE_HEADROOM_M`].
    pub fn workspace(&self, world: &World) -> Workspace {
        let f = &world.frame;
        let start =
            world.world_from_tcp(&self.expert.meta, &world.initial_state(&self.expert).joints);
        let z_min = f.table_z_m + WORKSPACE_CLEARANCE_M;
        Workspace {
            min_m: [f.table_x_m[0], f.table_y_m[0], z_min],
            max_m: [
                f.table_x_m[1],
                f.table_y_m[1],
                (start.translation.z + WORKSPACE_HEADROOM_M).max(z_min),
            ],
        }
    }

    /// Whether a scene state accomplishes the task (see [`SUCCESS_TOLERANCE_M`]).
    pub fn success(&self, world: &World, state: &SceneState) -> bool {
        self.error_m(world, state) < SUCCESS_TOLERANCE_M
            && (self.task != Task::PickPlace || state.held_object().is_none())
    }

    /// The task error of a state (metres): TCP distance to the expert's
    /// final TCP (reach), or horizontal distance of the task object to its
    /// expert final position.
    pub fn error_m(&self, world: &World, state: &SceneState) -> f64 {
        match self.task {
            Task::Reach | Task::Play => {
                let (want, got) = self.final_and_current_tcp(world, state);
                (want.translation.vector - got.translation.vector).norm()
            }
            Task::Push | Task::PickPlace => {
                let (Some(want), Some(got)) = (
                    self.reference()
                        .object_poses
                        .last()
                        .and_then(|p| p.get(TASK_OBJECT)),
                    state.object_poses.get(TASK_OBJECT),
                ) else {
                    return f64::INFINITY;
                };
                let dx = want.position_m[0] - got.position_m[0];
                let dy = want.position_m[1] - got.position_m[1];
                dx.hypot(dy)
            }
        }
    }

    /// The angle (radians) between the TCP orientation of a state and the
    /// expert's final one. No task's success depends on it (reach judges the
    /// position, push and pick_place the object); it is reported so that
    /// searches over rotation can be compared.
    pub fn tcp_rotation_error_rad(&self, world: &World, state: &SceneState) -> f64 {
        let (want, got) = self.final_and_current_tcp(world, state);
        want.rotation.angle_to(&got.rotation)
    }

    /// World poses of the expert's final TCP and of `state`'s TCP.
    fn final_and_current_tcp(
        &self,
        world: &World,
        state: &SceneState,
    ) -> (Isometry3<f64>, Isometry3<f64>) {
        let meta = &self.expert.meta;
        let last = self.reference().joints.last().unwrap_or(&state.joints);
        (
            world.world_from_tcp(meta, last),
            world.world_from_tcp(meta, &state.joints),
        )
    }
}

/// An observation of a synthetic scene state.
fn observe(world: &World, inst: &TaskInstance, state: &SceneState, rgb: &[u8]) -> Observation {
    let (h, w) = inst.resolution();
    let tcp = world.world_from_tcp(&inst.expert.meta, &state.joints);
    let v = xyz_rpy_from_pose(&tcp);
    Observation {
        image: image_from_rgb8(rgb, h, w),
        joints: state.joints.clone(),
        ee: [v[0], v[1], v[2], v[3], v[4], v[5], state.prev_gripper],
        scene: Some(state.clone()),
    }
}

/// The synthetic world executing actions of one task instance: the "real robot".
#[derive(Debug)]
pub struct SyntheticEnv<'w> {
    /// The world.
    pub world: &'w World,
    /// The task instance.
    pub instance: TaskInstance,
    /// The current state.
    pub state: SceneState,
    /// Frames executed so far.
    pub frames_executed: usize,
    /// The task object was held in the gripper at the end of some executed
    /// chunk: a pick_place success with it was a grasp and a carry, not a
    /// push into place.
    pub carried_task_object: bool,
    /// MuJoCo executing the actions instead of the built-in world
    /// ([`SyntheticEnv::in_mujoco`]).
    pub mujoco: Option<MujocoScene>,
}

impl<'w> SyntheticEnv<'w> {
    /// At the instance's start state.
    pub fn new(world: &'w World, instance: TaskInstance) -> Self {
        let state = world.initial_state(&instance.expert);
        Self {
            world,
            instance,
            state,
            frames_executed: 0,
            carried_task_object: false,
            mujoco: None,
        }
    }

    /// At the instance's start state in MuJoCo (issue 72): actions are
    /// executed and observed there, the success judged on MuJoCo's state
    /// against the instance's reference ([`TaskInstance::in_mujoco`]).
    pub fn in_mujoco(
        world: &'w World,
        instance: TaskInstance,
        engine: &MujocoEngine,
    ) -> Result<Self> {
        let name = format!(
            "{}-{}-{}",
            instance.task.name(),
            instance.expert.meta.split.name(),
            instance.expert.meta.index_in_split
        );
        let scene = MujocoScene::start(engine, world, &instance.expert, &name)?;
        Ok(Self {
            world,
            state: scene.state().clone(),
            instance,
            frames_executed: 0,
            carried_task_object: false,
            mujoco: Some(scene),
        })
    }

    /// The current observation.
    pub fn observe(&self) -> Observation {
        if let Some(scene) = &self.mujoco {
            return observe(self.world, &self.instance, &self.state, scene.rgb());
        }
        let rgb = self.world.render_state(
            &self.instance.expert.meta,
            &self.instance.expert.camera,
            &self.state,
        );
        observe(self.world, &self.instance, &self.state, &rgb)
    }

    /// Executes end-effector actions (one per frame) and observes.
    pub fn execute(&mut self, actions: &[EeAction]) -> Result<Observation> {
        crate::error::check_finite("executed actions", actions)?;
        let e = &self.instance.expert;
        let rows = full_rows(actions, e.meta.arm, &e.actions[0]);
        let (out, next) = match self.mujoco.as_mut() {
            Some(scene) => {
                let out = scene.step(self.world, &rows)?;
                (out, scene.state().clone())
            }
            None => self
                .world
                .step(&e.meta, &e.camera, &self.state, &rows, RenderFrames::Last)?,
        };
        self.state = next;
        self.frames_executed += actions.len();
        self.carried_task_object |= self.state.held_object() == Some(TASK_OBJECT);
        let rgb = out
            .rgb
            .last()
            .ok_or_else(|| PlanError::Invalid("the world rendered no frame".into()))?;
        Ok(observe(self.world, &self.instance, &self.state, rgb))
    }

    /// Whether the current state accomplishes the task.
    pub fn success(&self) -> bool {
        self.instance.success(self.world, &self.state)
    }
}

/// The synthetic world's renderer as a world model: from the true scene
/// state of the start observation it steps the actions and renders the
/// clip's last frame. Its latent is a Gaussian pyramid of the image
/// ([`crate::goal_latent::pyramid_latent`]).
#[derive(Debug)]
pub struct PerfectWorldModel<'w> {
    /// The world.
    pub world: &'w World,
    /// The task instance (scene, camera).
    pub instance: TaskInstance,
    /// Frames per clip.
    pub clip_frames: usize,
}

impl ActionWorldModel for PerfectWorldModel<'_> {
    fn clip_frames(&self) -> usize {
        self.clip_frames
    }

    fn resolution(&self) -> (usize, usize) {
        self.instance.resolution()
    }

    fn rollout_batch(
        &self,
        start: &Observation,
        sequences: &[Vec<EeAction>],
    ) -> Result<Vec<Observation>> {
        let state = start.scene.as_ref().ok_or_else(|| {
            PlanError::Invalid(
                "the perfect world model needs the synthetic scene state of the start observation"
                    .into(),
            )
        })?;
        let e = &self.instance.expert;
        sequences
            .par_iter()
            .map(|seq| {
                crate::error::check_finite("action sequence", seq)?;
                let padded = pad_to_clip(seq, self.clip_frames)?;
                let rows = full_rows(&padded, e.meta.arm, &e.actions[0]);
                let (out, next) =
                    self.world
                        .step(&e.meta, &e.camera, state, &rows, RenderFrames::Last)?;
                let rgb = out
                    .rgb
                    .last()
                    .ok_or_else(|| PlanError::Invalid("the world rendered no frame".into()))?;
                Ok(observe(self.world, &self.instance, &next, rgb))
            })
            .collect()
    }

    fn encode(&self, image: &RgbFrame) -> Result<Vec<f32>> {
        check_image_size(image, self.resolution())?;
        Ok(pyramid_latent(image))
    }
}
