//! Small file utilities every bridgev2w crate shares, each with one home:
//!
//! * [`atomic`]: files written through a synced temporary file and a rename,
//!   so a reader (or a killed run) sees the old file or the new one, never a
//!   part;
//! * [`json`]: JSON files read and written with errors that name the file;
//! * [`sections`]: a markdown results file that several commands share, each
//!   owning one marked section;
//! * [`peer`]: the Python peers of the benches (repository root, venvs,
//!   scripts that print a JSON result) and the benches' progress reports.

pub mod atomic;
pub mod json;
pub mod peer;
pub mod sections;

use std::path::{Path, PathBuf};

/// A file that could not be read, written or parsed: always names the file.
#[derive(Debug, thiserror::Error)]
pub enum FileError {
    /// The operating system refused.
    #[error("{}: {source}", path.display())]
    Io {
        /// The file or folder.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// Not valid JSON, or not the JSON expected.
    #[error("{}: {source}", path.display())]
    Json {
        /// The file.
        path: PathBuf,
        /// Where and why.
        source: serde_json::Error,
    },
    /// The content is not what was expected.
    #[error("{}: {message}", path.display())]
    Format {
        /// The file.
        path: PathBuf,
        /// What was found and what was expected.
        message: String,
    },
}

impl FileError {
    /// An I/O error on `path`.
    pub fn io(path: &Path, source: std::io::Error) -> Self {
        Self::Io {
            path: path.to_path_buf(),
            source,
        }
    }

    /// `path`'s content is not what was expected.
    pub fn format(path: &Path, message: impl Into<String>) -> Self {
        Self::Format {
            path: path.to_path_buf(),
            message: message.into(),
        }
    }
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, FileError>;
