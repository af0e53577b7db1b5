//! Video-prediction quality of a trained run on a split (paper Tables
//! droid/ablation, in the synthetic world): for the first clip of every
//! episode, the run's model predicts the video from the first frame and the
//! condition (masks, or actions for the `mask_action = false` ablation, or
//! nothing for an action-free prior); PSNR and SSIM against the ground truth,
//! next to the copy-the-first-frame baseline on the same clips; with a robot
//! segmenter ([`robot_segmenter`], fitted on the training split's frames and
//! masks), Mask-IoU of the robot segmented in the predicted frames against
//! the ground-truth masks, and the segmenter's ceiling (its Mask-IoU on the
//! ground-truth frames). The autoencoder's ceiling is scored too: the
//! ground-truth clip encoded (posterior mode) and decoded by the run's VAE,
//! the best any model that predicts latents of this VAE can do.

use crate::data::ClipDataset;
use crate::trainer::Trainer;
use crate::{Result, TrainError};
use bridgev2w_eval::clip::{copy_first_frame, predicted, score_clip};
use bridgev2w_eval::dynamic::dynamic_region;
use bridgev2w_eval::segment::{ColorSegmenter, RobotSegmenter};
use bridgev2w_eval::video::{mean_over_videos, video_mask_iou};
use bridgev2w_io::frame::RgbFrame;
use bridgev2w_world_model::pipeline::{FirstFrame, SampleOptions};
use tch::{Kind, Tensor};

/// Sampling settings of [`evaluate_split`].
#[derive(Debug, Clone, PartialEq)]
pub struct EvalOptions {
    /// Denoising steps.
    pub steps: usize,
    /// Classifier-free guidance scale (1 = off).
    pub guidance: f64,
    /// Sampling seed.
    pub seed: u64,
    /// At most this many videos (0 = all).
    pub max_videos: usize,
    /// The sampler's first latent frame.
    pub first_frame: FirstFrame,
    /// Where sampling starts ([`SampleOptions::strength`]; 1 = pure noise).
    pub strength: f64,
    /// Keep the static scene outside the robot's swept region, this many
    /// pixels around it ([`SampleOptions::keep_static_margin_px`]; `None`: off).
    pub keep_static_margin_px: Option<u32>,
    /// Also write `<grid_dir>/<split>.gif`: the first `grid_clips` clips,
    /// one row each, first frame | masks | prediction | ground truth.
    pub grid_dir: Option<std::path::PathBuf>,
    /// Clips in the grid.
    pub grid_clips: usize,
}

impl Default for EvalOptions {
    fn default() -> Self {
        Self {
            steps: 20,
            guidance: 1.0,
            seed: 0,
            max_videos: 0,
            first_frame: FirstFrame::Generated,
            strength: 1.0,
            keep_static_margin_px: None,
            grid_dir: None,
            grid_clips: 4,
        }
    }
}

impl EvalOptions {
    /// The sampler's settings.
    pub fn sample_options(&self) -> SampleOptions {
        SampleOptions {
            steps: self.steps,
            guidance_scale: self.guidance,
            dynamic_cfg: false,
            seed: self.seed,
            first_frame: self.first_frame,
            strength: self.strength,
            keep_static_margin_px: self.keep_static_margin_px,
            ..SampleOptions::default()
        }
    }
}

/// Scores of one split, each over the predicted frames 1.. of every clip
/// (frame 0 is the model's input: see [`bridgev2w_eval::clip`]).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct SplitScores {
    /// Split name.
    pub split: String,
    /// Videos scored.
    pub videos: usize,
    /// Mean PSNR (dB) of the predictions.
    pub psnr: f64,
    /// Mean SSIM of the predictions.
    pub ssim: f64,
    /// Mean PSNR of the predictions on the dynamic region
    /// ([`bridgev2w_eval::dynamic`]), over the videos that have one.
    pub dynamic_psnr: Option<f64>,
    /// Mean PSNR of the copy-the-first-frame baseline.
    pub baseline_psnr: f64,
    /// Mean dynamic-region PSNR of the baseline.
    pub baseline_dynamic_psnr: Option<f64>,
    /// Mean SSIM of the baseline.
    pub baseline_ssim: f64,
    /// Mean Mask-IoU (robot segmented in the predictions vs. ground-truth
    /// masks), when a segmenter was given and the split has masks.
    pub mask_iou: Option<f64>,
    /// Mask-IoU of the baseline (the first frame's robot, held still).
    pub baseline_mask_iou: Option<f64>,
    /// Mask-IoU of the segmenter on the ground-truth frames: the ceiling.
    pub segmenter_mask_iou: Option<f64>,
    /// Mean PSNR of the ground truth through the VAE (encode, posterior
    /// mode, decode): the autoencoder's ceiling.
    pub autoencoder_psnr: f64,
    /// Mean SSIM of the ground truth through the VAE.
    pub autoencoder_ssim: f64,
    /// Mean dynamic-region PSNR of the ground truth through the VAE.
    pub autoencoder_dynamic_psnr: Option<f64>,
    /// Mask-IoU of the robot segmented in the VAE's reconstructions.
    pub autoencoder_mask_iou: Option<f64>,
    /// PSNR (dB) of each predicted frame (1, 2, ..), averaged over the videos.
    pub psnr_per_frame: Vec<f64>,
    /// The baseline's PSNR of each predicted frame, averaged over the videos.
    pub baseline_psnr_per_frame: Vec<f64>,
    /// The VAE ceiling's PSNR of each predicted frame, averaged over the videos.
    pub autoencoder_psnr_per_frame: Vec<f64>,
}

