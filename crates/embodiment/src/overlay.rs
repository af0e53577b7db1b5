//! Pictures of masks for people to look at: label maps coloured and shaded
//! by depth over a checkerboard floor, panels side by side, animated GIFs.

use crate::camera::Camera;
use crate::raster::RenderOutput;
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbaImage};
use std::path::Path;

/// Errors of the picture code.
#[derive(Debug, thiserror::Error)]
pub enum OverlayError {
    /// A frame's byte count does not fit the stated size.
    #[error("GIF frame {index}: {len} bytes do not hold {width}x{height} RGB pixels")]
    FrameSize {
        /// The frame.
        index: usize,
        /// Its bytes.
        len: usize,
        /// Stated width.
        width: u32,
        /// Stated height.
        height: u32,
    },
    /// The GIF encoder failed.
    #[error("encoding a GIF: {0}")]
    Encode(#[from] image::ImageError),
    /// Writing the file failed.
    #[error(transparent)]
    File(#[from] bridgev2w_io::FileError),
}

/// A distinct colour per label (golden-angle hue walk).
pub fn label_color(label: u16) -> [f32; 3] {
    let h = (label as f32 * 137.508).rem_euclid(360.0) / 60.0;
    let (s, v) = (0.65, 0.95);
    let c = v * s;
    let x = c * (1.0 - (h.rem_euclid(2.0) - 1.0).abs());
    let (r, g, b) = match h as u32 {
        0 => (c, x, 0.0),
        1 => (x, c, 0.0),
        2 => (0.0, c, x),
        3 => (0.0, x, c),
        4 => (x, 0.0, c),
        _ => (c, 0.0, x),
    };
    let m = v - c;
    [r + m, g + m, b + m]
}

/// Background: a checkerboard floor (z = 0 in the robot base frame, 10 cm
/// squares) under a plain sky, seen through `camera`.
pub fn floor_background(camera: &Camera) -> Vec<u8> {
    let (w, h) = (camera.intrinsics.width, camera.intrinsics.height);
    let eye = camera.world_from_camera.translation.vector;
    let mut out = vec![0u8; (w * h * 3) as usize];
    for v in 0..h {
        for u in 0..w {
            let ray = camera.pixel_ray(u as f64, v as f64);
            let i = ((v * w + u) * 3) as usize;
            let rgb = if ray.z < -1e-6 && eye.z > 0.0 {
                let t = -eye.z / ray.z;
                let p = eye + ray * t;
                let check = ((p.x / 0.1).floor() as i64 + (p.y / 0.1).floor() as i64).rem_euclid(2);
                let fade = (1.0 / (1.0 + 0.15 * t)) as f32;
                let base = if check == 0 { 200.0 } else { 150.0 };
                [base * fade + 40.0; 3]
            } else {
                [215.0, 225.0, 240.0]
            };
            out[i..i + 3].copy_from_slice(&rgb.map(|c| c.min(255.0) as u8));
        }
    }
    out
}

/// RGB image: robot links coloured by label and shaded by depth over `background`.
pub fn overlay(frame: &RenderOutput, background: &[u8]) -> Vec<u8> {
    let mut out = background.to_vec();
    let (lo, hi) = frame
        .depth_m
        .iter()
        .filter(|d| d.is_finite())
        .fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), &d| {
            (lo.min(d), hi.max(d))
        });
    let span = (hi - lo).max(1e-3);
    for (i, (&label, &d)) in frame.labels.iter().zip(&frame.depth_m).enumerate() {
        if label == 0 {
            continue;
        }
        let shade = 1.0 - 0.45 * (d - lo) / span;
        let c = label_color(label);
        for k in 0..3 {
            out[i * 3 + k] = (c[k] * shade * 255.0).clamp(0.0, 255.0) as u8;
        }
    }
    out
}

