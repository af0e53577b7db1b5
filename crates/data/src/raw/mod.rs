//! Readers for real robot datasets in their published raw layouts, into one
//! in-memory form ([`RawEpisode`]): recorded joint positions, gripper
//! closures, end-effector actions and, per camera, the video file with its
//! intrinsics and per-frame `world_from_camera` (world = robot base).
//!
//! - [`droid`]: DROID raw episodes (`metadata_*.json`, `trajectory.h5`,
//!   `recordings/MP4/<serial>.mp4`).
//! - [`agibot`]: AgiBot World (`proprio_stats.h5`, camera parameter JSON,
//!   `videos/<cam>_color.mp4`).
//!
//! Masks for these episodes are rendered from the *recorded joint positions*
//! (no IK): [`RawEpisode::joint_trajectory`] maps them onto an
//! [`Embodiment`]'s degrees of freedom by joint name, grippers included.
//! Whatever a reader or the conversion changes (clamped gripper readings,
//! aligned frame counts, scaled intrinsics, joints outside the model's
//! limits, calibration fallbacks) is a [`report::Note`] in the conversion
//! report.

pub mod agibot;
pub mod align;
pub mod convert;
pub mod ctrl_world;
pub mod droid;
pub mod droid_calibration;
pub mod h5;
pub mod report;
pub mod request;
pub mod source;

use bridgev2w_embodiment::camera::{Camera, Intrinsics};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_io::confine::{self, Refusal};
use nalgebra::Isometry3;
use report::{EpisodeNote, Note};
use serde_json::Value;
use std::path::{Path, PathBuf};

/// Errors reading raw episodes; each names the file and, where known, the
/// episode and field.
#[derive(Debug, thiserror::Error)]
pub enum RawError {
    /// I/O failure.
    #[error("{path}: {source}")]
    Io {
        /// File.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// A required file or directory does not exist.
    #[error("{path}: missing {what}")]
    Missing {
        /// The path that should exist.
        path: PathBuf,
        /// What it should be.
        what: String,
    },
    /// An HDF5 file or dataset is unreadable or has the wrong shape/values.
    #[error("{path}{}: {message}", if field.is_empty() { String::new() } else { format!(", dataset \"{field}\"") })]
    Hdf5 {
        /// File.
        path: PathBuf,
        /// Dataset path inside the file (empty for the file itself).
        field: String,
        /// What is wrong.
        message: String,
    },
    /// A JSON file is unreadable or a field has the wrong type or value.
    #[error("{path}{}: {message}", if field.is_empty() { String::new() } else { format!(", field \"{field}\"") })]
    Json {
        /// File.
        path: PathBuf,
        /// Field (JSON path), empty for the whole file.
        field: String,
        /// What is wrong.
        message: String,
    },
    /// A file the episode is read from is not a regular file of bounded
    /// size inside the episode's folder (a FIFO, a device, a folder, a
    /// symbolic link out of the folder): refused before it is opened.
    #[error("{path}: {message}")]
    Refused {
        /// The path as named.
        path: PathBuf,
        /// Why (names the value and where it resolves, never its content).
        message: String,
    },
    /// The episode's parts disagree (frame counts, cameras).
    #[error("episode {episode}: {message}")]
    Inconsistent {
        /// Episode id.
        episode: String,
        /// What disagrees.
        message: String,
    },
    /// The episode does not fit the embodiment it is rendered with.
    #[error("episode {episode}: {message}")]
    Embodiment {
        /// Episode id.
        episode: String,
        /// What does not fit.
        message: String,
    },
}

pub(crate) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> RawError + '_ {
    move |source| RawError::Io {
        path: path.to_path_buf(),
        source,
    }
}

/// The sub-folders of `dir` (symbolic links to folders not followed),
/// sorted: how the readers walk a dataset's tree.
pub(crate) fn sub_dirs(dir: &Path) -> Result<Vec<PathBuf>, RawError> {
    let mut v = Vec::new();
    for e in std::fs::read_dir(dir).map_err(io_err(dir))? {
        let e = e.map_err(io_err(dir))?;
        if e.file_type().map_err(io_err(dir))?.is_dir() {
            v.push(e.path());
        }
    }
    v.sort();
    Ok(v)
}

