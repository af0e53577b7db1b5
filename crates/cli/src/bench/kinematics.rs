//! `bridgev2w bench kinematics`: [`bridgev2w_embodiment::bench::kinematics`]
//! (its options are the flags).

use anyhow::Result;
use bridgev2w_embodiment::bench::{bench_kinematics, KinematicsBenchOptions};

pub fn run(o: &KinematicsBenchOptions) -> Result<()> {
    crate::print_stdout(&bench_kinematics(o)?.to_string())
}
