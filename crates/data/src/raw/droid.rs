//! DROID raw episodes (the layout of the released `droid_raw` data):
//!
//! ```text
//! <episode>/metadata_<lab>+<uuid>+<date>.json   uuid, current_task, trajectory_length,
//!                                               {ext1,ext2,wrist}_cam_serial, *_mp4_path
//! <episode>/trajectory.h5                      observation/robot_state/{joint_positions [T,7],
//!                                               gripper_position [T], cartesian_position [T,6]},
//!                                               observation/camera_extrinsics/<serial>_left [T,6]
//! <episode>/recordings/MP4/<serial>.mp4        left image of each ZED camera
//! ```
//!
//! Neither the raw episodes nor RLDS carry camera intrinsics, so they come
//! from a user-supplied JSON file keyed by camera serial:
//! `{"<serial>": {"fx": .., "fy": .., "cx": .., "cy": .., "width": 1280, "height": 720}}`.
//! Re-calibrated extrinsics (the DROID team's improved calibrations, or
//! anyone's) replace the recorded ones through an override file:
//! `{"<uuid>": {"<serial>_left": [x, y, z, rx, ry, rz]}}`, or the same
//! camera map at the top level to apply to every episode. Extrinsics are
//! DROID's `[x, y, z, rx, ry, rz]` = `world_from_camera` with extrinsic XYZ
//! Euler angles ([`world_from_camera_from_xyz_rpy`]).
//!
//! The robot is a Franka Panda (`panda_joint1..7`) with a Robotiq 2F-85
//! gripper: `gripper_position` is its normalised closure (0 open, 1 closed),
//! i.e. an opening of [`ROBOTIQ_2F85_STROKE_M`]` * (1 - g)`.

use super::h5::H5;
use super::{
    io_err, json_err, json_intrinsics, json_vec, read_json, RawEpisode, RawError, RawView,
};
use bridgev2w_embodiment::camera::{world_from_camera_from_xyz_rpy, Intrinsics};
use nalgebra::Isometry3;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Full stroke of the Robotiq 2F-85 gripper (metres).
pub const ROBOTIQ_2F85_STROKE_M: f64 = 0.085;

/// The Franka joint names DROID's `joint_positions` columns correspond to.
pub const JOINT_NAMES: [&str; 7] = [
    "panda_joint1",
    "panda_joint2",
    "panda_joint3",
    "panda_joint4",
    "panda_joint5",
    "panda_joint6",
    "panda_joint7",
];

/// The camera roles of a DROID episode, in metadata order.
pub const ROLES: [&str; 3] = ["ext1", "ext2", "wrist"];

/// Robotiq 2F-85 opening (metres) for DROID's normalised gripper position.
pub fn robotiq_opening_m(gripper_position: f64) -> f64 {
    ROBOTIQ_2F85_STROKE_M * (1.0 - gripper_position.clamp(0.0, 1.0))
}

/// What to read.
#[derive(Debug, Clone)]
pub struct DroidOptions {
    /// Camera roles to load (`ext1`, `ext2`, `wrist`); default the two
    /// external cameras.
    pub roles: Vec<String>,
    /// Intrinsics per camera serial.
    pub intrinsics: BTreeMap<String, Intrinsics>,
    /// Extrinsics overrides: per episode uuid (or `"*"` for all) per
    /// `<serial>_left` key.
    pub calibration: BTreeMap<String, BTreeMap<String, [f64; 6]>>,
}

impl DroidOptions {
    /// Options with intrinsics read from `intrinsics_file` and, optionally,
    /// extrinsics overrides from `calibration_file`.
    pub fn from_files(
        intrinsics_file: &Path,
        calibration_file: Option<&Path>,
    ) -> Result<Self, RawError> {
        Ok(Self {
            roles: vec!["ext1".into(), "ext2".into()],
            intrinsics: read_intrinsics(intrinsics_file)?,
            calibration: match calibration_file {
                Some(p) => read_calibration(p)?,
                None => BTreeMap::new(),
            },
        })
    }
}

