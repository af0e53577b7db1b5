//! `bridgev2w bench metrics`: [`bridgev2w_eval::bench`] (its options are the flags).

use crate::progress::TerminalProgress;
use anyhow::Result;
use bridgev2w_eval::bench::{bench_metrics, MetricsBenchOptions};

pub fn run(o: &MetricsBenchOptions) -> Result<()> {
    let report = bench_metrics(o, &TerminalProgress::default())?;
    crate::print_stdout(&report.to_string())
}
