//! The VAE's resamplers: diffusers' `CogVideoXDownsample3D` and `CogVideoXUpsample3D`,
//! with the per-frame 2D convolution they end with.

use crate::error::Result;
use tch::nn::{self, Init};
use tch::Tensor;

/// `[B, C, T, H, W] -> [B*T, C, H, W]`, each frame an image.
fn frames_to_images(x: &Tensor) -> Result<(Tensor, i64, i64)> {
    let s = x.size();
    let (b, c, t, h, w) = (s[0], s[1], s[2], s[3], s[4]);
    let images = x.f_permute([0, 2, 1, 3, 4])?.f_reshape([b * t, c, h, w])?;
    Ok((images, b, t))
}

/// `[B*T, C, H, W] -> [B, C, T, H, W]`.
fn images_to_frames(x: &Tensor, b: i64, t: i64) -> Result<Tensor> {
    let s = x.size();
    Ok(x.f_reshape([b, t, s[1], s[2], s[3]])?
        .f_permute([0, 2, 1, 3, 4])?)
}

/// A 2D convolution applied to every frame (`conv.weight`, `conv.bias`).
#[derive(Debug)]
pub(super) struct FrameConv2d {
    weight: Tensor,
    bias: Tensor,
    stride: i64,
    padding: i64,
}

impl FrameConv2d {
    fn new(p: nn::Path, in_channels: i64, out_channels: i64, stride: i64, padding: i64) -> Self {
        Self {
            weight: p.var(
                "weight",
                &[out_channels, in_channels, 3, 3],
                Init::Const(0.),
            ),
            bias: p.var("bias", &[out_channels], Init::Const(0.)),
            stride,
            padding,
        }
    }

    /// `[B, Cin, T, H, W] -> [B, Cout, T, H', W']`.
    pub(super) fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (images, b, t) = frames_to_images(x)?;
        let out = crate::cpu_bf16::conv(
            &images,
            &self.weight,
            Some(&self.bias),
            [self.stride, self.stride],
            [self.padding, self.padding],
        )?;
        images_to_frames(&out, b, t)
    }
}

/// diffusers' `CogVideoXDownsample3D`: optional temporal 2× average pooling (an odd
/// frame count keeps the first frame and pools the rest), then zero padding of one
/// pixel right and bottom and a stride-2 3×3 convolution on every frame.
#[derive(Debug)]
pub struct Downsample3D {
    pub(super) conv: FrameConv2d,
    compress_time: bool,
}

impl Downsample3D {
    /// A downsampler of `channels` channels (`conv`).
    pub fn new(p: nn::Path, channels: i64, compress_time: bool) -> Self {
        Self {
            conv: FrameConv2d::new(p / "conv", channels, channels, 2, 0),
            compress_time,
        }
    }

    /// `[B, C, T, H, W] -> [B, C, T', (H - 1) / 2 + 1, (W - 1) / 2 + 1]` with
    /// `T' = T` or, compressing time, `T / 2` (even `T`) or `1 + (T - 1) / 2` (odd).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let x = if self.compress_time {
            let t = x.size()[2];
            // Average of frame pairs (diffusers' avg_pool3d of kernel and
            // stride [2, 1, 1]), as a reshape and a mean: libtorch has no
            // bf16 avg_pool3d on the CPU.
            let pool = |x: &Tensor| -> Result<Tensor> {
                let s = x.size();
                // [B, C, 2n, H, W] -> [B, C, n, 2, H, W]
                let pairs = x.f_reshape([s[0], s[1], s[2] / 2, 2, s[3], s[4]])?;
                // [B, C, n, 2, H, W] -> [B, C, n, H, W]
                Ok(pairs.f_mean_dim([3i64].as_slice(), false, None::<tch::Kind>)?)
            };
            if t % 2 == 1 {
                let first = x.narrow(2, 0, 1);
                if t > 1 {
                    Tensor::f_cat(&[first, pool(&x.narrow(2, 1, t - 1))?], 2)?
                } else {
                    first
                }
            } else {
                pool(x)?
            }
        } else {
            x.shallow_clone()
        };
        // [B, C, T, H, W] -> [B, C, T, H + 1, W + 1]
        let x = x.f_constant_pad_nd([0, 1, 0, 1])?;
        self.conv.forward(&x)
    }
}

/// diffusers' `CogVideoXUpsample3D`: nearest 2× upsampling in space, and in time when
/// compressing time (an odd frame count above 1 keeps the first frame single), then a
/// 3×3 convolution on every frame.
#[derive(Debug)]
pub struct Upsample3D {
    conv: FrameConv2d,
    compress_time: bool,
}

impl Upsample3D {
    /// An upsampler of `channels` channels (`conv`).
    pub fn new(p: nn::Path, channels: i64, compress_time: bool) -> Self {
        Self {
            conv: FrameConv2d::new(p / "conv", channels, channels, 1, 1),
            compress_time,
        }
    }

    /// `[B, C, T, H, W] -> [B, C, T', 2H, 2W]` with `T' = T` or, compressing time,
    /// `2T` (even `T`), `1 + 2 (T - 1)` (odd `T > 1`) or 1.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let s = x.size();
        let (t, h, w) = (s[2], s[3], s[4]);
        let up3 = |x: &Tensor, t_out: i64, st: f64| {
            x.f_upsample_nearest3d([t_out, 2 * h, 2 * w], st, 2.0, 2.0)
        };
        let x = if self.compress_time && t > 1 && t % 2 == 1 {
            // [B, C, H, W] -> [B, C, 1, 2H, 2W]
            let first = x
                .select(2, 0)
                .f_upsample_nearest2d([2 * h, 2 * w], 2.0, 2.0)?
                .unsqueeze(2);
            // [B, C, T - 1, H, W] -> [B, C, 2 (T - 1), 2H, 2W]
            let rest = up3(&x.narrow(2, 1, t - 1), 2 * (t - 1), 2.0)?;
            Tensor::f_cat(&[first, rest], 2)?
        } else if self.compress_time && t > 1 {
            up3(x, 2 * t, 2.0)?
        } else {
            // Space only, frame by frame: [B, C, T, H, W] -> [B, C, T, 2H, 2W].
            let (images, b, t) = frames_to_images(x)?;
            let images = images.f_upsample_nearest2d([2 * h, 2 * w], 2.0, 2.0)?;
            images_to_frames(&images, b, t)?
        };
        self.conv.forward(&x)
    }
}
