//! Prediction with [`BridgeV2W`]: the sampling loop with the mask branch
//! ([`BridgeV2W::sample`]), batch prediction with progress
//! ([`BridgeV2W::predict_batch_with_progress`]) and the [`WorldModel`] impl.
//!
//! Per batch, the first frames are encoded once (a frame that every item
//! shares: once in all, its posterior expanded to the batch) and the prompt
//! embedding is the model's, computed when it was loaded and expanded (a
//! view) to the batch in every transformer call.

use super::BridgeV2W;
use crate::error::{Result, WorldModelError};
use crate::pipeline::{
    check_batch, sample_latents_with_progress, BatchNoise, DecodeFrames, Denoiser, Guidance,
    PredictOptions, WorldModel,
};
use crate::scheduler::Scheduler;
use crate::static_scene::keep_static;
use crate::video::{image_to_tensor, MaskVideo, Video};
use bridgev2w_io::frame::RgbFrame;
use bridgev2w_io::progress::{Progress, Silent};
use tch::{Device, Kind, Tensor};

impl BridgeV2W {
    /// Samples a clip's latents `[B, t, C, h, w]` from image latents and control latents.
    pub fn sample(
        &self,
        image_latents: &Tensor,
        control: &Tensor,
        opts: &PredictOptions,
    ) -> Result<Tensor> {
        self.sample_with_progress(image_latents, control, opts, &Silent)
    }

    /// [`Self::sample`] reporting its denoising steps to `progress` (see
    /// [`sample_latents_with_progress`]).
    pub fn sample_with_progress(
        &self,
        image_latents: &Tensor,
        control: &Tensor,
        opts: &PredictOptions,
        progress: &dyn Progress,
    ) -> Result<Tensor> {
        let mut scheduler = Scheduler::new(self.scheduler.clone())?;
        let denoiser = Conditioned {
            model: self,
            control,
        };
        tch::no_grad(|| {
            sample_latents_with_progress(
                &denoiser,
                &mut scheduler,
                image_latents,
                &opts.sample,
                progress,
            )
        })
    }

    /// [`WorldModel::predict_batch`] reporting the denoising steps to
    /// `progress` (one stage per call). One batch: the first frames are
    /// encoded in one VAE call (once when they are all the same frame), the
    /// masks in one, and the batch is denoised and decoded together; with
    /// [`crate::pipeline::BatchNoise::Shared`] every item is the video a
    /// batch of one with the same seed gives.
    pub fn predict_batch_with_progress(
        &self,
        first_frames: &[RgbFrame],
        masks: &[MaskVideo],
        opts: &PredictOptions,
        progress: &dyn Progress,
    ) -> Result<Vec<Video>> {
        check_batch(first_frames, masks)?;
        if first_frames.is_empty() {
            return Err(WorldModelError::input(
                "predict_batch",
                "no frames: expected at least one (frame, masks) pair",
            ));
        }
        if let Some(max) = opts.max_batch {
            super::check_predict_batch("max_batch", max)?;
            if first_frames.len() > max {
                return self.predict_in_chunks(first_frames, masks, opts, max, progress);
            }
        }
        // A batch beyond the machine's memory is refused before it runs;
        // libtorch's ops panic on a device's out-of-memory: caught and
        // reported with what ran.
        self.check_predict_memory(first_frames.len())?;
        crate::error::guarded(|| self.predict_batch_at_once(first_frames, masks, opts, progress))
            .map_err(|e| {
                e.on_out_of_memory(
                    || self.describe_batch(first_frames.len(), opts),
                    crate::error::PREDICT_MEMORY_ADVICE,
                )
            })
    }

    /// What a prediction of `clips` clips runs, for error messages.
    fn describe_batch(&self, clips: usize, opts: &PredictOptions) -> String {
        format!(
            "predicting {clips} clip(s) of {} frames at {}x{} ({:?} on {:?}, {} denoising steps, guidance {})",
            self.cfg.frames,
            self.cfg.height,
            self.cfg.width,
            self.kind,
            self.device,
            opts.sample.steps_run(),
            opts.sample.guidance_scale
        )
    }

