//! Per-frame video metrics: PSNR, SSIM and Mask-IoU, averaged over frames and
//! then over videos (each video weighs the same whatever its length).

use crate::{MetricError, Result};
use bridgev2w_io::frame::RgbFrame;
use rayon::prelude::*;

/// Errors unless two frames have one size.
fn check_same(a: &RgbFrame, b: &RgbFrame, what: &str) -> Result<()> {
    if (a.width, a.height) != (b.width, b.height) {
        return Err(MetricError::ShapeMismatch {
            what: what.to_string(),
            left: format!("{}x{}", a.width, a.height),
            right: format!("{}x{}", b.width, b.height),
        });
    }
    Ok(())
}

/// PSNR value reported for (near-)identical frames, whose MSE is below
/// [`PSNR_MSE_FLOOR`].
pub const PSNR_IDENTICAL: f64 = 100.0;
/// MSE below which two frames count as identical for PSNR.
pub const PSNR_MSE_FLOOR: f64 = 1e-10;

/// PSNR of one frame pair on `[0, 1]` data: `20 log10(1 / sqrt(mse))`, or
/// [`PSNR_IDENTICAL`] when `mse < 1e-10`.
pub fn psnr(pred: &RgbFrame, gt: &RgbFrame) -> Result<f64> {
    check_same(pred, gt, "PSNR frames")?;
    let sum: f64 = pred
        .rgb
        .chunks(4096)
        .zip(gt.rgb.chunks(4096))
        .map(|(a, b)| {
            a.iter()
                .zip(b)
                .map(|(&x, &y)| {
                    let d = f64::from(x) - f64::from(y);
                    d * d
                })
                .sum::<f64>()
        })
        .sum();
    Ok(psnr_from_mse(sum / pred.rgb.len().max(1) as f64))
}

/// `20 log10(1 / sqrt(mse))` of a mean squared error on `[0, 1]` data, or
/// [`PSNR_IDENTICAL`] when `mse < PSNR_MSE_FLOOR`.
pub fn psnr_from_mse(mse: f64) -> f64 {
    if mse < PSNR_MSE_FLOOR {
        PSNR_IDENTICAL
    } else {
        20.0 * (1.0 / mse.sqrt()).log10()
    }
}

/// Side of the SSIM window, pixels.
pub const SSIM_WINDOW: usize = 11;
/// Standard deviation of the SSIM window's Gaussian, pixels.
pub const SSIM_SIGMA: f64 = 1.5;
const SSIM_K1: f64 = 0.01;
const SSIM_K2: f64 = 0.03;

/// The normalised 1-D Gaussian of the SSIM window (11 taps, sigma 1.5).
pub fn ssim_window() -> [f64; SSIM_WINDOW] {
    let r = (SSIM_WINDOW / 2) as f64;
    let mut w = [0.0; SSIM_WINDOW];
    for (i, v) in w.iter_mut().enumerate() {
        let x = i as f64 - r;
        *v = (-x * x / (2.0 * SSIM_SIGMA * SSIM_SIGMA)).exp();
    }
    let s: f64 = w.iter().sum();
    w.map(|v| v / s)
}

/// SSIM of one frame pair (Wang et al. 2004): 11x11 Gaussian window with
/// sigma 1.5, K1 = 0.01, K2 = 0.03, data range 1, population (co)variances,
/// averaged over the valid region only (windows entirely inside the frame,
/// no padding), per RGB channel and then over the channels. This is
/// scikit-image's `structural_similarity(..., gaussian_weights=True,
/// sigma=1.5, use_sample_covariance=False, data_range=1, channel_axis=-1)`.
///
/// Computed in f32 with AVX2/FMA when the CPU has them (runtime dispatch);
/// agrees with the f64 computation to ~1e-7 (checked in the tests and by
/// `bridgev2w bench metrics` against scikit-image).
pub fn ssim(pred: &RgbFrame, gt: &RgbFrame) -> Result<f64> {
    check_same(pred, gt, "SSIM frames")?;
    let (w, h) = (pred.width, pred.height);
    if w < SSIM_WINDOW || h < SSIM_WINDOW {
        return Err(MetricError::Invalid(format!(
            "SSIM needs frames of at least {SSIM_WINDOW}x{SSIM_WINDOW} pixels, got {w}x{h}"
        )));
    }
    Ok(pulp::Arch::new().dispatch(SsimKernel {
        x: &pred.rgb,
        y: &gt.rgb,
        width: w,
        height: h,
    }))
}

