//! Layers of the CogVideoX 3D causal VAE, after diffusers'
//! `models/autoencoders/autoencoder_kl_cogvideox.py`, `downsampling.py` and
//! `upsampling.py` (0.42.1). Every struct takes a [`nn::Path`] and creates its
//! parameters under diffusers' exact names, so a `vae/diffusion_pytorch_model.safetensors`
//! loads unchanged.
//!
//! Videos are `[batch, channels, frames, height, width]` throughout. Parameters are
//! created with constant values (zeros, ones for norm scales) without touching the
//! global RNG: the model is meant to be loaded from weights, or randomised with
//! [`crate::vae::init_like_pytorch`] to train from scratch.
//!
//! Causal temporal convolutions carry a *conv cache* between the frame batches that
//! the autoencoder feeds through the encoder/decoder one after another: the last
//! `kernel - 1` (padded) input frames of the previous batch, which replace the
//! first-frame replication padding of the first batch. The cache types here mirror
//! diffusers' nested `conv_cache` dicts, holding only the entries that are ever read
//! (convolutions with a temporal kernel above 1).

use crate::error::{Result, WorldModelError};
use tch::nn::{self, Init};
use tch::Tensor;

/// The resnets' nonlinearity (`act_fn` in the config, diffusers' `get_activation`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Activation {
    /// `silu` / `swish`: `x * sigmoid(x)`.
    Silu,
    /// `mish`: `x * tanh(softplus(x))`.
    Mish,
    /// `gelu` (exact, erf-based).
    Gelu,
    /// `relu`.
    Relu,
}

impl Activation {
    /// Parses diffusers' activation name.
    pub fn from_name(name: &str) -> Option<Self> {
        match name {
            "silu" | "swish" => Some(Self::Silu),
            "mish" => Some(Self::Mish),
            "gelu" => Some(Self::Gelu),
            "relu" => Some(Self::Relu),
            _ => None,
        }
    }

    /// Applies the activation.
    pub fn forward(self, x: &Tensor) -> Tensor {
        match self {
            Self::Silu => x.silu(),
            Self::Mish => x.mish(),
            Self::Gelu => x.gelu("none"),
            Self::Relu => x.relu(),
        }
    }
}

/// diffusers' `CogVideoXSafeConv3d`: an `nn.Conv3d` (parameters `weight`, `bias`) that
/// splits inputs above 2 GiB (counted at 2 bytes an element) into frame chunks, each
/// chunk after the first prefixed with the previous chunk's last `kernel_t - 1` frames,
/// so the output equals the unsplit convolution.
#[derive(Debug)]
pub struct SafeConv3d {
    weight: Tensor,
    bias: Tensor,
    stride: [i64; 3],
    padding: [i64; 3],
}

impl SafeConv3d {
    /// A convolution with kernel `[t, h, w]`, zero padding `padding` and `stride`.
    pub fn new(
        p: nn::Path,
        in_channels: i64,
        out_channels: i64,
        kernel: [i64; 3],
        stride: [i64; 3],
        padding: [i64; 3],
    ) -> Self {
        let weight = p.var(
            "weight",
            &[out_channels, in_channels, kernel[0], kernel[1], kernel[2]],
            Init::Const(0.),
        );
        let bias = p.var("bias", &[out_channels], Init::Const(0.));
        Self {
            weight,
            bias,
            stride,
            padding,
        }
    }

    /// The temporal kernel size.
    fn time_kernel(&self) -> i64 {
        self.weight.size()[2]
    }