pub(crate) fn json_err(path: &Path, field: &str, message: impl Into<String>) -> RawError {
    RawError::Json {
        path: path.to_path_buf(),
        field: field.to_string(),
        message: message.into(),
    }
}

/// Checks a list of cameras to convert (`--cameras`, Python's `cameras=`):
/// at least one, none named twice (a camera converted twice would write
/// the same episodes twice). The error says what is wrong; the caller
/// prefixes the flag or argument and the value.
pub fn check_camera_list(names: &[String]) -> Result<(), String> {
    if names.is_empty() {
        return Err("expected at least one camera name".into());
    }
    for (i, name) in names.iter().enumerate() {
        if names[..i].contains(name) {
            return Err(format!(
                "camera {name:?} is named twice: expected distinct names"
            ));
        }
    }
    Ok(())
}

/// A refusal of `path` (named `what` when missing) as a [`RawError`].
fn refused(path: PathBuf, what: &str, e: Refusal) -> RawError {
    if e.is_missing() {
        RawError::Missing {
            path,
            what: what.to_string(),
        }
    } else {
        RawError::Refused {
            path,
            message: e.to_string(),
        }
    }
}

/// `dir/rel`, a file an episode is read from (`what` names it when
/// missing): a regular file of at most `max_bytes` that lies inside `dir`
/// (the folder the user named or one found under it), symbolic links
/// followed; checked without opening it ([`confine::confined_file`]).
pub(crate) fn confined(
    dir: &Path,
    rel: &str,
    max_bytes: u64,
    what: &str,
) -> Result<PathBuf, RawError> {
    confine::confined_file(dir, rel, max_bytes).map_err(|e| refused(dir.join(rel), what, e))
}

/// [`confined`] for a file the episode may lack: `None` when nothing is
/// there (a dangling link counts as nothing).
pub(crate) fn confined_optional(
    dir: &Path,
    rel: &str,
    max_bytes: u64,
) -> Result<Option<PathBuf>, RawError> {
    match confine::confined_file(dir, rel, max_bytes) {
        Ok(p) => Ok(Some(p)),
        Err(e) if e.is_missing() => Ok(None),
        Err(e) => Err(refused(dir.join(rel), "file", e)),
    }
}

/// Reads and parses a JSON file, which must be a regular file of at most
/// [`confine::MAX_METADATA_BYTES`] (checked before it is opened, so a FIFO
/// or a device is an error, not a hang).
pub(crate) fn read_json(path: &Path) -> Result<Value, RawError> {
    confine::regular_file(path, confine::MAX_METADATA_BYTES)
        .map_err(|e| refused(path.to_path_buf(), "JSON file", e))?;
    bridgev2w_io::json::read_json(path).map_err(|e| match e {
        bridgev2w_io::FileError::Io { path, source } => RawError::Io { path, source },
        bridgev2w_io::FileError::Json { path, source } => {
            json_err(&path, "", format!("invalid JSON: {source}"))
        }
        bridgev2w_io::FileError::Format { path, message } => json_err(&path, "", message),
    })
}

/// A finite number at `value[field]`.
pub(crate) fn json_f64(path: &Path, value: &Value, field: &str) -> Result<f64, RawError> {
    let v = value
        .get(field)
        .ok_or_else(|| json_err(path, field, "missing: expected a number"))?;
    v.as_f64()
        .filter(|x| x.is_finite())
        .ok_or_else(|| json_err(path, field, format!("{v}: expected a finite number")))
}

/// `n` finite numbers from a JSON array.
pub(crate) fn json_vec(
    path: &Path,
    v: &Value,
    field: &str,
    n: usize,
) -> Result<Vec<f64>, RawError> {
    let arr = v.as_array().filter(|a| a.len() == n).ok_or_else(|| {
        json_err(
            path,
            field,
            format!("{v}: expected an array of {n} numbers"),
        )
    })?;
    arr.iter()
        .enumerate()
        .map(|(i, x)| {
            x.as_f64().filter(|x| x.is_finite()).ok_or_else(|| {
                json_err(
                    path,
                    &format!("{field}[{i}]"),
                    format!("{x}: expected a finite number"),
                )
            })
        })
        .collect()
}

