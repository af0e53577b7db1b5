//! diffusers' `CogVideoXEncoder3D` and `CogVideoXDecoder3D`: the two halves of the VAE,
//! each run on one frame batch at a time with the conv cache of the previous batch.

use super::layers::{
    Activation, BlockCache, CausalConv3d, DownBlock3D, GroupNorm, MidBlock3D, ResnetBlock3D,
    ResnetCache, SpatialNorm3D, UpBlock3D, Upsample3D,
};
use super::VaeConfig;
use crate::error::Result;
use tch::nn;
use tch::Tensor;

/// Number of resnets in the mid blocks (fixed in diffusers).
const MID_BLOCK_LAYERS: i64 = 2;

/// The conv cache of the encoder between frame batches.
#[derive(Debug, Default)]
pub struct EncoderCache {
    conv_in: Option<Tensor>,
    down_blocks: Vec<BlockCache>,
    mid_block: BlockCache,
    conv_out: Option<Tensor>,
}

/// diffusers' `CogVideoXEncoder3D`: `conv_in`, `down_blocks.i` (the first
/// `log2(temporal_compression_ratio)` halving time, all but the last halving space),
/// `mid_block`, `norm_out`, SiLU, `conv_out` to the posterior's `2 * latent_channels`
/// moments.
#[derive(Debug)]
pub struct Encoder3D {
    conv_in: CausalConv3d,
    down_blocks: Vec<DownBlock3D>,
    mid_block: MidBlock3D,
    norm_out: GroupNorm,
    conv_out: CausalConv3d,
}

impl Encoder3D {
    /// The encoder of `cfg` (which must be validated).
    pub fn new(cfg: &VaeConfig, p: nn::Path, act: Activation) -> Self {
        let ch = &cfg.block_out_channels;
        let last = ch[ch.len() - 1];
        let level = cfg.temporal_compress_level();
        let groups = cfg.norm_num_groups;
        let down_blocks = (0..ch.len())
            .map(|i| {
                let input = if i == 0 { ch[0] } else { ch[i - 1] };
                DownBlock3D::new(
                    &p / "down_blocks" / i,
                    input,
                    ch[i],
                    cfg.layers_per_block,
                    groups,
                    cfg.norm_eps,
                    act,
                    i + 1 != ch.len(),
                    (i as i64) < level,
                )
            })
            .collect();
        Self {
            conv_in: CausalConv3d::new(&p / "conv_in", cfg.in_channels, ch[0], 3),
            down_blocks,
            mid_block: MidBlock3D::new(
                &p / "mid_block",
                last,
                MID_BLOCK_LAYERS,
                groups,
                cfg.norm_eps,
                act,
                None,
            ),
            norm_out: GroupNorm::new(&p / "norm_out", groups, last, 1e-6),
            conv_out: CausalConv3d::new(&p / "conv_out", last, 2 * cfg.latent_channels, 3),
        }
    }

    /// `[B, Cin, T, H, W] -> [B, 2 * latent_channels, t, H / 8, W / 8]` for one frame
    /// batch, with the cache for the next batch.
    pub fn forward(
        &self,
        x: &Tensor,
        cache: Option<&EncoderCache>,
    ) -> Result<(Tensor, EncoderCache)> {
        let mut new_cache = EncoderCache::default();
        let (mut h, c) = self
            .conv_in
            .forward(x, cache.and_then(|c| c.conv_in.as_ref()))?;
        new_cache.conv_in = c;
        for (i, block) in self.down_blocks.iter().enumerate() {
            let (out, c) = block.forward(&h, cache.and_then(|c| c.down_blocks.get(i)))?;
            h = out;
            new_cache.down_blocks.push(c);
        }
        let (h, c) = self
            .mid_block
            .forward(&h, None, cache.map(|c| &c.mid_block))?;
        new_cache.mid_block = c;
        let h = self.norm_out.forward(&h)?.silu();
        let (h, c) = self
            .conv_out
            .forward(&h, cache.and_then(|c| c.conv_out.as_ref()))?;
        new_cache.conv_out = c;
        Ok((h, new_cache))
    }
}

