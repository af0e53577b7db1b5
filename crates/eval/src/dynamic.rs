//! PSNR on the *dynamic region* of a clip: the pixels that the motion
//! changes, where a copy of the first frame knows nothing.
//!
//! Definition (one for the whole project): in frame `t >= 1` of the ground
//! truth, a pixel is dynamic when any of its channels differs from the same
//! pixel of the ground-truth first frame by more than
//! [`DYNAMIC_THRESHOLD`] (on `[0, 1]` data), and every pixel within
//! [`DYNAMIC_DILATE_PX`] pixels (a square, Chebyshev distance) of such a
//! pixel is dynamic too. The robot's moving links, the objects it moves and
//! the shadows they cast are all in it; static background is not. The
//! region's PSNR pools the squared errors of every dynamic pixel (all three
//! channels) of frames `1..T` into one MSE, so frames with larger motion
//! weigh more, and `20 log10(1 / sqrt(mse))`. Frame 0 (the given image) and a
//! clip without motion have no dynamic pixels; such a clip has no score.

use crate::video::psnr_from_mse;
use crate::{MetricError, Result};
use bridgev2w_io::frame::RgbFrame;

/// Per-channel absolute difference from the first frame above which a pixel
/// is dynamic (about 8 levels of 255: above the video codec's noise).
pub const DYNAMIC_THRESHOLD: f32 = 8.0 / 255.0;
/// Dilation of the dynamic pixels, pixels (Chebyshev radius).
pub const DYNAMIC_DILATE_PX: usize = 2;

/// The dynamic region of a ground-truth clip: one `width * height` mask per
/// frame (frame 0's is empty), see the module's definition.
pub fn dynamic_region(gt: &[RgbFrame]) -> Result<Vec<Vec<bool>>> {
    let Some(first) = gt.first() else {
        return Err(MetricError::Invalid(
            "dynamic region: the clip has no frames".into(),
        ));
    };
    let (w, h) = (first.width, first.height);
    let mut out = Vec::with_capacity(gt.len());
    out.push(vec![false; w * h]);
    for (t, f) in gt.iter().enumerate().skip(1) {
        if (f.width, f.height) != (w, h) {
            return Err(MetricError::ShapeMismatch {
                what: format!("dynamic region: frame {t} against frame 0"),
                left: format!("{}x{}", f.width, f.height),
                right: format!("{w}x{h}"),
            });
        }
        let changed: Vec<bool> = f
            .rgb
            .chunks_exact(3)
            .zip(first.rgb.chunks_exact(3))
            .map(|(a, b)| {
                a.iter()
                    .zip(b)
                    .any(|(x, y)| (x - y).abs() > DYNAMIC_THRESHOLD)
            })
            .collect();
        out.push(dilate(&changed, w, h, DYNAMIC_DILATE_PX));
    }
    Ok(out)
}

/// Square (Chebyshev) dilation of a `w * h` mask by `r` pixels, separably.
fn dilate(mask: &[bool], w: usize, h: usize, r: usize) -> Vec<bool> {
    let mut rows = vec![false; w * h];
    for y in 0..h {
        for x in 0..w {
            let (x0, x1) = (x.saturating_sub(r), (x + r).min(w - 1));
            rows[y * w + x] = (x0..=x1).any(|i| mask[y * w + i]);
        }
    }
    let mut out = vec![false; w * h];
    for y in 0..h {
        let (y0, y1) = (y.saturating_sub(r), (y + r).min(h - 1));
        for x in 0..w {
            out[y * w + x] = (y0..=y1).any(|j| rows[j * w + x]);
        }
    }
    out
}

/// PSNR of `pred` against `gt` on `region` (one mask per frame, as from
/// [`dynamic_region`]), the squared errors of all region pixels pooled;
/// `None` when the region is empty. [`crate::video::PSNR_IDENTICAL`] when
/// the pooled MSE is below [`crate::video::PSNR_MSE_FLOOR`].
pub fn region_psnr(
    pred: &[RgbFrame],
    gt: &[RgbFrame],
    region: &[Vec<bool>],
) -> Result<Option<f64>> {
    if pred.len() != gt.len() || region.len() != gt.len() {
        return Err(MetricError::ShapeMismatch {
            what: "region PSNR: frame counts (prediction, ground truth, region)".into(),
            left: format!("{}, {}", pred.len(), gt.len()),
            right: region.len().to_string(),
        });
    }
    let (mut sum, mut n) = (0.0f64, 0usize);
    for (t, ((p, g), m)) in pred.iter().zip(gt).zip(region).enumerate() {
        if (p.width, p.height) != (g.width, g.height) || m.len() != g.width * g.height {
            return Err(MetricError::ShapeMismatch {
                what: format!("region PSNR, frame {t}: prediction, ground truth, region pixels"),
                left: format!("{}x{}, {}x{}", p.width, p.height, g.width, g.height),
                right: m.len().to_string(),
            });
        }
        for ((a, b), &inside) in p.rgb.chunks_exact(3).zip(g.rgb.chunks_exact(3)).zip(m) {
            if inside {
                for (x, y) in a.iter().zip(b) {
                    let d = f64::from(*x) - f64::from(*y);
                    sum += d * d;
                }
                n += 3;
            }
        }
    }
    if n == 0 {
        return Ok(None);
    }
    Ok(Some(psnr_from_mse(sum / n as f64)))
}

