//! The lens-distortion remap: each output pixel copies the nearest pixel
//! of an undistorted pinhole buffer (see the module header of `raster`).

use super::{Pinhole, RenderOutput};
use crate::camera::{Distortion, Intrinsics};

/// Largest pinhole buffer side relative to the output image when rendering
/// with distortion.
const MAX_PINHOLE_SCALE: f64 = 3.0;

/// The distortion remap: output pixel -> pinhole buffer index.
#[derive(Debug, Clone)]
pub(super) struct Remap {
    /// Pinhole buffer parameters.
    pub(super) pinhole: Pinhole,
    /// Per output pixel, the pinhole buffer index, or `u32::MAX` when the
    /// pixel's ray is not representable (background).
    source: Vec<u32>,
}

impl Remap {
    /// The remap of the camera with intrinsics `k` and active distortion
    /// `d`, precomputed by [`super::Rasterizer::new`].
    pub(super) fn new(k: &Intrinsics, d: &Distortion) -> Self {
        // Undistorted normalized coordinates of every output pixel centre.
        let n = k.width as usize * k.height as usize;
        let mut undistorted = Vec::with_capacity(n);
        let (mut lo_x, mut hi_x) = (f64::INFINITY, f64::NEG_INFINITY);
        let (mut lo_y, mut hi_y) = (f64::INFINITY, f64::NEG_INFINITY);
        for v in 0..k.height {
            for u in 0..k.width {
                let xd = (f64::from(u) - k.cx) / k.fx;
                let yd = (f64::from(v) - k.cy) / k.fy;
                let (x, y) = d.undistort(xd, yd);
                // Keep only rays that the lens model maps back correctly.
                let (rx, ry) = d.distort(x, y);
                let ok = x.is_finite()
                    && y.is_finite()
                    && (rx - xd).abs() < 1e-6
                    && (ry - yd).abs() < 1e-6;
                if ok {
                    lo_x = lo_x.min(x);
                    hi_x = hi_x.max(x);
                    lo_y = lo_y.min(y);
                    hi_y = hi_y.max(y);
                    undistorted.push(Some((x, y)));
                } else {
                    undistorted.push(None);
                }
            }
        }
        if !(lo_x <= hi_x && lo_y <= hi_y) {
            (lo_x, hi_x, lo_y, hi_y) = (0.0, 0.0, 0.0, 0.0);
        }
        // Same focal lengths as the camera unless that makes the buffer
        // larger than MAX_PINHOLE_SCALE times the output.
        let span_x = k.fx * (hi_x - lo_x);
        let span_y = k.fy * (hi_y - lo_y);
        let scale = 1.0f64
            .min(MAX_PINHOLE_SCALE * f64::from(k.width) / span_x.max(1e-9))
            .min(MAX_PINHOLE_SCALE * f64::from(k.height) / span_y.max(1e-9));
        let (fx, fy) = (k.fx * scale, k.fy * scale);
        // One pixel of margin on each side.
        let cx = 1.0 - fx * lo_x;
        let cy = 1.0 - fy * lo_y;
        let width = (fx * (hi_x - lo_x)).ceil() as u32 + 3;
        let height = (fy * (hi_y - lo_y)).ceil() as u32 + 3;
        let source = undistorted
            .iter()
            .map(|p| match p {
                Some((x, y)) => {
                    let su = (fx * x + cx).round();
                    let sv = (fy * y + cy).round();
                    let index = sv * f64::from(width) + su;
                    let inside =
                        su >= 0.0 && sv >= 0.0 && su < f64::from(width) && sv < f64::from(height);
                    if inside && index < f64::from(u32::MAX) {
                        index as u32
                    } else {
                        u32::MAX
                    }
                }
                None => u32::MAX,
            })
            .collect();
        Remap {
            pinhole: Pinhole {
                fx: fx as f32,
                fy: fy as f32,
                cx: cx as f32,
                cy: cy as f32,
                width,
                height,
            },
            source,
        }
    }

    /// Copies into `out` (camera size) the pixels of `buffer` (the pinhole
    /// buffer) that each output pixel maps to; the others keep their values.
    pub(super) fn copy_to(&self, buffer: &RenderOutput, out: &mut RenderOutput) {
        for ((&src, label), depth) in self
            .source
            .iter()
            .zip(out.labels.iter_mut())
            .zip(out.depth_m.iter_mut())
        {
            let src = src as usize;
            if let (Some(&l), Some(&d)) = (buffer.labels.get(src), buffer.depth_m.get(src)) {
                *label = l;
                *depth = d;
            }
        }
    }
}
