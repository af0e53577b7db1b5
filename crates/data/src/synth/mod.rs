//! The synthetic tabletop world: scripted robot tasks rendered to RGB clips
//! with ground-truth embodiment masks.
//!
//! World frame = the robot base frame (metres, radians). A table top (the
//! plane `z = table_z_m`) carries a few boxes and cylinders; a scripted
//! end-effector trajectory (`reach`, `push`, `pick_place`, with action noise)
//! is turned into joints by the embodiment crate's warm-started IK; objects
//! move by kinematic contact rules driven by the robot's *achieved* gripper
//! pose (forward kinematics of the IK joints): an object between the fingers
//! when the gripper closes is carried until the gripper opens, an object the
//! fingers/hand run into is pushed along the motion. RGB frames come from
//! [`crate::render`]; masks from the embodiment crate's mask rasterizer
//! ([`masks::render_trajectory_labels`], the renderer of `bridgev2w masks`).
//!
//! Every episode is generated from its own seeded ChaCha stream derived from
//! the dataset seed, the split and the episode's index within its split, so
//! output does not depend on threads or on the order of generation.

mod contacts;
mod draw;
pub mod mujoco;
mod perturb;
mod scene;
mod tasks;
mod world;
mod writer;

pub use contacts::Contact;
pub use perturb::{Perturbation, PerturbedOutcome, SUCCESS_TOLERANCE_M, TASK_OBJECT};
pub use scene::{
    split_specs, CameraRegion, ObjectPose, Pattern, SceneFrame, SceneLook, SceneObject,
    ScenePalette, Shape, SplitSpec,
};
pub use world::{Episode, EpisodeMeta, RenderFrames, SceneState, StepOutput, World};
pub use writer::{write_dataset, DatasetSummary, WriteDatasetError, VIDEO_KEY};

use bridgev2w_embodiment::actions::ActionError;
use bridgev2w_embodiment::camera::CameraError;
use bridgev2w_embodiment::embodiment::EmbodimentError;
use serde::{Deserialize, Serialize};

/// Errors of the synthetic world.
#[derive(Debug, thiserror::Error)]
pub enum SynthError {
    /// Unknown robot or bad embodiment.
    #[error(transparent)]
    Embodiment(#[from] EmbodimentError),
    /// A sampled camera was invalid.
    #[error(transparent)]
    Camera(#[from] CameraError),
    /// IK failed on the scripted actions.
    #[error(transparent)]
    Actions(#[from] ActionError),
    /// Bad configuration.
    #[error("invalid synth configuration: {0}")]
    Config(String),
    /// The simulation engine (MuJoCo) could not run.
    #[error("synth --engine mujoco: {0}")]
    Engine(String),
    /// No reachable trajectory after retries.
    #[error("episode {episode} of split {split}: no reachable {task} trajectory after {attempts} attempts (last IK residual {residual_mm:.1} mm)")]
    Unreachable {
        /// Split name.
        split: String,
        /// Index within the split.
        episode: usize,
        /// Task name.
        task: String,
        /// Attempts made.
        attempts: usize,
        /// Worst position residual of the last attempt (mm).
        residual_mm: f64,
    },
}

/// A dataset split (the paper's DROID protocol).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Split {
    /// Training episodes.
    Train,
    /// In-domain test: training distributions, other seeds.
    Test,
    /// Cameras from an azimuth region never used in train/test.
    UnseenCamera,
    /// Table/background textures, colours and object layouts never used in train/test.
    UnseenScene,
}

impl Split {
    /// All splits in order.
    pub const ALL: [Split; 4] = [
        Split::Train,
        Split::Test,
        Split::UnseenCamera,
        Split::UnseenScene,
    ];

    /// The split's name in metadata and on the command line.
    pub fn name(self) -> &'static str {
        match self {
            Split::Train => "train",
            Split::Test => "test",
            Split::UnseenCamera => "unseen_camera",
            Split::UnseenScene => "unseen_scene",
        }
    }

    /// Parses [`Split::name`].
    pub fn parse(s: &str) -> Option<Split> {
        Split::ALL.into_iter().find(|x| x.name() == s)
    }

    /// Parses [`Split::name`], or says what was expected (a flag's parser).
    pub fn parse_named(s: &str) -> Result<Split, String> {
        Split::parse(s).ok_or_else(|| {
            format!("unknown split {s:?}: expected train, test, unseen_camera or unseen_scene")
        })
    }

    fn stream_id(self) -> u64 {
        match self {
            Split::Train => 1,
            Split::Test => 2,
            Split::UnseenCamera => 3,
            Split::UnseenScene => 4,
        }
    }
}

/// A scripted task.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Task {
    /// Move the gripper to a random point above the table.
    Reach,
    /// Push an object along the table with the closed gripper.
    Push,
    /// Grasp an object, carry it and release it elsewhere.
    PickPlace,
    /// Random "play": a smooth path through a few random waypoints over the
    /// table, some at an object (grasps that may hold or slip, pushes), the
    /// gripper opened and closed at random. Training data that covers the
    /// action space; no success criterion, so no planning task.
    Play,
}

impl Task {
    /// The scripted tasks with a goal (planning, policy evaluation).
    pub const ALL: [Task; 3] = [Task::Reach, Task::Push, Task::PickPlace];
    /// Every task `synth` can generate: [`Task::ALL`] and [`Task::Play`].
    pub const GENERATED: [Task; 4] = [Task::Reach, Task::Push, Task::PickPlace, Task::Play];

