//! The synthetic world simulated and rendered by MuJoCo (`synth --engine
//! mujoco`, issue 72): each episode the home-made world plans (scene,
//! camera, the expert's joints by IK) is run again in MuJoCo, a real
//! physics engine and an OpenGL renderer: the robot (its URDF, real meshes
//! where the description has them) position-controlled along the planned
//! joints, the objects free bodies with contact and friction on a static
//! table, lights and shadows. The RGB frames, the joints the arm reached and
//! the objects' poses come from MuJoCo; the embodiment masks are this
//! project's rasterizer on the reached joints, checked per frame against
//! MuJoCo's own segmentation of the robot's geoms (IoU in the episode's
//! metadata).
//!
//! MuJoCo runs in Python (PyPI `mujoco`, the venv `scripts/setup-mujoco-venv.sh`
//! makes): the worker script `mujoco_world.py` is compiled into the binary
//! and written to a temporary folder with the robot's description; a
//! [`MujocoSession`] talks to it.

mod scene;
mod session;

pub use scene::MujocoScene;
pub use session::{MujocoSession, Render, SimFrame, SimReply};

use super::{Episode, Shape, SynthError, World};
use bridgev2w_embodiment::embodiment::builtin;
use bridgev2w_embodiment::masks::render_trajectory_labels;
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use std::process::Command;

/// The worker script.
const WORKER: &str = include_str!("mujoco_world.py");

/// The environment variable naming the Python that has `mujoco`.
pub const PYTHON_ENV: &str = "BRIDGEV2W_MUJOCO_PYTHON";

/// The side of the table's texture (pixels): the built-in world's pattern,
/// drawn by its own code.
const TABLE_TEXTURE_PX: usize = 512;

/// What MuJoCo reported of one episode, kept in its metadata.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MujocoCheck {
    /// MuJoCo's version.
    pub mujoco: String,
    /// Physics steps per frame.
    pub substeps: usize,
    /// Mean over frames of the IoU of this project's masks (on the reached
    /// joints) and MuJoCo's segmentation of the robot.
    pub mask_iou_mean: f64,
    /// The lowest frame's IoU.
    pub mask_iou_min: f64,
    /// The largest difference between planned and reached arm joints over
    /// frames (radians or metres; the grippers left out): the position
    /// control's tracking error.
    pub max_tracking_error: f64,
    /// The task error of MuJoCo's run against the home-made world's run of
    /// the same actions ([`World::task_error_m`]: the final TCP for reach
    /// and play, the task object's final place for push and pick_place;
    /// metres; `None` when pick_place ends with the object still held).
    pub task_error_m: Option<f64>,
    /// Whether MuJoCo's run ends where the home-made world's does, within
    /// [`super::SUCCESS_TOLERANCE_M`]: the scripted expert's task done with
    /// real contact and friction.
    pub as_planned: bool,
}

/// An episode MuJoCo ran, or why it was dropped.
#[derive(Debug)]
pub enum Simulated {
    /// The episode with MuJoCo's frames, joints and objects.
    Stable(Box<Episode>),
    /// The physics went unstable (a non-finite state, an object through the
    /// table): never written as training data.
    Unstable {
        /// What MuJoCo's run showed.
        reason: String,
    },
}

/// The MuJoCo side: a Python with `mujoco` and a folder with the worker and
/// the robot's description.
#[derive(Debug)]
pub struct MujocoEngine {
    python: PathBuf,
    dir: tempfile::TempDir,
    urdf: PathBuf,
}

pub(super) fn engine_error(message: impl Into<String>) -> SynthError {
    SynthError::Engine(message.into())
}

/// The Python to run MuJoCo with: `BRIDGEV2W_MUJOCO_PYTHON`, else
/// `.venv-mujoco/bin/python` in the current folder or a folder above it or
/// above the running binary (a checkout's `target/*/bridgev2w`).
pub fn find_python() -> Result<PathBuf, SynthError> {
    if let Some(p) = std::env::var_os(PYTHON_ENV) {
        let p = PathBuf::from(p);
        return if p.is_file() {
            Ok(p)
        } else {
            Err(engine_error(format!(
                "{PYTHON_ENV}={}: no such file (expected a Python with the mujoco package, e.g. .venv-mujoco/bin/python)",
                p.display()
            )))
        };
    }
    let mut starts: Vec<PathBuf> = std::env::current_dir().into_iter().collect();
    starts.extend(
        std::env::current_exe()
            .ok()
            .and_then(|e| e.parent().map(Path::to_path_buf)),
    );
    for start in &starts {
        for dir in start.ancestors() {
            let p = dir.join(".venv-mujoco/bin/python");
            if p.is_file() {
                return Ok(p);
            }
        }
    }
    Err(engine_error(format!(
        "no Python with MuJoCo: run scripts/setup-mujoco-venv.sh (it makes .venv-mujoco from PyPI) or set {PYTHON_ENV} to a Python that imports mujoco"
    )))
}

