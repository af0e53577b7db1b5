//! The image-to-video sampling loop (as diffusers' `CogVideoXImageToVideoPipeline`)
//! and the [`WorldModel`] trait that planners and evaluators use.
//!
//! Sampling: Gaussian latents `[B, F, C, h, w]` (seeded), at every inference timestep
//! the noisy latents are concatenated on channels with the first-frame image latents
//! (`[B, F, 2C, h, w]`, the image latent in frame 0, zeros after), the denoiser
//! predicts the velocity, classifier-free guidance mixes the conditional and
//! unconditional predictions `v_u + g (v_c - v_u)` (optionally with CogVideoX's
//! dynamic guidance schedule), and the scheduler steps.

use crate::error::{Result, WorldModelError};
use crate::scheduler::{PredictionType, Scheduler};
use crate::video::{MaskVideo, Video};
use bridgev2w_io::frame::RgbFrame;
use bridgev2w_io::progress::{Progress, Silent};
use tch::{Kind, Tensor};

/// Which side of classifier-free guidance a denoiser call is for.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Guidance {
    /// With the condition (the mask ControlNet branch active).
    Conditional,
    /// Without it (the condition dropped, as in training's condition dropout).
    Unconditional,
}

/// A velocity predictor over `[B, F, 2C, h, w]` inputs (noisy latents ++ image latents).
pub trait Denoiser {
    /// The predicted velocity `[B, F, C, h, w]` at `timestep` `[B]` (int64).
    fn velocity(&self, latent_in: &Tensor, timestep: &Tensor, guidance: Guidance)
        -> Result<Tensor>;
}

/// What the sampler does with the first latent frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FirstFrame {
    /// The model denoises it like every other frame (diffusers' pipeline).
    #[default]
    Generated,
    /// After every step it is replaced by the image latent, noised to the
    /// next step's level (the exact image latent after the last step), so
    /// the later frames attend to a first frame that is right. Meant for
    /// VAEs without time compression, where latent frame 0 is the image alone.
    Replaced,
}

crate::named_enum!(FirstFrame, WorldModelError, WorldModelError::input, "first_frame", {
    Generated => "generated",
    Replaced => "replaced",
});

/// Which frames of a predicted clip are decoded.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DecodeFrames {
    /// Every frame (the video).
    #[default]
    All,
    /// Only the VAE decoder's last latent-frame batch
    /// ([`crate::vae::AutoencoderKLCogVideoX::decode_last_batch`]): the
    /// clip's last frames, for a planner that scores the last one. Exact for
    /// a still clip, an approximation otherwise (a planned action's clip
    /// ends with hold frames); beyond the paper.
    Last,
}

crate::named_enum!(DecodeFrames, WorldModelError, WorldModelError::input, "decode frames", {
    All => "all",
    Last => "last",
});

/// How the noise of a batch is drawn.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BatchNoise {
    /// Every batch element its own noise (diffusers' pipeline with a batch).
    #[default]
    Independent,
    /// One noise draw shared by every batch element (common random numbers):
    /// element `i` gets the noise a batch of one would get with the same seed,
    /// so predictions for different actions differ by the actions alone. This
    /// is what a planner that ranks candidates wants.
    Shared,
}

crate::named_enum!(BatchNoise, WorldModelError, WorldModelError::input, "batch_noise", {
    Independent => "independent",
    Shared => "shared",
});

impl BatchNoise {
    /// Standard normal noise of `shape` `[B, ...]` on `device`, drawn from
    /// libtorch's global CPU generator (as diffusers' `randn_tensor` with a
    /// CPU generator: one seed, the same noise on every device): `B` draws,
    /// or one draw expanded to `B` when shared (the same values as a batch
    /// of one).
    pub fn randn(self, shape: &[i64], kind: Kind, device: tch::Device) -> Tensor {
        let host = (kind, tch::Device::Cpu);
        match (self, shape.split_first()) {
            (Self::Shared, Some((&b, rest))) if b > 1 => {
                let one: Vec<i64> = std::iter::once(1).chain(rest.iter().copied()).collect();
                // [1, ...] -> [B, ...]
                Tensor::randn(one.as_slice(), host)
                    .to_device(device)
                    .expand(shape, false)
                    .contiguous()
            }
            _ => Tensor::randn(shape, host).to_device(device),
        }
    }
}

