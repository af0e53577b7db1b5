//! The VAE's resnet blocks (group- or spatially normalized) and the down, mid and up
//! blocks built from them, each carrying its resnets' conv caches between frame batches.

use super::{
    Activation, CausalConv3d, Downsample3D, GroupNorm, SafeConv3d, SpatialNorm3D, Upsample3D,
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
