//! The background's consistency under a candidate camera: a second score,
//! beside the silhouette IoU of [`super::objective`], that needs no found
//! pixels.
//!
//! The camera renders the robot in every scored frame. Per pixel, the frames
//! where it renders no robot should all show the static background: their
//! per-channel median is the background's colour, and each of those frames
//! costs its largest channel difference to it (capped at
//! [`BACKGROUND_CAP`], over the cap: 0..1). Frames where it renders the
//! robot should differ from the background: each costs one minus that
//! difference (capped likewise). A pixel with fewer than
//! [`MIN_BACKGROUND_FRAMES`] robot-free frames has no background estimate:
//! each of its frames costs [`UNKNOWN_COST`]. The cost is the mean over
//! pixels and frames.
//!
//! Why: the silhouette IoU compares with pixels found against the temporal
//! median, which also change where the same link is now and usually (the
//! link turns, its shading moves) and miss robot parts the colour of the
//! background. Measured on the synthetic world (`calibrate-study`, cameras
//! the search placed 8-15 cm off with the focal length known): the
//! silhouette IoU scored the misplaced camera as well as the true one or
//! better, the sum of the two scores the true camera's neighbourhood best.
//! The pixels are the frames after the foreground's gain compensation, so
//! auto-exposure does not count as a change.

use rayon::prelude::*;

/// Colour difference (0..255, largest channel) at which a frame's cost
/// saturates.
pub(crate) const BACKGROUND_CAP: f32 = 30.0;

/// Robot-free frames a pixel needs for a background estimate.
pub(crate) const MIN_BACKGROUND_FRAMES: usize = 3;

/// The cost of each frame of a pixel without a background estimate.
pub(crate) const UNKNOWN_COST: f64 = 0.5;

/// Box-reduces interleaved RGB8 `frame` (`w` x `h`) by `factor` (the mean
/// of each block; the remainder rows and columns dropped).
pub(crate) fn reduce_rgb(frame: &[u8], (w, h): (usize, usize), factor: usize) -> Vec<u8> {
    if factor <= 1 {
        return frame.to_vec();
    }
    let (lw, lh) = (w / factor, h / factor);
    let mut sums = vec![0u32; lw * lh * 3];
    for y in 0..lh * factor {
        for x in 0..lw * factor {
            let o = ((y / factor) * lw + x / factor) * 3;
            for c in 0..3 {
                sums[o + c] += u32::from(frame[(y * w + x) * 3 + c]);
            }
        }
    }
    let area = (factor * factor) as u32;
    sums.iter()
        .map(|&s| ((s + area / 2) / area).min(255) as u8)
        .collect()
}

/// The summed cost and the number of pixel-frames it sums over, of the
/// frames `rgb[t]` for `t` in `frames` against the robot's rendered 0/1
/// masks `robot` (one per entry of `frames`, `pixels` each).
pub(crate) fn background_cost(
    rgb: &[Vec<u8>],
    frames: &[usize],
    robot: &[Vec<u8>],
    pixels: usize,
) -> (f64, f64) {
    if frames.is_empty() || pixels == 0 {
        return (0.0, 0.0);
    }
    let total: f64 = (0..pixels)
        .into_par_iter()
        .with_min_len(256)
        .map_init(
            || [Vec::new(), Vec::new(), Vec::new()],
            |values: &mut [Vec<u8>; 3], p| {
                for v in values.iter_mut() {
                    v.clear();
                }
                for (k, &t) in frames.iter().enumerate() {
                    if robot[k][p] == 0 {
                        for (c, v) in values.iter_mut().enumerate() {
                            v.push(rgb[t][3 * p + c]);
                        }
                    }
                }
                if values[0].len() < MIN_BACKGROUND_FRAMES {
                    return UNKNOWN_COST * frames.len() as f64;
                }
                let mut colour = [0u8; 3];
                for (c, v) in values.iter_mut().enumerate() {
                    let mid = v.len() / 2;
                    colour[c] = *v.select_nth_unstable(mid).1;
                }
                frames
                    .iter()
                    .enumerate()
                    .map(|(k, &t)| {
                        let d = (0..3)
                            .map(|c| rgb[t][3 * p + c].abs_diff(colour[c]))
                            .max()
                            .unwrap_or(0);
                        let e = (f32::from(d) / BACKGROUND_CAP).min(1.0);
                        f64::from(if robot[k][p] == 0 { e } else { 1.0 - e })
                    })
                    .sum::<f64>()
            },
        )
        .sum();
    (total, (frames.len() * pixels) as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grey 6 x 1 strip with a red square moving along it, one pixel a
    /// frame: `(frames, robot masks)`.
    fn moving_square(shift: isize) -> (Vec<Vec<u8>>, Vec<Vec<u8>>) {
        let (w, n) = (6usize, 5usize);
        let mut frames = Vec::new();
        let mut masks = Vec::new();
        for t in 0..n {
            let mut f = vec![100u8; w * 3];
            let mut m = vec![0u8; w];
            f[3 * t] = 250;
            let drawn = t as isize + shift;
            if (0..w as isize).contains(&drawn) {
                m[drawn as usize] = 1;
            }
            frames.push(f);
            masks.push(m);
        }
        (frames, masks)
    }

    #[test]
    fn the_true_masks_cost_nothing_and_shifted_ones_do() {
        let (frames, truth) = moving_square(0);
        let all: Vec<usize> = (0..frames.len()).collect();
        let (c, n) = background_cost(&frames, &all, &truth, 6);
        assert_eq!((c, n), (0.0, 30.0));
        let (_, shifted) = moving_square(1);
        let (c1, _) = background_cost(&frames, &all, &shifted, 6);
        // Each frame: the square's pixel called background (1) and the
        // grey pixel ahead of it called robot (1).
        assert_eq!(c1, 10.0);
        let everywhere: Vec<Vec<u8>> = truth.iter().map(|m| vec![1; m.len()]).collect();
        let (c2, _) = background_cost(&frames, &all, &everywhere, 6);
        assert_eq!(c2, UNKNOWN_COST * 30.0, "no pixel has a background");
    }

    #[test]
    fn reducing_averages_blocks() {
        let frame: Vec<u8> = (0..4 * 2 * 3).map(|i| (i * 10) as u8).collect();
        let r = reduce_rgb(&frame, (4, 2), 2);
        // Block (0,0): pixels 0, 1, 4, 5; channel 0 values 0, 30, 120, 150.
        assert_eq!(r.len(), 6);
        assert_eq!(r[0], 75);
        assert_eq!(reduce_rgb(&frame, (4, 2), 1), frame);
    }
}
