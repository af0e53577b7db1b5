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

    /// The convolution (3×3, stride 1, padding 1) of `x` upsampled 2× in
    /// space by nearest interpolation, without building the upsampled
    /// input: `[B, Cin, T, H, W] -> [B, Cout, T, 2H, 2W]`. Output pixel
    /// `(2i + a, 2j + b)` sees input rows `i - 1 + a, i + a` and columns
    /// `j - 1 + b, j + b` only, through a 2×2 kernel of the 3×3 one's taps
    /// summed ([`phase_kernels`]): the four phases are one 2×2 convolution
    /// of the padded input with `4 Cout` outputs, interleaved by a pixel
    /// shuffle: 16 products per input pixel and channel pair instead of 36,
    /// the same sums in another order.
    fn forward_upsampled(&self, x: &Tensor) -> Result<Tensor> {
        let s = x.size();
        let (h, w) = (s[3], s[4]);
        let (images, b, t) = frames_to_images(x)?;
        // [B*T, Cin, H, W] -> [B*T, Cin, H + 2, W + 2]
        let padded = images.f_constant_pad_nd([1, 1, 1, 1])?;
        let cout = self.weight.size()[0];
        // [Cout] -> [4 Cout], each phase's bias.
        let bias = self
            .bias
            .f_unsqueeze(1)?
            .f_expand([cout, 4], false)?
            .f_reshape([4 * cout])?;
        // [B*T, 4 Cout, H + 1, W + 1]
        let phases = crate::cpu_bf16::conv(
            &padded,
            &phase_kernels(&self.weight)?,
            Some(&bias),
            [1, 1],
            [0, 0],
        )?;
        // [B*T, 4 Cout, H + 1, W + 1] -> [B*T, Cout, 2H + 2, 2W + 2] -> [B*T, Cout, 2H, 2W]:
        // with the phases in the order (1 - a, 1 - b), output pixel (r, q) is
        // the shuffled pixel (r + 1, q + 1).
        let out = phases
            .f_pixel_shuffle(2)?
            .f_narrow(2, 1, 2 * h)?
            .f_narrow(3, 1, 2 * w)?;
        images_to_frames(&out, b, t)
    }
}

/// The 2×2 kernels of [`FrameConv2d::forward_upsampled`]'s phases from a 3×3
/// kernel `[Cout, Cin, 3, 3]`: for the even output rows (`a = 0`) the taps
/// `[k0, k1 + k2]` over input rows `i - 1, i`, for the odd ones `[k0 + k1, k2]`
/// over `i, i + 1`; columns alike. `[4 Cout, Cin, 2, 2]`, output channel
/// `4c + 2(1 - a) + (1 - b)`: the order a pixel shuffle of the phases needs.
fn phase_kernels(weight: &Tensor) -> Result<Tensor> {
    let kind = weight.kind();
    // The taps of `k` along `dim` (2 rows, 3 columns) for phase `a`.
    let fold = |k: &Tensor, dim: i64, a: i64| -> Result<Tensor> {
        let (one, two) = if a == 0 {
            (
                k.narrow(dim, 0, 1),
                k.narrow(dim, 1, 2).f_sum_dim_intlist(dim, true, kind)?,
            )
        } else {
            (
                k.narrow(dim, 0, 2).f_sum_dim_intlist(dim, true, kind)?,
                k.narrow(dim, 2, 1),
            )
        };
        Ok(Tensor::f_cat(&[one, two], dim)?)
    };
    let mut kernels = Vec::with_capacity(4);
    for a in [1, 0] {
        let rows = fold(weight, 2, a)?; // [Cout, Cin, 2, 3]
        for b in [1, 0] {
            kernels.push(fold(&rows, 3, b)?); // [Cout, Cin, 2, 2]
        }
    }
    let s = weight.size();
    // 4 x [Cout, Cin, 2, 2] -> [Cout, 4, Cin, 2, 2] -> [4 Cout, Cin, 2, 2]
    Ok(Tensor::f_stack(&kernels, 1)?.f_reshape([4 * s[0], s[1], 2, 2])?)
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

    /// Whether it halves the frame count (and so [`Self::forward`] pools
    /// frame pairs first).
    pub(super) fn compresses_time(&self) -> bool {
        self.compress_time
    }

    /// `[B, C, T, H, W] -> [B, C, T', (H - 1) / 2 + 1, (W - 1) / 2 + 1]` with
    /// `T' = T` or, compressing time, `T / 2` (even `T`) or `1 + (T - 1) / 2` (odd).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        if self.compress_time {
            self.forward_time_pooled(&pool_frame_pairs(x)?)
        } else {
            self.forward_time_pooled(x)
        }
    }

    /// The downsampler's spatial part alone, for an input already pooled in
    /// time (when it compresses time): `[B, C, T, H, W] -> [B, C, T, (H - 1)
    /// / 2 + 1, (W - 1) / 2 + 1]`.
    pub(super) fn forward_time_pooled(&self, x: &Tensor) -> Result<Tensor> {
        // [B, C, T, H, W] -> [B, C, T, H + 1, W + 1]
        let x = x.f_constant_pad_nd([0, 1, 0, 1])?;
        self.conv.forward(&x)
    }
}

