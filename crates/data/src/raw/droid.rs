//! DROID raw episodes, in the layout of the released `droid_raw` data
//! (droid-dataset/droid, `docs/the-droid-dataset.md`):
//!
//! ```text
//! <episode>/metadata_<uuid>.json        uuid (= "<lab>+<8 hex>+<date>", the episode id of
//!                                       DROID's annotation files), current_task,
//!                                       trajectory_length, {ext1,ext2,wrist}_cam_serial,
//!                                       {ext1,ext2,wrist}_mp4_path
//! <episode>/trajectory.h5               observation/robot_state/{joint_positions [T,7],
//!                                       gripper_position [T], cartesian_position [T,6]},
//!                                       observation/camera_extrinsics/<serial>_{left,right} [T,6],
//!                                       observation/timestamp/cameras/<serial>_{frame_received,
//!                                       estimated_capture,...} [T] (ms)
//! <episode>/recordings/MP4/<serial>.mp4         the camera's left image (1280x720)
//! <episode>/recordings/MP4/<serial>-stereo.mp4  left and right side by side (not read)
//! <episode>/recordings/MP4/<serial>_timestamps.json  (where present) per-frame ms, matched to
//!                                       `_frame_received` by DROID's own MP4 reader
//! ```
//!
//! The raw episodes carry no intrinsics (only the SVO files do); DROID
//! publishes them, with re-calibrated extrinsics, as `intrinsics.json` and
//! `cam2base_extrinsics.json` / `cam2base_extrinsic_superset.json`: these
//! are read as published ([`super::droid_calibration`], which also says
//! which eye a pose belongs to), as are the project's simple layouts. An
//! episode without published extrinsics uses the recorded
//! `<serial>_left` extrinsics, with a counted warning in the conversion
//! report (or is refused with [`MissingCalibration::Error`]). Extrinsics are
//! DROID's `[x, y, z, rx, ry, rz]` = `world_from_camera` with extrinsic XYZ
//! Euler angles ([`world_from_camera_from_xyz_rpy`]).
//!
//! The robot is a Franka Panda (`panda_joint1..7`) with a Robotiq 2F-85
//! gripper: `gripper_position` is its normalised closure (0 open, 1 closed),
//! i.e. an opening of [`ROBOTIQ_2F85_STROKE_M`]` * (1 - g)`.
//! `cartesian_position` is the pose of the flange, [`EE_FRAME`].
//! A video one or two frames longer or shorter than the states is aligned
//! at conversion ([`super::align`]).

use super::align::FrameTimes;
use super::droid_calibration::{find_pose, ExtrinsicsTable, IntrinsicsTable, MissingCalibration};
use super::h5::H5;
use super::report::{Eye, Note};
use super::{
    confined, confined_optional, io_err, json_err, read_json, RawEpisode, RawError, RawView,
};
use bridgev2w_embodiment::camera::world_from_camera_from_xyz_rpy;
use bridgev2w_io::confine;
use nalgebra::Isometry3;
use serde_json::Value;
use std::path::{Path, PathBuf};

/// The link whose pose `cartesian_position` is (the Franka flange).
pub const EE_FRAME: &str = "panda_link8";

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
    /// Intrinsics per camera (published `intrinsics.json` or simple layout).
    pub intrinsics: IntrinsicsTable,
    /// Extrinsics files, the first with a pose for a camera winning.
    pub calibration: Vec<ExtrinsicsTable>,
    /// What to do for a camera none of them calibrates.
    pub missing_calibration: MissingCalibration,
}

impl DroidOptions {
    /// Checks the camera roles (`--cameras`): at least one, none twice
    /// ([`super::check_camera_list`]), each one of [`ROLES`]. The error says
    /// what is wrong; the caller prefixes the flag or argument.
    pub fn check_roles(&self) -> Result<(), String> {
        super::check_camera_list(&self.roles)?;
        match self.roles.iter().find(|r| !ROLES.contains(&r.as_str())) {
            Some(r) => Err(format!("camera role {r:?}: expected one of {ROLES:?}")),
            None => Ok(()),
        }
    }

    /// Options with intrinsics read from `intrinsics_file` and, optionally,
    /// extrinsics from `calibration_file`.
    pub fn from_files(
        intrinsics_file: &Path,
        calibration_file: Option<&Path>,
    ) -> Result<Self, RawError> {
        let files: Vec<PathBuf> = calibration_file
            .map(Path::to_path_buf)
            .into_iter()
            .collect();
        Self::from_calibration_files(intrinsics_file, &files)
    }

