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

mod blocks;
mod resample;

use crate::error::Result;
use tch::nn::{self, Init};
use tch::Tensor;

pub use blocks::{BlockCache, DownBlock3D, MidBlock3D, ResnetBlock3D, ResnetCache, UpBlock3D};
use resample::pool_frame_pairs;
pub use resample::{Downsample3D, Upsample3D};

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
        Ok(crate::cpu_bf16::conv(
            x,
            &self.weight,
            Some(&self.bias),
            self.stride,
            self.padding,
        )?)
    }

    /// The convolution of a clip of `k` copies of one frame (`k` the temporal
    /// kernel, stride 1 in time): `[B, Cin, H, W] -> [B, Cout, 1, H', W']`.
    /// Every temporal tap sees the same frame, so this is one 2-D
    /// convolution with the taps' weights summed: a third of the
    /// arithmetic of the 3-D one for a `3³` kernel.
    fn forward_repeated_frame(&self, frame: &Tensor) -> Result<Tensor> {
        // [B, Cout, H', W'] -> [B, Cout, 1, H', W']
        Ok(self
            .conv_taps(frame, 0, self.time_kernel(), true)?
            .f_unsqueeze(2)?)
    }

    /// The temporal taps `first..end` of the kernel applied to one frame, as
    /// one 2-D convolution with those taps' weights summed:
    /// `[B, Cin, H, W] -> [B, Cout, H', W']` (the bias only `with_bias`).
    fn conv_taps(&self, frame: &Tensor, first: i64, end: i64, with_bias: bool) -> Result<Tensor> {
        // [Cout, Cin, kt, kh, kw] -> [Cout, Cin, kh, kw]
        let w = self
            .weight
            .narrow(2, first, end - first)
            .f_sum_dim_intlist(2, false, self.weight.kind())?;
        Ok(crate::cpu_bf16::conv(
            frame,
            &w,
            with_bias.then_some(&self.bias),
            [self.stride[1], self.stride[2]],
            [self.padding[1], self.padding[2]],
        )?)
    }

    /// The kernel whose stride-2 convolution gives the mean of two
    /// consecutive output frames: with `y_t = Σ_j W_j P_{t+j}` over the
    /// (padded) input `P`, `(y_t + y_{t+1}) / 2 = Σ_i V_i P_{t+i}` for the
    /// `k + 1` taps `V_i = (W_{i-1} + W_i) / 2` (`W_{-1} = W_k = 0`):
    /// `[Cout, Cin, k, kh, kw] -> [Cout, Cin, k + 1, kh, kw]`. The same sums,
    /// with the products of a frame seen by both outputs added once.
    fn pair_mean_weight(&self) -> Result<Tensor> {
        // Tap i of each: W_{i-1} (one zero tap in front), W_i (one behind).
        let later = self.weight.f_constant_pad_nd([0, 0, 0, 0, 1, 0])?;
        let earlier = self.weight.f_constant_pad_nd([0, 0, 0, 0, 0, 1])?;
        Ok(later.f_add(&earlier)?.f_mul_scalar(0.5)?)
    }

    /// The means of output frame pairs `(0, 1), (2, 3), ...` of the
    /// convolution of `x` zero-padded by `time_padding` frames at both ends
    /// (stride 1 in time): [`Self::pair_mean_weight`] at stride 2, with the
    /// bias. `[B, Cin, T, H, W] -> [B, Cout, (T + 2 p - k - 1) / 2 + 1, H', W']`.
    fn conv_pair_means(&self, x: &Tensor, time_padding: i64) -> Result<Tensor> {
        Ok(crate::cpu_bf16::conv(
            x,
            &self.pair_mean_weight()?,
            Some(&self.bias),
            [2, self.stride[1], self.stride[2]],
            [time_padding, self.padding[1], self.padding[2]],
        )?)
    }

    /// Whether diffusers splits an input of `numel` elements into frame
    /// chunks (`numel * 2 / 1024**3` GiB, split above 2).
    fn splits(numel: i64) -> bool {
        Self::memory_gib(numel) > 2.0
    }

    fn memory_gib(numel: i64) -> f64 {
        (numel as f64 * 2.0) / 1024f64.powi(3)
    }

    /// `[B, Cin, T, H, W] -> [B, Cout, T', H', W']`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let numel: i64 = x.size().iter().product();
        if !Self::splits(numel) {
            return self.conv(x);
        }
        let parts = (Self::memory_gib(numel) / 2.0) as i64 + 1;
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
        let t = x.size()[2];
        if cache.is_none() && t >= k - 1 && self.conv.padding[0] == 0 && self.conv.stride[0] == 1 {
            return self.forward_first_batch(x);
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

    /// [`Self::forward`] followed by a time-compressing downsampler's
    /// pooling ([`pool_frame_pairs`]: the first frame alone for an odd
    /// count, then the mean of each pair), with fewer products: each pair's
    /// mean is one stride-2 convolution of the padded input
    /// ([`SafeConv3d::pair_mean_weight`], `k + 1` taps for two output
    /// frames instead of `2k`). The same sums as diffusers' convolution and
    /// `avg_pool3d`, in another order. Where diffusers would split the input
    /// into frame chunks, or for a kernel other than 3 in time, it is
    /// [`Self::forward`] and the pooling as written.
    pub fn forward_time_pooled(
        &self,
        x: &Tensor,
        cache: Option<&Tensor>,
    ) -> Result<(Tensor, Option<Tensor>)> {
        let (k, t) = (self.time_kernel, x.size()[2]);
        let numel: i64 = x.size().iter().product();
        let padded_numel = numel / t.max(1) * (t + k - 1);
        if k != 3
            || t < 2
            || self.conv.stride[0] != 1
            || self.conv.padding[0] != 0
            || SafeConv3d::splits(padded_numel)
        {
            let (y, new_cache) = self.forward(x, cache)?;
            return Ok((pool_frame_pairs(&y)?, new_cache));
        }
        if cache.is_none() && t % 2 == 1 {
            return self.first_batch_time_pooled(x);
        }
        let front = match cache {
            Some(c) => c.shallow_clone(),
            // [B, C, 1, H, W] -> [B, C, k - 1, H, W]: the first frame, k - 1 times.
            None => x.narrow(2, 0, 1).f_repeat([1, 1, k - 1, 1, 1])?,
        };
        // [B, C, k - 1 + T, H, W]
        let padded = Tensor::f_cat(&[front, x.shallow_clone()], 2)?;
        let new_cache = padded.narrow(2, t, k - 1).copy();
        let out = if t % 2 == 0 {
            // Output pairs (0, 1), (2, 3), ...: [B, Cout, T / 2, H', W']
            self.conv.conv_pair_means(&padded, 0)?
        } else {
            // Output frame 0 alone: [B, Cout, 1, H', W']
            let first = self.conv.conv(&padded.narrow(2, 0, k))?;
            // Pairs (1, 2), (3, 4), ...: [B, Cout, (T - 1) / 2, H', W']
            let pairs = self
                .conv
                .conv_pair_means(&padded.narrow(2, 1, t + k - 2), 0)?;
            Tensor::f_cat(&[first, pairs], 2)?
        };
        Ok((out, Some(new_cache)))
    }

    /// [`Self::forward_time_pooled`] of the first frame batch (no cache, an
    /// odd `T >= 3`, `k = 3`) without building the time-padded input. Output
    /// frame 0 sees the first frame through all three taps; the pair means
    /// are one stride-2 convolution of the input zero-padded by a frame,
    /// whose first window `(-1, 0, 1, 2)` lacks the first frame's tap `V_0`
    /// that the replicated frame gives: both 2-D products of the first
    /// frame are one convolution with the kernels stacked.
    fn first_batch_time_pooled(&self, x: &Tensor) -> Result<(Tensor, Option<Tensor>)> {
        let t = x.size()[2];
        let conv = &self.conv;
        let v = conv.pair_mean_weight()?; // [Cout, Cin, 4, kh, kw]
        let cout = v.size()[0];
        // [Cout, Cin, 3, kh, kw] -> [Cout, Cin, kh, kw]
        let all_taps = conv
            .weight
            .f_sum_dim_intlist(2, false, conv.weight.kind())?;
        // [2 Cout, Cin, kh, kw]: frame 0's output, then the missing tap.
        let stacked = Tensor::f_cat(&[all_taps, v.f_select(2, 0)?], 0)?;
        let bias = Tensor::f_cat(&[conv.bias.shallow_clone(), conv.bias.f_zeros_like()?], 0)?;
        // [B, 2 Cout, H', W']
        let firsts = crate::cpu_bf16::conv(
            &x.f_select(2, 0)?,
            &stacked,
            Some(&bias),
            [conv.stride[1], conv.stride[2]],
            [conv.padding[1], conv.padding[2]],
        )?;
        // [B, Cout, H', W'] -> [B, Cout, 1, H', W'], twice
        let first = firsts.narrow(1, 0, cout).f_unsqueeze(2)?;
        let missing = firsts.narrow(1, cout, cout).f_unsqueeze(2)?;
        // Pairs (1, 2), (3, 4), ...: [B, Cout, (T - 1) / 2, H', W']
        let pairs = conv.conv_pair_means(x, 1)?;
        // In place on a convolution's output (not needed by its backward).
        let _ = pairs.narrow(2, 0, 1).f_add_(&missing)?;
        // [B, Cout, 1 + (T - 1) / 2, H', W']
        let out = Tensor::f_cat(&[first, pairs], 2)?;
        // The padded input's last two frames: the input's own (T >= 3).
        let new_cache = x.narrow(2, t - 2, 2).copy();
        Ok((out, Some(new_cache)))
    }

    /// The first frame batch (no cache, `T >= k - 1` frames) without building
    /// the time-padded input. With the first frame `k - 1` times in front,
    /// output frame `o < k - 1` sees the first frame through its taps
    /// `0..=k-1-o` (one 2-D convolution with those taps summed) and frame
    /// `o + j - k + 1` through tap `j` above that; the frames from `k - 1` on
    /// are the 3-D convolution of the input without padding. The same sums
    /// as diffusers' padded convolution, in another order, with fewer
    /// products: `k - 1` frames' taps on a repeated frame are added once.
    fn forward_first_batch(&self, x: &Tensor) -> Result<(Tensor, Option<Tensor>)> {
        let (k, t) = (self.time_kernel, x.size()[2]);
        let first = x.f_select(2, 0)?; // [B, Cin, H, W]
        let mut parts = Vec::with_capacity(k as usize);
        for o in 0..(k - 1) {
            let mut y = self.conv.conv_taps(&first, 0, k - o, true)?;
            for j in (k - o)..k {
                let frame = x.f_select(2, o + j - k + 1)?;
                // In place on a convolution's output (not needed by its backward).
                let _ = y.f_add_(&self.conv.conv_taps(&frame, j, j + 1, false)?)?;
            }
            parts.push(y.f_unsqueeze(2)?); // [B, Cout, H', W'] -> [B, Cout, 1, H', W']
        }
        if t > k - 1 {
            parts.push(self.conv.forward(x)?); // [B, Cout, T - k + 1, H', W']
        }
        // [B, Cout, T, H', W']
        let out = Tensor::f_cat(&parts, 2)?;
        // The padded input's last k - 1 frames: the input's own (T >= k - 1).
        let new_cache = x.narrow(2, t - (k - 1), k - 1).copy();
        Ok((out, Some(new_cache)))
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
///
/// A 1×1×1 convolution acts on each pixel alone, so it commutes with nearest
/// resizing: the two convolutions run on the latent at its own size (a
/// 64th of the products at the decoder's last stage, and no full-size
/// copy of the resized latent), the results are resized in time, and where
/// the spatial resize repeats each latent pixel in a block (every integer
/// factor libtorch maps so, checked by [`nearest_block`]) scale and shift
/// reach the normalized features by broadcasting, in one pass
/// (`addcmul`). The same values as diffusers' order of operations.
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
        let (b, c, t, h, w) = (fs[0], fs[1], fs[2], fs[3], fs[4]);
        let zs = zq.size();
        let (zh, zw) = (zs[3], zs[4]);
        // [B, Cz, t, h, w] -> [B, Cf, t, h, w]
        let (scale, _) = self.conv_y.forward(zq, None)?;
        let (shift, _) = self.conv_b.forward(zq, None)?;
        // [B, Cf, t, h, w] -> [B, Cf, T, h, w]
        let scale = resize_frames(&scale, t)?;
        let shift = resize_frames(&shift, t)?;
        let norm_f = self.norm_layer.forward(f)?;
        if let (Some(sh), Some(sw)) = (nearest_block(zh, h)?, nearest_block(zw, w)?) {
            // [B, Cf, T, h, w] -> [B, Cf, T, h, 1, w, 1]
            let lift = |x: &Tensor| x.f_reshape([b, c, t, zh, 1, zw, 1]);
            // [B, Cf, T, H, W] -> [B, Cf, T, h, sh, w, sw]
            let blocks = norm_f.f_reshape([b, c, t, zh, sh, zw, sw])?;
            // [B, Cf, T, h, sh, w, sw] -> [B, Cf, T, H, W]
            return Ok(lift(&shift)?
                .f_addcmul(&blocks, &lift(&scale)?)?
                .f_reshape([b, c, t, h, w])?);
        }
        // [B, Cf, T, h, w] -> [B, Cf, T, H, W]
        let scale = scale.f_upsample_nearest3d([t, h, w], None, None, None)?;
        let shift = shift.f_upsample_nearest3d([t, h, w], None, None, None)?;
        Ok(shift.f_addcmul(&norm_f, &scale)?)
    }
}

