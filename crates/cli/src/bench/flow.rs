//! `bridgev2w bench flow`: flags of [`bridgev2w_train::bench::flow`].

use anyhow::Result;
use bridgev2w_train::bench::flow::{FlowBenchEstimator, FlowBenchVae};
use bridgev2w_train::bench::{bench_flow, FlowBenchOptions};
use bridgev2w_train::decoded_flow::FlowBackward;
use bridgev2w_world_model::vae::TileSize;
use bridgev2w_world_model::{ComputeDevice, Precision};

#[derive(Debug, clap::Args)]
pub struct FlowBench {
    /// VAE preset with random weights: cogvideox (2B and 5B's architecture), tiny, small, small2x.
    #[arg(long, default_value = "cogvideox")]
    vae: FlowBenchVae,
    /// Pixel frames (the VAE's 4k + 1 for cogvideox). The defaults run in
    /// about a minute on 2 cores; the full size is `--frames 25 --height 480
    /// --width 720 --tile 240x360 --precision bf16 --device cuda`.
    #[arg(long, default_value_t = 17)]
    frames: i64,
    #[arg(long, default_value_t = 128)]
    height: i64,
    #[arg(long, default_value_t = 192)]
    width: i64,
    /// Spatial tiles of HxW pixels (training tiles above 256x256 with the
    /// VAE's default tiles, half its sample size); default: whole frames.
    #[arg(long)]
    tile: Option<TileSize>,
    /// f32 or bf16.
    #[arg(long, default_value = "f32")]
    precision: Precision,
    /// cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: ComputeDevice,
    /// The modes, comma-separated, in order (the first one's gradient is the reference).
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "autograd,recorded,stepwise"
    )]
    modes: Vec<FlowBackward>,
    /// Flow estimator: lucas_kanade (the CPU stand-in), raft_small or
    /// raft_large (random weights: the cost, not the flow, is measured).
    #[arg(long, default_value = "lucas_kanade")]
    flow: FlowBenchEstimator,
    /// RAFT's refinement iterations.
    #[arg(long, default_value_t = 12)]
    raft_iterations: usize,
}

impl From<&FlowBench> for FlowBenchOptions {
    fn from(a: &FlowBench) -> Self {
        Self {
            vae: a.vae,
            frames: a.frames,
            height: a.height,
            width: a.width,
            tile: a.tile,
            precision: a.precision,
            device: a.device,
            modes: a.modes.clone(),
            estimator: a.flow,
            raft_iterations: a.raft_iterations,
        }
    }
}

pub fn run(a: &FlowBench) -> Result<()> {
    let report = bench_flow(&a.into())?;
    crate::print_stdout(&report.to_string())
}
