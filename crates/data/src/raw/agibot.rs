//! AgiBot World episodes (the layout of the released AgiBot World data):
//!
//! ```text
//! <root>/observations/<task>/<episode>/videos/<cam>_color.mp4
//! <root>/parameters/<task>/<episode>/parameters/camera/<cam>_intrinsic_params.json
//!     {"intrinsic": {"fx": .., "fy": .., "ppx": .., "ppy": .. [, "width": .., "height": ..]}}
//! <root>/parameters/<task>/<episode>/parameters/camera/<cam>_extrinsic_params_aligned.json
//!     [{"extrinsic": {"rotation_matrix": [[3x3]], "translation_vector": [3]}}, ...]  (one per frame)
//! <root>/proprio_stats/<task>/<episode>/proprio_stats.h5
//!     state/joint/position [T,14]   left arm joints 1..7, right arm joints 1..7 (rad)
//!     state/effector/position [T,2] gripper readings, rising as the gripper closes
//!                                   (about 35 open, about 120 closed; [T,12] on
//!                                   dexterous-hand robots)
//!     action/effector/position [T,2] gripper commands, 0 open .. 1 closed
//!     state/end/position [T,2,3], state/end/orientation [T,2,4] (x, y, z, w): the
//!                                   arms' flange poses in the robot base frame
//!     state/waist/position [T,2]    (pitch rad, lift m)
//!     state/head/position [T,2]     (yaw, pitch; rad)
//! <root>/task_info/task_<task>.json (optional; [{"episode_id": .., "task_name": ..}])
//! ```
//!
//! The aligned extrinsics are `world_from_camera` (camera to robot base,
//! OpenCV camera axes) per frame: the head can move. Intrinsics files that do
//! not give the image size use [`AgibotOptions::default_size`] (AgiBot
//! World's colour cameras: 640x480). The joint columns are named as the real
//! G1's URDF names them ([`ARM_JOINTS`], [`WAIST_JOINTS`], [`HEAD_JOINTS`]);
//! the waist and head are read when recorded (otherwise noted, and the
//! robot's home is used). The gripper closure comes from [`GripperSource`]:
//! readings outside the stated range are clamped and counted in the
//! conversion report. Dexterous-hand episodes are refused by name.

use super::h5::H5;
use super::report::Note;
use super::{
    confined, confined_optional, io_err, json_err, json_intrinsics, json_vec, read_json,
    rpy_from_xyzw, RawEpisode, RawError, RawView,
};
use bridgev2w_embodiment::camera::Intrinsics;
use bridgev2w_io::confine;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde_json::Value;
use std::path::Path;

/// The robot's names for `state/joint/position`'s 14 columns (left arm
/// 1..7, right arm 1..7): the real G1's URDF (genie_sim G01) names.
pub const ARM_JOINTS: [&str; 14] = [
    "idx21_arm_l_joint1",
    "idx22_arm_l_joint2",
    "idx23_arm_l_joint3",
    "idx24_arm_l_joint4",
    "idx25_arm_l_joint5",
    "idx26_arm_l_joint6",
    "idx27_arm_l_joint7",
    "idx61_arm_r_joint1",
    "idx62_arm_r_joint2",
    "idx63_arm_r_joint3",
    "idx64_arm_r_joint4",
    "idx65_arm_r_joint5",
    "idx66_arm_r_joint6",
    "idx67_arm_r_joint7",
];

/// The robot's names for `state/waist/position`'s 2 columns, in the file's
/// order (pitch in rad, then lift in metres, 0..0.55).
pub const WAIST_JOINTS: [&str; 2] = ["idx02_body_joint2", "idx01_body_joint1"];

/// The robot's names for `state/head/position`'s 2 columns (yaw, pitch).
pub const HEAD_JOINTS: [&str; 2] = ["idx11_head_joint1", "idx12_head_joint2"];

