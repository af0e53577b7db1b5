//! Where a model comes from, by name: `random:PRESET` (random weights of a
//! small preset, for tests and for training a video prior from scratch) or
//! a diffusers CogVideoX image-to-video folder. Parsed once
//! ([`std::str::FromStr`]) wherever a model is named: `model.backbone`,
//! `predict --model`, `plan --model`.

use crate::bridge::{BridgeV2W, BridgeV2WConfig, CONFIG_METADATA_KEY};
use crate::checkpoint::PipelineFolder;
use crate::device::{ComputeDevice, Precision};
use crate::error::WorldModelError;
use crate::scheduler::SchedulerConfig;
use crate::transformer::TransformerConfig;
use crate::vae::VaeConfig;
use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

/// The VAE + transformer presets with random weights (`random:NAME`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum RandomPreset {
    /// Tiny VAE and transformer (a smoke test).
    Tiny,
    /// 4x spatial and temporal VAE, a transformer of 128 with patches of 2.
    Small,
    /// 2x spatial VAE without time compression, patches of 4 (the CPU proof run).
    Small2x,
    /// [`Self::Small2x`] with a transformer of 256.
    Small2xWide,
    /// CogVideoX-5B-I2V's shapes (42 blocks of 3072, the 16-channel 8x VAE)
    /// at the paper's 480x720: random weights at full size, for measuring
    /// speed and memory on a GPU (about 22 GB of f32 weights).
    Cogvideox5bI2v,
}

crate::named_enum!(RandomPreset, WorldModelError, WorldModelError::input, "random preset", {
    Tiny => "tiny",
    Small => "small",
    Small2x => "small2x",
    Small2xWide => "small2x-wide",
    Cogvideox5bI2v => "cogvideox-5b-i2v",
});

impl RandomPreset {
    /// The preset's VAE and transformer configurations.
    pub fn configs(self) -> (VaeConfig, TransformerConfig) {
        match self {
            Self::Tiny => (VaeConfig::tiny(), TransformerConfig::tiny()),
            Self::Small => (VaeConfig::small(), TransformerConfig::small()),
            Self::Small2x => (VaeConfig::small_2x(), TransformerConfig::small_2x()),
            Self::Small2xWide => (VaeConfig::small_2x(), TransformerConfig::small_2x_wide()),
            Self::Cogvideox5bI2v => (
                VaeConfig::cogvideox_5b_i2v(),
                TransformerConfig::cogvideox_5b_i2v(),
            ),
        }
    }

    /// The BridgeV2W settings a random model of this preset gets: the tiny
    /// ones (9 frames at 64x96, a small ControlNet and LoRA) for the small
    /// presets, the paper's (480x720) for the full-size one.
    pub fn bridge_config(self) -> BridgeV2WConfig {
        match self {
            Self::Cogvideox5bI2v => BridgeV2WConfig::paper(),
            _ => BridgeV2WConfig::tiny(),
        }
    }
}

/// A model by name: `random:PRESET` or a diffusers folder.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum ModelSpec {
    /// Random weights of a preset.
    Random(RandomPreset),
    /// A diffusers CogVideoX image-to-video folder (`model_index.json`,
    /// `vae/`, `transformer/`, `scheduler/`).
    Folder(PathBuf),
}

impl ModelSpec {
    /// Refuses adapter `weights` or `prompt_embeds` with a `random:` model,
    /// which has no use for them (they would be silently ignored).
    pub fn check_inputs(
        &self,
        weights: Option<&Path>,
        prompt_embeds: Option<&Path>,
    ) -> Result<(), WorldModelError> {
        if let Self::Random(_) = self {
            for (flag, path) in [("--weights", weights), ("--prompt-embeds", prompt_embeds)] {
                if let Some(path) = path {
                    return Err(WorldModelError::input(
                        flag,
                        format!(
                            "{} given with --model {self}: a random: model has random weights and a zero prompt and would ignore it (expected a diffusers model folder, or no {flag})",
                            path.display()
                        ),
                    ));
                }
            }
        }
        Ok(())
    }

