//! `bridgev2w bench model`: flags of [`bridgev2w_world_model::bench::compare`].

use crate::progress::TerminalProgress;
use anyhow::Result;
use bridgev2w_world_model::bench::{bench_model_precisions, ModelBenchOptions, ModelStyle};
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::PathBuf;

#[derive(Debug, clap::Args)]
pub struct ModelBench {
    /// Architecture family: `2b` (sin-cos positions) or `5b-i2v` (RoPE, learned positions, I2V input).
    #[arg(long, default_value = "2b")]
    style: ModelStyle,
    /// Transformer blocks (the full models have 30 / 42).
    #[arg(long, default_value_t = 8)]
    layers: i64,
    /// Pixel frames (4k + 1). The defaults keep a 2-core CPU run near two minutes;
    /// `--frames 25 --height 256 --width 384` is the mid-size setting of the issue
    /// (the full-width VAE then dominates: tens of minutes on 2 cores).
    #[arg(long, default_value_t = 9)]
    frames: i64,
    #[arg(long, default_value_t = 128)]
    height: i64,
    #[arg(long, default_value_t = 192)]
    width: i64,
    /// Transformer batch: 2 times one denoising step with classifier-free
    /// guidance (the pipeline's conditional and unconditional halves).
    #[arg(long, default_value_t = 1)]
    batch: i64,
    /// Timed runs per operation (best is reported), after one warm-up.
    #[arg(long, default_value_t = 1)]
    repeat: usize,
    /// f32 or bf16; `f32,bf16` (or the flag twice) runs both in turn and
    /// ends with every speed-up over diffusers side by side.
    #[arg(long, default_value = "f32", value_delimiter = ',')]
    precision: Vec<Precision>,
    /// cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: ComputeDevice,
    /// Skip diffusers (time this crate only).
    #[arg(long)]
    no_diffusers: bool,
    /// Python with torch + diffusers (default: the project venv's).
    #[arg(long)]
    python: Option<PathBuf>,
    /// Repository root (holds scripts/bench/); default: found from the current directory.
    #[arg(long)]
    repo: Option<PathBuf>,
    /// Time the VAE with spatial tiling on both sides (diffusers'
    /// `enable_tiling()`, default tiles), as `predict` runs it above 256x256.
    #[arg(long)]
    vae_tiling: bool,
    /// Give each of diffusers' operations (transformer forward, VAE encode,
    /// VAE decode) at most SECONDS from its start: one still running then
    /// is stopped and reported with a lower bound (`>`), and the ones after
    /// it run in a new process. For bf16 on a CPU without AVX-512, where
    /// diffusers' VAE takes hours.
    #[arg(long, value_name = "SECONDS", conflicts_with = "no_diffusers",
          value_parser = clap::value_parser!(u64).range(1..))]
    diffusers_limit: Option<u64>,
}

impl From<&ModelBench> for ModelBenchOptions {
    fn from(a: &ModelBench) -> Self {
        Self {
            style: a.style,
            layers: a.layers,
            frames: a.frames,
            height: a.height,
            width: a.width,
            batch: a.batch,
            repeat: a.repeat,
            precision: a.precision.first().copied().unwrap_or(Precision::F32),
            device: a.device,
            diffusers: !a.no_diffusers,
            python: a.python.clone(),
            repo: a.repo.clone(),
            vae_tiling: a.vae_tiling,
            diffusers_limit: a.diffusers_limit.map(std::time::Duration::from_secs),
        }
    }
}

pub fn run(a: &ModelBench) -> Result<()> {
    let report = bench_model_precisions(&a.into(), &a.precision, &TerminalProgress::default())?;
    crate::print_stdout(&report.to_string())
}
