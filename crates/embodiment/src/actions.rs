//! Action and joint trajectories: reading them from JSON, CSV or `.npy`, and
//! turning end-effector actions into joint trajectories with IK.
//!
//! Layouts (one row per frame):
//! - single arm, 7-D: `[x, y, z, roll, pitch, yaw, gripper]`;
//! - dual arm, 14-D: the left arm's 7 values, then the right arm's;
//! - joints: one value per actuated joint in URDF order
//!   (`bridgev2w robot-info` prints it).
//!
//! Positions are metres in the robot's root (base) frame; angles radians,
//! extrinsic XYZ (see [`crate::kinematics::pose_from_xyz_rpy`]). `gripper`
//! is in `[0, 1]`: 0 = open (finger joint at its upper limit), 1 = closed
//! (lower limit), the DROID convention.

use crate::kinematics::{pose_from_xyz_rpy, IkOptions, IkSolver};
use crate::robot::Robot;
use bridgev2w_io::FileError;
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Errors reading trajectories or converting actions; each names the file
/// (or input) and, where it applies, the frame and column.
#[derive(Debug, thiserror::Error)]
pub enum ActionError {
    /// I/O failure.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The file's content is not a numeric table.
    #[error("{source_name}: {message}")]
    Format {
        /// File path or input name.
        source_name: String,
        /// What is wrong, with frame/column/value where known.
        message: String,
    },
    /// The IK could not reach a target within tolerance.
    #[error(transparent)]
    Unreachable(Box<Unreachable>),
}

/// An end-effector target the IK could not reach.
#[derive(Debug, Clone, thiserror::Error)]
#[error("{source_name}: frame {frame}, arm \"{arm}\": end-effector target {target:?} not reached: residual {position_mm:.2} mm / {rotation_deg:.2} deg (tolerance {tol_mm:.2} mm / {tol_deg:.2} deg); the pose may be outside the workspace or joint limits (use --allow-ik-residual to render anyway and flag the frames)")]
pub struct Unreachable {
    /// File path or input name.
    pub source_name: String,
    /// Frame index.
    pub frame: usize,
    /// Arm name.
    pub arm: String,
    /// `[x, y, z, roll, pitch, yaw]` requested.
    pub target: [f64; 6],
    /// Remaining position error.
    pub position_mm: f64,
    /// Remaining rotation error.
    pub rotation_deg: f64,
    /// Position tolerance.
    pub tol_mm: f64,
    /// Rotation tolerance.
    pub tol_deg: f64,
}

/// A numeric table: `rows[frame][column]`.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// Where it came from (for messages).
    pub source_name: String,
    /// One row per frame, all the same length, all finite.
    pub rows: Vec<Vec<f64>>,
}

