//! A robot segmenter for generated frames, so Mask-IoU can be measured on
//! videos that come with no masks of their own.
//!
//! [`ColorSegmenter`] is a per-pixel Bayes classifier on quantised RGB: it
//! counts, over frames with ground-truth robot masks (a training split), how
//! often each colour bin is robot, and labels a pixel robot when that
//! frequency is above one half. It needs no network and no weights, and it
//! suits worlds where the robot's colours are distinctive (the synthetic
//! tabletop's white and grey links); its own ceiling, the Mask-IoU of its
//! masks of the *ground-truth* frames, should be reported next to any score
//! it gives, since a prediction cannot score above what the segmenter reads
//! from real frames.

use crate::{MetricError, Result};
use bridgev2w_io::frame::RgbFrame;

/// Anything that labels the robot's pixels in a frame (1 = robot, one value
/// per pixel, row-major).
pub trait RobotSegmenter {
    /// The robot mask of `frame`.
    fn segment(&self, frame: &RgbFrame) -> Result<Vec<u8>>;
}

impl RobotSegmenter for ColorSegmenter {
    fn segment(&self, frame: &RgbFrame) -> Result<Vec<u8>> {
        Ok(ColorSegmenter::segment(self, frame))
    }
}

/// Colour-bin statistics of robot vs. other pixels.
#[derive(Debug, Clone, PartialEq)]
pub struct ColorSegmenter {
    bits: u32,
    robot: Vec<u32>,
    total: Vec<u32>,
}

impl ColorSegmenter {
    /// An empty segmenter with `bits` levels per channel (`2^bits`, 1..=8).
    pub fn new(bits: u32) -> Result<Self> {
        if !(1..=8).contains(&bits) {
            return Err(MetricError::Invalid(format!(
                "colour segmenter: {bits} bits per channel, expected 1..=8"
            )));
        }
        let bins = 1usize << (3 * bits);
        Ok(Self {
            bits,
            robot: vec![0; bins],
            total: vec![0; bins],
        })
    }

    fn bin(&self, rgb: &[f32]) -> usize {
        let levels = (1u32 << self.bits) as f32;
        let q = |v: f32| ((v.clamp(0.0, 1.0) * levels) as usize).min(levels as usize - 1);
        (q(rgb[0]) << (2 * self.bits)) | (q(rgb[1]) << self.bits) | q(rgb[2])
    }

    /// Adds the pixels of `frame` with their ground-truth `mask` (one value
    /// per pixel, non-zero = robot).
    pub fn observe(&mut self, frame: &RgbFrame, mask: &[u8]) -> Result<()> {
        if mask.len() != frame.width * frame.height {
            return Err(MetricError::ShapeMismatch {
                what: "colour segmenter frame and mask".into(),
                left: format!("{}x{} pixels", frame.width, frame.height),
                right: format!("{} mask values", mask.len()),
            });
        }
        for (px, &m) in frame.rgb.chunks_exact(3).zip(mask) {
            let b = self.bin(px);
            self.total[b] = self.total[b].saturating_add(1);
            if m != 0 {
                self.robot[b] = self.robot[b].saturating_add(1);
            }
        }
        Ok(())
    }

    /// Pixels observed so far, and how many of them were robot.
    pub fn counts(&self) -> (u64, u64) {
        let sum = |v: &[u32]| v.iter().map(|&c| u64::from(c)).sum::<u64>();
        (sum(&self.total), sum(&self.robot))
    }

    /// The robot mask of `frame` (1 = robot): pixels whose colour bin was
    /// robot in more than half of its observations; unseen colours are not
    /// robot.
    pub fn segment(&self, frame: &RgbFrame) -> Vec<u8> {
        frame
            .rgb
            .chunks_exact(3)
            .map(|px| {
                let b = self.bin(px);
                u8::from(2 * u64::from(self.robot[b]) > u64::from(self.total[b]))
            })
            .collect()
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::video::mask_iou;

    /// A 4x2 frame: robot pixels white or grey, the rest red or dark grey,
    /// one colour shared by both classes.
    fn frame(colors: &[[f32; 3]]) -> RgbFrame {
        RgbFrame::new(colors.len(), 1, colors.iter().flatten().copied().collect()).unwrap()
    }

    #[test]
    fn learns_colour_classes_and_breaks_ties_by_majority() {
        let white = [0.95, 0.95, 0.95];
        let grey = [0.5, 0.5, 0.52];
        let red = [0.8, 0.1, 0.1];
        let shared = [0.3, 0.3, 0.3];
        let mut s = ColorSegmenter::new(4).unwrap();
        // `shared` is robot twice and background once: robot wins.
        s.observe(
            &frame(&[white, grey, red, shared, shared, shared]),
            &[1, 1, 0, 1, 1, 0],
        )
        .unwrap();
        assert_eq!(s.counts(), (6, 4));
        let blue = [0.1, 0.1, 0.9];
        let test = frame(&[red, white, shared, blue, grey]);
        assert_eq!(s.segment(&test), vec![0, 1, 1, 0, 1]);
        // Nearby shades fall into the same bin (16 levels: width 1/16).
        let near = frame(&[[0.96, 0.96, 0.94], [0.82, 0.12, 0.08]]);
        assert_eq!(s.segment(&near), vec![1, 0]);
        // A perfect segmentation of the training frame except the tie colour.
        let seg = s.segment(&frame(&[white, grey, red, shared, shared, shared]));
        let iou = mask_iou(&seg, &[1, 1, 0, 1, 1, 0]).unwrap();
        assert!((iou - 4.0 / 5.0).abs() < 1e-12, "{iou}");
    }

    #[test]
    fn rejects_bad_shapes_and_bit_counts() {
        assert!(ColorSegmenter::new(0).is_err());
        assert!(ColorSegmenter::new(9).is_err());
        let mut s = ColorSegmenter::new(3).unwrap();
        let e = s
            .observe(&frame(&[[0.0; 3], [1.0; 3]]), &[1])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("2x1 pixels") && e.contains("1 mask values"),
            "{e}"
        );
    }
}
