//! The table `bridgev2w parity` prints: every output of every fixture with
//! its errors against diffusers and whether it is within the bound.

use super::{run_fixture, run_fixture_bf16};
use crate::error::{Result, WorldModelError};
use std::path::{Path, PathBuf};

/// A parity run over fixtures.
#[derive(Debug, Clone, PartialEq)]
pub struct ParityTable {
    /// The Markdown table, a row per output.
    pub markdown: String,
    /// `fixture:output` of each output beyond the bound.
    pub failed: Vec<String>,
    /// The bound, in words (for the failure message).
    pub bound: String,
}

fn fixture_err(dir: &Path) -> impl FnOnce(WorldModelError) -> WorldModelError + '_ {
    move |e| WorldModelError::Fixture {
        path: dir.to_path_buf(),
        source: Box::new(e),
    }
}

fn mark(ok: bool) -> &'static str {
    if ok {
        "ok"
    } else {
        "FAIL"
    }
}

/// Runs each fixture in f32; an output fails above relative error `tolerance`.
pub fn parity_table(fixtures: &[PathBuf], tolerance: f64) -> Result<ParityTable> {
    let mut failed = Vec::new();
    let mut md = String::from("| fixture | kind | output | shape | max abs err | max rel err | |\n|---|---|---|---|---|---|---|\n");
    for dir in fixtures {
        let report = run_fixture(dir).map_err(fixture_err(dir))?;
        for o in &report.outputs {
            let ok = o.max_rel <= tolerance && o.max_rel.is_finite();
            if !ok {
                failed.push(format!("{}:{}", dir.display(), o.name));
            }
            md.push_str(&format!(
                "| {} | {} | {} | {:?} | {:.3e} | {:.3e} | {} |\n",
                dir.display(),
                report.kind,
                o.name,
                o.shape,
                o.max_abs,
                o.max_rel,
                mark(ok)
            ));
        }
    }
    Ok(ParityTable {
        markdown: md,
        failed,
        bound: format!("relative error above {tolerance:e}"),
    })
}

/// Runs each fixture in bf16; an output fails where our bf16 error exceeds
/// `factor` times diffusers' bf16 error plus `epsilon` ([`super::Bf16Output::within`]).
pub fn parity_table_bf16(fixtures: &[PathBuf], factor: f64, epsilon: f64) -> Result<ParityTable> {
    let mut failed = Vec::new();
    let mut md = String::from(
        "errors against diffusers' f32 output (max rel = max |err| / max |f32|, rms rel = rms err / rms f32)\n\
         | fixture | kind | output | shape | ours bf16 max rel | diffusers bf16 max rel | ours bf16 rms rel | diffusers bf16 rms rel | |\n\
         |---|---|---|---|---|---|---|---|---|\n",
    );
    for dir in fixtures {
        let report = run_fixture_bf16(dir).map_err(fixture_err(dir))?;
        for o in &report.outputs {
            let ok = o.within(factor, epsilon);
            if !ok {
                failed.push(format!("{}:{}", dir.display(), o.name));
            }
            md.push_str(&format!(
                "| {} | {} | {} | {:?} | {:.3e} | {:.3e} | {:.3e} | {:.3e} | {} |\n",
                dir.display(),
                report.kind,
                o.name,
                o.shape,
                o.ours.max_rel,
                o.diffusers.max_rel,
                o.ours.rms_rel,
                o.diffusers.rms_rel,
                mark(ok)
            ));
        }
    }
    Ok(ParityTable {
        markdown: md,
        failed,
        bound: format!("bf16 error above {factor} x diffusers' + {epsilon:e}"),
    })
}
