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

use crate::render::{camera_depth_m, draw_mesh, pixel_ray_world, Canvas, Light};
use bridgev2w_embodiment::actions::{actions_to_joints, ActionError, Trajectory};
use bridgev2w_embodiment::camera::{Camera, CameraError, Intrinsics};
use bridgev2w_embodiment::embodiment::{Embodiment, EmbodimentError};
use bridgev2w_embodiment::kinematics::{xyz_rpy_from_pose, IkOptions};
use bridgev2w_embodiment::masks::render_trajectory_labels;
use bridgev2w_embodiment::mesh::TriMesh;
use nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector2, Vector3};
use rand::{Rng, SeedableRng};
use rand_chacha::ChaCha8Rng;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

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
    /// Built-in robot name (`franka`, `agibot-g1`).
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
        Ok(())
    }
}

/// A procedural texture.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Pattern {
    /// One colour.
    Solid,
    /// Two-colour checkerboard with squares of `period` (metres on the table, radians on the background).
    Checker {
        /// Square size.
        period: f64,
    },
    /// Two-colour stripes of `period` at `angle_rad`.
    Stripes {
        /// Stripe period.
        period: f64,
        /// Stripe direction.
        angle_rad: f64,
    },
    /// Smooth value noise of feature size `period`, blending the two colours.
    Noise {
        /// Feature size.
        period: f64,
        /// Noise seed.
        seed: u32,
    },
    /// Dots of the second colour on the first.
    Dots {
        /// Dot spacing.
        period: f64,
    },
}

impl Pattern {
    /// Blend weight of the second colour at `(x, y)`, in `[0, 1]`.
    pub fn weight(&self, x: f64, y: f64) -> f64 {
        match *self {
            Pattern::Solid => 0.0,
            Pattern::Checker { period } => {
                let (i, j) = ((x / period).floor() as i64, (y / period).floor() as i64);
                ((i + j).rem_euclid(2)) as f64
            }
            Pattern::Stripes { period, angle_rad } => {
                let s = x * angle_rad.cos() + y * angle_rad.sin();
                if (s / period).rem_euclid(1.0) < 0.5 {
                    0.0
                } else {
                    1.0
                }
            }
            Pattern::Noise { period, seed } => value_noise(x / period, y / period, seed),
            Pattern::Dots { period } => {
                let fx = (x / period).rem_euclid(1.0) - 0.5;
                let fy = (y / period).rem_euclid(1.0) - 0.5;
                if fx * fx + fy * fy < 0.09 {
                    1.0
                } else {
                    0.0
                }
            }
        }
    }

    /// The pattern family name (palettes list allowed families).
    pub fn family(&self) -> &'static str {
        match self {
            Pattern::Solid => "solid",
            Pattern::Checker { .. } => "checker",
            Pattern::Stripes { .. } => "stripes",
            Pattern::Noise { .. } => "noise",
            Pattern::Dots { .. } => "dots",
        }
    }
}

fn hash2(i: i64, j: i64, seed: u32) -> f64 {
    let mut h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
        ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
        ^ u64::from(seed).wrapping_mul(0x1656_67B1_9E37_79F9);
    h ^= h >> 31;
    h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
    h ^= h >> 29;
    (h >> 11) as f64 / (1u64 << 53) as f64
}

fn value_noise(x: f64, y: f64, seed: u32) -> f64 {
    let (i, j) = (x.floor(), y.floor());
    let (fx, fy) = (x - i, y - j);
    let (sx, sy) = (fx * fx * (3.0 - 2.0 * fx), fy * fy * (3.0 - 2.0 * fy));
    let (i, j) = (i as i64, j as i64);
    let a = hash2(i, j, seed);
    let b = hash2(i + 1, j, seed);
    let c = hash2(i, j + 1, seed);
    let d = hash2(i + 1, j + 1, seed);
    let top = a + (b - a) * sx;
    let bottom = c + (d - c) * sx;
    top + (bottom - top) * sy
}

/// Camera sampling region: the camera sits at `distance` from the look-at
/// point (the workspace centre), at `azimuth` around the world z axis
/// (0 = in front of the robot, on the +x side, looking back at it) and
/// `elevation` above the table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CameraRegion {
    /// Allowed azimuth intervals (degrees), union.
    pub azimuth_deg: Vec<[f64; 2]>,
    /// Elevation interval (degrees).
    pub elevation_deg: [f64; 2],
    /// Distance interval (metres).
    pub distance_m: [f64; 2],
    /// Focal length as a fraction of the image width.
    pub focal_over_width: [f64; 2],
    /// Look-at jitter around the workspace centre (metres, per axis).
    pub target_jitter_m: f64,
}

impl CameraRegion {
    /// Whether `azimuth_deg` lies in the region.
    pub fn contains_azimuth(&self, azimuth_deg: f64) -> bool {
        self.azimuth_deg
            .iter()
            .any(|r| (r[0]..=r[1]).contains(&azimuth_deg))
    }
}

/// Scene appearance and object-layout palette of a split.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ScenePalette {
    /// Palette name.
    pub name: String,
    /// Table colours (sRGB 0..255), pairs for two-colour patterns.
    pub table_colors: Vec<[[u8; 3]; 2]>,
    /// Table pattern families.
    pub table_patterns: Vec<String>,
    /// Background colours, pairs.
    pub background_colors: Vec<[[u8; 3]; 2]>,
    /// Background pattern families.
    pub background_patterns: Vec<String>,
    /// Object colours.
    pub object_colors: Vec<[u8; 3]>,
    /// Object layout region relative to the workspace centre: `[x_min, x_max]` (metres).
    pub layout_dx_m: [f64; 2],
    /// `[y_min, y_max]` relative to the workspace centre (metres).
    pub layout_dy_m: [f64; 2],
}

