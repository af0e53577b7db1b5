//! How a library reports progress while it runs, without terminal code: one
//! trait, [`Progress`], that the benches, the video scores, a run's
//! evaluation and the sampling loop call, and that the command-line tool
//! implements once (a progress bar, or a spinner when the count is unknown,
//! and notes on stderr).

/// What a long computation reports while it runs: stages of counted steps
/// (a progress bar in the command-line tool) and notes (one line on stderr
/// there). Stages come one after the other: each is started, ticked and
/// finished. Every method does nothing unless overridden.
pub trait Progress: Sync {
    /// A stage of `total` steps called `label` begins (`total` 0: a count
    /// not known in advance).
    fn start(&self, total: usize, label: &str) {
        let _ = (total, label);
    }
    /// One step of the current stage is done (called from any thread).
    fn tick(&self) {}
    /// The current stage is over.
    fn finish(&self) {}
    /// A note for the user, e.g. that a slow peer runs now.
    fn note(&self, text: &str) {
        let _ = text;
    }
}

/// A [`Progress`] that reports nothing.
#[derive(Debug, Clone, Copy, Default)]
pub struct Silent;

impl Progress for Silent {}
