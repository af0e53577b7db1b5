//! Forward and inverse kinematics on a [`Robot`], in f64.
//!
//! Forward kinematics is a pure function of the robot and the actuated joint
//! vector `q` (in [`Robot::dofs`] order): [`Robot::link_poses`] returns
//! `world_from_link` for every link, where "world" is the root link's frame.
//! Trajectories are batched and run in parallel with rayon.
//!
//! Inverse kinematics ([`IkSolver`]) solves for an end-effector link pose with
//! damped least squares (Levenberg-Marquardt damping), joint limits enforced
//! by clamping each step, warm-started from a given `q`, with deterministic
//! random restarts when the warm start fails. Orientation targets use the
//! extrinsic XYZ Euler convention (see [`pose_from_xyz_rpy`]).

use crate::robot::{JointKind, JointSource, Robot};
use nalgebra::{Isometry3, Matrix6, Translation3, UnitQuaternion, Vector3, Vector6};
use rayon::prelude::*;

impl Robot {
    /// `world_from_link` for every link (same order as [`Robot::links`]).
    ///
    /// # Panics
    /// If `q.len() != self.dof()`; validate user input with
    /// [`Robot::check_q`] first.
    pub fn link_poses(&self, q: &[f64]) -> Vec<Isometry3<f64>> {
        let mut out = Vec::with_capacity(self.links.len());
        self.link_poses_into(q, &mut out);
        out
    }

    /// [`Robot::link_poses`] into a reused buffer.
    ///
    /// # Panics
    /// If `q.len() != self.dof()`.
    pub fn link_poses_into(&self, q: &[f64], out: &mut Vec<Isometry3<f64>>) {
        assert_eq!(
            q.len(),
            self.dof(),
            "{}: link_poses needs {} joint values",
            self.source_name,
            self.dof()
        );
        out.clear();
        out.push(Isometry3::identity());
        // Links are topologically ordered and joint `i` has child link `i + 1`.
        for (i, joint) in self.joints.iter().enumerate() {
            let parent = out[joint.parent];
            let value = self.joint_value(i, q);
            out.push(parent * joint.parent_from_child(value));
        }
    }

    /// `world_from_link` of one link, walking only its chain.
    ///
    /// # Panics
    /// If `q.len() != self.dof()` or `link` is out of range.
    pub fn link_pose(&self, link: usize, q: &[f64]) -> Isometry3<f64> {
        assert_eq!(
            q.len(),
            self.dof(),
            "{}: link_pose needs {} joint values",
            self.source_name,
            self.dof()
        );
        let mut pose = Isometry3::identity();
        for j in self.chain_joints(link) {
            pose *= self.joints[j].parent_from_child(self.joint_value(j, q));
        }
        pose
    }

    /// Forward kinematics of every frame of a trajectory, in parallel.
    ///
    /// # Panics
    /// If any frame has the wrong length.
    pub fn trajectory_link_poses(&self, qs: &[Vec<f64>]) -> Vec<Vec<Isometry3<f64>>> {
        qs.par_iter().map(|q| self.link_poses(q)).collect()
    }
}

/// An end-effector pose from `[x, y, z, roll, pitch, yaw]`.
///
/// Convention (DROID's `cartesian_position`, scipy `from_euler("xyz")`):
/// extrinsic rotations about the fixed X, then Y, then Z axes, i.e.
/// `R = Rz(yaw) * Ry(pitch) * Rx(roll)`, the same as URDF `rpy` and
/// nalgebra's `UnitQuaternion::from_euler_angles(roll, pitch, yaw)`.
pub fn pose_from_xyz_rpy(v: [f64; 6]) -> Isometry3<f64> {
    Isometry3::from_parts(
        Translation3::new(v[0], v[1], v[2]),
        UnitQuaternion::from_euler_angles(v[3], v[4], v[5]),
    )
}