    fn conv(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.f_conv3d(
            &self.weight,
            Some(&self.bias),
            self.stride,
            self.padding,
            [1, 1, 1],
            1,
        )?)
    }

    /// The convolution of a clip of `k` copies of one frame (`k` the temporal
    /// kernel, stride 1 in time): `[B, Cin, H, W] -> [B, Cout, 1, H', W']`.
    /// Every temporal tap sees the same frame, so this is one 2-D
    /// convolution with the taps' weights summed: a third of the
    /// arithmetic of the 3-D one for a `3³` kernel.
    fn forward_repeated_frame(&self, frame: &Tensor) -> Result<Tensor> {
        // [Cout, Cin, kt, kh, kw] -> [Cout, Cin, kh, kw]
        let w = self
            .weight
            .f_sum_dim_intlist(2, false, self.weight.kind())?;
        Ok(frame
            .f_conv2d(
                &w,
                Some(&self.bias),
                [self.stride[1], self.stride[2]],
                [self.padding[1], self.padding[2]],
                [1, 1],
                1,
            )?
            .f_unsqueeze(2)?) // [B, Cout, H', W'] -> [B, Cout, 1, H', W']
    }

    /// `[B, Cin, T, H, W] -> [B, Cout, T', H', W']`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let numel: i64 = x.size().iter().product();
        // diffusers: `numel * 2 / 1024**3` GiB, split above 2.
        let memory_gib = (numel as f64 * 2.0) / 1024f64.powi(3);
        if memory_gib <= 2.0 {
            return self.conv(x);
        }
        let parts = (memory_gib / 2.0) as i64 + 1;
        let chunks = x.f_chunk(parts, 2)?;
        let k = self.time_kernel();
        let mut outputs = Vec::with_capacity(chunks.len());
        for (i, chunk) in chunks.iter().enumerate() {
            let out = if i > 0 && k > 1 {
                // Prefix the previous chunk's last k - 1 frames (fewer if it is shorter).
                let prev = &chunks[i - 1];
                let prev_t = prev.size()[2];
                let n = (k - 1).min(prev_t);
                let input =
                    Tensor::f_cat(&[prev.narrow(2, prev_t - n, n), chunk.shallow_clone()], 2)?;
                self.conv(&input)?
            } else {
                self.conv(chunk)?
            };
            outputs.push(out);
        }
        Ok(Tensor::f_cat(&outputs, 2)?)
    }
}

/// diffusers' `CogVideoXCausalConv3d` with CogVideoX's padding mode (`"first"`, i.e.
/// not `"replicate"`): a cubic-kernel convolution (`conv.weight`, `conv.bias`), zero
/// padding `(k - 1) / 2` in height and width, and causal temporal padding: the first
/// frame replicated `k - 1` times in front, or the conv cache of the previous frame
/// batch instead.
#[derive(Debug)]
pub struct CausalConv3d {
    conv: SafeConv3d,
    time_kernel: i64,
}

impl CausalConv3d {
    /// A causal convolution with a `kernel³` kernel and stride 1.
    pub fn new(p: nn::Path, in_channels: i64, out_channels: i64, kernel: i64) -> Self {
        let spatial_pad = (kernel - 1) / 2;
        let conv = SafeConv3d::new(
            p / "conv",
            in_channels,
            out_channels,
            [kernel, kernel, kernel],
            [1, 1, 1],
            [0, spatial_pad, spatial_pad],
        );
        Self {
            conv,
            time_kernel: kernel,
        }
    }

    /// `[B, Cin, T, H, W] -> [B, Cout, T, H, W]`, with the cache for the next frame batch
    /// (the last `k - 1` frames of the time-padded input; `None` when `k == 1`, where
    /// diffusers' cache is never read).
    pub fn forward(&self, x: &Tensor, cache: Option<&Tensor>) -> Result<(Tensor, Option<Tensor>)> {
        let k = self.time_kernel;
        if k <= 1 {
            return Ok((self.conv.forward(x)?, None));
        }
        if cache.is_none() && x.size()[2] == 1 && self.conv.padding[0] == 0 {
            // One frame and no cache: the time-padded input is k copies of it.
            // [B, C, 1, H, W] -> [B, C, k - 1, H, W]
            let new_cache = x.f_repeat([1, 1, k - 1, 1, 1])?;
            let out = self.conv.forward_repeated_frame(&x.f_squeeze_dim(2)?)?;
            return Ok((out, Some(new_cache)));
        }
        let front = match cache {
            Some(c) => c.shallow_clone(),
            // [B, C, 1, H, W] -> [B, C, k - 1, H, W]: the first frame, k - 1 times.
            None => x.narrow(2, 0, 1).f_repeat([1, 1, k - 1, 1, 1])?,
        };
        // [B, C, k - 1 + T, H, W]
        let padded = Tensor::f_cat(&[front, x.shallow_clone()], 2)?;
        let t = padded.size()[2];
        // A copy, so the cache does not keep the whole padded input alive.
        let new_cache = padded.narrow(2, t - (k - 1), k - 1).copy();
        Ok((self.conv.forward(&padded)?, Some(new_cache)))
    }
}

