//! diffusers pipeline folders: `model_index.json` naming the components, each in its
//! own subfolder (`transformer/`, `vae/`, `scheduler/`) with `config.json` (or
//! `scheduler_config.json`) and safetensors weights, single or sharded. A downloaded
//! `THUDM/CogVideoX-5b-I2V` loads unchanged; `text_encoder/` and `tokenizer/` are not
//! used (the prompt is fixed: its embedding is read from a file, see [`PromptEmbedding`]).

use crate::conditioning::ImageConditioning;
use crate::error::{Result, WorldModelError};
use bridgev2w_io::json::read_json;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// The pipeline classes accepted in `model_index.json`.
pub const PIPELINE_CLASSES: [&str; 2] = ["CogVideoXImageToVideoPipeline", "CogVideoXPipeline"];

/// A parsed `model_index.json`.
#[derive(Debug, Clone)]
pub struct PipelineFolder {
    /// The folder.
    pub root: PathBuf,
    /// `_class_name`.
    pub class_name: String,
    /// component name -> (library, class), e.g. `vae -> (diffusers, AutoencoderKLCogVideoX)`.
    pub components: BTreeMap<String, (String, String)>,
    /// `_bridgev2w_image_conditioning`: how a backbone trained here takes its
    /// image latent (absent in diffusers' own folders: CogVideoX's first frame).
    pub image_conditioning: Option<ImageConditioning>,
}

/// The `model_index.json` key recording a backbone's [`ImageConditioning`]
/// (diffusers ignores keys that start with `_`).
pub const IMAGE_CONDITIONING_KEY: &str = "_bridgev2w_image_conditioning";

impl PipelineFolder {
    /// Reads `DIR/model_index.json` and checks the components this crate loads.
    pub fn open(root: &Path) -> Result<Self> {
        let path = root.join("model_index.json");
        let value: serde_json::Value = read_json(&path)?;
        let obj = value
            .as_object()
            .ok_or_else(|| WorldModelError::config(&path, "(root)", "expected a JSON object"))?;
        let class_name = obj
            .get("_class_name")
            .and_then(|v| v.as_str())
            .ok_or_else(|| WorldModelError::config(&path, "_class_name", "missing"))?
            .to_owned();
        if !PIPELINE_CLASSES.contains(&class_name.as_str()) {
            return Err(WorldModelError::config(
                &path,
                "_class_name",
                format!("`{class_name}`: expected one of {PIPELINE_CLASSES:?}"),
            ));
        }
        let mut components = BTreeMap::new();
        for (k, v) in obj.iter().filter(|(k, _)| !k.starts_with('_')) {
            if let Some([lib, class]) = v.as_array().map(|a| a.as_slice()) {
                if let (Some(lib), Some(class)) = (lib.as_str(), class.as_str()) {
                    components.insert(k.clone(), (lib.to_owned(), class.to_owned()));
                }
            }
        }
        let image_conditioning = match obj.get(IMAGE_CONDITIONING_KEY) {
            None => None,
            Some(v) => Some(
                v.as_str()
                    .ok_or_else(|| {
                        WorldModelError::config(&path, IMAGE_CONDITIONING_KEY, "expected a string")
                    })?
                    .parse::<ImageConditioning>()
                    .map_err(|e| {
                        WorldModelError::config(&path, IMAGE_CONDITIONING_KEY, e.to_string())
                    })?,
            ),
        };
        let folder = Self {
            root: root.to_path_buf(),
            class_name,
            components,
            image_conditioning,
        };
        folder.expect_class("transformer", &["CogVideoXTransformer3DModel"])?;
        folder.expect_class("vae", &["AutoencoderKLCogVideoX"])?;
        folder.expect_class(
            "scheduler",
            &["CogVideoXDDIMScheduler", "CogVideoXDPMScheduler"],
        )?;
        Ok(folder)
    }

    fn expect_class(&self, component: &str, classes: &[&str]) -> Result<()> {
        let path = self.root.join("model_index.json");
        match self.components.get(component) {
            Some((_, class)) if classes.contains(&class.as_str()) => {
                let dir = self.root.join(component);
                if dir.is_dir() {
                    Ok(())
                } else {
                    Err(WorldModelError::io(
                        &dir,
                        std::io::Error::new(
                            std::io::ErrorKind::NotFound,
                            format!(
                                "component folder missing (model_index.json names {component})"
                            ),
                        ),
                    ))
                }
            }
            Some((_, class)) => Err(WorldModelError::config(
                &path,
                component,
                format!("class `{class}`: expected one of {classes:?}"),
            )),
            None => Err(WorldModelError::config(
                &path,
                component,
                format!("missing: expected [\"diffusers\", \"{}\"]", classes[0]),
            )),
        }
    }

    /// A component's folder.
    pub fn component_dir(&self, component: &str) -> PathBuf {
        self.root.join(component)
    }

    /// Checks that each of `components` has its weights (one safetensors
    /// file or the shards of its index), before any is read: a folder with
    /// the configs alone is named as such, not met later as a mismatch.
    pub fn check_weights(&self, components: &[&str]) -> Result<()> {
        for c in components {
            crate::weights::resolve_weight_files(
                &self.component_dir(c),
                crate::weights::DIFFUSERS_WEIGHTS_STEM,
            )?;
        }
        Ok(())
    }
}

