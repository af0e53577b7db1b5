//! Embodiments: a robot model plus what actions mean for it (which links the
//! end-effector poses refer to, which joints the gripper values drive, and a
//! home configuration). The built-in `franka` and `agibot-g1` ship with the
//! crate (`robots/*.urdf`, primitive geometry); any URDF works with
//! user-given end-effector links.

use crate::actions::EndEffector;
use crate::robot::{LoadOptions, Robot, RobotError};
use std::path::Path;

/// A built-in robot.
#[derive(Debug, Clone, Copy)]
pub struct BuiltinRobot {
    /// Name used on the command line.
    pub name: &'static str,
    /// One-line description.
    pub description: &'static str,
    /// URDF text.
    pub urdf: &'static str,
    /// `(arm name, end-effector link, gripper joint)` in action order.
    pub end_effectors: &'static [(&'static str, &'static str, Option<&'static str>)],
    /// Home configuration by joint name; unnamed dofs are 0 clamped to limits.
    pub home: &'static [(&'static str, f64)],
}

/// The built-in robots.
pub const BUILTIN_ROBOTS: &[BuiltinRobot] = &[
    BuiltinRobot {
        name: "franka",
        description: "Franka Emika Panda (7-DoF) with parallel gripper; primitive geometry",
        urdf: include_str!("../robots/franka.urdf"),
        end_effectors: &[("arm", "panda_hand_tcp", Some("panda_finger_joint1"))],
        home: &[
            ("panda_joint1", 0.0),
            ("panda_joint2", -0.785),
            ("panda_joint3", 0.0),
            ("panda_joint4", -2.356),
            ("panda_joint5", 0.0),
            ("panda_joint6", 1.571),
            ("panda_joint7", 0.785),
            ("panda_finger_joint1", 0.04),
        ],
    },
    BuiltinRobot {
        name: "agibot-g1",
        description: "AgiBot G1-like dual-arm robot: two 7-DoF arms with grippers on a torso; primitive geometry",
        urdf: include_str!("../robots/agibot_g1.urdf"),
        end_effectors: &[
            ("left", "left_gripper_tcp", Some("left_gripper_joint")),
            ("right", "right_gripper_tcp", Some("right_gripper_joint")),
        ],
        home: &[],
    },
];

/// Errors choosing or loading an embodiment.
#[derive(Debug, thiserror::Error)]
pub enum EmbodimentError {
    /// The robot model failed to load.
    #[error(transparent)]
    Robot(#[from] RobotError),
    /// The `--robot` value is neither a built-in name nor a file.
    #[error("--robot \"{0}\": not a built-in robot ({1}) and no such URDF file")]
    Unknown(String, String),
    /// A URDF file where only a built-in robot is accepted (e.g. `synth`).
    #[error("--robot \"{0}\": a file, but only built-in robots are accepted here ({1}); URDF files work with masks, convert and train's data.robot")]
    BuiltinOnly(String, String),
    /// An end-effector link or gripper joint does not exist or is unsuitable.
    #[error("{source_name}: {message}")]
    Invalid {
        /// The robot source.
        source_name: String,
        /// What is wrong.
        message: String,
    },
}

/// A robot plus the meaning of actions for it.
#[derive(Debug, Clone)]
pub struct Embodiment {
    /// The kinematic and geometric model.
    pub robot: Robot,
    /// End effectors in action order.
    pub end_effectors: Vec<EndEffector>,
    /// Home configuration (start of IK, and the pose of unused joints).
    pub home: Vec<f64>,
}

impl Embodiment {
    /// A built-in robot by name.
    pub fn builtin(name: &str) -> Result<Self, EmbodimentError> {
        let spec = BUILTIN_ROBOTS
            .iter()
            .find(|b| b.name == name)
            .ok_or_else(|| {
                if std::path::Path::new(name).is_file() {
                    EmbodimentError::BuiltinOnly(name.to_string(), builtin_names())
                } else {
                    EmbodimentError::Unknown(name.to_string(), builtin_names())
                }
            })?;
        let robot = Robot::from_urdf_str(spec.urdf, spec.name, None, &LoadOptions::default())?;
        let ees: Vec<(String, String, Option<String>)> = spec
            .end_effectors
            .iter()
            .map(|(a, l, g)| (a.to_string(), l.to_string(), g.map(str::to_string)))
            .collect();
        let mut e = Self::with_end_effectors(robot, &ees)?;
        for (joint, value) in spec.home {
            let d = e
                .robot
                .dof_index(joint)
                .ok_or_else(|| EmbodimentError::Invalid {
                    source_name: spec.name.to_string(),
                    message: format!("home joint \"{joint}\" is not an actuated joint"),
                })?;
            e.home[d] = *value;
        }
        Ok(e)
    }