impl Trajectory {
    /// Builds a trajectory from rows, checking shape and values.
    pub fn new(source_name: &str, rows: Vec<Vec<f64>>) -> Result<Self, ActionError> {
        let fmt = |message: String| ActionError::Format {
            source_name: source_name.to_string(),
            message,
        };
        let Some(first) = rows.first() else {
            return Err(fmt("no frames: expected at least one row".into()));
        };
        let dim = first.len();
        if dim == 0 {
            return Err(fmt(
                "frame 0 is empty: expected at least one value per row".into()
            ));
        }
        for (f, row) in rows.iter().enumerate() {
            if row.len() != dim {
                return Err(fmt(format!(
                    "frame {f} has {} values but frame 0 has {dim}: every row must have the same length",
                    row.len()
                )));
            }
            if let Some((c, v)) = row.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(fmt(format!(
                    "frame {f}, column {c}: value {v} is not a finite number"
                )));
            }
        }
        Ok(Self {
            source_name: source_name.to_string(),
            rows,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.rows.len()
    }

    /// Whether there are no frames (never true for a validated trajectory).
    pub fn is_empty(&self) -> bool {
        self.rows.is_empty()
    }

    /// Values per frame.
    pub fn dim(&self) -> usize {
        self.rows.first().map_or(0, Vec::len)
    }

    /// Reads `.json` (array of arrays of numbers), `.csv` (optional header
    /// row) or `.npy` (2-D numeric array, or 1-D for a single frame).
    pub fn read(path: &Path) -> Result<Self, ActionError> {
        let name = path.display().to_string();
        let ext = path
            .extension()
            .map(|e| e.to_string_lossy().to_ascii_lowercase())
            .unwrap_or_default();
        let rows = match ext.as_str() {
            "npy" => {
                let a = bridgev2w_io::npy::read_npy(path).map_err(|e| ActionError::Format {
                    source_name: name.clone(),
                    message: e.to_string(),
                })?;
                match a.shape.as_slice() {
                    [_] => vec![a.data],
                    [t, n] if *n > 0 => a.data.chunks(*n).take(*t).map(<[f64]>::to_vec).collect(),
                    s => {
                        return Err(ActionError::Format {
                            source_name: name,
                            message: format!("array shape {s:?}: expected [frames, values]"),
                        })
                    }
                }
            }
            "json" | "csv" => {
                let text = std::fs::read_to_string(path).map_err(|source| ActionError::Io {
                    path: path.to_path_buf(),
                    source,
                })?;
                if ext == "json" {
                    parse_json_rows(&text, &name)?
                } else {
                    parse_csv_rows(&text, &name)?
                }
            }
            other => {
                return Err(ActionError::Format {
                    source_name: name,
                    message: format!("unknown extension \"{other}\": expected .json, .csv or .npy"),
                })
            }
        };
        Self::new(&name, rows)
    }
}

/// Parses a JSON array of arrays of numbers.
pub fn parse_json_rows(text: &str, source_name: &str) -> Result<Vec<Vec<f64>>, ActionError> {
    let fmt = |message: String| ActionError::Format {
        source_name: source_name.to_string(),
        message,
    };
    let v: serde_json::Value =
        serde_json::from_str(text).map_err(|e| fmt(format!("invalid JSON: {e}")))?;
    let serde_json::Value::Array(frames) = v else {
        return Err(fmt(
            "expected a JSON array of frames, each an array of numbers".into(),
        ));
    };
    frames
        .iter()
        .enumerate()
        .map(|(f, row)| {
            let serde_json::Value::Array(vals) = row else {
                return Err(fmt(format!(
                    "frame {f}: expected an array of numbers, found {row}"
                )));
            };
            vals.iter()
                .enumerate()
                .map(|(c, x)| {
                    x.as_f64()
                        .ok_or_else(|| fmt(format!("frame {f}, column {c}: {x} is not a number")))
                })
                .collect()
        })
        .collect()
}

/// Parses CSV; a first row that is not all numbers is taken as a header.
pub fn parse_csv_rows(text: &str, source_name: &str) -> Result<Vec<Vec<f64>>, ActionError> {
    let mut reader = csv::ReaderBuilder::new()
        .has_headers(false)
        .trim(csv::Trim::All)
        .flexible(true)
        .from_reader(text.as_bytes());
    let mut rows = Vec::new();
    for (line, record) in reader.records().enumerate() {
        let record = record.map_err(|e| ActionError::Format {
            source_name: source_name.to_string(),
            message: format!("line {}: {e}", line + 1),
        })?;
        let parsed: Result<Vec<f64>, (usize, String)> = record
            .iter()
            .enumerate()
            .map(|(c, s)| s.parse::<f64>().map_err(|_| (c, s.to_string())))
            .collect();
        match parsed {
            Ok(r) if r.is_empty() => {}
            Ok(r) => rows.push(r),
            Err(_) if line == 0 => {} // header
            Err((c, s)) => {
                return Err(ActionError::Format {
                    source_name: source_name.to_string(),
                    message: format!(
                        "line {} (frame {}), column {c}: \"{s}\" is not a number",
                        line + 1,
                        rows.len()
                    ),
                })
            }
        }
    }
    Ok(rows)
}

/// One end effector of an embodiment.
#[derive(Debug, Clone, PartialEq)]
pub struct EndEffector {
    /// Arm name ("arm", "left", "right").
    pub arm: String,
    /// The link whose pose the action gives.
    pub link: usize,
    /// The actuated gripper joint (index in `q`), if any.
    pub gripper_dof: Option<usize>,
    /// Which limit of the gripper joint is closed.
    pub gripper_closed_at: GripperClosedAt,
}

impl EndEffector {
    /// The gripper joint's value for a gripper command `g` in `[0, 1]`
    /// (0 open, 1 closed), given the joint's `limits`.
    pub fn gripper_joint_value(&self, g: f64, limits: (f64, f64)) -> f64 {
        match self.gripper_closed_at {
            GripperClosedAt::Lower => gripper_to_joint(g, limits),
            GripperClosedAt::Upper => {
                let (lower, upper) = limits;
                lower + g.clamp(0.0, 1.0) * (upper - lower)
            }
        }
    }
}

/// Which limit of a gripper joint is the closed gripper.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum GripperClosedAt {
    /// Closed at the lower limit, open at the upper (parallel fingers whose
    /// joint is the opening: the Franka Hand).
    Lower,
    /// Closed at the upper limit, open at the lower (a linkage whose joint
    /// angle grows as it closes: the Robotiq 2F-85).
    Upper,
}

