//! diffusers' `CogVideoXEncoder3D` and `CogVideoXDecoder3D`: the two halves of the VAE,
//! each run on one frame batch at a time with the conv cache of the previous batch.

use super::layers::{
    Activation, BlockCache, CausalConv3d, DownBlock3D, GroupNorm, MidBlock3D, SpatialNorm3D,
    UpBlock3D,
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

/// The conv cache of the decoder between frame batches.
#[derive(Debug, Default)]
pub struct DecoderCache {
    conv_in: Option<Tensor>,
    mid_block: BlockCache,
    up_blocks: Vec<BlockCache>,
    conv_out: Option<Tensor>,
}

impl DecoderCache {
    /// Every cached tensor, in a fixed order (the one [`Self::map`] visits).
    pub fn tensors(&self) -> Vec<&Tensor> {
        let mut all: Vec<&Tensor> = self.conv_in.iter().collect();
        all.extend(self.mid_block.tensors());
        all.extend(self.up_blocks.iter().flat_map(BlockCache::tensors));
        all.extend(self.conv_out.iter());
        all
    }

    /// The same cache with `f` applied to every tensor, in [`Self::tensors`]' order.
    pub fn map(&self, f: &mut dyn FnMut(&Tensor) -> Tensor) -> Self {
        Self {
            conv_in: self.conv_in.as_ref().map(&mut *f),
            mid_block: self.mid_block.map(f),
            up_blocks: self.up_blocks.iter().map(|b| b.map(f)).collect(),
            conv_out: self.conv_out.as_ref().map(&mut *f),
        }
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

    /// `[B, latent_channels, t, h, w] -> [B, out_channels, T, 8h, 8w]` for one frame
    /// batch, with the cache for the next batch.
    pub fn forward(
        &self,
        z: &Tensor,
        cache: Option<&DecoderCache>,
    ) -> Result<(Tensor, DecoderCache)> {
        let mut new_cache = DecoderCache::default();
        let (h, c) = self
            .conv_in
            .forward(z, cache.and_then(|c| c.conv_in.as_ref()))?;
        new_cache.conv_in = c;
        let (mut h, c) = self
            .mid_block
            .forward(&h, Some(z), cache.map(|c| &c.mid_block))?;
        new_cache.mid_block = c;
        for (i, block) in self.up_blocks.iter().enumerate() {
            let (out, c) = block.forward(&h, z, cache.and_then(|c| c.up_blocks.get(i)))?;
            h = out;
            new_cache.up_blocks.push(c);
        }
        let h = self.norm_out.forward(&h, z)?.silu();
        let (h, c) = self
            .conv_out
            .forward(&h, cache.and_then(|c| c.conv_out.as_ref()))?;
        new_cache.conv_out = c;
        Ok((h, new_cache))
    }
}