/// A time-compressing downsampler's pooling: the mean of each pair of
/// frames (diffusers' `avg_pool3d` of kernel and stride `[2, 1, 1]`), after
/// the first frame kept alone when the count is odd: `[B, C, T, H, W] ->
/// [B, C, T', H, W]`, `T' = T / 2` (even `T`) or `1 + (T - 1) / 2` (odd).
/// A reshape and a mean: libtorch has no bf16 `avg_pool3d` on the CPU.
pub(super) fn pool_frame_pairs(x: &Tensor) -> Result<Tensor> {
    let pool = |x: &Tensor| -> Result<Tensor> {
        let s = x.size();
        // [B, C, 2n, H, W] -> [B, C, n, 2, H, W]
        let pairs = x.f_reshape([s[0], s[1], s[2] / 2, 2, s[3], s[4]])?;
        // [B, C, n, 2, H, W] -> [B, C, n, H, W]
        Ok(pairs.f_mean_dim([3i64].as_slice(), false, None::<tch::Kind>)?)
    };
    let t = x.size()[2];
    if t % 2 == 0 {
        return pool(x);
    }
    let first = x.narrow(2, 0, 1);
    if t == 1 {
        return Ok(first);
    }
    Ok(Tensor::f_cat(&[first, pool(&x.narrow(2, 1, t - 1))?], 2)?)
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
    /// `2T` (even `T`), `1 + 2 (T - 1)` (odd `T > 1`) or 1. The convolution
    /// runs on each frame before its repetition in time (the same frame
    /// twice gives the same output twice) and without the spatial
    /// upsampling ([`FrameConv2d::forward_upsampled`]).
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let t = x.size()[2];
        // [B, C, T, H, W] -> [B, C, T, 2H, 2W]
        let y = self.conv.forward_upsampled(x)?;
        if !(self.compress_time && t > 1) {
            return Ok(y.f_contiguous()?);
        }
        // Nearest 2x in time: output frame d reads frame d / 2, after a
        // single first frame when T is odd.
        let first = t % 2;
        let sources: Vec<i64> = (0..first)
            .chain((0..2 * (t - first)).map(|d| first + d / 2))
            .collect();
        // [B, C, T, 2H, 2W] -> [B, C, T', 2H, 2W]
        Ok(y.f_index_select(2, &Tensor::from_slice(&sources).to_device(y.device()))?)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    /// diffusers' upsampler as written there: the frames upsampled in
    /// space (and time), then the 3x3 convolution on every frame.
    fn upsample_as_diffusers(up: &Upsample3D, x: &Tensor) -> Tensor {
        let s = x.size();
        let (t, h, w) = (s[2], s[3], s[4]);
        let space = |x: &Tensor| {
            let (images, b, t) = frames_to_images(x).unwrap();
            let images = images.upsample_nearest2d([2 * h, 2 * w], 2.0, 2.0);
            images_to_frames(&images, b, t).unwrap()
        };
        let x = if up.compress_time && t > 1 && t % 2 == 1 {
            let rest = x.narrow(2, 1, t - 1).upsample_nearest3d(
                [2 * (t - 1), 2 * h, 2 * w],
                2.0,
                2.0,
                2.0,
            );
            Tensor::cat(&[space(&x.narrow(2, 0, 1)), rest], 2)
        } else if up.compress_time && t > 1 {
            x.upsample_nearest3d([2 * t, 2 * h, 2 * w], 2.0, 2.0, 2.0)
        } else {
            space(x)
        };
        up.conv.forward(&x).unwrap()
    }

    #[test]
    fn upsampler_convolves_each_frame_at_its_own_size_with_diffusers_values() {
        tch::manual_seed(5);
        let vs = nn::VarStore::new(Device::Cpu);
        let ups = [
            Upsample3D::new(vs.root() / "time", 6, true),
            Upsample3D::new(vs.root() / "space", 6, false),
        ];
        tch::no_grad(|| {
            for mut v in vs.variables().into_values() {
                let r = Tensor::randn_like(&v) * 0.3;
                v.copy_(&r);
            }
        });
        for up in &ups {
            for (t, h, w) in [(3, 4, 5), (2, 3, 3), (1, 5, 4), (5, 1, 2)] {
                let x = Tensor::randn([2, 6, t, h, w], (Kind::Float, Device::Cpu))
                    .set_requires_grad(true);
                let ours = up.forward(&x).unwrap();
                let theirs = upsample_as_diffusers(up, &x);
                assert_eq!(ours.size(), theirs.size(), "{t}x{h}x{w}");
                let diff = (&ours - &theirs).abs().max().double_value(&[]);
                assert!(diff < 1e-5, "{t}x{h}x{w}: {diff}");
                // The gradients too (decode_backward replays the upsamplers).
                let g = Tensor::randn_like(&ours);
                let grads = |out: &Tensor| {
                    let mut params = vec![x.shallow_clone()];
                    params.push(up.conv.weight.shallow_clone());
                    Tensor::run_backward(&[(out * &g).sum(Kind::Float)], &params, false, false)
                };
                for (a, b) in grads(&ours).iter().zip(grads(&theirs).iter()) {
                    let d = (a - b).abs().max().double_value(&[]);
                    assert!(d < 1e-4, "{t}x{h}x{w}: gradient {d}");
                }
            }
        }
    }
}