/// Inverse of [`pose_from_xyz_rpy`] (`roll, yaw` in `(-pi, pi]`, `pitch` in `[-pi/2, pi/2]`).
pub fn xyz_rpy_from_pose(pose: &Isometry3<f64>) -> [f64; 6] {
    let t = pose.translation.vector;
    let (r, p, y) = pose.rotation.euler_angles();
    [t.x, t.y, t.z, r, p, y]
}

/// Position and rotation distance between two poses: `(metres, radians)`.
pub fn pose_error(a: &Isometry3<f64>, b: &Isometry3<f64>) -> (f64, f64) {
    let dp = (a.translation.vector - b.translation.vector).norm();
    let dr = a.rotation.angle_to(&b.rotation);
    (dp, dr)
}

/// A small deterministic PRNG (SplitMix64) for IK restarts and tests.
pub use bridgev2w_io::seed::SplitMix64;

/// Uniform random joint vector within limits (continuous joints in `[-pi, pi)`).
pub fn random_q(robot: &Robot, rng: &mut SplitMix64) -> Vec<f64> {
    robot
        .dof_limits()
        .into_iter()
        .map(|(lo, hi)| {
            let (lo, hi) = (lo.max(-std::f64::consts::PI), hi.min(std::f64::consts::PI));
            rng.uniform(lo, hi)
        })
        .collect()
}

/// Inverse-kinematics settings.
#[derive(Debug, Clone)]
pub struct IkOptions {
    /// Iteration cap per attempt.
    pub max_iterations: usize,
    /// A solution within this position error counts as reached (metres).
    pub position_tolerance_m: f64,
    /// A solution within this rotation error counts as reached (radians).
    pub rotation_tolerance_rad: f64,
    /// Random restarts after the warm start fails.
    pub restarts: usize,
    /// Seed of the restart generator (solves are deterministic).
    pub seed: u64,
    /// Solve orientation too (otherwise position only).
    pub orientation: bool,
}

impl Default for IkOptions {
    fn default() -> Self {
        Self {
            max_iterations: 100,
            position_tolerance_m: 1e-3,
            rotation_tolerance_rad: 0.5f64.to_radians(),
            restarts: 32,
            seed: 0x5EED,
            orientation: true,
        }
    }
}

/// The outcome of one IK solve.
#[derive(Debug, Clone, PartialEq)]
pub struct IkSolution {
    /// Full joint vector (dofs the solver may not move keep their input values).
    pub q: Vec<f64>,
    /// Remaining position error (metres).
    pub position_error_m: f64,
    /// Remaining rotation error (radians; 0 when orientation is not solved).
    pub rotation_error_rad: f64,
    /// Whether both errors are within the tolerances.
    pub reached: bool,
    /// Iterations summed over attempts.
    pub iterations: usize,
    /// Random restarts used (0 when the warm start succeeded).
    pub restarts_used: usize,
}

/// Damped-least-squares IK for one end-effector link.
#[derive(Debug, Clone)]
pub struct IkSolver<'r> {
    robot: &'r Robot,
    link: usize,
    /// Joints from the root to `link`.
    chain: Vec<usize>,
    /// Column in the Jacobian of each dof, `None` if it may not move.
    column_of_dof: Vec<Option<usize>>,
    /// Dof of each Jacobian column.
    free: Vec<usize>,
    limits: Vec<(f64, f64)>,
}

/// A movable joint on the chain: world axis, world origin, dof, multiplier, kind.
type AxisColumn = (Vector3<f64>, Vector3<f64>, usize, f64, JointKind);

/// Stop refining once errors are this small (far below any tolerance).
const TIGHT_POSITION_M: f64 = 1e-6;
const TIGHT_ROTATION_RAD: f64 = 1e-5;