/// The links whose poses `state/end/{position,orientation}` hold, per arm
/// (the arms' flanges: `agibot-g1`'s `arm_{l,r}_link7`, checked by FK of the
/// recorded joints on AgiBot World's ge-sim-v2 sample).
pub const EE_FRAMES: [&str; 2] = ["arm_l_link7", "arm_r_link7"];

/// The gripper readings of `state/effector/position` this converter expects
/// per frame (one per arm).
pub const GRIPPER_VALUES: usize = 2;

/// Where the gripper closure (0 open, 1 closed) comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum GripperSource {
    /// `action/effector/position` when the file has it, else the state.
    #[default]
    Auto,
    /// `action/effector/position` (already 0 open .. 1 closed).
    Action,
    /// `state/effector/position`, mapped through
    /// [`AgibotOptions::gripper_open`] / [`AgibotOptions::gripper_closed`].
    State,
}

impl std::str::FromStr for GripperSource {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "auto" => Ok(Self::Auto),
            "action" => Ok(Self::Action),
            "state" => Ok(Self::State),
            _ => Err(format!(
                "\"{s}\": expected \"auto\", \"action\" or \"state\""
            )),
        }
    }
}

/// The field of the state's gripper readings.
pub const STATE_EFFECTOR: &str = "state/effector/position";
/// The field of the commanded gripper closure (0..1).
pub const ACTION_EFFECTOR: &str = "action/effector/position";

/// What to read.
#[derive(Debug, Clone)]
pub struct AgibotOptions {
    /// Cameras to load (`head`, `hand_left`, `hand_right`); default `head`.
    pub cameras: Vec<String>,
    /// Image size `(width, height)` when an intrinsics file does not give it.
    pub default_size: (u32, u32),
    /// Where the gripper closure comes from.
    pub gripper: GripperSource,
    /// `state/effector/position` reading when fully open (default 35).
    pub gripper_open: f64,
    /// `state/effector/position` reading when fully closed (default 120).
    pub gripper_closed: f64,
}

impl AgibotOptions {
    /// Checks the camera names (`--cameras`): at least one, none twice
    /// ([`super::check_camera_list`]); each becomes part of a file
    /// name (`<cam>_color.mp4`, `<cam>_intrinsic_params.json`), so each must
    /// be a plain name (no `/`, `..` or NUL). The error names the flag, the
    /// value and what was expected.
    pub fn check_cameras(&self) -> Result<(), String> {
        super::check_camera_list(&self.cameras)
            .map_err(|e| format!("--cameras {:?}: {e}", self.cameras))?;
        for cam in &self.cameras {
            bridgev2w_io::confine::check_name(cam)
                .map_err(|e| format!("--cameras: camera name {e}"))?;
        }
        Ok(())
    }
}

impl Default for AgibotOptions {
    fn default() -> Self {
        Self {
            cameras: vec!["head".into()],
            default_size: (640, 480),
            gripper: GripperSource::default(),
            gripper_open: 35.0,
            gripper_closed: 120.0,
        }
    }
}

/// One episode's identity.
#[derive(Debug, Clone, PartialEq, Eq, PartialOrd, Ord)]
pub struct EpisodeKey {
    /// Task id (directory name).
    pub task: String,
    /// Episode id (directory name).
    pub episode: String,
}

impl std::fmt::Display for EpisodeKey {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.task, self.episode)
    }
}

/// Every episode under `root` (each `proprio_stats/<task>/<episode>/proprio_stats.h5`), sorted.
pub fn find_episodes(root: &Path) -> Result<Vec<EpisodeKey>, RawError> {
    let base = root.join("proprio_stats");
    if !base.is_dir() {
        return Err(RawError::Missing {
            path: base,
            what: "AgiBot World proprio_stats directory".into(),
        });
    }
    let dirs = |p: &Path| -> Result<Vec<String>, RawError> {
        let mut v = Vec::new();
        for e in std::fs::read_dir(p).map_err(io_err(p))? {
            let e = e.map_err(io_err(p))?;
            if e.file_type().map_err(io_err(p))?.is_dir() {
                v.push(e.file_name().to_string_lossy().into_owned());
            }
        }
        v.sort();
        Ok(v)
    };
    let mut out = Vec::new();
    for task in dirs(&base)? {
        for episode in dirs(&base.join(&task))? {
            if base
                .join(&task)
                .join(&episode)
                .join("proprio_stats.h5")
                .is_file()
            {
                out.push(EpisodeKey {
                    task: task.clone(),
                    episode,
                });
            }
        }
    }
    Ok(out)
}

