//! Errors of [`crate::score`]: each names the folder, video, frame or file
//! and what was expected.

use std::path::PathBuf;

/// Errors of scoring video folders.
#[derive(Debug, thiserror::Error)]
pub enum ScoreError {
    /// A metric name that is not one of [`super::VideoMetric::ALL`].
    #[error("unknown metric \"{name}\" (expected some of {})", super::VideoMetric::names().join(", "))]
    UnknownMetric {
        /// The name given (trimmed, lower case).
        name: String,
    },
    /// Inputs that do not fit together or are not laid out as expected:
    /// the message names the video, frame or file and what was expected.
    #[error("{0}")]
    Invalid(String),
    /// A folder or file that could not be read.
    #[error("{context}")]
    Io {
        /// What was being read (names the path).
        context: String,
        /// Why.
        source: std::io::Error,
    },
    /// An image that could not be decoded.
    #[error("{what} {}: not a readable image", path.display())]
    Image {
        /// "frame" or "mask".
        what: &'static str,
        /// The file.
        path: PathBuf,
        /// Why.
        source: image::ImageError,
    },
    /// An MP4 that could not be decoded.
    #[error(transparent)]
    Mp4(#[from] bridgev2w_data::video::VideoError),
    /// A metric failed on a named video or frame.
    #[error("{context}")]
    MetricAt {
        /// The video or frame.
        context: String,
        /// Why.
        source: bridgev2w_eval::MetricError,
    },
    /// From the metric functions.
    #[error(transparent)]
    Metric(#[from] bridgev2w_eval::MetricError),
    /// The LPIPS or I3D network failed (loading its weights, or on a video).
    #[error("{context}")]
    Network {
        /// The weights file or the video.
        context: String,
        /// Why.
        source: bridgev2w_world_model::error::WorldModelError,
    },
}

/// Result of [`crate::score`].
pub type Result<T> = std::result::Result<T, ScoreError>;

/// `Err(ScoreError::Invalid(format!(...)))`.
macro_rules! invalid {
    ($($arg:tt)*) => {
        Err($crate::score::ScoreError::Invalid(format!($($arg)*)))
    };
}
pub(crate) use invalid;
