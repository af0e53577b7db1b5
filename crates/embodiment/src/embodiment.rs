//! Embodiments: a robot model plus what actions mean for it (which links the
//! end-effector poses refer to, which joints the gripper values drive, and a
//! home configuration). The built-in robots ship with the crate, each a
//! description folder under `robots/` (URDF, meshes, README of its frames
//! and joint conventions, licence) compiled into the binary; any URDF works
//! with user-given end-effector links.

use crate::actions::{EndEffector, GripperClosedAt};
use crate::kinematics::{pose_from_xyz_rpy, xyz_rpy_from_pose};
use crate::robot::{LoadOptions, Robot, RobotError};
use std::path::Path;

/// One arm of a built-in robot.
#[derive(Debug, Clone, Copy)]
pub struct BuiltinArm {
    /// Arm name (`arm`, `left`, `right`).
    pub arm: &'static str,
    /// The link whose pose an action gives by default (the TCP where the
    /// robot defines one).
    pub ee_link: &'static str,
    /// The arm's flange: the link whose pose robot logs record (DROID's
    /// `cartesian_position`, AgiBot World's `state/end`).
    pub flange_link: &'static str,
    /// The gripper joint a gripper value drives, and which of its limits is
    /// closed.
    pub gripper: Option<(&'static str, GripperClosedAt)>,
}

/// A built-in robot.
#[derive(Debug, Clone, Copy)]
pub struct BuiltinRobot {
    /// Name used on the command line.
    pub name: &'static str,
    /// One-line description: what it is, and whether it is a real robot.
    pub description: &'static str,
    /// Its description folder under `crates/embodiment/robots/`.
    pub folder: &'static str,
    /// URDF text.
    pub urdf: &'static str,
    /// The mesh files its URDF names, by path relative to the folder.
    pub files: &'static [(&'static str, &'static [u8])],
    /// Arms in action order.
    pub arms: &'static [BuiltinArm],
    /// Home configuration by joint name; unnamed dofs are 0 clamped to limits.
    pub home: &'static [(&'static str, f64)],
    /// Whether `synth`'s tabletop scenes are laid out for it (a table in
    /// reach of its home pose).
    pub synthetic_world: bool,
}

/// `(path, bytes)` of files in a robot's description folder, compiled in.
macro_rules! robot_files {
    ($folder:literal: $($file:literal),* $(,)?) => {
        &[$(($file, include_bytes!(concat!("../robots/", $folder, "/", $file)) as &[u8])),*]
    };
}

