//! The inputs of a calibration: one episode's video (decoded, reduced to the
//! analysis grid) and the robot's joints per frame, from a trajectory file
//! (as `bridgev2w masks --joints` reads it) or a DROID annotation JSON of the
//! Ctrl-World layout (`joints`, or the 15 Hz `observation.state.*` arrays).

use super::CalibrateError;
use crate::video::VideoStream;
use bridgev2w_embodiment::actions::Trajectory;
use bridgev2w_embodiment::embodiment::Embodiment;
use std::path::{Path, PathBuf};

/// One episode to calibrate from (or to check a calibration on).
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeInput {
    /// The camera's video (MP4, H.264 or AV1).
    pub video: PathBuf,
    /// Joint states: a trajectory file (`.json` array of arrays, `.csv`,
    /// `.npy`; one column per actuated joint of the robot, URDF order) or a
    /// DROID annotation JSON (an object with `joints` T x 8, or
    /// `observation.state.joint_position` and `.gripper_position`).
    pub joints: PathBuf,
}

/// Pairs videos with joint files in order (`--video` with `--joints`, or
/// `--check-video` with `--check-joints`): the counts must match.
pub fn pair_inputs(
    videos: &[PathBuf],
    joints: &[PathBuf],
    (video_flag, joints_flag): (&'static str, &'static str),
) -> Result<Vec<EpisodeInput>, CalibrateError> {
    if videos.len() != joints.len() {
        return Err(CalibrateError::Option {
            field: joints_flag,
            value: format!(
                "given {} times for {} {video_flag}",
                joints.len(),
                videos.len()
            ),
            expected: format!("one {joints_flag} per {video_flag}, in the same order"),
        });
    }
    Ok(videos
        .iter()
        .zip(joints)
        .map(|(v, j)| EpisodeInput {
            video: v.clone(),
            joints: j.clone(),
        })
        .collect())
}

/// An episode in memory: its frames on the analysis grid and the robot's
/// configuration in each.
#[derive(Debug, Clone)]
pub struct EpisodeData {
    /// A name for reports (the video's path unless set otherwise).
    pub name: String,
    /// The video's own size (pixels): the calibration is written at it.
    pub video_size: (u32, u32),
    /// Integer reduction of the video to the analysis grid (1 = none): an
    /// analysis pixel is the mean of a `factor` x `factor` block.
    pub factor: u32,
    /// Analysis grid width (pixels).
    pub width: usize,
    /// Analysis grid height (pixels).
    pub height: usize,
    /// Frames, RGB8 row-major on the analysis grid.
    pub frames: Vec<Vec<u8>>,
    /// Full joint configuration (the robot's actuated joints) per frame.
    pub joints: Vec<Vec<f64>>,
    /// What was adapted on reading (frame-count mismatch, subsampling).
    pub notes: Vec<String>,
    /// Hand marks of the tool point (see [`super::marks`]); none unless
    /// given.
    pub marks: Vec<super::marks::Mark>,
}

impl EpisodeData {
    /// Builds an episode from frames already on the analysis grid (the
    /// video's own size when `factor` is 1), checking sizes and counts.
    pub fn new(
        name: &str,
        video_size: (u32, u32),
        factor: u32,
        (width, height): (usize, usize),
        frames: Vec<Vec<u8>>,
        joints: Vec<Vec<f64>>,
    ) -> Result<Self, CalibrateError> {
        let bad = |message: String| CalibrateError::Episode {
            episode: name.to_string(),
            message,
        };
        if frames.len() != joints.len() {
            return Err(bad(format!(
                "{} frames but {} joint rows: expected one configuration per frame",
                frames.len(),
                joints.len()
            )));
        }
        if let Some((t, f)) = frames
            .iter()
            .enumerate()
            .find(|(_, f)| f.len() != width * height * 3)
        {
            return Err(bad(format!(
                "frame {t} has {} bytes: expected {width}x{height}x3",
                f.len()
            )));
        }
        Ok(Self {
            name: name.to_string(),
            video_size,
            factor,
            width,
            height,
            frames,
            joints,
            notes: Vec::new(),
            marks: Vec::new(),
        })
    }
}

/// The analysis grid's reduction factor for a video `width` pixels wide:
/// the smallest integer that brings it to at most `max_width`.
pub fn analysis_factor(width: u32, max_width: u32) -> u32 {
    width.div_ceil(max_width.max(1)).max(1)
}

