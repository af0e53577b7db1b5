//! `bridgev2w bench masks`: flags of [`bridgev2w_embodiment::bench::masks`].

use crate::progress::TerminalProgress;
use anyhow::Result;
use bridgev2w_embodiment::bench::{bench_masks, MasksBenchOptions};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct MasksBench {
    /// Frames in the joint trajectory.
    #[arg(long, default_value_t = 100)]
    frames: usize,
    /// Times the trajectory is rendered (by each renderer).
    #[arg(long, default_value_t = 3)]
    repeat: usize,
    #[arg(long, default_value_t = 720)]
    width: u32,
    #[arg(long, default_value_t = 480)]
    height: u32,
    /// Worker processes for pybullet (default: all cores, like this renderer's threads).
    #[arg(long)]
    workers: Option<usize>,
    /// Only measure this renderer (no Python needed) on the given URDF.
    #[arg(long)]
    no_pybullet: bool,
    /// URDF to render (default: pybullet's franka_panda/panda.urdf).
    #[arg(long)]
    urdf: Option<PathBuf>,
    /// Repository root (holds scripts/bench/); default: found from the current directory.
    #[arg(long)]
    repo: Option<PathBuf>,
}

impl From<&MasksBench> for MasksBenchOptions {
    fn from(a: &MasksBench) -> Self {
        Self {
            frames: a.frames,
            repeat: a.repeat,
            width: a.width,
            height: a.height,
            workers: a.workers,
            pybullet: !a.no_pybullet,
            urdf: a.urdf.clone(),
            repo: a.repo.clone(),
        }
    }
}

pub fn run(a: &MasksBench) -> Result<()> {
    let report = bench_masks(&a.into(), &TerminalProgress::default())?;
    crate::print_stdout(&report.to_string())?;
    for w in report.warnings() {
        eprintln!("{w}");
    }
    Ok(())
}
