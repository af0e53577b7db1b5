//! Matching a view's video frames to the episode's states when their counts
//! differ by a frame or two (DROID's MP4s often hold one frame fewer or more
//! than `trajectory.h5`, droid-dataset/droid issue 54): by the recorded
//! camera timestamps where the raw data has them, otherwise by cutting the
//! longer to the shorter; each alignment becomes a [`Note::FramesAligned`].
//! Larger differences are refused, naming both counts.

use super::report::{AlignMethod, Note};
use super::{RawEpisode, RawError, RawView};

/// The largest difference between a video's frame count and the states that
/// is aligned; larger ones are refused.
pub const MAX_FRAME_DIFFERENCE: usize = 2;

/// Timestamps (milliseconds) matching a view's video frames to states: DROID
/// writes one per video frame (`recordings/MP4/<serial>_timestamps.json`,
/// read by its `MP4Reader`) and one per state
/// (`observation/timestamp/cameras/<serial>_frame_received`): a state's
/// frame is the video frame with the same timestamp.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameTimes {
    /// Per video frame.
    pub video_ms: Vec<f64>,
    /// Per state.
    pub state_ms: Vec<f64>,
}

/// Matched pairs `(video frame, state)`, increasing in both.
#[derive(Debug, Clone, PartialEq)]
pub struct Alignment {
    /// The frames to write: video frame index and state index.
    pub pairs: Vec<(usize, usize)>,
    /// What was done, when the counts differed.
    pub note: Option<Note>,
}

/// Timestamps of one frame and one state match within this (milliseconds).
const MATCH_TOLERANCE_MS: f64 = 1.0;

/// Aligns a video of `video_frames` frames with `episode`'s states (see the
/// module documentation).
pub fn align_frames(
    episode: &RawEpisode,
    view: &RawView,
    video_frames: usize,
) -> Result<Alignment, RawError> {
    let states = episode.frames;
    if video_frames == states {
        return Ok(Alignment {
            pairs: (0..states).map(|i| (i, i)).collect(),
            note: None,
        });
    }
    let inconsistent = |message: String| RawError::Inconsistent {
        episode: episode.id.clone(),
        message,
    };
    let diff = video_frames.abs_diff(states);
    if diff > MAX_FRAME_DIFFERENCE {
        return Err(inconsistent(format!(
            "camera \"{}\": video {} has {video_frames} frames but the states have {states} \
             (they differ by {diff}; at most {MAX_FRAME_DIFFERENCE} are aligned)",
            view.name,
            view.video.display()
        )));
    }
    let by_time = view
        .frame_times
        .as_ref()
        .filter(|t| t.video_ms.len() == video_frames && t.state_ms.len() == states)
        .map(|t| match_times(&t.video_ms, &t.state_ms))
        .filter(|p| p.len() >= video_frames.min(states));
    let (pairs, method) = match by_time {
        Some(p) => (p, AlignMethod::Timestamps),
        None => {
            let n = video_frames.min(states);
            ((0..n).map(|i| (i, i)).collect(), AlignMethod::Truncated)
        }
    };
    if pairs.is_empty() {
        return Err(inconsistent(format!(
            "camera \"{}\": video {} has {video_frames} frames, the states {states}: nothing to align",
            view.name,
            view.video.display()
        )));
    }
    let dropped = |n: usize, used: &dyn Fn(usize) -> bool| (0..n).filter(|&i| !used(i)).collect();
    let note = Note::FramesAligned {
        video: view.video.clone(),
        video_frames,
        states,
        frames_used: pairs.len(),
        method,
        dropped_states: dropped(states, &|i| pairs.iter().any(|p| p.1 == i)),
        dropped_video_frames: dropped(video_frames, &|i| pairs.iter().any(|p| p.0 == i)),
    };
    Ok(Alignment {
        pairs,
        note: Some(note),
    })
}

/// Pairs each state with the video frame of the same timestamp (within
/// [`MATCH_TOLERANCE_MS`]), both in increasing order.
fn match_times(video_ms: &[f64], state_ms: &[f64]) -> Vec<(usize, usize)> {
    let mut pairs = Vec::new();
    let mut v = 0;
    for (s, &ts) in state_ms.iter().enumerate() {
        while v < video_ms.len() && video_ms[v] < ts - MATCH_TOLERANCE_MS {
            v += 1;
        }
        if v < video_ms.len() && (video_ms[v] - ts).abs() <= MATCH_TOLERANCE_MS {
            pairs.push((v, s));
            v += 1;
        }
    }
    pairs
}
