//! The demo's built-in scene: a camera looking at the Franka's workspace
//! and a pick-and-place in end-effector space.

use bridgev2w_embodiment::actions::{ActionError, Trajectory};
use bridgev2w_embodiment::camera::{Camera, CameraError, Intrinsics};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::xyz_rpy_from_pose;
use nalgebra::{Point3, UnitQuaternion, Vector3};

/// The built-in demo camera: 720x480, looking at the Franka's workspace
/// from the front-right, about 1.3 m away.
pub fn demo_camera() -> Result<Camera, CameraError> {
    let intrinsics = Intrinsics::centered(560.0, 720, 480);
    Camera::look_at(
        intrinsics,
        Point3::new(1.3, 0.8, 0.85),
        Point3::new(0.38, 0.0, 0.36),
        Vector3::z(),
    )
}

/// A pick-and-place in end-effector space: from home, approach, descend,
/// grasp, lift, carry, lower, release. `[x,y,z,roll,pitch,yaw,gripper]` rows.
pub fn demo_actions(e: &Embodiment, frames: usize) -> Result<Trajectory, ActionError> {
    let ee = e.end_effectors.first().ok_or_else(|| ActionError::Format {
        source_name: "built-in demo trajectory".into(),
        message: format!("robot \"{}\" has no end effector", e.robot.name),
    })?;
    let home = e.robot.link_pose(ee.link, &e.home);
    // (x, y, z, yaw offset, gripper)
    let keys: [(f64, f64, f64, f64, f64); 8] = [
        (
            home.translation.x,
            home.translation.y,
            home.translation.z,
            0.0,
            0.0,
        ),
        (0.50, 0.15, 0.25, 0.3, 0.0),
        (0.50, 0.15, 0.13, 0.3, 0.0),
        (0.50, 0.15, 0.13, 0.3, 1.0),
        (0.50, 0.15, 0.30, 0.3, 1.0),
        (0.40, -0.20, 0.30, -0.2, 1.0),
        (0.40, -0.20, 0.15, -0.2, 1.0),
        (0.40, -0.20, 0.15, -0.2, 0.0),
    ];
    let frames = frames.max(2);
    let rows = (0..frames)
        .map(|f| {
            let s = f as f64 / (frames - 1) as f64 * (keys.len() - 1) as f64;
            let k = (s.floor() as usize).min(keys.len() - 2);
            let t = s - k as f64;
            // Smoothstep within each segment: the arm eases in and out.
            let t = t * t * (3.0 - 2.0 * t);
            let (a, b) = (keys[k], keys[k + 1]);
            let lerp = |x: f64, y: f64| x + (y - x) * t;
            let yaw = lerp(a.3, b.3);
            let mut pose = home;
            pose.translation.vector = Vector3::new(lerp(a.0, b.0), lerp(a.1, b.1), lerp(a.2, b.2));
            pose.rotation =
                UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw) * home.rotation;
            let mut row = xyz_rpy_from_pose(&pose).to_vec();
            row.push(lerp(a.4, b.4));
            row
        })
        .collect();
    Trajectory::new("built-in demo trajectory", rows)
}
