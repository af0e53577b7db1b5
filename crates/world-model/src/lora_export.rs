//! The backbone's LoRA in diffusers' layout: the `pytorch_lora_weights.safetensors`
//! that `CogVideoXLoraLoaderMixin.save_lora_weights` writes and
//! `CogVideoXImageToVideoPipeline.load_lora_weights(DIR)` (or
//! `CogVideoXTransformer3DModel.load_lora_adapter`) loads.
//!
//! Keys: `transformer.transformer_blocks.{i}.attn1.{to_q,to_k,to_v,to_out.0}.lora_A.weight`
//! `[r, in]` and `.lora_B.weight` `[out, r]` (the `transformer.` prefix is the
//! pipeline component, the rest the module path in `CogVideoXTransformer3DModel`);
//! header metadata `{"format": "pt"}`, the file's dtype the adapters'.
//!
//! Scaling: a file without PEFT metadata is loaded by diffusers with
//! `lora_alpha = r` (scale 1, `W + B A`). BridgeV2W's update is
//! `(alpha / r) B A`, so the export writes `lora_B * alpha / r` (computed in
//! f32) and `lora_A` unchanged: diffusers' output then equals this crate's
//! for any alpha.
//!
//! Only the backbone's adapters go into the file: the ControlNet branch
//! (`controlnet.*` in BridgeV2W's weights) has no diffusers counterpart, so a
//! diffusers pipeline with the exported LoRA is BridgeV2W without its mask
//! branch (the unconditional half of classifier-free guidance).

use crate::bridge::{BridgeV2W, CONFIG_METADATA_KEY};
use crate::checkpoint::PipelineFolder;
use crate::error::{Result, WorldModelError};
use crate::lora::{LoraConfig, LORA_TARGETS};
use crate::transformer::TransformerConfig;
use crate::weights::{check_finite, read_safetensors, save_safetensors_with_metadata};
use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use tch::{Kind, Tensor};

/// diffusers' file name for LoRA weights (`LORA_WEIGHT_NAME_SAFE`).
pub const DIFFUSERS_LORA_FILE: &str = "pytorch_lora_weights.safetensors";

/// The key prefix of the transformer's adapters, in BridgeV2W's weights and in
/// diffusers' file alike (the CogVideoX pipelines' `transformer_name`).
pub const TRANSFORMER_PREFIX: &str = "transformer.";

/// What an export wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct LoraExport {
    /// The file written (`OUT/pytorch_lora_weights.safetensors`).
    pub path: PathBuf,
    /// Adapted linear layers (4 per transformer block).
    pub layers: usize,
    /// The rank r.
    pub rank: i64,
    /// BridgeV2W's alpha (folded into `lora_B` as `alpha / r`).
    pub alpha: f64,
}

/// The diffusers tensors of BridgeV2W adapter tensors `named` (keys as in its
/// weights file; `controlnet.*` and anything not a transformer LoRA factor are
/// left out): every `lora_A` as is, every `lora_B` times `cfg.scale()`, sorted
/// by key. Errors on no adapters, an `A` without its `B` (or the reverse), or
/// a rank other than `cfg.rank`.
pub fn diffusers_lora_tensors(
    named: &[(String, Tensor)],
    cfg: LoraConfig,
) -> Result<Vec<(String, Tensor)>> {
    let mut out: BTreeMap<String, Tensor> = BTreeMap::new();
    for (key, t) in named {
        if !key.starts_with(TRANSFORMER_PREFIX) {
            continue;
        }
        let t = t.detach();
        if key.ends_with(".lora_A.weight") {
            out.insert(key.clone(), t.to_device(tch::Device::Cpu).contiguous());
        } else if key.ends_with(".lora_B.weight") {
            let kind = t.kind();
            let scaled = (t.to_device(tch::Device::Cpu).to_kind(Kind::Float) * cfg.scale())
                .to_kind(kind)
                .contiguous();
            out.insert(key.clone(), scaled);
        }
    }
    if out.is_empty() {
        return Err(WorldModelError::input(
            "lora",
            format!("no `{TRANSFORMER_PREFIX}*.lora_{{A,B}}.weight` tensors: nothing to export"),
        ));
    }
    for (key, t) in &out {
        let (other, rank_dim) = match key.strip_suffix(".lora_A.weight") {
            Some(layer) => (format!("{layer}.lora_B.weight"), 0),
            None => (key.replace(".lora_B.weight", ".lora_A.weight"), 1),
        };
        if !out.contains_key(&other) {
            return Err(WorldModelError::input(
                "lora",
                format!("`{key}` without `{other}`"),
            ));
        }
        let s = t.size();
        if s.len() != 2 || s[rank_dim] != cfg.rank {
            return Err(WorldModelError::input(
                "lora",
                format!(
                    "`{key}` has shape {s:?}: expected rank {} in dimension {rank_dim} (the config's lora.rank)",
                    cfg.rank
                ),
            ));
        }
    }
    Ok(out.into_iter().collect())
}