/// The definition of one split (written into the dataset metadata).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SplitSpec {
    /// The split.
    pub split: Split,
    /// Camera region.
    pub camera: CameraRegion,
    /// Scene palette.
    pub scene: ScenePalette,
}

fn training_camera() -> CameraRegion {
    CameraRegion {
        azimuth_deg: vec![[-75.0, 35.0]],
        elevation_deg: [25.0, 50.0],
        distance_m: [1.0, 1.35],
        focal_over_width: [0.85, 1.1],
        target_jitter_m: 0.04,
    }
}

fn training_palette() -> ScenePalette {
    ScenePalette {
        name: "train".into(),
        table_colors: vec![
            [[150, 111, 72], [120, 86, 55]],
            [[180, 180, 176], [140, 140, 138]],
            [[196, 170, 128], [170, 140, 100]],
            [[90, 90, 96], [70, 70, 76]],
        ],
        table_patterns: vec!["solid".into(), "checker".into(), "stripes".into()],
        background_colors: vec![
            [[210, 205, 195], [185, 180, 170]],
            [[150, 170, 190], [120, 140, 160]],
            [[200, 190, 160], [170, 160, 130]],
        ],
        background_patterns: vec!["solid".into(), "stripes".into()],
        object_colors: vec![[200, 40, 40], [40, 160, 60], [40, 80, 200], [230, 200, 40]],
        layout_dx_m: [-0.10, 0.10],
        layout_dy_m: [-0.18, 0.06],
    }
}

fn unseen_palette() -> ScenePalette {
    ScenePalette {
        name: "unseen_scene".into(),
        table_colors: vec![
            [[60, 110, 70], [40, 85, 50]],
            [[70, 80, 150], [50, 60, 120]],
            [[140, 70, 120], [110, 50, 95]],
        ],
        table_patterns: vec!["noise".into(), "dots".into()],
        background_colors: vec![[[90, 50, 40], [60, 35, 30]], [[40, 90, 90], [25, 65, 65]]],
        background_patterns: vec!["noise".into(), "checker".into()],
        object_colors: vec![[240, 120, 20], [150, 60, 200], [20, 200, 200]],
        layout_dx_m: [-0.10, 0.10],
        layout_dy_m: [0.09, 0.20],
    }
}

/// The four split definitions. Train and test share distributions;
/// `unseen_camera` samples azimuths in a region disjoint from training's;
/// `unseen_scene` uses a palette (colours, patterns) and object-layout region
/// disjoint from training's.
pub fn split_specs() -> Vec<SplitSpec> {
    Split::ALL
        .into_iter()
        .map(|split| {
            let mut camera = training_camera();
            let mut scene = training_palette();
            match split {
                Split::UnseenCamera => camera.azimuth_deg = vec![[50.0, 85.0]],
                Split::UnseenScene => scene = unseen_palette(),
                Split::Train | Split::Test => {}
            }
            SplitSpec {
                split,
                camera,
                scene,
            }
        })
        .collect()
}

/// Per-robot placement of the table and workspace, derived from the home
/// end-effector poses.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneFrame {
    /// Height of the table top (world z, metres).
    pub table_z_m: f64,
    /// Table extent in x (metres).
    pub table_x_m: [f64; 2],
    /// Table extent in y (metres).
    pub table_y_m: [f64; 2],
    /// Workspace centre on the table (world frame, metres).
    pub workspace_center_m: [f64; 3],
}

impl SceneFrame {
    /// The scene frame for an embodiment: the workspace centre lies in front
    /// of the home end effector(s); the table top sits below them.
    pub fn for_embodiment(e: &Embodiment) -> SceneFrame {
        let poses = e.robot.link_poses(&e.home);
        let n = e.end_effectors.len().max(1) as f64;
        let mut c = Vector3::zeros();
        for ee in &e.end_effectors {
            c += poses[ee.link].translation.vector;
        }
        c /= n;
        // A single arm stands on the table (base at z = 0); a dual-arm
        // torso (arms hanging at home) faces a table at waist height in
        // front of it.
        let dual = e.end_effectors.len() > 1;
        let table_z_m = if dual { c.z + 0.275 } else { 0.0 };
        let cx = if dual { c.x + 0.38 } else { c.x + 0.15 };
        let x_min = if dual { cx - 0.2 } else { cx - 0.55 };
        SceneFrame {
            table_z_m,
            table_x_m: [x_min, cx + 0.45],
            table_y_m: [c.y - 0.75, c.y + 0.75],
            workspace_center_m: [cx, c.y, table_z_m],
        }
    }
}

/// A movable object's shape.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum Shape {
    /// A box with full side lengths (metres).
    Box {
        /// `[x, y, z]` sizes.
        size_m: [f64; 3],
    },
    /// An upright cylinder.
    Cylinder {
        /// Radius.
        radius_m: f64,
        /// Height.
        height_m: f64,
    },
}

impl Shape {
    /// Height (metres).
    pub fn height_m(&self) -> f64 {
        match *self {
            Shape::Box { size_m } => size_m[2],
            Shape::Cylinder { height_m, .. } => height_m,
        }
    }

