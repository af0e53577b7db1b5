//! `bridgev2w eval-policy-rollout`: policy evaluation by world-model
//! rollouts vs synthetic-world success ([`RolloutOptions`] are its flags,
//! but for the scripted policies' offsets and the JSON report).

use super::progress;
use anyhow::Result;
use bridgev2w_io::json::write_json_atomic;
use bridgev2w_io::output::check_new_file;
use bridgev2w_plan::experiment::rollout::parse_offsets_mm;
use bridgev2w_plan::experiment::{rollout_report, RolloutOptions};
use std::path::PathBuf;

#[derive(Debug, Clone, clap::Args)]
pub struct EvalRolloutArgs {
    #[command(flatten)]
    pub options: RolloutOptions,
    /// Offset standard deviations of the scripted policies (mm,
    /// comma-separated; default 0,10,20,30,50, none with --policy unless given).
    #[arg(long)]
    pub offsets_mm: Option<String>,
    /// Also write the report as JSON (rates, agreement, the policies not
    /// evaluated and why).
    #[arg(long, value_name = "FILE")]
    pub json: Option<PathBuf>,
    /// Replace an existing --json file.
    #[arg(long, requires = "json")]
    pub overwrite: bool,
}

/// `bridgev2w eval-policy-rollout`.
pub fn run(a: &EvalRolloutArgs) -> Result<()> {
    if let Some(path) = &a.json {
        check_new_file(path, a.overwrite).map_err(|e| anyhow::anyhow!("--json {e}"))?;
    }
    let o = RolloutOptions {
        offsets_mm: match (&a.offsets_mm, a.options.served.is_empty()) {
            (Some(text), _) => parse_offsets_mm(text)?,
            (None, true) => RolloutOptions::new(a.options.task).offsets_mm,
            (None, false) => Vec::new(),
        },
        ..a.options.clone()
    };
    let r = rollout_report(&o, &mut progress)?;
    if let Some(path) = &a.json {
        write_json_atomic(path, &r.to_json())?;
    }
    crate::print_stdout(&r.markdown())
}