/// `nn.GroupNorm` with affine parameters `weight`, `bias`.
#[derive(Debug)]
pub struct GroupNorm {
    weight: Tensor,
    bias: Tensor,
    groups: i64,
    eps: f64,
}

impl GroupNorm {
    /// Group norm over `channels` in `groups` groups.
    pub fn new(p: nn::Path, groups: i64, channels: i64, eps: f64) -> Self {
        Self {
            weight: p.var("weight", &[channels], Init::Const(1.)),
            bias: p.var("bias", &[channels], Init::Const(0.)),
            groups,
            eps,
        }
    }

    /// Normalizes `[B, C, ...]` over each group of channels and all other dimensions.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        Ok(x.f_group_norm(
            self.groups,
            Some(&self.weight),
            Some(&self.bias),
            self.eps,
            true,
        )?)
    }
}

/// diffusers' `CogVideoXSpatialNorm3D`: group norm (eps 1e-6) of the features `f`,
/// scaled and shifted by 1×1×1 convolutions (`conv_y`, `conv_b`) of the latent `zq`
/// resized to `f` by nearest interpolation. When `f` has an odd frame count above 1,
/// the first latent frame is resized to the first feature frame and the rest to the
/// rest separately.
#[derive(Debug)]
pub struct SpatialNorm3D {
    norm_layer: GroupNorm,
    conv_y: CausalConv3d,
    conv_b: CausalConv3d,
}

impl SpatialNorm3D {
    /// Norm of `f_channels` features conditioned on a `zq_channels` latent.
    pub fn new(p: nn::Path, f_channels: i64, zq_channels: i64, groups: i64) -> Self {
        Self {
            norm_layer: GroupNorm::new(&p / "norm_layer", groups, f_channels, 1e-6),
            conv_y: CausalConv3d::new(&p / "conv_y", zq_channels, f_channels, 1),
            conv_b: CausalConv3d::new(&p / "conv_b", zq_channels, f_channels, 1),
        }
    }

    /// `f [B, Cf, T, H, W]`, `zq [B, Cz, t, h, w]` -> `[B, Cf, T, H, W]`.
    pub fn forward(&self, f: &Tensor, zq: &Tensor) -> Result<Tensor> {
        let fs = f.size();
        let (t, h, w) = (fs[2], fs[3], fs[4]);
        let zq = if t > 1 && t % 2 == 1 {
            let zt = zq.size()[2];
            // [B, Cz, 1, h, w] -> [B, Cz, 1, H, W]
            let z_first = zq
                .narrow(2, 0, 1)
                .f_upsample_nearest3d([1, h, w], None, None, None)?;
            // [B, Cz, t - 1, h, w] -> [B, Cz, T - 1, H, W]
            let z_rest =
                zq.narrow(2, 1, zt - 1)
                    .f_upsample_nearest3d([t - 1, h, w], None, None, None)?;
            Tensor::f_cat(&[z_first, z_rest], 2)?
        } else {
            // [B, Cz, t, h, w] -> [B, Cz, T, H, W]
            zq.f_upsample_nearest3d([t, h, w], None, None, None)?
        };
        let (conv_y, _) = self.conv_y.forward(&zq, None)?;
        let (conv_b, _) = self.conv_b.forward(&zq, None)?;
        let norm_f = self.norm_layer.forward(f)?;
        Ok(norm_f * conv_y + conv_b)
    }
}