/// Sampling options.
#[derive(Debug, Clone, PartialEq)]
pub struct SampleOptions {
    /// Inference steps.
    pub steps: usize,
    /// Classifier-free guidance scale (1 = no guidance: one denoiser call per step).
    pub guidance_scale: f64,
    /// CogVideoX's dynamic guidance: `1 + g (1 - cos(pi ((N - t) / N)^5)) / 2`.
    pub dynamic_cfg: bool,
    /// Seed of the initial noise and of the sampler's noise.
    pub seed: u64,
    /// The first latent frame: generated, or replaced by the image latent.
    pub first_frame: FirstFrame,
    /// How a batch's noise is drawn (initial latents, sampler noise and the
    /// first frame's posterior sample).
    pub batch_noise: BatchNoise,
    /// Where sampling starts (in (0, 1]). 1: from pure noise at the first
    /// inference timestep (diffusers' pipeline). `s < 1`: from the first
    /// frame's latent copied to every latent frame and noised to the level of
    /// the inference timestep a fraction `s` from the end, running only the
    /// last `ceil(s * steps)` steps (SDEdit's start, as diffusers' img2img
    /// `strength`): the static scene starts right and only what moves must be
    /// drawn.
    pub strength: f64,
    /// Keep the static scene (beyond the paper; [`crate::static_scene`]):
    /// outside the region the robot has swept in frames `0..=t`, dilated by
    /// this many pixels, frame `t` is the first frame. `None`: every pixel
    /// is the model's (diffusers' pipeline).
    pub keep_static_margin_px: Option<u32>,
}

impl Default for SampleOptions {
    fn default() -> Self {
        Self {
            steps: 50,
            guidance_scale: 6.0,
            dynamic_cfg: false,
            seed: 42,
            first_frame: FirstFrame::Generated,
            batch_noise: BatchNoise::Independent,
            strength: 1.0,
            keep_static_margin_px: None,
        }
    }
}

impl SampleOptions {
    /// Checks the options before any work: at least one step, a finite
    /// guidance scale >= 1, a strength in (0, 1]. (The steps' upper bound is
    /// the scheduler's training timesteps, checked when the chain starts.)
    pub fn validate(&self) -> Result<()> {
        if self.steps == 0 {
            return Err(WorldModelError::input(
                "steps (--steps, plan: --denoise-steps)",
                "0: expected at least 1 denoising step",
            ));
        }
        if !(self.guidance_scale.is_finite() && self.guidance_scale >= 1.0) {
            return Err(WorldModelError::input(
                "guidance_scale (--guidance)",
                format!(
                    "{}: expected a finite number >= 1 (1 = no guidance)",
                    self.guidance_scale
                ),
            ));
        }
        if !(self.strength > 0.0 && self.strength <= 1.0) {
            return Err(WorldModelError::input(
                "strength (--strength)",
                format!("{}: expected a number in (0, 1]", self.strength),
            ));
        }
        Ok(())
    }

    /// The inference steps that run at `strength` (at least one).
    pub fn steps_run(&self) -> usize {
        ((self.strength * self.steps as f64).ceil() as usize).clamp(1, self.steps.max(1))
    }
}

/// Runs the sampling loop: returns the denoised latents `[B, F, C, h, w]`.
/// `image_latents` `[B, F, C, h, w]` are the (scaled) first-frame latents in
/// latent frame 0, the later frames zeros or the same latents again (see
/// [`crate::bridge::ImageConditioning`]).
pub fn sample_latents(
    denoiser: &dyn Denoiser,
    scheduler: &mut Scheduler,
    image_latents: &Tensor,
    opts: &SampleOptions,
) -> Result<Tensor> {
    sample_latents_with_progress(denoiser, scheduler, image_latents, opts, &Silent)
}

/// The stage label that [`sample_latents_with_progress`] reports.
pub const DENOISING: &str = "denoising";

