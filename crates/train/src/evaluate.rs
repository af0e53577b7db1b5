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
use bridgev2w_io::frame::{u8_from_unit, RgbFrame};
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
            grid_dir: None,
            grid_clips: 4,
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

/// `[1, 3, T, H, W]` masks in {-1, 1} to per-frame 0/1 masks.
/// Grid upscaling: each pixel as `GRID_SCALE` x `GRID_SCALE`.
const GRID_SCALE: usize = 2;

/// One clip's row of the grid, per frame: first frame | masks | prediction |
/// ground truth, RGB8, upscaled.
fn grid_row(gt: &[RgbFrame], pred: &[RgbFrame], masks: &[Vec<u8>]) -> Vec<Vec<u8>> {
    use bridgev2w_embodiment::overlay::{mask_rgb, side_by_side, upscale};
    let rgb8 = |f: &RgbFrame| -> Vec<u8> { f.rgb.iter().map(|&v| u8_from_unit(v)).collect() };
    let (w, h) = (gt[0].width, gt[0].height);
    let k = GRID_SCALE;
    let first = upscale(&rgb8(&gt[0]), w, h, k);
    (0..gt.len().min(pred.len()))
        .map(|t| {
            let mask = masks
                .get(t)
                .map(|m| mask_rgb(m))
                .unwrap_or_else(|| vec![0; w * h * 3]);
            let mask = upscale(&mask, w, h, k);
            let (p, g) = (
                upscale(&rgb8(&pred[t]), w, h, k),
                upscale(&rgb8(&gt[t]), w, h, k),
            );
            side_by_side(&[&first, &mask, &p, &g], w * k, h * k)
        })
        .collect()
}

/// The rows stacked top to bottom, frame by frame, as an animated GIF.
fn write_grid(path: &std::path::Path, rows: &[Vec<Vec<u8>>], (w, h): (usize, usize)) -> Result<()> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|e| {
            TrainError::input(dir.display().to_string(), format!("cannot create: {e}"))
        })?;
    }
    let t = rows.iter().map(Vec::len).min().unwrap_or(0);
    let frames: Vec<Vec<u8>> = (0..t)
        .map(|i| rows.iter().flat_map(|r| r[i].iter().copied()).collect())
        .collect();
    let k = GRID_SCALE;
    bridgev2w_embodiment::overlay::write_gif(
        path,
        (4 * w * k) as u32,
        (rows.len() * h * k) as u32,
        &frames,
        4,
    )
    .map_err(|e| TrainError::input(path.display().to_string(), e.to_string()))
}

fn mask_frames(masks: &Tensor) -> Result<Vec<Vec<u8>>> {
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
fn frames(video: &Tensor) -> Result<Vec<RgbFrame>> {
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

/// Scores `trainer`'s model (as loaded or resumed) on `split` of the run's
/// primary dataset.
pub fn evaluate_split(
    trainer: &Trainer,
    split: &str,
    opts: &EvalOptions,
    segmenter: Option<&dyn RobotSegmenter>,
    on_video: &dyn Fn(),
) -> Result<SplitScores> {
    let mut spec = trainer
        .cfg
        .data
        .sources()?
        .into_iter()
        .next()
        .ok_or_else(|| TrainError::input("data", "no dataset"))?;
    spec.split = split.to_string();
    let d = &trainer.data;
    let data = ClipDataset::open_sources(&[spec], d.clip_frames, d.height, d.width, 1)?;
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
    let with_masks = segmenter.filter(|_| data.has_masks());
    let mut grid: Vec<Vec<Vec<u8>>> = Vec::new(); // [clip][frame] -> a row's RGB8 panel strip
    for i in 0..n {
        let batch = data.clips(&[(i, 0)], trainer.model.device())?;
        let pred = trainer.predict(
            &batch,
            &SampleOptions {
                steps: opts.steps,
                guidance_scale: opts.guidance,
                dynamic_cfg: false,
                seed: opts.seed,
                first_frame: opts.first_frame,
                strength: opts.strength,
                ..SampleOptions::default()
            },
        )?;
        let gt = frames(&batch.video)?;
        let pf = frames(&pred)?;
        if opts.grid_dir.is_some() && i < opts.grid_clips {
            grid.push(grid_row(&gt, &pf, &mask_frames(&batch.masks)?));
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
        for (v, psnr, ssim, dynamic) in [
            (&pf, &mut p, &mut s, &mut dp),
            (&copy, &mut bp, &mut bs, &mut dbp),
            (&af, &mut ap, &mut as_, &mut dap),
        ] {
            let score = score_clip(v, &gt_p, region_p).map_err(metric)?;
            psnr.push(score.psnr);
            ssim.push(score.ssim);
            dynamic.extend(score.dynamic_psnr);
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
        write_grid(
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
    })
}
