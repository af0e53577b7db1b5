//! Speed of this crate measured in the same run as a peer, for `bridgev2w
//! bench masks` and `bridgev2w bench kinematics`: each bench takes its
//! options, runs, and returns a report whose `Display` is the printed table.
//!
//! * [`masks`]: this rasterizer vs pybullet's `getCameraImage` (TinyRenderer)
//!   on the same URDF, joints and camera, with the masks' agreement;
//! * [`kinematics`]: forward-kinematics poses/s and warm-started IK time.

pub mod kinematics;
pub mod masks;

pub use kinematics::{bench_kinematics, KinematicsBenchOptions, KinematicsBenchReport};
pub use masks::{bench_masks, MaskAgreement, MasksBenchOptions, MasksBenchReport, PybulletMasks};

use crate::camera::CameraError;
use crate::embodiment::EmbodimentError;
use crate::robot::RobotError;
use bridgev2w_io::npy::NpyError;
use bridgev2w_io::peer::PeerError;
use bridgev2w_io::FileError;

/// Why a bench could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The options do not fit together: says which and what is expected.
    #[error("{0}")]
    Invalid(String),
    /// The peer (pybullet) could not be found, run or understood.
    #[error(transparent)]
    Peer(#[from] PeerError),
    /// A file handed to the peer could not be written.
    #[error(transparent)]
    File(#[from] FileError),
    /// The URDF did not load.
    #[error(transparent)]
    Robot(#[from] RobotError),
    /// The built-in robot did not load.
    #[error(transparent)]
    Embodiment(#[from] EmbodimentError),
    /// The bench camera is invalid.
    #[error(transparent)]
    Camera(#[from] CameraError),
    /// An array exchanged with the peer could not be written or read.
    #[error(transparent)]
    Npy(#[from] NpyError),
    /// A size beyond its maximum or this machine's memory.
    #[error(transparent)]
    Memory(#[from] bridgev2w_io::memory::MemoryError),
}

/// Result of the benches.
pub type Result<T> = std::result::Result<T, BenchError>;