/// The folder of an episode's camera parameters, relative to the root.
fn camera_dir(key: &EpisodeKey) -> String {
    format!("parameters/{}/{}/parameters/camera", key.task, key.episode)
}

fn read_intrinsics(path: &Path, default_size: (u32, u32)) -> Result<Intrinsics, RawError> {
    let v = read_json(path)?;
    let k = v.get("intrinsic").ok_or_else(|| {
        json_err(
            path,
            "intrinsic",
            "missing: expected {\"fx\", \"fy\", \"ppx\", \"ppy\"}",
        )
    })?;
    json_intrinsics(
        path,
        k,
        "intrinsic",
        ["fx", "fy", "ppx", "ppy"],
        Some(default_size),
    )
}

fn pose_from_json(path: &Path, field: &str, e: &Value) -> Result<Isometry3<f64>, RawError> {
    let ext = e.get("extrinsic").ok_or_else(|| {
        json_err(
            path,
            field,
            "missing \"extrinsic\": expected {\"rotation_matrix\", \"translation_vector\"}",
        )
    })?;
    let rows = ext
        .get("rotation_matrix")
        .and_then(Value::as_array)
        .filter(|r| r.len() == 3)
        .ok_or_else(|| {
            json_err(
                path,
                &format!("{field}.extrinsic.rotation_matrix"),
                "expected a 3x3 array",
            )
        })?;
    let mut m = Matrix3::zeros();
    for (i, r) in rows.iter().enumerate() {
        let r = json_vec(
            path,
            r,
            &format!("{field}.extrinsic.rotation_matrix[{i}]"),
            3,
        )?;
        for j in 0..3 {
            m[(i, j)] = r[j];
        }
    }
    let t = json_vec(
        path,
        ext.get("translation_vector").unwrap_or(&Value::Null),
        &format!("{field}.extrinsic.translation_vector"),
        3,
    )?;
    // A rotation: orthonormal with determinant +1 (within calibration noise).
    let err = (m.transpose() * m - Matrix3::identity()).norm();
    if err > 1e-3 || m.determinant() < 0.0 {
        return Err(json_err(
            path,
            &format!("{field}.extrinsic.rotation_matrix"),
            format!(
                "not a rotation (|R^T R - I| = {err:.2e}, det = {:.4})",
                m.determinant()
            ),
        ));
    }
    let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix(&m));
    Ok(Isometry3::from_parts(
        Translation3::from(Vector3::new(t[0], t[1], t[2])),
        rot,
    ))
}

fn read_extrinsics(path: &Path, frames: usize) -> Result<Vec<Isometry3<f64>>, RawError> {
    let v = read_json(path)?;
    match &v {
        Value::Array(items) => {
            if items.len() != frames {
                return Err(json_err(
                    path,
                    "",
                    format!("{} extrinsics, but proprio_stats.h5 has {frames} frames (expected one per frame)", items.len()),
                ));
            }
            items
                .iter()
                .enumerate()
                .map(|(i, e)| pose_from_json(path, &format!("[{i}]"), e))
                .collect()
        }
        Value::Object(_) => Ok(vec![pose_from_json(path, "", &v)?; frames]),
        _ => Err(json_err(
            path,
            "",
            "expected a list of per-frame {\"extrinsic\": ..} objects",
        )),
    }
}

