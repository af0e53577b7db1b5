//! `bridgev2w bench metrics`: flags of [`bridgev2w_eval::bench`].

use crate::progress::TerminalProgress;
use anyhow::Result;
use bridgev2w_eval::bench::{bench_metrics, MetricsBenchOptions};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct MetricsBench {
    /// Frame pairs scored.
    #[arg(long, default_value_t = 50)]
    frames: usize,
    #[arg(long, default_value_t = 720)]
    width: usize,
    #[arg(long, default_value_t = 480)]
    height: usize,
    /// Worker processes for scikit-image (default: all cores, like this crate's threads).
    #[arg(long)]
    workers: Option<usize>,
    /// Repository root (holds scripts/bench/); default: found from the current directory.
    #[arg(long)]
    repo: Option<PathBuf>,
}

impl From<&MetricsBench> for MetricsBenchOptions {
    fn from(a: &MetricsBench) -> Self {
        Self {
            frames: a.frames,
            width: a.width,
            height: a.height,
            workers: a.workers,
            repo: a.repo.clone(),
        }
    }
}

pub fn run(a: &MetricsBench) -> Result<()> {
    let report = bench_metrics(&a.into(), &TerminalProgress::default())?;
    crate::print_stdout(&report.to_string())
}
