//! A robot's unrecorded joints from what was recorded: the body (waist,
//! head, any joints on a camera's chain) from a recorded camera pose, and
//! full joint trajectories from recorded flange poses plus that camera.
//!
//! Datasets such as AgiBot World's genie-envisioner samples record each
//! arm's flange pose (`state/end`), the gripper opening and per-frame camera
//! extrinsics, but not the joints. The arm joints follow from the flanges by
//! inverse kinematics, but the joints the arms share (a waist) and the head
//! are on no arm's chain that IK may move: they are recovered from the head
//! camera, whose recorded `world_from_camera` is forward kinematics of the
//! body joints through the camera's mount ([`body_from_camera`]).
//! [`joints_from_flange_poses`] does both for every frame.
//!
//! When the camera's chain has fewer than 6 dofs (the AgiBot G1 head camera:
//! lift, waist pitch, head yaw, head pitch), the damped-least-squares solve
//! minimises the residual `|dp|^2 + |dr|^2` (metres, radians); the residual
//! that remains says how well the robot model (and its camera mount) fits
//! the recording.

use crate::actions::{actions_to_joints, ActionError, EndEffector, FrameResidual, Trajectory};
use crate::embodiment::Embodiment;
use crate::kinematics::{pose_error, xyz_rpy_from_pose, IkOptions, IkSolver};
use crate::robot::Robot;
use nalgebra::{Isometry3, Quaternion, Translation3, UnitQuaternion};

