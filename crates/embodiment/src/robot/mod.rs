//! Robot models from URDF: the kinematic tree, joint limits, mimic joints and
//! link geometry as triangle meshes in each link's frame.
//!
//! A [`Robot`] is immutable once built; kinematics ([`crate::kinematics`]) are
//! pure functions of it and a joint vector. Links are stored in topological
//! order (every parent before its children), the root first. The *actuated*
//! joints (revolute, continuous and prismatic joints without `<mimic>`) define
//! the joint vector `q`, in URDF document order; `bridgev2w robot-info`
//! prints that order.

// One job per file: `error` (what can go wrong), `urdf` (URDF document to
// kinematic tree), `geometry` (link visuals to meshes, mesh file search);
// this file holds the model itself.
mod error;
mod geometry;
mod urdf;

pub use error::RobotError;
pub use geometry::{mesh_candidates, PRIMITIVE_SEGMENTS};

use crate::mesh::TriMesh;
use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use urdf::{parse_urdf, Builder};

/// The motion a joint allows.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum JointKind {
    /// No motion.
    Fixed,
    /// Rotation about `axis` (radians).
    Revolute,
    /// Rotation about `axis` without limits (radians).
    Continuous,
    /// Translation along `axis` (metres).
    Prismatic,
}

impl JointKind {
    /// Whether the joint has a degree of freedom.
    pub fn is_movable(self) -> bool {
        !matches!(self, JointKind::Fixed)
    }
}

/// Where a joint's value comes from.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum JointSource {
    /// A fixed joint: no value.
    None,
    /// Actuated: `q[index]`.
    Dof(usize),
    /// `<mimic>`: `q[dof] * multiplier + offset` (chains of mimics resolved).
    Mimic {
        /// The actuated joint's index in `q`.
        dof: usize,
        /// Multiplier (URDF default 1).
        multiplier: f64,
        /// Offset (URDF default 0).
        offset: f64,
    },
}

/// A joint, connecting `parent` link to `child` link.
#[derive(Debug, Clone)]
pub struct Joint {
    /// URDF name.
    pub name: String,
    /// Motion type.
    pub kind: JointKind,
    /// Index of the parent link in [`Robot::links`].
    pub parent: usize,
    /// Index of the child link in [`Robot::links`].
    pub child: usize,
    /// The joint frame in the parent link frame at zero joint value (`<origin>`).
    pub parent_from_joint: Isometry3<f64>,
    /// Unit axis in the joint frame.
    pub axis: Unit<Vector3<f64>>,
    /// Position limits `(lower, upper)` (radians or metres); `None` for
    /// continuous and fixed joints.
    pub limits: Option<(f64, f64)>,
    /// Where the value comes from.
    pub source: JointSource,
}

impl Joint {
    /// The child link frame in the parent link frame at joint value `value`.
    #[inline]
    pub fn parent_from_child(&self, value: f64) -> Isometry3<f64> {
        match self.kind {
            JointKind::Fixed => self.parent_from_joint,
            JointKind::Revolute | JointKind::Continuous => {
                self.parent_from_joint * UnitQuaternion::from_axis_angle(&self.axis, value)
            }
            JointKind::Prismatic => {
                self.parent_from_joint * Translation3::from(self.axis.into_inner() * value)
            }
        }
    }
}

/// A link and its geometry.
#[derive(Debug, Clone)]
pub struct Link {
    /// URDF name.
    pub name: String,
    /// Index of the joint whose child this link is (`None` for the root).
    pub parent_joint: Option<usize>,
    /// Index of the parent link (`None` for the root).
    pub parent: Option<usize>,
    /// All `<visual>` geometry merged into one mesh in the link frame, or
    /// `None` if the link has no visual geometry.
    pub mesh: Option<Arc<TriMesh>>,
    /// Whether `mesh` is closed (every part bounds a volume) with outward
    /// winding, so back faces may be culled when rendering.
    pub mesh_closed: bool,
    /// Number of leading triangles of `mesh` that belong to closed,
    /// outward-wound connected components (all of them when `mesh_closed`):
    /// the renderer may skip their back faces. Meshes are stored with such
    /// components first ([`TriMesh::closed_components_first`]).
    pub mesh_closed_triangles: usize,
}