/// Pinhole intrinsics from a JSON object `k` whose focal lengths and principal
/// point are under `keys` (`[fx, fy, cx, cy]` names) and whose image size is
/// `width`/`height` (or `default_size` when absent). Errors name
/// `prefix.<key>`.
pub(crate) fn json_intrinsics(
    path: &Path,
    k: &Value,
    prefix: &str,
    keys: [&str; 4],
    default_size: Option<(u32, u32)>,
) -> Result<Intrinsics, RawError> {
    let field = |name: &str| format!("{prefix}.{name}");
    let f = |name: &str| {
        json_f64(path, k, name).map_err(|e| match e {
            RawError::Json { message, .. } => json_err(path, &field(name), message),
            other => other,
        })
    };
    let size = |name: &str, default: Option<u32>| -> Result<u32, RawError> {
        match (k.get(name), default) {
            (None, Some(d)) => Ok(d),
            (x, _) => x
                .and_then(Value::as_u64)
                .and_then(|x| u32::try_from(x).ok())
                .filter(|&x| x > 0)
                .ok_or_else(|| {
                    json_err(
                        path,
                        &field(name),
                        format!(
                            "{}: expected a positive integer (pixels)",
                            x.map_or("missing".to_string(), Value::to_string)
                        ),
                    )
                }),
        }
    };
    let intr = Intrinsics {
        fx: f(keys[0])?,
        fy: f(keys[1])?,
        cx: f(keys[2])?,
        cy: f(keys[3])?,
        width: size("width", default_size.map(|s| s.0))?,
        height: size("height", default_size.map(|s| s.1))?,
        distortion: None,
    };
    intr.validate()
        .map_err(|e| json_err(path, prefix, e.to_string()))?;
    Ok(intr)
}

/// One camera of an episode.
#[derive(Debug, Clone, PartialEq)]
pub struct RawView {
    /// Camera name (DROID: serial number; AgiBot: `head`, `hand_left`, ...).
    pub name: String,
    /// The MP4 file.
    pub video: PathBuf,
    /// Intrinsics at the video's resolution.
    pub intrinsics: Intrinsics,
    /// `world_from_camera` per state (OpenCV camera axes; world = robot base).
    pub world_from_camera: Vec<Isometry3<f64>>,
    /// Recorded timestamps matching video frames to states, where the raw
    /// data has them (used only when the counts differ; see [`align`]).
    pub frame_times: Option<align::FrameTimes>,
    /// The split this view's episode is written with, instead of the
    /// conversion's (e.g. a held-out camera view as `unseen_camera`).
    pub split: Option<String>,
}

impl RawView {
    /// The calibrated camera of frame `t`.
    pub fn camera(&self, t: usize) -> Camera {
        Camera {
            intrinsics: self.intrinsics,
            world_from_camera: self.world_from_camera[t.min(self.world_from_camera.len() - 1)],
        }
    }

    /// Whether the camera does not move over the episode (within 1e-9).
    pub fn is_static(&self) -> bool {
        let first = self.world_from_camera[0];
        self.world_from_camera.iter().all(|p| {
            (p.translation.vector - first.translation.vector).norm() < 1e-9
                && p.rotation.angle_to(&first.rotation) < 1e-9
        })
    }
}

