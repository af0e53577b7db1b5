//! `bridgev2w bench model`: [`bridgev2w_world_model::bench::compare`] (its
//! options are the flags, but for the precisions and the limit).

use crate::progress::TerminalProgress;
use anyhow::Result;
use bridgev2w_world_model::bench::{bench_model_precisions, ModelBenchOptions};
use bridgev2w_world_model::Precision;

#[derive(Debug, clap::Args)]
pub struct ModelBench {
    #[command(flatten)]
    options: ModelBenchOptions,
    /// f32 or bf16; `f32,bf16` (or the flag twice) runs both in turn and
    /// ends with every speed-up over diffusers side by side.
    #[arg(long, default_value = "f32", value_delimiter = ',')]
    precision: Vec<Precision>,
    /// Give each of diffusers' operations (transformer forward, VAE encode,
    /// VAE decode) at most SECONDS from its start: one still running then
    /// is stopped and reported with a lower bound (`>`), and the ones after
    /// it run in a new process. For bf16 on a CPU without AVX-512, where
    /// diffusers' VAE takes hours.
    #[arg(long, value_name = "SECONDS", conflicts_with = "diffusers",
          value_parser = clap::value_parser!(u64).range(1..))]
    diffusers_limit: Option<u64>,
}

pub fn run(a: &ModelBench) -> Result<()> {
    let o = ModelBenchOptions {
        diffusers_limit: a.diffusers_limit.map(std::time::Duration::from_secs),
        ..a.options.clone()
    };
    let report = bench_model_precisions(&o, &a.precision, &TerminalProgress::default())?;
    crate::print_stdout(&report.to_string())
}
