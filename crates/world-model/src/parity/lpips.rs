//! LPIPS's arm of the parity fixtures (`kind: "lpips"`).

use super::FixtureIo;
use crate::device::ComputeDevice;
use crate::error::Result;
use crate::nets::lpips::Lpips;
use crate::weights::resolve_weight_files;
use std::path::Path;
use tch::Tensor;

/// Outputs of an `lpips` parity fixture: `distance` from `in0`, `in1`.
pub(super) fn fixture_outputs(model_dir: &Path, io: &FixtureIo) -> Result<Vec<(String, Tensor)>> {
    let files = resolve_weight_files(model_dir, "lpips_alex")?;
    let net = Lpips::load(&files, ComputeDevice::Cpu)?;
    let d = net.forward(io.get("in0")?, io.get("in1")?)?;
    Ok(vec![("distance".to_string(), d)])
}
