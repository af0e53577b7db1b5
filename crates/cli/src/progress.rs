//! Terminal progress of the commands: indicatif bars, and the bar-and-stderr
//! reporter that the libraries take as their [`Progress`] (benches, video
//! scores, a run's evaluation, the denoising steps of `predict`).

use bridgev2w_io::progress::Progress;
use indicatif::{ProgressBar, ProgressStyle};
use std::sync::Mutex;

/// A bar of `len` steps labelled `what`, with rate and time left.
pub fn progress_bar(len: usize, what: &str) -> ProgressBar {
    let pb = ProgressBar::new(len as u64);
    pb.set_style(
        ProgressStyle::with_template("{msg} [{bar:30}] {pos}/{len} {per_sec} eta {eta}")
            .unwrap_or_else(|_| ProgressStyle::default_bar())
            .progress_chars("=> "),
    );
    pb.set_message(what.to_string());
    pb
}

/// A spinner labelled `what`, for a stage whose length is not known.
pub fn spinner(what: &str) -> ProgressBar {
    let pb = ProgressBar::new_spinner().with_message(what.to_string());
    pb.enable_steady_tick(std::time::Duration::from_millis(200));
    pb
}

/// Shows a library's stages as [`progress_bar`]s (a [`spinner`] when the
/// stage's total is 0, unknown), cleared when done, and its notes as lines
/// on stderr.
#[derive(Debug, Default)]
pub struct TerminalProgress {
    bar: Mutex<Option<ProgressBar>>,
}

impl TerminalProgress {
    fn with_bar(&self, f: impl FnOnce(&mut Option<ProgressBar>)) {
        // A poisoned lock only means a panicking thread held it: the bar is still usable.
        let mut bar = self.bar.lock().unwrap_or_else(|e| e.into_inner());
        f(&mut bar);
    }
}

impl Progress for TerminalProgress {
    fn start(&self, total: usize, label: &str) {
        self.with_bar(|bar| {
            let new = if total == 0 {
                spinner(label)
            } else {
                progress_bar(total, label)
            };
            if let Some(old) = bar.replace(new) {
                old.finish_and_clear();
            }
        });
    }

    fn tick(&self) {
        self.with_bar(|bar| {
            if let Some(b) = bar {
                b.inc(1);
            }
        });
    }

    fn finish(&self) {
        self.with_bar(|bar| {
            if let Some(b) = bar.take() {
                b.finish_and_clear();
            }
        });
    }

    fn note(&self, text: &str) {
        // Above a bar that is drawn, not through it.
        self.with_bar(|bar| match bar {
            Some(b) => b.suspend(|| eprintln!("{text}")),
            None => eprintln!("{text}"),
        });
    }
}
