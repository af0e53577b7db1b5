//! The scripted end-effector motions of the tasks (`reach`, `push`,
//! `pick_place`, `play`): keyframes eased per frame, with action noise.

use super::contacts::FINGER_RADIUS_M;
use super::{SceneObject, Task, World};
use bridgev2w_embodiment::kinematics::xyz_rpy_from_pose;
use nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use std::f64::consts::PI;

impl World {
    /// Scripted end-effector actions of `arm`; other arms hold their home pose.
    pub(super) fn script(
        &self,
        task: Task,
        arm: usize,
        objects: &[SceneObject],
        reach: Vector3<f64>,
        rng: &mut ChaCha8Rng,
    ) -> Vec<Vec<f64>> {
        let tz = self.frame.table_z_m;
        let c = Vector3::from(self.frame.workspace_center_m);
        let home = self.home_tcp[arm];
        let home_p = home.translation.vector;
        // Top-down orientation: the home orientation turned about world z.
        let yaw0: f64 = rng.gen_range(-0.4..0.4);
        let mut noise = |s: f64| rng.gen_range(-s..=s);
        // Keyframes: (time fraction, position, extra yaw, gripper).
        let mut keys: Vec<(f64, Vector3<f64>, f64, f64)> = vec![(0.0, home_p, 0.0, 0.0)];
        let above = 0.13;
        match (task, objects.first()) {
            (Task::PickPlace, Some(o)) => {
                let p = Vector3::from(o.initial.position_m);
                let grasp_z = tz + (0.5 * o.shape.height_m()).max(0.022);
                let dir = noise(PI);
                let dist = 0.10 + noise(0.03).abs();
                let place = Vector3::new(
                    (p.x + dist * dir.cos()).clamp(c.x - 0.15, c.x + 0.15),
                    (p.y + dist * dir.sin()).clamp(c.y - 0.22, c.y + 0.22),
                    grasp_z,
                );
                let gx = p.x + noise(0.004);
                let gy = p.y + noise(0.004);
                let y1 = noise(0.5);
                keys.extend([
                    (0.25, Vector3::new(gx, gy, tz + above), y1, 0.0),
                    (0.40, Vector3::new(gx, gy, grasp_z), y1, 0.0),
                    (0.48, Vector3::new(gx, gy, grasp_z), y1, 1.0),
                    (0.62, Vector3::new(gx, gy, tz + 0.15 + noise(0.02)), y1, 1.0),
                    (
                        0.78,
                        Vector3::new(place.x, place.y, tz + 0.12),
                        y1 + noise(0.3),
                        1.0,
                    ),
                    (0.86, place, y1, 1.0),
                    (0.92, place, y1, 0.0),
                    (
                        1.0,
                        Vector3::new(place.x, place.y, tz + 0.12 + noise(0.02)),
                        y1,
                        0.0,
                    ),
                ]);
            }
            (Task::Push, Some(o)) => {
                let p = Vector3::from(o.initial.position_m);
                let dir = noise(PI);
                let u = Vector3::new(dir.cos(), dir.sin(), 0.0);
                let r = o.shape.footprint_radius_m() + FINGER_RADIUS_M;
                let push_z = tz + 0.02 + noise(0.003);
                let start = Vector3::new(p.x, p.y, push_z) - u * (r + 0.04);
                let len = 0.08 + noise(0.03).abs();
                let end = Vector3::new(p.x, p.y, push_z) + u * (len - r);
                let y1 = noise(0.4);
                keys.extend([
                    (0.3, Vector3::new(start.x, start.y, tz + above), y1, 1.0),
                    (0.45, start, y1, 1.0),
                    (0.85, end, y1, 1.0),
                    (
                        1.0,
                        Vector3::new(end.x, end.y, tz + above + noise(0.02)),
                        y1,
                        1.0,
                    ),
                ]);
            }
            (Task::Play, _) => {
                // 3 to 5 waypoints at jittered, increasing times; about 40%
                // at an object (grasp height), the rest anywhere over the
                // table; the gripper flips with probability 0.4 at each.
                let n_way = 3 + ((noise(1.0) + 1.0) * 1.5).floor().min(2.0) as usize;
                let (mut g, mut yaw) = (0.0, 0.0);
                for i in 1..=n_way {
                    let t = if i == n_way {
                        1.0
                    } else {
                        (i as f64 + noise(0.25)) / n_way as f64
                    };
                    let p = if !objects.is_empty() && noise(1.0) > 0.2 {
                        let k = (((noise(0.5) + 0.5) * objects.len() as f64) as usize)
                            .min(objects.len() - 1);
                        let o = &objects[k];
                        let z = tz + (0.5 * o.shape.height_m()).max(0.022) + noise(0.015).abs();
                        let q = o.initial.position_m;
                        Vector3::new(q[0] + noise(0.02), q[1] + noise(0.02), z)
                    } else {
                        Vector3::new(
                            c.x + noise(0.15),
                            c.y + noise(0.22),
                            tz + 0.115 + noise(0.085),
                        )
                    };
                    if noise(1.0) > 0.2 {
                        g = 1.0 - g;
                    }
                    yaw += noise(0.4);
                    keys.push((t, p, yaw, g));
                }
            }
            _ => {
                // Reach (or no object): a random point above the table.
                let target = reach;
                let mid = 0.5 * (home_p + target) + Vector3::new(noise(0.03), noise(0.03), 0.05);
                let g = if noise(1.0) > 0.0 { 1.0 } else { 0.0 };
                keys.extend([
                    (0.45, mid, noise(0.3), 0.5 * g),
                    (0.85, target, noise(0.5), g),
                    (1.0, target, 0.0, g),
                ]);
            }
        }
        let frames = self.config.frames;
        let n_arms = self.home_tcp.len();
        let mut rows = Vec::with_capacity(frames);
        for f in 0..frames {
            let t = f as f64 / (frames - 1) as f64;
            let k = keys
                .windows(2)
                .position(|w| t <= w[1].0)
                .unwrap_or(keys.len() - 2);
            let (a, b) = (keys[k], keys[k + 1]);
            let s = ((t - a.0) / (b.0 - a.0).max(1e-9)).clamp(0.0, 1.0);
            let s = s * s * (3.0 - 2.0 * s);
            let mut p = a.1 + (b.1 - a.1) * s;
            // Small per-frame action noise, not at the start frame.
            if f > 0 {
                p += Vector3::new(noise(0.0015), noise(0.0015), noise(0.0015));
            }
            let yaw = yaw0 * (t.min(0.25) * 4.0) + a.2 + (b.2 - a.2) * s;
            let g = a.3 + (b.3 - a.3) * s;
            let mut row = Vec::with_capacity(7 * n_arms);
            for (ai, h) in self.home_tcp.iter().enumerate() {
                if ai == arm {
                    let rot =
                        UnitQuaternion::from_axis_angle(&Vector3::z_axis(), yaw) * home.rotation;
                    let v = xyz_rpy_from_pose(&Isometry3::from_parts(Translation3::from(p), rot));
                    row.extend_from_slice(&v);
                    row.push(g.clamp(0.0, 1.0));
                } else {
                    row.extend_from_slice(&xyz_rpy_from_pose(h));
                    row.push(0.0);
                }
            }
            rows.push(row);
        }
        rows
    }
}
