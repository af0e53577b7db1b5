//! Sampling predictions from the run's model (evaluation during and after training).

use super::Trainer;
use crate::config::Stage;
use crate::data::Batch;
use crate::Result;
use bridgev2w_torch_ext::autocast;
use bridgev2w_world_model::bridge::BridgeV2W;
use bridgev2w_world_model::pipeline::{sample_latents, Denoiser, Guidance, SampleOptions};
use bridgev2w_world_model::scheduler::Scheduler;
use bridgev2w_world_model::static_scene::keep_static;
use tch::Tensor;

impl Trainer {
    /// A preview for the training logs: the first clip of step 0's batch,
    /// ground truth (top row) above the model's prediction (bottom row),
    /// every frame side by side, as an RGB8 image `(width, height, pixels)`;
    /// `None` for the autoencoder stage or with `train.preview_steps = 0`.
    /// Sampled with `preview_steps` steps and seed 0; training itself is
    /// unaffected (every step reseeds its random draws).
    pub fn preview(&self) -> Result<Option<(u32, u32, Vec<u8>)>> {
        let steps = self.cfg.train.preview_steps;
        if steps == 0 || self.cfg.train.stage == Stage::Vae {
            return Ok(None);
        }
        let b = self.global_batch(0)?;
        let one = Batch {
            first_frames: b.first_frames.narrow(0, 0, 1),
            video: b.video.narrow(0, 0, 1),
            masks: b.masks.narrow(0, 0, 1),
            actions: b.actions.narrow(0, 0, 1),
            episodes: b.episodes.into_iter().take(1).collect(),
        };
        let opts = SampleOptions {
            steps,
            seed: 0,
            ..SampleOptions::default()
        };
        let pred = self.predict(&one, &opts)?;
        // [1, 3, T, H, W] x 2 rows -> [3, 2H, T*W] -> [2H, T*W, 3] in 0..255
        let rows = Tensor::cat(&[one.video.to_device(pred.device()), pred], 3); // [1, 3, T, 2H, W]
        let (t, h2, w) = (rows.size()[2], rows.size()[3], rows.size()[4]);
        let grid = rows
            .squeeze_dim(0)
            .permute([2, 1, 3, 0]) // [2H, T, W, 3]
            .reshape([h2, t * w, 3]);
        let bytes = ((grid.to_device(tch::Device::Cpu).to_kind(tch::Kind::Float) + 1.0) * 127.5)
            .round()
            .clamp(0.0, 255.0)
            .to_kind(tch::Kind::Uint8)
            .contiguous();
        let pixels = Vec::<u8>::try_from(&bytes.reshape([-1]))?;
        Ok(Some(((t * w) as u32, h2 as u32, pixels)))
    }

    /// The model's prediction `[B, 3, T, H, W]` in [-1, 1] for `batch`: from
    /// the first frames (posterior mode) and the run's condition (mask
    /// branch, action MLP, or none for a prior), sampled with `opts`.
    /// libtorch's panics (a device's out-of-memory among them) are errors
    /// naming the clips' shapes ([`crate::TrainError::OutOfMemory`]).
    pub fn predict(&self, batch: &Batch, opts: &SampleOptions) -> Result<Tensor> {
        crate::guarded(|| self.predict_unguarded(batch, opts)).map_err(|e| {
            e.on_out_of_memory(
                || {
                    format!(
                        "predicting clips {:?} ([B, 3, T, H, W]) with {} denoising steps",
                        batch.video.size(),
                        opts.steps_run()
                    )
                },
                bridgev2w_world_model::error::PREDICT_MEMORY_ADVICE,
            )
        })
    }

    fn predict_unguarded(&self, batch: &Batch, opts: &SampleOptions) -> Result<Tensor> {
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
            // In the training's autocast: a frozen backbone may be stored
            // in its dtype (see the trainer's setup).
            let z = autocast(model.device(), self.autocast, || {
                sample_latents(&denoiser, &mut scheduler, &img, opts)
            })??;
            let video = model.decode_latents(&z)?.clamp(-1.0, 1.0); // [B, 3, T, H, W]
            Ok(match opts.keep_static_margin_px {
                Some(margin) => keep_static(
                    &video,
                    &batch.first_frames.to_device(video.device()),
                    &batch.masks.to_device(video.device()),
                    margin,
                )?,
                None => video,
            })
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