/// [`region_psnr`] on the [`dynamic_region`] of `gt`.
pub fn dynamic_psnr(pred: &[RgbFrame], gt: &[RgbFrame]) -> Result<Option<f64>> {
    region_psnr(pred, gt, &dynamic_region(gt)?)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::video::PSNR_IDENTICAL;

    fn flat(w: usize, h: usize, v: f32) -> RgbFrame {
        RgbFrame::new(w, h, vec![v; w * h * 3]).unwrap()
    }

    /// A frame of `v` with the pixel `(x, y)` set to `p`.
    fn dot(w: usize, h: usize, v: f32, x: usize, y: usize, p: f32) -> RgbFrame {
        let mut f = flat(w, h, v);
        for c in 0..3 {
            f.rgb[(y * w + x) * 3 + c] = p;
        }
        f
    }

    #[test]
    fn region_is_the_changed_pixels_dilated_by_two() {
        let gt = vec![flat(9, 7, 0.5), dot(9, 7, 0.5, 4, 3, 0.9)];
        let r = dynamic_region(&gt).unwrap();
        assert!(r[0].iter().all(|&b| !b));
        let inside: Vec<(usize, usize)> = (0..63)
            .filter(|&i| r[1][i])
            .map(|i| (i % 9, i / 9))
            .collect();
        // A 5x5 square around (4, 3).
        assert_eq!(inside.len(), 25);
        assert!(inside
            .iter()
            .all(|&(x, y)| (2..=6).contains(&x) && (1..=5).contains(&y)));
        // Clipped at the border: a corner pixel gives a 3x3 square.
        let gt = vec![flat(9, 7, 0.5), dot(9, 7, 0.5, 0, 0, 0.9)];
        assert_eq!(
            dynamic_region(&gt).unwrap()[1]
                .iter()
                .filter(|&&b| b)
                .count(),
            9
        );
        // Below the threshold nothing is dynamic.
        let gt = vec![flat(9, 7, 0.5), dot(9, 7, 0.5, 4, 3, 0.5 + 7.0 / 255.0)];
        assert!(dynamic_region(&gt).unwrap()[1].iter().all(|&b| !b));
    }

    #[test]
    fn psnr_pools_the_region_pixels_only() {
        // Motion at one pixel: 25 region pixels in frame 1, none in frame 0.
        let gt = vec![flat(9, 7, 0.5), dot(9, 7, 0.5, 4, 3, 0.9)];
        // The copy of the first frame errs by 0.4 at one of 25 pixels:
        // mse = 0.16 / 25 = 0.0064 -> 20 log10(1 / 0.08) = 21.938 dB.
        let copy = vec![gt[0].clone(), gt[0].clone()];
        let v = dynamic_psnr(&copy, &gt).unwrap().unwrap();
        assert!((v - 20.0 * (1.0f64 / 0.08).log10()).abs() < 1e-4, "{v}");
        // An error outside the region (and in frame 0) does not count.
        let off = vec![flat(9, 7, 0.0), dot(9, 7, 0.5, 4, 3, 0.9)];
        let mut far = off.clone();
        far[1].rgb[(6 * 9 + 8) * 3] = 0.0;
        assert_eq!(dynamic_psnr(&far, &gt).unwrap(), Some(PSNR_IDENTICAL));
        // A perfect prediction of a moving clip is identical; a still clip has no score.
        assert_eq!(dynamic_psnr(&gt, &gt).unwrap(), Some(PSNR_IDENTICAL));
        let still = vec![flat(9, 7, 0.5), flat(9, 7, 0.5)];
        assert_eq!(dynamic_psnr(&still, &still).unwrap(), None);
    }

    #[test]
    fn mismatched_inputs_are_errors() {
        let gt = vec![flat(9, 7, 0.5), flat(9, 7, 0.5)];
        assert!(dynamic_psnr(&gt[..1], &gt).is_err());
        assert!(dynamic_region(&[]).is_err());
        let odd = vec![flat(9, 7, 0.5), flat(8, 7, 0.5)];
        assert!(dynamic_region(&odd).is_err());
        let region = vec![vec![false; 63], vec![true; 62]];
        assert!(region_psnr(&gt, &gt, &region).is_err());
    }
}