    /// [`Self::predict_batch_with_progress`] for one chunk.
    fn predict_batch_at_once(
        &self,
        first_frames: &[RgbFrame],
        masks: &[MaskVideo],
        opts: &PredictOptions,
        progress: &dyn Progress,
    ) -> Result<Vec<Video>> {
        let _guard = tch::no_grad_guard();
        if opts.decode_frames == DecodeFrames::Last && opts.sample.keep_static_margin_px.is_some() {
            return Err(WorldModelError::input(
                "decode_frames",
                "last with keep_static: keeping the static scene needs every frame decoded (decode all)",
            ));
        }
        let mut mask_videos = Vec::with_capacity(masks.len());
        for (f, m) in first_frames.iter().zip(masks) {
            self.check_inputs(f, m)?;
            let coding = self.cfg.mask_coding;
            mask_videos.push(m.to_tensor(coding, Device::Cpu, Kind::Float)?); // [1, 3, T, H, W]
        }
        let mask_videos = Tensor::cat(&mask_videos, 0); // [B, 3, T, H, W]
        let first = first_frames
            .iter()
            .map(|f| image_to_tensor(f, Device::Cpu, Kind::Float)) // [1, 3, H, W]
            .collect::<Result<Vec<_>>>()?;
        let first = Tensor::cat(&first, 0); // [B, 3, H, W]
        let image_latents = self.batch_image_latents(first_frames, &first, opts)?;
        let control = self.control_latents(&mask_videos, &image_latents)?;
        let latents = self.sample_with_progress(&image_latents, &control, opts, progress)?;
        let videos = match opts.decode_frames {
            DecodeFrames::All => self.decode_latents(&latents)?, // [B, 3, T, H, W]
            DecodeFrames::Last => self.decode_latents_last(&latents)?, // [B, 3, T', H, W]
        };
        let videos = match opts.sample.keep_static_margin_px {
            Some(margin) => {
                let first = first.to_device(videos.device()); // [B, 3, H, W]
                let masks = mask_videos.to_device(videos.device());
                keep_static(&videos, &first, &masks, margin)?
            }
            None => videos,
        };
        (0..videos.size()[0])
            .map(|i| Video::from_tensor(&videos.get(i)))
            .collect()
    }

    /// [`Self::predict_batch_with_progress`] in chunks of at most `max`
    /// clips; chunk `k` draws independent noise from seed `seed + k`.
    fn predict_in_chunks(
        &self,
        first_frames: &[RgbFrame],
        masks: &[MaskVideo],
        opts: &PredictOptions,
        max: usize,
        progress: &dyn Progress,
    ) -> Result<Vec<Video>> {
        let mut videos = Vec::with_capacity(first_frames.len());
        for (k, (frames, masks)) in first_frames.chunks(max).zip(masks.chunks(max)).enumerate() {
            let mut chunk = opts.clone();
            chunk.max_batch = None;
            if chunk.sample.batch_noise == BatchNoise::Independent {
                chunk.sample.seed = opts.sample.seed.wrapping_add(k as u64);
            }
            videos.extend(self.predict_batch_with_progress(frames, masks, &chunk, progress)?);
        }
        Ok(videos)
    }