    /// Radius of the circular footprint used by the contact rules (metres).
    pub fn footprint_radius_m(&self) -> f64 {
        match *self {
            Shape::Box { size_m } => 0.5 * size_m[0].max(size_m[1]),
            Shape::Cylinder { radius_m, .. } => radius_m,
        }
    }

    /// The shape's triangle mesh, centred on its origin.
    pub fn mesh(&self) -> TriMesh {
        match *self {
            Shape::Box { size_m } => {
                TriMesh::cuboid([size_m[0] as f32, size_m[1] as f32, size_m[2] as f32])
            }
            Shape::Cylinder { radius_m, height_m } => {
                TriMesh::cylinder(radius_m as f32, height_m as f32, 20)
            }
        }
    }
}

/// A movable object's pose: bottom centre on the table and yaw.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ObjectPose {
    /// Bottom-centre position (world frame, metres).
    pub position_m: [f64; 3],
    /// Rotation about world z (radians).
    pub yaw_rad: f64,
}

impl ObjectPose {
    fn world_from_object_center(&self, height_m: f64) -> Isometry3<f64> {
        Isometry3::from_parts(
            Translation3::new(
                self.position_m[0],
                self.position_m[1],
                self.position_m[2] + 0.5 * height_m,
            ),
            UnitQuaternion::from_axis_angle(&Vector3::z_axis(), self.yaw_rad),
        )
    }
}

/// A movable object of an episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneObject {
    /// Shape.
    pub shape: Shape,
    /// sRGB colour.
    pub color: [u8; 3],
    /// Initial pose.
    pub initial: ObjectPose,
}

/// The appearance chosen for one episode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SceneLook {
    /// Table colour pair.
    pub table_colors: [[u8; 3]; 2],
    /// Table pattern.
    pub table_pattern: Pattern,
    /// Background colour pair.
    pub background_colors: [[u8; 3]; 2],
    /// Background pattern.
    pub background_pattern: Pattern,
    /// Unit direction towards the light (world frame).
    pub to_light_world: [f64; 3],
}

/// What the contact rules did to one object in one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Contact {
    /// No contact.
    None,
    /// Pushed by the fingers/hand.
    Pushed,
    /// Grasped this frame.
    Grasped,
    /// Carried in the closed gripper.
    Carried,
    /// Released this frame (dropped onto the table).
    Released,
}

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
    /// Per frame: end-effector actions, 7 per arm.
    pub actions: Vec<Vec<f64>>,
    /// Per frame: joint positions (URDF actuated order).
    pub joints: Vec<Vec<f64>>,
    /// Per frame, per object: pose.
    pub object_poses: Vec<Vec<ObjectPose>>,
    /// Per frame, per object: contact event.
    pub contacts: Vec<Vec<Contact>>,
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
    h = h.wrapping_mul(0x9E37_79B9_7F4A_7C15);
    h ^ (h >> 29)
}

fn srgb_to_linear(c: [u8; 3]) -> [f32; 3] {
    c.map(|v| (f32::from(v) / 255.0).powf(2.2))
}

fn linear_to_srgb(c: [f32; 3]) -> [f32; 3] {
    c.map(|v| v.clamp(0.0, 1.0).powf(1.0 / 2.2))
}

fn mix(a: [f32; 3], b: [f32; 3], w: f32) -> [f32; 3] {
    [
        a[0] + (b[0] - a[0]) * w,
        a[1] + (b[1] - a[1]) * w,
        a[2] + (b[2] - a[2]) * w,
    ]
}

/// Link colours (sRGB), by link index.
const LINK_COLORS: [[u8; 3]; 6] = [
    [235, 235, 232],
    [60, 62, 68],
    [200, 200, 205],
    [245, 245, 245],
    [110, 112, 120],
    [225, 225, 220],
];

fn jitter_color(rng: &mut ChaCha8Rng, c: [u8; 3]) -> [u8; 3] {
    c.map(|v| (f64::from(v) + rng.gen_range(-8.0..=8.0)).clamp(0.0, 255.0) as u8)
}

fn pick_pattern(rng: &mut ChaCha8Rng, families: &[String], scale: f64) -> Pattern {
    let f = families
        .get(rng.gen_range(0..families.len().max(1)))
        .map(String::as_str)
        .unwrap_or("solid");
    match f {
        "checker" => Pattern::Checker {
            period: scale * rng.gen_range(0.6..1.4),
        },
        "stripes" => Pattern::Stripes {
            period: scale * rng.gen_range(0.6..1.4),
            angle_rad: rng.gen_range(0.0..PI),
        },
        "noise" => Pattern::Noise {
            period: scale * rng.gen_range(0.5..1.5),
            seed: rng.gen(),
        },
        "dots" => Pattern::Dots {
            period: scale * rng.gen_range(0.6..1.4),
        },
        _ => Pattern::Solid,
    }
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
    held: Option<(usize, Isometry3<f64>)>,
    /// Contact points (fingertips, hand) of the previous frame (world frame).
    prev_points: Option<[Point3<f64>; 3]>,
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
    home_tcp: Vec<Isometry3<f64>>,
}

/// Contact geometry of the gripper (metres).
const FINGER_RADIUS_M: f64 = 0.008;
/// Horizontal tolerance for a grasp (TCP to object axis).
const GRASP_RADIUS_M: f64 = 0.03;