/// A resnet's normalization: plain group norm (encoder) or spatial norm (decoder).
#[derive(Debug)]
enum Norm {
    Group(GroupNorm),
    Spatial(SpatialNorm3D),
}

impl Norm {
    fn new(
        p: nn::Path,
        channels: i64,
        groups: i64,
        eps: f64,
        spatial_norm_dim: Option<i64>,
    ) -> Self {
        match spatial_norm_dim {
            None => Self::Group(GroupNorm::new(p, groups, channels, eps)),
            Some(zq_channels) => {
                Self::Spatial(SpatialNorm3D::new(p, channels, zq_channels, groups))
            }
        }
    }

    fn forward(&self, x: &Tensor, zq: Option<&Tensor>) -> Result<Tensor> {
        match (self, zq) {
            (Self::Group(norm), _) => norm.forward(x),
            (Self::Spatial(norm), Some(zq)) => norm.forward(x, zq),
            (Self::Spatial(_), None) => Err(WorldModelError::input(
                "zq",
                "a spatially normalized (decoder) resnet needs the latent",
            )),
        }
    }
}

/// The conv cache of a resnet block (`conv1`, `conv2`; the spatial norms' and the
/// shortcut's kernels are 1 in time and need none).
#[derive(Debug, Default)]
pub struct ResnetCache {
    conv1: Option<Tensor>,
    conv2: Option<Tensor>,
}

/// diffusers' `CogVideoXResnetBlock3D` without time embedding (`temb_channels = 0`, as
/// everywhere in the VAE): `norm1 -> act -> conv1 -> norm2 -> act -> conv2` plus the
/// input, through a 1×1×1 `conv_shortcut` when the channel counts differ.
#[derive(Debug)]
pub struct ResnetBlock3D {
    norm1: Norm,
    norm2: Norm,
    conv1: CausalConv3d,
    conv2: CausalConv3d,
    conv_shortcut: Option<SafeConv3d>,
    act: Activation,
}

impl ResnetBlock3D {
    /// `num_layers` blocks under `p/resnets/{i}`: the first from `in_channels`,
    /// the others from `out_channels`, all to `out_channels`.
    #[allow(clippy::too_many_arguments)]
    pub fn stack(
        p: &nn::Path,
        in_channels: i64,
        out_channels: i64,
        num_layers: i64,
        groups: i64,
        eps: f64,
        act: Activation,
        spatial_norm_dim: Option<i64>,
    ) -> Vec<Self> {
        (0..num_layers)
            .map(|i| {
                let cin = if i == 0 { in_channels } else { out_channels };
                Self::new(
                    p / "resnets" / i,
                    cin,
                    out_channels,
                    groups,
                    eps,
                    act,
                    spatial_norm_dim,
                )
            })
            .collect()
    }

    /// A block from `in_channels` to `out_channels`; `spatial_norm_dim` is the latent's
    /// channel count for decoder blocks, `None` for group-normalized encoder blocks.
    pub fn new(
        p: nn::Path,
        in_channels: i64,
        out_channels: i64,
        groups: i64,
        eps: f64,
        act: Activation,
        spatial_norm_dim: Option<i64>,
    ) -> Self {
        let conv_shortcut = (in_channels != out_channels).then(|| {
            SafeConv3d::new(
                &p / "conv_shortcut",
                in_channels,
                out_channels,
                [1, 1, 1],
                [1, 1, 1],
                [0, 0, 0],
            )
        });
        Self {
            norm1: Norm::new(&p / "norm1", in_channels, groups, eps, spatial_norm_dim),
            norm2: Norm::new(&p / "norm2", out_channels, groups, eps, spatial_norm_dim),
            conv1: CausalConv3d::new(&p / "conv1", in_channels, out_channels, 3),
            conv2: CausalConv3d::new(&p / "conv2", out_channels, out_channels, 3),
            conv_shortcut,
            act,
        }
    }