/// Checks adapter tensors (diffusers keys) against a backbone transformer:
/// every target of every block adapted (`LORA_TARGETS`), `A` `[r, inner_dim]`,
/// `B` `[inner_dim, r]`, no other key.
pub fn check_against_transformer(
    tensors: &[(String, Tensor)],
    tf: &TransformerConfig,
    source: &Path,
) -> Result<()> {
    let d = tf.inner_dim();
    let mut expected = BTreeSet::new();
    for i in 0..tf.num_layers {
        for target in LORA_TARGETS {
            for factor in ["lora_A", "lora_B"] {
                expected.insert(format!(
                    "{TRANSFORMER_PREFIX}transformer_blocks.{i}.attn1.{target}.{factor}.weight"
                ));
            }
        }
    }
    for (key, t) in tensors {
        if !expected.remove(key) {
            return Err(WorldModelError::UnexpectedWeight {
                path: source.to_path_buf(),
                key: key.clone(),
            });
        }
        let s = t.size();
        let ok = if key.ends_with(".lora_A.weight") {
            s.get(1) == Some(&d)
        } else {
            s.first() == Some(&d)
        };
        if !ok {
            let r = if key.ends_with(".lora_A.weight") {
                vec![s[0], d]
            } else {
                vec![d, s[1]]
            };
            return Err(WorldModelError::ShapeMismatch {
                path: source.to_path_buf(),
                key: key.clone(),
                expected: r,
                found: s,
            });
        }
    }
    match expected.into_iter().next() {
        Some(key) => Err(WorldModelError::config(
            source,
            "lora",
            format!(
                "no `{key}`, but the backbone's transformer has {} blocks with 4 adapted projections each (is the model folder the backbone these weights were trained on?)",
                tf.num_layers
            ),
        )),
        None => Ok(()),
    }
}

/// Writes the adapters of a model in memory to `out_dir/pytorch_lora_weights.safetensors`
/// (atomically; an existing file is refused unless `overwrite`).
pub fn export_lora(model: &BridgeV2W, out_dir: &Path, overwrite: bool) -> Result<LoraExport> {
    let cfg = model.config().lora.ok_or_else(|| {
        WorldModelError::input("lora", "the model has no LoRA (config lora = null)")
    })?;
    let named: Vec<(String, Tensor)> = model.adapters.variables().into_iter().collect();
    write(
        &diffusers_lora_tensors(&named, cfg)?,
        cfg,
        out_dir,
        overwrite,
    )
}