impl World {
    /// The world for `config.robot`.
    pub fn new(config: &SynthConfig) -> Result<World, SynthError> {
        config.validate()?;
        let embodiment = Embodiment::builtin(&config.robot)?;
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
            let traj = Trajectory::new("synth", actions.clone())?;
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
            let worst = residuals
                .iter()
                .map(|r| r.position_error_m)
                .fold(0.0, f64::max);
            let worst_rot = residuals
                .iter()
                .map(|r| r.rotation_error_rad)
                .fold(0.0, f64::max);
            last_residual = worst;
            if worst > 0.01 || worst_rot > 5f64.to_radians() {
                continue;
            }
            let mut meta = meta;
            meta.max_ik_residual_m = worst;
            return Ok(self.finish(meta, camera, actions, joints));
        }
        Err(SynthError::Unreachable {
            split: split.name().into(),
            episode: index,
            task: task.name().into(),
            attempts: ATTEMPTS,
            residual_mm: last_residual * 1e3,
        })
    }

    fn sample(
        &self,
        split: Split,
        index: usize,
        task: Task,
        seed: u64,
        rng: &mut ChaCha8Rng,
    ) -> Result<(EpisodeMeta, Camera, Vec<Vec<f64>>), SynthError> {
        let spec = self.spec(split);
        let c = Vector3::from(self.frame.workspace_center_m);
        // Camera.
        let region = &spec.camera.azimuth_deg[rng.gen_range(0..spec.camera.azimuth_deg.len())];
        let az = rng.gen_range(region[0]..=region[1]);
        let el = rng.gen_range(spec.camera.elevation_deg[0]..=spec.camera.elevation_deg[1]);
        let dist = rng.gen_range(spec.camera.distance_m[0]..=spec.camera.distance_m[1]);
        let f = rng.gen_range(spec.camera.focal_over_width[0]..=spec.camera.focal_over_width[1]);
        let j = spec.camera.target_jitter_m;
        let target = Point3::new(
            c.x + rng.gen_range(-j..=j),
            c.y + rng.gen_range(-j..=j),
            c.z + 0.2 + rng.gen_range(-j..=j),
        );
        let (azr, elr) = (az.to_radians(), el.to_radians());
        let eye =
            target + dist * Vector3::new(elr.cos() * azr.cos(), elr.cos() * azr.sin(), elr.sin());
        let intrinsics = Intrinsics::centered(
            f * f64::from(self.config.width),
            self.config.width,
            self.config.height,
        );
        let camera = Camera::look_at(intrinsics, eye, target, Vector3::z())?;

        // Look.
        let pal = &spec.scene;
        let tc = pal.table_colors[rng.gen_range(0..pal.table_colors.len())];
        let bc = pal.background_colors[rng.gen_range(0..pal.background_colors.len())];
        let look = SceneLook {
            table_colors: [jitter_color(rng, tc[0]), jitter_color(rng, tc[1])],
            table_pattern: pick_pattern(rng, &pal.table_patterns, 0.08),
            background_colors: [jitter_color(rng, bc[0]), jitter_color(rng, bc[1])],
            background_pattern: pick_pattern(rng, &pal.background_patterns, 0.25),
            to_light_world: {
                let a: f64 = rng.gen_range(0.0..2.0 * PI);
                let e: f64 = rng.gen_range(0.9..1.3);
                [e.cos() * a.cos(), e.cos() * a.sin(), e.sin()]
            },
        };

        // Objects: 1..=3, non-overlapping, in the layout region.
        let n_obj = rng.gen_range(1..=3usize);
        let mut objects: Vec<SceneObject> = Vec::new();
        let mut tries = 0;
        while objects.len() < n_obj && tries < 200 {
            tries += 1;
            let shape = if rng.gen_bool(0.5) {
                Shape::Box {
                    size_m: [
                        rng.gen_range(0.035..0.05),
                        rng.gen_range(0.035..0.05),
                        rng.gen_range(0.04..0.07),
                    ],
                }
            } else {
                Shape::Cylinder {
                    radius_m: rng.gen_range(0.018..0.028),
                    height_m: rng.gen_range(0.045..0.08),
                }
            };
            let x = c.x + rng.gen_range(pal.layout_dx_m[0]..=pal.layout_dx_m[1]);
            let y = c.y + rng.gen_range(pal.layout_dy_m[0]..=pal.layout_dy_m[1]);
            let r = shape.footprint_radius_m();
            let clear = objects.iter().all(|o| {
                let d = Vector2::new(o.initial.position_m[0] - x, o.initial.position_m[1] - y);
                d.norm() > r + o.shape.footprint_radius_m() + 0.06
            });
            if !clear {
                continue;
            }
            let base = pal.object_colors[rng.gen_range(0..pal.object_colors.len())];
            objects.push(SceneObject {
                shape,
                color: jitter_color(rng, base),
                initial: ObjectPose {
                    position_m: [x, y, self.frame.table_z_m],
                    yaw_rad: rng.gen_range(-PI..PI),
                },
            });
        }

        // Reach target: a random point above the table.
        let reach = Vector3::new(
            c.x + rng.gen_range(-0.1..=0.1),
            c.y + rng.gen_range(-0.2..=0.2),
            self.frame.table_z_m + rng.gen_range(0.1..=0.18),
        );
        // Acting arm: the one whose home TCP is nearest the task's focus.
        let focus = match (task, objects.first()) {
            (Task::Reach, _) | (_, None) => reach.xy(),
            (_, Some(o)) => Vector2::new(o.initial.position_m[0], o.initial.position_m[1]),
        };
        let arm = (0..self.home_tcp.len())
            .min_by(|&a, &b| {
                let da = (self.home_tcp[a].translation.vector.xy() - focus).norm();
                let db = (self.home_tcp[b].translation.vector.xy() - focus).norm();
                da.total_cmp(&db)
            })
            .unwrap_or(0);

        let actions = self.script(task, arm, &objects, reach, rng);
        let meta = EpisodeMeta {
            split,
            index_in_split: index,
            task,
            seed,
            arm,
            camera_azimuth_deg: az,
            camera_elevation_deg: el,
            camera_distance_m: dist,
            look,
            objects,
            max_ik_residual_m: 0.0,
        };
        Ok((meta, camera, actions))
    }

    /// Scripted end-effector actions of `arm`; other arms hold their home pose.
    fn script(
        &self,
        task: Task,
        arm: usize,
        objects: &[SceneObject],
        reach: Vector3<f64>,
        rng: &mut ChaCha8Rng,
    ) -> Vec<Vec<f64>> {
        let tz = self.frame.table_z_m;
        let c = Vector3::from(self.frame.workspace_center_m);
        let home = self.home_tcp[arm];
        let home_p = home.translation.vector;
        // Top-down orientation: the home orientation turned about world z.
        let yaw0: f64 = rng.gen_range(-0.4..0.4);
        let mut noise = |s: f64| rng.gen_range(-s..=s);
        // Keyframes: (time fraction, position, extra yaw, gripper).
        let mut keys: Vec<(f64, Vector3<f64>, f64, f64)> = vec![(0.0, home_p, 0.0, 0.0)];
        let above = 0.13;
        match (task, objects.first()) {
            (Task::PickPlace, Some(o)) => {
                let p = Vector3::from(o.initial.position_m);
                let grasp_z = tz + (0.5 * o.shape.height_m()).max(0.022);
                let dir = noise(PI);
                let dist = 0.10 + noise(0.03).abs();
                let place = Vector3::new(
                    (p.x + dist * dir.cos()).clamp(c.x - 0.15, c.x + 0.15),
                    (p.y + dist * dir.sin()).clamp(c.y - 0.22, c.y + 0.22),
                    grasp_z,
                );
                let gx = p.x + noise(0.004);
                let gy = p.y + noise(0.004);
                let y1 = noise(0.5);
                keys.extend([
                    (0.25, Vector3::new(gx, gy, tz + above), y1, 0.0),
                    (0.40, Vector3::new(gx, gy, grasp_z), y1, 0.0),
                    (0.48, Vector3::new(gx, gy, grasp_z), y1, 1.0),
                    (0.62, Vector3::new(gx, gy, tz + 0.15 + noise(0.02)), y1, 1.0),
                    (
                        0.78,
                        Vector3::new(place.x, place.y, tz + 0.12),
                        y1 + noise(0.3),
                        1.0,
                    ),
                    (0.86, place, y1, 1.0),
                    (0.92, place, y1, 0.0),
                    (
                        1.0,
                        Vector3::new(place.x, place.y, tz + 0.12 + noise(0.02)),
                        y1,
                        0.0,
                    ),
                ]);
            }
            (Task::Push, Some(o)) => {
                let p = Vector3::from(o.initial.position_m);
                let dir = noise(PI);
                let u = Vector3::new(dir.cos(), dir.sin(), 0.0);
                let r = o.shape.footprint_radius_m() + FINGER_RADIUS_M;
                let push_z = tz + 0.02 + noise(0.003);
                let start = Vector3::new(p.x, p.y, push_z) - u * (r + 0.04);
                let len = 0.08 + noise(0.03).abs();
                let end = Vector3::new(p.x, p.y, push_z) + u * (len - r);
                let y1 = noise(0.4);
                keys.extend([
                    (0.3, Vector3::new(start.x, start.y, tz + above), y1, 1.0),
                    (0.45, start, y1, 1.0),
                    (0.85, end, y1, 1.0),
                    (
                        1.0,
                        Vector3::new(end.x, end.y, tz + above + noise(0.02)),
                        y1,
                        1.0,
                    ),
                ]);
            }
            (Task::Play, _) => {
                // 3 to 5 waypoints at jittered, increasing times; about 40%
                // at an object (grasp height), the rest anywhere over the
                // table; the gripper flips with probability 0.4 at each.
                let n_way = 3 + ((noise(1.0) + 1.0) * 1.5).floor().min(2.0) as usize;
                let (mut g, mut yaw) = (0.0, 0.0);
                for i in 1..=n_way {
                    let t = if i == n_way {
                        1.0
                    } else {
                        (i as f64 + noise(0.25)) / n_way as f64
                    };
                    let p = if !objects.is_empty() && noise(1.0) > 0.2 {
                        let k = (((noise(0.5) + 0.5) * objects.len() as f64) as usize)
                            .min(objects.len() - 1);
                        let o = &objects[k];
                        let z = tz + (0.5 * o.shape.height_m()).max(0.022) + noise(0.015).abs();
                        let q = o.initial.position_m;
                        Vector3::new(q[0] + noise(0.02), q[1] + noise(0.02), z)
                    } else {
                        Vector3::new(
                            c.x + noise(0.15),
                            c.y + noise(0.22),
                            tz + 0.115 + noise(0.085),
                        )
                    };
                    if noise(1.0) > 0.2 {
                        g = 1.0 - g;
                    }
                    yaw += noise(0.4);
                    keys.push((t, p, yaw, g));
                }
            }
            _ => {
                // Reach (or no object): a random point above the table.
                let target = reach;
                let mid = 0.5 * (home_p + target) + Vector3::new(noise(0.03), noise(0.03), 0.05);
                let g = if noise(1.0) > 0.0 { 1.0 } else { 0.0 };
                keys.extend([
                    (0.45, mid, noise(0.3), 0.5 * g),
                    (0.85, target, noise(0.5), g),
                    (1.0, target, 0.0, g),
                ]);
            }
        }
        let frames = self.config.frames;
        let n_arms = self.home_tcp.len();
        let mut rows = Vec::with_capacity(frames);
        for f in 0..frames {
            let t = f as f64 / (frames - 1) as f64;
            let k = keys
                .windows(2)
                .position(|w| t <= w[1].0)
                .unwrap_or(keys.len() - 2);
            let (a, b) = (keys[k], keys[k + 1]);
            let s = ((t - a.0) / (b.0 - a.0).max(1e-9)).clamp(0.0, 1.0);
            let s = s * s * (3.0 - 2.0 * s);
            let mut p = a.1 + (b.1 - a.1) * s;
            // Small per-frame action noise, not at the start frame.
            if f > 0 {
                p += Vector3::new(noise(0.0015), noise(0.0015), noise(0.0015));
            }
            let yaw = yaw0 * (t.min(0.25) * 4.0) + a.2 + (b.2 - a.2) * s;
            let g = a.3 + (b.3 - a.3) * s;
            let mut row = Vec::with_capacity(7 * n_arms);
            for (ai, h) in self.home_tcp.iter().enumerate() {
                if ai == arm {
                    let rot =
                        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw) * home.rotation;
                    let v = xyz_rpy_from_pose(&Isometry3::from_parts(Translation3::from(p), rot));
                    row.extend_from_slice(&v);
                    row.push(g.clamp(0.0, 1.0));
                } else {
                    row.extend_from_slice(&xyz_rpy_from_pose(h));
                    row.push(0.0);
                }
            }
            rows.push(row);
        }
        rows
    }

    /// Simulates the objects and renders the clip.
    fn finish(
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
            actions,
            joints,
            object_poses,
            contacts,
        }
    }

    /// Kinematic contact rules over the clip, driven by the achieved joints.
    fn simulate(
        &self,
        meta: &EpisodeMeta,
        actions: &[Vec<f64>],
        joints: &[Vec<f64>],
    ) -> (Vec<Vec<ObjectPose>>, Vec<Vec<Contact>>) {
        let mut state = SceneState {
            joints: joints.first().cloned().unwrap_or_default(),
            object_poses: meta.objects.iter().map(|o| o.initial).collect(),
            held: None,
            prev_points: None,
            prev_gripper: 0.0,
        };
        let mut all_poses = Vec::with_capacity(joints.len());
        let mut all_contacts = Vec::with_capacity(joints.len());
        for (f, q) in joints.iter().enumerate() {
            let g = actions[f][7 * meta.arm + 6];
            let contacts = self.contact_step(meta, &mut state, q, g);
            all_poses.push(state.object_poses.clone());
            all_contacts.push(contacts);
        }
        (all_poses, all_contacts)
    }

    /// One frame of the kinematic contact rules: the robot is at joints `q`
    /// with gripper command `g`; updates `state` (objects, grasp, joints).
    fn contact_step(
        &self,
        meta: &EpisodeMeta,
        state: &mut SceneState,
        q: &[f64],
        g: f64,
    ) -> Vec<Contact> {
        let robot = &self.embodiment.robot;
        let ee = &self.embodiment.end_effectors[meta.arm];
        let tz = self.frame.table_z_m;
        let poses = &mut state.object_poses;
        let held = &mut state.held;
        let prev_g = state.prev_gripper;
        let prev_points = state.prev_points;
        {
            let tcp = robot.link_pose(ee.link, q);
            let mut contacts = vec![Contact::None; poses.len()];
            // Contact points: the two fingertips (either side of the TCP
            // along its y axis, at the finger opening) and the hand centre
            // 6 cm back along the approach axis.
            let half_open_m = ee.gripper_dof.map_or(0.0, |d| q[d].abs());
            let points = [
                tcp * Point3::new(0.0, half_open_m, 0.0),
                tcp * Point3::new(0.0, -half_open_m, 0.0),
                tcp * Point3::new(0.0, 0.0, -0.06),
            ];
            let tcp_point = Point3::from(tcp.translation.vector);
            // An object whose axis lies between the fingers is in the grasp
            // region: closing fingers squeeze it instead of pushing it.
            let between_fingers = |p: &ObjectPose, h: f64| {
                let d = (tcp_point.xy() - Point3::from(p.position_m).xy()).norm();
                d < GRASP_RADIUS_M
                    && tcp_point.z > p.position_m[2]
                    && tcp_point.z < p.position_m[2] + h + 0.01
            };
            // Release.
            if let Some((i, _)) = *held {
                if g < 0.5 {
                    *held = None;
                    poses[i].position_m[2] = tz;
                    contacts[i] = Contact::Released;
                }
            }
            // Carry.
            if let Some((i, tcp_from_obj)) = *held {
                let w = tcp * tcp_from_obj;
                let h = meta.objects[i].shape.height_m();
                let (_, _, yaw) = w.rotation.euler_angles();
                let t = w.translation.vector;
                poses[i] = ObjectPose {
                    position_m: [t.x, t.y, (t.z - 0.5 * h).max(tz)],
                    yaw_rad: yaw,
                };
                contacts[i] = Contact::Carried;
            }
            // Grasp: the gripper closes with the TCP inside an object.
            if held.is_none() && prev_g < 0.5 && g >= 0.5 {
                for (i, o) in meta.objects.iter().enumerate() {
                    let p = &poses[i];
                    let h = o.shape.height_m();
                    if between_fingers(p, h) {
                        let w = p.world_from_object_center(h);
                        *held = Some((i, tcp.inverse() * w));
                        contacts[i] = Contact::Grasped;
                        break;
                    }
                }
            }
            // Push: fingers/hand inside an object's footprint.
            for (i, o) in meta.objects.iter().enumerate() {
                if held.map(|(h, _)| h) == Some(i) || contacts[i] != Contact::None {
                    continue;
                }
                let h = o.shape.height_m();
                let r = o.shape.footprint_radius_m() + FINGER_RADIUS_M;
                let squeezed = half_open_m > 1e-3 && between_fingers(&poses[i], h);
                for (k, pt) in points.iter().enumerate() {
                    if squeezed && k < 2 {
                        continue;
                    }
                    let p = &mut poses[i];
                    if pt.z < p.position_m[2] - 0.01 || pt.z > p.position_m[2] + h + 0.005 {
                        continue;
                    }
                    let d = Vector2::new(p.position_m[0] - pt.x, p.position_m[1] - pt.y);
                    if d.norm() >= r {
                        continue;
                    }
                    let motion = prev_points
                        .map(|pp| (pt - pp[k]).xy())
                        .unwrap_or_else(Vector2::zeros);
                    let u = if motion.norm() > 1e-4 {
                        motion.normalize()
                    } else if d.norm() > 1e-9 {
                        d.normalize()
                    } else {
                        Vector2::x()
                    };
                    let along = d.dot(&u);
                    let perp = d - u * along;
                    let new_along = (r * r - perp.norm_squared()).max(0.0).sqrt();
                    if new_along > along {
                        let moved = Vector2::new(pt.x, pt.y) + perp + u * new_along;
                        p.position_m[0] = moved.x;
                        p.position_m[1] = moved.y;
                        contacts[i] = Contact::Pushed;
                    }
                }
            }
            state.prev_points = Some(points);
            state.prev_gripper = g;
            state.joints = q.to_vec();
            contacts
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
            &state.joints,
            &opts,
            true,
        )?;
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

    /// Renders the scene in `state` (interleaved RGB8).
    pub fn render_state(&self, meta: &EpisodeMeta, camera: &Camera, state: &SceneState) -> Vec<u8> {
        let meshes: Vec<TriMesh> = meta.objects.iter().map(|o| o.shape.mesh()).collect();
        self.render_rgb(meta, camera, &meshes, &state.joints, &state.object_poses)
    }

    fn render_rgb(
        &self,
        meta: &EpisodeMeta,
        camera: &Camera,
        meshes: &[TriMesh],
        q: &[f64],
        object_poses: &[ObjectPose],
    ) -> Vec<u8> {
        let (w, h) = (
            camera.intrinsics.width as usize,
            camera.intrinsics.height as usize,
        );
        let mut canvas = Canvas::new(w, h);
        let look = &meta.look;
        let light = Light {
            to_light_world: Vector3::from(look.to_light_world).normalize(),
            ambient: 0.35,
        };
        let table = look.table_colors.map(srgb_to_linear);
        let back = look.background_colors.map(srgb_to_linear);
        let fr = &self.frame;
        let table_shade = light.shade(&Vector3::z()) as f32;
        for y in 0..h {
            for x in 0..w {
                let i = y * w + x;
                let (eye, dir) = pixel_ray_world(camera, x as f64, y as f64);
                let mut hit = false;
                if dir.z < -1e-9 {
                    let t = (fr.table_z_m - eye.z) / dir.z;
                    let p = eye + dir * t;
                    if t > 0.0
                        && (fr.table_x_m[0]..=fr.table_x_m[1]).contains(&p.x)
                        && (fr.table_y_m[0]..=fr.table_y_m[1]).contains(&p.y)
                    {
                        let wgt = look.table_pattern.weight(p.x, p.y) as f32;
                        let c = mix(table[0], table[1], wgt);
                        canvas.rgb[i] = c.map(|v| v * table_shade);
                        canvas.inv_depth[i] = (1.0 / camera_depth_m(camera, &p)) as f32;
                        hit = true;
                    }
                }
                if !hit {
                    let az = dir.y.atan2(dir.x);
                    let el = dir.z.clamp(-1.0, 1.0).asin();
                    let wgt = look.background_pattern.weight(az, el) as f32;
                    let shade = 0.75 + 0.25 * (el as f32 + 0.5).clamp(0.0, 1.0);
                    canvas.rgb[i] = mix(back[0], back[1], wgt).map(|v| v * shade);
                }
            }
        }
        for (o, (mesh, pose)) in meta.objects.iter().zip(meshes.iter().zip(object_poses)) {
            let world_from_obj = pose.world_from_object_center(o.shape.height_m());
            draw_mesh(
                &mut canvas,
                camera,
                mesh,
                &world_from_obj,
                srgb_to_linear(o.color),
                &light,
            );
        }
        let robot = &self.embodiment.robot;
        let link_poses = robot.link_poses(q);
        for (li, (link, pose)) in robot.links.iter().zip(&link_poses).enumerate() {
            if let Some(mesh) = &link.mesh {
                let color = srgb_to_linear(LINK_COLORS[li % LINK_COLORS.len()]);
                draw_mesh(&mut canvas, camera, mesh, pose, color, &light);
            }
        }
        for px in &mut canvas.rgb {
            *px = linear_to_srgb(*px);
        }
        canvas.to_rgb8()
    }
}