    /// `--robot` semantics: a built-in name, or a URDF path with
    /// `ee_links` (one per arm, action order) and optional `gripper_joints`
    /// (same order; may be shorter).
    pub fn load(
        robot: &str,
        options: &LoadOptions,
        ee_links: &[String],
        gripper_joints: &[String],
    ) -> Result<Self, EmbodimentError> {
        let is_builtin = BUILTIN_ROBOTS.iter().any(|b| b.name == robot);
        if is_builtin && !Path::new(robot).is_file() {
            if !ee_links.is_empty() || !gripper_joints.is_empty() {
                return Err(EmbodimentError::Invalid {
                    source_name: robot.to_string(),
                    message: "--ee-link/--gripper-joint apply to URDF files only; built-in robots define their own".into(),
                });
            }
            return Self::builtin(robot);
        }
        let path = Path::new(robot);
        if !path.is_file() {
            return Err(EmbodimentError::Unknown(robot.to_string(), builtin_names()));
        }
        let model = Robot::from_urdf_file(path, options)?;
        let arms: Vec<(String, String, Option<String>)> = ee_links
            .iter()
            .enumerate()
            .map(|(i, l)| {
                let arm = if ee_links.len() == 1 {
                    "arm".to_string()
                } else {
                    format!("arm{i}")
                };
                (arm, l.clone(), gripper_joints.get(i).cloned())
            })
            .collect();
        if gripper_joints.len() > ee_links.len() {
            return Err(EmbodimentError::Invalid {
                source_name: robot.to_string(),
                message: format!(
                    "{} --gripper-joint values but {} --ee-link values: give one end-effector link per gripper",
                    gripper_joints.len(),
                    ee_links.len()
                ),
            });
        }
        Self::with_end_effectors(model, &arms)
    }

    fn with_end_effectors(
        robot: Robot,
        arms: &[(String, String, Option<String>)],
    ) -> Result<Self, EmbodimentError> {
        let invalid = |message: String| EmbodimentError::Invalid {
            source_name: robot.source_name.clone(),
            message,
        };
        let mut end_effectors = Vec::new();
        for (arm, link, gripper) in arms {
            let l = robot.link_index(link).ok_or_else(|| {
                invalid(format!(
                    "end-effector link \"{link}\" does not exist (links: {})",
                    robot
                        .links
                        .iter()
                        .map(|l| l.name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ))
            })?;
            let gripper_dof = match gripper {
                None => None,
                Some(g) => {
                    let d = robot.dof_index(g).ok_or_else(|| {
                        invalid(format!(
                            "gripper joint \"{g}\" is not an actuated joint (actuated: {})",
                            robot.dof_names().join(", ")
                        ))
                    })?;
                    if robot.joints[robot.dofs[d]].limits.is_none() {
                        return Err(invalid(format!(
                            "gripper joint \"{g}\" has no limits: the gripper value needs an open..closed range"
                        )));
                    }
                    Some(d)
                }
            };
            end_effectors.push(EndEffector {
                arm: arm.clone(),
                link: l,
                gripper_dof,
            });
        }
        let home = robot
            .dof_limits()
            .into_iter()
            .map(|(lo, hi)| 0.0f64.clamp(lo, hi))
            .collect();
        Ok(Self {
            robot,
            end_effectors,
            home,
        })
    }

    /// Action width: 7 per arm.
    pub fn action_dim(&self) -> usize {
        7 * self.end_effectors.len()
    }
}

/// Comma-separated built-in robot names.
pub fn builtin_names() -> String {
    BUILTIN_ROBOTS
        .iter()
        .map(|b| b.name)
        .collect::<Vec<_>>()
        .join(", ")
}
