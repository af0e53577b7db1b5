//! Loading and saving weights in diffusers' safetensors layout.
//!
//! A diffusers component folder (`transformer/`, `vae/`) holds `config.json` and either
//! one `diffusion_pytorch_model.safetensors` or shards listed by
//! `diffusion_pytorch_model.safetensors.index.json` (`{"weight_map": {key: file}}`).
//! Parameters are matched by their exact diffusers key names; a tensor of another
//! shape, a parameter without a tensor and a tensor without a parameter are errors
//! (each can be allowed explicitly, e.g. for the ControlNet/LoRA parameters that a
//! base checkpoint lacks).

use crate::error::{read_json, Result, WorldModelError};
use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use tch::nn::VarStore;
use tch::Tensor;

/// The file stem diffusers uses for model weights.
pub const DIFFUSERS_WEIGHTS_STEM: &str = "diffusion_pytorch_model";

/// Finds the safetensors file(s) of a component: `DIR/STEM.safetensors`, or the shards
/// named by `DIR/STEM.safetensors.index.json`.
pub fn resolve_weight_files(dir: &Path, stem: &str) -> Result<Vec<PathBuf>> {
    let single = dir.join(format!("{stem}.safetensors"));
    if single.is_file() {
        return Ok(vec![single]);
    }
    let index = dir.join(format!("{stem}.safetensors.index.json"));
    if index.is_file() {
        #[derive(serde::Deserialize)]
        struct Index {
            weight_map: BTreeMap<String, String>,
        }
        let parsed: Index = read_json(&index)?;
        let mut files: Vec<String> = parsed.weight_map.into_values().collect();
        files.sort();
        files.dedup();
        if files.is_empty() {
            return Err(WorldModelError::config(
                &index,
                "weight_map",
                "is empty: expected at least one shard",
            ));
        }
        return files
            .into_iter()
            .map(|f| {
                let path = dir.join(&f);
                if path.is_file() {
                    Ok(path)
                } else {
                    Err(WorldModelError::config(
                        &index,
                        "weight_map",
                        format!(
                            "names shard `{f}`, which does not exist in {}",
                            dir.display()
                        ),
                    ))
                }
            })
            .collect();
    }
    let pickle = dir.join(format!("{stem}.bin"));
    let hint = if pickle.is_file() {
        format!(
            "; found {} (PyTorch pickle): convert it to safetensors first",
            pickle.display()
        )
    } else {
        String::new()
    };
    Err(WorldModelError::io(
        &single,
        std::io::Error::new(
            std::io::ErrorKind::NotFound,
            format!(
                "no weights: expected {stem}.safetensors or {stem}.safetensors.index.json{hint}"
            ),
        ),
    ))
}

/// What [`load_weights`] did.
#[derive(Debug, Default, Clone)]
pub struct LoadReport {
    /// Parameters filled from the files.
    pub loaded: usize,
    /// Parameters without a tensor (allowed by the caller).
    pub missing: Vec<String>,
    /// Tensors without a parameter (allowed by the caller).
    pub unexpected: Vec<String>,
}

/// Reads all tensors of one safetensors file, with errors naming the file.
pub fn read_safetensors(path: &Path) -> Result<Vec<(String, Tensor)>> {
    if !path.is_file() {
        return Err(WorldModelError::io(
            path,
            std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        ));
    }
    Tensor::read_safetensors(path).map_err(|e| {
        WorldModelError::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("not a valid safetensors file: {e}"),
            ),
        )
    })
}

/// Copies the tensors of `files` into the variables of `vs` by name, converting dtype
/// and device to the variable's. `missing_ok(key)` allows a variable without a tensor,
/// `unexpected_ok(key)` a tensor without a variable; anything else not matched, and
/// any shape mismatch, is an error.
pub fn load_weights(
    vs: &VarStore,
    files: &[PathBuf],
    missing_ok: impl Fn(&str) -> bool,
    unexpected_ok: impl Fn(&str) -> bool,
) -> Result<LoadReport> {
    let vars: HashMap<String, Tensor> = vs.variables();
    let mut seen: HashSet<String> = HashSet::new();
    let mut report = LoadReport::default();
    for path in files {
        for (key, tensor) in read_safetensors(path)? {
            let Some(var) = vars.get(&key) else {
                if unexpected_ok(&key) {
                    report.unexpected.push(key);
                    continue;
                }
                return Err(WorldModelError::UnexpectedWeight {
                    path: path.clone(),
                    key,
                });
            };
            if var.size() != tensor.size() {
                return Err(WorldModelError::ShapeMismatch {
                    path: path.clone(),
                    key,
                    expected: var.size(),
                    found: tensor.size(),
                });
            }
            tch::no_grad(|| {
                let mut var = var.shallow_clone();
                var.f_copy_(&tensor.to_kind(var.kind()).to_device(var.device()))
            })?;
            seen.insert(key);
            report.loaded += 1;
        }
    }
    let mut missing: Vec<&String> = vars.keys().filter(|k| !seen.contains(*k)).collect();
    missing.sort();
    for key in missing {
        if missing_ok(key) {
            report.missing.push(key.clone());
        } else {
            return Err(WorldModelError::MissingWeight {
                key: key.clone(),
                expected: vars[key].size(),
                files: files
                    .iter()
                    .map(|p| p.display().to_string())
                    .collect::<Vec<_>>()
                    .join(", "),
            });
        }
    }
    Ok(report)
}

/// Loads a diffusers component folder's weights (single file or shards) strictly.
pub fn load_component(vs: &VarStore, dir: &Path) -> Result<LoadReport> {
    let files = resolve_weight_files(dir, DIFFUSERS_WEIGHTS_STEM)?;
    load_weights(vs, &files, |_| false, |_| false)
}

/// Writes named tensors to a safetensors file atomically (temporary file in the same
/// directory, then rename), so an interrupted write never leaves a truncated file.
pub fn save_safetensors(named: &[(String, Tensor)], path: &Path) -> Result<()> {
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty());
    let dir = dir.unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| WorldModelError::io(dir, e))?;
    let file_name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "weights".to_owned());
    let tmp = dir.join(format!(".{file_name}.tmp-{}", std::process::id()));
    let cpu: Vec<(String, Tensor)> = named
        .iter()
        .map(|(k, t)| {
            (
                k.clone(),
                t.detach().to_device(tch::Device::Cpu).contiguous(),
            )
        })
        .collect();
    Tensor::write_safetensors(&cpu, &tmp).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        WorldModelError::io(&tmp, std::io::Error::other(e.to_string()))
    })?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        WorldModelError::io(path, e)
    })
}

/// Number of scalar parameters in a var store.
pub fn parameter_count(vs: &VarStore) -> i64 {
    vs.variables().values().map(|t| t.numel() as i64).sum()
}

/// Elements of the learnable variables only (PyTorch's `parameters()`:
/// buffers such as batch-norm statistics or CogVideoX's learned-position
/// buffer excluded).
pub fn learnable_parameter_count(vs: &VarStore) -> i64 {
    vs.trainable_variables()
        .iter()
        .map(|t| t.numel() as i64)
        .sum()
}
