//! The VAE's resnet blocks (group- or spatially normalized) and the down, mid and up
//! blocks built from them, each carrying its resnets' conv caches between frame batches.

use super::{
    pool_frame_pairs, Activation, CausalConv3d, Downsample3D, GroupNorm, SafeConv3d, SpatialNorm3D,
    Upsample3D,
};
use crate::error::{Result, WorldModelError};
use tch::nn;
use tch::Tensor;

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

impl ResnetCache {
    /// Every cached tensor, in a fixed order (the one [`Self::map`] visits).
    pub fn tensors(&self) -> Vec<&Tensor> {
        self.conv1.iter().chain(self.conv2.iter()).collect()
    }

    /// The same cache with `f` applied to every tensor, in [`Self::tensors`]' order.
    pub fn map(&self, f: &mut dyn FnMut(&Tensor) -> Tensor) -> Self {
        Self {
            conv1: self.conv1.as_ref().map(&mut *f),
            conv2: self.conv2.as_ref().map(&mut *f),
        }
    }
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
        self.forward_with(x, zq, cache, false)
    }

    /// [`Self::forward`] followed by a time-compressing downsampler's
    /// pooling of frame pairs ([`pool_frame_pairs`]), which is linear: it
    /// reaches `conv2` ([`CausalConv3d::forward_time_pooled`], fewer
    /// products) and the shortcut (pooled before its 1×1×1 convolution,
    /// half the frames) separately. `[B, Cin, T, H, W] -> [B, Cout, T', H, W]`.
    pub fn forward_time_pooled(
        &self,
        x: &Tensor,
        zq: Option<&Tensor>,
        cache: Option<&ResnetCache>,
    ) -> Result<(Tensor, ResnetCache)> {
        self.forward_with(x, zq, cache, true)
    }

    fn forward_with(
        &self,
        x: &Tensor,
        zq: Option<&Tensor>,
        cache: Option<&ResnetCache>,
        pool_time: bool,
    ) -> Result<(Tensor, ResnetCache)> {
        // Each intermediate is let go as soon as the next is made (the
        // norms' outputs at the end of their statements), so at most the
        // input, one convolution's input and its output are held at once.
        let conv1_in = self.act.forward(&self.norm1.forward(x, zq)?);
        let (conv1_out, conv1) = self
            .conv1
            .forward(&conv1_in, cache.and_then(|c| c.conv1.as_ref()))?;
        drop(conv1_in);
        // Dropout: identity at inference.
        let conv2_in = self.act.forward(&self.norm2.forward(&conv1_out, zq)?);
        drop(conv1_out);
        let conv2_cache = cache.and_then(|c| c.conv2.as_ref());
        let (mut out, conv2) = if pool_time {
            self.conv2.forward_time_pooled(&conv2_in, conv2_cache)?
        } else {
            self.conv2.forward(&conv2_in, conv2_cache)?
        };
        drop(conv2_in);
        let x = if pool_time {
            pool_frame_pairs(x)?
        } else {
            x.shallow_clone()
        };
        let shortcut = match &self.conv_shortcut {
            Some(conv) => conv.forward(&x)?,
            None => x,
        };
        // In place on the convolution's output (its backward does not read it).
        let _ = out.f_add_(&shortcut)?;
        Ok((out, ResnetCache { conv1, conv2 }))
    }
}

/// The conv caches of a block's resnets, in order.
#[derive(Debug, Default)]
pub struct BlockCache {
    resnets: Vec<ResnetCache>,
}

impl BlockCache {
    /// Every cached tensor, resnet by resnet (the order [`Self::map`] visits).
    pub fn tensors(&self) -> Vec<&Tensor> {
        self.resnets.iter().flat_map(ResnetCache::tensors).collect()
    }

    /// The same cache with `f` applied to every tensor, in [`Self::tensors`]' order.
    pub fn map(&self, f: &mut dyn FnMut(&Tensor) -> Tensor) -> Self {
        Self {
            resnets: self.resnets.iter().map(|r| r.map(f)).collect(),
        }
    }
}

/// The resnets in order; with `pool_last`, the last one's output pooled in
/// time ([`ResnetBlock3D::forward_time_pooled`]).
fn resnets_forward(
    resnets: &[ResnetBlock3D],
    x: &Tensor,
    zq: Option<&Tensor>,
    cache: Option<&BlockCache>,
    pool_last: bool,
) -> Result<(Tensor, BlockCache)> {
    let mut h = x.shallow_clone();
    let mut new_cache = BlockCache::default();
    for (i, resnet) in resnets.iter().enumerate() {
        let c = cache.and_then(|c| c.resnets.get(i));
        let (out, c) = if pool_last && i + 1 == resnets.len() {
            resnet.forward_time_pooled(&h, zq, c)?
        } else {
            resnet.forward(&h, zq, c)?
        };
        h = out;
        new_cache.resnets.push(c);
    }
    Ok((h, new_cache))
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

    /// Runs the block on one frame batch. When the downsampler compresses
    /// time, its pooling of frame pairs runs inside the last resnet
    /// ([`ResnetBlock3D::forward_time_pooled`]: the same values, fewer
    /// products).
    pub fn forward(&self, x: &Tensor, cache: Option<&BlockCache>) -> Result<(Tensor, BlockCache)> {
        let pool_in_resnet = !self.resnets.is_empty()
            && self
                .downsampler
                .as_ref()
                .is_some_and(Downsample3D::compresses_time);
        let (h, cache) = resnets_forward(&self.resnets, x, None, cache, pool_in_resnet)?;
        let h = match &self.downsampler {
            Some(d) if pool_in_resnet => d.forward_time_pooled(&h)?,
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
        resnets_forward(&self.resnets, x, zq, cache, false)
    }

    /// The resnets, in order.
    pub fn resnets(&self) -> &[ResnetBlock3D] {
        &self.resnets
    }
}

/// diffusers' `CogVideoXUpBlock3D` (decoder): spatially normalized resnets, then an
/// optional upsampler. The decoder runs them unit by unit (`coder::Decoder3D`).
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

    /// The resnets, in order.
    pub fn resnets(&self) -> &[ResnetBlock3D] {
        &self.resnets
    }

    /// The upsampler, when the block has one.
    pub fn upsampler(&self) -> Option<&Upsample3D> {
        self.upsampler.as_ref()
    }
}
