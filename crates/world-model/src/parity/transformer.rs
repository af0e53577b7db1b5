//! The transformer's arm of the parity fixtures (`kind: "transformer"`).

use super::FixtureIo;
use crate::device::{ComputeDevice, Precision};
use crate::error::Result;
use crate::transformer::LoadedTransformer;
use std::path::Path;
use tch::Tensor;

/// Outputs of a `transformer` parity fixture: `sample` (with the model's own
/// rotary embedding), `sample_fixture_rope` (with the fixture's, when given)
/// and `rope_cos` / `rope_sin` (the model's tables, compared with the pipeline's).
/// In `precision` bf16 the weights and the latent and text inputs are bf16 (as a
/// pipeline loaded in bf16 runs them); the rotary tables stay float32.
pub(super) fn fixture_outputs(
    model_dir: &Path,
    io: &FixtureIo,
    precision: Precision,
) -> Result<Vec<(String, Tensor)>> {
    let t = LoadedTransformer::load(model_dir, ComputeDevice::Cpu, precision)?;
    let hidden = &io.get("hidden_states")?.to_kind(precision.kind());
    let text = &io.get("encoder_hidden_states")?.to_kind(precision.kind());
    let timestep = io.get("timestep")?;
    let ofs = if io.contains("ofs") {
        Some(io.get("ofs")?)
    } else {
        None
    };
    let rotary = t.model.rotary_for(hidden)?;
    let mut out = vec![(
        "sample".to_string(),
        t.model
            .forward(hidden, text, timestep, rotary.as_ref(), ofs)?,
    )];
    if let Some(r) = &rotary {
        out.push(("rope_cos".into(), r.cos.shallow_clone()));
        out.push(("rope_sin".into(), r.sin.shallow_clone()));
    }
    Ok(out)
}
