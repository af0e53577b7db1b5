//! Robot models from URDF: the kinematic tree, joint limits, mimic joints and
//! link geometry as triangle meshes in each link's frame.
//!
//! A [`Robot`] is immutable once built; kinematics ([`crate::kinematics`]) are
//! pure functions of it and a joint vector. Links are stored in topological
//! order (every parent before its children), the root first. The *actuated*
//! joints (revolute, continuous and prismatic joints without `<mimic>`) define
//! the joint vector `q`, in URDF document order; `bridgev2w robot-info`
//! prints that order.

use crate::mesh::load::{load_mesh, MeshError};
use crate::mesh::TriMesh;
use nalgebra::{Isometry3, Translation3, Unit, UnitQuaternion, Vector3};
use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Segments used to tessellate URDF cylinders, spheres and capsules.
pub const PRIMITIVE_SEGMENTS: u32 = 32;

/// Errors building a [`Robot`]. Every message names the URDF source.
#[derive(Debug, thiserror::Error)]
pub enum RobotError {
    /// The URDF file could not be read.
    #[error("{path}: cannot read URDF: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The XML is not a valid URDF document.
    #[error("{source_name}: malformed URDF: {message}")]
    Parse {
        /// File path or built-in robot name.
        source_name: String,
        /// What the parser reported.
        message: String,
    },
    /// The document parsed but describes an invalid robot.
    #[error("{source_name}: {message}")]
    Invalid {
        /// File path or built-in robot name.
        source_name: String,
        /// What is wrong, naming the link/joint/field and value.
        message: String,
    },
    /// A `<mesh filename=..>` could not be found on disk.
    #[error("{source_name}: link \"{link}\": mesh \"{filename}\" not found (tried: {tried}); add its directory with --mesh-path")]
    MeshNotFound {
        /// File path or built-in robot name.
        source_name: String,
        /// The link whose visual references the mesh.
        link: String,
        /// The filename as written in the URDF.
        filename: String,
        /// The candidate paths that were tried.
        tried: String,
    },
    /// A mesh file was found but could not be loaded.
    #[error("{source_name}: link \"{link}\": {source}")]
    Mesh {
        /// File path or built-in robot name.
        source_name: String,
        /// The link whose visual references the mesh.
        link: String,
        /// The loader error (names the mesh file).
        source: MeshError,
    },
}

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
}

fn parse_urdf(text: &str, source_name: &str) -> Result<urdf_rs::Robot, RobotError> {
    // The XML parsers are third-party code: turn any panic into an error.
    let result = crate::quiet_panic::catch_quiet(|| urdf_rs::read_from_string(text));
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

struct Builder<'a> {
    source_name: &'a str,
    base_dir: Option<&'a Path>,
    options: &'a LoadOptions,
    mesh_cache: HashMap<PathBuf, Arc<TriMesh>>,
}

fn finite3(v: &[f64; 3]) -> bool {
    v.iter().all(|x| x.is_finite())
}

fn pose_to_isometry(pose: &urdf_rs::Pose) -> Isometry3<f64> {
    let [x, y, z] = pose.xyz.0;
    let [r, p, yaw] = pose.rpy.0;
    // URDF rpy: fixed-axis (extrinsic) X, then Y, then Z: R = Rz(yaw) Ry(p) Rx(r).
    Isometry3::from_parts(
        Translation3::new(x, y, z),
        UnitQuaternion::from_euler_angles(r, p, yaw),
    )
}