fn task_name(root: &Path, key: &EpisodeKey) -> Result<Option<String>, RawError> {
    let rel = format!("task_info/task_{}.json", key.task);
    let Some(path) = confined_optional(root, &rel, confine::MAX_METADATA_BYTES)? else {
        return Ok(None);
    };
    let v = read_json(&path)?;
    Ok(v.as_array().and_then(|items| {
        items.iter().find_map(|it| {
            let id = it.get("episode_id")?;
            let matches = id.as_str() == Some(key.episode.as_str())
                || id.as_u64().map(|n| n.to_string()).as_deref() == Some(key.episode.as_str());
            if matches {
                it.get("task_name")
                    .and_then(Value::as_str)
                    .map(str::to_string)
            } else {
                None
            }
        })
    }))
}

/// Gripper closures `[frames][2]` (0 open, 1 closed) from the source chosen
/// in `options`, readings outside the range clamped and noted per arm.
fn read_grippers(
    h5: &H5,
    frames: usize,
    options: &AgibotOptions,
    ep_id: &str,
    notes: &mut Vec<Note>,
) -> Result<Vec<Vec<f64>>, RawError> {
    // The state's width first: a dexterous hand is refused by name whatever the source.
    let state = h5.read(STATE_EFFECTOR)?;
    let width = state.shape.get(1).copied().unwrap_or(1);
    if state.shape.len() == 2 && state.shape[0] == frames && width != GRIPPER_VALUES {
        return Err(RawError::Hdf5 {
            path: h5.path().to_path_buf(),
            field: STATE_EFFECTOR.into(),
            message: format!(
                "dexterous hand: {width} effector values per frame, this converter supports the {GRIPPER_VALUES}-value gripper"
            ),
        });
    }
    let use_action = match options.gripper {
        GripperSource::Action => true,
        GripperSource::State => false,
        GripperSource::Auto => h5.has(ACTION_EFFECTOR),
    };
    let (field, values, open, closed) = if use_action {
        let a = h5.read_shaped(ACTION_EFFECTOR, &[Some(frames), Some(GRIPPER_VALUES)])?;
        (ACTION_EFFECTOR, a.values, 0.0, 1.0)
    } else {
        let s = h5.read_shaped(STATE_EFFECTOR, &[Some(frames), Some(GRIPPER_VALUES)])?;
        (
            STATE_EFFECTOR,
            s.values,
            options.gripper_open,
            options.gripper_closed,
        )
    };
    let span = closed - open;
    if !(span.is_finite() && span.abs() > 1e-12) {
        return Err(RawError::Inconsistent {
            episode: ep_id.to_string(),
            message: format!(
                "gripper range open={open} closed={closed}: expected two different finite readings"
            ),
        });
    }
    let mut out = vec![vec![0.0; GRIPPER_VALUES]; frames];
    for arm in 0..GRIPPER_VALUES {
        let (mut count, mut worst, mut worst_c) = (0usize, 0.0, 0.5f64);
        for (t, row) in out.iter_mut().enumerate() {
            let raw = values[GRIPPER_VALUES * t + arm];
            let c = (raw - open) / span;
            if !(0.0..=1.0).contains(&c) {
                count += 1;
                if (c - 0.5).abs() > (worst_c - 0.5).abs() {
                    (worst, worst_c) = (raw, c);
                }
            }
            row[arm] = c.clamp(0.0, 1.0);
        }
        if count > 0 {
            notes.push(Note::GripperClamped {
                arm,
                field: field.into(),
                count,
                worst,
                open,
                closed,
            });
        }
    }
    Ok(out)
}