/// The latent-side tensor `x [B, C, t, h, w]` resized by nearest
/// interpolation to `frames` frames as diffusers' spatial norm resizes the
/// latent in time: for an odd count above 1 the first frame alone to the
/// first and the rest to the rest.
fn resize_frames(x: &Tensor, frames: i64) -> Result<Tensor> {
    let s = x.size();
    let (t, h, w) = (s[2], s[3], s[4]);
    if frames > 1 && frames % 2 == 1 {
        // [B, C, t - 1, h, w] -> [B, C, frames - 1, h, w]
        let rest =
            x.narrow(2, 1, t - 1)
                .f_upsample_nearest3d([frames - 1, h, w], None, None, None)?;
        // [B, C, frames, h, w]
        return Ok(Tensor::f_cat(&[x.narrow(2, 0, 1), rest], 2)?);
    }
    // [B, C, t, h, w] -> [B, C, frames, h, w]
    Ok(x.f_upsample_nearest3d([frames, h, w], None, None, None)?)
}

/// `Some(k)` when libtorch's nearest resize of a side of `from` pixels to
/// `to` repeats every source pixel `k` times in order (output `i` reads
/// `i / k`), asked of the op itself on an index ramp, since it computes
/// the source in floating point; `None` otherwise.
fn nearest_block(from: i64, to: i64) -> Result<Option<i64>> {
    if from < 1 || to % from != 0 {
        return Ok(None);
    }
    let k = to / from;
    let opts = (tch::Kind::Float, tch::Device::Cpu);
    // [1, 1, from, 1, 1] -> [1, 1, to, 1, 1]
    let sources = Tensor::f_arange(from, opts)?
        .f_reshape([1, 1, from, 1, 1])?
        .f_upsample_nearest3d([to, 1, 1], None, None, None)?
        .f_reshape([to])?;
    let blocks = Tensor::f_arange(to, opts)?
        .f_div_scalar(k as f64)?
        .f_floor()?;
    Ok(sources.equal(&blocks).then_some(k))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests;