/// Errors recovering joints; each names the input that was wrong.
#[derive(Debug, thiserror::Error)]
pub enum PostureError {
    /// A link named in the inputs is not one of the robot's.
    #[error("robot \"{robot}\": {role} link \"{link}\" does not exist")]
    UnknownLink {
        /// The robot's name.
        robot: String,
        /// What the link was meant to be ("camera").
        role: String,
        /// The name given.
        link: String,
    },
    /// The camera link is moved by no joint the solver may move.
    #[error("robot \"{robot}\": camera link \"{link}\" is moved by no actuated joint: nothing to solve for")]
    NothingToSolve {
        /// The robot's name.
        robot: String,
        /// The camera link.
        link: String,
    },
    /// A start configuration of the wrong length or with bad values.
    #[error("start configuration: {0}")]
    StartConfiguration(String),
    /// A recording that is malformed (shapes, non-finite values, quaternions).
    #[error("{source_name}: {message}")]
    Recording {
        /// The recording's name (file or sample).
        source_name: String,
        /// What is wrong, with frame and column where known.
        message: String,
    },
    /// The arm IK failed (an unreachable flange pose, or bad actions).
    #[error(transparent)]
    Arms(#[from] ActionError),
}

/// The body joints recovered from one recorded camera pose.
#[derive(Debug, Clone, PartialEq)]
pub struct BodyFromCamera {
    /// Full joint vector: the start configuration with the camera chain's
    /// dofs solved.
    pub q: Vec<f64>,
    /// The dofs that were solved (indices into `q`).
    pub solved_dofs: Vec<usize>,
    /// Distance between the model's camera and the recorded one (metres).
    pub position_residual_m: f64,
    /// Rotation between the model's camera and the recorded one (radians).
    pub rotation_residual_rad: f64,
}

/// Settings of [`body_from_camera`]: the IK's, with tolerances that only
/// decide when random restarts stop (an under-determined chain rarely
/// reaches them; the best residual is returned either way).
pub fn default_body_ik() -> IkOptions {
    IkOptions {
        max_iterations: 200,
        restarts: 16,
        ..IkOptions::default()
    }
}

/// Solves the dofs on `camera_link`'s chain so that forward kinematics of
/// `camera_link` matches the recorded `world_from_camera` as closely as
/// possible, starting from `q_start` (dofs off the chain keep their values).
///
/// With 6 or more dofs on the chain the pose is matched within the IK
/// tolerances when reachable; with fewer (a head camera on lift, pitch and
/// a 2-dof neck) the least-squares pose is returned with its residual.
pub fn body_from_camera(
    robot: &Robot,
    camera_link: &str,
    world_from_camera: &Isometry3<f64>,
    q_start: &[f64],
    opts: &IkOptions,
) -> Result<BodyFromCamera, PostureError> {
    let link = robot
        .link_index(camera_link)
        .ok_or_else(|| PostureError::UnknownLink {
            robot: robot.name.clone(),
            role: "camera".into(),
            link: camera_link.to_string(),
        })?;
    robot
        .check_q(q_start, 1e-9)
        .map_err(PostureError::StartConfiguration)?;
    let solver = IkSolver::new(robot, link, None);
    if solver.free_dofs().is_empty() {
        return Err(PostureError::NothingToSolve {
            robot: robot.name.clone(),
            link: camera_link.to_string(),
        });
    }
    let solution = solver.solve(world_from_camera, q_start, opts);
    let (position_residual_m, rotation_residual_rad) =
        pose_error(&robot.link_pose(link, &solution.q), world_from_camera);
    Ok(BodyFromCamera {
        q: solution.q,
        solved_dofs: solver.free_dofs().to_vec(),
        position_residual_m,
        rotation_residual_rad,
    })
}

/// Recorded flange poses of one or more arms over a clip, with the pose of
/// a camera on the robot's body in each frame.
#[derive(Debug, Clone, PartialEq)]
pub struct FlangeRecording {
    /// Name for messages (file or sample).
    pub source_name: String,
    /// `world_from_flange[frame][arm]`, arms in the embodiment's order.
    pub world_from_flange: Vec<Vec<Isometry3<f64>>>,
    /// `gripper_raw[frame][arm]`, in the recording's own units.
    pub gripper_raw: Vec<Vec<f64>>,
    /// `world_from_camera` of the body camera, one per frame.
    pub world_from_body_camera: Vec<Isometry3<f64>>,
}

impl FlangeRecording {
    /// Parses AgiBot World-style rows, 8 values per arm: flange position
    /// `x, y, z` (metres), orientation quaternion `x, y, z, w`, raw gripper
    /// value (genie-envisioner's `actions.npy`, `state/end` +
    /// `state/effector`). `world_from_body_camera` gives one camera pose per
    /// row.
    pub fn from_agibot_rows(
        source_name: &str,
        rows: &[Vec<f64>],
        arms: usize,
        world_from_body_camera: Vec<Isometry3<f64>>,
    ) -> Result<Self, PostureError> {
        let bad = |message: String| PostureError::Recording {
            source_name: source_name.to_string(),
            message,
        };
        if arms == 0 || rows.is_empty() {
            return Err(bad(format!(
                "{} rows for {arms} arm(s): expected at least one row and one arm",
                rows.len()
            )));
        }
        if world_from_body_camera.len() != rows.len() {
            return Err(bad(format!(
                "{} rows but {} camera poses: expected one camera pose per row",
                rows.len(),
                world_from_body_camera.len()
            )));
        }
        let mut world_from_flange = Vec::with_capacity(rows.len());
        let mut gripper_raw = Vec::with_capacity(rows.len());
        for (f, row) in rows.iter().enumerate() {
            if row.len() != 8 * arms {
                return Err(bad(format!(
                    "row {f} has {} values: expected {} (per arm: x, y, z, qx, qy, qz, qw, gripper)",
                    row.len(),
                    8 * arms
                )));
            }
            if let Some((c, v)) = row.iter().enumerate().find(|(_, v)| !v.is_finite()) {
                return Err(bad(format!(
                    "row {f}, column {c}: {v} is not a finite number"
                )));
            }
            let mut poses = Vec::with_capacity(arms);
            for a in 0..arms {
                let v = &row[8 * a..8 * a + 8];
                let quat = Quaternion::new(v[6], v[3], v[4], v[5]);
                let norm = quat.norm();
                if !(0.5..=1.5).contains(&norm) {
                    return Err(bad(format!(
                        "row {f}, arm {a}: quaternion (x, y, z, w) = ({}, {}, {}, {}) has norm {norm:.3}: expected a unit quaternion in x, y, z, w order",
                        v[3], v[4], v[5], v[6]
                    )));
                }
                poses.push(Isometry3::from_parts(
                    Translation3::new(v[0], v[1], v[2]),
                    UnitQuaternion::from_quaternion(quat),
                ));
            }
            world_from_flange.push(poses);
            gripper_raw.push((0..arms).map(|a| row[8 * a + 7]).collect());
        }
        Ok(Self {
            source_name: source_name.to_string(),
            world_from_flange,
            gripper_raw,
            world_from_body_camera,
        })
    }

