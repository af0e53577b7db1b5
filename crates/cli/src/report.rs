//! `bridgev2w eval-report`: the video-prediction table in the paper's layout
//! from `eval-run --json` files ([`bridgev2w_train::report`]), written to the
//! `video` section of the results file.

use anyhow::Result;
use bridgev2w_io::sections::write_section;
use bridgev2w_train::report::{video_report, VideoReportOptions};
use std::path::PathBuf;

/// Arguments of `eval-report`.
#[derive(Debug, clap::Args)]
pub struct EvalReportArgs {
    /// `NAME=FILE`: a method's `eval-run --json` scores (repeat; rows in this order).
    /// The copy-the-first-frame baseline row comes from the first file.
    #[arg(long = "entry", required = true)]
    entries: Vec<String>,
    /// Markdown prepended to the tables (setup, timings), e.g. written by the
    /// reproduction script.
    #[arg(long)]
    preamble: Option<PathBuf>,
    /// The results file; only its `video` section is replaced.
    #[arg(long, default_value = "docs/results.md")]
    out: PathBuf,
}

impl From<&EvalReportArgs> for VideoReportOptions {
    fn from(a: &EvalReportArgs) -> Self {
        Self {
            entries: a.entries.clone(),
            preamble: a.preamble.clone(),
        }
    }
}

/// `bridgev2w eval-report`.
pub fn run_eval_report(a: &EvalReportArgs) -> Result<()> {
    let md = video_report(&a.into())?;
    write_section(&a.out, "video", &md)?;
    crate::print_stdout(&md)
}
