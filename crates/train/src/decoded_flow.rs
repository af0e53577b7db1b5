//! The flow loss of decoded latents: the fine-tuning stage's flow term
//! decodes the predicted clean latents with the frozen VAE, estimates the
//! flow of the decoded video and of the ground truth, and pushes the
//! discrepancy's gradient back through the decode into the latents.
//!
//! How the gradient crosses the decoder is a [`FlowBackward`] mode: through
//! autograd over the whole decode (simple, every decoder activation kept),
//! batch by batch from a recorded decode ([`vae::DecodeRecord`]: one
//! latent-frame batch of one tile under autograd at a time), or the same
//! with each batch checkpointed unit by unit (one resnet's activations at a
//! time). All give the same gradient up to float rounding; `bridgev2w bench
//! flow` measures their time and peak memory.
//!
//! [`vae::DecodeRecord`]: bridgev2w_world_model::vae::DecodeRecord

use crate::flow::{flow_loss, FlowEstimator, FlowLossConfig};
use crate::{Result, TrainError};
use bridgev2w_world_model::vae::{AutoencoderKLCogVideoX, BatchReplay};
use tch::{Kind, Tensor};

/// How the flow loss's gradient crosses the VAE's decoder.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FlowBackward {
    /// Autograd through the whole decode: every decoder activation of every
    /// frame batch and tile kept until the backward pass.
    Autograd,
    /// A decode without autograd that records each batch's starting conv
    /// cache, then the batches replayed under autograd from the last to the
    /// first ([`AutoencoderKLCogVideoX::decode_backward`]): one batch's
    /// activations at a time, for a second decoder pass. What training uses
    /// without gradient checkpointing.
    #[default]
    Recorded,
    /// [`Self::Recorded`] with each batch replayed unit by unit
    /// ([`BatchReplay::Stepwise`]: `conv_in`, each resnet, each upsampler,
    /// the output): one unit's activations at a time, for a third decoder
    /// pass; tiled, one tile's conv caches at a time, computed again at its
    /// replay (a fourth pass, without autograd). What training uses with
    /// gradient checkpointing.
    Stepwise,
}
bridgev2w_world_model::named_enum!(FlowBackward, TrainError, TrainError::input, "flow backward", {
    Autograd => "autograd",
    Recorded => "recorded",
    Stepwise => "stepwise",
});

impl FlowBackward {
    /// The mode training uses: [`Self::Stepwise`] where the step trades
    /// compute for memory (`train.gradient_checkpointing`), else
    /// [`Self::Recorded`].
    pub fn for_training(gradient_checkpointing: bool) -> Self {
        if gradient_checkpointing {
            Self::Stepwise
        } else {
            Self::Recorded
        }
    }
}

/// [`decoded_flow`]'s result.
#[derive(Debug)]
pub struct DecodedFlow {
    /// The loss: a scalar whose value is the flow loss and whose gradient
    /// with respect to `z` is the loss's.
    pub loss: Tensor,
    /// The bytes the recorded decode kept between the decode and the
    /// backward ([`vae::DecodeRecord::bytes`]); `None` for autograd.
    ///
    /// [`vae::DecodeRecord::bytes`]: bridgev2w_world_model::vae::DecodeRecord::bytes
    pub record_bytes: Option<u64>,
}

/// The flow loss of the video the VAE decodes from `z` (`[B, C, t, h, w]`,
/// unscaled latents, usually requiring gradients) against `gt`
/// (`[B, 3, T, H, W]` in `[-1, 1]`): a scalar whose value is the loss and
/// whose gradient with respect to `z` is the loss's, by `how`. The decoded
/// video is clamped to `[-1, 1]` before the flow is estimated, as the
/// predicted frames are elsewhere. The recorded modes give the decoder's
/// own parameters no gradient; autograd does where they require one (the
/// VAE is frozen in training).
pub fn decoded_flow(
    vae: &AutoencoderKLCogVideoX,
    z: &Tensor,
    gt: &Tensor,
    estimator: &dyn FlowEstimator,
    cfg: &FlowLossConfig,
    how: FlowBackward,
) -> Result<DecodedFlow> {
    match how {
        FlowBackward::Autograd => {
            let video = vae.decode_with_grad(z)?;
            let gt = gt.to_device(video.device());
            Ok(DecodedFlow {
                loss: flow_loss(estimator, &video.clamp(-1.0, 1.0), &gt, cfg)?,
                record_bytes: None,
            })
        }
        FlowBackward::Recorded | FlowBackward::Stepwise => {
            let replay = if how == FlowBackward::Stepwise {
                BatchReplay::Stepwise
            } else {
                BatchReplay::Whole
            };
            let (decoded, record) = vae.decode_recorded(&z.detach(), replay)?;
            let leaf = decoded.detach().set_requires_grad(true);
            let gt = gt.to_device(leaf.device());
            let fl = flow_loss(estimator, &leaf.clamp(-1.0, 1.0), &gt, cfg)?;
            let grad_video = Tensor::f_run_backward(&[&fl], &[&leaf], false, false)?.remove(0);
            // Undefined when no pixel moves in either video (nothing to push back).
            let grad_video = if grad_video.defined() {
                grad_video
            } else {
                leaf.zeros_like()
            };
            drop(leaf);
            let grad_z = vae.decode_backward(&record, &grad_video)?;
            let record_bytes = Some(record.bytes());
            drop(record);
            // The value of the flow loss, the gradient of it through z.
            let pushed = (z * grad_z.to_kind(z.kind())).sum(Kind::Float);
            Ok(DecodedFlow {
                loss: &pushed - pushed.detach() + fl.detach(),
                record_bytes,
            })
        }
    }
}