/// Parses an intrinsics file: `{"<serial>": {"fx", "fy", "cx", "cy", "width", "height"}}`.
pub fn read_intrinsics(path: &Path) -> Result<BTreeMap<String, Intrinsics>, RawError> {
    let v = read_json(path)?;
    let map = v
        .as_object()
        .ok_or_else(|| json_err(path, "", "expected an object keyed by camera serial"))?;
    let mut out = BTreeMap::new();
    for (serial, k) in map {
        let intr = json_intrinsics(path, k, serial, ["fx", "fy", "cx", "cy"], None)?;
        out.insert(serial.clone(), intr);
    }
    Ok(out)
}

/// Parses an extrinsics override file (see the module docs). Top-level keys
/// ending in `_left`/`_right` are camera keys applying to every episode
/// (stored under `"*"`); other keys are episode uuids.
pub fn read_calibration(
    path: &Path,
) -> Result<BTreeMap<String, BTreeMap<String, [f64; 6]>>, RawError> {
    let v = read_json(path)?;
    let map = v.as_object().ok_or_else(|| {
        json_err(
            path,
            "",
            "expected an object keyed by episode uuid or camera",
        )
    })?;
    let mut out: BTreeMap<String, BTreeMap<String, [f64; 6]>> = BTreeMap::new();
    let six = |field: &str, x: &Value| -> Result<[f64; 6], RawError> {
        let v = json_vec(path, x, field, 6)?;
        Ok([v[0], v[1], v[2], v[3], v[4], v[5]])
    };
    for (key, x) in map {
        if key.ends_with("_left") || key.ends_with("_right") {
            out.entry("*".into())
                .or_default()
                .insert(key.clone(), six(key, x)?);
        } else {
            let cams = x.as_object().ok_or_else(|| {
                json_err(
                    path,
                    key,
                    "expected an object of <serial>_left: [x, y, z, rx, ry, rz]",
                )
            })?;
            for (cam, e) in cams {
                out.entry(key.clone())
                    .or_default()
                    .insert(cam.clone(), six(&format!("{key}.{cam}"), e)?);
            }
        }
    }
    Ok(out)
}

/// Every DROID episode directory under `root` (directories holding a
/// `trajectory.h5`), sorted.
pub fn find_episodes(root: &Path) -> Result<Vec<PathBuf>, RawError> {
    if !root.is_dir() {
        return Err(RawError::Missing {
            path: root.to_path_buf(),
            what: "DROID dataset directory".into(),
        });
    }
    let mut out = Vec::new();
    let mut stack = vec![root.to_path_buf()];
    while let Some(dir) = stack.pop() {
        if dir.join("trajectory.h5").is_file() {
            out.push(dir);
            continue;
        }
        for entry in std::fs::read_dir(&dir).map_err(io_err(&dir))? {
            let entry = entry.map_err(io_err(&dir))?;
            if entry.file_type().map_err(io_err(&dir))?.is_dir() {
                stack.push(entry.path());
            }
        }
    }
    out.sort();
    Ok(out)
}

fn metadata_file(dir: &Path) -> Result<PathBuf, RawError> {
    let mut found: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io_err(dir))?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| {
            p.file_name()
                .and_then(|n| n.to_str())
                .is_some_and(|n| n.starts_with("metadata") && n.ends_with(".json"))
        })
        .collect();
    found.sort();
    match found.len() {
        1 => Ok(found.remove(0)),
        0 => Err(RawError::Missing {
            path: dir.join("metadata_*.json"),
            what: "DROID episode metadata".into(),
        }),
        n => Err(RawError::Inconsistent {
            episode: dir.display().to_string(),
            message: format!("{n} metadata_*.json files, expected one"),
        }),
    }
}

