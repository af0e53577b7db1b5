//! Metrics of the BridgeV2W paper.
//!
//! * Video quality ([`video`]): PSNR and SSIM per frame on `[0, 1]` RGB data,
//!   averaged over frames and then over videos, and Mask-IoU between robot
//!   masks of generated and ground-truth frames.
//! * Distribution distance ([`frechet`]): the Frechet distance between two
//!   Gaussians fitted to features (the statistic behind FVD).
//! * Policy evaluation ([`ranking`]): MMRV and Pearson r between real and
//!   world-model success rates, as SIMPLER computes them; [`policy_rates`]
//!   reads success-rate files and compares them per task.

pub mod bench;
pub mod clip;
pub mod dynamic;
pub mod frechet;
pub mod policy_rates;
pub mod ranking;
pub mod segment;
pub mod video;

/// Errors of the metric functions: inputs that do not fit together.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum MetricError {
    /// Two inputs that must have the same shape do not.
    #[error("{what}: shapes differ ({left} vs {right})")]
    ShapeMismatch {
        /// What was compared.
        what: String,
        /// Shape of the first input.
        left: String,
        /// Shape of the second input.
        right: String,
    },
    /// An input is empty, too small or otherwise unusable.
    #[error("{0}")]
    Invalid(String),
}

impl From<bridgev2w_io::frame::FrameError> for MetricError {
    /// A frame that does not fit its size or holds a non-finite value.
    fn from(e: bridgev2w_io::frame::FrameError) -> Self {
        Self::Invalid(e.0)
    }
}

/// Result of the metric functions.
pub type Result<T> = std::result::Result<T, MetricError>;
