//! Errors building a robot.

use crate::mesh::load::MeshError;
use std::path::PathBuf;

/// Errors building a [`Robot`](super::Robot). Every message names the URDF source.
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