impl<'r> IkSolver<'r> {
    /// A solver for `link`, moving the dofs on its chain that are in
    /// `allowed` (all chain dofs when `None`).
    pub fn new(robot: &'r Robot, link: usize, allowed: Option<&[usize]>) -> Self {
        let chain = robot.chain_joints(link);
        let mut column_of_dof = vec![None; robot.dof()];
        let mut free = Vec::new();
        for &j in &chain {
            let dof = match robot.joints[j].source {
                JointSource::Dof(d) | JointSource::Mimic { dof: d, .. } => d,
                JointSource::None => continue,
            };
            if allowed.is_some_and(|a| !a.contains(&dof)) || column_of_dof[dof].is_some() {
                continue;
            }
            column_of_dof[dof] = Some(free.len());
            free.push(dof);
        }
        Self {
            robot,
            link,
            chain,
            column_of_dof,
            free,
            limits: robot.dof_limits(),
        }
    }

    /// The dofs this solver moves, in Jacobian column order.
    pub fn free_dofs(&self) -> &[usize] {
        &self.free
    }

    /// The end-effector link index.
    pub fn link(&self) -> usize {
        self.link
    }

    /// Solves for `world_from_target`, starting from `q_init` (warm start),
    /// then from random configurations if that does not reach the target.
    ///
    /// # Panics
    /// If `q_init.len() != robot.dof()`.
    pub fn solve(
        &self,
        world_from_target: &Isometry3<f64>,
        q_init: &[f64],
        opts: &IkOptions,
    ) -> IkSolution {
        let mut best = self.attempt(world_from_target, q_init, opts);
        if best.reached {
            return best;
        }
        let mut rng = SplitMix64::new(opts.seed);
        let mut iterations = best.iterations;
        for r in 0..opts.restarts {
            let mut q0 = q_init.to_vec();
            let random = random_q(self.robot, &mut rng);
            for &d in &self.free {
                q0[d] = random[d];
            }
            let sol = self.attempt(world_from_target, &q0, opts);
            iterations += sol.iterations;
            let better = sol.reached || self.score(&sol, opts) < self.score(&best, opts);
            if better {
                best = sol;
                best.restarts_used = r + 1;
            }
            if best.reached {
                break;
            }
        }
        best.iterations = iterations;
        best
    }

    fn score(&self, s: &IkSolution, opts: &IkOptions) -> f64 {
        s.position_error_m / opts.position_tolerance_m
            + s.rotation_error_rad / opts.rotation_tolerance_rad
    }

    /// End-effector pose plus Jacobian columns (world frame, about the
    /// end-effector origin) for the free dofs.
    fn pose_and_jacobian(&self, q: &[f64], columns: &mut [Vector6<f64>]) -> Isometry3<f64> {
        columns.iter_mut().for_each(|c| *c = Vector6::zeros());
        // First pass: pose of each movable joint's frame; we need the
        // end-effector position before forming the columns, so store them.
        let mut pose = Isometry3::identity();
        let mut axes: [AxisColumn; 32] =
            [(Vector3::zeros(), Vector3::zeros(), 0, 0.0, JointKind::Fixed); 32];
        let mut n = 0;
        for &j in &self.chain {
            let joint = &self.robot.joints[j];
            let value = self.robot.joint_value(j, q);
            if joint.kind.is_movable() && n < axes.len() {
                let (dof, mult) = match joint.source {
                    JointSource::Dof(d) => (d, 1.0),
                    JointSource::Mimic {
                        dof, multiplier, ..
                    } => (dof, multiplier),
                    JointSource::None => (usize::MAX, 0.0),
                };
                if dof != usize::MAX && self.column_of_dof[dof].is_some() {
                    let frame = pose * joint.parent_from_joint;
                    let axis_world = frame.rotation * joint.axis.into_inner();
                    axes[n] = (axis_world, frame.translation.vector, dof, mult, joint.kind);
                    n += 1;
                }
            }
            pose *= joint.parent_from_child(value);
        }
        let p_ee = pose.translation.vector;
        for &(axis, origin, dof, mult, kind) in &axes[..n] {
            let Some(col) = self.column_of_dof[dof] else {
                continue;
            };
            let c = match kind {
                JointKind::Prismatic => Vector6::new(axis.x, axis.y, axis.z, 0.0, 0.0, 0.0),
                _ => {
                    let v = axis.cross(&(p_ee - origin));
                    Vector6::new(v.x, v.y, v.z, axis.x, axis.y, axis.z)
                }
            };
            columns[col] += c * mult;
        }
        pose
    }