    /// The task's name.
    pub fn name(self) -> &'static str {
        match self {
            Task::Reach => "reach",
            Task::Push => "push",
            Task::PickPlace => "pick_place",
            Task::Play => "play",
        }
    }

    /// Parses [`Task::name`] (any of [`Task::GENERATED`]).
    pub fn parse(s: &str) -> Option<Task> {
        Task::GENERATED.into_iter().find(|x| x.name() == s)
    }

    /// Parses the name of a task with a goal ([`Task::ALL`]), or says what
    /// was expected (a flag's parser).
    pub fn parse_goal_task(s: &str) -> Result<Task, String> {
        Task::parse(s)
            .filter(|t| Task::ALL.contains(t))
            .ok_or_else(|| format!("unknown task {s:?}: expected reach, push or pick_place"))
    }

    /// The natural-language task string stored in `meta/tasks.parquet`.
    pub fn description(self) -> &'static str {
        match self {
            Task::Reach => "reach to a point above the table",
            Task::Push => "push the object across the table",
            Task::PickPlace => "pick up the object and place it elsewhere",
            Task::Play => "move the arm freely over the table",
        }
    }
}

/// Options of the synthetic world.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SynthConfig {
    /// Built-in robot name (`franka`, `dual-arm`).
    pub robot: String,
    /// Frames per clip.
    pub frames: usize,
    /// Image width (pixels, even).
    pub width: u32,
    /// Image height (pixels, even).
    pub height: u32,
    /// Frames per second of the clips.
    pub fps: u32,
    /// Dataset seed.
    pub seed: u64,
    /// Tasks, assigned round-robin over the dataset's episodes.
    pub tasks: Vec<Task>,
    /// Episodes per split, in [`Split::ALL`] order.
    pub episodes_per_split: [usize; 4],
    /// Perturbed (and so sometimes failed) demonstrations in the `train`
    /// split ([`Perturbation`]; none by default).
    pub perturb: Perturbation,
    /// What simulates and renders the episodes.
    pub engine: Engine,
}

/// What simulates and renders the synthetic world's episodes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Engine {
    /// This project's world: kinematic contact rules, a flat-shaded software
    /// renderer (fast; the tests' fixture).
    #[default]
    Builtin,
    /// MuJoCo ([`mujoco`]): physics with contact and friction, OpenGL
    /// rendering with lights and shadows, the robot's real meshes.
    Mujoco,
}

impl Engine {
    /// Every engine's name.
    pub const NAMES: &'static str = "builtin, mujoco";

    /// The engine's name.
    pub fn name(self) -> &'static str {
        match self {
            Self::Builtin => "builtin",
            Self::Mujoco => "mujoco",
        }
    }
}

impl std::fmt::Display for Engine {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for Engine {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        match s {
            "builtin" => Ok(Self::Builtin),
            "mujoco" => Ok(Self::Mujoco),
            _ => Err(format!(
                "unknown engine {s:?}: expected one of {}",
                Self::NAMES
            )),
        }
    }
}

impl Default for SynthConfig {
    fn default() -> Self {
        Self {
            robot: "franka".into(),
            frames: 25,
            width: 96,
            height: 64,
            fps: 10,
            seed: 0,
            tasks: Task::ALL.to_vec(),
            episodes_per_split: [8, 2, 2, 2],
            perturb: Perturbation::default(),
            engine: Engine::Builtin,
        }
    }
}

/// The most frames an episode may have.
pub const MAX_FRAMES: usize = 10_000;
/// The most pixels a side of the rendered video may have.
pub const MAX_SIDE: u32 = 4096;
/// The most episodes a split may have.
pub const MAX_EPISODES: usize = 100_000;

impl SynthConfig {
    /// Checks the configuration.
    pub fn validate(&self) -> Result<(), SynthError> {
        let bad = |m: String| Err(SynthError::Config(m));
        if self.frames < 2 {
            return bad(format!("--frames {} must be at least 2", self.frames));
        }
        if self.width < 16 || self.height < 16 || self.width % 2 != 0 || self.height % 2 != 0 {
            return bad(format!(
                "resolution {}x{} must be even and at least 16x16 (H.264 4:2:0)",
                self.width, self.height
            ));
        }
        if self.frames > MAX_FRAMES {
            return bad(format!(
                "--frames {}: at most {MAX_FRAMES} frames per episode",
                self.frames
            ));
        }
        if self.width > MAX_SIDE || self.height > MAX_SIDE {
            return bad(format!(
                "resolution {}x{}: at most {MAX_SIDE} pixels a side",
                self.width, self.height
            ));
        }
        if let Some(n) = self.episodes_per_split.iter().find(|&&n| n > MAX_EPISODES) {
            return bad(format!(
                "--episodes-per-split {n}: at most {MAX_EPISODES} episodes per split"
            ));
        }
        if self.fps == 0 {
            return bad("fps must be > 0".into());
        }
        if self.tasks.is_empty() {
            return bad("at least one task is needed".into());
        }
        self.perturb.validate()
    }
}

/// The episodes a configuration produces: `(split, index in split, task)`.
pub fn plan(config: &SynthConfig) -> Vec<(Split, usize, Task)> {
    let mut out = Vec::new();
    for (s, split) in Split::ALL.into_iter().enumerate() {
        for i in 0..config.episodes_per_split[s] {
            // Round-robin over the dataset, so small splits get every task too.
            let task = config.tasks[out.len() % config.tasks.len()];
            out.push((split, i, task));
        }
    }
    out
}

/// The episode seed from the dataset seed, split and index.
pub fn episode_seed(seed: u64, split: Split, index: usize) -> u64 {
    let mut h = seed ^ split.stream_id().wrapping_mul(0xA076_1D64_78BD_642F);
    h = h.wrapping_add((index as u64).wrapping_mul(0xE703_7ED1_A0B4_28DB));
    h ^= h >> 32;
    h = h.wrapping_mul(bridgev2w_io::seed::GOLDEN_GAMMA);
    h ^ (h >> 29)
}