/// Output values (interleaved RGB columns) per vertical strip: the strip's
/// ring of filtered rows (11 rows x 5 moments) stays in the L2 cache.
const SSIM_STRIP: usize = 768;

/// The SSIM computation, compiled once per SIMD level by `pulp`.
struct SsimKernel<'a> {
    x: &'a [f32],
    y: &'a [f32],
    width: usize,
    height: usize,
}

impl pulp::WithSimd for SsimKernel<'_> {
    type Output = f64;

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) -> f64 {
        ssim_interleaved(self.x, self.y, self.width, self.height)
    }
}

/// Mean SSIM over the valid region of all three channels at once.
///
/// The channels stay interleaved: a horizontal tap is 3 values away, and an
/// output value's channel is its index mod 3, so the mean over all outputs
/// is the mean of the three channel means. Separable filtering: each input
/// row is filtered horizontally into a ring of the last [`SSIM_WINDOW`]
/// rows (five moments each), and every full ring yields one output row; the
/// frame is processed in vertical strips of [`SSIM_STRIP`] outputs so the
/// ring stays in cache. Row sums are accumulated in f64.
#[inline(always)]
fn ssim_interleaved(x: &[f32], y: &[f32], w: usize, h: usize) -> f64 {
    const HALO: usize = (SSIM_WINDOW - 1) * 3;
    let window = ssim_window().map(|v| v as f32);
    let row_len = w * 3;
    let valid_len = (w - SSIM_WINDOW + 1) * 3;
    let valid_rows = h - SSIM_WINDOW + 1;
    let c1 = (SSIM_K1 * SSIM_K1) as f32;
    let c2 = (SSIM_K2 * SSIM_K2) as f32;
    // ring[slot][moment][column]: horizontally filtered moments of one row.
    let mut ring: Vec<[Vec<f32>; 5]> = (0..SSIM_WINDOW)
        .map(|_| std::array::from_fn(|_| vec![0.0; SSIM_STRIP]))
        .collect();
    let mut products: [Vec<f32>; 5] = std::array::from_fn(|_| vec![0.0; SSIM_STRIP + HALO]);
    let mut m: [Vec<f32>; 5] = std::array::from_fn(|_| vec![0.0; SSIM_STRIP]);
    let mut values = vec![0.0f32; SSIM_STRIP];
    let mut sum = 0.0f64;
    let mut first = 0;
    while first < valid_len {
        let n = SSIM_STRIP.min(valid_len - first);
        let input_len = n + HALO;
        for row in 0..h {
            let start = row * row_len + first;
            let xr = &x[start..start + input_len];
            let yr = &y[start..start + input_len];
            {
                let [px, py, pxx, pyy, pxy] = &mut products;
                let (px, py) = (&mut px[..input_len], &mut py[..input_len]);
                let (pxx, pyy) = (&mut pxx[..input_len], &mut pyy[..input_len]);
                let pxy = &mut pxy[..input_len];
                for i in 0..input_len {
                    let (a, b) = (xr[i], yr[i]);
                    px[i] = a;
                    py[i] = b;
                    pxx[i] = a * a;
                    pyy[i] = b * b;
                    pxy[i] = a * b;
                }
            }
            let slot = &mut ring[row % SSIM_WINDOW];
            for (out, p) in slot.iter_mut().zip(&products) {
                // Horizontal taps: the same channel, 3 values apart.
                let taps: [&[f32]; SSIM_WINDOW] = std::array::from_fn(|k| &p[3 * k..3 * k + n]);
                symmetric_filter(&taps, &window, &mut out[..n]);
            }
            if row + 1 < SSIM_WINDOW {
                continue;
            }
            // Output row `row + 1 - SSIM_WINDOW`: ring slot of input row r is
            // r % SSIM_WINDOW.
            let top = row + 1 - SSIM_WINDOW;
            for (moment, out) in m.iter_mut().enumerate() {
                let taps: [&[f32]; SSIM_WINDOW] =
                    std::array::from_fn(|k| &ring[(top + k) % SSIM_WINDOW][moment][..n]);
                symmetric_filter(&taps, &window, &mut out[..n]);
            }
            let [mx, my, mxx, myy, mxy] = &m;
            let (mx, my, mxx, myy, mxy) = (&mx[..n], &my[..n], &mxx[..n], &myy[..n], &mxy[..n]);
            let values = &mut values[..n];
            for i in 0..n {
                let (ux, uy) = (mx[i], my[i]);
                let vx = mxx[i] - ux * ux;
                let vy = myy[i] - uy * uy;
                let vxy = mxy[i] - ux * uy;
                let num = (2.0 * ux * uy + c1) * (2.0 * vxy + c2);
                let den = (ux * ux + uy * uy + c1) * (vx + vy + c2);
                values[i] = num / den;
            }
            // Sixteen independent f32 partial sums of one row (at most 48
            // values each), then f64 across rows.
            let mut partial = [0.0f32; 16];
            let chunks = values.chunks_exact(16);
            let rest: f64 = chunks.remainder().iter().map(|&v| f64::from(v)).sum();
            for c in chunks {
                for (p, v) in partial.iter_mut().zip(c) {
                    *p += v;
                }
            }
            sum += partial.iter().map(|&v| f64::from(v)).sum::<f64>() + rest;
        }
        first += n;
    }
    sum / (valid_len * valid_rows) as f64
}

