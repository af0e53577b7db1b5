//! What a reader or the conversion did to an episode beyond copying it: each
//! clamp, alignment, rescale, fallback or missing field is one [`Note`],
//! tied to its episode (and camera) by [`EpisodeNote`], and written into
//! the conversion report (`conversion_report.json`). Nothing is changed
//! without one.

use serde::Serialize;
use std::path::PathBuf;

/// How a view's video frames were matched to the episode's states.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum AlignMethod {
    /// By the recorded per-frame camera timestamps (DROID:
    /// `recordings/MP4/<serial>_timestamps.json` against trajectory.h5's
    /// `observation/timestamp/cameras/<serial>_frame_received`).
    Timestamps,
    /// Frame `i` with state `i`, the longer one cut to the shorter.
    Truncated,
}

/// Which stereo eye (of a ZED camera) a pose or image belongs to.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Eye {
    /// The left image (DROID's `recordings/MP4/<serial>.mp4`).
    Left,
    /// The right image.
    Right,
}

impl std::fmt::Display for Eye {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Eye::Left => "left",
            Eye::Right => "right",
        })
    }
}

/// One thing done to an episode that is not a plain copy.
#[derive(Debug, Clone, PartialEq, Serialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum Note {
    /// Gripper readings outside the stated range were clamped into it.
    GripperClamped {
        /// Arm index (0 left, 1 right; 0 for one arm).
        arm: usize,
        /// The dataset field read.
        field: String,
        /// Readings clamped.
        count: usize,
        /// The reading farthest outside the range.
        worst: f64,
        /// The reading taken as fully open (closure 0).
        open: f64,
        /// The reading taken as fully closed (closure 1).
        closed: f64,
    },
    /// A recorded joint group is absent: its joints stay at the robot's home.
    JointsMissing {
        /// The dataset field that is absent.
        field: String,
        /// The joints it would have driven.
        joints: Vec<String>,
    },
    /// Recorded joint columns not driven on the robot (named `-` in the
    /// joint-name list).
    JointColumnsIgnored {
        /// The dataset's names of the ignored columns.
        columns: Vec<String>,
    },
    /// Recorded values of a joint outside the robot model's limits (kept as
    /// recorded, not clamped).
    JointOutOfLimits {
        /// The robot's joint name.
        joint: String,
        /// Frames whose value is outside `[lower, upper]`.
        count: usize,
        /// The value farthest outside.
        worst: f64,
        /// Lower limit.
        lower: f64,
        /// Upper limit.
        upper: f64,
    },
    /// A view's video and the states differ in length by a frame or two and
    /// were aligned.
    FramesAligned {
        /// The video file.
        video: PathBuf,
        /// Frames in the video.
        video_frames: usize,
        /// States in the episode.
        states: usize,
        /// Frames written (video frame and state pairs).
        frames_used: usize,
        /// How they were matched.
        method: AlignMethod,
        /// State indices left without a video frame (not written).
        dropped_states: Vec<usize>,
        /// Video frame indices left without a state (not written).
        dropped_video_frames: Vec<usize>,
    },
    /// Frames at the start of a view's video that its edit list (`elst`)
    /// hides were not converted (as a player, and the LeRobot reader, skip
    /// them); the rest were aligned with the states.
    EditListSkipped {
        /// The video file.
        video: PathBuf,
        /// Frames in the file.
        video_frames: usize,
        /// Leading frames the edit list hides.
        hidden: usize,
    },
    /// Intrinsics given for one image size were scaled to the video's size.
    IntrinsicsScaled {
        /// The size the intrinsics were given for.
        from: [u32; 2],
        /// The video's size.
        to: [u32; 2],
        /// Horizontal and vertical factors.
        scale: [f64; 2],
        /// Whether both factors agree (within 1%); if not, the video was
        /// resized non-uniformly (or the intrinsics are for another camera).
        uniform: bool,
    },
    /// Where a camera's calibration came from.
    Calibration {
        /// Intrinsics: file and key.
        intrinsics: String,
        /// Extrinsics: file and key, or the recorded per-frame extrinsics.
        extrinsics: String,
        /// The eye the published pose was given for.
        eye: Eye,
        /// Whether a right-eye pose was moved to the left eye (with the
        /// recorded stereo offset of the same camera).
        right_to_left: bool,
    },
    /// No published extrinsics for this camera: the recorded ones are used.
    CalibrationMissing {
        /// The calibration files searched.
        files: Vec<PathBuf>,
        /// Why none applied.
        reason: String,
    },
    /// A calibration key of this episode's entry matches none of its cameras.
    CalibrationKeyUnmatched {
        /// The file.
        file: PathBuf,
        /// The key.
        key: String,
    },
}

impl Note {
    /// A short name for summaries (the JSON `kind`).
    pub fn kind(&self) -> &'static str {
        match self {
            Note::GripperClamped { .. } => "gripper_clamped",
            Note::JointsMissing { .. } => "joints_missing",
            Note::JointColumnsIgnored { .. } => "joint_columns_ignored",
            Note::JointOutOfLimits { .. } => "joint_out_of_limits",
            Note::FramesAligned { .. } => "frames_aligned",
            Note::EditListSkipped { .. } => "edit_list_skipped",
            Note::IntrinsicsScaled { .. } => "intrinsics_scaled",
            Note::Calibration { .. } => "calibration",
            Note::CalibrationMissing { .. } => "calibration_missing",
            Note::CalibrationKeyUnmatched { .. } => "calibration_key_unmatched",
        }
    }

    /// Whether the note is a warning (something possibly wrong), not only a
    /// record of what was done.
    pub fn is_warning(&self) -> bool {
        match self {
            Note::Calibration { .. }
            | Note::JointColumnsIgnored { .. }
            | Note::EditListSkipped { .. } => false,
            Note::IntrinsicsScaled { uniform, .. } => !uniform,
            _ => true,
        }
    }
}

/// A [`Note`] about one episode (and camera).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EpisodeNote {
    /// Episode id.
    pub episode: String,
    /// Camera name, when the note is about one view.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub camera: Option<String>,
    /// What was done.
    #[serde(flatten)]
    pub note: Note,
}