    /// The image latents `[B, t, C, h, w]` of a batch's first frames
    /// (`images`: the same frames as a tensor `[B, 3, H, W]`), the posterior
    /// sampled with the options' seed and batch noise. A frame that every
    /// item shares is encoded once and its posterior expanded: the same
    /// latents as encoding it `B` times.
    fn batch_image_latents(
        &self,
        first_frames: &[RgbFrame],
        images: &Tensor,
        opts: &PredictOptions,
    ) -> Result<Tensor> {
        let b = first_frames.len();
        let post = match first_frames.split_first() {
            Some((first, rest)) if rest.iter().all(|f| f == first) => {
                // [1, 3, H, W] -> [1, 3, 1, H, W]
                let x = images.narrow(0, 0, 1).unsqueeze(2);
                self.vae.encode(&x)?.repeat_batch(b as i64)? // [B, C, 1, h, w]
            }
            // [B, 3, H, W] -> [B, 3, 1, H, W]
            _ => self.vae.encode(&images.unsqueeze(2))?,
        };
        let z = self.posterior_latents(&post, Some(opts.sample.seed), opts.sample.batch_noise)?;
        let (t, _, _) = self.latent_geometry();
        Ok(self.cfg.image_conditioning.expand(&z, t)) // [B, t, C, h, w]
    }

    fn check_inputs(&self, first_frame: &RgbFrame, masks: &MaskVideo) -> Result<()> {
        let (h, w, t) = (self.cfg.height, self.cfg.width, self.cfg.frames);
        if (first_frame.height, first_frame.width) != (h, w) {
            return Err(WorldModelError::input(
                "first_frame",
                format!(
                    "{}x{} (HxW): the model works at {h}x{w}",
                    first_frame.height, first_frame.width
                ),
            ));
        }
        if (masks.frames, masks.height, masks.width) != (t, h, w) {
            return Err(WorldModelError::input(
                "masks",
                format!(
                    "[{}, {}, {}]: expected [{t}, {h}, {w}] (frames, height, width)",
                    masks.frames, masks.height, masks.width
                ),
            ));
        }
        self.cfg.mask_coding.check_values(&masks.data, "masks")
    }
}

/// The model with a fixed branch input: conditional = branch on, unconditional
/// = branch off (as training's condition dropout).
struct Conditioned<'a> {
    model: &'a BridgeV2W,
    control: &'a Tensor,
}

impl Denoiser for Conditioned<'_> {
    fn velocity(
        &self,
        latent_in: &Tensor,
        timestep: &Tensor,
        guidance: Guidance,
    ) -> Result<Tensor> {
        let control = match guidance {
            Guidance::Conditional => Some(self.control),
            Guidance::Unconditional => None,
        };
        self.model.velocity_with(latent_in, timestep, control)
    }
}

impl WorldModel for BridgeV2W {
    fn clip_frames(&self) -> usize {
        self.cfg.frames
    }

    fn resolution(&self) -> (usize, usize) {
        (self.cfg.height, self.cfg.width)
    }

    fn predict(
        &self,
        first_frame: &RgbFrame,
        masks: &MaskVideo,
        opts: &PredictOptions,
    ) -> Result<Video> {
        Ok(self
            .predict_batch(
                std::slice::from_ref(first_frame),
                std::slice::from_ref(masks),
                opts,
            )?
            .remove(0))
    }

    fn predict_batch(
        &self,
        first_frames: &[RgbFrame],
        masks: &[MaskVideo],
        opts: &PredictOptions,
    ) -> Result<Vec<Video>> {
        self.predict_batch_with_progress(first_frames, masks, opts, &Silent)
    }

    fn encode_image(&self, image: &RgbFrame) -> Result<Vec<f32>> {
        // As a prediction: an op's panic (a device's out-of-memory) is an
        // error naming what ran.
        crate::error::guarded(|| {
            let x = image_to_tensor(image, Device::Cpu, Kind::Float)?.unsqueeze(2); // [1, 3, 1, H, W]
            let z = self.vae.encode(&x)?.mode();
            Ok(Vec::<f32>::try_from(
                &z.to_kind(Kind::Float).to_device(Device::Cpu).flatten(0, -1),
            )?)
        })
        .map_err(|e| {
            e.on_out_of_memory(
                || {
                    format!(
                        "encoding a {}x{} image with the VAE ({:?} on {:?})",
                        image.height, image.width, self.kind, self.device
                    )
                },
                crate::error::PREDICT_MEMORY_ADVICE,
            )
        })
    }
}