    /// Number of frames.
    pub fn len(&self) -> usize {
        self.world_from_flange.len()
    }

    /// Whether there are no frames.
    pub fn is_empty(&self) -> bool {
        self.world_from_flange.is_empty()
    }
}

/// How often the body is solved from the camera.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BodySolve {
    /// Every frame (the waist or head moves during the clip).
    PerFrame,
    /// Once, from the first frame's camera pose, kept for the whole clip.
    Once,
}

/// Settings of [`joints_from_flange_poses`].
#[derive(Debug, Clone)]
pub struct PostureOptions {
    /// The body camera's link (e.g. `head_camera_optical`).
    pub camera_link: String,
    /// Per frame or once.
    pub body_solve: BodySolve,
    /// The body solve's IK settings ([`default_body_ik`]).
    pub body_ik: IkOptions,
    /// The arms' IK settings.
    pub arm_ik: IkOptions,
    /// The raw gripper value of a fully closed gripper: `g = raw / this`,
    /// clamped to `[0, 1]` (AgiBot World: 120).
    pub gripper_raw_closed: f64,
    /// Return frames whose flange pose was not reached (flagged in the
    /// residuals) instead of failing.
    pub allow_residual: bool,
}

impl PostureOptions {
    /// Defaults for a body camera on `camera_link`: per-frame body solve,
    /// default IK settings, AgiBot World's gripper scale (120), unreachable
    /// flanges are errors.
    pub fn new(camera_link: &str) -> Self {
        Self {
            camera_link: camera_link.to_string(),
            body_solve: BodySolve::PerFrame,
            body_ik: default_body_ik(),
            arm_ik: IkOptions::default(),
            gripper_raw_closed: 120.0,
            allow_residual: false,
        }
    }
}

/// Joint trajectories recovered from a [`FlangeRecording`].
#[derive(Debug, Clone, PartialEq)]
pub struct Posture {
    /// One full joint vector per frame.
    pub joints: Vec<Vec<f64>>,
    /// The body solve of each frame (the same one repeated with
    /// [`BodySolve::Once`]).
    pub body: Vec<BodyFromCamera>,
    /// Per frame and arm (frame-major), the flange residual of the final
    /// joints against the recorded flange pose.
    pub arms: Vec<FrameResidual>,
}

/// Full joint trajectories from recorded flange poses: per frame (or once)
/// the body from the body camera ([`body_from_camera`], warm-started from
/// the previous frame, the first from `q_start`), then each arm's IK to its
/// flange ([`actions_to_joints`], warm-started from the previous frame's arm
/// joints, on top of that frame's body), gripper `g = raw /
/// gripper_raw_closed` clamped to `[0, 1]`.
///
/// `embodiment`'s end-effector links must be the recorded flanges, in the
/// recording's arm order (see [`Embodiment::set_ee_links`]).
pub fn joints_from_flange_poses(
    embodiment: &Embodiment,
    recording: &FlangeRecording,
    q_start: &[f64],
    opts: &PostureOptions,
) -> Result<Posture, PostureError> {
    let robot = &embodiment.robot;
    let ees: &[EndEffector] = &embodiment.end_effectors;
    let bad = |message: String| PostureError::Recording {
        source_name: recording.source_name.clone(),
        message,
    };
    check_recording(recording, ees.len()).map_err(bad)?;
    if !(opts.gripper_raw_closed.is_finite() && opts.gripper_raw_closed > 0.0) {
        return Err(bad(format!(
            "gripper_raw_closed = {}: expected a positive number (the raw value of a closed gripper)",
            opts.gripper_raw_closed
        )));
    }
    robot
        .check_q(q_start, 1e-9)
        .map_err(PostureError::StartConfiguration)?;

    let mut body: Vec<BodyFromCamera> = Vec::with_capacity(recording.len());
    let mut joints = Vec::with_capacity(recording.len());
    let mut arms = Vec::with_capacity(recording.len() * ees.len());
    let mut previous = q_start.to_vec();
    for f in 0..recording.len() {
        let b = match (opts.body_solve, body.last()) {
            (BodySolve::Once, Some(first)) => first.clone(),
            _ => body_from_camera(
                robot,
                &opts.camera_link,
                &recording.world_from_body_camera[f],
                &previous,
                &opts.body_ik,
            )?,
        };
        // This frame's body, the previous frame's arms as the warm start.
        let mut q_warm = previous.clone();
        for &d in &b.solved_dofs {
            q_warm[d] = b.q[d];
        }
        let row: Vec<f64> = recording.world_from_flange[f]
            .iter()
            .zip(&recording.gripper_raw[f])
            .flat_map(|(pose, raw)| {
                let mut v = xyz_rpy_from_pose(pose).to_vec();
                v.push((raw / opts.gripper_raw_closed).clamp(0.0, 1.0));
                v
            })
            .collect();
        let name = format!("{} frame {f}", recording.source_name);
        let actions = Trajectory::new(&name, vec![row])?;
        let (mut q, residuals) = actions_to_joints(
            robot,
            ees,
            &actions,
            &q_warm,
            &opts.arm_ik,
            opts.allow_residual,
        )?;
        let q = q.pop().unwrap_or(q_warm);
        // The residuals against the recorded poses themselves (not their
        // Euler-angle round trip), with the solver's iteration counts.
        let poses = robot.link_poses(&q);
        for (k, (ee, mut r)) in ees.iter().zip(residuals).enumerate() {
            let (dp, dr) = pose_error(&poses[ee.link], &recording.world_from_flange[f][k]);
            r.frame = f;
            r.position_error_m = dp;
            r.rotation_error_rad = dr;
            r.reached =
                dp <= opts.arm_ik.position_tolerance_m && dr <= opts.arm_ik.rotation_tolerance_rad;
            arms.push(r);
        }
        previous.clone_from(&q);
        joints.push(q);
        body.push(b);
    }
    Ok(Posture { joints, body, arms })
}