/// `out[i] = sum_k window[k] * taps[k][i]` for the symmetric window
/// (`window[k] == window[10 - k]`), pairing mirrored taps; one store per
/// output, vectorised across `i`.
#[inline(always)]
fn symmetric_filter(taps: &[&[f32]; SSIM_WINDOW], window: &[f32; SSIM_WINDOW], out: &mut [f32]) {
    let n = out.len();
    let [t0, t1, t2, t3, t4, t5, t6, t7, t8, t9, t10] = taps.map(|t| &t[..n]);
    let [w0, w1, w2, w3, w4, w5, ..] = *window;
    for (i, o) in out.iter_mut().enumerate() {
        *o = (t0[i] + t10[i]) * w0
            + (t1[i] + t9[i]) * w1
            + (t2[i] + t8[i]) * w2
            + (t3[i] + t7[i]) * w3
            + (t4[i] + t6[i]) * w4
            + t5[i] * w5;
    }
}

/// Intersection over union of two binary masks (non-zero = robot). Two
/// empty masks agree perfectly: 1.
pub fn mask_iou(pred: &[u8], gt: &[u8]) -> Result<f64> {
    if pred.len() != gt.len() {
        return Err(MetricError::ShapeMismatch {
            what: "Mask-IoU masks".into(),
            left: format!("{} pixels", pred.len()),
            right: format!("{} pixels", gt.len()),
        });
    }
    let (mut inter, mut union) = (0usize, 0usize);
    for (&a, &b) in pred.iter().zip(gt) {
        let (a, b) = (a != 0, b != 0);
        inter += usize::from(a && b);
        union += usize::from(a || b);
    }
    Ok(if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    })
}

/// A per-frame metric averaged over the frames of one video pair.
pub fn video_mean<T>(
    pred: &[T],
    gt: &[T],
    what: &str,
    metric: impl Fn(&T, &T) -> Result<f64> + Sync,
) -> Result<f64>
where
    T: Sync,
{
    if pred.len() != gt.len() {
        return Err(MetricError::ShapeMismatch {
            what: format!("{what}: frame counts"),
            left: pred.len().to_string(),
            right: gt.len().to_string(),
        });
    }
    if pred.is_empty() {
        return Err(MetricError::Invalid(format!(
            "{what}: a video has no frames"
        )));
    }
    let values = pred
        .par_iter()
        .zip(gt)
        .enumerate()
        .map(|(i, (a, b))| {
            metric(a, b).map_err(|e| MetricError::Invalid(format!("{what}, frame {i}: {e}")))
        })
        .collect::<Result<Vec<f64>>>()?;
    Ok(values.iter().sum::<f64>() / values.len() as f64)
}