impl MujocoEngine {
    /// The engine for built-in robot `robot`, with the Python `python`
    /// (see [`find_python`]); checks that it imports `mujoco` (a failing
    /// offscreen renderer is named at the first scene, with the fix).
    pub fn new(robot: &str, python: PathBuf) -> Result<Self, SynthError> {
        let spec = builtin(robot).ok_or_else(|| {
            engine_error(format!(
                "robot {robot:?}: the MuJoCo engine runs the built-in robots (their description folders)"
            ))
        })?;
        let dir =
            tempfile::tempdir().map_err(|e| engine_error(format!("a temporary folder: {e}")))?;
        let write = |rel: &str, bytes: &[u8]| -> Result<(), SynthError> {
            let path = dir.path().join("robot").join(rel);
            if let Some(parent) = path.parent() {
                std::fs::create_dir_all(parent)
                    .map_err(|e| engine_error(format!("{}: {e}", parent.display())))?;
            }
            std::fs::write(&path, bytes)
                .map_err(|e| engine_error(format!("{}: {e}", path.display())))
        };
        let urdf_name = format!("{}.urdf", spec.folder);
        write(&urdf_name, spec.urdf.as_bytes())?;
        for (rel, bytes) in spec.files {
            write(rel, bytes)?;
        }
        write("../mujoco_world.py", WORKER.as_bytes())?;
        let engine = Self {
            python,
            urdf: dir.path().join("robot").join(urdf_name),
            dir,
        };
        engine.check_python()?;
        Ok(engine)
    }

    fn check_python(&self) -> Result<(), SynthError> {
        let o = Command::new(&self.python)
            .args(["-c", "import mujoco; print(mujoco.__version__)"])
            .output()
            .map_err(|e| engine_error(format!("{}: cannot run it: {e}", self.python.display())))?;
        if !o.status.success() {
            return Err(engine_error(format!(
                "{} cannot import mujoco ({}): run scripts/setup-mujoco-venv.sh or set {PYTHON_ENV}",
                self.python.display(),
                String::from_utf8_lossy(&o.stderr).lines().last().unwrap_or("").trim()
            )));
        }
        Ok(())
    }

    /// A new session (its worker process), its errors written beside the
    /// script as `name.stderr`.
    pub fn session(&self, name: &str) -> Result<MujocoSession, SynthError> {
        MujocoSession::start(
            &self.python,
            &self.dir.path().join("mujoco_world.py"),
            &self.dir.path().join(format!("{name}.stderr")),
        )
    }

    /// The worker's description of `episode`'s scene (planned by `world`):
    /// robot, camera, table (its pattern written as a texture beside the
    /// script, `name-table.png`), the backdrop as the camera sees it
    /// (`name-backdrop.rgb`, raw sRGB8 at the camera's size: the built-in
    /// world's, drawn where MuJoCo's rays meet nothing), light, objects, and
    /// the plan's joints. The worker reads the files on reset;
    /// [`MujocoEngine::remove_scene_files`] removes them.
    pub fn scene_json(
        &self,
        world: &World,
        episode: &Episode,
        name: &str,
    ) -> Result<serde_json::Value, SynthError> {
        let texture = self.dir.path().join(format!("{name}-table.png"));
        let png = bridgev2w_io::png::encode_rgb8(
            TABLE_TEXTURE_PX as u32,
            TABLE_TEXTURE_PX as u32,
            &super::draw::table_texture(world, &episode.meta, TABLE_TEXTURE_PX, TABLE_TEXTURE_PX),
        );
        std::fs::write(&texture, png)
            .map_err(|e| engine_error(format!("{}: {e}", texture.display())))?;
        let backdrop = self.dir.path().join(format!("{name}-backdrop.rgb"));
        std::fs::write(&backdrop, world.backdrop(&episode.meta, &episode.camera))
            .map_err(|e| engine_error(format!("{}: {e}", backdrop.display())))?;
        let mut json = self.episode_json(world, episode);
        json["table"]["texture_png"] = serde_json::json!(texture);
        json["backdrop_rgb"] = serde_json::json!(backdrop);
        Ok(json)
    }

    /// Removes the files [`MujocoEngine::scene_json`] wrote for `name`
    /// (after the worker's reset has read them).
    pub fn remove_scene_files(&self, name: &str) {
        for file in [format!("{name}-table.png"), format!("{name}-backdrop.rgb")] {
            let _ = std::fs::remove_file(self.dir.path().join(file));
        }
    }

