//! The memory a prediction needs at the least, checked against the machine
//! before it runs ([`BridgeV2W::check_predict_memory`]), and the bound on
//! the clips of one model call ([`MAX_PREDICT_BATCH`]).

use super::BridgeV2W;
use crate::error::{Result, PREDICT_MEMORY_ADVICE};
use bridgev2w_io::memory::{at_most, bytes, check_fits};
use tch::{Device, Kind};

/// The most clips one model call takes (`predict --batch-size`, `plan
/// --max-batch`, the batch of `bw.WorldModel.predict`).
pub const MAX_PREDICT_BATCH: usize = 4096;

/// Bytes per pixel of each frame of each clip that a prediction holds on
/// the host at the least: the masks as a float video `[B, 3, T, H, W]` and
/// the predicted video returned as floats (3 channels x 4 bytes each).
const HOST_BYTES_PER_PIXEL: u64 = 12 + 12;

/// Activations of one transformer block per token and channel, in units of
/// the model's element size: the residual stream, queries, keys and values,
/// and the 4x-wide hidden state of its feed-forward layer.
const BLOCK_ACTIVATIONS_PER_CHANNEL: u64 = 1 + 3 + 4;

/// `clips` (named `name`: the flag or argument that gave it) of one model
/// call: at least 1 and at most [`MAX_PREDICT_BATCH`].
pub fn check_predict_batch(name: &str, clips: usize) -> Result<()> {
    if clips == 0 {
        return Err(crate::WorldModelError::input(
            name,
            "0: expected at least 1 clip per model call",
        ));
    }
    at_most(name, clips as u64, MAX_PREDICT_BATCH as u64, "clips")?;
    Ok(())
}

/// What a prediction of `clips` clips holds at the least, in bytes: on the
/// host, and on the model's device (the same memory on a CPU).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PredictBytes {
    /// The masks and the predicted videos as floats ([`HOST_BYTES_PER_PIXEL`]
    /// per pixel of every frame of every clip).
    pub host: u64,
    /// One transformer block's activations for the whole batch (residual
    /// stream, queries, keys, values, the feed-forward hidden state: 8 x
    /// tokens x the model's width) and the mask branch's residuals held
    /// for the backbone (one per branch block), at the model's precision.
    /// The weights are not counted: they are loaded already.
    pub device: u64,
}

impl BridgeV2W {
    /// A floor of the memory a prediction of `clips` clips needs besides the
    /// loaded weights ([`PredictBytes`]): what must be held at once, so a
    /// request beyond the machine is certain to fail. Attention scores, the
    /// VAE's activations and libtorch's workspace come on top.
    pub fn predict_bytes(&self, clips: usize) -> PredictBytes {
        let cfg = &self.cfg;
        let tf = self.transformer.model.config();
        let b = clips as u64;
        let host = bytes(&[
            b,
            cfg.frames as u64,
            cfg.height as u64,
            cfg.width as u64,
            HOST_BYTES_PER_PIXEL,
        ]);
        let (t, h, w) = self.latent_geometry();
        let p = tf.patch_size.max(1);
        let pt = tf.patch_size_t.unwrap_or(1).max(1);
        let video_tokens = bytes(&[
            ((t + pt - 1) / pt).max(0) as u64,
            (h / p).max(0) as u64,
            (w / p).max(0) as u64,
        ]);
        let tokens = video_tokens.saturating_add(tf.max_text_seq_length.max(0) as u64);
        let element = match self.kind {
            Kind::BFloat16 | Kind::Half => 2,
            _ => 4,
        };
        let width = tf.inner_dim().max(0) as u64;
        let block = bytes(&[b, tokens, width, element, BLOCK_ACTIVATIONS_PER_CHANNEL]);
        let branch = bytes(&[
            b,
            video_tokens,
            width,
            element,
            cfg.controlnet.num_layers as u64,
        ]);
        PredictBytes {
            host,
            device: block.saturating_add(branch),
        }
    }

