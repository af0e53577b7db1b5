//! `bridgev2w eval-report`: the video-prediction table in the paper's layout
//! from `eval-run --json` files ([`bridgev2w_train::report`]), written to the
//! `video` section of the results file, with its figures (PNG, in the
//! folder named after the results file: `docs/results/figures/` for
//! `docs/results.md`) and links to `eval-grid`'s side-by-side GIFs.

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
    /// `NAME=DIR`: a training run (a stage of the proof run) whose
    /// metrics.jsonl is drawn in the loss-curves figure (repeat; panels in
    /// this order).
    #[arg(long = "training-run", value_name = "NAME=DIR")]
    training_runs: Vec<String>,
    /// `eval-grid`'s folder of side-by-side GIFs (DIR/<split>.gif for every
    /// split of the entries, drawn with the entries' runs in their order):
    /// linked from the section.
    #[arg(long, value_name = "DIR")]
    grids: Option<PathBuf>,
    /// The results file; only its `video` section is replaced. The figures
    /// go to the folder named after it: OUT_WITHOUT_.md/figures/.
    #[arg(long, default_value = "docs/results.md")]
    out: PathBuf,
    /// The section of --out replaced (`video`: the synthetic study's);
    /// another section's figures are named SECTION-*.png.
    #[arg(long, default_value = "video")]
    section: String,
    /// The section's heading (default: the synthetic study's).
    #[arg(long)]
    title: Option<String>,
}

impl From<&EvalReportArgs> for VideoReportOptions {
    fn from(a: &EvalReportArgs) -> Self {
        Self {
            entries: a.entries.clone(),
            preamble: a.preamble.clone(),
            training_runs: a.training_runs.clone(),
            grids: a.grids.clone(),
            results: Some(a.out.clone()),
            section: a.section.clone(),
            title: a
                .title
                .clone()
                .unwrap_or_else(|| VideoReportOptions::synthetic(Vec::new()).title),
        }
    }
}

/// `bridgev2w eval-report`.
pub fn run_eval_report(a: &EvalReportArgs) -> Result<()> {
    let md = video_report(&a.into())?;
    write_section(&a.out, &a.section, &md)?;
    if let Some(w) = bridgev2w_io::plot::missing_font_warning() {
        eprintln!("{w}");
    }
    crate::print_stdout(&md)
}
