//! The objective of one step: the `bridgev2w` and `prior` stages' diffusion, dynamics
//! and flow losses, and the `vae` stage's reconstruction and KL terms.

use super::shard::rank_items;
use super::{check_finite, Losses, Trainer};
use crate::augment::{recolor, ColorDraw};
use crate::config::Stage;
use crate::data::{rng_for, seed_for, Batch};
use crate::decoded_flow::{decoded_flow, FlowBackward};
use crate::flow::flow_weight;
use crate::losses::{
    diffusion_loss, dynamics_loss, motion_weights, predicted_x0, weighted_diffusion_loss,
};
use crate::Result;
use bridgev2w_io::seed::box_muller;
use bridgev2w_torch_ext::{AutocastDevice, AutocastGuard};
use rand::Rng;
use tch::{Kind, Tensor};

/// One draw of `N(mean, std^2)` ([`box_muller`]). The second uniform comes
/// from `rng.gen()`, not `gen_range` as in
/// [`bridgev2w_io::seed::standard_normal`]: the two give different streams,
/// and this one is what the shipped model was trained with.
fn normal(rng: &mut impl Rng, mean: f64, std: f64) -> f64 {
    let u1: f64 = rng.gen_range(f64::MIN_POSITIVE..1.0);
    let u2: f64 = rng.gen();
    mean + std * box_muller(u1, u2)
}

impl Trainer {
    /// The flow loss's weight at step `step`: 0 before `e_switch` epochs, in
    /// the prior stage and with the flow-loss ablation off.
    pub(super) fn flow_weight_at(&self, step: usize) -> f64 {
        let t = &self.cfg.train;
        if self.cfg.ablation.flow_loss && t.stage != Stage::Prior {
            flow_weight(step / self.steps_per_epoch(), t.e_switch, t.lambda_flow)
        } else {
            0.0
        }
    }

    /// The `vae` stage's objective: L1 reconstruction of the clip through a
    /// posterior sample plus `kl_weight` times the per-element KL from N(0, I).
    fn vae_losses(&self, batch: &Batch, step: usize) -> Result<Losses> {
        let t = &self.cfg.train;
        let vae = &self.model.vae;
        let video = if t.color_augment {
            // Per-item draws for the whole batch; this rank keeps its own.
            let rank_world = self.rank_and_world();
            let global_b = batch.video.size()[0] as usize * rank_world.1;
            let mut rng = rng_for(t.seed, step as u64, 7);
            let all: Vec<ColorDraw> = (0..global_b).map(|_| ColorDraw::sample(&mut rng)).collect();
            recolor(&batch.video, &rank_items(all, rank_world))?
        } else {
            batch.video.shallow_clone()
        };
        let post = vae.encode_with_grad(&video)?;
        let z = self.shard_sample(&post, seed_for(t.seed, step as u64, 5))?;
        let recon = vae.decode_with_grad(&z)?;
        let l1 = (recon - video.to_device(z.device()))
            .abs()
            .mean(Kind::Float);
        let (mean, logvar) = (post.mean(), post.logvar());
        let kl = ((mean * mean) + logvar.exp() - 1.0 - logvar).mean(Kind::Float) * 0.5;
        let l1 = if t.inject_nan_at_step.is_some_and(|n| step >= n) {
            l1 * f64::NAN
        } else {
            l1
        };
        let (rv, kv) = (l1.double_value(&[]), kl.double_value(&[]));
        check_finite(step, "reconstruction", rv)?;
        check_finite(step, "kl", kv)?;
        Ok(Losses {
            total: l1 + kl * t.kl_weight,
            diffusion: 0.0,
            dynamics: 0.0,
            flow: 0.0,
            flow_weight: 0.0,
            dropped: false,
            recon: rv,
            kl: kv,
            checkpointed: None,
        })
    }

