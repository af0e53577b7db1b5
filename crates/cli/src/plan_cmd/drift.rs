//! `bridgev2w eval-drift`: how far autoregressive rollouts drift from the
//! synthetic world over many chunks ([`bridgev2w_plan::experiment::drift`];
//! its options are the flags).

use super::progress;
use anyhow::Result;
use bridgev2w_plan::experiment::{drift_study, DriftOptions};

pub fn run(o: &DriftOptions) -> Result<()> {
    let r = drift_study(o, &mut progress)?;
    crate::print_stdout(&r.markdown())
}