    fn error(target: &Isometry3<f64>, pose: &Isometry3<f64>, orientation: bool) -> Vector6<f64> {
        let ep = target.translation.vector - pose.translation.vector;
        let er = if orientation {
            (target.rotation * pose.rotation.inverse()).scaled_axis()
        } else {
            Vector3::zeros()
        };
        Vector6::new(ep.x, ep.y, ep.z, er.x, er.y, er.z)
    }

    fn attempt(&self, target: &Isometry3<f64>, q_init: &[f64], opts: &IkOptions) -> IkSolution {
        assert_eq!(
            q_init.len(),
            self.robot.dof(),
            "IK needs a full joint vector"
        );
        let mut q = q_init.to_vec();
        for &d in &self.free {
            let (lo, hi) = self.limits[d];
            q[d] = q[d].clamp(lo, hi);
        }
        let mut columns = vec![Vector6::zeros(); self.free.len()];
        let mut pose = self.pose_and_jacobian(&q, &mut columns);
        let mut err = Self::error(target, &pose, opts.orientation);
        let mut cost = err.norm_squared();
        let mut lambda = 1e-3;
        let mut q_new = q.clone();
        let mut new_columns = columns.clone();
        let mut iterations = 0;
        while iterations < opts.max_iterations {
            let (ep, er) = (err.fixed_rows::<3>(0).norm(), err.fixed_rows::<3>(3).norm());
            if ep < TIGHT_POSITION_M && er < TIGHT_ROTATION_RAD {
                break;
            }
            iterations += 1;
            // (J J^T + lambda^2 I) y = e ; dq = J^T y
            let mut a = Matrix6::identity() * (lambda * lambda);
            for c in &columns {
                a += c * c.transpose();
            }
            if !opts.orientation {
                for k in 3..6 {
                    a.row_mut(k).fill(0.0);
                    a.column_mut(k).fill(0.0);
                    a[(k, k)] = 1.0;
                }
            }
            let Some(chol) = a.cholesky() else {
                lambda *= 10.0;
                continue;
            };
            let mut e = err;
            if !opts.orientation {
                e.fixed_rows_mut::<3>(3).fill(0.0);
            }
            let y = chol.solve(&e);
            q_new.copy_from_slice(&q);
            for (col, &d) in self.free.iter().enumerate() {
                let (lo, hi) = self.limits[d];
                q_new[d] = (q[d] + columns[col].dot(&y)).clamp(lo, hi);
            }
            let new_pose = self.pose_and_jacobian(&q_new, &mut new_columns);
            let new_err = Self::error(target, &new_pose, opts.orientation);
            let new_cost = new_err.norm_squared();
            if new_cost < cost {
                std::mem::swap(&mut q, &mut q_new);
                std::mem::swap(&mut columns, &mut new_columns);
                pose = new_pose;
                err = new_err;
                let improvement = cost - new_cost;
                cost = new_cost;
                lambda = (lambda * 0.3).max(1e-7);
                if improvement < 1e-18 {
                    break;
                }
            } else {
                lambda *= 8.0;
                if lambda > 1e4 {
                    break;
                }
            }
        }
        let _ = pose;
        let position_error_m = err.fixed_rows::<3>(0).norm();
        let rotation_error_rad = if opts.orientation {
            err.fixed_rows::<3>(3).norm()
        } else {
            0.0
        };
        IkSolution {
            reached: position_error_m <= opts.position_tolerance_m
                && rotation_error_rad <= opts.rotation_tolerance_rad,
            q,
            position_error_m,
            rotation_error_rad,
            iterations,
            restarts_used: 0,
        }
    }
}
