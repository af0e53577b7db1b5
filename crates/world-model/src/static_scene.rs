//! Keeping the static scene of a prediction from the masks (a sampler
//! option beyond the paper, [`crate::pipeline::SampleOptions::keep_static_margin_px`]).
//!
//! In a scene where only the robot moves things, a pixel the robot has not
//! covered in frames `0..=t` (nor come within `margin` pixels of) is in frame
//! `t` what it was in the first frame. The masks are the model's own input,
//! so the prediction can take those pixels from the first frame and keep the
//! model's drawing only in the region the robot has swept: the union of its
//! silhouettes so far, dilated by `margin` pixels (objects it pushes or
//! carries lie at its edge).

use crate::error::{Result, WorldModelError};
use tch::{Kind, Tensor};

/// The robot's silhouette per frame, `[B, 1, T, H, W]` (1 where any
/// channel of the mask videos `[B, 3, T, H, W]` in {-1, 1} is > 0, else 0):
/// the one definition the swept region and the training's motion weights use.
pub fn robot_silhouettes(masks: &Tensor) -> Tensor {
    masks
        .amax([1i64].as_slice(), true)
        .gt(0.0)
        .to_kind(Kind::Float)
}

/// The swept region `[B, 1, T, H, W]` (1 inside, 0 outside) of mask videos
/// `[B, 3, T, H, W]` in {-1, 1}: a pixel is inside at frame `t` when any
/// channel of any frame `0..=t` is > 0 within `margin_px` pixels (a square
/// neighbourhood).
pub fn swept_region(masks: &Tensor, margin_px: u32) -> Result<Tensor> {
    let size = masks.size();
    if size.len() != 5 {
        return Err(WorldModelError::input(
            "masks",
            format!("shape {size:?}: expected [B, 3, T, H, W]"),
        ));
    }
    // A margin beyond the frame covers it all: clamp it to the frame's size.
    let m = i64::from(margin_px).min(size[3].max(size[4]));
    let robot = robot_silhouettes(masks); // [B, 1, T, H, W]
    let (so_far, _) = robot.cummax(2); // the union over frames 0..=t
    Ok(so_far.max_pool3d(
        [1, 2 * m + 1, 2 * m + 1],
        [1, 1, 1],
        [0, m, m],
        [1, 1, 1],
        false,
    ))
}

/// `videos` `[B, 3, T, H, W]` with every pixel outside the [`swept_region`]
/// of `masks` (`[B, 3, T, H, W]` in {-1, 1}) taken from `first_frames`
/// (`[B, 3, H, W]`, the same value range as the videos).
pub fn keep_static(
    videos: &Tensor,
    first_frames: &Tensor,
    masks: &Tensor,
    margin_px: u32,
) -> Result<Tensor> {
    let (v, f, m) = (videos.size(), first_frames.size(), masks.size());
    if v.len() != 5 || m != v || f.len() != 4 || f[..2] != v[..2] || f[2..] != v[3..] {
        return Err(WorldModelError::input(
            "keep_static",
            format!(
                "videos {v:?}, first frames {f:?}, masks {m:?}: expected [B, 3, T, H, W], [B, 3, H, W] and [B, 3, T, H, W]"
            ),
        ));
    }
    let swept = swept_region(masks, margin_px)?.to_kind(videos.kind()); // [B, 1, T, H, W]
    let first = first_frames.unsqueeze(2).to_kind(videos.kind()); // [B, 3, 1, H, W]
    Ok(&swept * videos + (-&swept + 1.0) * first)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use tch::Device;

    fn masks_with(pixels: &[(i64, i64, i64)]) -> Tensor {
        // One clip of 3 frames of 6 x 8 pixels; the robot at (frame, row, column).
        let m = Tensor::full([1, 3, 3, 6, 8], -1.0, (Kind::Float, Device::Cpu));
        for &(t, y, x) in pixels {
            let _ = m
                .get(0)
                .narrow(0, 2, 1)
                .narrow(1, t, 1)
                .narrow(2, y, 1)
                .narrow(3, x, 1)
                .fill_(1.0);
        }
        m
    }

    #[test]
    fn the_swept_region_grows_over_frames_and_by_the_margin() {
        let masks = masks_with(&[(0, 0, 0), (2, 5, 7)]);
        let s = swept_region(&masks, 1).unwrap();
        assert_eq!(s.size(), vec![1, 1, 3, 6, 8]);
        let at = |t: i64, y: i64, x: i64| s.double_value(&[0, 0, t, y, x]);
        for t in 0..3 {
            // Frame 0's pixel and its 1-pixel margin stay swept in every later frame.
            assert_eq!(
                (at(t, 0, 0), at(t, 1, 1), at(t, 0, 2)),
                (1.0, 1.0, 0.0),
                "frame {t}"
            );
        }
        // Frame 2's pixel only from frame 2 on.
        assert_eq!((at(1, 5, 7), at(2, 5, 7), at(2, 4, 6)), (0.0, 1.0, 1.0));
        // 4 + 4 swept pixels in frame 2, 4 in frames 0 and 1.
        assert_eq!(s.sum(Kind::Float).double_value(&[]), 4.0 + 4.0 + 8.0);
        // Margin 0: the silhouettes alone; a huge margin: everything.
        assert_eq!(
            swept_region(&masks, 0)
                .unwrap()
                .sum(Kind::Float)
                .double_value(&[]),
            4.0
        );
        assert_eq!(
            swept_region(&masks, u32::MAX)
                .unwrap()
                .sum(Kind::Float)
                .double_value(&[]),
            3.0 * 48.0
        );
    }

    #[test]
    fn outside_the_swept_region_the_first_frame_inside_the_prediction() {
        let masks = masks_with(&[(1, 2, 3)]);
        let videos = Tensor::full([1, 3, 3, 6, 8], 0.5, (Kind::Float, Device::Cpu));
        let first = Tensor::full([1, 3, 6, 8], -0.25, (Kind::Float, Device::Cpu));
        let out = keep_static(&videos, &first, &masks, 0).unwrap();
        assert_eq!(out.size(), videos.size());
        for c in 0..3 {
            assert_eq!(out.double_value(&[0, c, 0, 2, 3]), -0.25);
            assert_eq!(out.double_value(&[0, c, 1, 2, 3]), 0.5);
            assert_eq!(out.double_value(&[0, c, 2, 2, 3]), 0.5);
            assert_eq!(out.double_value(&[0, c, 2, 2, 4]), -0.25);
        }
        let wrong = Tensor::zeros([1, 3, 5, 8], (Kind::Float, Device::Cpu));
        let e = keep_static(&videos, &wrong, &masks, 0)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("keep_static") && e.contains("[B, 3, H, W]"),
            "{e}"
        );
    }
}