/// Bits per channel of the colour segmenter (32 levels).
const SEGMENTER_BITS: u32 = 5;

/// A colour segmenter fitted on every frame and mask of `data` (resized to
/// its clip size); `None` when no episode has masks. See also
/// [`crate::segmenter::CnnSegmenter`], the learned one.
pub fn color_segmenter(data: &ClipDataset) -> Result<Option<ColorSegmenter>> {
    let metric = |e: bridgev2w_eval::MetricError| TrainError::input("segmenter", e.to_string());
    let mut seg = ColorSegmenter::new(SEGMENTER_BITS).map_err(metric)?;
    let frames = data.masked_frames();
    for f in &frames {
        let frame = RgbFrame::from_rgb8(f.width, f.height, f.rgb).map_err(|e| metric(e.into()))?;
        seg.observe(&frame, f.mask).map_err(metric)?;
    }
    Ok((!frames.is_empty()).then_some(seg))
}

/// `[1, 3, T, H, W]` coded masks to per-frame 0/1 masks (channel 0 is the
/// silhouette in every [`bridgev2w_world_model::mask_coding::MaskCoding`]).
pub(crate) fn mask_frames(masks: &Tensor) -> Result<Vec<Vec<u8>>> {
    // [1, 3, T, H, W] -> [T, H, W] (channel 0: robot)
    let m = masks
        .get(0)
        .get(0)
        .gt(0.0)
        .to_kind(Kind::Uint8)
        .contiguous();
    let t = m.size()[0];
    (0..t)
        .map(|i| Ok(Vec::<u8>::try_from(m.get(i).flatten(0, -1))?))
        .collect()
}

/// `[1, 3, T, H, W]` in [-1, 1] to metric frames in [0, 1].
pub(crate) fn frames(video: &Tensor) -> Result<Vec<RgbFrame>> {
    let v = ((video.to_kind(Kind::Float).clamp(-1.0, 1.0) + 1.0) / 2.0)
        .squeeze_dim(0)
        .permute([1, 2, 3, 0]) // [3, T, H, W] -> [T, H, W, 3]
        .contiguous();
    let s = v.size();
    let (t, h, w) = (s[0] as usize, s[1] as usize, s[2] as usize);
    let data: Vec<f32> = Vec::<f32>::try_from(v.flatten(0, -1))?;
    data.chunks(h * w * 3)
        .take(t)
        .map(|c| {
            RgbFrame::new(w, h, c.to_vec())
                .map_err(|e| TrainError::input("prediction", e.to_string()))
        })
        .collect()
}

/// `split` of the run's primary dataset, as clips of the run's size.
pub(crate) fn split_data(trainer: &Trainer, split: &str) -> Result<ClipDataset> {
    let mut spec = trainer
        .cfg
        .data
        .sources()?
        .into_iter()
        .next()
        .ok_or_else(|| TrainError::input("data", "no dataset"))?;
    spec.split = split.to_string();
    let d = &trainer.data;
    let mut split = ClipDataset::open_sources(&[spec], d.clip_frames, d.height, d.width, 1)?;
    split.set_mask_coding(d.mask_coding)?;
    Ok(split)
}

