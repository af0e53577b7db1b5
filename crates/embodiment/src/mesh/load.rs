//! Mesh files (temporary placeholder until the loader lands).
use super::TriMesh;
use std::path::Path;
/// Mesh loading error.
#[derive(Debug, thiserror::Error)]
#[error("{0}")]
pub struct MeshError(String);
/// Loads a mesh file.
pub fn load_mesh(path: &Path) -> Result<TriMesh, MeshError> {
    Err(MeshError(format!(
        "{}: mesh loading not available",
        path.display()
    )))
}
