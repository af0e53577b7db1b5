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
use crate::model::{check_image_size, full_rows, pad_to_clip, ActionWorldModel};
use crate::{EeAction, Observation};
use bridgev2w_data::synth::{Episode, RenderFrames, SceneState, Split, Task, World};
use bridgev2w_embodiment::kinematics::xyz_rpy_from_pose;
use bridgev2w_world_model::video::Image;
use rayon::prelude::*;

/// Success tolerance: TCP (reach) or object (push, pick-and-place) within
/// this distance of the expert's final one (metres, horizontal for objects).
pub const SUCCESS_TOLERANCE_M: f64 = 0.03;

/// RGB8 to an [`Image`].
pub fn image_from_rgb8(rgb: &[u8], height: usize, width: usize) -> Image {
    Image {
        height,
        width,
        data: rgb.iter().map(|&v| f32::from(v) / 255.0).collect(),
    }
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
}

impl TaskInstance {
    /// The instance `index` of `task` in `split` of `world`.
    pub fn new(world: &World, split: Split, index: usize, task: Task) -> Result<Self> {
        let expert = world.generate(split, index, task)?;
        let n = expert.rgb.len();
        let at = |frac: f64| ((frac * (n - 1) as f64).round() as usize).min(n - 1);
        let goal_frames = match task {
            Task::Reach => vec![n - 1],
            Task::Push => vec![at(0.85), n - 1],
            Task::PickPlace => vec![at(0.52), n - 1],
        };
        Ok(Self {
            task,
            expert,
            goal_frames,
        })
    }

    /// `(height, width)` of the episode's images.
    pub fn resolution(&self) -> (usize, usize) {
        (
            self.expert.camera.intrinsics.height as usize,
            self.expert.camera.intrinsics.width as usize,
        )
    }

    /// The goal images, subgoal first.
    pub fn goal_images(&self) -> Vec<Image> {
        let (h, w) = self.resolution();
        self.goal_frames
            .iter()
            .map(|&f| image_from_rgb8(&self.expert.rgb[f], h, w))
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

    /// Whether a scene state accomplishes the task (see [`SUCCESS_TOLERANCE_M`]).
    pub fn success(&self, world: &World, state: &SceneState) -> bool {
        self.error_m(world, state) < SUCCESS_TOLERANCE_M
            && (self.task != Task::PickPlace || state.held_object().is_none())
    }

    /// The task error of a state (metres): TCP distance to the expert's
    /// final TCP (reach), or horizontal distance of the task object to its
    /// expert final position.
    pub fn error_m(&self, world: &World, state: &SceneState) -> f64 {
        let meta = &self.expert.meta;
        match self.task {
            Task::Reach => {
                let want =
                    world.world_from_tcp(meta, self.expert.joints.last().unwrap_or(&state.joints));
                let got = world.world_from_tcp(meta, &state.joints);
                (want.translation.vector - got.translation.vector).norm()
            }
            Task::Push | Task::PickPlace => {
                let (Some(want), Some(got)) = (
                    self.expert.object_poses.last().and_then(|p| p.first()),
                    state.object_poses.first(),
                ) else {
                    return f64::INFINITY;
                };
                let dx = want.position_m[0] - got.position_m[0];
                let dy = want.position_m[1] - got.position_m[1];
                dx.hypot(dy)
            }
        }
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
        }
    }

    /// The current observation.
    pub fn observe(&self) -> Observation {
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
        let (out, next) =
            self.world
                .step(&e.meta, &e.camera, &self.state, &rows, RenderFrames::Last)?;
        self.state = next;
        self.frames_executed += actions.len();
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
/// clip's last frame. Its latent is the image average-pooled over 4x4
/// pixel cells.
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

    fn encode(&self, image: &Image) -> Result<Vec<f32>> {
        check_image_size(image, self.resolution())?;
        Ok(pool4(image))
    }
}

/// Average pooling over 4x4 pixel cells (partial cells at the border).
pub fn pool4(image: &Image) -> Vec<f32> {
    let (h, w) = (image.height, image.width);
    let (ph, pw) = (h.div_ceil(4), w.div_ceil(4));
    let mut out = vec![0.0f32; ph * pw * 3];
    let mut count = vec![0.0f32; ph * pw];
    for y in 0..h {
        for x in 0..w {
            let cell = (y / 4) * pw + x / 4;
            count[cell] += 1.0;
            for c in 0..3 {
                out[cell * 3 + c] += image.data[(y * w + x) * 3 + c];
            }
        }
    }
    for (i, v) in out.iter_mut().enumerate() {
        *v /= count[i / 3].max(1.0);
    }
    out
}