/// Gripper command `g` in `[0, 1]` (0 open, 1 closed) to the joint value of
/// a gripper closed at its lower limit: `upper - g * (upper - lower)`.
pub fn gripper_to_joint(g: f64, (lower, upper): (f64, f64)) -> f64 {
    upper - g.clamp(0.0, 1.0) * (upper - lower)
}

/// The IK result of one arm in one frame.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct FrameResidual {
    /// Frame index.
    pub frame: usize,
    /// Arm name.
    pub arm: String,
    /// The link whose pose the action gave (the arm's end effector: its
    /// TCP, or the link `--ee-link` named, e.g. a flange).
    pub link: String,
    /// Remaining position error (metres).
    pub position_error_m: f64,
    /// Remaining rotation error (radians).
    pub rotation_error_rad: f64,
    /// Within tolerance.
    pub reached: bool,
    /// IK iterations used.
    pub iterations: usize,
    /// Random restarts used.
    pub restarts: usize,
}

/// Converts end-effector actions to joint trajectories.
///
/// Frames are solved in order, each warm-started from the previous frame's
/// solution (the first from `q_start`), with random restarts when the warm
/// start fails. Each arm moves only the joints on its own chain that no
/// other arm's chain uses. When `allow_residual` is false, the first frame
/// whose target is not reached within tolerance is an error; otherwise all
/// frames are returned with their residuals flagged.
pub fn actions_to_joints(
    robot: &Robot,
    end_effectors: &[EndEffector],
    actions: &Trajectory,
    q_start: &[f64],
    opts: &IkOptions,
    allow_residual: bool,
) -> Result<(Vec<Vec<f64>>, Vec<FrameResidual>), ActionError> {
    let fmt = |message: String| ActionError::Format {
        source_name: actions.source_name.clone(),
        message,
    };
    let expected = 7 * end_effectors.len();
    if end_effectors.is_empty() {
        return Err(fmt(
            "the robot has no end effector configured for actions".into()
        ));
    }
    if actions.dim() != expected {
        let arms: Vec<&str> = end_effectors.iter().map(|e| e.arm.as_str()).collect();
        return Err(fmt(format!(
            "actions have {} values per frame but {} expects {expected} ([x,y,z,roll,pitch,yaw,gripper] for arm(s) {}); for joint positions use --joints",
            actions.dim(),
            robot.name,
            arms.join(", ")
        )));
    }
    robot
        .check_q(q_start, 1e-9)
        .map_err(|m| fmt(format!("start configuration: {m}")))?;
    let limits = robot.dof_limits();
    for (f, row) in actions.rows.iter().enumerate() {
        for (k, ee) in end_effectors.iter().enumerate() {
            let g = row[7 * k + 6];
            if !(-1e-6..=1.0 + 1e-6).contains(&g) {
                return Err(fmt(format!(
                    "frame {f}, column {} (gripper of arm \"{}\"): {g} is outside [0, 1] (0 = open, 1 = closed)",
                    7 * k + 6,
                    ee.arm
                )));
            }
        }
    }
    // Each arm moves the chain dofs that are not shared with another arm.
    let chains: Vec<Vec<usize>> = end_effectors
        .iter()
        .map(|ee| IkSolver::new(robot, ee.link, None).free_dofs().to_vec())
        .collect();
    let solvers: Vec<IkSolver> = end_effectors
        .iter()
        .enumerate()
        .map(|(k, ee)| {
            let own: Vec<usize> = chains[k]
                .iter()
                .copied()
                .filter(|d| {
                    chains
                        .iter()
                        .enumerate()
                        .all(|(o, c)| o == k || !c.contains(d))
                })
                .collect();
            IkSolver::new(robot, ee.link, Some(&own))
        })
        .collect();

    // Arms are independent given their own dofs: solve them in parallel,
    // each sequentially over frames (warm start).
    let per_arm: Vec<Vec<(Vec<f64>, FrameResidual)>> = end_effectors
        .par_iter()
        .enumerate()
        .map(|(k, ee)| {
            let mut q = q_start.to_vec();
            actions
                .rows
                .iter()
                .enumerate()
                .map(|(f, row)| {
                    let target = pose_from_xyz_rpy([
                        row[7 * k],
                        row[7 * k + 1],
                        row[7 * k + 2],
                        row[7 * k + 3],
                        row[7 * k + 4],
                        row[7 * k + 5],
                    ]);
                    let sol = solvers[k].solve(&target, &q, opts);
                    q = sol.q.clone();
                    (
                        sol.q,
                        FrameResidual {
                            frame: f,
                            arm: ee.arm.clone(),
                            link: robot.links[ee.link].name.clone(),
                            position_error_m: sol.position_error_m,
                            rotation_error_rad: sol.rotation_error_rad,
                            reached: sol.reached,
                            iterations: sol.iterations,
                            restarts: sol.restarts_used,
                        },
                    )
                })
                .collect()
        })
        .collect();

    let mut joints = Vec::with_capacity(actions.len());
    let mut residuals = Vec::new();
    for (f, row) in actions.rows.iter().enumerate() {
        let mut q = q_start.to_vec();
        for (k, ee) in end_effectors.iter().enumerate() {
            let (arm_q, res) = &per_arm[k][f];
            for &d in solvers[k].free_dofs() {
                q[d] = arm_q[d];
            }
            if let Some(g) = ee.gripper_dof {
                q[g] = ee.gripper_joint_value(row[7 * k + 6], limits[g]);
            }
            if !res.reached && !allow_residual {
                let t = &row[7 * k..7 * k + 6];
                return Err(ActionError::Unreachable(Box::new(Unreachable {
                    source_name: actions.source_name.clone(),
                    frame: f,
                    arm: ee.arm.clone(),
                    target: [t[0], t[1], t[2], t[3], t[4], t[5]],
                    position_mm: res.position_error_m * 1e3,
                    rotation_deg: res.rotation_error_rad.to_degrees(),
                    tol_mm: opts.position_tolerance_m * 1e3,
                    tol_deg: opts.rotation_tolerance_rad.to_degrees(),
                })));
            }
            residuals.push(res.clone());
        }
        joints.push(q);
    }
    Ok((joints, residuals))
}

