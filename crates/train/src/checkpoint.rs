//! Checkpoint file helpers shared by the trainer and the moving averages.

use crate::{Result, TrainError};
use std::collections::BTreeMap;
use std::path::Path;
use tch::Tensor;

/// Copies the tensors `saved` (read from `path`) into `targets` by name:
/// every target must be there with its shape, and nothing else may be.
pub fn copy_named_into(
    targets: &[(String, Tensor)],
    saved: Vec<(String, Tensor)>,
    path: &Path,
) -> Result<()> {
    let bad = |message: String| TrainError::input(path.display().to_string(), message);
    let mut map: BTreeMap<String, Tensor> = saved.into_iter().collect();
    for (name, t) in targets {
        let src = map.remove(name).ok_or_else(|| {
            bad(format!(
                "no `{name}` (a checkpoint of another configuration?)"
            ))
        })?;
        if src.size() != t.size() {
            return Err(bad(format!(
                "`{name}` {:?} but the model has {:?}",
                src.size(),
                t.size()
            )));
        }
        tch::no_grad(|| t.shallow_clone().copy_(&src.to_device(t.device())));
    }
    match map.keys().next() {
        Some(extra) => Err(bad(format!(
            "unexpected `{extra}` (a checkpoint of another configuration?)"
        ))),
        None => Ok(()),
    }
}