    /// `[B, Cin, T, H, W] -> [B, Cout, T, H, W]` and the block's new conv cache.
    pub fn forward(
        &self,
        x: &Tensor,
        zq: Option<&Tensor>,
        cache: Option<&ResnetCache>,
    ) -> Result<(Tensor, ResnetCache)> {
        let h = self.norm1.forward(x, zq)?;
        let h = self.act.forward(&h);
        let (h, conv1) = self
            .conv1
            .forward(&h, cache.and_then(|c| c.conv1.as_ref()))?;
        let h = self.norm2.forward(&h, zq)?;
        let h = self.act.forward(&h);
        // Dropout: identity at inference.
        let (h, conv2) = self
            .conv2
            .forward(&h, cache.and_then(|c| c.conv2.as_ref()))?;
        let shortcut = match &self.conv_shortcut {
            Some(conv) => conv.forward(x)?,
            None => x.shallow_clone(),
        };
        Ok((h + shortcut, ResnetCache { conv1, conv2 }))
    }
}

/// The conv caches of a block's resnets, in order.
#[derive(Debug, Default)]
pub struct BlockCache {
    resnets: Vec<ResnetCache>,
}

fn resnets_forward(
    resnets: &[ResnetBlock3D],
    x: &Tensor,
    zq: Option<&Tensor>,
    cache: Option<&BlockCache>,
) -> Result<(Tensor, BlockCache)> {
    let mut h = x.shallow_clone();
    let mut new_cache = BlockCache::default();
    for (i, resnet) in resnets.iter().enumerate() {
        let (out, c) = resnet.forward(&h, zq, cache.and_then(|c| c.resnets.get(i)))?;
        h = out;
        new_cache.resnets.push(c);
    }
    Ok((h, new_cache))
}

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
struct FrameConv2d {
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
    fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let (images, b, t) = frames_to_images(x)?;
        let out = images.f_conv2d(
            &self.weight,
            Some(&self.bias),
            [self.stride, self.stride],
            [self.padding, self.padding],
            [1, 1],
            1,
        )?;
        images_to_frames(&out, b, t)
    }
}

/// diffusers' `CogVideoXDownsample3D`: optional temporal 2× average pooling (an odd
/// frame count keeps the first frame and pools the rest), then zero padding of one
/// pixel right and bottom and a stride-2 3×3 convolution on every frame.
#[derive(Debug)]
pub struct Downsample3D {
    conv: FrameConv2d,
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

/// diffusers' `CogVideoXDownBlock3D` (encoder): resnets, then an optional downsampler.
#[derive(Debug)]
pub struct DownBlock3D {
    resnets: Vec<ResnetBlock3D>,
    downsampler: Option<Downsample3D>,
}

impl DownBlock3D {
    /// `num_layers` group-normalized resnets from `in_channels` to `out_channels`
    /// (`resnets.i`), and `downsamplers.0` when `add_downsample`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        p: nn::Path,
        in_channels: i64,
        out_channels: i64,
        num_layers: i64,
        groups: i64,
        eps: f64,
        act: Activation,
        add_downsample: bool,
        compress_time: bool,
    ) -> Self {
        let resnets = ResnetBlock3D::stack(
            &p,
            in_channels,
            out_channels,
            num_layers,
            groups,
            eps,
            act,
            None,
        );
        let downsampler = add_downsample
            .then(|| Downsample3D::new(&p / "downsamplers" / 0, out_channels, compress_time));
        Self {
            resnets,
            downsampler,
        }
    }

    /// Runs the block on one frame batch.
    pub fn forward(&self, x: &Tensor, cache: Option<&BlockCache>) -> Result<(Tensor, BlockCache)> {
        let (h, cache) = resnets_forward(&self.resnets, x, None, cache)?;
        let h = match &self.downsampler {
            Some(d) => d.forward(&h)?,
            None => h,
        };
        Ok((h, cache))
    }
}

/// diffusers' `CogVideoXMidBlock3D`: resnets at constant width, spatially normalized
/// in the decoder.
#[derive(Debug)]
pub struct MidBlock3D {
    resnets: Vec<ResnetBlock3D>,
}

