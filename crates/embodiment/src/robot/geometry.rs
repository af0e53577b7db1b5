//! Link geometry: `<visual>` elements to one triangle mesh per link, and
//! the search for mesh files.

use super::urdf::{pose_to_isometry, Builder};
use super::{LoadOptions, RobotError};
use crate::mesh::load::{load_mesh, load_mesh_from_bytes, MeshError, MeshFormat};
use crate::mesh::TriMesh;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Segments used to tessellate URDF cylinders, spheres and capsules.
pub const PRIMITIVE_SEGMENTS: u32 = 32;

impl Builder<'_> {
    pub(super) fn link_mesh(
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
        if let Some(mesh) = self.embedded_mesh(link, filename)? {
            return Ok(mesh);
        }
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

impl Builder<'_> {
    /// The mesh named `filename` (a path relative to the URDF's folder) from
    /// [`LoadOptions::embedded_files`], if it is there.
    fn embedded_mesh(
        &mut self,
        link: &str,
        filename: &str,
    ) -> Result<Option<Arc<TriMesh>>, RobotError> {
        let wanted = filename.trim_start_matches("./");
        let Some((name, bytes)) = self
            .options
            .embedded_files
            .iter()
            .find(|(name, _)| *name == wanted)
        else {
            return Ok(None);
        };
        let key = PathBuf::from(format!("<embedded>/{name}"));
        if let Some(mesh) = self.mesh_cache.get(&key) {
            return Ok(Some(mesh.clone()));
        }
        let mesh_err = |source| RobotError::Mesh {
            source_name: self.source_name.to_string(),
            link: link.to_string(),
            source,
        };
        let format = MeshFormat::from_path(Path::new(name)).ok_or_else(|| {
            mesh_err(MeshError::UnsupportedFormat {
                name: name.to_string(),
                extension: Path::new(name)
                    .extension()
                    .map(|e| e.to_string_lossy().into_owned())
                    .unwrap_or_default(),
            })
        })?;
        let mesh = Arc::new(
            load_mesh_from_bytes(bytes, format, &format!("{}/{name}", self.source_name))
                .map_err(mesh_err)?
                .welded(),
        );
        self.mesh_cache.insert(key, mesh.clone());
        Ok(Some(mesh))
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
