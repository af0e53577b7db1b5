//! A task's scene executed in MuJoCo, step by step: what a planner or a
//! policy acts on when the world is MuJoCo (issue 72, item 3), as
//! [`World::step`] is for the built-in world. End-effector actions become
//! joint targets by the world's IK warm-started from the joints MuJoCo's arm
//! reached; MuJoCo moves the arm and the objects; the state after a step is
//! MuJoCo's.

use super::{engine_error, MujocoEngine, MujocoSession, Render, SimFrame};
use crate::synth::{Contact, Episode, EpisodeMeta, SceneState, StepOutput, SynthError, World};
use nalgebra::Isometry3;

/// One scene in a MuJoCo session.
#[derive(Debug)]
pub struct MujocoScene {
    session: MujocoSession,
    meta: EpisodeMeta,
    state: SceneState,
    rgb: Vec<u8>,
    table_z_m: f64,
}

impl MujocoScene {
    /// The scene of `episode` (its camera, look, objects), the robot at the
    /// episode's first joints; `name` names the session's files.
    pub fn start(
        engine: &MujocoEngine,
        world: &World,
        episode: &Episode,
        name: &str,
    ) -> Result<Self, SynthError> {
        let mut plan = episode.clone();
        plan.joints.truncate(1);
        let json = engine.scene_json(world, &plan, name)?;
        let mut session = engine.session(name)?;
        let k = &episode.camera.intrinsics;
        let start = session.reset(&json, (k.height as usize, k.width as usize))?;
        engine.remove_scene_files(name);
        if let Some(reason) = start.unstable {
            return Err(engine_error(format!("the scene's start: {reason}")));
        }
        let frame = start
            .frames
            .into_iter()
            .next()
            .ok_or_else(|| engine_error("MuJoCo returned no start frame"))?;
        let mut state = world.initial_state(episode);
        let table_z_m = world.frame.table_z_m;
        let gripper = state.prev_gripper;
        let rgb = update(&mut state, &frame, table_z_m, gripper)?;
        Ok(Self {
            session,
            meta: episode.meta.clone(),
            state,
            rgb,
            table_z_m,
        })
    }

    /// The current state (MuJoCo's joints and object poses).
    pub fn state(&self) -> &SceneState {
        &self.state
    }

    /// The current frame, RGB8 as rendered by MuJoCo.
    pub fn rgb(&self) -> &[u8] {
        &self.rgb
    }

    /// The session (for rollouts of candidates from the current state).
    pub fn session(&mut self) -> &mut MujocoSession {
        &mut self.session
    }

    /// Executes end-effector `actions` (full rows, 7 per arm, as
    /// [`World::step`] takes them), rendering the last frame; the frames'
    /// joints, object poses and contacts as [`World::step`] returns them.
    /// A step whose physics goes unstable is an error naming the frame.
    pub fn step(&mut self, world: &World, actions: &[Vec<f64>]) -> Result<StepOutput, SynthError> {
        let targets = world.step_joints(&self.meta, &self.state.joints, actions)?;
        let reply = self.session.step(&targets, Render::Last)?;
        if let Some(reason) = reply.unstable {
            return Err(engine_error(format!(
                "MuJoCo's physics went unstable: {reason}"
            )));
        }
        let mut out = StepOutput {
            rgb: Vec::new(),
            joints: Vec::with_capacity(reply.frames.len()),
            object_poses: Vec::with_capacity(reply.frames.len()),
            contacts: Vec::with_capacity(reply.frames.len()),
        };
        for (f, frame) in reply.frames.iter().enumerate() {
            let gripper = actions[f][7 * self.meta.arm + 6];
            if let Some(rgb) = frame.rgb.as_ref().filter(|_| f + 1 == reply.frames.len()) {
                self.rgb = update(&mut self.state, frame, self.table_z_m, gripper)?;
                out.rgb.push(rgb.clone());
            }
            out.joints.push(frame.joints.clone());
            out.object_poses.push(frame.objects.clone());
            out.contacts.push(frame.contacts(self.table_z_m));
        }
        Ok(out)
    }
}

/// `state` as MuJoCo's `frame` left it (the held object: one the robot
/// touches above the table); its rendered RGB.
fn update(
    state: &mut SceneState,
    frame: &SimFrame,
    table_z_m: f64,
    gripper: f64,
) -> Result<Vec<u8>, SynthError> {
    state.joints = frame.joints.clone();
    state.object_poses = frame.objects.clone();
    state.held = frame
        .contacts(table_z_m)
        .iter()
        .position(|c| *c == Contact::Carried)
        .map(|i| (i, Isometry3::identity()));
    state.prev_points = None;
    state.prev_gripper = gripper;
    frame
        .rgb
        .clone()
        .ok_or_else(|| engine_error("MuJoCo returned the frame unrendered"))
}