/// Reads one AgiBot World episode. Every file read (`proprio_stats.h5`, the
/// videos, the camera parameters, the task information) must be a regular
/// file of bounded size inside `root`, symbolic links followed: a FIFO, a
/// device or a link out of the root is refused before it is opened.
pub fn read_episode(
    root: &Path,
    key: &EpisodeKey,
    options: &AgibotOptions,
) -> Result<RawEpisode, RawError> {
    let id = key.to_string();
    options
        .check_cameras()
        .map_err(|message| RawError::Inconsistent {
            episode: id.clone(),
            message,
        })?;
    let h5_path = confined(
        root,
        &format!(
            "proprio_stats/{}/{}/proprio_stats.h5",
            key.task, key.episode
        ),
        confine::MAX_DATA_BYTES,
        "HDF5 file",
    )?;
    let h5 = H5::open(&h5_path)?;
    let mut joints = h5
        .read_shaped("state/joint/position", &[None, Some(14)])?
        .rows();
    let frames = joints.len();
    let mut joint_names: Vec<String> = ARM_JOINTS.iter().map(|s| s.to_string()).collect();
    let mut notes = Vec::new();
    for (field, names) in [
        ("state/waist/position", WAIST_JOINTS),
        ("state/head/position", HEAD_JOINTS),
    ] {
        if h5.has(field) {
            let a = h5.read_shaped(field, &[Some(frames), Some(names.len())])?;
            for (row, v) in joints.iter_mut().zip(a.values.chunks(names.len())) {
                row.extend_from_slice(v);
            }
            joint_names.extend(names.iter().map(|s| s.to_string()));
        } else {
            notes.push(Note::JointsMissing {
                field: field.into(),
                joints: names.iter().map(|s| s.to_string()).collect(),
            });
        }
    }
    let grippers = read_grippers(&h5, frames, options, &id, &mut notes)?;
    let pos = h5.read_shaped("state/end/position", &[Some(frames), Some(2), Some(3)])?;
    let ori = h5.read_shaped("state/end/orientation", &[Some(frames), Some(2), Some(4)])?;
    let mut ee_actions = Vec::with_capacity(frames);
    for (t, g) in grippers.iter().enumerate() {
        let mut row = Vec::with_capacity(14);
        for (arm, &g) in g.iter().enumerate() {
            let p = &pos.values[6 * t + 3 * arm..6 * t + 3 * arm + 3];
            let q = &ori.values[8 * t + 4 * arm..8 * t + 4 * arm + 4];
            let rpy = rpy_from_xyzw([q[0], q[1], q[2], q[3]]).ok_or_else(|| RawError::Hdf5 {
                path: h5_path.clone(),
                field: "state/end/orientation".into(),
                message: format!("frame {t}, arm {arm}: zero quaternion {q:?}"),
            })?;
            row.extend_from_slice(p);
            row.extend_from_slice(&rpy);
            row.push(g);
        }
        ee_actions.push(row);
    }

    let cams = camera_dir(key);
    let json = |name: String| confined(root, &name, confine::MAX_METADATA_BYTES, "JSON file");
    let mut views = Vec::new();
    for cam in &options.cameras {
        let video = confined(
            root,
            &format!(
                "observations/{}/{}/videos/{cam}_color.mp4",
                key.task, key.episode
            ),
            confine::MAX_VIDEO_BYTES,
            &format!("video of camera \"{cam}\""),
        )?;
        views.push(RawView {
            name: cam.clone(),
            video,
            intrinsics: read_intrinsics(
                &json(format!("{cams}/{cam}_intrinsic_params.json"))?,
                options.default_size,
            )?,
            world_from_camera: read_extrinsics(
                &json(format!("{cams}/{cam}_extrinsic_params_aligned.json"))?,
                frames,
            )?,
            frame_times: None,
            split: None,
        });
    }
    let mut ep = RawEpisode {
        id,
        source: h5_path.clone(),
        task: task_name(root, key)?,
        frames,
        joints,
        joint_names,
        grippers,
        ee_actions,
        ee_frames: EE_FRAMES.iter().map(|s| s.to_string()).collect(),
        views,
        notes: Vec::new(),
    };
    for n in notes {
        ep.note(None, n);
    }
    ep.validate()?;
    Ok(ep)
}