    /// Refuses a prediction of `clips` clips whose [`Self::predict_bytes`]
    /// exceed the memory this machine has
    /// ([`bridgev2w_io::memory::MemoryError::Exceeds`], with the estimate):
    /// on a CPU the host and device parts together, on a GPU the host part
    /// (a GPU's own memory is not read here; an out-of-memory there is an
    /// error naming the shapes).
    pub fn check_predict_memory(&self, clips: usize) -> Result<()> {
        let need = self.predict_bytes(clips);
        let estimate = match self.device {
            Device::Cpu => need.host.saturating_add(need.device),
            _ => need.host,
        };
        check_fits(
            &format!(
                "predicting {clips} clip(s) of {} frames at {}x{} ({:?})",
                self.cfg.frames, self.cfg.height, self.cfg.width, self.kind
            ),
            estimate,
            PREDICT_MEMORY_ADVICE,
        )?;
        Ok(())
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::bridge::{BridgeV2WConfig, MAX_CLIP_FRAMES};
    use crate::scheduler::SchedulerConfig;
    use crate::transformer::TransformerConfig;
    use crate::vae::VaeConfig;
    use crate::{ComputeDevice, WorldModelError};

    fn tiny() -> BridgeV2W {
        BridgeV2W::random(
            BridgeV2WConfig::tiny(),
            &VaeConfig::tiny(),
            &TransformerConfig::tiny(),
            SchedulerConfig::cogvideox_5b_i2v(),
            ComputeDevice::Cpu,
            0,
        )
        .unwrap()
    }

    #[test]
    fn batch_sizes_are_bounded() {
        assert!(check_predict_batch("--batch-size", 1).is_ok());
        assert!(check_predict_batch("--batch-size", MAX_PREDICT_BATCH).is_ok());
        let e = check_predict_batch("--batch-size", 0).unwrap_err();
        assert!(e.to_string().contains("--batch-size"), "{e}");
        let e = check_predict_batch("--max-batch", MAX_PREDICT_BATCH + 1).unwrap_err();
        assert_eq!(
            e.to_string(),
            "--max-batch 4097: at most 4096 clips is supported"
        );
    }

    #[test]
    fn the_estimate_grows_with_the_batch_and_a_request_beyond_the_machine_is_refused() {
        let mut m = tiny();
        let one = m.predict_bytes(1);
        let four = m.predict_bytes(4);
        assert_eq!(four.host, 4 * one.host);
        assert_eq!(four.device, 4 * one.device);
        // 9 frames of 64x96, 24 bytes a pixel.
        assert_eq!(one.host, 9 * 64 * 96 * 24);
        assert!(m.check_predict_memory(4).is_ok());
        // The largest clip at the largest batch: far beyond any machine.
        m.set_clip_frames(MAX_CLIP_FRAMES - 7).unwrap();
        let e = m.check_predict_memory(MAX_PREDICT_BATCH);
        if bridgev2w_io::memory::available_bytes().is_some() {
            let text = e.unwrap_err().to_string();
            assert!(
                text.starts_with("predicting 4096 clip(s) of 1017 frames at 64x96"),
                "{text}"
            );
            assert!(
                text.contains("is available") && text.contains("--batch-size"),
                "{text}"
            );
        }
    }

    #[test]
    fn clip_sizes_beyond_their_maximum_are_refused_naming_the_field() {
        let mut m = tiny();
        let e = m.set_clip_frames(MAX_CLIP_FRAMES + 9).unwrap_err();
        assert!(matches!(e, WorldModelError::Input { .. }), "{e}");
        assert!(e.to_string().contains("frames"), "{e}");
        assert!(e.to_string().contains("at most 1024 frames"), "{e}");
    }

    #[test]
    fn a_weights_file_whose_config_claims_a_clip_beyond_the_maximum_is_refused() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("w.safetensors");
        let cfg = BridgeV2WConfig {
            frames: 1_000_001,
            ..BridgeV2WConfig::tiny()
        };
        let meta = [(
            crate::bridge::CONFIG_METADATA_KEY.to_owned(),
            serde_json::to_string(&cfg).unwrap(),
        )]
        .into_iter()
        .collect();
        let t = tch::Tensor::zeros([2], (Kind::Float, Device::Cpu));
        crate::weights::save_safetensors_with_metadata(&[("x".to_owned(), t)], &meta, &path)
            .unwrap();
        let e = BridgeV2W::weights_config(&path).unwrap_err().to_string();
        assert!(e.contains("w.safetensors"), "{e}");
        assert!(e.contains("bridgev2w_config.frames"), "{e}");
        assert!(e.contains("1000001: at most 1024 frames"), "{e}");
    }
}
