//! Cameras that move over a clip: a `world_from_camera` per frame (AgiBot
//! World's aligned extrinsics, DROID's recorded wrist-camera poses), or a
//! camera mounted on a robot link and posed by forward kinematics every
//! frame (`world_from_camera = world_from_link(q_t) * link_from_camera`).
//! A fixed camera is the special case of one pose for every frame.

use super::{isometry_from_rows, Camera, CameraError, Intrinsics};
use crate::robot::Robot;
use nalgebra::Isometry3;
use std::path::Path;

/// Where a clip's camera is, frame by frame.
#[derive(Debug, Clone, PartialEq)]
pub enum CameraPose {
    /// One `world_from_camera` for every frame.
    Fixed(Isometry3<f64>),
    /// `world_from_camera` of each frame.
    PerFrame(Vec<Isometry3<f64>>),
    /// Mounted on the robot link named `link`.
    Mounted {
        /// The link the camera is fixed to.
        link: String,
        /// The mount: camera frame (OpenCV axes) in the link frame.
        link_from_camera: Isometry3<f64>,
    },
}

impl CameraPose {
    /// The camera-file field that gives this kind of pose.
    pub fn kind_field(&self) -> &'static str {
        match self {
            CameraPose::Fixed(_) => "world_from_camera",
            CameraPose::PerFrame(_) => "world_from_camera_per_frame",
            CameraPose::Mounted { .. } => "parent_link",
        }
    }
}

/// A camera over a clip: fixed intrinsics, a pose per frame.
#[derive(Debug, Clone, PartialEq)]
pub struct CameraTrack {
    /// Intrinsics (validated by the constructors).
    pub intrinsics: Intrinsics,
    /// The pose of each frame.
    pub pose: CameraPose,
}

impl From<&Camera> for CameraTrack {
    fn from(camera: &Camera) -> Self {
        CameraTrack {
            intrinsics: camera.intrinsics,
            pose: CameraPose::Fixed(camera.world_from_camera),
        }
    }
}

impl CameraTrack {
    /// The same track with the pose of each frame replaced by `poses`
    /// (`world_from_camera`, e.g. from a `[T, 4, 4]` `.npy` file).
    pub fn with_poses(&self, poses: Vec<Isometry3<f64>>) -> Self {
        CameraTrack {
            intrinsics: self.intrinsics,
            pose: CameraPose::PerFrame(poses),
        }
    }

    /// The same track imaged at `width` x `height`.
    pub fn rescaled(&self, width: u32, height: u32) -> Self {
        CameraTrack {
            intrinsics: self.intrinsics.rescaled(width, height),
            pose: self.pose.clone(),
        }
    }

    /// The fixed camera, if the track does not move.
    pub fn as_fixed(&self) -> Option<Camera> {
        match &self.pose {
            CameraPose::Fixed(world_from_camera) => Some(Camera {
                intrinsics: self.intrinsics,
                world_from_camera: *world_from_camera,
            }),
            _ => None,
        }
    }

    /// Checks the track against a clip of `frames` frames of `robot`: one
    /// pose per frame, a mount link that exists. `origin` names the camera
    /// in errors.
    pub fn check(&self, robot: &Robot, frames: usize, origin: &str) -> Result<(), CameraError> {
        match &self.pose {
            CameraPose::Fixed(_) => Ok(()),
            CameraPose::PerFrame(poses) if poses.len() == frames => Ok(()),
            CameraPose::PerFrame(poses) => Err(CameraError::InvalidField {
                origin: origin.to_string(),
                field: "world_from_camera_per_frame".into(),
                value: format!("{} poses", poses.len()),
                expected: format!("one pose per frame of the trajectory ({frames})"),
            }),
            CameraPose::Mounted { link, .. } => match robot.link_index(link) {
                Some(_) => Ok(()),
                None => Err(CameraError::InvalidField {
                    origin: origin.to_string(),
                    field: "parent_link".into(),
                    value: format!("\"{link}\""),
                    expected: format!(
                        "a link of robot \"{}\" ({})",
                        robot.name,
                        robot.link_names()
                    ),
                }),
            },
        }
    }

    /// Whether the pose depends on the robot's configuration.
    pub fn is_mounted(&self) -> bool {
        matches!(self.pose, CameraPose::Mounted { .. })
    }

    /// The camera of frame `t`, given the robot's `world_from_link` poses in
    /// that frame (from [`Robot::link_poses`]; used by a mounted camera).
    ///
    /// # Panics
    /// If `t` is past a per-frame track's end or the mount link is not one
    /// of `robot`'s (validate with [`CameraTrack::check`]).
    pub fn camera_at(&self, robot: &Robot, t: usize, link_poses: &[Isometry3<f64>]) -> Camera {
        let world_from_camera = match &self.pose {
            CameraPose::Fixed(p) => *p,
            CameraPose::PerFrame(poses) => poses[t],
            CameraPose::Mounted {
                link,
                link_from_camera,
            } => {
                let l = robot
                    .link_index(link)
                    .unwrap_or_else(|| panic!("mount link \"{link}\" not checked"));
                link_poses[l] * link_from_camera
            }
        };
        Camera {
            intrinsics: self.intrinsics,
            world_from_camera,
        }
    }
}

/// A moving camera's poses from a `.npy` file of shape `[T, 4, 4]`
/// (row-major `world_from_camera` per frame, any float dtype), e.g. AgiBot
/// World's per-frame camera-to-base extrinsics.
pub fn read_poses_npy(path: &Path) -> Result<Vec<Isometry3<f64>>, CameraError> {
    let origin = path.display().to_string();
    let a = bridgev2w_io::npy::read_npy(path).map_err(|e| CameraError::InvalidField {
        origin: origin.clone(),
        field: "(file)".into(),
        value: e.to_string(),
        expected: "a .npy array of shape [T, 4, 4]".into(),
    })?;
    if a.shape.len() != 3 || a.shape[1..] != [4, 4] || a.shape[0] == 0 {
        return Err(CameraError::InvalidField {
            origin,
            field: "shape".into(),
            value: format!("{:?}", a.shape),
            expected: "[T, 4, 4] with T >= 1 (one world_from_camera matrix per frame)".into(),
        });
    }
    a.data
        .chunks_exact(16)
        .enumerate()
        .map(|(t, m)| {
            let rows: [[f64; 4]; 4] =
                std::array::from_fn(|r| std::array::from_fn(|c| m[4 * r + c]));
            isometry_from_rows(&rows, &origin, &format!("[{t}]"))
        })
        .collect()
}
