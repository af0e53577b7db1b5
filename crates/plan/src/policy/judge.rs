//! Judges of a rollout's success: on the model's predicted frames (the
//! latent distance to the goal image, [`GoalDistanceJudge`]) or from labels
//! a person gave ([`LabelJudge`]).

use crate::error::{PlanError, Result};
use crate::model::latent_l1;
use bridgev2w_io::frame::RgbFrame;
use std::collections::HashMap;

/// What a judge sees of one rollout.
#[derive(Debug, Clone)]
pub struct JudgeInput<'a> {
    /// Policy name.
    pub policy: &'a str,
    /// Trial index.
    pub trial: usize,
    /// The start image.
    pub start: &'a RgbFrame,
    /// The rollout's final image.
    pub last: &'a RgbFrame,
    /// The task's goal image.
    pub goal: &'a RgbFrame,
}

/// A judge's verdict on one rollout.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Verdict {
    /// Success.
    pub success: bool,
    /// A graded score in `[-1, 1]` when the judge has one (see
    /// [`goal_progress`]): it still ranks rollouts when none succeeds.
    pub progress: Option<f64>,
}

/// Decides whether a rollout succeeded.
pub trait SuccessJudge {
    /// The verdict on one rollout.
    fn judge(&self, input: &JudgeInput<'_>) -> Result<Verdict>;
}

/// How much nearer the goal a rollout ended than it started, from the
/// distances `d_start = d(start, goal)` and `d_last = d(last, goal)`:
/// `(d_start - d_last) / max(d_start, d_last)`, in `[-1, 1]`. 1: the goal
/// reached exactly; 0: no nearer (or both distances 0); negative: farther
/// away, -1 only in the limit. Bounded, so one diverging rollout cannot
/// dominate a policy's mean. For `d_start > 0` and `ratio` in `(0, 1]`,
/// `d_last <= ratio * d_start` holds exactly when the progress is at least
/// `1 - ratio`.
pub fn goal_progress(d_start: f64, d_last: f64) -> f64 {
    let scale = d_start.max(d_last);
    if scale > 0.0 {
        (d_start - d_last) / scale
    } else {
        0.0
    }
}

/// Success when the final frame is much nearer the goal than the start was:
/// `d(last, goal) <= ratio * d(start, goal)` with `d` the latent mean L1;
/// the verdict's progress is [`goal_progress`] of the two distances.
pub struct GoalDistanceJudge<'m> {
    /// The latent encoder.
    pub encode: &'m dyn Fn(&RgbFrame) -> Result<Vec<f32>>,
    /// The ratio.
    pub ratio: f64,
}

impl std::fmt::Debug for GoalDistanceJudge<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("GoalDistanceJudge")
            .field("ratio", &self.ratio)
            .finish_non_exhaustive()
    }
}

impl SuccessJudge for GoalDistanceJudge<'_> {
    fn judge(&self, i: &JudgeInput<'_>) -> Result<Verdict> {
        let g = (self.encode)(i.goal)?;
        let d_last = latent_l1(&(self.encode)(i.last)?, &g)?;
        let d_start = latent_l1(&(self.encode)(i.start)?, &g)?;
        Ok(Verdict {
            success: d_last <= self.ratio * d_start,
            progress: Some(goal_progress(d_start, d_last)),
        })
    }
}

/// Success labels from a file (human raters): CSV lines
/// `policy,trial,success` with success `1`/`0` (or `true`/`false`); `#`
/// starts a comment.
#[derive(Debug, Clone, Default)]
pub struct LabelJudge {
    labels: HashMap<(String, usize), bool>,
}

impl LabelJudge {
    /// Parses label text (`path` names it in errors).
    pub fn parse(text: &str, path: &str) -> Result<Self> {
        let err = |line: usize, m: &str| PlanError::Labels {
            path: path.to_string(),
            message: format!("line {line}: {m}"),
        };
        let mut labels = HashMap::new();
        for (n, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() || line.starts_with('#') || line.starts_with("policy,") {
                continue;
            }
            let f: Vec<&str> = line.split(',').map(str::trim).collect();
            let [policy, trial, success] = f[..] else {
                return Err(err(n + 1, "expected policy,trial,success"));
            };
            let trial: usize = trial.parse().map_err(|_| {
                err(
                    n + 1,
                    &format!("trial {trial:?} is not a non-negative integer"),
                )
            })?;
            let success = match success {
                "1" | "true" => true,
                "0" | "false" => false,
                s => {
                    return Err(err(
                        n + 1,
                        &format!("success {s:?}: expected 1/0/true/false"),
                    ))
                }
            };
            labels.insert((policy.to_string(), trial), success);
        }
        Ok(Self { labels })
    }

    /// Reads a label file.
    pub fn read(path: &std::path::Path) -> Result<Self> {
        let text = std::fs::read_to_string(path).map_err(|e| PlanError::Labels {
            path: path.display().to_string(),
            message: e.to_string(),
        })?;
        Self::parse(&text, &path.display().to_string())
    }
}

impl SuccessJudge for LabelJudge {
    fn judge(&self, i: &JudgeInput<'_>) -> Result<Verdict> {
        let success = self
            .labels
            .get(&(i.policy.to_string(), i.trial))
            .copied()
            .ok_or_else(|| PlanError::Labels {
                path: "labels".into(),
                message: format!("no label for policy {} trial {}", i.policy, i.trial),
            })?;
        Ok(Verdict {
            success,
            progress: None,
        })
    }
}