/// Options for building a robot from URDF.
#[derive(Debug, Clone, Default)]
pub struct LoadOptions {
    /// Directories searched for `package://` and relative mesh paths, in
    /// order, after the URDF's own directory. `ROS_PACKAGE_PATH` entries are
    /// appended when `use_ros_package_path` is set.
    pub mesh_search_paths: Vec<PathBuf>,
    /// Also search the directories listed in `ROS_PACKAGE_PATH`.
    pub use_ros_package_path: bool,
    /// Skip all visual geometry (kinematics only).
    pub skip_geometry: bool,
    /// Mesh files compiled into the binary, by their path relative to the
    /// URDF's folder (`meshes/link1.stl`): a relative mesh filename is looked
    /// up here first (the built-in robots' meshes, [`crate::embodiment::BuiltinRobot::files`]).
    pub embedded_files: &'static [(&'static str, &'static [u8])],
}

/// A robot: kinematic tree plus link meshes.
#[derive(Debug, Clone)]
pub struct Robot {
    /// `<robot name=..>`.
    pub name: String,
    /// Where it came from (file path or built-in name), used in messages.
    pub source_name: String,
    /// Links in topological order, root first.
    pub links: Vec<Link>,
    /// Joints; `links[j.child].parent_joint == Some(j)`.
    pub joints: Vec<Joint>,
    /// Indices into `joints` of the actuated joints, in `q` order.
    pub dofs: Vec<usize>,
}

impl Robot {
    /// Loads a URDF file; relative and `package://` mesh paths are resolved
    /// against the file's directory and `options.mesh_search_paths`.
    pub fn from_urdf_file(path: &Path, options: &LoadOptions) -> Result<Robot, RobotError> {
        let text = std::fs::read_to_string(path).map_err(|source| RobotError::Io {
            path: path.to_path_buf(),
            source,
        })?;
        let base_dir = path.parent().map(Path::to_path_buf);
        Self::from_urdf_str(
            &text,
            &path.display().to_string(),
            base_dir.as_deref(),
            options,
        )
    }

    /// Builds a robot from URDF text. `source_name` names it in errors;
    /// `base_dir` is where relative mesh paths start.
    pub fn from_urdf_str(
        text: &str,
        source_name: &str,
        base_dir: Option<&Path>,
        options: &LoadOptions,
    ) -> Result<Robot, RobotError> {
        let parsed = parse_urdf(text, source_name)?;
        Builder {
            source_name,
            base_dir,
            options,
            mesh_cache: HashMap::new(),
        }
        .build(&parsed)
    }

    /// Number of actuated joints (the length of `q`).
    pub fn dof(&self) -> usize {
        self.dofs.len()
    }

    /// Names of the actuated joints in `q` order.
    pub fn dof_names(&self) -> Vec<&str> {
        self.dofs
            .iter()
            .map(|&j| self.joints[j].name.as_str())
            .collect()
    }

    /// Index of a link by name.
    pub fn link_index(&self, name: &str) -> Option<usize> {
        self.links.iter().position(|l| l.name == name)
    }

    /// Every link's name, comma-separated (for messages).
    pub fn link_names(&self) -> String {
        self.links
            .iter()
            .map(|l| l.name.as_str())
            .collect::<Vec<_>>()
            .join(", ")
    }

    /// The movable joints (actuated or mimic) that move `link`, root to
    /// tip: two links with the same list are rigidly attached.
    pub fn moving_joints(&self, link: usize) -> Vec<usize> {
        self.chain_joints(link)
            .into_iter()
            .filter(|&j| self.joints[j].kind.is_movable())
            .collect()
    }

    /// Index of a joint by name.
    pub fn joint_index(&self, name: &str) -> Option<usize> {
        self.joints.iter().position(|j| j.name == name)
    }

    /// Index in `q` of an actuated joint by name.
    pub fn dof_index(&self, joint_name: &str) -> Option<usize> {
        self.dofs
            .iter()
            .position(|&j| self.joints[j].name == joint_name)
    }

