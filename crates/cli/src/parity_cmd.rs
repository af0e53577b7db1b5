//! `bridgev2w parity DIR...`: runs diffusers parity fixtures with the Rust world model.

use anyhow::{bail, Result};
use bridgev2w_world_model::parity::{
    parity_table, parity_table_bf16, BF16_EPSILON, BF16_FACTOR, DEFAULT_TOLERANCE,
};
use bridgev2w_world_model::Precision;
use clap::Args;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct ParityArgs {
    /// Fixture directories written by scripts/parity/make_parity_fixture.py.
    #[arg(required = true)]
    pub fixtures: Vec<PathBuf>,
    /// Largest allowed relative error (max |rust - diffusers| / max |diffusers|), in f32.
    #[arg(long, default_value_t = DEFAULT_TOLERANCE)]
    pub tolerance: f64,
    /// f32, or bf16: the model in bfloat16 against diffusers in bfloat16 (transformer
    /// and VAE fixtures made with --bf16), both against diffusers' f32 output; ours may
    /// reach --bf16-factor times diffusers' error plus --bf16-epsilon.
    #[arg(long, default_value = "f32")]
    pub precision: Precision,
    /// bf16: how many times diffusers' own bf16 error ours may reach.
    #[arg(long, default_value_t = BF16_FACTOR)]
    pub bf16_factor: f64,
    /// bf16: added to the bound (relative error).
    #[arg(long, default_value_t = BF16_EPSILON)]
    pub bf16_epsilon: f64,
}

pub fn run(args: &ParityArgs) -> Result<()> {
    let table = match args.precision {
        Precision::Bf16 => parity_table_bf16(&args.fixtures, args.bf16_factor, args.bf16_epsilon)?,
        Precision::F32 => parity_table(&args.fixtures, args.tolerance)?,
    };
    crate::print_stdout(&table.markdown)?;
    if !table.failed.is_empty() {
        bail!("{} in: {}", table.bound, table.failed.join(", "));
    }
    Ok(())
}
