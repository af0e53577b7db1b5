//! Cheap models and environments shared by the planning tests: a model
//! whose frame is the end-effector position, and environments that move to
//! the last executed action (one of them recording every executed frame).
#![allow(dead_code, clippy::unwrap_used)]

use bridgev2w_io::frame::RgbFrame;
use bridgev2w_plan::model::{pad_to_clip, ActionWorldModel};
use bridgev2w_plan::mpc::Environment;
use bridgev2w_plan::{EeAction, Observation, Result};
use std::sync::Mutex;

/// A model whose "frame" is the end-effector position: pixel `i` holds
/// `0.5 + x_i` for `x, y, z`, so the goal image of a position is known and
/// the latent distance is the mean position error (plus the gripper pixel).
pub struct PositionModel {
    pub clip: usize,
    pub padded: Mutex<Vec<Vec<EeAction>>>,
}

pub fn position_image(a: &EeAction) -> RgbFrame {
    RgbFrame {
        height: 1,
        width: 2,
        rgb: vec![
            (0.5 + a[0]) as f32,
            (0.5 + a[1]) as f32,
            (0.5 + a[2]) as f32,
            a[6] as f32,
            0.0,
            0.0,
        ],
    }
}

pub fn position_obs(a: EeAction) -> Observation {
    Observation {
        image: position_image(&a),
        joints: vec![],
        ee: a,
        scene: None,
    }
}

impl ActionWorldModel for PositionModel {
    fn clip_frames(&self) -> usize {
        self.clip
    }
    fn resolution(&self) -> (usize, usize) {
        (1, 2)
    }
    fn rollout_batch(&self, _: &Observation, seqs: &[Vec<EeAction>]) -> Result<Vec<Observation>> {
        seqs.iter()
            .map(|s| {
                let p = pad_to_clip(s, self.clip)?;
                self.padded.lock().unwrap().push(p.clone());
                Ok(position_obs(*p.last().unwrap()))
            })
            .collect()
    }
    fn encode(&self, image: &RgbFrame) -> Result<Vec<f32>> {
        Ok(image.rgb.clone())
    }
}

/// Executes by moving the end effector to the last action.
pub struct PositionEnv {
    pub ee: EeAction,
    pub target: [f64; 3],
}

impl Environment for PositionEnv {
    fn observe(&self) -> Result<Observation> {
        Ok(position_obs(self.ee))
    }
    fn execute(&mut self, a: &[EeAction]) -> Result<Observation> {
        self.ee = *a.last().unwrap();
        self.observe()
    }
    fn goal_reached(&self) -> bool {
        (0..3).all(|i| (self.ee[i] - self.target[i]).abs() < 0.01)
    }
}

pub fn position_model() -> PositionModel {
    PositionModel {
        clip: 9,
        padded: Mutex::new(vec![]),
    }
}

/// Records the gripper command and position of every executed frame.
pub struct RecordingEnv {
    pub inner: PositionEnv,
    pub executed: Vec<(f64, f64)>,
}

impl Environment for RecordingEnv {
    fn observe(&self) -> Result<Observation> {
        self.inner.observe()
    }
    fn execute(&mut self, a: &[EeAction]) -> Result<Observation> {
        self.executed.extend(a.iter().map(|a| (a[0], a[6])));
        self.inner.execute(a)
    }
    fn goal_reached(&self) -> bool {
        self.inner.goal_reached()
    }
}
