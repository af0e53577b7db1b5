//! `bridgev2w bench flow`: [`bridgev2w_train::bench::flow`] (its options are
//! the flags).

use anyhow::Result;
use bridgev2w_train::bench::{bench_flow, FlowBenchOptions};

pub fn run(o: &FlowBenchOptions) -> Result<()> {
    crate::print_stdout(&bench_flow(o)?.to_string())
}