/// Draws a label map over an RGB8 frame (`w` x `h`, both row-major): every
/// robot pixel is tinted by `tint` (0 none .. 1 opaque) towards its link's
/// colour, and the outline of each link (a labelled pixel with a
/// 4-neighbour of another label) is drawn in that colour. The real frame
/// stays visible, so a mask that is off by a few pixels shows as an offset
/// outline.
pub fn draw_outlines(rgb: &mut [u8], labels: &[u16], w: usize, h: usize, tint: f32) {
    let at = |x: usize, y: usize| labels[y * w + x];
    for y in 0..h {
        for x in 0..w {
            let l = at(x, y);
            if l == 0 {
                continue;
            }
            let edge = x == 0
                || y == 0
                || x + 1 == w
                || y + 1 == h
                || at(x - 1, y) != l
                || at(x + 1, y) != l
                || at(x, y - 1) != l
                || at(x, y + 1) != l;
            let c = label_color(l);
            let a = if edge { 1.0 } else { tint };
            let i = (y * w + x) * 3;
            for (k, &ck) in c.iter().enumerate() {
                let v = f32::from(rgb[i + k]) * (1.0 - a) + ck * 255.0 * a;
                rgb[i + k] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
}

/// Nearest-neighbour upscaling of a `w` x `h` RGB8 image by `k`.
pub fn upscale(rgb: &[u8], w: usize, h: usize, k: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(rgb.len() * k * k);
    for y in 0..h * k {
        for x in 0..w * k {
            let i = ((y / k) * w + x / k) * 3;
            out.extend_from_slice(&rgb[i..i + 3]);
        }
    }
    out
}

/// RGB8 panels of `w` x `h` side by side: `[h, w * n, 3]`.
pub fn side_by_side(panels: &[&[u8]], w: usize, h: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(panels.len() * w * h * 3);
    for y in 0..h {
        for p in panels {
            out.extend_from_slice(&p[y * w * 3..(y + 1) * w * 3]);
        }
    }
    out
}

/// A binary mask (non-zero = robot) as a white-on-black RGB8 image.
pub fn mask_rgb(mask: &[u8]) -> Vec<u8> {
    mask.iter()
        .flat_map(|&m| if m != 0 { [255, 255, 255] } else { [0, 0, 0] })
        .collect()
}

/// An animated, looping GIF of RGB8 frames at `fps` frames per second.
pub fn encode_gif(
    width: u32,
    height: u32,
    frames: &[Vec<u8>],
    fps: u32,
) -> Result<Vec<u8>, OverlayError> {
    let mut bytes = Vec::new();
    {
        let mut enc = GifEncoder::new_with_speed(&mut bytes, 20);
        enc.set_repeat(Repeat::Infinite)?;
        let delay = Delay::from_numer_denom_ms(1000, fps.max(1));
        for (index, rgb) in frames.iter().enumerate() {
            let rgba: Vec<u8> = rgb
                .chunks_exact(3)
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect();
            let img = RgbaImage::from_raw(width, height, rgba).ok_or(OverlayError::FrameSize {
                index,
                len: rgb.len(),
                width,
                height,
            })?;
            enc.encode_frame(Frame::from_parts(img, 0, 0, delay))?;
        }
    }
    Ok(bytes)
}

/// [`encode_gif`], written to `path` atomically.
pub fn write_gif(
    path: &Path,
    width: u32,
    height: u32,
    frames: &[Vec<u8>],
    fps: u32,
) -> Result<(), OverlayError> {
    let bytes = encode_gif(width, height, frames, fps)?;
    bridgev2w_io::atomic::write_atomic(path, &bytes)?;
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn panels_and_upscaling_place_pixels() {
        let a = [1u8, 2, 3, 4, 5, 6]; // 2x1
        let up = upscale(&a, 2, 1, 2); // 4x2
        assert_eq!(&up[..12], &[1, 2, 3, 1, 2, 3, 4, 5, 6, 4, 5, 6]);
        assert_eq!(&up[12..], &up[..12]);
        let b = [7u8, 8, 9, 10, 11, 12];
        assert_eq!(
            side_by_side(&[&a, &b], 2, 1),
            vec![1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12]
        );
        assert_eq!(mask_rgb(&[0, 3]), vec![0, 0, 0, 255, 255, 255]);
    }

    #[test]
    fn outlines_mark_link_borders_and_keep_the_background() {
        // 4x3: a 2x2 link (label 1) at the left, background elsewhere.
        let labels = [1u16, 1, 0, 0, 1, 1, 0, 0, 0, 0, 0, 0];
        let mut rgb = vec![10u8; 4 * 3 * 3];
        draw_outlines(&mut rgb, &labels, 4, 3, 0.3);
        let c = label_color(1).map(|v| (v * 255.0).round() as u8);
        assert_eq!(&rgb[0..3], &c, "edge pixel in the link colour");
        assert_eq!(
            &rgb[2 * 3..2 * 3 + 3],
            &[10, 10, 10],
            "background untouched"
        );
        let mut big = vec![1u16; 9];
        big[0] = 0;
        let mut rgb = vec![0u8; 27];
        draw_outlines(&mut rgb, &big, 3, 3, 0.0);
        assert_eq!(&rgb[4 * 3..4 * 3 + 3], &[0, 0, 0], "interior, no tint");
    }

    #[test]
    fn gifs_decode_and_bad_frames_are_refused() {
        let frames = vec![vec![255u8; 4 * 2 * 3], vec![0u8; 4 * 2 * 3]];
        let bytes = encode_gif(4, 2, &frames, 5).unwrap();
        assert!(bytes.starts_with(b"GIF89a"));
        let e = encode_gif(4, 2, &[vec![0u8; 5]], 5)
            .unwrap_err()
            .to_string();
        assert!(e.contains("frame 0") && e.contains("4x2"), "{e}");
    }
}
