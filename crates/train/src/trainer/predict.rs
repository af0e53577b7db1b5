//! Sampling predictions from the run's model (evaluation during and after training).

use super::Trainer;
use crate::config::Stage;
use crate::data::Batch;
use crate::Result;
use bridgev2w_world_model::bridge::BridgeV2W;
use bridgev2w_world_model::pipeline::{sample_latents, Denoiser, Guidance, SampleOptions};
use bridgev2w_world_model::scheduler::Scheduler;
use tch::Tensor;

impl Trainer {
    /// The model's prediction `[B, 3, T, H, W]` in [-1, 1] for `batch`: from
    /// the first frames (posterior mode) and the run's condition (mask
    /// branch, action MLP, or none for a prior), sampled with `opts`.
    pub fn predict(&self, batch: &Batch, opts: &SampleOptions) -> Result<Tensor> {
        let model = &self.model;
        tch::no_grad(|| -> Result<Tensor> {
            let img = model.image_latents(&batch.first_frames, None)?;
            let bridge = self.cfg.train.stage == Stage::Bridgev2w;
            let control = if bridge && self.cfg.ablation.mask_action {
                Some(model.control_latents(&batch.masks, &img)?)
            } else {
                None
            };
            let extra = match (&self.action, bridge) {
                (Some(enc), true) => {
                    let zs = img.size(); // [B, t, C, h, w]
                    let p = model.transformer.model.config().patch_size;
                    enc.residuals(
                        &batch.actions.to_device(model.device()),
                        (zs[3] / p) * (zs[4] / p),
                    )?
                }
                _ => Vec::new(),
            };
            let denoiser = RunDenoiser {
                model,
                control: control.as_ref(),
                extra: &extra,
            };
            let mut scheduler = Scheduler::new(model.scheduler.clone())?;
            let z = sample_latents(&denoiser, &mut scheduler, &img, opts)?;
            Ok(model.decode_latents(&z)?.clamp(-1.0, 1.0))
        })
    }
}

/// The run's model as a denoiser: the mask branch and/or action residuals
/// when conditioned, neither when unconditioned (classifier-free guidance).
struct RunDenoiser<'a> {
    model: &'a BridgeV2W,
    control: Option<&'a Tensor>,
    extra: &'a [Tensor],
}

impl Denoiser for RunDenoiser<'_> {
    fn velocity(
        &self,
        latent_in: &Tensor,
        timestep: &Tensor,
        guidance: Guidance,
    ) -> bridgev2w_world_model::Result<Tensor> {
        match guidance {
            Guidance::Conditional => {
                self.model
                    .velocity_with_extra(latent_in, timestep, self.control, self.extra)
            }
            Guidance::Unconditional => {
                self.model
                    .velocity_with_extra(latent_in, timestep, None, &[])
            }
        }
    }
}