    /// Limits of every dof in `q` order (`(-inf, inf)` for continuous joints).
    pub fn dof_limits(&self) -> Vec<(f64, f64)> {
        self.dofs
            .iter()
            .map(|&j| {
                self.joints[j]
                    .limits
                    .unwrap_or((f64::NEG_INFINITY, f64::INFINITY))
            })
            .collect()
    }

    /// Value of joint `j` given the actuated vector `q` (mimics applied).
    #[inline]
    pub fn joint_value(&self, j: usize, q: &[f64]) -> f64 {
        match self.joints[j].source {
            JointSource::None => 0.0,
            JointSource::Dof(i) => q[i],
            JointSource::Mimic {
                dof,
                multiplier,
                offset,
            } => q[dof] * multiplier + offset,
        }
    }

    /// The dof indices that move `link` (its ancestors' actuated or mimic
    /// joints), root to tip, each with the joint index.
    pub fn chain_joints(&self, link: usize) -> Vec<usize> {
        let mut chain = Vec::new();
        let mut current = link;
        while let Some(j) = self.links[current].parent_joint {
            chain.push(j);
            current = self.joints[j].parent;
        }
        chain.reverse();
        chain
    }

    /// Checks that `q` has the right length and finite values within limits
    /// (with `tolerance`). `what` names the input in the error.
    pub fn check_q(&self, q: &[f64], tolerance: f64) -> Result<(), String> {
        if q.len() != self.dof() {
            return Err(format!(
                "expected {} joint values ({}) but got {}",
                self.dof(),
                self.dof_names().join(", "),
                q.len()
            ));
        }
        for (i, (&v, (lo, hi))) in q.iter().zip(self.dof_limits()).enumerate() {
            let name = &self.joints[self.dofs[i]].name;
            if !v.is_finite() {
                return Err(format!("joint \"{name}\" = {v}: expected a finite value"));
            }
            if v < lo - tolerance || v > hi + tolerance {
                return Err(format!(
                    "joint \"{name}\" = {v}: outside its limits [{lo}, {hi}]"
                ));
            }
        }
        Ok(())
    }

    /// The joints whose values in `rows` (joint vectors in `q` order) lie
    /// outside their limits by more than `tolerance`: per joint, how many
    /// values, the worst one and its frame. Values are not changed: a
    /// recorded state past a limit is rendered as recorded, and reported.
    pub fn limit_violations(&self, rows: &[Vec<f64>], tolerance: f64) -> Vec<LimitViolation> {
        let limits = self.dof_limits();
        let mut out: Vec<LimitViolation> = Vec::new();
        for (d, &(lo, hi)) in limits.iter().enumerate() {
            let mut v: Option<LimitViolation> = None;
            for (t, row) in rows.iter().enumerate() {
                let Some(&x) = row.get(d) else { continue };
                let excess = (lo - x).max(x - hi);
                if excess.is_nan() || excess <= tolerance {
                    continue;
                }
                let e = v.get_or_insert_with(|| LimitViolation {
                    joint: self.joints[self.dofs[d]].name.clone(),
                    limits: (lo, hi),
                    count: 0,
                    worst_value: x,
                    worst_frame: t,
                });
                e.count += 1;
                if excess > (lo - e.worst_value).max(e.worst_value - hi) {
                    e.worst_value = x;
                    e.worst_frame = t;
                }
            }
            out.extend(v);
        }
        out
    }
}

/// Values of one joint outside its limits over a trajectory
/// ([`Robot::limit_violations`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct LimitViolation {
    /// The joint's name.
    pub joint: String,
    /// Its limits `(lower, upper)`.
    pub limits: (f64, f64),
    /// How many frames are outside them.
    pub count: usize,
    /// The value furthest outside.
    pub worst_value: f64,
    /// The frame of that value.
    pub worst_frame: usize,
}

impl std::fmt::Display for LimitViolation {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(
            f,
            "joint \"{}\": {} frame(s) outside its limits [{}, {}], worst {} (frame {})",
            self.joint,
            self.count,
            self.limits.0,
            self.limits.1,
            self.worst_value,
            self.worst_frame
        )
    }
}