/// Reads an episode: decodes the video frame by frame onto the analysis
/// grid (at most `max_width` wide) and reads the joints as configurations of
/// `embodiment`. A video with one frame more or fewer than joint rows (a
/// known DROID quirk) is cut to the shorter, noted; a larger mismatch is an
/// error naming both counts.
pub fn load_episode(
    input: &EpisodeInput,
    embodiment: &Embodiment,
    max_width: u32,
) -> Result<EpisodeData, CalibrateError> {
    let name = input.video.display().to_string();
    let mut stream = VideoStream::open(&input.video)?;
    let info = stream.info().clone();
    let (vw, vh) = (info.width as u32, info.height as u32);
    let factor = analysis_factor(vw, max_width);
    let (w, h) = (info.width / factor as usize, info.height / factor as usize);
    let mut frames = Vec::with_capacity(info.frames);
    while let Some(f) = stream.next_frame()? {
        frames.push(reduce_rgb(&f.rgb, info.width, factor as usize, (w, h)));
    }
    let (joints, mut notes) = read_joints(&input.joints, embodiment, frames.len())?;
    let n = frames.len().min(joints.len());
    if frames.len() != joints.len() {
        let diff = frames.len().abs_diff(joints.len());
        if diff > 1 {
            return Err(CalibrateError::Episode {
                episode: name,
                message: format!(
                    "{} video frames but {} joint rows from {}: expected equal counts (one more or fewer is tolerated)",
                    frames.len(),
                    joints.len(),
                    input.joints.display()
                ),
            });
        }
        notes.push(format!(
            "{} video frames and {} joint rows: the last {} dropped",
            frames.len(),
            joints.len(),
            if frames.len() > joints.len() {
                "frame"
            } else {
                "joint row"
            }
        ));
    }
    frames.truncate(n);
    let joints = joints[..n].to_vec();
    let mut data = EpisodeData::new(&name, (vw, vh), factor, (w, h), frames, joints)?;
    data.notes = notes;
    Ok(data)
}

/// Box-averages an RGB8 frame of `src_width` pixels per row by `factor` onto
/// a `w` x `h` grid (a copy when `factor` is 1).
pub fn reduce_rgb(rgb: &[u8], src_width: usize, factor: usize, (w, h): (usize, usize)) -> Vec<u8> {
    if factor == 1 {
        return rgb[..w * h * 3].to_vec();
    }
    let mut out = vec![0u8; w * h * 3];
    let area = (factor * factor) as u32;
    for y in 0..h {
        for x in 0..w {
            let mut sum = [0u32; 3];
            for dy in 0..factor {
                let row = (y * factor + dy) * src_width;
                for dx in 0..factor {
                    let i = (row + x * factor + dx) * 3;
                    for (c, s) in sum.iter_mut().enumerate() {
                        *s += u32::from(rgb[i + c]);
                    }
                }
            }
            let o = (y * w + x) * 3;
            for (c, s) in sum.iter().enumerate() {
                out[o + c] = ((s + area / 2) / area) as u8;
            }
        }
    }
    out
}