impl Builder<'_> {
    fn invalid(&self, message: String) -> RobotError {
        RobotError::Invalid {
            source_name: self.source_name.to_string(),
            message,
        }
    }

    fn check_pose(&self, pose: &urdf_rs::Pose, what: &str) -> Result<(), RobotError> {
        if !finite3(&pose.xyz.0) || !finite3(&pose.rpy.0) {
            return Err(self.invalid(format!(
                "{what}: origin xyz={:?} rpy={:?}: expected finite numbers",
                pose.xyz.0, pose.rpy.0
            )));
        }
        Ok(())
    }

    fn build(mut self, urdf: &urdf_rs::Robot) -> Result<Robot, RobotError> {
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

    fn link_mesh(
        &mut self,
        l: &urdf_rs::Link,
    ) -> Result<Option<(Arc<TriMesh>, usize)>, RobotError> {
        if l.visual.is_empty() {
            return Ok(None);
        }
        // Closed components of every visual first (outward-wound), then
        // the open ones.
        let mut closed = TriMesh::default();
        let mut open = TriMesh::default();
        for (vi, v) in l.visual.iter().enumerate() {
            self.check_pose(&v.origin, &format!("link \"{}\" visual {vi}", l.name))?;
            let link_from_visual = pose_to_isometry(&v.origin);
            let bad =
                |what: String| self.invalid(format!("link \"{}\" visual {vi}: {what}", l.name));
            let positive = |x: f64| x.is_finite() && x > 0.0;
            let part: Arc<TriMesh> = match &v.geometry {
                urdf_rs::Geometry::Box { size } => {
                    if !size.0.iter().all(|&s| positive(s)) {
                        return Err(bad(format!(
                            "box size={:?}: expected three finite sizes > 0",
                            size.0
                        )));
                    }
                    Arc::new(TriMesh::cuboid(size.0.map(|s| s as f32)))
                }
                urdf_rs::Geometry::Cylinder { radius, length } => {
                    if !positive(*radius) || !positive(*length) {
                        return Err(bad(format!(
                            "cylinder radius={radius} length={length}: expected finite values > 0"
                        )));
                    }
                    Arc::new(TriMesh::cylinder(
                        *radius as f32,
                        *length as f32,
                        PRIMITIVE_SEGMENTS,
                    ))
                }
                urdf_rs::Geometry::Capsule { radius, length } => {
                    if !(positive(*radius) && length.is_finite() && *length >= 0.0) {
                        return Err(bad(format!(
                            "capsule radius={radius} length={length}: expected radius > 0 and length >= 0"
                        )));
                    }
                    Arc::new(TriMesh::capsule(
                        *radius as f32,
                        *length as f32,
                        PRIMITIVE_SEGMENTS,
                    ))
                }
                urdf_rs::Geometry::Sphere { radius } => {
                    if !positive(*radius) {
                        return Err(bad(format!(
                            "sphere radius={radius}: expected a finite value > 0"
                        )));
                    }
                    Arc::new(TriMesh::sphere(*radius as f32, PRIMITIVE_SEGMENTS))
                }
                urdf_rs::Geometry::Mesh { filename, scale } => {
                    let scale = scale.as_ref().map(|s| s.0).unwrap_or([1.0; 3]);
                    if !scale.iter().all(|s| s.is_finite() && *s != 0.0) {
                        return Err(bad(format!(
                            "mesh \"{filename}\" scale={scale:?}: expected finite non-zero factors"
                        )));
                    }
                    let mesh = self.mesh_file(&l.name, filename)?;
                    if scale == [1.0; 3] {
                        mesh
                    } else {
                        Arc::new((*mesh).clone().scaled(scale.map(|s| s as f32)))
                    }
                }
            };
            let placed = part.transformed(&link_from_visual);
            if let Some(v) = placed
                .vertices
                .iter()
                .find(|v| !v.iter().all(|c| c.is_finite()))
            {
                return Err(self.invalid(format!(
                    "link \"{}\" visual {vi}: a vertex lands at {v:?} after scale and origin: expected coordinates within the f32 range",
                    l.name
                )));
            }
            // Closed components are made outward-facing so the renderer may
            // skip their back faces (exact for closed surfaces).
            let (sorted, n_closed) = placed.closed_components_first();
            let (head, tail) = sorted.triangles.split_at(n_closed);
            closed.append(&TriMesh {
                vertices: sorted.vertices.clone(),
                triangles: head.to_vec(),
            });
            open.append(&TriMesh {
                vertices: sorted.vertices,
                triangles: tail.to_vec(),
            });
        }
        let n_closed = closed.triangles.len();
        closed.append(&open);
        // Each visual's vertices were appended twice: drop unused ones.
        Ok(Some((Arc::new(closed.compacted()), n_closed)))
    }

    fn mesh_file(&mut self, link: &str, filename: &str) -> Result<Arc<TriMesh>, RobotError> {
        let candidates = mesh_candidates(filename, self.base_dir, self.options);
        let Some(path) = candidates.iter().find(|p| p.is_file()) else {
            return Err(RobotError::MeshNotFound {
                source_name: self.source_name.to_string(),
                link: link.to_string(),
                filename: filename.to_string(),
                tried: candidates
                    .iter()
                    .map(|p| p.display().to_string())
                    .collect::<Vec<_>>()
                    .join(", "),
            });
        };
        if let Some(mesh) = self.mesh_cache.get(path) {
            return Ok(mesh.clone());
        }
        let mesh = Arc::new(
            load_mesh(path)
                .map_err(|source| RobotError::Mesh {
                    source_name: self.source_name.to_string(),
                    link: link.to_string(),
                    source,
                })?
                .welded(),
        );
        self.mesh_cache.insert(path.clone(), mesh.clone());
        Ok(mesh)
    }
}

/// Candidate paths for a URDF mesh filename, in search order.
///
/// - `package://pkg/rest`: for each search directory `d`: `d/pkg/rest`,
///   `d/rest`; also the URDF directory and its parents (a package's URDF
///   usually lives in `pkg/urdf/`).
/// - `file:///abs`: that path.
/// - absolute paths: as is.
/// - relative paths: the URDF directory, then each search directory.
pub fn mesh_candidates(
    filename: &str,
    base_dir: Option<&Path>,
    options: &LoadOptions,
) -> Vec<PathBuf> {
    let mut dirs: Vec<PathBuf> = Vec::new();
    if let Some(b) = base_dir {
        dirs.push(b.to_path_buf());
    }
    dirs.extend(options.mesh_search_paths.iter().cloned());
    if options.use_ros_package_path {
        if let Some(v) = std::env::var_os("ROS_PACKAGE_PATH") {
            dirs.extend(std::env::split_paths(&v));
        }
    }
    let mut out = Vec::new();
    if let Some(rest) = filename.strip_prefix("package://") {
        let (pkg, tail) = rest.split_once('/').unwrap_or((rest, ""));
        for d in &dirs {
            out.push(d.join(pkg).join(tail));
            out.push(d.join(tail));
        }
        // A URDF inside `<pkg>/urdf/`: walk up the base directory looking for `<pkg>`.
        if let Some(b) = base_dir {
            for anc in b.ancestors().skip(1) {
                out.push(anc.join(pkg).join(tail));
                if anc.file_name().is_some_and(|n| n == pkg) {
                    out.push(anc.join(tail));
                }
            }
            if b.file_name().is_some_and(|n| n == pkg) {
                out.push(b.join(tail));
            }
        }
    } else if let Some(abs) = filename.strip_prefix("file://") {
        out.push(PathBuf::from(abs));
    } else {
        let p = Path::new(filename);
        if p.is_absolute() {
            out.push(p.to_path_buf());
        } else {
            for d in &dirs {
                out.push(d.join(p));
            }
            if dirs.is_empty() {
                out.push(p.to_path_buf());
            }
        }
    }
    let mut seen = std::collections::HashSet::new();
    out.retain(|p| seen.insert(p.clone()));
    out
}
