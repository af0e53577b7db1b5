//! URDF documents to a [`Robot`]: parsing, validation, the kinematic tree
//! in topological order, joint kinds, limits and mimic chains.

use super::{Joint, JointKind, JointSource, Link, LoadOptions, Robot, RobotError};
use crate::mesh::TriMesh;
use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

pub(super) fn parse_urdf(text: &str, source_name: &str) -> Result<urdf_rs::Robot, RobotError> {
    // The XML parsers are third-party code: turn any panic into an error.
    let result = bridgev2w_io::quiet_panic::catch_quiet(|| urdf_rs::read_from_string(text));
    match result {
        Ok(Ok(robot)) => Ok(robot),
        Ok(Err(e)) => Err(RobotError::Parse {
            source_name: source_name.to_string(),
            message: e.to_string(),
        }),
        Err(_) => Err(RobotError::Parse {
            source_name: source_name.to_string(),
            message: "the XML parser panicked on this input".to_string(),
        }),
    }
}

pub(super) struct Builder<'a> {
    pub(super) source_name: &'a str,
    pub(super) base_dir: Option<&'a Path>,
    pub(super) options: &'a LoadOptions,
    pub(super) mesh_cache: HashMap<PathBuf, Arc<TriMesh>>,
}

fn finite3(v: &[f64; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
}

pub(super) fn pose_to_isometry(pose: &urdf_rs::Pose) -> Isometry3<f64> {
    let [x, y, z] = pose.xyz.0;
    let [r, p, yaw] = pose.rpy.0;
    // URDF rpy: fixed-axis (extrinsic) X, then Y, then Z: R = Rz(yaw) Ry(p) Rx(r).
    Isometry3::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_euler_angles(r, p, yaw),
    )
}

