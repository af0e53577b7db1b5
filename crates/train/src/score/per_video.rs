//! The frame metrics of one video of [`crate::score`]: PSNR and SSIM of the
//! predicted frames against the ground truth, and Mask-IoU of the predicted
//! robot masks against the ground-truth masks, each averaged over frames.

use super::error::{invalid, Result, ScoreError};
use super::files::{check_numbers, frame_files, load_frames, read_mask};
use super::{ScoreOptions, VideoMetric};
use bridgev2w_eval::video::{mask_iou, psnr, ssim};
use bridgev2w_io::frame::RgbFrame;
use std::path::PathBuf;

/// Per-video values of the frame metrics (`None`: not asked for, or no masks).
#[derive(Debug, Default, Clone, PartialEq)]
pub struct VideoScores {
    /// Mean PSNR (dB) over the frames.
    pub psnr: Option<f64>,
    /// Mean SSIM over the frames.
    pub ssim: Option<f64>,
    /// Mean Mask-IoU over the frames.
    pub mask_iou: Option<f64>,
}

/// The frame metrics of video `name` that `opts` asks for; frames and
/// masks are paired by frame number.
pub fn score_video(opts: &ScoreOptions, name: &str) -> Result<VideoScores> {
    let (want_psnr, want_ssim) = (opts.wants(VideoMetric::Psnr), opts.wants(VideoMetric::Ssim));
    let mut s = VideoScores::default();
    if want_psnr || want_ssim {
        let pred = load_frames(&opts.pred, name)?;
        let gt = load_frames(&opts.gt, name)?;
        let numbers = |v: &[(u64, RgbFrame)]| v.iter().map(|f| f.0).collect::<Vec<_>>();
        check_numbers(name, "frames", &numbers(&pred), &numbers(&gt))?;
        let (mut sum_psnr, mut sum_ssim) = (0.0, 0.0);
        for ((i, fp), (_, fg)) in pred.iter().zip(&gt) {
            if (fp.width, fp.height) != (fg.width, fg.height) {
                return invalid!(
                    "video \"{name}\", frame {i}: predicted {}x{} vs ground truth {}x{}: resolutions must match",
                    fp.width, fp.height, fg.width, fg.height
                );
            }
            if want_psnr {
                sum_psnr += psnr(fp, fg)?;
            }
            if want_ssim {
                sum_ssim += ssim(fp, fg).map_err(|source| ScoreError::MetricAt {
                    context: format!("video \"{name}\", frame {i}"),
                    source,
                })?;
            }
        }
        let n = pred.len() as f64;
        s.psnr = want_psnr.then_some(sum_psnr / n);
        s.ssim = want_ssim.then_some(sum_ssim / n);
    }
    if let (true, Some(masks)) = (opts.wants(VideoMetric::MaskIou), &opts.masks) {
        let pred = frame_files(&masks.pred.join(name))?;
        let gt = frame_files(&masks.gt.join(name))?;
        let numbers = |v: &[(u64, PathBuf)]| v.iter().map(|f| f.0).collect::<Vec<_>>();
        check_numbers(name, "masks", &numbers(&pred), &numbers(&gt))?;
        let mut sum = 0.0;
        for ((i, p), (_, g)) in pred.iter().zip(&gt) {
            let ((wp, hp, vp), (wg, hg, vg)) = (read_mask(p)?, read_mask(g)?);
            if (wp, hp) != (wg, hg) {
                return invalid!("video \"{name}\", mask {i}: predicted {wp}x{hp} vs ground truth {wg}x{hg}: resolutions must match");
            }
            sum += mask_iou(&vp, &vg)?;
        }
        s.mask_iou = Some(sum / pred.len() as f64);
    }
    Ok(s)
}