/// [`sample_latents`] reporting its steps to `progress`: one stage
/// ([`DENOISING`]) of as many steps as the scheduler's timesteps, a tick
/// after each step (whatever the guidance's denoiser calls per step), and
/// the stage finished however the loop ends.
pub fn sample_latents_with_progress(
    denoiser: &dyn Denoiser,
    scheduler: &mut Scheduler,
    image_latents: &Tensor,
    opts: &SampleOptions,
    progress: &dyn Progress,
) -> Result<Tensor> {
    opts.validate()?;
    if image_latents.dim() != 5 {
        return Err(WorldModelError::input(
            "image_latents",
            format!("shape {:?}: expected [B, F, C, h, w]", image_latents.size()),
        ));
    }
    if !all_finite(image_latents)? {
        return Err(WorldModelError::NonFinite {
            during: "in the image latents before denoising".into(),
            check: "the first frame's VAE latents (times the VAE's scaling_factor) are not finite: check the VAE's weights and the scaling_factor in its config.json".into(),
        });
    }
    let all_timesteps = scheduler.set_timesteps(opts.steps)?.to_vec();
    let skipped = all_timesteps.len() - opts.steps_run().min(all_timesteps.len());
    scheduler.skip_steps(skipped)?;
    let timesteps = all_timesteps[skipped..].to_vec();
    let (device, kind) = (image_latents.device(), image_latents.kind());
    let shape = image_latents.size();
    let generator_seed = opts.seed as i64;
    tch::manual_seed(generator_seed);
    let mut latents = opts.batch_noise.randn(&shape, Kind::Float, device);
    if skipped > 0 {
        // [B, 1, C, h, w] -> [B, F, C, h, w]: the first frame's latent in every frame,
        // noised to the level of the first timestep that runs.
        let copy = image_latents
            .narrow(1, 0, 1)
            .to_kind(Kind::Float)
            .expand(shape.as_slice(), false)
            .contiguous();
        let ts = Tensor::full([shape[0]], timesteps[0], (Kind::Int64, device));
        latents = scheduler.add_noise(&copy, &latents, &ts)?;
    }
    let mut latents = latents.to_kind(kind);
    let n_train = scheduler.config().num_train_timesteps as f64;
    let batch = shape[0];
    let mut noise = |s: &[i64]| opts.batch_noise.randn(s, Kind::Float, device);
    progress.start(timesteps.len(), DENOISING);
    let _finish = FinishOnDrop(progress);
    for (i, &t) in timesteps.iter().enumerate() {
        // [B, F, C, h, w] ++ [B, F, C, h, w] -> [B, F, 2C, h, w]
        let latent_in = Tensor::cat(&[&latents, image_latents], 2);
        let ts = Tensor::full([batch], t, (Kind::Int64, device));
        let cond = denoiser.velocity(&latent_in, &ts, Guidance::Conditional)?;
        let v = if opts.guidance_scale > 1.0 {
            let uncond = denoiser.velocity(&latent_in, &ts, Guidance::Unconditional)?;
            let g = if opts.dynamic_cfg {
                let frac = (n_train - t as f64) / n_train;
                1.0 + opts.guidance_scale * (1.0 - (std::f64::consts::PI * frac.powf(5.0)).cos())
                    / 2.0
            } else {
                opts.guidance_scale
            };
            &uncond + (cond - &uncond) * g
        } else {
            cond
        };
        if v.size() != shape {
            return Err(WorldModelError::input(
                "denoiser output",
                format!("shape {:?}: expected {shape:?}", v.size()),
            ));
        }
        latents = scheduler
            .step(
                &v.to_kind(Kind::Float),
                &latents.to_kind(Kind::Float),
                &mut noise,
            )?
            .to_kind(kind);
        if !all_finite(&latents)? {
            return Err(diverged(&v, (i, timesteps.len(), t), opts, scheduler));
        }
        if opts.first_frame == FirstFrame::Replaced {
            // [B, 1, C, h, w]: the image latent at the level of the next step.
            let z0 = image_latents.narrow(1, 0, 1).to_kind(Kind::Float);
            let frame0 = match timesteps.get(i + 1) {
                Some(&next) => {
                    let ts = Tensor::full([batch], next, (Kind::Int64, device));
                    scheduler.add_noise(&z0, &noise(&z0.size()), &ts)?
                }
                None => z0,
            };
            // [B, 1, C, h, w] ++ [B, F-1, C, h, w] -> [B, F, C, h, w]
            latents = Tensor::cat(
                &[frame0.to_kind(kind), latents.narrow(1, 1, shape[1] - 1)],
                1,
            );
        }
        progress.tick();
    }
    Ok(latents)
}

/// Whether every value of `x` is finite.
fn all_finite(x: &Tensor) -> Result<bool> {
    Ok(x.f_isfinite()?.f_all()?.int64_value(&[]) != 0)
}

