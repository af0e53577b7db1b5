//! The robot's appearance under a candidate camera: a third score, beside
//! the silhouette IoU of [`super::objective`] and the background's
//! consistency of [`super::background`], that sees the parts of the robot
//! that never move.
//!
//! Both other scores see only what changes: a link that stays put (the
//! base, the shoulder in a reach) covers the same pixels in every frame, so
//! the found pixels miss it and the background's median is its colour. A
//! camera that renders it a few centimetres off costs them nothing. The
//! colours tell it: the robot's colours are not the background's.
//!
//! The camera renders the robot in every scored frame, which splits the
//! pixel-frames in two: robot and background. Each side's colour histogram
//! ([`BITS`] bits a channel) gives, for each colour, how likely a robot
//! pixel and a background pixel are to show it; a pixel-frame costs the
//! probability of the side it was not given (the side's likelihood over the
//! sum of both: region-based pose estimation's posterior, as in PWP3D,
//! Prisacariu and Reid 2012). The cost is the mean over the robot's
//! pixel-frames plus the mean over the background's: 0 when no colour is
//! shared, 1 when the split tells nothing (both sides alike), whatever the
//! sides' sizes. A camera that renders the robot too small leaves
//! robot-coloured pixels on the background's side, one that renders it
//! misplaced takes background colours onto the robot's: both raise it. On
//! the gain-compensated frames, like the background's consistency.

/// Bits a channel of the colour histograms (4096 bins).
pub(crate) const BITS: u32 = 4;

/// The number of histogram bins.
const BINS: usize = 1 << (3 * BITS);

/// The histogram bin of an RGB8 colour.
fn bin(rgb: &[u8]) -> usize {
    let shift = 8 - BITS;
    (usize::from(rgb[0] >> shift) << (2 * BITS))
        | (usize::from(rgb[1] >> shift) << BITS)
        | usize::from(rgb[2] >> shift)
}

/// The colour histograms of the robot's and the background's pixel-frames
/// of `rgb[t]` for `t` in `frames`, split by the rendered 0/1 masks `robot`
/// (one per entry of `frames`, `pixels` each).
pub(crate) fn histograms(
    rgb: &[Vec<u8>],
    frames: &[usize],
    robot: &[Vec<u8>],
    pixels: usize,
) -> [Vec<u32>; 2] {
    let mut h = [vec![0u32; BINS], vec![0u32; BINS]];
    for (k, &t) in frames.iter().enumerate() {
        let (frame, mask) = (&rgb[t], &robot[k]);
        for p in 0..pixels {
            h[usize::from(mask[p] != 0)][bin(&frame[3 * p..3 * p + 3])] += 1;
        }
    }
    h
}

/// The appearance cost (0..1, see the module documentation) of the split
/// `[background, robot]` histograms; 1 when either side is empty.
pub(crate) fn appearance_cost(h: &[Vec<u32>; 2]) -> f64 {
    let n: [f64; 2] = [0, 1].map(|s| h[s].iter().map(|&c| f64::from(c)).sum());
    if n[0] <= 0.0 || n[1] <= 0.0 {
        return 1.0;
    }
    let mut cost = [0.0f64; 2];
    for (&c0, &c1) in h[0].iter().zip(&h[1]) {
        let (c0, c1) = (f64::from(c0), f64::from(c1));
        if c0 == 0.0 || c1 == 0.0 {
            // A colour only one side shows costs nothing.
            continue;
        }
        let (p0, p1) = (c0 / n[0], c1 / n[1]);
        // Each side's pixels of this colour cost the other side's posterior.
        cost[0] += c0 * p1 / (p0 + p1);
        cost[1] += c1 * p0 / (p0 + p1);
    }
    cost[0] / n[0] + cost[1] / n[1]
}

#[cfg(test)]
mod tests {
    use super::*;

    /// One 4 x 1 frame: two white pixels (the robot) and two blue.
    fn frame() -> Vec<Vec<u8>> {
        vec![vec![250, 250, 250, 250, 250, 250, 20, 40, 200, 20, 40, 200]]
    }

    #[test]
    fn the_true_split_costs_nothing_and_a_wrong_one_does() {
        let rgb = frame();
        let truth = histograms(&rgb, &[0], &[vec![1, 1, 0, 0]], 4);
        assert_eq!(appearance_cost(&truth), 0.0);
        // Robot drawn one pixel right: robot = white + blue, background =
        // white + blue: the split tells nothing.
        let shifted = histograms(&rgb, &[0], &[vec![0, 1, 1, 0]], 4);
        assert!((appearance_cost(&shifted) - 1.0).abs() < 1e-12);
        // Robot drawn too small: robot = one white, background = one white +
        // two blue. White: robot likelihood 1, background 1/3. The robot's
        // white costs (1/3)/(4/3) = 1/4; the background's white costs 3/4 of
        // one pixel in three: 1/4. Total 1/2.
        let small = histograms(&rgb, &[0], &[vec![1, 0, 0, 0]], 4);
        assert!((appearance_cost(&small) - 0.5).abs() < 1e-12);
        let none = histograms(&rgb, &[0], &[vec![0, 0, 0, 0]], 4);
        assert_eq!(appearance_cost(&none), 1.0);
    }

    #[test]
    fn colours_share_a_bin_within_its_width() {
        assert_eq!(bin(&[0, 0, 0]), bin(&[15, 15, 15]));
        assert_ne!(bin(&[15, 0, 0]), bin(&[16, 0, 0]));
        assert_eq!(bin(&[255, 255, 255]), BINS - 1);
    }
}