    /// Builds the BridgeV2W this names, in `precision`: random weights of a
    /// preset (its [`RandomPreset::bridge_config`], initialised from `seed`,
    /// the same weights in either precision), or a diffusers
    /// folder with the paper's settings and the given adapter `weights` and
    /// `prompt_embeds` (a folder error names the folder). Adapter files
    /// with a random preset are refused ([`Self::check_inputs`]).
    pub fn load_bridge(
        &self,
        weights: Option<&Path>,
        prompt_embeds: Option<&Path>,
        device: ComputeDevice,
        precision: Precision,
        seed: i64,
    ) -> Result<BridgeV2W, WorldModelError> {
        self.check_inputs(weights, prompt_embeds)?;
        match self {
            Self::Random(preset) => {
                let (vae, tf) = preset.configs();
                BridgeV2W::random_in(
                    preset.bridge_config(),
                    &vae,
                    &tf,
                    SchedulerConfig::cogvideox_5b_i2v(),
                    device,
                    precision,
                    seed,
                )
            }
            // A Hub name's refusal (bad revision, a cache entry leading out
            // of its folder) names the flag this value came from.
            Self::Folder(dir) => crate::hub::resolve_model_dir(dir)
                .map_err(|e| match e {
                    WorldModelError::ModelName { .. } => {
                        WorldModelError::input("--model", e.to_string())
                    }
                    e => e,
                })
                .and_then(|root| {
                    check_backbone(&root, weights)?;
                    BridgeV2W::load(
                        &root,
                        weights,
                        prompt_embeds,
                        BridgeV2WConfig::paper(),
                        device,
                        precision,
                    )
                })
                .map_err(|e| e.in_folder(dir)),
        }
    }
}

/// Checks a diffusers folder `root` before any weights are read: its VAE
/// and transformer weights are there, and the clip the model will take
/// (the config in the BridgeV2W `weights`, else the paper's 25 frames at
/// 480x720) fits its VAE and transformer. A misfit says where the clip
/// came from (no `--weights`, a weights file without a config, or one
/// trained on another backbone) instead of a bare resolution mismatch.
pub fn check_backbone(root: &Path, weights: Option<&Path>) -> Result<(), WorldModelError> {
    let folder = PipelineFolder::open(root)?;
    folder.check_weights(&["vae", "transformer"])?;
    let vae = VaeConfig::from_file(&folder.component_dir("vae").join("config.json"))?;
    let tf =
        TransformerConfig::from_file(&folder.component_dir("transformer").join("config.json"))?;
    let stored = weights
        .map(BridgeV2W::weights_config)
        .transpose()?
        .flatten();
    if let (Some(w), Some(message)) = (
        weights,
        stored.as_ref().and_then(|c| c.controlnet.scale_error()),
    ) {
        let field = format!("{CONFIG_METADATA_KEY}.controlnet.conditioning_scale");
        return Err(WorldModelError::config(w, field, message));
    }
    let clip = stored.clone().unwrap_or_else(BridgeV2WConfig::paper);
    let Err(e) = clip.validate(&vae, &tf) else {
        return Ok(());
    };
    let paper = "the paper's clip (25 frames at 480x720) is assumed";
    let backbone = root.display();
    Err(match (weights, stored) {
        (None, _) => WorldModelError::input(
            "--weights",
            format!(
                "not given, so {paper}, which the backbone {backbone} does not take ({e}); expected the BridgeV2W weights trained on this backbone (their config sets the clip), e.g. the bridgev2w.safetensors beside it"
            ),
        ),
        (Some(w), None) => WorldModelError::config(
            w,
            CONFIG_METADATA_KEY,
            format!(
                "absent, so {paper}, which the backbone {backbone} does not take ({e}); expected a weights file written by `bridgev2w train` for this backbone"
            ),
        ),
        (Some(w), Some(c)) => WorldModelError::config(
            w,
            CONFIG_METADATA_KEY,
            format!(
                "{} frames at {}x{} (HxW), which the backbone {backbone} does not take ({e}); were these weights trained on another backbone?",
                c.frames, c.height, c.width
            ),
        ),
    })
}

impl FromStr for ModelSpec {
    type Err = WorldModelError;
    fn from_str(s: &str) -> Result<Self, WorldModelError> {
        match s.strip_prefix("random:") {
            Some(name) => name.parse().map(Self::Random).map_err(|_| {
                let names: Vec<String> = RandomPreset::NAMES
                    .iter()
                    .map(|n| format!("random:{n}"))
                    .collect();
                WorldModelError::input(
                    "model",
                    format!("{s:?}: expected {} or a diffusers folder", names.join(", ")),
                )
            }),
            None if s.is_empty() => Err(WorldModelError::input(
                "model",
                "empty: expected random:PRESET or a diffusers folder",
            )),
            None => {
                // A Hub name's revision (`OWNER/NAME@REV`, no such local
                // folder) is checked here, so the flag's error names it.
                if !Path::new(s).is_dir() {
                    if let Some(hub) = crate::hub::HubName::parse(s) {
                        hub.check_revision()
                            .map_err(|m| WorldModelError::input("model", format!("{s:?}: {m}")))?;
                    }
                }
                Ok(Self::Folder(PathBuf::from(s)))
            }
        }
    }
}

