//! `bridgev2w bench loader`: clip loader throughput of
//! `bridgev2w_train::data::ClipDataset` (`bridgev2w_train::bench`).

use crate::progress::TerminalProgress;
use anyhow::Result;
use bridgev2w_train::bench::{bench_loader, LoaderBenchOptions};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct LoaderBench {
    /// Dataset (LeRobot with masks/ or calibration); default: a synthetic one generated here.
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Robot for rendering calc masks (when the dataset has calibration and joint states).
    #[arg(long, default_value = "franka")]
    robot: String,
    /// Episodes of the generated dataset.
    #[arg(long, default_value_t = 8)]
    episodes: usize,
    /// Clip frames.
    #[arg(long, default_value_t = 25)]
    frames: usize,
    /// Clip width and height.
    #[arg(long, default_value_t = 96)]
    width: usize,
    #[arg(long, default_value_t = 64)]
    height: usize,
    /// Batch size and number of batches assembled.
    #[arg(long, default_value_t = 4)]
    batch: usize,
    #[arg(long, default_value_t = 50)]
    steps: usize,
}

impl From<&LoaderBench> for LoaderBenchOptions {
    fn from(a: &LoaderBench) -> Self {
        Self {
            dataset: a.dataset.clone(),
            robot: a.robot.clone(),
            episodes: a.episodes,
            frames: a.frames,
            width: a.width,
            height: a.height,
            batch: a.batch,
            steps: a.steps,
        }
    }
}

pub fn run(a: &LoaderBench) -> Result<()> {
    let report = bench_loader(&a.into(), &TerminalProgress::default())?;
    crate::print_stdout(&report.to_string())
}
