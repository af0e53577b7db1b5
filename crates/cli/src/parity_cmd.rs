//! `bridgev2w parity DIR...`: runs diffusers parity fixtures with the Rust world model.

use anyhow::{bail, Context, Result};
use bridgev2w_world_model::parity::{run_fixture, DEFAULT_TOLERANCE};
use clap::Args;
use std::path::PathBuf;

#[derive(Debug, Args)]
pub struct ParityArgs {
    /// Fixture directories written by scripts/parity/make_parity_fixture.py.
    #[arg(required = true)]
    pub fixtures: Vec<PathBuf>,
    /// Largest allowed relative error (max |rust - diffusers| / max |diffusers|).
    #[arg(long, default_value_t = DEFAULT_TOLERANCE)]
    pub tolerance: f64,
}

pub fn run(args: &ParityArgs) -> Result<()> {
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
