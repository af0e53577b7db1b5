//! Errors of the world-model crate: every variant names the file, key or value at fault.

use std::path::PathBuf;

/// Errors from loading configs and weights, running models and parity fixtures.
#[derive(Debug, thiserror::Error)]
pub enum WorldModelError {
    /// A file could not be read or written.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        error: std::io::Error,
    },
    /// A JSON file is malformed or does not match the expected schema.
    #[error("{path}: invalid JSON: {error}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        error: serde_json::Error,
    },
    /// A config value is out of range or inconsistent with another.
    #[error("{path}: config field `{field}`: {message}")]
    Config {
        /// The config file (or a preset's name).
        path: PathBuf,
        /// The field at fault.
        field: String,
        /// What was expected.
        message: String,
    },
    /// A parameter of the model has no tensor in the weight files.
    #[error("missing weight `{key}` (expected shape {expected:?}) in {files}")]
    MissingWeight {
        /// The parameter's key (diffusers naming).
        key: String,
        /// The model's shape for it.
        expected: Vec<i64>,
        /// The weight files searched.
        files: String,
    },
    /// A tensor in the weight files matches no parameter of the model.
    #[error(
        "{path}: unexpected weight `{key}` (the model has no such parameter; is the config right?)"
    )]
    UnexpectedWeight {
        /// The weight file.
        path: PathBuf,
        /// The tensor's key.
        key: String,
    },
    /// A tensor in the weight files has another shape than the model's parameter.
    #[error("{path}: weight `{key}` has shape {found:?}, the model expects {expected:?} (is the config right?)")]
    ShapeMismatch {
        /// The weight file.
        path: PathBuf,
        /// The tensor's key.
        key: String,
        /// The model's shape.
        expected: Vec<i64>,
        /// The file's shape.
        found: Vec<i64>,
    },
    /// A tensor in the weight files holds NaN or infinite values.
    #[error("{path}: weight `{key}` holds {count} NaN or infinite value(s) (a diverged run or a corrupt file)")]
    NonFiniteWeight {
        /// The weight file.
        path: PathBuf,
        /// The tensor's key.
        key: String,
        /// How many values are not finite.
        count: i64,
    },
    /// An input has the wrong shape, range or type.
    #[error("invalid input `{name}`: {message}")]
    Input {
        /// The input's name.
        name: String,
        /// What was expected.
        message: String,
    },
    /// An error from libtorch.
    #[error("libtorch: {0}")]
    Torch(#[from] tch::TchError),
}

/// Result alias of this crate.
pub type Result<T, E = WorldModelError> = std::result::Result<T, E>;

impl WorldModelError {
    pub(crate) fn io(path: impl Into<PathBuf>, error: std::io::Error) -> Self {
        Self::Io {
            path: path.into(),
            error,
        }
    }

    pub(crate) fn config(
        path: impl Into<PathBuf>,
        field: impl Into<String>,
        message: impl Into<String>,
    ) -> Self {
        Self::Config {
            path: path.into(),
            field: field.into(),
            message: message.into(),
        }
    }

    pub(crate) fn input(name: impl Into<String>, message: impl Into<String>) -> Self {
        Self::Input {
            name: name.into(),
            message: message.into(),
        }
    }
}

/// Reads and parses a JSON file with errors naming the file.
pub(crate) fn read_json<T: serde::de::DeserializeOwned>(path: &std::path::Path) -> Result<T> {
    let text = std::fs::read_to_string(path).map_err(|e| WorldModelError::io(path, e))?;
    serde_json::from_str(&text).map_err(|error| WorldModelError::Json {
        path: path.to_path_buf(),
        error,
    })
}

/// Writes a file atomically (a temporary file in the same folder, then rename).
pub(crate) fn write_atomic(path: &std::path::Path, bytes: &[u8]) -> Result<()> {
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(std::path::Path::new("."));
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "file".to_owned());
    let tmp = dir.join(format!(".{name}.tmp-{}", std::process::id()));
    std::fs::write(&tmp, bytes).map_err(|e| WorldModelError::io(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        WorldModelError::io(path, e)
    })
}