/// The conv cache of the decoder between frame batches: one entry per
/// [unit](Decoder3D::unit_count) of the decoder, in order.
#[derive(Debug, Default)]
pub struct DecoderCache {
    units: Vec<UnitCache>,
}

impl DecoderCache {
    /// Every cached tensor, in a fixed order (the one [`Self::map`] visits):
    /// unit by unit.
    pub fn tensors(&self) -> Vec<&Tensor> {
        self.units.iter().flat_map(UnitCache::tensors).collect()
    }

    /// The same cache with `f` applied to every tensor, in [`Self::tensors`]' order.
    pub fn map(&self, f: &mut dyn FnMut(&Tensor) -> Tensor) -> Self {
        Self {
            units: self.units.iter().map(|u| u.map(f)).collect(),
        }
    }

    /// Unit `k`'s part.
    pub(super) fn unit(&self, k: usize) -> Option<&UnitCache> {
        self.units.get(k)
    }
}

/// The conv cache of one decoder unit: a causal convolution's, a resnet's,
/// or none (an upsampler).
#[derive(Debug)]
pub(super) enum UnitCache {
    Conv(Option<Tensor>),
    Resnet(ResnetCache),
    Empty,
}

impl UnitCache {
    /// Its tensors, in a fixed order.
    pub(super) fn tensors(&self) -> Vec<&Tensor> {
        match self {
            Self::Conv(c) => c.iter().collect(),
            Self::Resnet(r) => r.tensors(),
            Self::Empty => Vec::new(),
        }
    }

    /// The same cache with `f` applied to every tensor, in [`Self::tensors`]' order.
    pub(super) fn map(&self, f: &mut dyn FnMut(&Tensor) -> Tensor) -> Self {
        match self {
            Self::Conv(c) => Self::Conv(c.as_ref().map(f)),
            Self::Resnet(r) => Self::Resnet(r.map(f)),
            Self::Empty => Self::Empty,
        }
    }

    fn conv(&self) -> Option<&Tensor> {
        match self {
            Self::Conv(c) => c.as_ref(),
            _ => None,
        }
    }

    fn resnet(&self) -> Option<&ResnetCache> {
        match self {
            Self::Resnet(r) => Some(r),
            _ => None,
        }
    }
}

