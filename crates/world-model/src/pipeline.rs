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
use crate::scheduler::Scheduler;
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
    if !(opts.guidance_scale.is_finite() && opts.guidance_scale >= 1.0) {
        return Err(WorldModelError::input(
            "guidance_scale",
            format!("{}: expected a finite number >= 1", opts.guidance_scale),
        ));
    }
    if image_latents.dim() != 5 {
        return Err(WorldModelError::input(
            "image_latents",
            format!("shape {:?}: expected [B, F, C, h, w]", image_latents.size()),
        ));
    }
    if !(opts.strength > 0.0 && opts.strength <= 1.0) {
        return Err(WorldModelError::input(
            "strength",
            format!("{}: expected a number in (0, 1]", opts.strength),
        ));
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
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::scheduler::{SamplerKind, SchedulerConfig};
    use tch::Device;

    /// A perfect v-predictor for a known clean sample x0: from x_t it recovers the
    /// noise and returns sqrt(a) eps - sqrt(1 - a) x0. Unconditional calls predict
    /// toward zero instead, so guidance is observable.
    struct Oracle {
        x0: Tensor,
        alphas: Vec<f64>,
    }

    impl Denoiser for Oracle {
        fn velocity(
            &self,
            latent_in: &Tensor,
            timestep: &Tensor,
            guidance: Guidance,
        ) -> Result<Tensor> {
            let c = latent_in.size()[2] / 2;
            let xt = latent_in.narrow(2, 0, c);
            let a = self.alphas[timestep.int64_value(&[0]) as usize];
            let target = match guidance {
                Guidance::Conditional => self.x0.shallow_clone(),
                Guidance::Unconditional => self.x0.zeros_like(),
            };
            let eps = (&xt - &target * a.sqrt()) / (1.0 - a).sqrt().max(1e-12);
            Ok(eps * a.sqrt() - target * (1.0 - a).sqrt())
        }
    }

    fn run(kind: SamplerKind, guidance: f64) -> (Tensor, Tensor) {
        let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
        cfg.rescale_betas_zero_snr = false; // keep 1 - a > 0 for the oracle's inversion
        let mut sched = Scheduler::new(cfg).unwrap().with_kind(kind);
        let alphas = sched.schedule().alphas_cumprod.clone();
        tch::manual_seed(3);
        let x0 = Tensor::randn([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
        let oracle = Oracle {
            x0: x0.shallow_clone(),
            alphas,
        };
        let image = Tensor::zeros([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
        let opts = SampleOptions {
            steps: 10,
            guidance_scale: guidance,
            dynamic_cfg: false,
            seed: 7,
            first_frame: FirstFrame::Generated,
            ..SampleOptions::default()
        };
        (
            sample_latents(&oracle, &mut sched, &image, &opts).unwrap(),
            x0,
        )
    }

    #[test]
    fn ddim_and_dpm_with_a_perfect_denoiser_reach_the_clean_sample() {
        for kind in [SamplerKind::Ddim, SamplerKind::Dpm] {
            let (out, x0) = run(kind, 1.0);
            let err = (out - &x0).abs().max().double_value(&[]);
            assert!(err < 1e-3, "{kind:?}: {err}");
        }
    }

    #[test]
    fn guidance_extrapolates_away_from_the_unconditional_prediction() {
        // cond -> x0, uncond -> 0: with scale g the result is g * x0 (velocity is linear
        // in the target and DDIM is linear in the velocity).
        let (out, x0) = run(SamplerKind::Ddim, 3.0);
        let err = (out - &x0 * 3.0).abs().max().double_value(&[]);
        assert!(err < 1e-2, "{err}");
    }

    #[test]
    fn a_replaced_first_frame_ends_as_the_image_latent() {
        let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
        cfg.rescale_betas_zero_snr = false; // keep 1 - a > 0 for the oracle's inversion
        let mut sched = Scheduler::new(cfg).unwrap().with_kind(SamplerKind::Ddim);
        let alphas = sched.schedule().alphas_cumprod.clone();
        tch::manual_seed(5);
        let x0 = Tensor::randn([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
        let oracle = Oracle {
            x0: x0.shallow_clone(),
            alphas,
        };
        // The image latent in frame 0 differs from what the denoiser predicts.
        let image = Tensor::zeros([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
        let _ = image.narrow(1, 0, 1).fill_(0.5);
        let opts = SampleOptions {
            steps: 10,
            guidance_scale: 1.0,
            first_frame: FirstFrame::Replaced,
            ..SampleOptions::default()
        };
        let out = sample_latents(&oracle, &mut sched, &image, &opts).unwrap();
        let first = (out.narrow(1, 0, 1) - 0.5).abs().max().double_value(&[]);
        assert_eq!(first, 0.0);
        let rest = (out.narrow(1, 1, 2) - x0.narrow(1, 1, 2))
            .abs()
            .max()
            .double_value(&[]);
        assert!(rest < 1e-3, "{rest}");
        assert_eq!(
            "replaced".parse::<FirstFrame>().unwrap(),
            FirstFrame::Replaced
        );
        let e = "both".parse::<FirstFrame>().unwrap_err().to_string();
        assert!(e.contains("generated, replaced"), "{e}");
    }

    /// Counts what a [`Progress`] is told.
    #[derive(Default)]
    struct Counter {
        starts: std::sync::Mutex<Vec<(usize, String)>>,
        ticks: std::sync::atomic::AtomicUsize,
        finishes: std::sync::atomic::AtomicUsize,
    }

    impl Progress for Counter {
        fn start(&self, total: usize, label: &str) {
            self.starts.lock().unwrap().push((total, label.to_owned()));
        }
        fn tick(&self) {
            self.ticks.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        }
        fn finish(&self) {
            self.finishes
                .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        }
    }

    #[test]
    fn progress_is_ticked_once_per_step() {
        use std::sync::atomic::Ordering::SeqCst;
        let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
        cfg.rescale_betas_zero_snr = false;
        let alphas = Scheduler::new(cfg.clone())
            .unwrap()
            .schedule()
            .alphas_cumprod
            .clone();
        let oracle = Oracle {
            x0: Tensor::zeros([2, 3, 4, 2, 2], (Kind::Float, Device::Cpu)),
            alphas,
        };
        let image = Tensor::zeros([2, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
        // Guidance (two denoiser calls per step) and a replaced first frame
        // (more noise per step) still tick once per step.
        for (steps, guidance, first_frame) in [
            (7, 1.0, FirstFrame::Generated),
            (3, 4.0, FirstFrame::Replaced),
        ] {
            let mut sched = Scheduler::new(cfg.clone()).unwrap();
            let counter = Counter::default();
            let opts = SampleOptions {
                steps,
                guidance_scale: guidance,
                first_frame,
                ..SampleOptions::default()
            };
            let with =
                sample_latents_with_progress(&oracle, &mut sched, &image, &opts, &counter).unwrap();
            assert_eq!(
                *counter.starts.lock().unwrap(),
                [(steps, DENOISING.to_owned())]
            );
            assert_eq!(counter.ticks.load(SeqCst), steps);
            assert_eq!(counter.finishes.load(SeqCst), 1);
            // Reporting changes nothing.
            let mut sched = Scheduler::new(cfg.clone()).unwrap();
            let without = sample_latents(&oracle, &mut sched, &image, &opts).unwrap();
            assert!(with.equal(&without));
        }
        // A failing loop still finishes its stage.
        let counter = Counter::default();
        let mut sched = Scheduler::new(cfg).unwrap();
        struct Failing;
        impl Denoiser for Failing {
            fn velocity(&self, _: &Tensor, _: &Tensor, _: Guidance) -> Result<Tensor> {
                Err(WorldModelError::input("denoiser", "fails"))
            }
        }
        let opts = SampleOptions {
            steps: 2,
            guidance_scale: 1.0,
            ..SampleOptions::default()
        };
        assert!(
            sample_latents_with_progress(&Failing, &mut sched, &image, &opts, &counter).is_err()
        );
        assert_eq!(counter.ticks.load(SeqCst), 0);
        assert_eq!(counter.finishes.load(SeqCst), 1);
    }

    /// Records the timesteps and the noisy latents it is called with, and
    /// predicts like the oracle.
    struct Recording {
        oracle: Oracle,
        calls: std::sync::Mutex<Vec<(i64, Tensor)>>,
    }

    impl Denoiser for Recording {
        fn velocity(&self, latent_in: &Tensor, timestep: &Tensor, g: Guidance) -> Result<Tensor> {
            let c = latent_in.size()[2] / 2;
            self.calls
                .lock()
                .unwrap()
                .push((timestep.int64_value(&[0]), latent_in.narrow(2, 0, c).copy()));
            self.oracle.velocity(latent_in, timestep, g)
        }
    }

    #[test]
    fn a_partial_strength_starts_from_the_noised_first_frame() {
        let mut cfg = SchedulerConfig::cogvideox_5b_i2v();
        cfg.rescale_betas_zero_snr = false; // keep 1 - a > 0 for the oracle's inversion
        let alphas = Scheduler::new(cfg.clone())
            .unwrap()
            .schedule()
            .alphas_cumprod
            .clone();
        tch::manual_seed(11);
        let x0 = Tensor::randn([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
        // Image latents: frame 0 set, later frames zeros (first-frame conditioning).
        let image = Tensor::zeros([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
        let z0 = Tensor::randn([1, 1, 4, 2, 2], (Kind::Float, Device::Cpu));
        image.narrow(1, 0, 1).copy_(&z0);
        for kind in [SamplerKind::Ddim, SamplerKind::Dpm] {
            let all = Scheduler::new(cfg.clone())
                .unwrap()
                .set_timesteps(10)
                .unwrap()
                .to_vec();
            for (strength, run) in [(0.5, 5), (0.31, 4), (0.01, 1), (1.0, 10)] {
                let rec = Recording {
                    oracle: Oracle {
                        x0: x0.shallow_clone(),
                        alphas: alphas.clone(),
                    },
                    calls: Default::default(),
                };
                let opts = SampleOptions {
                    steps: 10,
                    guidance_scale: 1.0,
                    seed: 9,
                    strength,
                    ..SampleOptions::default()
                };
                assert_eq!(opts.steps_run(), run);
                let mut sched = Scheduler::new(cfg.clone()).unwrap().with_kind(kind);
                let out = sample_latents(&rec, &mut sched, &image, &opts).unwrap();
                let calls = rec.calls.lock().unwrap();
                // Only the last `run` timesteps are denoised ...
                let seen: Vec<i64> = calls.iter().map(|(t, _)| *t).collect();
                assert_eq!(seen, all[10 - run..], "{kind:?} {strength}");
                // ... starting from the image latent in every frame, noised to
                // the first of them (pure noise at strength 1).
                tch::manual_seed(9);
                let eps = Tensor::randn([1, 3, 4, 2, 2], (Kind::Float, Device::Cpu));
                let expected = if run < 10 {
                    let a = alphas[all[10 - run] as usize];
                    z0.expand([1, 3, 4, 2, 2], false) * a.sqrt() + eps * (1.0 - a).sqrt()
                } else {
                    eps
                };
                let start = (&calls[0].1 - expected).abs().max().double_value(&[]);
                assert!(start < 1e-5, "{kind:?} {strength}: {start}");
                // A perfect denoiser still ends at its clean sample.
                let err = (out - &x0).abs().max().double_value(&[]);
                assert!(err < 1e-3, "{kind:?} {strength}: {err}");
            }
        }
        for bad in [0.0, -0.5, 1.5, f64::NAN] {
            let opts = SampleOptions {
                strength: bad,
                ..SampleOptions::default()
            };
            let mut sched = Scheduler::new(cfg.clone()).unwrap();
            let oracle = Oracle {
                x0: x0.shallow_clone(),
                alphas: alphas.clone(),
            };
            let e = sample_latents(&oracle, &mut sched, &image, &opts)
                .unwrap_err()
                .to_string();
            assert!(e.contains("strength") && e.contains("(0, 1]"), "{e}");
        }
    }

    #[test]
    fn bad_guidance_is_an_error() {
        let mut sched = Scheduler::new(SchedulerConfig::cogvideox_2b()).unwrap();
        let oracle = Oracle {
            x0: Tensor::zeros([1], (Kind::Float, Device::Cpu)),
            alphas: vec![],
        };
        let image = Tensor::zeros([1, 1, 2, 1, 1], (Kind::Float, Device::Cpu));
        let opts = SampleOptions {
            guidance_scale: 0.5,
            ..SampleOptions::default()
        };
        assert!(sample_latents(&oracle, &mut sched, &image, &opts).is_err());
    }
}