impl Builder<'_> {
    pub(super) fn invalid(&self, message: String) -> RobotError {
        RobotError::Invalid {
            source_name: self.source_name.to_string(),
            message,
        }
    }

    pub(super) fn check_pose(&self, pose: &urdf_rs::Pose, what: &str) -> Result<(), RobotError> {
        if !finite3(&pose.xyz.0) || !finite3(&pose.rpy.0) {
            return Err(self.invalid(format!(
                "{what}: origin xyz={:?} rpy={:?}: expected finite numbers",
                pose.xyz.0, pose.rpy.0
            )));
        }
        Ok(())
    }

    pub(super) fn build(mut self, urdf: &urdf_rs::Robot) -> Result<Robot, RobotError> {
        if urdf.links.is_empty() {
            return Err(self.invalid("the robot has no <link>".to_string()));
        }
        let mut link_by_name: HashMap<&str, usize> = HashMap::new();
        for (i, l) in urdf.links.iter().enumerate() {
            if link_by_name.insert(l.name.as_str(), i).is_some() {
                return Err(self.invalid(format!("link \"{}\" is defined twice", l.name)));
            }
        }
        let mut joint_names: HashMap<&str, usize> = HashMap::new();
        // child link (URDF index) -> joint (URDF index)
        let mut joint_of_child: HashMap<usize, usize> = HashMap::new();
        let mut children: Vec<Vec<usize>> = vec![Vec::new(); urdf.links.len()];
        for (ji, j) in urdf.joints.iter().enumerate() {
            if joint_names.insert(j.name.as_str(), ji).is_some() {
                return Err(self.invalid(format!("joint \"{}\" is defined twice", j.name)));
            }
            let parent = *link_by_name.get(j.parent.link.as_str()).ok_or_else(|| {
                self.invalid(format!(
                    "joint \"{}\": parent link \"{}\" does not exist",
                    j.name, j.parent.link
                ))
            })?;
            let child = *link_by_name.get(j.child.link.as_str()).ok_or_else(|| {
                self.invalid(format!(
                    "joint \"{}\": child link \"{}\" does not exist",
                    j.name, j.child.link
                ))
            })?;
            if let Some(other) = joint_of_child.insert(child, ji) {
                return Err(self.invalid(format!(
                    "link \"{}\" is the child of two joints (\"{}\" and \"{}\")",
                    j.child.link, urdf.joints[other].name, j.name
                )));
            }
            children[parent].push(ji);
        }
        let roots: Vec<usize> = (0..urdf.links.len())
            .filter(|i| !joint_of_child.contains_key(i))
            .collect();
        let root = match roots.as_slice() {
            [r] => *r,
            [] => return Err(self.invalid("the joints form a cycle: no root link".to_string())),
            many => {
                let names: Vec<&str> = many.iter().map(|&i| urdf.links[i].name.as_str()).collect();
                return Err(self.invalid(format!(
                    "expected one root link but found {}: {}",
                    many.len(),
                    names.join(", ")
                )));
            }
        };

        // Topological order by depth-first traversal from the root; joints
        // are visited in document order so the result is deterministic.
        let mut order: Vec<usize> = Vec::with_capacity(urdf.links.len());
        let mut stack = vec![root];
        while let Some(l) = stack.pop() {
            order.push(l);
            for &ji in children[l].iter().rev() {
                let c = link_by_name[urdf.joints[ji].child.link.as_str()];
                stack.push(c);
            }
        }
        if order.len() != urdf.links.len() {
            return Err(self.invalid("the joints form a cycle".to_string()));
        }
        let mut new_link_index = vec![0usize; urdf.links.len()];
        for (new, &old) in order.iter().enumerate() {
            new_link_index[old] = new;
        }

        // Actuated joints in document order.
        let mut dof_of_joint: HashMap<usize, usize> = HashMap::new();
        let mut dofs_urdf = Vec::new();
        for (ji, j) in urdf.joints.iter().enumerate() {
            let kind = self.joint_kind(j)?;
            if kind.is_movable() && j.mimic.is_none() {
                dof_of_joint.insert(ji, dofs_urdf.len());
                dofs_urdf.push(ji);
            }
        }

        // Joints ordered like their child links (root has none).
        let mut joints = Vec::with_capacity(urdf.joints.len());
        let mut new_joint_index = vec![usize::MAX; urdf.joints.len()];
        for &old_link in order.iter().skip(1) {
            let ji = joint_of_child[&old_link];
            new_joint_index[ji] = joints.len();
            joints.push(self.joint(
                urdf,
                ji,
                &joint_names,
                &dof_of_joint,
                &link_by_name,
                &new_link_index,
            )?);
        }
        let dofs = dofs_urdf.iter().map(|&ji| new_joint_index[ji]).collect();

        let mut links = Vec::with_capacity(order.len());
        for &old in &order {
            let l = &urdf.links[old];
            let parent_joint = joint_of_child.get(&old).map(|&ji| new_joint_index[ji]);
            let parent = parent_joint.map(|j: usize| joints[j].parent);
            let geometry = if self.options.skip_geometry {
                None
            } else {
                self.link_mesh(l)?
            };
            links.push(Link {
                name: l.name.clone(),
                parent_joint,
                parent,
                mesh_closed: geometry
                    .as_ref()
                    .is_some_and(|g| g.1 == g.0.triangles.len()),
                mesh_closed_triangles: geometry.as_ref().map_or(0, |g| g.1),
                mesh: geometry.map(|g| g.0),
            });
        }
        Ok(Robot {
            name: urdf.name.clone(),
            source_name: self.source_name.to_string(),
            links,
            joints,
            dofs,
        })
    }

    fn joint_kind(&self, j: &urdf_rs::Joint) -> Result<JointKind, RobotError> {
        use urdf_rs::JointType as T;
        Ok(match j.joint_type {
            T::Fixed => JointKind::Fixed,
            T::Revolute => JointKind::Revolute,
            T::Continuous => JointKind::Continuous,
            T::Prismatic => JointKind::Prismatic,
            T::Floating | T::Planar | T::Spherical => {
                return Err(self.invalid(format!(
                    "joint \"{}\": type {:?} is not supported (expected revolute, continuous, prismatic or fixed)",
                    j.name, j.joint_type
                )))
            }
        })
    }

    fn joint(
        &self,
        urdf: &urdf_rs::Robot,
        ji: usize,
        joint_names: &HashMap<&str, usize>,
        dof_of_joint: &HashMap<usize, usize>,
        link_by_name: &HashMap<&str, usize>,
        new_link_index: &[usize],
    ) -> Result<Joint, RobotError> {
        let j = &urdf.joints[ji];
        let kind = self.joint_kind(j)?;
        self.check_pose(&j.origin, &format!("joint \"{}\"", j.name))?;
        let axis_v = Vector3::from(j.axis.xyz.0);
        let axis = if kind.is_movable() {
            let norm = axis_v.norm();
            if !norm.is_finite() || norm < 1e-9 {
                return Err(self.invalid(format!(
                    "joint \"{}\": axis xyz={:?}: expected a finite non-zero vector",
                    j.name, j.axis.xyz.0
                )));
            }
            Unit::new_normalize(axis_v)
        } else {
            Vector3::x_axis()
        };
        let limits = match kind {
            JointKind::Revolute | JointKind::Prismatic => {
                let (lo, hi) = (j.limit.lower, j.limit.upper);
                if !lo.is_finite() || !hi.is_finite() || lo > hi {
                    return Err(self.invalid(format!(
                        "joint \"{}\": limit lower={lo} upper={hi}: expected finite values with lower <= upper",
                        j.name
                    )));
                }
                // urdf-rs reads a missing <limit> as lower = upper = 0, which
                // would lock the joint and fail much later.
                if lo == 0.0 && hi == 0.0 {
                    return Err(self.invalid(format!(
                        "joint \"{}\" ({}): no <limit lower upper> (or a zero range): URDF requires one on revolute and prismatic joints; use type=\"continuous\" for an unlimited revolute joint, type=\"fixed\" for a locked one",
                        j.name,
                        if kind == JointKind::Revolute { "revolute" } else { "prismatic" }
                    )));
                }
                Some((lo, hi))
            }
            _ => None,
        };
        let source = if !kind.is_movable() {
            JointSource::None
        } else if let Some(m) = &j.mimic {
            // Resolve chains of mimics down to an actuated joint.
            let (mut multiplier, mut offset) =
                (m.multiplier.unwrap_or(1.0), m.offset.unwrap_or(0.0));
            let mut target_name = m.joint.as_str();
            let mut hops = 0;
            loop {
                let t = *joint_names.get(target_name).ok_or_else(|| {
                    self.invalid(format!(
                        "joint \"{}\": <mimic joint=\"{target_name}\"> names a joint that does not exist",
                        j.name
                    ))
                })?;
                if let Some(&dof) = dof_of_joint.get(&t) {
                    break JointSource::Mimic {
                        dof,
                        multiplier,
                        offset,
                    };
                }
                let tj = &urdf.joints[t];
                match (&tj.mimic, self.joint_kind(tj)?.is_movable()) {
                    (Some(m2), true) if hops < urdf.joints.len() => {
                        // value = (q * m2 + o2) * m + o
                        let (m2m, m2o) = (m2.multiplier.unwrap_or(1.0), m2.offset.unwrap_or(0.0));
                        offset += multiplier * m2o;
                        multiplier *= m2m;
                        target_name = m2.joint.as_str();
                        hops += 1;
                    }
                    _ => {
                        return Err(self.invalid(format!(
                            "joint \"{}\": <mimic joint=\"{}\"> must name a movable joint (mimic cycles are not allowed)",
                            j.name, m.joint
                        )))
                    }
                }
            }
        } else {
            JointSource::Dof(dof_of_joint[&ji])
        };
        if let JointSource::Mimic {
            multiplier, offset, ..
        } = source
        {
            if !multiplier.is_finite() || !offset.is_finite() {
                return Err(self.invalid(format!(
                    "joint \"{}\": mimic multiplier={multiplier} offset={offset}: expected finite values",
                    j.name
                )));
            }
        }
        let parent = new_link_index[link_by_name[j.parent.link.as_str()]];
        let child = new_link_index[link_by_name[j.child.link.as_str()]];
        Ok(Joint {
            name: j.name.clone(),
            kind,
            parent,
            child,
            parent_from_joint: pose_to_isometry(&j.origin),
            axis,
            limits,
            source,
        })
    }
}