/// One episode of a real dataset, in robot-base coordinates.
#[derive(Debug, Clone, PartialEq)]
pub struct RawEpisode {
    /// Episode id (DROID: metadata `uuid`; AgiBot: `<task>/<episode>`).
    pub id: String,
    /// The episode's directory or main file.
    pub source: PathBuf,
    /// Language instruction, when the dataset records one.
    pub task: Option<String>,
    /// Frames (states, actions and every video).
    pub frames: usize,
    /// Recorded arm joint positions per frame (radians), in the order of
    /// [`RawEpisode::joint_names`].
    pub joints: Vec<Vec<f64>>,
    /// The dataset's names for the joint columns (for the built-in robots,
    /// their URDF joint names).
    pub joint_names: Vec<String>,
    /// Gripper closure per frame and arm: 0 open, 1 closed.
    pub grippers: Vec<Vec<f64>>,
    /// End-effector actions per frame: `[x, y, z, roll, pitch, yaw, gripper]`
    /// per arm: the pose of the link named in [`RawEpisode::ee_frames`] (a
    /// flange, not a TCP) in the robot base frame, extrinsic XYZ Euler angles.
    pub ee_actions: Vec<Vec<f64>>,
    /// Per arm, the link whose pose `ee_actions` holds (DROID:
    /// `panda_link8`; AgiBot World: [`agibot::EE_FRAMES`]).
    pub ee_frames: Vec<String>,
    /// Cameras.
    pub views: Vec<RawView>,
    /// What the reader changed or could not find (for the conversion report).
    pub notes: Vec<EpisodeNote>,
}

/// Joint configurations of an [`Embodiment`] per frame, and the recorded
/// values outside its limits (kept, not clamped).
#[derive(Debug, Clone, PartialEq)]
pub struct JointTrajectory {
    /// Full configurations, one per state.
    pub q: Vec<Vec<f64>>,
    /// Per joint outside its limits in some frame: a
    /// [`Note::JointOutOfLimits`]; and a [`Note::JointColumnsIgnored`] for
    /// columns named `-`.
    pub notes: Vec<Note>,
}

impl RawEpisode {
    /// Number of arms.
    pub fn arms(&self) -> usize {
        self.grippers.first().map_or(0, Vec::len)
    }

    /// Checks that every per-frame series has `frames` entries of equal width.
    pub fn validate(&self) -> Result<(), RawError> {
        let bad = |message: String| RawError::Inconsistent {
            episode: self.id.clone(),
            message,
        };
        if self.frames == 0 {
            return Err(bad("no frames".into()));
        }
        if self.ee_frames.len() != self.arms() {
            return Err(bad(format!(
                "{} end-effector frame names for {} arms",
                self.ee_frames.len(),
                self.arms()
            )));
        }
        for (what, rows, width) in [
            ("joint positions", &self.joints, self.joint_names.len()),
            ("gripper values", &self.grippers, self.arms()),
            ("end-effector actions", &self.ee_actions, 7 * self.arms()),
        ] {
            if rows.len() != self.frames {
                return Err(bad(format!(
                    "{} frames of {what}, expected {} (the state count)",
                    rows.len(),
                    self.frames
                )));
            }
            if let Some(t) = rows.iter().position(|r| r.len() != width) {
                return Err(bad(format!(
                    "frame {t} has {} {what}, expected {width}",
                    rows[t].len()
                )));
            }
        }
        for v in &self.views {
            if v.world_from_camera.len() != self.frames {
                return Err(bad(format!(
                    "camera \"{}\" has {} extrinsics, expected {} (one per frame)",
                    v.name,
                    v.world_from_camera.len(),
                    self.frames
                )));
            }
        }
        Ok(())
    }

    /// The view named `name`.
    pub fn view(&self, name: &str) -> Option<&RawView> {
        self.views.iter().find(|v| v.name == name)
    }

