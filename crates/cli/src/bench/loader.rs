//! `bridgev2w bench loader`: clip loader throughput of
//! `bridgev2w_train::data::ClipDataset` (`bridgev2w_train::bench`; its
//! options are the flags).

use crate::progress::TerminalProgress;
use anyhow::Result;
use bridgev2w_train::bench::{bench_loader, LoaderBenchOptions};

pub fn run(o: &LoaderBenchOptions) -> Result<()> {
    let report = bench_loader(o, &TerminalProgress::default())?;
    crate::print_stdout(&report.to_string())
}
