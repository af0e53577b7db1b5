//! I3D's arm of the parity fixtures (`kind: "i3d"`).

use super::FixtureIo;
use crate::device::ComputeDevice;
use crate::error::Result;
use crate::nets::i3d::I3d;
use crate::weights::resolve_weight_files;
use std::path::Path;
use tch::Tensor;

/// Parity fixture outputs (`kind: i3d`): `logits` of the input `video`.
pub(super) fn fixture_outputs(model_dir: &Path, io: &FixtureIo) -> Result<Vec<(String, Tensor)>> {
    let files = resolve_weight_files(model_dir, "i3d")?;
    let net = I3d::load(&files, ComputeDevice::Cpu)?;
    Ok(vec![("logits".to_string(), net.forward(io.get("video")?)?)])
}