impl fmt::Display for ModelSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Random(p) => write!(f, "random:{p}"),
            Self::Folder(dir) => write!(f, "{}", dir.display()),
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn specs_parse_print_and_an_unknown_preset_lists_them() {
        for text in ["random:tiny", "random:small2x-wide", "some/folder"] {
            assert_eq!(text.parse::<ModelSpec>().unwrap().to_string(), text);
        }
        assert_eq!(
            "random:small2x".parse::<ModelSpec>().unwrap(),
            ModelSpec::Random(RandomPreset::Small2x)
        );
        let (vae, tf) = RandomPreset::Small2xWide.configs();
        assert_eq!((vae, tf.num_attention_heads), (VaeConfig::small_2x(), 8));
        let e = "random:huge".parse::<ModelSpec>().unwrap_err().to_string();
        assert!(
            e.contains("random:huge")
                && e.contains("random:tiny")
                && e.contains("random:small2x-wide"),
            "{e}"
        );
        assert!("".parse::<ModelSpec>().is_err());
    }

    /// The error and its sources, one line each.
    fn chain(e: &WorldModelError) -> String {
        let mut text = e.to_string();
        let mut source = std::error::Error::source(e);
        while let Some(s) = source {
            text = format!("{text}\n{s}");
            source = s.source();
        }
        text
    }

    #[test]
    fn a_backbone_without_the_weights_it_needs_says_so() {
        let (vae, tf) = RandomPreset::Tiny.configs();
        let sched = SchedulerConfig::cogvideox_5b_i2v();
        let cpu = ComputeDevice::Cpu;
        let m = BridgeV2W::random(BridgeV2WConfig::tiny(), &vae, &tf, sched, cpu, 0).unwrap();
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path().join("backbone");
        m.save_backbone(&root).unwrap();
        let w = dir.path().join("bridgev2w.safetensors");
        m.save_weights(&w).unwrap();
        let spec = ModelSpec::Folder(root.clone());
        let load = |w: Option<&Path>| spec.load_bridge(w, None, cpu, Precision::F32, 0);
        assert_eq!(load(Some(&w)).unwrap().config().height, 64);
        // No --weights: the paper's 480x720 is assumed, which this 64x96
        // backbone does not take. Today's message was the bare mismatch.
        let e = chain(&load(None).unwrap_err());
        assert!(
            e.contains("--weights")
                && e.contains("not given")
                && e.contains("480x720")
                && e.contains("64x96"),
            "{e}"
        );
        // A weights file without a config, or with another clip's.
        let one = vec![(
            "x".to_owned(),
            tch::Tensor::zeros([1], tch::kind::FLOAT_CPU),
        )];
        let bare = dir.path().join("bare.safetensors");
        crate::weights::save_safetensors(&one, &bare).unwrap();
        let e = chain(&load(Some(&bare)).unwrap_err());
        assert!(
            e.contains(&bare.display().to_string())
                && e.contains(CONFIG_METADATA_KEY)
                && e.contains("absent"),
            "{e}"
        );
        let other = dir.path().join("other.safetensors");
        let cfg = BridgeV2WConfig {
            height: 128,
            ..BridgeV2WConfig::tiny()
        };
        let meta = [(
            CONFIG_METADATA_KEY.to_owned(),
            serde_json::to_string(&cfg).unwrap(),
        )];
        crate::weights::save_safetensors_with_metadata(&one, &meta.into(), &other).unwrap();
        let e = chain(&load(Some(&other)).unwrap_err());
        assert!(
            e.contains(&other.display().to_string())
                && e.contains("128x96")
                && e.contains("another backbone"),
            "{e}"
        );
        // A residual weight that would overflow the backbone's tokens.
        let mut cfg = BridgeV2WConfig::tiny();
        cfg.controlnet.conditioning_scale = vec![1e30];
        let meta = [(
            CONFIG_METADATA_KEY.to_owned(),
            serde_json::to_string(&cfg).unwrap(),
        )];
        crate::weights::save_safetensors_with_metadata(&one, &meta.into(), &other).unwrap();
        let e = chain(&load(Some(&other)).unwrap_err());
        assert!(
            e.contains(&other.display().to_string())
                && e.contains("controlnet.conditioning_scale")
                && e.contains("weight 0 is 1000000000000000000000000000000"),
            "{e}"
        );
        // Configs without weights: the missing file is named first, before
        // any mismatch (and before the transformer is allocated).
        for component in ["transformer", "vae"] {
            let file = root
                .join(component)
                .join("diffusion_pytorch_model.safetensors");
            let kept = dir.path().join(format!("{component}.safetensors"));
            std::fs::rename(&file, &kept).unwrap();
            for weights in [None, Some(w.as_path())] {
                let e = chain(&load(weights).unwrap_err());
                assert!(
                    e.contains(&file.display().to_string())
                        && e.contains("config.json but not its weights")
                        && !e.contains("480x720"),
                    "{e}"
                );
            }
            if component == "transformer" {
                let dir = root.join(component);
                let e = crate::transformer::LoadedTransformer::load(&dir, cpu, Precision::F32);
                assert!(chain(&e.unwrap_err()).contains("not its weights"));
            }
            std::fs::rename(&kept, &file).unwrap();
        }
    }
}