fn joints_err(path: &Path, message: impl Into<String>) -> CalibrateError {
    CalibrateError::Joints {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// Joint configurations from `path` (see [`EpisodeInput::joints`]) with
/// notes; `video_frames` sets the subsampling of DROID's 15 Hz arrays.
pub fn read_joints(
    path: &Path,
    embodiment: &Embodiment,
    video_frames: usize,
) -> Result<(Vec<Vec<f64>>, Vec<String>), CalibrateError> {
    let is_json = path
        .extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("json"));
    if is_json {
        let text = std::fs::read_to_string(path).map_err(|e| joints_err(path, e.to_string()))?;
        let value: serde_json::Value = serde_json::from_str(&text)
            .map_err(|e| joints_err(path, format!("invalid JSON: {e}")))?;
        if let serde_json::Value::Object(map) = value {
            return droid_annotation_joints(path, &map, embodiment, video_frames);
        }
    }
    let t = Trajectory::read(path).map_err(|e| joints_err(path, e.to_string()))?;
    let robot = &embodiment.robot;
    if t.dim() != robot.dof() {
        return Err(joints_err(
            path,
            format!(
                "{} values per frame but robot \"{}\" has {} actuated joints ({}): expected one column per joint (or a DROID annotation JSON object)",
                t.dim(),
                robot.name,
                robot.dof(),
                robot.dof_names().join(", ")
            ),
        ));
    }
    Ok((t.rows, Vec::new()))
}

/// A numeric matrix field of a DROID annotation (`rows` x `cols`, finite).
fn matrix_field(
    path: &Path,
    map: &serde_json::Map<String, serde_json::Value>,
    field: &str,
    cols: Option<usize>,
) -> Result<Option<Vec<Vec<f64>>>, CalibrateError> {
    let Some(v) = map.get(field) else {
        return Ok(None);
    };
    let bad = |what: String| joints_err(path, format!("field \"{field}\": {what}"));
    let rows = v
        .as_array()
        .ok_or_else(|| bad("expected an array of frames".into()))?;
    let mut out = Vec::with_capacity(rows.len());
    for (t, row) in rows.iter().enumerate() {
        let values: Vec<f64> = match row {
            serde_json::Value::Number(n) => vec![n.as_f64().unwrap_or(f64::NAN)],
            serde_json::Value::Array(items) => items
                .iter()
                .map(|x| x.as_f64().unwrap_or(f64::NAN))
                .collect(),
            other => return Err(bad(format!("frame {t} is {other}: expected numbers"))),
        };
        if let Some(c) = cols {
            if values.len() != c {
                return Err(bad(format!(
                    "frame {t} has {} values: expected {c}",
                    values.len()
                )));
            }
        }
        if let Some(x) = values.iter().find(|x| !x.is_finite()) {
            return Err(bad(format!("frame {t} holds {x}: expected finite numbers")));
        }
        out.push(values);
    }
    if out.is_empty() {
        return Err(bad("no frames".into()));
    }
    Ok(Some(out))
}

/// DROID's 7 Franka joints + gripper closure (0 open, 1 closed) per frame
/// to configurations of `embodiment` (its `panda_joint1..7` and its first
/// end effector's gripper joint; the rest at home).
fn droid_annotation_joints(
    path: &Path,
    map: &serde_json::Map<String, serde_json::Value>,
    embodiment: &Embodiment,
    video_frames: usize,
) -> Result<(Vec<Vec<f64>>, Vec<String>), CalibrateError> {
    let robot = &embodiment.robot;
    let dofs: Vec<usize> = (1..=7)
        .map(|i| {
            robot.dof_index(&format!("panda_joint{i}")).ok_or_else(|| {
                joints_err(
                    path,
                    format!(
                        "a DROID annotation records Franka joints but robot \"{}\" has no actuated joint \"panda_joint{i}\": expected a Franka (e.g. --robot franka-robotiq)",
                        robot.name
                    ),
                )
            })
        })
        .collect::<Result<_, _>>()?;
    let mut notes = Vec::new();
    let rows: Vec<(Vec<f64>, f64)> = if let Some(j) = matrix_field(path, map, "joints", Some(8))? {
        j.into_iter().map(|r| (r[..7].to_vec(), r[7])).collect()
    } else {
        let field = "observation.state.joint_position";
        let Some(arm) = matrix_field(path, map, field, Some(7))? else {
            return Err(joints_err(
                path,
                "a JSON object without \"joints\" or \"observation.state.joint_position\": expected a DROID annotation (Ctrl-World layout) or an array of joint rows",
            ));
        };
        let grip = matrix_field(path, map, "observation.state.gripper_position", Some(1))?
            .ok_or_else(|| {
                joints_err(
                    path,
                    "\"observation.state.joint_position\" without \"observation.state.gripper_position\": expected both",
                )
            })?;
        if grip.len() != arm.len() {
            return Err(joints_err(
                path,
                format!(
                    "{} joint rows but {} gripper rows: expected equal counts",
                    arm.len(),
                    grip.len()
                ),
            ));
        }
        // droid_subset: the video is the 15 Hz record taken every third
        // state (frame k = raw index 3k); in general the stride that gives
        // the video's frame count.
        let stride = ((arm.len() as f64 / video_frames.max(1) as f64).round() as usize).max(1);
        let picked: Vec<(Vec<f64>, f64)> = arm
            .iter()
            .zip(&grip)
            .step_by(stride)
            .map(|(a, g)| (a.clone(), g[0]))
            .collect();
        notes.push(format!(
            "{} rows of \"{field}\" taken every {stride} (frame k = row {stride}k) for {video_frames} video frames",
            arm.len()
        ));
        picked
    };
    let limits = robot.dof_limits();
    let ee = embodiment.end_effectors.first();
    let out = rows
        .into_iter()
        .map(|(arm, g)| {
            let mut q = embodiment.home.clone();
            for (&d, &v) in dofs.iter().zip(&arm) {
                q[d] = v;
            }
            if let Some(ee) = ee {
                if let Some(d) = ee.gripper_dof {
                    q[d] = ee.gripper_joint_value(g, limits[d]);
                }
            }
            q
        })
        .collect();
    Ok((out, notes))
}