    /// Runs `episode` (planned by `world`) in MuJoCo.
    pub fn simulate(&self, world: &World, episode: Episode) -> Result<Simulated, SynthError> {
        let name = format!(
            "{}-{}",
            episode.meta.split.name(),
            episode.meta.index_in_split
        );
        let json = self.scene_json(world, &episode, &name)?;
        let size = (
            episode.camera.intrinsics.height as usize,
            episode.camera.intrinsics.width as usize,
        );
        let mut session = self.session(&name)?;
        let start = session.reset(&json, size)?;
        let mut reply = match start.unstable {
            Some(reason) => return Ok(Simulated::Unstable { reason }),
            None => session.step(&episode.joints[1..], Render::All)?,
        };
        drop(session);
        self.remove_scene_files(&name);
        if let Some(reason) = reply.unstable {
            return Ok(Simulated::Unstable { reason });
        }
        let mut frames = start.frames;
        frames.append(&mut reply.frames);
        let planned = episode.clone();
        let mut e = self.read_back(world, episode, frames, &reply)?;
        let error_m = world.task_error_m(&planned, &e);
        if let Some(m) = e.meta.mujoco.as_mut() {
            m.task_error_m = error_m.is_finite().then_some(error_m);
            m.as_planned = error_m < super::SUCCESS_TOLERANCE_M;
        }
        Ok(Simulated::Stable(Box::new(e)))
    }

    fn episode_json(&self, world: &World, e: &Episode) -> serde_json::Value {
        let f = &world.frame;
        let look = &e.meta.look;
        let camera: serde_json::Value =
            serde_json::from_str(&e.camera.to_json()).unwrap_or_default();
        let objects: Vec<_> = e
            .meta
            .objects
            .iter()
            .map(|o| {
                let mut v = match o.shape {
                    Shape::Box { size_m } => serde_json::json!({"kind": "box", "size_m": size_m}),
                    Shape::Cylinder { radius_m, height_m } => serde_json::json!({
                        "kind": "cylinder", "radius_m": radius_m, "height_m": height_m
                    }),
                };
                v["color"] = serde_json::json!(o.color);
                v["position_m"] = serde_json::json!(o.initial.position_m);
                v["yaw_rad"] = serde_json::json!(o.initial.yaw_rad);
                v
            })
            .collect();
        let robot = &world.embodiment.robot;
        serde_json::json!({
            "urdf": self.urdf,
            "joint_names": robot.dof_names(),
            "joints": e.joints,
            "fps": world.config.fps,
            "camera": camera,
            "table": {
                "z_m": f.table_z_m, "x_m": f.table_x_m, "y_m": f.table_y_m,
                "colors": look.table_colors,
            },
            "background": look.background_colors,
            "to_light_world": look.to_light_world,
            "objects": objects,
        })
    }

    fn read_back(
        &self,
        world: &World,
        mut e: Episode,
        frames: Vec<SimFrame>,
        reply: &SimReply,
    ) -> Result<Episode, SynthError> {
        if frames.len() != e.joints.len() {
            return Err(engine_error(format!(
                "MuJoCo returned {} frames of the episode's {}",
                frames.len(),
                e.joints.len()
            )));
        }
        let missing = || engine_error("MuJoCo returned a frame unrendered");
        let rgb: Vec<Vec<u8>> = frames
            .iter()
            .map(|f| f.rgb.clone().ok_or_else(missing))
            .collect::<Result<_, _>>()?;
        let theirs: Vec<Vec<u8>> = frames
            .iter()
            .map(|f| f.robot.clone().ok_or_else(missing))
            .collect::<Result<_, _>>()?;
        let reached: Vec<Vec<f64>> = frames.iter().map(|f| f.joints.clone()).collect();
        // The arm's tracking (a gripper closed on an object stops short of
        // its command by design).
        let grippers: Vec<usize> = world
            .embodiment
            .end_effectors
            .iter()
            .filter_map(|ee| ee.gripper_dof)
            .collect();
        let max_tracking_error = reached
            .iter()
            .zip(&e.joints)
            .flat_map(|(a, b)| {
                a.iter()
                    .zip(b)
                    .enumerate()
                    .filter(|(d, _)| !grippers.contains(d))
                    .map(|(_, (x, y))| (x - y).abs())
            })
            .fold(0.0, f64::max);
        let labels = render_trajectory_labels(&world.embodiment.robot, &e.camera, &reached, &|| {});
        let ious: Vec<f64> = labels
            .iter()
            .zip(&theirs)
            .map(|(ours, theirs)| crate::overlay::iou(ours, theirs))
            .collect();
        e.rgb = rgb;
        e.masks = labels
            .iter()
            .map(|l| l.iter().map(|&v| u8::from(v != 0)).collect())
            .collect();
        e.labels = labels
            .iter()
            .map(|l| l.iter().map(|&v| v.min(255) as u8).collect())
            .collect();
        e.joints = reached;
        e.mujoco_masks = Some(theirs);
        let table_z = world.frame.table_z_m;
        e.object_poses = frames.iter().map(|f| f.objects.clone()).collect();
        e.contacts = frames.iter().map(|f| f.contacts(table_z)).collect();
        e.meta.mujoco = Some(MujocoCheck {
            mujoco: reply.mujoco.clone(),
            substeps: reply.substeps,
            mask_iou_mean: ious.iter().sum::<f64>() / ious.len().max(1) as f64,
            mask_iou_min: ious.iter().copied().fold(1.0, f64::min),
            max_tracking_error,
            task_error_m: None,
            as_planned: false,
        });
        Ok(e)
    }
}
