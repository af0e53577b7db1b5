//! Colour overlays of label maps and animated GIFs, for looking at masks.

use anyhow::{Context, Result};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_embodiment::raster::RenderOutput;
use image::codecs::gif::{GifEncoder, Repeat};
use image::{Delay, Frame, RgbaImage};
use std::path::Path;

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

/// Writes an animated GIF of RGB frames (`fps` frames per second), atomically.
pub fn write_gif(path: &Path, width: u32, height: u32, frames: &[Vec<u8>], fps: u32) -> Result<()> {
    let mut bytes = Vec::new();
    {
        let mut enc = GifEncoder::new_with_speed(&mut bytes, 20);
        enc.set_repeat(Repeat::Infinite)?;
        let delay = Delay::from_numer_denom_ms(1000, fps.max(1));
        for rgb in frames {
            let rgba: Vec<u8> = rgb
                .chunks_exact(3)
                .flat_map(|p| [p[0], p[1], p[2], 255])
                .collect();
            let img = RgbaImage::from_raw(width, height, rgba).context("frame size mismatch")?;
            enc.encode_frame(Frame::from_parts(img, 0, 0, delay))?;
        }
    }
    bridgev2w_embodiment::npy::write_atomic(path, &bytes)
        .with_context(|| format!("writing {}", path.display()))?;
    Ok(())
}
