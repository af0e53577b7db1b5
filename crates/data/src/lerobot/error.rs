//! The dataset error type and its constructors.

use crate::video::VideoError;
use arrow_schema::ArrowError;
use std::path::{Path, PathBuf};

/// Dataset errors; each names the file and, where known, the episode and field.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// I/O failure.
    #[error("{path}: {source}")]
    Io {
        /// File.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// Bad JSON / JSONL / metadata.
    #[error("{path}: {message}")]
    Meta {
        /// File.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The parquet file is corrupt or unreadable.
    #[error("{path}: corrupt or unreadable parquet: {message}")]
    Parquet {
        /// File.
        path: PathBuf,
        /// Cause.
        message: String,
    },
    /// A column is missing or has the wrong type or values.
    #[error("{path}: episode {episode}, field \"{field}\": {message}")]
    Field {
        /// File.
        path: PathBuf,
        /// Episode index (or -1 when not tied to one episode).
        episode: i64,
        /// Column / field name.
        field: String,
        /// What is wrong.
        message: String,
    },
    /// A synthetic episode has no camera calibration.
    #[error("{path}: missing camera calibration of episode {episode}")]
    MissingCalibration {
        /// Expected file.
        path: PathBuf,
        /// Episode index.
        episode: i64,
    },
    /// A video could not be read.
    #[error("episode {episode}, video \"{key}\": {source}")]
    Video {
        /// Episode index.
        episode: i64,
        /// Video key.
        key: String,
        /// Cause (names the file).
        source: VideoError,
    },
    /// The layout version is not supported.
    #[error("{path}: unsupported LeRobot codebase_version \"{version}\" (supported: v2.1, v3.0)")]
    Version {
        /// `meta/info.json`.
        path: PathBuf,
        /// The version found.
        version: String,
    },
}

pub(super) fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

pub(super) fn pq_err(path: &Path) -> impl Fn(parquet::errors::ParquetError) -> DatasetError + '_ {
    move |e| DatasetError::Parquet {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

pub(super) fn arrow_err(path: &Path) -> impl Fn(ArrowError) -> DatasetError + '_ {
    move |e| DatasetError::Parquet {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

pub(super) fn meta_err(path: &Path, message: impl Into<String>) -> DatasetError {
    DatasetError::Meta {
        path: path.to_path_buf(),
        message: message.into(),
    }
}