/// Writes the adapters of a BridgeV2W weights file (`bridgev2w train`'s
/// `bridgev2w.safetensors`, its LoRA settings from the header's config) to
/// `out_dir/pytorch_lora_weights.safetensors`, after checking them against the
/// transformer of the backbone folder `backbone` (a diffusers pipeline folder;
/// only its `transformer/config.json` is read). Atomic; an existing file is
/// refused unless `overwrite`; so is an output file that is, is inside or
/// contains `weights` or `backbone` (it would replace or change an input).
pub fn export_lora_file(
    weights: &Path,
    backbone: &Path,
    out_dir: &Path,
    overwrite: bool,
) -> Result<LoraExport> {
    bridgev2w_io::output::check_no_overlap(
        &out_dir.join(DIFFUSERS_LORA_FILE),
        &[weights, backbone],
    )
    .map_err(|e| WorldModelError::input("--out", e.to_string()))?;
    let cfg = BridgeV2W::weights_config(weights)?
        .ok_or_else(|| {
            WorldModelError::config(
                weights,
                CONFIG_METADATA_KEY,
                "missing: not a BridgeV2W weights file (bridgev2w train writes one)",
            )
        })?
        .lora
        .ok_or_else(|| {
            WorldModelError::config(
                weights,
                "lora",
                "null: the model was trained without LoRA, nothing to export",
            )
        })?;
    let root = crate::hub::resolve_model_dir(backbone)?;
    let folder = PipelineFolder::open(&root).map_err(|e| e.in_folder(backbone))?;
    let tf = TransformerConfig::from_file(&folder.component_dir("transformer").join("config.json"))
        .map_err(|e| e.in_folder(backbone))?;
    // As loading the weights for `predict` does: a NaN or infinite value is
    // refused, naming the tensor, not exported.
    let named = read_safetensors(weights)?;
    for (key, t) in &named {
        check_finite(weights, key, t)?;
    }
    let tensors = diffusers_lora_tensors(&named, cfg)?;
    check_against_transformer(&tensors, &tf, weights)?;
    write(&tensors, cfg, out_dir, overwrite)
}

fn write(
    tensors: &[(String, Tensor)],
    cfg: LoraConfig,
    out_dir: &Path,
    overwrite: bool,
) -> Result<LoraExport> {
    let path = out_dir.join(DIFFUSERS_LORA_FILE);
    if path.exists() && !overwrite {
        return Err(WorldModelError::io(
            &path,
            std::io::Error::new(
                std::io::ErrorKind::AlreadyExists,
                "exists (pass --overwrite to replace it)",
            ),
        ));
    }
    std::fs::create_dir_all(out_dir).map_err(|e| WorldModelError::io(out_dir, e))?;
    let meta = BTreeMap::from([("format".to_owned(), "pt".to_owned())]);
    save_safetensors_with_metadata(tensors, &meta, &path)?;
    Ok(LoraExport {
        path,
        layers: tensors.len() / 2,
        rank: cfg.rank,
        alpha: cfg.alpha,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use tch::Device;

    fn named(rank: i64) -> Vec<(String, Tensor)> {
        let o = (Kind::Float, Device::Cpu);
        let k = |f: &str| format!("transformer.transformer_blocks.0.attn1.to_q.{f}.weight");
        vec![
            (k("lora_A"), Tensor::ones([rank, 6], o)),
            (k("lora_B"), Tensor::ones([6, rank], o)),
            (
                "controlnet.out_projectors.0.weight".into(),
                Tensor::ones([6, 6], o),
            ),
        ]
    }

    #[test]
    fn b_carries_alpha_over_rank_and_the_branch_is_left_out() {
        let cfg = LoraConfig {
            rank: 2,
            alpha: 6.0,
        };
        let out = diffusers_lora_tensors(&named(2), cfg).unwrap();
        let keys: Vec<&str> = out.iter().map(|(k, _)| k.as_str()).collect();
        assert_eq!(
            keys,
            [
                "transformer.transformer_blocks.0.attn1.to_q.lora_A.weight",
                "transformer.transformer_blocks.0.attn1.to_q.lora_B.weight"
            ]
        );
        assert_eq!(out[0].1.max().double_value(&[]), 1.0);
        assert_eq!(out[1].1.min().double_value(&[]), 3.0);
    }

    #[test]
    fn wrong_rank_lone_factor_and_no_adapters_are_errors() {
        let cfg = LoraConfig {
            rank: 3,
            alpha: 3.0,
        };
        let e = diffusers_lora_tensors(&named(2), cfg)
            .unwrap_err()
            .to_string();
        assert!(e.contains("expected rank 3"), "{e}");
        let mut lone = named(3);
        let _ = lone.remove(1);
        let e = diffusers_lora_tensors(&lone, cfg).unwrap_err().to_string();
        assert!(e.contains("without") && e.contains("lora_B"), "{e}");
        let e = diffusers_lora_tensors(&named(3)[2..], cfg)
            .unwrap_err()
            .to_string();
        assert!(e.contains("nothing to export"), "{e}");
    }
}