/// Checks a joint trajectory against the robot (length, finite values),
/// naming the frame. Limits are not enforced here: see
/// [`Robot::limit_violations`], which reports them.
pub fn check_joint_trajectory(robot: &Robot, joints: &Trajectory) -> Result<(), ActionError> {
    for (f, q) in joints.rows.iter().enumerate() {
        robot
            .check_q(q, f64::INFINITY)
            .map_err(|m| ActionError::Format {
                source_name: joints.source_name.clone(),
                message: format!("frame {f}: {m}"),
            })?;
    }
    Ok(())
}

/// The residual report `ik.json` of an IK solve: the link each arm's
/// actions were poses of, the frames not reached, the largest position and
/// rotation errors, and every frame's residuals.
pub fn ik_report(residuals: &[FrameResidual]) -> serde_json::Value {
    let mut ee_links: Vec<(&str, &str)> = Vec::new();
    for r in residuals {
        if !ee_links.iter().any(|(arm, _)| *arm == r.arm) {
            ee_links.push((&r.arm, &r.link));
        }
    }
    serde_json::json!({
        "ee_links": ee_links.iter().map(|(arm, link)| serde_json::json!({"arm": arm, "link": link})).collect::<Vec<_>>(),
        "frames_not_reached": residuals.iter().filter(|r| !r.reached).map(|r| r.frame).collect::<Vec<_>>(),
        "max_position_error_m": residuals.iter().map(|r| r.position_error_m).fold(0.0, f64::max),
        "max_rotation_error_rad": residuals.iter().map(|r| r.rotation_error_rad).fold(0.0, f64::max),
        "residuals": residuals,
    })
}

/// Writes [`ik_report`] as `dir/ik.json`, atomically.
pub fn write_ik_report(dir: &Path, residuals: &[FrameResidual]) -> Result<(), FileError> {
    let p = dir.join("ik.json");
    let text =
        serde_json::to_string_pretty(&ik_report(residuals)).map_err(|source| FileError::Json {
            path: p.clone(),
            source,
        })?;
    bridgev2w_io::atomic::write_atomic(&p, text.as_bytes())
}