/// Mean PSNR over the frames of one video pair.
pub fn video_psnr(pred: &[RgbFrame], gt: &[RgbFrame]) -> Result<f64> {
    video_mean(pred, gt, "PSNR", psnr)
}

/// Mean SSIM over the frames of one video pair.
pub fn video_ssim(pred: &[RgbFrame], gt: &[RgbFrame]) -> Result<f64> {
    video_mean(pred, gt, "SSIM", ssim)
}

/// Mean Mask-IoU over the frames (one mask per frame) of one video pair.
pub fn video_mask_iou(pred: &[Vec<u8>], gt: &[Vec<u8>]) -> Result<f64> {
    video_mean(pred, gt, "Mask-IoU", |a, b| mask_iou(a, b))
}

/// Mean of per-video values (each video weighs the same).
pub fn mean_over_videos(values: &[f64]) -> Result<f64> {
    if values.is_empty() {
        return Err(MetricError::Invalid("no videos to average".into()));
    }
    Ok(values.iter().sum::<f64>() / values.len() as f64)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    struct Rng(u64);
    impl Rng {
        fn next(&mut self) -> f32 {
            self.0 ^= self.0 << 13;
            self.0 ^= self.0 >> 7;
            self.0 ^= self.0 << 17;
            (self.0 >> 40) as f32 / (1u64 << 24) as f32
        }
    }

    fn random_frame(rng: &mut Rng, w: usize, h: usize) -> RgbFrame {
        RgbFrame::new(w, h, (0..w * h * 3).map(|_| rng.next()).collect()).unwrap()
    }

    /// Straightforward SSIM in f64: a full 2-D window at every valid
    /// position (a second implementation).
    fn ssim_reference(a: &RgbFrame, b: &RgbFrame) -> f64 {
        let g = ssim_window();
        let (w, h) = (a.width, a.height);
        let (c1, c2) = (1e-4, 9e-4);
        let mut total = 0.0;
        for c in 0..3 {
            let px = |f: &RgbFrame, x: usize, y: usize| f64::from(f.rgb[(y * w + x) * 3 + c]);
            let mut sum = 0.0;
            let mut n = 0;
            for y0 in 0..=h - SSIM_WINDOW {
                for x0 in 0..=w - SSIM_WINDOW {
                    let (mut ux, mut uy, mut xx, mut yy, mut xy) = (0.0, 0.0, 0.0, 0.0, 0.0);
                    for j in 0..SSIM_WINDOW {
                        for i in 0..SSIM_WINDOW {
                            let wt = g[i] * g[j];
                            let (p, q) = (px(a, x0 + i, y0 + j), px(b, x0 + i, y0 + j));
                            ux += wt * p;
                            uy += wt * q;
                            xx += wt * p * p;
                            yy += wt * q * q;
                            xy += wt * p * q;
                        }
                    }
                    let (vx, vy, vxy) = (xx - ux * ux, yy - uy * uy, xy - ux * uy);
                    sum += ((2.0 * ux * uy + c1) * (2.0 * vxy + c2))
                        / ((ux * ux + uy * uy + c1) * (vx + vy + c2));
                    n += 1;
                }
            }
            total += sum / n as f64;
        }
        total / 3.0
    }

    #[test]
    fn psnr_closed_form() {
        let a = RgbFrame::new(4, 3, vec![0.5; 36]).unwrap();
        let b = RgbFrame::new(4, 3, vec![0.6; 36]).unwrap();
        // mse = 0.01 -> 20 log10(1 / 0.1) = 20 dB.
        assert!((psnr(&a, &b).unwrap() - 20.0).abs() < 1e-5);
        assert_eq!(psnr(&a, &a).unwrap(), PSNR_IDENTICAL);
        let c = RgbFrame::new(4, 3, vec![0.0; 36]).unwrap();
        let d = RgbFrame::new(4, 3, vec![1.0; 36]).unwrap();
        assert!(psnr(&c, &d).unwrap().abs() < 1e-12);
    }

    #[test]
    fn ssim_matches_direct_window_sums() {
        let mut rng = Rng(7);
        // 300 pixels wide: two column strips (the second one partial).
        for (w, h) in [(11, 11), (23, 17), (40, 31), (300, 14)] {
            let a = random_frame(&mut rng, w, h);
            // A correlated second frame: a blend with noise.
            let noise = random_frame(&mut rng, w, h);
            let b = RgbFrame::new(
                w,
                h,
                a.rgb
                    .iter()
                    .zip(&noise.rgb)
                    .map(|(x, n)| 0.7 * x + 0.3 * n)
                    .collect(),
            )
            .unwrap();
            let fast = ssim(&a, &b).unwrap();
            let reference = ssim_reference(&a, &b);
            assert!(
                (fast - reference).abs() < 1e-6,
                "{w}x{h}: {fast} vs {reference}"
            );
            assert!(fast > 0.3 && fast < 0.99, "{fast}");
        }
    }

    #[test]
    fn ssim_of_identical_frames_is_one_and_symmetric() {
        let mut rng = Rng(11);
        let a = random_frame(&mut rng, 32, 20);
        let b = random_frame(&mut rng, 32, 20);
        assert!((ssim(&a, &a).unwrap() - 1.0).abs() < 1e-5);
        let (ab, ba) = (ssim(&a, &b).unwrap(), ssim(&b, &a).unwrap());
        assert!((ab - ba).abs() < 1e-6);
        // Independent noise: close to zero structure.
        assert!(ab.abs() < 0.1, "{ab}");
    }

    #[test]
    fn ssim_of_constant_frames_closed_form() {
        // Constant frames: variances vanish, SSIM = (2 a b + C1) / (a^2 + b^2 + C1).
        let (p, q) = (0.2f32, 0.7f32);
        let a = RgbFrame::new(12, 12, vec![p; 12 * 12 * 3]).unwrap();
        let b = RgbFrame::new(12, 12, vec![q; 12 * 12 * 3]).unwrap();
        let (p, q) = (f64::from(p), f64::from(q));
        let expected = (2.0 * p * q + 1e-4) / (p * p + q * q + 1e-4);
        assert!((ssim(&a, &b).unwrap() - expected).abs() < 1e-9);
    }

    #[test]
    fn errors_name_the_problem() {
        let a = RgbFrame::new(12, 12, vec![0.0; 432]).unwrap();
        let small = RgbFrame::new(10, 12, vec![0.0; 360]).unwrap();
        assert!(matches!(
            psnr(&a, &small),
            Err(MetricError::ShapeMismatch { .. })
        ));
        let e = ssim(&small, &small).unwrap_err().to_string();
        assert!(e.contains("11x11") && e.contains("10x12"), "{e}");
        assert!(RgbFrame::new(2, 2, vec![0.0; 11]).is_err());
        let e = RgbFrame::new(1, 1, vec![0.0, f32::NAN, 0.0])
            .unwrap_err()
            .to_string();
        assert!(e.contains("NaN"), "{e}");
        let e = video_psnr(std::slice::from_ref(&a), &[a.clone(), a.clone()])
            .unwrap_err()
            .to_string();
        assert!(e.contains("frame counts"), "{e}");
    }

    #[test]
    fn mask_iou_counts() {
        let a = [1u8, 1, 0, 0, 1];
        let b = [1u8, 0, 0, 1, 1];
        assert!((mask_iou(&a, &b).unwrap() - 0.5).abs() < 1e-12);
        assert_eq!(mask_iou(&[0, 0], &[0, 0]).unwrap(), 1.0);
        assert_eq!(mask_iou(&[255, 0], &[0, 7]).unwrap(), 0.0);
        assert!(mask_iou(&[0], &[0, 0]).is_err());
        let v = video_mask_iou(&[a.to_vec(), a.to_vec()], &[b.to_vec(), a.to_vec()]).unwrap();
        assert!((v - 0.75).abs() < 1e-12);
    }
}