/// The built-in robots.
pub const BUILTIN_ROBOTS: &[BuiltinRobot] = &[
    BuiltinRobot {
        name: "franka",
        description: "Franka Emika Panda: the real arm's kinematics (DH table), primitive shapes and a parallel gripper shaped like the Franka Hand; the synthetic world's robot",
        folder: "franka",
        urdf: include_str!("../robots/franka/franka.urdf"),
        files: &[],
        arms: &[BuiltinArm {
            arm: "arm",
            ee_link: "panda_hand_tcp",
            flange_link: "panda_link8",
            gripper: Some(("panda_finger_joint1", GripperClosedAt::Lower)),
        }],
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
        synthetic_world: true,
    },
    BuiltinRobot {
        name: "dual-arm",
        description: "an invented dual-arm robot (two 7-DoF arms with grippers on a torso; primitive shapes), the synthetic world's second robot; not a real robot",
        folder: "dual_arm",
        urdf: include_str!("../robots/dual_arm/dual_arm.urdf"),
        files: &[],
        arms: &[
            BuiltinArm {
                arm: "left",
                ee_link: "left_gripper_tcp",
                flange_link: "left_gripper_base",
                gripper: Some(("left_gripper_joint", GripperClosedAt::Lower)),
            },
            BuiltinArm {
                arm: "right",
                ee_link: "right_gripper_tcp",
                flange_link: "right_gripper_base",
                gripper: Some(("right_gripper_joint", GripperClosedAt::Lower)),
            },
        ],
        home: &[],
        synthetic_world: true,
    },
    BuiltinRobot {
        name: "agibot-g1",
        description: "AgiBot G1 (AgiBot World's robot): the real kinematics (genie_sim G01), real arm, torso and head meshes, the Omnipicker gripper modelled from its dimensions; waist lift/pitch and head pan/tilt joints; root = AgiBot World's recorded base frame",
        folder: "agibot_g1",
        urdf: include_str!("../robots/agibot_g1/agibot_g1.urdf"),
        files: robot_files!("agibot_g1":
            "meshes/arm_base_link.stl", "meshes/arm_link1.stl", "meshes/arm_link2.stl",
            "meshes/arm_link3.stl", "meshes/arm_link4.stl", "meshes/arm_link5.stl",
            "meshes/arm_link6.stl", "meshes/arm_link7.stl", "meshes/body_link1.stl",
            "meshes/head_link1.stl", "meshes/head_link2.stl",
        ),
        arms: &[
            BuiltinArm {
                arm: "left",
                ee_link: "gripper_l_center_link",
                flange_link: "arm_l_link7",
                gripper: Some(("idx41_gripper_l_outer_joint1", GripperClosedAt::Lower)),
            },
            BuiltinArm {
                arm: "right",
                ee_link: "gripper_r_center_link",
                flange_link: "arm_r_link7",
                gripper: Some(("idx81_gripper_r_outer_joint1", GripperClosedAt::Lower)),
            },
        ],
        // The waist and head of the real sample with joint states
        // (ge-sim-v2 demo_000): lift 0.27 m, pitch 0.5061 rad, head tilt
        // 0.4363 rad; recorded values replace them where a dataset has them.
        home: &[
            ("idx01_body_joint1", 0.27),
            ("idx02_body_joint2", 0.5061),
            ("idx11_head_joint1", 0.0),
            ("idx12_head_joint2", 0.4363),
        ],
        synthetic_world: false,
    },
    BuiltinRobot {
        name: "franka-robotiq",
        description: "DROID's robot: Franka Emika Panda with a Robotiq 2F-85 gripper, real meshes (franka_ros, ROS-Industrial robotiq) and the 2F-85 linkage; TCP between the closed pads",
        folder: "franka_robotiq",
        urdf: include_str!("../robots/franka_robotiq/franka_robotiq.urdf"),
        files: robot_files!("franka_robotiq":
            "meshes/link0.stl", "meshes/link1.stl", "meshes/link2.stl", "meshes/link3.stl",
            "meshes/link4.stl", "meshes/link5.stl", "meshes/link6.stl", "meshes/link7.stl",
            "meshes/robotiq_base_link.stl", "meshes/robotiq_coupling.stl",
            "meshes/robotiq_inner_finger.stl", "meshes/robotiq_inner_knuckle.stl",
            "meshes/robotiq_outer_finger.stl", "meshes/robotiq_outer_knuckle.stl",
        ),
        arms: &[BuiltinArm {
            arm: "arm",
            ee_link: "robotiq_tcp",
            flange_link: "panda_link8",
            gripper: Some(("finger_joint", GripperClosedAt::Upper)),
        }],
        // DROID's reset pose.
        home: &[
            ("panda_joint1", 0.0),
            ("panda_joint2", -0.6283185307179586),
            ("panda_joint3", 0.0),
            ("panda_joint4", -2.5132741228718345),
            ("panda_joint5", 0.0),
            ("panda_joint6", 1.8849555921538759),
            ("panda_joint7", 0.0),
        ],
        synthetic_world: true,
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
        let options = LoadOptions {
            embedded_files: spec.files,
            ..LoadOptions::default()
        };
        let robot = Robot::from_urdf_str(spec.urdf, spec.name, None, &options)?;
        let ees: Vec<ArmSpec> = spec
            .arms
            .iter()
            .map(|a| ArmSpec {
                arm: a.arm.to_string(),
                link: a.ee_link.to_string(),
                gripper: a.gripper.map(|(j, at)| (j.to_string(), at)),
            })
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
    /// (same order; may be shorter). For a built-in robot, `ee_links` (one
    /// per arm) replaces the links the actions are poses of (e.g. the flange
    /// `panda_link8` for DROID's recorded poses, see `robot-info`); its
    /// gripper joints stay its own.
    pub fn load(
        robot: &str,
        options: &LoadOptions,
        ee_links: &[String],
        gripper_joints: &[String],
    ) -> Result<Self, EmbodimentError> {
        let is_builtin = BUILTIN_ROBOTS.iter().any(|b| b.name == robot);
        if is_builtin && !Path::new(robot).is_file() {
            if !gripper_joints.is_empty() {
                return Err(EmbodimentError::Invalid {
                    source_name: robot.to_string(),
                    message: "--gripper-joint applies to URDF files only; built-in robots define their own gripper joints".into(),
                });
            }
            let mut e = Self::builtin(robot)?;
            if !ee_links.is_empty() {
                e.set_ee_links(ee_links)?;
            }
            return Ok(e);
        }
        let path = Path::new(robot);
        if !path.is_file() {
            return Err(EmbodimentError::Unknown(robot.to_string(), builtin_names()));
        }
        let model = Robot::from_urdf_file(path, options)?;
        let arms: Vec<ArmSpec> = ee_links
            .iter()
            .enumerate()
            .map(|(i, l)| ArmSpec {
                arm: if ee_links.len() == 1 {
                    "arm".to_string()
                } else {
                    format!("arm{i}")
                },
                link: l.clone(),
                gripper: gripper_joints
                    .get(i)
                    .map(|g| (g.clone(), GripperClosedAt::Lower)),
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

    /// Makes the actions poses of `links` (one per arm, action order)
    /// instead of the current end-effector links.
    pub fn set_ee_links(&mut self, links: &[String]) -> Result<(), EmbodimentError> {
        let robot = &self.robot;
        if links.len() != self.end_effectors.len() {
            return Err(EmbodimentError::Invalid {
                source_name: robot.source_name.clone(),
                message: format!(
                    "{} --ee-link values for {} arm(s) ({}): give one link per arm, in action order",
                    links.len(),
                    self.end_effectors.len(),
                    self.end_effectors
                        .iter()
                        .map(|e| e.arm.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                ),
            });
        }
        let mut indices = Vec::with_capacity(links.len());
        for (ee, link) in self.end_effectors.iter().zip(links) {
            let l = link_by_name(robot, link)?;
            // The new link must be moved by exactly the joints that move
            // the old one (rigidly attached to the same arm link), so the
            // arm's IK and its gripper stay as they were.
            let (old, new) = (robot.moving_joints(ee.link), robot.moving_joints(l));
            if old != new {
                let names = |js: &[usize]| {
                    js.iter()
                        .map(|&j| robot.joints[j].name.as_str())
                        .collect::<Vec<_>>()
                        .join(", ")
                };
                return Err(EmbodimentError::Invalid {
                    source_name: robot.source_name.clone(),
                    message: format!(
                        "--ee-link \"{link}\" for arm \"{}\": moved by joints [{}], but the arm's end effector \"{}\" by [{}]; expected a link rigidly attached to it (its flange, TCP or a frame on its last link)",
                        ee.arm,
                        names(&new),
                        robot.links[ee.link].name,
                        names(&old)
                    ),
                });
            }
            indices.push(l);
        }
        for (ee, l) in self.end_effectors.iter_mut().zip(indices) {
            ee.link = l;
        }
        Ok(())
    }

    /// Re-expresses end-effector actions (7 values per arm, action order:
    /// `[x, y, z, roll, pitch, yaw, gripper]`) given as poses of `from`
    /// (one link per arm) as poses of `to`: e.g. recorded flange poses
    /// (`panda_link8`) as TCP poses (`robotiq_tcp`), or back. Each pair of
    /// links must be rigidly attached to each other (moved by the same
    /// joints), so `world_from_to = world_from_from * from_from_to` with a
    /// fixed `from_from_to`; grippers are copied.
    pub fn convert_action_links(
        &self,
        actions: &[Vec<f64>],
        from: &[String],
        to: &[String],
    ) -> Result<Vec<Vec<f64>>, EmbodimentError> {
        let robot = &self.robot;
        let arms = self.end_effectors.len();
        let invalid = |message: String| EmbodimentError::Invalid {
            source_name: robot.source_name.clone(),
            message,
        };
        if from.len() != arms || to.len() != arms {
            return Err(invalid(format!(
                "{} \"from\" and {} \"to\" links for {arms} arm(s): give one of each per arm",
                from.len(),
                to.len()
            )));
        }
        let mut from_to = Vec::with_capacity(arms);
        for (f, t) in from.iter().zip(to) {
            let (fi, ti) = (link_by_name(robot, f)?, link_by_name(robot, t)?);
            if robot.moving_joints(fi) != robot.moving_joints(ti) {
                return Err(invalid(format!(
                    "links \"{f}\" and \"{t}\" are not rigidly attached (different joints move them): expected an arm's flange and its TCP, or two frames of one link"
                )));
            }
            let (wf, wt) = (
                robot.link_pose(fi, &self.home),
                robot.link_pose(ti, &self.home),
            );
            from_to.push(wf.inverse() * wt);
        }
        actions
            .iter()
            .enumerate()
            .map(|(t, row)| {
                if row.len() != 7 * arms {
                    return Err(invalid(format!(
                        "action frame {t}: {} values, expected {} (7 per arm)",
                        row.len(),
                        7 * arms
                    )));
                }
                let mut out = row.clone();
                for (k, f_t) in from_to.iter().enumerate() {
                    let v = &row[7 * k..7 * k + 6];
                    let pose = pose_from_xyz_rpy([v[0], v[1], v[2], v[3], v[4], v[5]]) * f_t;
                    out[7 * k..7 * k + 6].copy_from_slice(&xyz_rpy_from_pose(&pose));
                }
                Ok(out)
            })
            .collect()
    }

    fn with_end_effectors(robot: Robot, arms: &[ArmSpec]) -> Result<Self, EmbodimentError> {
        let invalid = |message: String| EmbodimentError::Invalid {
            source_name: robot.source_name.clone(),
            message,
        };
        let mut end_effectors = Vec::new();
        for spec in arms {
            let l = link_by_name(&robot, &spec.link)?;
            let (gripper_dof, gripper_closed_at) = match &spec.gripper {
                None => (None, GripperClosedAt::Lower),
                Some((g, at)) => {
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
                    (Some(d), *at)
                }
            };
            end_effectors.push(EndEffector {
                arm: spec.arm.clone(),
                link: l,
                gripper_dof,
                gripper_closed_at,
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

/// One arm to set up: its name, end-effector link and gripper joint.
struct ArmSpec {
    arm: String,
    link: String,
    gripper: Option<(String, GripperClosedAt)>,
}

fn link_by_name(robot: &Robot, link: &str) -> Result<usize, EmbodimentError> {
    robot
        .link_index(link)
        .ok_or_else(|| EmbodimentError::Invalid {
            source_name: robot.source_name.clone(),
            message: format!(
                "end-effector link \"{link}\" does not exist (links: {})",
                robot.link_names()
            ),
        })
}

/// The built-in robot named `name`.
pub fn builtin(name: &str) -> Option<&'static BuiltinRobot> {
    BUILTIN_ROBOTS.iter().find(|b| b.name == name)
}

/// Comma-separated built-in robot names.
pub fn builtin_names() -> String {
    BUILTIN_ROBOTS
        .iter()
        .map(|b| b.name)
        .collect::<Vec<_>>()
        .join(", ")
}