/// The error of latents that became NaN or infinite at denoising step
/// `i` of `n` (timestep `t`): from the denoiser's prediction `v`, or from
/// the scheduler's step of a finite one, with the settings to check.
fn diverged(
    v: &Tensor,
    (i, n, t): (usize, usize, i64),
    opts: &SampleOptions,
    scheduler: &Scheduler,
) -> WorldModelError {
    let during = format!(
        "in the latents after denoising step {} of {n} (timestep {t})",
        i + 1
    );
    let largest = v
        .abs()
        .nan_to_num(f64::INFINITY, None, None)
        .max()
        .double_value(&[]);
    let c = scheduler.config();
    let check = if !largest.is_finite() {
        format!(
            "the denoiser's prediction was not finite: check the model's weights (transformer, ControlNet, LoRA), the ControlNet's conditioning_scale and guidance_scale {}",
            opts.guidance_scale
        )
    } else {
        format!(
            "the denoiser's prediction was finite (largest magnitude {largest:.3e}) but the scheduler's step was not: check guidance_scale {} and the scheduler config (beta_start {}, beta_end {}, snr_shift_scale {}, rescale_betas_zero_snr {}, prediction_type {}); a prediction this large points at the model's weights",
            opts.guidance_scale,
            c.beta_start,
            c.beta_end,
            c.snr_shift_scale,
            c.rescale_betas_zero_snr,
            match c.prediction_type {
                PredictionType::Epsilon => "epsilon",
                PredictionType::Sample => "sample",
                PredictionType::VPrediction => "v_prediction",
            }
        )
    };
    WorldModelError::NonFinite { during, check }
}

/// Finishes a [`Progress`] stage when dropped (an early error included).
struct FinishOnDrop<'a>(&'a dyn Progress);

impl Drop for FinishOnDrop<'_> {
    fn drop(&mut self) {
        self.0.finish();
    }
}

/// Checks that a batch pairs every first frame with one mask sequence.
pub fn check_batch(first_frames: &[RgbFrame], masks: &[MaskVideo]) -> Result<()> {
    if first_frames.len() != masks.len() {
        return Err(WorldModelError::input(
            "predict_batch",
            format!(
                "{} frames but {} mask sequences",
                first_frames.len(),
                masks.len()
            ),
        ));
    }
    Ok(())
}

/// Options of one prediction.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct PredictOptions {
    /// Sampling options.
    pub sample: SampleOptions,
    /// At most this many clips go through the model at once (`None`: a
    /// whole batch at once): a larger batch runs in chunks of this size,
    /// which bounds the device memory of a planner's candidates. With shared
    /// batch noise the results are those of one call; with independent
    /// noise, chunk `k` draws from seed `seed + k`.
    pub max_batch: Option<usize>,
    /// Which frames are decoded: all, or only the last few (a returned
    /// [`crate::video::Video`] then holds those frames alone).
    pub decode_frames: DecodeFrames,
}

/// An action-conditioned world model: from the current frame and the embodiment masks
/// of the actions to the predicted video. Planners, policy evaluation and metrics use
/// this trait, so any model (the diffusion model, a renderer, a cheap stand-in) fits.
pub trait WorldModel {
    /// Frames per predicted clip (the mask sequence length it expects).
    fn clip_frames(&self) -> usize;

    /// `(height, width)` it works at.
    fn resolution(&self) -> (usize, usize);

    /// Predicts the video `[T, H, W, 3]` (frame 0 = the given frame's reconstruction)
    /// caused by the actions whose masks are `masks` `[T, H, W]`.
    fn predict(
        &self,
        first_frame: &RgbFrame,
        masks: &MaskVideo,
        opts: &PredictOptions,
    ) -> Result<Video>;

    /// Several predictions; models that batch override this.
    fn predict_batch(
        &self,
        first_frames: &[RgbFrame],
        masks: &[MaskVideo],
        opts: &PredictOptions,
    ) -> Result<Vec<Video>> {
        check_batch(first_frames, masks)?;
        first_frames
            .iter()
            .zip(masks)
            .map(|(f, m)| self.predict(f, m, opts))
            .collect()
    }

    /// A latent code of an image for goal distances (e.g. the VAE posterior mean).
    fn encode_image(&self, image: &RgbFrame) -> Result<Vec<f32>>;
}

#[cfg(test)]
mod tests;
