//! RAFT's arm of the parity fixtures (`kind: "raft"`).

use super::FixtureIo;
use crate::device::ComputeDevice;
use crate::error::Result;
use crate::nets::raft::{Raft, RaftConfig};
use crate::weights::resolve_weight_files;
use std::path::Path;
use tch::Tensor;

/// Outputs of a `raft` parity fixture: `flow` (final estimate) from
/// `image1`, `image2`, with the variant and iterations of `meta`.
pub(super) fn fixture_outputs(
    model_dir: &Path,
    meta: &serde_json::Value,
    io: &FixtureIo,
) -> Result<Vec<(String, Tensor)>> {
    let variant = meta
        .get("variant")
        .and_then(|v| v.as_str())
        .unwrap_or("raft_large");
    let iterations = meta
        .get("iterations")
        .and_then(serde_json::Value::as_u64)
        .unwrap_or(12) as usize;
    let files = resolve_weight_files(model_dir, variant)?;
    let net = Raft::load(RaftConfig::by_name(variant)?, &files, ComputeDevice::Cpu)?;
    let flows = net.forward_all(io.get("image1")?, io.get("image2")?, iterations)?;
    let mut out = vec![];
    if let Some(first) = flows.first() {
        out.push(("flow_first".to_string(), first.shallow_clone()));
    }
    if let Some(last) = flows.last() {
        out.push(("flow".to_string(), last.shallow_clone()));
    }
    Ok(out)
}