/// Shape and value checks of a recording for `arms` arms.
fn check_recording(r: &FlangeRecording, arms: usize) -> Result<(), String> {
    if r.is_empty() {
        return Err("no frames".into());
    }
    if r.gripper_raw.len() != r.len() || r.world_from_body_camera.len() != r.len() {
        return Err(format!(
            "{} frames of flange poses, {} of gripper values, {} camera poses: expected the same number",
            r.len(),
            r.gripper_raw.len(),
            r.world_from_body_camera.len()
        ));
    }
    for f in 0..r.len() {
        let (poses, grippers) = (&r.world_from_flange[f], &r.gripper_raw[f]);
        if poses.len() != arms || grippers.len() != arms {
            return Err(format!(
                "frame {f}: {} flange poses and {} gripper values for a robot with {arms} arm(s): expected one of each per arm",
                poses.len(),
                grippers.len()
            ));
        }
        let finite = |p: &Isometry3<f64>| {
            p.translation.vector.iter().all(|v| v.is_finite())
                && p.rotation.coords.iter().all(|v| v.is_finite())
        };
        if let Some(a) = poses.iter().position(|p| !finite(p)) {
            return Err(format!("frame {f}, arm {a}: flange pose is not finite"));
        }
        if let Some(a) = grippers.iter().position(|g| !g.is_finite()) {
            return Err(format!("frame {f}, arm {a}: gripper value is not finite"));
        }
        if !finite(&r.world_from_body_camera[f]) {
            return Err(format!("frame {f}: body camera pose is not finite"));
        }
    }
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn agibot_rows_are_checked_and_named() {
        let cam = vec![Isometry3::identity()];
        let row = vec![0.5, 0.2, 0.8, 0.0, 0.0, 0.0, 1.0, 60.0];
        let r = FlangeRecording::from_agibot_rows("s", std::slice::from_ref(&row), 1, cam.clone())
            .unwrap();
        assert_eq!(r.len(), 1);
        assert!((r.world_from_flange[0][0].translation.vector.x - 0.5).abs() < 1e-12);
        assert_eq!(r.gripper_raw[0], vec![60.0]);
        let e = FlangeRecording::from_agibot_rows("s", &[row[..7].to_vec()], 1, cam.clone());
        assert!(e.unwrap_err().to_string().contains("row 0 has 7 values"));
        let mut zero_quat = row.clone();
        zero_quat[3..7].fill(0.0);
        let e = FlangeRecording::from_agibot_rows("s", &[zero_quat], 1, cam);
        assert!(e.unwrap_err().to_string().contains("unit quaternion"));
        let e = FlangeRecording::from_agibot_rows("s", &[row], 1, Vec::new());
        assert!(e
            .unwrap_err()
            .to_string()
            .contains("one camera pose per row"));
    }

    /// A known configuration of the G1: its head camera and flange poses
    /// (forward kinematics) give back its body, arms and grippers.
    #[test]
    fn g1_joints_come_back_from_its_own_camera_and_flange_poses() {
        let mut e = Embodiment::builtin("agibot-g1").unwrap();
        e.set_ee_links(&["arm_l_link7".into(), "arm_r_link7".into()])
            .unwrap();
        let r = &e.robot;
        let dof = |n: &str| r.dof_index(n).unwrap();
        let mut q_true = e.home.clone();
        for (n, v) in [
            ("idx01_body_joint1", 0.31),
            ("idx02_body_joint2", 0.45),
            ("idx11_head_joint1", 0.05),
            ("idx12_head_joint2", 0.38),
        ] {
            q_true[dof(n)] = v;
        }
        for k in 1..=7 {
            let v = [0.0, -0.9, 0.4, 0.3, -1.1, 0.2, 0.3, -0.1][k];
            q_true[dof(&format!("idx2{k}_arm_l_joint{k}"))] = v;
            q_true[dof(&format!("idx6{k}_arm_r_joint{k}"))] = -v;
        }
        let poses = r.link_poses(&q_true);
        let camera = poses[r.link_index("head_camera_optical").unwrap()];

        // The body alone, from the home configuration.
        let b = body_from_camera(
            r,
            "head_camera_optical",
            &camera,
            &e.home,
            &default_body_ik(),
        )
        .unwrap();
        assert_eq!(b.solved_dofs.len(), 4, "lift, pitch, head yaw, head pitch");
        assert!(
            b.position_residual_m < 1e-5 && b.rotation_residual_rad < 1e-4,
            "{b:?}"
        );
        for &d in &b.solved_dofs {
            assert!(
                (b.q[d] - q_true[d]).abs() < 1e-3,
                "dof {d}: {} vs {}",
                b.q[d],
                q_true[d]
            );
        }

        // Whole frames: 2 frames, grippers 60/120 and 200 (clamped) raw.
        let flanges: Vec<Isometry3<f64>> =
            e.end_effectors.iter().map(|ee| poses[ee.link]).collect();
        let rec = FlangeRecording {
            source_name: "synthetic".into(),
            world_from_flange: vec![flanges.clone(), flanges],
            gripper_raw: vec![vec![60.0, 200.0]; 2],
            world_from_body_camera: vec![camera; 2],
        };
        let p = joints_from_flange_poses(
            &e,
            &rec,
            &e.home,
            &PostureOptions::new("head_camera_optical"),
        )
        .unwrap();
        assert_eq!(p.joints.len(), 2);
        assert!(p.arms.iter().all(|a| a.reached), "{:?}", p.arms);
        let pq = r.link_poses(&p.joints[1]);
        let (dp, dr) = pose_error(&pq[r.link_index("head_camera_optical").unwrap()], &camera);
        assert!(dp < 1e-5 && dr < 1e-4, "camera {dp} m {dr} rad");
        let limits = r.dof_limits();
        let g = |k: usize| e.end_effectors[k].gripper_dof.unwrap();
        assert!((p.joints[0][g(0)] - 0.5 * (limits[g(0)].0 + limits[g(0)].1)).abs() < 1e-9);
        assert!(
            (p.joints[0][g(1)] - limits[g(1)].0).abs() < 1e-9,
            "raw 200 clamps to closed"
        );

        // Errors name what was wrong.
        let e1 = body_from_camera(r, "no_such_link", &camera, &e.home, &default_body_ik());
        assert!(e1.unwrap_err().to_string().contains("\"no_such_link\""));
        let e2 = body_from_camera(
            r,
            "head_camera_optical",
            &camera,
            &[0.0; 3],
            &default_body_ik(),
        );
        assert!(matches!(e2, Err(PostureError::StartConfiguration(_))));
        let mut short = rec.clone();
        short.gripper_raw.pop();
        let e3 = joints_from_flange_poses(
            &e,
            &short,
            &e.home,
            &PostureOptions::new("head_camera_optical"),
        );
        assert!(e3.unwrap_err().to_string().contains("1 of gripper values"));
    }
}
