//! `bridgev2w bench kinematics`: flags of [`bridgev2w_embodiment::bench::kinematics`].

use anyhow::Result;
use bridgev2w_embodiment::bench::{bench_kinematics, KinematicsBenchOptions};

#[derive(Debug, clap::Args)]
pub struct KinematicsBench {
    /// Forward-kinematics evaluations.
    #[arg(long, default_value_t = 2_000_000)]
    fk: usize,
    /// Warm-started IK solves along a smooth trajectory.
    #[arg(long, default_value_t = 20_000)]
    ik: usize,
}

impl From<&KinematicsBench> for KinematicsBenchOptions {
    fn from(a: &KinematicsBench) -> Self {
        Self { fk: a.fk, ik: a.ik }
    }
}

pub fn run(a: &KinematicsBench) -> Result<()> {
    let report = bench_kinematics(&a.into())?;
    crate::print_stdout(&report.to_string())
}