/// Reads one DROID episode directory.
pub fn read_episode(dir: &Path, options: &DroidOptions) -> Result<RawEpisode, RawError> {
    let meta_path = metadata_file(dir)?;
    let meta = read_json(&meta_path)?;
    let text = |field: &str| -> Option<String> {
        meta.get(field).and_then(|v| match v {
            Value::String(s) => Some(s.clone()),
            Value::Number(n) => Some(n.to_string()),
            _ => None,
        })
    };
    let id = text("uuid").ok_or_else(|| {
        json_err(
            &meta_path,
            "uuid",
            "missing: expected the episode's uuid string",
        )
    })?;
    let h5 = H5::open(&dir.join("trajectory.h5"))?;
    let joints = h5
        .read_shaped("observation/robot_state/joint_positions", &[None, Some(7)])?
        .rows();
    let frames = joints.len();
    let grip = h5.read_shaped("observation/robot_state/gripper_position", &[Some(frames)])?;
    let cart = h5
        .read_shaped(
            "observation/robot_state/cartesian_position",
            &[Some(frames), Some(6)],
        )?
        .rows();
    if let Some(t) = meta.get("trajectory_length") {
        if t.as_u64() != Some(frames as u64) {
            return Err(json_err(
                &meta_path,
                "trajectory_length",
                format!("{t}, but trajectory.h5 has {frames} states"),
            ));
        }
    }
    let mut grippers = Vec::with_capacity(frames);
    for (t, &g) in grip.values.iter().enumerate() {
        if !(-0.05..=1.05).contains(&g) {
            return Err(RawError::Hdf5 {
                path: h5.path().to_path_buf(),
                field: "observation/robot_state/gripper_position".into(),
                message: format!("frame {t}: {g}, expected a closure in [0, 1]"),
            });
        }
        grippers.push(vec![g.clamp(0.0, 1.0)]);
    }
    let ee_actions = cart
        .iter()
        .zip(&grippers)
        .map(|(c, g)| {
            let mut row = c.clone();
            row.push(g[0]);
            row
        })
        .collect();

    let overrides = |key: &str| -> Option<[f64; 6]> {
        options
            .calibration
            .get(&id)
            .and_then(|m| m.get(key))
            .or_else(|| options.calibration.get("*").and_then(|m| m.get(key)))
            .copied()
    };
    let mut views = Vec::new();
    for role in &options.roles {
        if !ROLES.contains(&role.as_str()) {
            return Err(RawError::Inconsistent {
                episode: id.clone(),
                message: format!("camera role \"{role}\": expected one of {ROLES:?}"),
            });
        }
        let field = format!("{role}_cam_serial");
        let serial = text(&field).ok_or_else(|| {
            json_err(
                &meta_path,
                &field,
                "missing: expected the camera's serial number",
            )
        })?;
        let video = text(&format!("{role}_mp4_path"))
            .map(|p| dir.join(p))
            .filter(|p| p.is_file())
            .unwrap_or_else(|| dir.join(format!("recordings/MP4/{serial}.mp4")));
        if !video.is_file() {
            return Err(RawError::Missing {
                path: video,
                what: format!("video of camera {role} ({serial})"),
            });
        }
        let intrinsics = *options.intrinsics.get(&serial).ok_or_else(|| RawError::Inconsistent {
            episode: id.clone(),
            message: format!(
                "no intrinsics for camera {role} (serial {serial}) in the intrinsics file: DROID does not record them, add an entry \"{serial}\""
            ),
        })?;
        let key = format!("{serial}_left");
        let world_from_camera: Vec<Isometry3<f64>> = match overrides(&key) {
            Some(e) => vec![world_from_camera_from_xyz_rpy(e); frames],
            None => h5
                .read_shaped(
                    &format!("observation/camera_extrinsics/{key}"),
                    &[Some(frames), Some(6)],
                )?
                .rows()
                .iter()
                .map(|r| world_from_camera_from_xyz_rpy([r[0], r[1], r[2], r[3], r[4], r[5]]))
                .collect(),
        };
        views.push(RawView {
            name: serial,
            video,
            intrinsics,
            world_from_camera,
        });
    }
    let ep = RawEpisode {
        id,
        source: dir.to_path_buf(),
        task: text("current_task").filter(|t| !t.is_empty()),
        frames,
        joints,
        joint_names: JOINT_NAMES.iter().map(|s| s.to_string()).collect(),
        grippers,
        ee_actions,
        views,
    };
    ep.validate()?;
    Ok(ep)
}
