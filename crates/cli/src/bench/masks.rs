//! `bridgev2w bench masks`: [`bridgev2w_embodiment::bench::masks`] (its
//! options are the flags).

use crate::progress::TerminalProgress;
use anyhow::Result;
use bridgev2w_embodiment::bench::{bench_masks, MasksBenchOptions};

pub fn run(o: &MasksBenchOptions) -> Result<()> {
    let report = bench_masks(o, &TerminalProgress::default())?;
    crate::print_stdout(&report.to_string())?;
    for w in report.warnings() {
        eprintln!("{w}");
    }
    Ok(())
}
