//! The kinematic contact rules: grasping, carrying, releasing and pushing
//! objects, driven by the robot's achieved gripper pose.

use super::{EpisodeMeta, ObjectPose, SceneState, World};
use nalgebra::{Point3, Vector2};
use serde::{Deserialize, Serialize};

/// What the contact rules did to one object in one frame.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Contact {
    /// No contact.
    None,
    /// Pushed by the fingers/hand.
    Pushed,
    /// Grasped this frame.
    Grasped,
    /// Carried in the closed gripper.
    Carried,
    /// Released this frame (dropped onto the table).
    Released,
}

/// Contact geometry of the gripper (metres).
pub(super) const FINGER_RADIUS_M: f64 = 0.008;
/// Horizontal tolerance for a grasp (TCP to object axis).
const GRASP_RADIUS_M: f64 = 0.03;

impl World {
    /// Kinematic contact rules over the clip, driven by the achieved joints.
    pub(super) fn simulate(
        &self,
        meta: &EpisodeMeta,
        actions: &[Vec<f64>],
        joints: &[Vec<f64>],
    ) -> (Vec<Vec<ObjectPose>>, Vec<Vec<Contact>>) {
        let mut state = SceneState {
            joints: joints.first().cloned().unwrap_or_default(),
            object_poses: meta.objects.iter().map(|o| o.initial).collect(),
            held: None,
            prev_points: None,
            prev_gripper: 0.0,
        };
        let mut all_poses = Vec::with_capacity(joints.len());
        let mut all_contacts = Vec::with_capacity(joints.len());
        for (f, q) in joints.iter().enumerate() {
            let g = actions[f][7 * meta.arm + 6];
            let contacts = self.contact_step(meta, &mut state, q, g);
            all_poses.push(state.object_poses.clone());
            all_contacts.push(contacts);
        }
        (all_poses, all_contacts)
    }

    /// One frame of the kinematic contact rules: the robot is at joints `q`
    /// with gripper command `g`; updates `state` (objects, grasp, joints).
    pub(super) fn contact_step(
        &self,
        meta: &EpisodeMeta,
        state: &mut SceneState,
        q: &[f64],
        g: f64,
    ) -> Vec<Contact> {
        let robot = &self.embodiment.robot;
        let ee = &self.embodiment.end_effectors[meta.arm];
        let tz = self.frame.table_z_m;
        let poses = &mut state.object_poses;
        let held = &mut state.held;
        let prev_g = state.prev_gripper;
        let prev_points = state.prev_points;
        {
            let tcp = robot.link_pose(ee.link, q);
            let mut contacts = vec![Contact::None; poses.len()];
            // Contact points: the two fingertips (either side of the TCP
            // along its y axis, at the finger opening) and the hand centre
            // 6 cm back along the approach axis.
            let half_open_m = ee.gripper_dof.map_or(0.0, |d| q[d].abs());
            let points = [
                tcp * Point3::new(0.0, half_open_m, 0.0),
                tcp * Point3::new(0.0, -half_open_m, 0.0),
                tcp * Point3::new(0.0, 0.0, -0.06),
            ];
            let tcp_point = Point3::from(tcp.translation.vector);
            // An object whose axis lies between the fingers is in the grasp
            // region: closing fingers squeeze it instead of pushing it.
            let between_fingers = |p: &ObjectPose, h: f64| {
                let d = (tcp_point.xy() - Point3::from(p.position_m).xy()).norm();
                d < GRASP_RADIUS_M
                    && tcp_point.z > p.position_m[2]
                    && tcp_point.z < p.position_m[2] + h + 0.01
            };
            // Release.
            if let Some((i, _)) = *held {
                if g < 0.5 {
                    *held = None;
                    poses[i].position_m[2] = tz;
                    contacts[i] = Contact::Released;
                }
            }
            // Carry.
            if let Some((i, tcp_from_obj)) = *held {
                let w = tcp * tcp_from_obj;
                let h = meta.objects[i].shape.height_m();
                let (_, _, yaw) = w.rotation.euler_angles();
                let t = w.translation.vector;
                poses[i] = ObjectPose {
                    position_m: [t.x, t.y, (t.z - 0.5 * h).max(tz)],
                    yaw_rad: yaw,
                };
                contacts[i] = Contact::Carried;
            }
            // Grasp: the gripper closes with the TCP inside an object.
            if held.is_none() && prev_g < 0.5 && g >= 0.5 {
                for (i, o) in meta.objects.iter().enumerate() {
                    let p = &poses[i];
                    let h = o.shape.height_m();
                    if between_fingers(p, h) {
                        let w = p.world_from_object_center(h);
                        *held = Some((i, tcp.inverse() * w));
                        contacts[i] = Contact::Grasped;
                        break;
                    }
                }
            }
            // Push: fingers/hand inside an object's footprint.
            for (i, o) in meta.objects.iter().enumerate() {
                if held.map(|(h, _)| h) == Some(i) || contacts[i] != Contact::None {
                    continue;
                }
                let h = o.shape.height_m();
                let r = o.shape.footprint_radius_m() + FINGER_RADIUS_M;
                let squeezed = half_open_m > 1e-3 && between_fingers(&poses[i], h);
                for (k, pt) in points.iter().enumerate() {
                    if squeezed && k < 2 {
                        continue;
                    }
                    let p = &mut poses[i];
                    if pt.z < p.position_m[2] - 0.01 || pt.z > p.position_m[2] + h + 0.005 {
                        continue;
                    }
                    let d = Vector2::new(p.position_m[0] - pt.x, p.position_m[1] - pt.y);
                    if d.norm() >= r {
                        continue;
                    }
                    let motion = prev_points
                        .map(|pp| (pt - pp[k]).xy())
                        .unwrap_or_else(Vector2::zeros);
                    let u = if motion.norm() > 1e-4 {
                        motion.normalize()
                    } else if d.norm() > 1e-9 {
                        d.normalize()
                    } else {
                        Vector2::x()
                    };
                    let along = d.dot(&u);
                    let perp = d - u * along;
                    let new_along = (r * r - perp.norm_squared()).max(0.0).sqrt();
                    if new_along > along {
                        let moved = Vector2::new(pt.x, pt.y) + perp + u * new_along;
                        p.position_m[0] = moved.x;
                        p.position_m[1] = moved.y;
                        contacts[i] = Contact::Pushed;
                    }
                }
            }
            state.prev_points = Some(points);
            state.prev_gripper = g;
            state.joints = q.to_vec();
            contacts
        }
    }
}