/// Scores `trainer`'s model (as loaded or resumed) on `split` of the run's
/// primary dataset.
pub fn evaluate_split(
    trainer: &Trainer,
    split: &str,
    opts: &EvalOptions,
    segmenter: Option<&dyn RobotSegmenter>,
    on_video: &dyn Fn(),
) -> Result<SplitScores> {
    if opts.grid_dir.is_some() {
        bridgev2w_io::memory::at_most(
            "--grid-clips",
            opts.grid_clips as u64,
            crate::grid::MAX_GRID_CLIPS as u64,
            "clips",
        )?;
    }
    let data = split_data(trainer, split)?;
    let d = &trainer.data;
    let n = match opts.max_videos {
        0 => data.episodes.len(),
        m => m.min(data.episodes.len()),
    };
    let metric = |e: bridgev2w_eval::MetricError| TrainError::input("metrics", e.to_string());
    let (mut p, mut s, mut bp, mut bs) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
    let (mut iou, mut biou, mut ceil) = (Vec::new(), Vec::new(), Vec::new());
    let (mut ap, mut as_, mut aiou) = (Vec::new(), Vec::new(), Vec::new());
    // Dynamic-region PSNR of the prediction, the baseline and the VAE.
    let (mut dp, mut dbp, mut dap) = (Vec::new(), Vec::new(), Vec::new());
    // Sums over videos of each predicted frame's PSNR: prediction, baseline, VAE.
    let mut per_frame: [Vec<f64>; 3] = Default::default();
    let with_masks = segmenter.filter(|_| data.has_masks());
    let mut grid: Vec<crate::grid::image::GridRow> = Vec::new();
    for i in 0..n {
        let batch = data.clips(&[(i, 0)], trainer.model.device())?;
        let pred = trainer.predict(&batch, &opts.sample_options())?;
        let gt = frames(&batch.video)?;
        let pf = frames(&pred)?;
        if opts.grid_dir.is_some() && i < opts.grid_clips {
            grid.push(crate::grid::image::grid_row(
                &gt,
                &[&pf],
                &mask_frames(&batch.masks)?,
            ));
        }
        let copy = copy_first_frame(&gt).map_err(metric)?;
        let model = &trainer.model;
        let recon = tch::no_grad(|| -> Result<Tensor> {
            let z = model.encode_latents(&batch.video, None)?; // [1, t, C, h, w]
            Ok(model.decode_latents(&z)?)
        })?;
        let af = frames(&recon)?;
        let region = dynamic_region(&gt).map_err(metric)?;
        // Scored on the predicted frames 1.. (frame 0 is the input; see
        // `bridgev2w_eval::clip`).
        let later = |v: &[RgbFrame]| -> Result<Vec<RgbFrame>> {
            Ok(predicted(v).map_err(metric)?.to_vec())
        };
        let (gt_p, region_p) = (later(&gt)?, predicted(&region).map_err(metric)?);
        let (pf, copy, af) = (later(&pf)?, later(&copy)?, later(&af)?);
        for ((v, psnr, ssim, dynamic), sums) in [
            (&pf, &mut p, &mut s, &mut dp),
            (&copy, &mut bp, &mut bs, &mut dbp),
            (&af, &mut ap, &mut as_, &mut dap),
        ]
        .into_iter()
        .zip(&mut per_frame)
        {
            let score = score_clip(v, &gt_p, region_p).map_err(metric)?;
            psnr.push(score.psnr);
            ssim.push(score.ssim);
            dynamic.extend(score.dynamic_psnr);
            add_frame_psnr(sums, v, &gt_p).map_err(metric)?;
        }
        if let Some(seg) = with_masks {
            let gt_masks = mask_frames(&batch.masks)?;
            let gt_masks = predicted(&gt_masks).map_err(metric)?;
            let segment = |v: &[RgbFrame]| {
                v.iter()
                    .map(|f| seg.segment(f))
                    .collect::<std::result::Result<Vec<_>, _>>()
                    .map_err(metric)
            };
            iou.push(video_mask_iou(&segment(&pf)?, gt_masks).map_err(metric)?);
            biou.push(video_mask_iou(&segment(&copy)?, gt_masks).map_err(metric)?);
            ceil.push(video_mask_iou(&segment(&gt_p)?, gt_masks).map_err(metric)?);
            aiou.push(video_mask_iou(&segment(&af)?, gt_masks).map_err(metric)?);
        }
        on_video();
    }
    if let (Some(dir), false) = (&opts.grid_dir, grid.is_empty()) {
        crate::grid::image::write_grid(
            &dir.join(format!("{split}.gif")),
            &grid,
            (d.width, d.height),
        )?;
    }
    let mean = |v: &[f64]| mean_over_videos(v).map_err(metric);
    let opt_mean = |v: &[f64]| -> Result<Option<f64>> {
        if v.is_empty() {
            Ok(None)
        } else {
            mean(v).map(Some)
        }
    };
    let [psnr_per_frame, baseline_psnr_per_frame, autoencoder_psnr_per_frame] =
        per_frame.map(|sums| sums.iter().map(|v| v / n.max(1) as f64).collect());
    Ok(SplitScores {
        split: split.to_string(),
        videos: n,
        psnr: mean(&p)?,
        dynamic_psnr: opt_mean(&dp)?,
        ssim: mean(&s)?,
        baseline_psnr: mean(&bp)?,
        baseline_dynamic_psnr: opt_mean(&dbp)?,
        baseline_ssim: mean(&bs)?,
        mask_iou: opt_mean(&iou)?,
        baseline_mask_iou: opt_mean(&biou)?,
        segmenter_mask_iou: opt_mean(&ceil)?,
        autoencoder_psnr: mean(&ap)?,
        autoencoder_ssim: mean(&as_)?,
        autoencoder_dynamic_psnr: opt_mean(&dap)?,
        autoencoder_mask_iou: opt_mean(&aiou)?,
        psnr_per_frame,
        baseline_psnr_per_frame,
        autoencoder_psnr_per_frame,
    })
}

/// Adds each frame's PSNR of `video` against `gt` to `sums` (grown to the
/// clip's length on the first video).
fn add_frame_psnr(
    sums: &mut Vec<f64>,
    video: &[RgbFrame],
    gt: &[RgbFrame],
) -> std::result::Result<(), bridgev2w_eval::MetricError> {
    if sums.len() < video.len() {
        sums.resize(video.len(), 0.0);
    }
    for ((sum, v), g) in sums.iter_mut().zip(video).zip(gt) {
        *sum += bridgev2w_eval::video::psnr(v, g)?;
    }
    Ok(())
}