    /// Options with intrinsics read from `intrinsics_file` and extrinsics
    /// from each of `calibration_files` (earlier files take precedence).
    pub fn from_calibration_files(
        intrinsics_file: &Path,
        calibration_files: &[PathBuf],
    ) -> Result<Self, RawError> {
        Ok(Self {
            roles: vec!["ext1".into(), "ext2".into()],
            intrinsics: IntrinsicsTable::read(intrinsics_file)?,
            calibration: calibration_files
                .iter()
                .map(|p| ExtrinsicsTable::read(p))
                .collect::<Result<_, _>>()?,
            missing_calibration: MissingCalibration::default(),
        })
    }
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
        stack.extend(super::sub_dirs(&dir)?);
    }
    out.sort();
    Ok(out)
}

/// The episode's one `metadata*.json`, a regular file inside `dir` (see
/// [`super::confined`]).
fn metadata_file(dir: &Path) -> Result<PathBuf, RawError> {
    let mut found: Vec<String> = std::fs::read_dir(dir)
        .map_err(io_err(dir))?
        .filter_map(Result::ok)
        .filter_map(|e| e.file_name().to_str().map(str::to_string))
        .filter(|n| n.starts_with("metadata") && n.ends_with(".json"))
        .collect();
    found.sort();
    match found.len() {
        1 => confined(
            dir,
            &found[0],
            confine::MAX_METADATA_BYTES,
            "DROID episode metadata",
        ),
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

/// The metadata's episode id candidates: the `uuid` field, then the id in
/// the file name (`metadata_<id>.json`) when it differs.
fn episode_ids(uuid: &str, meta_path: &Path) -> Vec<String> {
    let mut ids = vec![uuid.to_string()];
    if let Some(stem) = meta_path
        .file_stem()
        .and_then(|s| s.to_str())
        .and_then(|s| s.strip_prefix("metadata_"))
    {
        if stem != uuid {
            ids.push(stem.to_string());
        }
    }
    ids
}

/// Reads one DROID episode directory. Every file read (the metadata,
/// `trajectory.h5`, the videos, the per-frame timestamps) must be a regular
/// file of bounded size inside `dir`, symbolic links followed: a FIFO, a
/// device or a link out of the folder is refused before it is opened.
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
    let ids = episode_ids(&id, &meta_path);
    let ids: Vec<&str> = ids.iter().map(String::as_str).collect();
    let h5 = H5::open(&confined(
        dir,
        "trajectory.h5",
        confine::MAX_DATA_BYTES,
        "HDF5 file",
    )?)?;
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
    let grip_field = "observation/robot_state/gripper_position";
    let mut grippers = Vec::with_capacity(frames);
    let (mut clamped, mut worst) = (0usize, 0.5f64);
    for (t, &g) in grip.values.iter().enumerate() {
        if !(-0.05..=1.05).contains(&g) {
            return Err(RawError::Hdf5 {
                path: h5.path().to_path_buf(),
                field: grip_field.into(),
                message: format!("frame {t}: {g}, expected a closure in [0, 1]"),
            });
        }
        if !(0.0..=1.0).contains(&g) {
            clamped += 1;
            if (g - 0.5).abs() > (worst - 0.5).abs() {
                worst = g;
            }
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
    let mut ep = RawEpisode {
        id: id.clone(),
        source: dir.to_path_buf(),
        task: text("current_task").filter(|t| !t.is_empty()),
        frames,
        joints,
        joint_names: JOINT_NAMES.iter().map(|s| s.to_string()).collect(),
        grippers,
        ee_actions,
        ee_frames: vec![EE_FRAME.to_string()],
        views: Vec::new(),
        notes: Vec::new(),
    };
    if clamped > 0 {
        ep.note(
            None,
            Note::GripperClamped {
                arm: 0,
                field: grip_field.into(),
                count: clamped,
                worst,
                open: 0.0,
                closed: 1.0,
            },
        );
    }

    // Calibration keys of this episode's entries that match none of its cameras.
    let serials: Vec<String> = ROLES
        .iter()
        .filter_map(|r| text(&format!("{r}_cam_serial")))
        .collect();
    for table in &options.calibration {
        if let (Some(_), poses) = table.entry(&ids) {
            for p in poses {
                if !serials.contains(&p.camera.serial) {
                    ep.note(
                        None,
                        Note::CalibrationKeyUnmatched {
                            file: table.file.clone(),
                            key: p.key.clone(),
                        },
                    );
                }
            }
        }
    }

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
        let video = camera_video(
            dir,
            &meta_path,
            role,
            &serial,
            text(&format!("{role}_mp4_path")),
        )?;
        let (intrinsics, k_key) = options.intrinsics.lookup(&ids, &serial).ok_or_else(|| {
            json_err(
                &options.intrinsics.file,
                &format!("{}.{serial}", ids[0]),
                format!(
                    "no intrinsics for camera {role} (serial {serial}) of episode {}: expected an entry \"{}\": {{\"{serial}\": [fx, cx, fy, cy]}} or a top-level \"{serial}\"",
                    ids[0], ids[0]
                ),
            )
        })?;
        let poses = view_extrinsics(&h5, options, &ids, &serial, frames, &mut ep)?;
        ep.note(
            Some(&serial),
            Note::Calibration {
                intrinsics: format!("{} [{k_key}]", options.intrinsics.file.display()),
                extrinsics: poses.source,
                eye: poses.eye,
                right_to_left: poses.right_to_left,
            },
        );
        let world_from_camera = poses.world_from_camera;
        let frame_times = read_frame_times(&h5, dir, &video, &serial)?;
        ep.views.push(RawView {
            name: serial,
            video,
            intrinsics,
            world_from_camera,
            frame_times,
            split: None,
        });
    }
    ep.validate()?;
    Ok(ep)
}

/// The video of camera `role` (serial `serial`) of the episode in `dir`:
/// the metadata's `<role>_mp4_path` where it names a file, else
/// `recordings/MP4/<serial>.mp4`. Both are confined to `dir`: a relative
/// path without `..` that resolves (links followed) inside the folder, to a
/// regular file of at most [`confine::MAX_VIDEO_BYTES`]; the serial must be
/// a plain serial number. A recorded path that does not exist falls back
/// (DROID's metadata records paths relative to the lab's folder); any
/// other refusal is an error naming the metadata file and the field.
fn camera_video(
    dir: &Path,
    meta_path: &Path,
    role: &str,
    serial: &str,
    mp4_path: Option<String>,
) -> Result<PathBuf, RawError> {
    let serial_field = format!("{role}_cam_serial");
    if serial.is_empty()
        || !serial
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_')
    {
        return Err(json_err(
            meta_path,
            &serial_field,
            format!("{serial:?}: expected a plain serial number (letters, digits, '-', '_')"),
        ));
    }
    if let Some(p) = mp4_path {
        match confine::confined_file(dir, &p, confine::MAX_VIDEO_BYTES) {
            Ok(video) => return Ok(video),
            Err(e) if e.is_missing() => {}
            Err(e) => {
                return Err(json_err(
                    meta_path,
                    &format!("{role}_mp4_path"),
                    e.to_string(),
                ))
            }
        }
    }
    let fallback = format!("recordings/MP4/{serial}.mp4");
    match confine::confined_file(dir, &fallback, confine::MAX_VIDEO_BYTES) {
        Ok(video) => Ok(video),
        Err(e) if e.is_missing() => Err(RawError::Missing {
            path: dir.join(fallback),
            what: format!("video of camera {role} ({serial})"),
        }),
        Err(e) => Err(json_err(
            meta_path,
            &serial_field,
            format!("the camera's video {fallback}: {e}"),
        )),
    }
}

/// A camera's extrinsics and where they came from.
struct ViewPoses {
    /// Per state, of the left image.
    world_from_camera: Vec<Isometry3<f64>>,
    /// File and key (or the recorded dataset).
    source: String,
    /// The eye the pose was given for.
    eye: Eye,
    /// Whether a right-eye pose was moved to the left eye.
    right_to_left: bool,
}

/// `world_from_camera` per state for camera `serial`'s left image: the first
/// calibration file's pose for it (a right-eye pose moved to the left eye
/// with the recorded stereo offset), else the recorded `<serial>_left`
/// extrinsics (noted, or refused).
fn view_extrinsics(
    h5: &H5,
    options: &DroidOptions,
    ids: &[&str],
    serial: &str,
    frames: usize,
    ep: &mut RawEpisode,
) -> Result<ViewPoses, RawError> {
    let recorded = |eye: Eye| -> Result<Vec<Isometry3<f64>>, RawError> {
        Ok(h5
            .read_shaped(
                &format!("observation/camera_extrinsics/{serial}_{eye}"),
                &[Some(frames), Some(6)],
            )?
            .rows()
            .iter()
            .map(|r| world_from_camera_from_xyz_rpy([r[0], r[1], r[2], r[3], r[4], r[5]]))
            .collect())
    };
    let mut searched = Vec::new();
    for table in &options.calibration {
        let (entry, poses) = table.entry(ids);
        let Some(p) = find_pose(poses, serial) else {
            searched.push(match entry {
                Some(e) => format!(
                    "{}: entry \"{e}\" has no key \"{serial}\"",
                    table.file.display()
                ),
                None => format!("{}: no entry for episode {}", table.file.display(), ids[0]),
            });
            continue;
        };
        let source = format!(
            "{} [{}{}]",
            table.file.display(),
            entry.map_or(String::new(), |e| format!("{e}.")),
            p.key
        );
        let pose = world_from_camera_from_xyz_rpy(p.pose);
        return match p.camera.eye() {
            Eye::Left => Ok(ViewPoses {
                world_from_camera: vec![pose; frames],
                source,
                eye: Eye::Left,
                right_to_left: false,
            }),
            Eye::Right => {
                let field = format!("observation/camera_extrinsics/{serial}_right");
                if !h5.has(&field) {
                    return Err(RawError::Inconsistent {
                        episode: ep.id.clone(),
                        message: format!(
                            "{source} is a pose of camera {serial}'s right eye, but the video is its left image and {} records no \"{field}\" to take the stereo offset from (DROID publishes no per-camera baseline): give a left-eye pose",
                            h5.path().display()
                        ),
                    });
                }
                let (l, r) = (recorded(Eye::Left)?, recorded(Eye::Right)?);
                let right_from_left = r[0].inverse() * l[0];
                Ok(ViewPoses {
                    world_from_camera: vec![pose * right_from_left; frames],
                    source,
                    eye: Eye::Right,
                    right_to_left: true,
                })
            }
        };
    }
    let files: Vec<PathBuf> = options.calibration.iter().map(|t| t.file.clone()).collect();
    let reason = if files.is_empty() {
        "no calibration file given".to_string()
    } else {
        searched.join("; ")
    };
    if options.missing_calibration == MissingCalibration::Error {
        return Err(RawError::Inconsistent {
            episode: ep.id.clone(),
            message: format!("camera {serial}: no published extrinsics ({reason})"),
        });
    }
    ep.note(
        Some(serial),
        Note::CalibrationMissing {
            files,
            reason: format!("{reason}: the recorded extrinsics are used"),
        },
    );
    let field = format!("observation/camera_extrinsics/{serial}_left");
    Ok(ViewPoses {
        world_from_camera: recorded(Eye::Left)?,
        source: format!("{} [{field}]", h5.path().display()),
        eye: Eye::Left,
        right_to_left: false,
    })
}

/// The recorded timestamps matching `video`'s frames to the states, when
/// both sides are present: `<video stem>_timestamps.json` (a list of ms per
/// frame) and `observation/timestamp/cameras/<serial>_frame_received`. The
/// JSON file, beside `video` in the episode folder `dir`, must be a regular
/// file inside `dir` ([`confined_optional`]).
fn read_frame_times(
    h5: &H5,
    dir: &Path,
    video: &Path,
    serial: &str,
) -> Result<Option<FrameTimes>, RawError> {
    let name = format!(
        "{}_timestamps.json",
        video.file_stem().and_then(|s| s.to_str()).unwrap_or(serial)
    );
    let field = format!("observation/timestamp/cameras/{serial}_frame_received");
    // `video` is `dir` joined with a checked relative path.
    let Ok(rel) = video.strip_prefix(dir).map(|r| r.with_file_name(&name)) else {
        return Ok(None);
    };
    if !h5.has(&field) {
        return Ok(None);
    }
    let rel = rel.to_string_lossy();
    let Some(json) = confined_optional(dir, &rel, confine::MAX_METADATA_BYTES)? else {
        return Ok(None);
    };
    let v = read_json(&json)?;
    let video_ms = v
        .as_array()
        .and_then(|a| a.iter().map(Value::as_f64).collect::<Option<Vec<f64>>>())
        .ok_or_else(|| json_err(&json, "", "expected a list of per-frame timestamps (ms)"))?;
    let state_ms = h5.read_shaped(&field, &[None])?.values;
    Ok(Some(FrameTimes { video_ms, state_ms }))
}