/// The fixed prompt ("Follow this action sequence represented in mask") as T5
/// embeddings `[L, D]`, read from a safetensors file with key `prompt_embeds`
/// (`[1, L, D]` or `[L, D]`; `scripts/encode_prompt.py` writes it from a CogVideoX
/// folder's text encoder). Without a file the embedding is all zeros `[226, 4096]`
/// (documented fallback: the text tokens then carry only the text projection's bias).
#[derive(Debug)]
pub struct PromptEmbedding {
    /// `[L, D]`.
    pub embeds: tch::Tensor,
}

impl PromptEmbedding {
    /// The prompt BridgeV2W is trained with.
    pub const PROMPT: &'static str = "Follow this action sequence represented in mask";

    /// Reads `prompt_embeds` from a safetensors file, checking the width `text_dim`.
    pub fn load(path: &Path, text_dim: i64) -> Result<Self> {
        let tensors = crate::weights::read_safetensors(path)?;
        let t = tensors
            .into_iter()
            .find(|(k, _)| k == "prompt_embeds")
            .map(|(_, t)| t)
            .ok_or_else(|| {
                WorldModelError::config(path, "prompt_embeds", "no tensor with this key")
            })?;
        let t = match t.dim() {
            3 if t.size()[0] == 1 => t.squeeze_dim(0),
            2 => t,
            _ => {
                return Err(WorldModelError::config(
                    path,
                    "prompt_embeds",
                    format!("shape {:?}: expected [1, L, D] or [L, D]", t.size()),
                ))
            }
        };
        if t.size()[1] != text_dim {
            return Err(WorldModelError::config(
                path,
                "prompt_embeds",
                format!(
                    "width {} but the transformer's text_embed_dim is {text_dim}",
                    t.size()[1]
                ),
            ));
        }
        Ok(Self {
            embeds: t.to_kind(tch::Kind::Float),
        })
    }

    /// The zero fallback `[max_text_seq_length, text_dim]`.
    pub fn zeros(seq_len: i64, text_dim: i64) -> Self {
        Self {
            embeds: tch::Tensor::zeros([seq_len, text_dim], (tch::Kind::Float, tch::Device::Cpu)),
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn write_index(dir: &Path, body: &str) {
        std::fs::write(dir.join("model_index.json"), body).unwrap();
        for c in ["transformer", "vae", "scheduler"] {
            std::fs::create_dir_all(dir.join(c)).unwrap();
        }
    }

    const INDEX: &str = r#"{"_class_name": "CogVideoXImageToVideoPipeline", "_diffusers_version": "0.30.0",
      "scheduler": ["diffusers", "CogVideoXDDIMScheduler"], "text_encoder": ["transformers", "T5EncoderModel"],
      "tokenizer": ["transformers", "T5Tokenizer"], "transformer": ["diffusers", "CogVideoXTransformer3DModel"],
      "vae": ["diffusers", "AutoencoderKLCogVideoX"]}"#;

    #[test]
    fn reads_a_cogvideox_model_index() {
        let d = tempfile::tempdir().unwrap();
        write_index(d.path(), INDEX);
        let f = PipelineFolder::open(d.path()).unwrap();
        assert_eq!(f.class_name, "CogVideoXImageToVideoPipeline");
        assert_eq!(f.components["vae"].1, "AutoencoderKLCogVideoX");
        assert_eq!(f.components.len(), 5);
    }

    #[test]
    fn wrong_classes_and_missing_folders_are_named() {
        let d = tempfile::tempdir().unwrap();
        write_index(
            d.path(),
            &INDEX.replace("AutoencoderKLCogVideoX", "AutoencoderKL"),
        );
        let e = PipelineFolder::open(d.path()).unwrap_err().to_string();
        assert!(e.contains("vae") && e.contains("AutoencoderKL`"), "{e}");
        let d = tempfile::tempdir().unwrap();
        write_index(d.path(), INDEX);
        std::fs::remove_dir(d.path().join("scheduler")).unwrap();
        let e = PipelineFolder::open(d.path()).unwrap_err().to_string();
        assert!(e.contains("scheduler"), "{e}");
        let d = tempfile::tempdir().unwrap();
        write_index(
            d.path(),
            &INDEX.replace("CogVideoXImageToVideoPipeline", "StableDiffusionPipeline"),
        );
        assert!(PipelineFolder::open(d.path()).is_err());
    }

    #[test]
    fn prompt_embedding_file_and_fallback() {
        let d = tempfile::tempdir().unwrap();
        let p = d.path().join("prompt.safetensors");
        let t = tch::Tensor::ones([1, 7, 16], (tch::Kind::Float, tch::Device::Cpu));
        crate::weights::save_safetensors(&[("prompt_embeds".to_owned(), t)], &p).unwrap();
        let e = PromptEmbedding::load(&p, 16).unwrap();
        assert_eq!(e.embeds.size(), [7, 16]);
        let err = PromptEmbedding::load(&p, 32).unwrap_err().to_string();
        assert!(err.contains("text_embed_dim is 32"), "{err}");
        assert_eq!(PromptEmbedding::zeros(226, 4096).embeds.size(), [226, 4096]);
    }
}