    /// The recorded joints as full configurations of `embodiment`, frame by
    /// frame: each joint column goes to the actuated joint of the same name
    /// (or, with `rename`, of `rename[i]`; a `-` there leaves the column
    /// undriven, noted), each arm's gripper closure to its gripper joint
    /// through
    /// [`EndEffector::gripper_joint_value`](bridgev2w_embodiment::actions::EndEffector::gripper_joint_value)
    /// (open and closed as the robot defines them); joints the dataset does
    /// not record stay at the embodiment's home. Values outside a joint's limits are kept as
    /// recorded and listed in [`JointTrajectory::notes`] (count, worst value,
    /// limits), never clamped.
    pub fn joint_trajectory(
        &self,
        embodiment: &Embodiment,
        rename: Option<&[String]>,
    ) -> Result<JointTrajectory, RawError> {
        let robot = &embodiment.robot;
        let names = rename.unwrap_or(&self.joint_names);
        let bad = |message: String| RawError::Embodiment {
            episode: self.id.clone(),
            message,
        };
        if names.len() != self.joint_names.len() {
            return Err(bad(format!(
                "{} joint names given for {} recorded joint columns",
                names.len(),
                self.joint_names.len()
            )));
        }
        let dofs: Vec<Option<usize>> = names
            .iter()
            .map(|n| {
                if n == "-" {
                    return Ok(None);
                }
                robot.dof_index(n).map(Some).ok_or_else(|| {
                    bad(format!(
                        "recorded joint \"{n}\" is not an actuated joint of robot \"{}\" (pass the robot's names for the {} columns)",
                        robot.name,
                        names.len()
                    ))
                })
            })
            .collect::<Result<_, _>>()?;
        if self.arms() > embodiment.end_effectors.len() {
            return Err(bad(format!(
                "{} grippers recorded but robot \"{}\" has {} end effectors",
                self.arms(),
                robot.name,
                embodiment.end_effectors.len()
            )));
        }
        let limits = robot.dof_limits();
        // Per column: (count outside, worst value, its distance outside).
        let mut outside = vec![(0usize, 0.0f64, 0.0f64); dofs.len()];
        let q = self
            .joints
            .iter()
            .zip(&self.grippers)
            .map(|(row, grips)| {
                let mut q = embodiment.home.clone();
                for (c, (d, &v)) in dofs.iter().zip(row).enumerate() {
                    let Some(d) = *d else { continue };
                    let (lo, hi) = limits[d];
                    let excess = (lo - v).max(v - hi);
                    if excess > 0.0 {
                        let o = &mut outside[c];
                        o.0 += 1;
                        if excess > o.2 {
                            (o.1, o.2) = (v, excess);
                        }
                    }
                    q[d] = v;
                }
                for (ee, &g) in embodiment.end_effectors.iter().zip(grips) {
                    if let Some(d) = ee.gripper_dof {
                        q[d] = ee.gripper_joint_value(g, limits[d]);
                    }
                }
                q
            })
            .collect();
        let mut notes: Vec<Note> = dofs
            .iter()
            .zip(&outside)
            .filter_map(|(d, &(count, worst, _))| {
                let d = (*d)?;
                (count > 0).then(|| Note::JointOutOfLimits {
                    joint: robot.dof_names()[d].to_string(),
                    count,
                    worst,
                    lower: limits[d].0,
                    upper: limits[d].1,
                })
            })
            .collect();
        let ignored: Vec<String> = dofs
            .iter()
            .zip(&self.joint_names)
            .filter(|(d, _)| d.is_none())
            .map(|(_, n)| n.clone())
            .collect();
        if !ignored.is_empty() {
            notes.push(Note::JointColumnsIgnored { columns: ignored });
        }
        Ok(JointTrajectory { q, notes })
    }

    /// Records `note` about this episode (and `camera`).
    pub fn note(&mut self, camera: Option<&str>, note: Note) {
        self.notes.push(EpisodeNote {
            episode: self.id.clone(),
            camera: camera.map(str::to_string),
            note,
        });
    }
}

/// Roll, pitch, yaw (extrinsic XYZ) of a unit quaternion given as
/// `[x, y, z, w]`; errors on a non-finite or zero-norm quaternion.
pub fn rpy_from_xyzw(q: [f64; 4]) -> Option<[f64; 3]> {
    let [x, y, z, w] = q;
    let n = (x * x + y * y + z * z + w * w).sqrt();
    if !(n.is_finite() && n > 1e-9) {
        return None;
    }
    let uq = nalgebra::UnitQuaternion::from_quaternion(nalgebra::Quaternion::new(w, x, y, z));
    let (r, p, yaw) = uq.euler_angles();
    Some([r, p, yaw])
}
