//! One predicted clip scored against its ground truth, next to the
//! copy-the-first-frame baseline (the prediction that knows nothing of the
//! motion): the per-clip scores behind `eval-run`'s tables and the demo's
//! check.
//!
//! Only the predicted frames are scored: frame 0 is the model's input (the
//! conditioning image). Copying it is exact, so scoring it would give the
//! baseline one frame at [`crate::video::PSNR_IDENTICAL`] (100 dB) and SSIM
//! 1, which dominates a per-frame mean: with 9 frames, a baseline at 24 dB
//! on frames 1-8 would read 32.5 dB.

use crate::dynamic::{dynamic_region, region_psnr};
use crate::video::{video_psnr, video_ssim};
use crate::{MetricError, Result};
use bridgev2w_io::frame::RgbFrame;

/// PSNR, SSIM and dynamic-region PSNR of one clip (see [`crate::dynamic`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClipScore {
    /// PSNR (dB), per frame then averaged over the clip's frames.
    pub psnr: f64,
    /// SSIM, per frame then averaged.
    pub ssim: f64,
    /// PSNR (dB) on the dynamic region; `None` when nothing moves.
    pub dynamic_psnr: Option<f64>,
}

/// A prediction's [`ClipScore`] and the copy-the-first-frame baseline's on
/// the same ground truth.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ClipComparison {
    /// The prediction.
    pub prediction: ClipScore,
    /// Every frame replaced by the ground truth's first frame.
    pub copy_first_frame: ClipScore,
}

/// Scores `pred` against `gt` (same frame count and size) with a given
/// dynamic region (from [`dynamic_region`] of `gt`).
pub fn score_clip(pred: &[RgbFrame], gt: &[RgbFrame], region: &[Vec<bool>]) -> Result<ClipScore> {
    Ok(ClipScore {
        psnr: video_psnr(pred, gt)?,
        ssim: video_ssim(pred, gt)?,
        dynamic_psnr: region_psnr(pred, gt, region)?,
    })
}

/// The ground truth's first frame repeated for every frame.
pub fn copy_first_frame(gt: &[RgbFrame]) -> Result<Vec<RgbFrame>> {
    let first = gt
        .first()
        .ok_or_else(|| MetricError::Invalid("copy first frame: the clip has no frames".into()))?;
    Ok(vec![first.clone(); gt.len()])
}

/// The frames a model predicts: all but frame 0, its input. An error for a
/// clip of fewer than 2 frames (nothing predicted).
pub fn predicted<T>(clip: &[T]) -> Result<&[T]> {
    match clip {
        [_, rest @ ..] if !rest.is_empty() => Ok(rest),
        _ => Err(MetricError::Invalid(format!(
            "a clip of {} frame(s) has no predicted frames: expected at least 2 (frame 0 is the input)",
            clip.len()
        ))),
    }
}

/// Scores a prediction and the copy-the-first-frame baseline on `gt`, on
/// the predicted frames 1.. (see the module's note).
pub fn compare_with_copy(pred: &[RgbFrame], gt: &[RgbFrame]) -> Result<ClipComparison> {
    let region = dynamic_region(gt)?;
    let copy = copy_first_frame(gt)?;
    let (gt_p, region_p) = (predicted(gt)?, predicted(&region)?);
    Ok(ClipComparison {
        prediction: score_clip(predicted(pred)?, gt_p, region_p)?,
        copy_first_frame: score_clip(predicted(&copy)?, gt_p, region_p)?,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::video::{psnr_from_mse, PSNR_IDENTICAL};

    fn flat(v: f32) -> RgbFrame {
        RgbFrame::new(16, 12, vec![v; 16 * 12 * 3]).unwrap()
    }

    #[test]
    fn the_baseline_is_exact_on_frame_zero_and_blind_to_motion() {
        // Ground truth: a 2x2 square moves right by one pixel a frame.
        let gt: Vec<RgbFrame> = (0..3)
            .map(|t| {
                let mut f = flat(0.0);
                for y in 2..4 {
                    for x in (1 + t)..(3 + t) {
                        for c in 0..3 {
                            f.rgb[(y * 16 + x) * 3 + c] = 1.0;
                        }
                    }
                }
                f
            })
            .collect();
        let perfect = compare_with_copy(&gt, &gt).unwrap();
        assert!(perfect.prediction.psnr > 99.0);
        assert!(perfect.prediction.dynamic_psnr.unwrap() > 99.0);
        assert!((perfect.prediction.ssim - 1.0).abs() < 1e-9);
        // The copy misses the square's motion: frame 1 differs from frame 0
        // in 4 pixels (2 appear, 2 vanish), frame 2 in 8, by 1.0 in every
        // channel. Frame 0, the input, is not scored: it would add a frame
        // at PSNR_IDENTICAL.
        let copy = perfect.copy_first_frame;
        let frame_mse = |px: f64| px * 3.0 / (16.0 * 12.0 * 3.0);
        let expected = (psnr_from_mse(frame_mse(4.0)) + psnr_from_mse(frame_mse(8.0))) / 2.0;
        assert!(copy.psnr < PSNR_IDENTICAL / 3.0);
        assert!(
            (copy.psnr - expected).abs() < 1e-4,
            "{copy:?} vs {expected}"
        );
        assert!(copy.dynamic_psnr.unwrap() < 15.0, "{copy:?}");
        // A static clip has no dynamic region.
        let still = vec![flat(0.5); 3];
        let c = compare_with_copy(&still, &still).unwrap();
        assert_eq!(c.copy_first_frame.dynamic_psnr, None);
        assert!(copy_first_frame(&[]).is_err());
        // One frame: nothing was predicted.
        let e = compare_with_copy(&still[..1], &still[..1])
            .unwrap_err()
            .to_string();
        assert!(e.contains("at least 2"), "{e}");
    }
}