/// One unit of the decoder's forward pass, the granularity at which
/// [`super::DecodeRecord`]'s stepwise replay checkpoints a frame batch.
enum Unit<'a> {
    /// `conv_in` (on the latent).
    ConvIn(&'a CausalConv3d),
    /// One resnet of the mid block or of an up block.
    Resnet(&'a ResnetBlock3D),
    /// An up block's upsampler.
    Upsample(&'a Upsample3D),
    /// `norm_out`, SiLU, `conv_out`.
    Out(&'a SpatialNorm3D, &'a CausalConv3d),
}

impl Unit<'_> {
    fn forward(
        &self,
        h: &Tensor,
        zq: &Tensor,
        cache: Option<&UnitCache>,
    ) -> Result<(Tensor, UnitCache)> {
        Ok(match self {
            Self::ConvIn(conv) => {
                let (h, c) = conv.forward(h, cache.and_then(UnitCache::conv))?;
                (h, UnitCache::Conv(c))
            }
            Self::Resnet(r) => {
                let (h, c) = r.forward(h, Some(zq), cache.and_then(UnitCache::resnet))?;
                (h, UnitCache::Resnet(c))
            }
            Self::Upsample(u) => (u.forward(h)?, UnitCache::Empty),
            Self::Out(norm, conv) => {
                let h = norm.forward(h, zq)?.silu();
                let (h, c) = conv.forward(&h, cache.and_then(UnitCache::conv))?;
                (h, UnitCache::Conv(c))
            }
        })
    }
}

/// diffusers' `CogVideoXDecoder3D`: `conv_in`, `mid_block`, `up_blocks.i` (the first
/// `log2(temporal_compression_ratio)` doubling time, all but the last doubling space),
/// `norm_out`, SiLU, `conv_out`; every norm is a spatial norm conditioned on the
/// decoder's input latent.
#[derive(Debug)]
pub struct Decoder3D {
    conv_in: CausalConv3d,
    mid_block: MidBlock3D,
    up_blocks: Vec<UpBlock3D>,
    norm_out: SpatialNorm3D,
    conv_out: CausalConv3d,
}

impl Decoder3D {
    /// The decoder of `cfg` (which must be validated).
    pub fn new(cfg: &VaeConfig, p: nn::Path, act: Activation) -> Self {
        // Widest first: [c_{n-1}, ..., c_0].
        let ch: Vec<i64> = cfg.block_out_channels.iter().rev().copied().collect();
        let level = cfg.temporal_compress_level();
        let groups = cfg.norm_num_groups;
        let zq = cfg.latent_channels;
        let up_blocks = (0..ch.len())
            .map(|i| {
                let input = if i == 0 { ch[0] } else { ch[i - 1] };
                UpBlock3D::new(
                    &p / "up_blocks" / i,
                    input,
                    ch[i],
                    cfg.layers_per_block + 1,
                    groups,
                    cfg.norm_eps,
                    act,
                    zq,
                    i + 1 != ch.len(),
                    (i as i64) < level,
                )
            })
            .collect();
        let last = ch[ch.len() - 1];
        Self {
            conv_in: CausalConv3d::new(&p / "conv_in", zq, ch[0], 3),
            mid_block: MidBlock3D::new(
                &p / "mid_block",
                ch[0],
                MID_BLOCK_LAYERS,
                groups,
                cfg.norm_eps,
                act,
                Some(zq),
            ),
            up_blocks,
            norm_out: SpatialNorm3D::new(&p / "norm_out", last, zq, groups),
            conv_out: CausalConv3d::new(&p / "conv_out", last, cfg.out_channels, 3),
        }
    }

    /// The units of the forward pass, in order: `conv_in`, the mid block's
    /// resnets, each up block's resnets and upsampler, the output.
    fn units(&self) -> Vec<Unit<'_>> {
        let mut units = vec![Unit::ConvIn(&self.conv_in)];
        units.extend(self.mid_block.resnets().iter().map(Unit::Resnet));
        for block in &self.up_blocks {
            units.extend(block.resnets().iter().map(Unit::Resnet));
            units.extend(block.upsampler().map(Unit::Upsample));
        }
        units.push(Unit::Out(&self.norm_out, &self.conv_out));
        units
    }

    /// The number of units [`Self::forward`] runs in order.
    pub(super) fn unit_count(&self) -> usize {
        self.units().len()
    }

    /// Unit `k` of [`Self::forward`] on its input `h` (unit 0's is the
    /// latent), conditioned on the latent `zq`, continuing `cache` (the
    /// unit's part of the previous batch's): its output and its new cache.
    pub(super) fn unit_forward(
        &self,
        k: usize,
        h: &Tensor,
        zq: &Tensor,
        cache: Option<&UnitCache>,
    ) -> Result<(Tensor, UnitCache)> {
        let units = self.units();
        let unit = units.get(k).ok_or_else(|| {
            crate::error::WorldModelError::input(
                "decoder unit",
                format!("{k}: the decoder has {} units", units.len()),
            )
        })?;
        unit.forward(h, zq, cache)
    }

    /// `[B, latent_channels, t, h, w] -> [B, out_channels, T, 8h, 8w]` for one frame
    /// batch, with the cache for the next batch.
    pub fn forward(
        &self,
        z: &Tensor,
        cache: Option<&DecoderCache>,
    ) -> Result<(Tensor, DecoderCache)> {
        let mut h = z.shallow_clone();
        let mut units = Vec::new();
        for (k, unit) in self.units().iter().enumerate() {
            let (out, c) = unit.forward(&h, z, cache.and_then(|c| c.unit(k)))?;
            h = out;
            units.push(c);
        }
        Ok((h, DecoderCache { units }))
    }
}