    /// The objective on `batch` with the random draws of step `step`.
    pub fn losses(&self, batch: &Batch, step: usize) -> Result<Losses> {
        if self.cfg.train.stage == Stage::Vae {
            return self.vae_losses(batch, step);
        }
        let prior = self.cfg.train.stage == Stage::Prior;
        let t = &self.cfg.train;
        let seed = t.seed;
        let s = step as u64;
        tch::manual_seed(seed_for(seed, s, 3) as i64);
        let mut rng = rng_for(seed, s, 4);
        let b = batch.video.size()[0];
        let rank_world = self.rank_and_world();
        // Per-item draws are made for the whole batch; this rank keeps its own.
        let global_b = b * rank_world.1 as i64;
        let model = &self.model;
        // The frozen encoders make the targets and conditions: in f32 even
        // inside an autocast region (a guard with autocast off), so mixed
        // precision changes only the trained networks' forward passes.
        let f32_island = match (self.autocast, AutocastDevice::of(model.device())) {
            (Some(dtype), Some(dev)) => Some(AutocastGuard::new(dev, dtype, false)?),
            _ => None,
        };
        let (z0, image_latents, control) = tch::no_grad(|| -> Result<_> {
            let z0 = self.encode_sampled(&batch.video, seed_for(seed, s, 5))?;
            let mut first = batch.first_frames.shallow_clone();
            if t.image_noise {
                let all: Vec<f32> = (0..global_b)
                    .map(|_| {
                        normal(&mut rng, t.image_noise_log_mean, t.image_noise_log_std).exp() as f32
                    })
                    .collect();
                let sig = rank_items(all, rank_world);
                let sig = Tensor::from_slice(&sig)
                    .view([b, 1, 1, 1])
                    .to_device(first.device());
                first = (&first + self.shard_randn(&first) * sig).clamp(-1.0, 1.0);
            }
            let img = self.image_latents_sampled(&first, seed_for(seed, s, 6), z0.size()[1])?;
            let control = if self.cfg.ablation.mask_action && !prior {
                Some(model.control_latents(&batch.masks, &img)?)
            } else {
                None
            };
            Ok((z0, img, control))
        })?;
        drop(f32_island);
        // The prior is action-free: never conditioned.
        let dropped = rng.gen::<f64>() < t.condition_dropout || prior;
        let n_train = model.scheduler.num_train_timesteps as i64;
        let all: Vec<i64> = (0..global_b).map(|_| rng.gen_range(0..n_train)).collect();
        let ts = rank_items(all, rank_world);
        let timesteps = Tensor::from_slice(&ts).to_device(model.device());
        let noise = self.shard_randn(&z0);
        let x_t = self.scheduler.add_noise(&z0, &noise, &timesteps)?;
        let latent_in = Tensor::cat(&[&x_t, &image_latents], 2);
        let extra = match (&self.action, dropped) {
            (Some(enc), false) => {
                let zs = z0.size(); // [B, t, C, h, w]
                let p = model.transformer.model.config().patch_size;
                enc.residuals(&batch.actions, (zs[3] / p) * (zs[4] / p))?
            }
            _ => Vec::new(),
        };
        let ctrl = if dropped { None } else { control.as_ref() };
        let (v, checkpointed) = if t.gradient_checkpointing {
            let (v, record) = model.velocity_checkpointed(&latent_in, &timesteps, ctrl, &extra)?;
            (v, Some(record))
        } else {
            (
                model.velocity_with_extra(&latent_in, &timesteps, ctrl, &extra)?,
                None,
            )
        };
        let v = v.to_kind(Kind::Float);
        let alpha = self.scheduler.alpha_bar_like(&timesteps, &z0)?;
        let diff = if t.motion_loss_weight > 0.0 {
            let w = motion_weights(
                &batch.masks.to_device(z0.device()),
                &z0.size(),
                t.motion_loss_weight,
            )?;
            weighted_diffusion_loss(&z0, &x_t, &v, &alpha, &w)?
        } else {
            diffusion_loss(&z0, &x_t, &v, &alpha)?
        };
        let diff = if t.inject_nan_at_step.is_some_and(|n| step >= n) {
            diff * f64::NAN
        } else {
            diff
        };
        let diffusion = diff.double_value(&[]);
        check_finite(step, "diffusion", diffusion)?;
        let x0 = predicted_x0(&x_t, &v, &alpha);
        let dynl = dynamics_loss(&x0, &z0, t.dyn_k)?;
        let dynamics = dynl.double_value(&[]);
        check_finite(step, "dynamics", dynamics)?;
        let total = diff + &dynl * t.lambda_dyn;
        let fw = self.flow_weight_at(step);
        let mut flow = 0.0;
        let total = if fw > 0.0 {
            // The decode runs without autograd and the flow loss's gradient
            // is pushed back through it batch by batch, unit by unit with
            // gradient checkpointing (exact, and bounded in memory: see
            // `decoded_flow`).
            let z = model
                .vae
                .unscale_latents(&x0.permute([0, 2, 1, 3, 4])) // [B, C, t, h, w]
                .to_kind(Kind::Float);
            let fl = decoded_flow(
                &model.vae,
                &z,
                &batch.video,
                self.estimator.as_ref(),
                &self.flow_cfg,
                FlowBackward::for_training(t.gradient_checkpointing),
            )?
            .loss;
            flow = fl.double_value(&[]);
            check_finite(step, "flow", flow)?;
            total + fl * fw
        } else {
            total
        };
        Ok(Losses {
            total,
            diffusion,
            dynamics,
            flow,
            flow_weight: fw,
            dropped,
            recon: 0.0,
            kl: 0.0,
            checkpointed,
        })
    }
}