impl MidBlock3D {
    /// `num_layers` resnets of `channels` channels (`resnets.i`).
    pub fn new(
        p: nn::Path,
        channels: i64,
        num_layers: i64,
        groups: i64,
        eps: f64,
        act: Activation,
        spatial_norm_dim: Option<i64>,
    ) -> Self {
        let resnets = (0..num_layers)
            .map(|i| {
                ResnetBlock3D::new(
                    &p / "resnets" / i,
                    channels,
                    channels,
                    groups,
                    eps,
                    act,
                    spatial_norm_dim,
                )
            })
            .collect();
        Self { resnets }
    }

    /// Runs the block on one frame batch (`zq`: the decoder's latent).
    pub fn forward(
        &self,
        x: &Tensor,
        zq: Option<&Tensor>,
        cache: Option<&BlockCache>,
    ) -> Result<(Tensor, BlockCache)> {
        resnets_forward(&self.resnets, x, zq, cache)
    }
}

/// diffusers' `CogVideoXUpBlock3D` (decoder): spatially normalized resnets, then an
/// optional upsampler.
#[derive(Debug)]
pub struct UpBlock3D {
    resnets: Vec<ResnetBlock3D>,
    upsampler: Option<Upsample3D>,
}

impl UpBlock3D {
    /// `num_layers` resnets from `in_channels` to `out_channels` conditioned on a
    /// `spatial_norm_dim`-channel latent (`resnets.i`), and `upsamplers.0` when
    /// `add_upsample`.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        p: nn::Path,
        in_channels: i64,
        out_channels: i64,
        num_layers: i64,
        groups: i64,
        eps: f64,
        act: Activation,
        spatial_norm_dim: i64,
        add_upsample: bool,
        compress_time: bool,
    ) -> Self {
        let resnets = ResnetBlock3D::stack(
            &p,
            in_channels,
            out_channels,
            num_layers,
            groups,
            eps,
            act,
            Some(spatial_norm_dim),
        );
        let upsampler = add_upsample
            .then(|| Upsample3D::new(&p / "upsamplers" / 0, out_channels, compress_time));
        Self { resnets, upsampler }
    }

    /// Runs the block on one frame batch conditioned on the latent `zq`.
    pub fn forward(
        &self,
        x: &Tensor,
        zq: &Tensor,
        cache: Option<&BlockCache>,
    ) -> Result<(Tensor, BlockCache)> {
        let (h, cache) = resnets_forward(&self.resnets, x, Some(zq), cache)?;
        let h = match &self.upsampler {
            Some(u) => u.forward(&h)?,
            None => h,
        };
        Ok((h, cache))
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use tch::{Device, Kind};

    /// A 3 -> `out` causal 3x3x3 convolution with N(0, 0.2²) weights and bias.
    fn random_conv(seed: i64, out: i64) -> (nn::VarStore, CausalConv3d) {
        tch::manual_seed(seed);
        let vs = nn::VarStore::new(Device::Cpu);
        let conv = CausalConv3d::new(vs.root() / "c", 3, out, 3);
        tch::no_grad(|| {
            for mut v in vs.variables().into_values() {
                let r = Tensor::randn_like(&v) * 0.2;
                v.copy_(&r);
            }
        });
        (vs, conv)
    }

    #[test]
    fn inflated_causal_conv_is_the_frame_by_frame_conv_and_keeps_single_frames() {
        let (vs, conv) = random_conv(1, 4);
        let frame = Tensor::randn([1, 3, 1, 5, 6], (Kind::Float, Device::Cpu));
        let clip = Tensor::randn([1, 3, 4, 5, 6], (Kind::Float, Device::Cpu));
        let (single_before, _) = conv.forward(&frame, None).unwrap();
        let (clip_before, _) = conv.forward(&clip, None).unwrap();
        assert_eq!(crate::vae::inflate_image_weights(&vs), 1);
        let (single_after, _) = conv.forward(&frame, None).unwrap();
        assert!(
            (&single_after - &single_before)
                .abs()
                .max()
                .double_value(&[])
                < 1e-5
        );
        // Every output frame is now the conv of its own frame alone.
        let (clip_after, _) = conv.forward(&clip, None).unwrap();
        for t in 0..4 {
            let (alone, _) = conv.forward(&clip.narrow(2, t, 1), None).unwrap();
            let d = (clip_after.narrow(2, t, 1) - alone)
                .abs()
                .max()
                .double_value(&[]);
            assert!(d < 1e-5, "frame {t}: {d}");
        }
        // Before, later frames mixed in their predecessors.
        let (alone, _) = conv.forward(&clip.narrow(2, 3, 1), None).unwrap();
        assert!(
            (clip_before.narrow(2, 3, 1) - alone)
                .abs()
                .max()
                .double_value(&[])
                > 1e-2
        );
    }

    #[test]
    fn one_frame_causal_conv_matches_the_time_padded_3d_conv() {
        let (_vs, conv) = random_conv(0, 5);
        let x = Tensor::randn([2, 3, 1, 6, 7], (Kind::Float, Device::Cpu));
        let (fast, cache) = conv.forward(&x, None).unwrap();
        // The general path: the frame k = 3 times, one 3-D convolution.
        let slow = conv.conv.forward(&x.repeat([1, 1, 3, 1, 1])).unwrap();
        assert_eq!(fast.size(), vec![2, 5, 1, 6, 7]);
        let diff = (&fast - &slow).abs().max().double_value(&[]);
        assert!(diff < 1e-5, "{diff}");
        // The cache for the next frames is the general path's: the frame, twice.
        assert!(cache.unwrap().equal(&x.repeat([1, 1, 2, 1, 1])));
        // With a cache (a later frame batch) the 3-D path runs as before.
        let (next, _) = conv.forward(&x, Some(&x.repeat([1, 1, 2, 1, 1]))).unwrap();
        assert!((&next - &slow).abs().max().double_value(&[]) < 1e-5);
    }

    #[test]
    fn time_pooling_is_avg_pool3d_and_runs_in_bf16_on_the_cpu() {
        tch::manual_seed(3);
        let mut vs = nn::VarStore::new(Device::Cpu);
        let down = Downsample3D::new(vs.root() / "d", 3, true);
        tch::no_grad(|| {
            for mut v in vs.variables().into_values() {
                let r = Tensor::randn_like(&v) * 0.2;
                v.copy_(&r);
            }
        });
        let pooled =
            |x: &Tensor| x.avg_pool3d([2, 1, 1], [2, 1, 1], [0, 0, 0], false, true, None::<i64>);
        let mut f32_outputs = Vec::new();
        for t in [1i64, 4, 5] {
            let x = Tensor::randn([2, 3, t, 6, 8], (Kind::Float, Device::Cpu));
            let got = down.forward(&x).unwrap();
            // The reference: diffusers' avg_pool3d, the first frame kept
            // alone for an odd count.
            let reference = match t {
                1 => x.shallow_clone(),
                _ if t % 2 == 1 => {
                    Tensor::cat(&[x.narrow(2, 0, 1), pooled(&x.narrow(2, 1, t - 1))], 2)
                }
                _ => pooled(&x),
            };
            let want = down
                .conv
                .forward(&reference.constant_pad_nd([0, 1, 0, 1]))
                .unwrap();
            let d = (&got - &want).abs().max().double_value(&[]);
            assert!(d < 1e-6, "t = {t}: {d}");
            f32_outputs.push((x, got));
        }
        // The same downsampler in bf16 on the CPU, where avg_pool3d has no
        // bf16 kernel: it runs and stays within bf16 rounding of f32.
        vs.bfloat16();
        for (x, want) in f32_outputs {
            let got = down.forward(&x.to_kind(Kind::BFloat16)).unwrap();
            assert_eq!(got.kind(), Kind::BFloat16);
            let scale = want.abs().max().double_value(&[]);
            let d = (got.to_kind(Kind::Float) - &want)
                .abs()
                .max()
                .double_value(&[]);
            assert!(
                scale > 0.1 && d < 0.05 * scale,
                "bf16 off by {d} (scale {scale})"
            );
        }
    }
}
