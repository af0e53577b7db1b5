//! Errors of planning and policy evaluation.

use bridgev2w_world_model::WorldModelError;

/// Errors of this crate.
#[derive(Debug, thiserror::Error)]
pub enum PlanError {
    /// The goal image does not have the model's resolution.
    #[error("goal image is {got_h}x{got_w} (HxW) but the world model works at {want_h}x{want_w}")]
    GoalImageSize {
        /// Goal height.
        got_h: usize,
        /// Goal width.
        got_w: usize,
        /// Model height.
        want_h: usize,
        /// Model width.
        want_w: usize,
    },
    /// The planning horizon is zero.
    #[error("horizon must be at least 1 action")]
    ZeroHorizon,
    /// More elites than samples.
    #[error("elites k = {elites} must be between 1 and the samples S = {samples}")]
    Elites {
        /// k.
        elites: usize,
        /// S.
        samples: usize,
    },
    /// An action (proposed, planned or from a policy) is not finite.
    #[error(
        "{source_name}: action {index}, value {value} at column {column} is not a finite number"
    )]
    NonFinite {
        /// Where it came from.
        source_name: String,
        /// Action index.
        index: usize,
        /// Column within `[x, y, z, roll, pitch, yaw, gripper]`.
        column: usize,
        /// The value.
        value: f64,
    },
    /// The action sequence does not fit the model's clip.
    #[error("{actions} actions x {frames_per_action} frames each do not fit the model's clip of {clip_frames} frames (frame 0 is the current frame)")]
    ClipTooShort {
        /// Actions.
        actions: usize,
        /// Frames per action.
        frames_per_action: usize,
        /// Model clip frames.
        clip_frames: usize,
    },
    /// Any other bad setting.
    #[error("invalid setting: {0}")]
    Invalid(String),
    /// The world model failed.
    #[error(transparent)]
    Model(#[from] WorldModelError),
    /// A results file could not be written.
    #[error(transparent)]
    File(#[from] bridgev2w_io::FileError),
    /// A figure of the report that could not be drawn or written.
    #[error(transparent)]
    Plot(#[from] bridgev2w_io::plot::PlotError),
    /// The synthetic world failed.
    #[error(transparent)]
    Synth(#[from] bridgev2w_data::synth::SynthError),
    /// IK failed on actions.
    #[error(transparent)]
    Actions(#[from] bridgev2w_embodiment::actions::ActionError),
    /// A metric could not be computed.
    #[error(transparent)]
    Metric(#[from] bridgev2w_eval::MetricError),
    /// Reading a label file failed.
    #[error("{path}: {message}")]
    Labels {
        /// File.
        path: String,
        /// What went wrong.
        message: String,
    },
    /// A size beyond its stated maximum, or candidates beyond the machine's
    /// memory (refused before the first trial).
    #[error(transparent)]
    Memory(#[from] bridgev2w_io::memory::MemoryError),
    /// A policy from outside failed (unreachable, closed, slow, a bad chunk).
    #[error("policy {policy}{}: {message}", step.map(|s| format!(", step {s}")).unwrap_or_default())]
    Policy {
        /// The policy's name.
        policy: String,
        /// The query that failed (0-based, per trial), if any.
        step: Option<usize>,
        /// What failed, naming the field.
        message: String,
    },
    /// A setting or argument with a value it cannot take.
    #[error("{name}: {message}")]
    Input {
        /// The setting.
        name: String,
        /// The value and what was expected.
        message: String,
    },
}

impl PlanError {
    /// A bad setting `name`.
    pub fn input(name: impl Into<String>, message: impl Into<String>) -> Self {
        Self::Input {
            name: name.into(),
            message: message.into(),
        }
    }
}

/// Result of this crate.
pub type Result<T> = std::result::Result<T, PlanError>;

/// Checks that every value of `actions` is finite.
pub fn check_finite(source_name: &str, actions: &[crate::EeAction]) -> Result<()> {
    for (index, a) in actions.iter().enumerate() {
        if let Some((column, &value)) = a.iter().enumerate().find(|(_, v)| !v.is_finite()) {
            return Err(PlanError::NonFinite {
                source_name: source_name.to_string(),
                index,
                column,
                value,
            });
        }
    }
    Ok(())
}