/// Errors of [`write_dataset`].
#[derive(Debug, thiserror::Error)]
pub enum WriteDatasetError {
    /// Generating an episode failed.
    #[error(transparent)]
    Synth(#[from] SynthError),
    /// Writing the dataset failed.
    #[error(transparent)]
    Dataset(#[from] crate::lerobot::DatasetError),
    /// The output exists.
    #[error("{0}: already exists; choose another --out or remove it")]
    Exists(std::path::PathBuf),
    /// Creating or committing the output folder failed.
    #[error(transparent)]
    Output(#[from] bridgev2w_embodiment::output::OutputError),
    /// File-system failure.
    #[error("{path}: {source}")]
    Io {
        /// Path.
        path: std::path::PathBuf,
        /// Cause.
        source: std::io::Error,
    },
}

/// What [`write_dataset`] wrote.
#[derive(Debug, Clone, Serialize)]
pub struct DatasetSummary {
    /// The dataset directory.
    pub out: std::path::PathBuf,
    /// Episodes per split name.
    pub episodes_per_split: std::collections::BTreeMap<String, usize>,
    /// Episodes per task name.
    pub episodes_per_task: std::collections::BTreeMap<String, usize>,
    /// Total frames.
    pub total_frames: usize,
    /// Object-moving contacts (push, grasp) over all episodes.
    pub contact_events: usize,
}

/// The camera's video key in the dataset.
pub const VIDEO_KEY: &str = "observation.images.main";

/// Generates the configured episodes and writes them as a LeRobot v3.0
/// dataset at `out` (first into `out.tmp`, renamed when complete).
/// Episodes are rendered in parallel batches and written in plan order, so
/// the bytes do not depend on the thread count. `on_episode` is called after
/// each generated episode.
pub fn write_dataset(
    config: &SynthConfig,
    out: &std::path::Path,
    on_episode: &(dyn Fn() + Sync),
) -> Result<DatasetSummary, WriteDatasetError> {
    use crate::lerobot::{LeRobotV3Writer, WriterEpisode};
    use bridgev2w_embodiment::output::{OutputDir, OutputError};
    let world = World::new(config)?;
    // Removed again if anything below fails.
    let output = OutputDir::create(out, false).map_err(|e| match e {
        OutputError::Exists { path } => WriteDatasetError::Exists(path),
        other => WriteDatasetError::Output(other),
    })?;
    let tmp = output.path().to_path_buf();
    let robot = &world.embodiment.robot;
    let state_names: Vec<String> = robot.dof_names().iter().map(|s| s.to_string()).collect();
    let mut action_names = Vec::new();
    for ee in &world.embodiment.end_effectors {
        for c in ["x", "y", "z", "roll", "pitch", "yaw", "gripper"] {
            action_names.push(format!("{}.{c}", ee.arm));
        }
    }
    let mut writer = LeRobotV3Writer::new(
        &tmp,
        &config.robot,
        config.fps,
        VIDEO_KEY,
        (config.width as usize, config.height as usize),
        state_names,
        action_names,
    )?;
    let plan = plan(config);
    let batch = (2 * rayon::current_num_threads()).max(4);
    let mut summary = DatasetSummary {
        out: out.to_path_buf(),
        episodes_per_split: Default::default(),
        episodes_per_task: Default::default(),
        total_frames: 0,
        contact_events: 0,
    };
    let mut metas = Vec::new();
    for chunk in plan.chunks(batch) {
        let episodes: Vec<Episode> = chunk
            .par_iter()
            .map(|&(split, i, task)| {
                let e = world.generate(split, i, task);
                on_episode();
                e
            })
            .collect::<Result<_, _>>()?;
        for e in &episodes {
            let f32s = |rows: &[Vec<f64>]| -> Vec<Vec<f32>> {
                rows.iter()
                    .map(|r| r.iter().map(|&v| v as f32).collect())
                    .collect()
            };
            let index = writer.add_episode(WriterEpisode {
                task: e.meta.task.description(),
                split: Some(e.meta.split.name()),
                states: f32s(&e.joints),
                actions: f32s(&e.actions),
                rgb: &e.rgb,
                masks: Some(&e.masks),
                camera: Some(&e.camera),
            })?;
            *summary
                .episodes_per_split
                .entry(e.meta.split.name().into())
                .or_default() += 1;
            *summary
                .episodes_per_task
                .entry(e.meta.task.name().into())
                .or_default() += 1;
            summary.total_frames += e.rgb.len();
            summary.contact_events += e
                .contacts
                .iter()
                .flatten()
                .filter(|c| matches!(c, Contact::Pushed | Contact::Grasped))
                .count();
            let mut m = serde_json::to_value(&e.meta).unwrap_or_default();
            if let Some(o) = m.as_object_mut() {
                o.insert("episode_index".into(), serde_json::json!(index));
            }
            metas.push(m);
        }
    }
    let specs = serde_json::to_value(&world.specs).unwrap_or_default();
    writer.finish(serde_json::json!({ "synth_splits": specs.clone() }))?;
    let synth_path = tmp.join("meta/synth.json");
    let synth = serde_json::json!({
        "generator": "bridgev2w synth",
        "config": config,
        "scene_frame": world.frame,
        "video_key": VIDEO_KEY,
        "splits": specs,
        "episodes": metas,
    });
    let text = serde_json::to_string_pretty(&synth).unwrap_or_default();
    std::fs::write(&synth_path, text).map_err(|source| WriteDatasetError::Io {
        path: synth_path.clone(),
        source,
    })?;
    output.commit()?;
    Ok(summary)
}
