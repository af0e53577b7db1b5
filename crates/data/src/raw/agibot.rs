//! AgiBot World episodes (the layout of the released AgiBot World data):
//!
//! ```text
//! <root>/observations/<task>/<episode>/videos/<cam>_color.mp4
//! <root>/parameters/<task>/<episode>/parameters/camera/<cam>_intrinsic_params.json
//!     {"intrinsic": {"fx": .., "fy": .., "ppx": .., "ppy": .. [, "width": .., "height": ..]}}
//! <root>/parameters/<task>/<episode>/parameters/camera/<cam>_extrinsic_params_aligned.json
//!     [{"extrinsic": {"rotation_matrix": [[3x3]], "translation_vector": [3]}}, ...]  (one per frame)
//! <root>/proprio_stats/<task>/<episode>/proprio_stats.h5
//!     state/joint/position [T,14] (left arm 1..7, right arm 1..7, radians)
//!     state/effector/position [T,2] (left, right gripper)
//!     state/end/position [T,2,3], state/end/orientation [T,2,4] (quaternion x, y, z, w)
//! <root>/task_info/task_<task>.json (optional; [{"episode_id": .., "task_name": ..}])
//! ```
//!
//! The aligned extrinsics are `world_from_camera` (camera to robot base,
//! OpenCV camera axes) per frame: the head can move. Intrinsics files that do
//! not give the image size use [`AgibotOptions::default_size`] (AgiBot
//! World's head colour camera: 640x480). Gripper readings are converted to a
//! closure in [0, 1] with [`AgibotOptions::gripper_open`] and
//! [`AgibotOptions::gripper_closed`] (defaults 0 and 120, the G1 gripper's
//! range in the released data; swap them if your data counts the other way).

use super::h5::H5;
use super::{
    io_err, json_err, json_intrinsics, json_vec, read_json, rpy_from_xyzw, RawEpisode, RawError,
    RawView,
};
use bridgev2w_embodiment::camera::Intrinsics;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion, Vector3};
use serde_json::Value;
use std::path::{Path, PathBuf};

/// The joint names of `state/joint/position`'s 14 columns (the built-in
/// `agibot-g1` robot's names).
pub fn joint_names() -> Vec<String> {
    ["left", "right"]
        .iter()
        .flat_map(|side| (1..=7).map(move |j| format!("{side}_arm_joint{j}")))
        .collect()
}

/// What to read.
#[derive(Debug, Clone)]
pub struct AgibotOptions {
    /// Cameras to load (`head`, `hand_left`, `hand_right`); default `head`.
    pub cameras: Vec<String>,
    /// Image size `(width, height)` when an intrinsics file does not give it.
    pub default_size: (u32, u32),
    /// Gripper reading when fully open.
    pub gripper_open: f64,
    /// Gripper reading when fully closed.
    pub gripper_closed: f64,
}

impl Default for AgibotOptions {
    fn default() -> Self {
        Self {
            cameras: vec!["head".into()],
            default_size: (640, 480),
            gripper_open: 0.0,
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

fn camera_dir(root: &Path, key: &EpisodeKey) -> PathBuf {
    root.join("parameters")
        .join(&key.task)
        .join(&key.episode)
        .join("parameters/camera")
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
    let path = root
        .join("task_info")
        .join(format!("task_{}.json", key.task));
    if !path.is_file() {
        return Ok(None);
    }
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

/// Reads one AgiBot World episode.
pub fn read_episode(
    root: &Path,
    key: &EpisodeKey,
    options: &AgibotOptions,
) -> Result<RawEpisode, RawError> {
    let id = key.to_string();
    let h5_path = root
        .join("proprio_stats")
        .join(&key.task)
        .join(&key.episode)
        .join("proprio_stats.h5");
    let h5 = H5::open(&h5_path)?;
    let joints = h5
        .read_shaped("state/joint/position", &[None, Some(14)])?
        .rows();
    let frames = joints.len();
    let eff = h5.read_shaped("state/effector/position", &[Some(frames), Some(2)])?;
    let pos = h5.read_shaped("state/end/position", &[Some(frames), Some(2), Some(3)])?;
    let ori = h5.read_shaped("state/end/orientation", &[Some(frames), Some(2), Some(4)])?;
    let span = options.gripper_closed - options.gripper_open;
    if !(span.is_finite() && span.abs() > 1e-12) {
        return Err(RawError::Inconsistent {
            episode: id,
            message: format!(
                "gripper range open={} closed={}: expected two different finite readings",
                options.gripper_open, options.gripper_closed
            ),
        });
    }
    let mut grippers = Vec::with_capacity(frames);
    let mut ee_actions = Vec::with_capacity(frames);
    for t in 0..frames {
        let mut g = [0.0; 2];
        for (arm, g) in g.iter_mut().enumerate() {
            let raw = eff.values[2 * t + arm];
            let c = (raw - options.gripper_open) / span;
            if !(-0.05..=1.05).contains(&c) {
                return Err(RawError::Hdf5 {
                    path: h5_path.clone(),
                    field: "state/effector/position".into(),
                    message: format!(
                        "frame {t}, arm {arm}: {raw} is outside the gripper range [{}, {}]",
                        options.gripper_open.min(options.gripper_closed),
                        options.gripper_open.max(options.gripper_closed)
                    ),
                });
            }
            *g = c.clamp(0.0, 1.0);
        }
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
        grippers.push(g.to_vec());
        ee_actions.push(row);
    }

    let cams = camera_dir(root, key);
    let videos = root
        .join("observations")
        .join(&key.task)
        .join(&key.episode)
        .join("videos");
    let mut views = Vec::new();
    for cam in &options.cameras {
        let video = videos.join(format!("{cam}_color.mp4"));
        if !video.is_file() {
            return Err(RawError::Missing {
                path: video,
                what: format!("video of camera \"{cam}\""),
            });
        }
        views.push(RawView {
            name: cam.clone(),
            video,
            intrinsics: read_intrinsics(
                &cams.join(format!("{cam}_intrinsic_params.json")),
                options.default_size,
            )?,
            world_from_camera: read_extrinsics(
                &cams.join(format!("{cam}_extrinsic_params_aligned.json")),
                frames,
            )?,
        });
    }
    let ep = RawEpisode {
        id,
        source: h5_path.clone(),
        task: task_name(root, key)?,
        frames,
        joints,
        joint_names: joint_names(),
        grippers,
        ee_actions,
        views,
    };
    ep.validate()?;
    Ok(ep)
}
