//! `bridgev2w parity DIR...`: runs diffusers parity fixtures with the Rust world model.

use anyhow::{bail, Context, Result};
use bridgev2w_world_model::parity::{
    run_fixture, run_fixture_bf16, BF16_EPSILON, BF16_FACTOR, DEFAULT_TOLERANCE,
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
    if args.precision == Precision::Bf16 {
        return run_bf16(args);
    }
    let mut failed = Vec::new();
    let mut text = String::from("| fixture | kind | output | shape | max abs err | max rel err | |\n|---|---|---|---|---|---|---|\n");
    for dir in &args.fixtures {
        let report =
            run_fixture(dir).with_context(|| format!("parity fixture {}", dir.display()))?;
        for o in &report.outputs {
            let ok = o.max_rel <= args.tolerance && o.max_rel.is_finite();
            if !ok {
                failed.push(format!("{}:{}", dir.display(), o.name));
            }
            text.push_str(&format!(
                "| {} | {} | {} | {:?} | {:.3e} | {:.3e} | {} |\n",
                dir.display(),
                report.kind,
                o.name,
                o.shape,
                o.max_abs,
                o.max_rel,
                if ok { "ok" } else { "FAIL" }
            ));
        }
    }
    crate::print_stdout(&text)?;
    if !failed.is_empty() {
        bail!(
            "relative error above {:e} in: {}",
            args.tolerance,
            failed.join(", ")
        );
    }
    Ok(())
}

fn run_bf16(args: &ParityArgs) -> Result<()> {
    let mut failed = Vec::new();
    let mut text = String::from(
        "errors against diffusers' f32 output (max rel = max |err| / max |f32|, rms rel = rms err / rms f32)\n\
         | fixture | kind | output | shape | ours bf16 max rel | diffusers bf16 max rel | ours bf16 rms rel | diffusers bf16 rms rel | |\n\
         |---|---|---|---|---|---|---|---|---|\n",
    );
    for dir in &args.fixtures {
        let report = run_fixture_bf16(dir)
            .with_context(|| format!("bf16 parity fixture {}", dir.display()))?;
        for o in &report.outputs {
            let ok = o.within(args.bf16_factor, args.bf16_epsilon);
            if !ok {
                failed.push(format!("{}:{}", dir.display(), o.name));
            }
            text.push_str(&format!(
                "| {} | {} | {} | {:?} | {:.3e} | {:.3e} | {:.3e} | {:.3e} | {} |\n",
                dir.display(),
                report.kind,
                o.name,
                o.shape,
                o.ours.max_rel,
                o.diffusers.max_rel,
                o.ours.rms_rel,
                o.diffusers.rms_rel,
                if ok { "ok" } else { "FAIL" }
            ));
        }
    }
    crate::print_stdout(&text)?;
    if !failed.is_empty() {
        bail!(
            "bf16 error above {} x diffusers' + {:e} in: {}",
            args.bf16_factor,
            args.bf16_epsilon,
            failed.join(", ")
        );
    }
    Ok(())
}
