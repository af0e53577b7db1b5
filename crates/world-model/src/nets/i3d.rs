//! I3D: Inception-v1 inflated to 3D (Carreira and Zisserman 2017), the
//! Kinetics-400 network whose logits are the features of FVD.
//!
//! Layout and key names follow the widely used PyTorch port
//! (`InceptionI3d`, checkpoint `rgb_imagenet.pt`): `Conv3d_1a_7x7`,
//! `Conv3d_2b_1x1`, `Conv3d_2c_3x3`, `Mixed_3b` ... `Mixed_5c` (branches
//! `b0`, `b1a`, `b1b`, `b2a`, `b2b`, `b3b`), `logits`; every unit holds
//! `conv3d.weight` and `bn.{weight,bias,running_mean,running_var}` (BatchNorm
//! eps 0.001), the logits unit `conv3d.{weight,bias}` without BatchNorm.
//! Convolutions and max-pools use TensorFlow's "SAME" padding computed from
//! the input size (zeros; the pooled inputs are non-negative after ReLU).
//!
//! Input: `[B, 3, T, 224, 224]` in `[-1, 1]` with `T >= 9` (16 in the FVD
//! protocol); output: the 400 logits averaged over the remaining time steps.

use crate::device::ComputeDevice;
use crate::error::{Result, WorldModelError};
use crate::weights::load_weights;
use std::path::PathBuf;
use tch::nn::{self, Module, ModuleT, VarStore};
use tch::Tensor;

/// Kinetics-400 classes (the feature dimension of FVD).
pub const NUM_CLASSES: i64 = 400;
/// Frame side the network expects.
pub const INPUT_SIDE: i64 = 224;
/// Fewest frames the network accepts (the final 2x7x7 average pool needs two
/// time steps).
pub const MIN_FRAMES: i64 = 9;

/// TensorFlow "SAME" padding of one dimension: `(front, back)`.
fn same_pad(size: i64, kernel: i64, stride: i64) -> (i64, i64) {
    let total = if size % stride == 0 {
        (kernel - stride).max(0)
    } else {
        (kernel - size % stride).max(0)
    };
    (total / 2, total - total / 2)
}

/// `x` `[B, C, T, H, W]` zero-padded for a "SAME" window.
fn pad_same(x: &Tensor, kernel: [i64; 3], stride: [i64; 3]) -> Tensor {
    let s = x.size();
    let (tf, tb) = same_pad(s[2], kernel[0], stride[0]);
    let (hf, hb) = same_pad(s[3], kernel[1], stride[1]);
    let (wf, wb) = same_pad(s[4], kernel[2], stride[2]);
    // Padding order: last dimension first.
    x.constant_pad_nd([wf, wb, hf, hb, tf, tb])
}

/// Max-pool with "SAME" padding.
fn max_pool_same(x: &Tensor, kernel: [i64; 3], stride: [i64; 3]) -> Tensor {
    pad_same(x, kernel, stride).max_pool3d(kernel, stride, [0, 0, 0], [1, 1, 1], false)
}

/// An unpadded 3D convolution config. Weights start constant (they are
/// loaded; this also keeps construction off the global RNG).
fn conv_config(stride: [i64; 3], bias: bool) -> nn::ConvConfigND<[i64; 3]> {
    nn::ConvConfigND {
        stride,
        padding: [0, 0, 0],
        dilation: [1, 1, 1],
        groups: 1,
        bias,
        ws_init: nn::Init::Const(0.0),
        bs_init: nn::Init::Const(0.0),
        padding_mode: nn::PaddingMode::Zeros,
    }
}

/// Convolution + BatchNorm + ReLU (or, for the logits, convolution with bias).
#[derive(Debug)]
pub struct Unit3D {
    conv: nn::Conv3D,
    bn: Option<nn::BatchNorm>,
    kernel: [i64; 3],
    stride: [i64; 3],
}

impl Unit3D {
    /// A BatchNorm + ReLU unit under `p` (`p / "conv3d"`, `p / "bn"`).
    pub fn new(p: nn::Path, cin: i64, cout: i64, kernel: [i64; 3], stride: [i64; 3]) -> Self {
        let conv = nn::conv(&p / "conv3d", cin, cout, kernel, conv_config(stride, false));
        let bn = nn::batch_norm3d(
            &p / "bn",
            cout,
            nn::BatchNormConfig {
                eps: 1e-3,
                ..Default::default()
            },
        );
        Self {
            conv,
            bn: Some(bn),
            kernel,
            stride,
        }
    }

    /// The logits unit: a 1x1x1 convolution with bias, no BatchNorm, no ReLU.
    pub fn logits(p: nn::Path, cin: i64, cout: i64) -> Self {
        let conv = nn::conv(
            &p / "conv3d",
            cin,
            cout,
            [1, 1, 1],
            conv_config([1, 1, 1], true),
        );
        Self {
            conv,
            bn: None,
            kernel: [1, 1, 1],
            stride: [1, 1, 1],
        }
    }

    /// `[B, Cin, T, H, W]` -> `[B, Cout, T', H', W']`.
    pub fn forward(&self, x: &Tensor) -> Tensor {
        let y = self.conv.forward(&pad_same(x, self.kernel, self.stride));
        match &self.bn {
            Some(bn) => bn.forward_t(&y, false).relu(),
            None => y,
        }
    }
}

/// An inception module: four branches concatenated over channels.
#[derive(Debug)]
pub struct InceptionModule {
    b0: Unit3D,
    b1a: Unit3D,
    b1b: Unit3D,
    b2a: Unit3D,
    b2b: Unit3D,
    b3b: Unit3D,
}

impl InceptionModule {
    /// `out = [b0, b1a, b1b, b2a, b2b, b3b]` output channels.
    pub fn new(p: nn::Path, cin: i64, out: [i64; 6]) -> Self {
        let one = [1, 1, 1];
        let three = [3, 3, 3];
        Self {
            b0: Unit3D::new(&p / "b0", cin, out[0], one, one),
            b1a: Unit3D::new(&p / "b1a", cin, out[1], one, one),
            b1b: Unit3D::new(&p / "b1b", out[1], out[2], three, one),
            b2a: Unit3D::new(&p / "b2a", cin, out[3], one, one),
            b2b: Unit3D::new(&p / "b2b", out[3], out[4], three, one),
            b3b: Unit3D::new(&p / "b3b", cin, out[5], one, one),
        }
    }

    /// `[B, Cin, T, H, W]` -> `[B, out0 + out2 + out4 + out5, T, H, W]`.
    pub fn forward(&self, x: &Tensor) -> Tensor {
        let b0 = self.b0.forward(x);
        let b1 = self.b1b.forward(&self.b1a.forward(x));
        let b2 = self.b2b.forward(&self.b2a.forward(x));
        let b3 = self.b3b.forward(&max_pool_same(x, [3, 3, 3], [1, 1, 1]));
        Tensor::cat(&[b0, b1, b2, b3], 1)
    }
}

/// The I3D network up to its logits.
#[derive(Debug)]
pub struct I3d {
    vs: VarStore,
    conv1a: Unit3D,
    conv2b: Unit3D,
    conv2c: Unit3D,
    mixed: Vec<(String, InceptionModule)>,
    logits: Unit3D,
}

/// `(name, input channels, branch outputs)` of the inception modules.
const MIXED: [(&str, i64, [i64; 6]); 9] = [
    ("Mixed_3b", 192, [64, 96, 128, 16, 32, 32]),
    ("Mixed_3c", 256, [128, 128, 192, 32, 96, 64]),
    ("Mixed_4b", 480, [192, 96, 208, 16, 48, 64]),
    ("Mixed_4c", 512, [160, 112, 224, 24, 64, 64]),
    ("Mixed_4d", 512, [128, 128, 256, 24, 64, 64]),
    ("Mixed_4e", 512, [112, 144, 288, 32, 64, 64]),
    ("Mixed_4f", 528, [256, 160, 320, 32, 128, 128]),
    ("Mixed_5b", 832, [256, 160, 320, 32, 128, 128]),
    ("Mixed_5c", 832, [384, 192, 384, 48, 128, 128]),
];

impl I3d {
    /// The network with constant (untrained) weights on `device`.
    pub fn new(device: ComputeDevice) -> Result<Self> {
        let device = device.check_available()?;
        let vs = VarStore::new(device.to_tch());
        let root = vs.root();
        let conv1a = Unit3D::new(&root / "Conv3d_1a_7x7", 3, 64, [7, 7, 7], [2, 2, 2]);
        let conv2b = Unit3D::new(&root / "Conv3d_2b_1x1", 64, 64, [1, 1, 1], [1, 1, 1]);
        let conv2c = Unit3D::new(&root / "Conv3d_2c_3x3", 64, 192, [3, 3, 3], [1, 1, 1]);
        let mixed = MIXED
            .iter()
            .map(|&(name, cin, out)| {
                (
                    name.to_string(),
                    InceptionModule::new(&root / name, cin, out),
                )
            })
            .collect();
        let logits = Unit3D::logits(&root / "logits", 1024, NUM_CLASSES);
        Ok(Self {
            vs,
            conv1a,
            conv2b,
            conv2c,
            mixed,
            logits,
        })
    }

    /// Loads the weights from safetensors files (strict; BatchNorm's
    /// `num_batches_tracked` counters are ignored), frozen.
    pub fn load(files: &[PathBuf], device: ComputeDevice) -> Result<Self> {
        let mut me = Self::new(device)?;
        load_weights(
            &me.vs,
            files,
            |_| false,
            |k| k.ends_with("num_batches_tracked"),
        )?;
        me.vs.freeze();
        Ok(me)
    }

    /// The variables.
    pub fn var_store(&self) -> &VarStore {
        &self.vs
    }

    /// Logits of `x` `[B, 3, T, 224, 224]` in `[-1, 1]`: `[B, 400]`.
    pub fn forward(&self, x: &Tensor) -> Result<Tensor> {
        let s = x.size();
        if s.len() != 5
            || s[1] != 3
            || s[3] != INPUT_SIDE
            || s[4] != INPUT_SIDE
            || s[2] < MIN_FRAMES
        {
            return Err(WorldModelError::input(
                "I3D",
                format!(
                    "input {s:?}: expected [B, 3, T >= {MIN_FRAMES}, {INPUT_SIDE}, {INPUT_SIDE}]"
                ),
            ));
        }
        let x = x.to_device(self.vs.device());
        let mut h = self.conv1a.forward(&x); // [B, 64, T/2, 112, 112]
        h = max_pool_same(&h, [1, 3, 3], [1, 2, 2]); // [B, 64, T/2, 56, 56]
        h = self.conv2c.forward(&self.conv2b.forward(&h)); // [B, 192, T/2, 56, 56]
        h = max_pool_same(&h, [1, 3, 3], [1, 2, 2]); // [B, 192, T/2, 28, 28]
        for (name, m) in &self.mixed {
            match name.as_str() {
                // Before Mixed_4b: [B, 480, T/4, 14, 14].
                "Mixed_4b" => h = max_pool_same(&h, [3, 3, 3], [2, 2, 2]),
                // Before Mixed_5b: [B, 832, T/8, 7, 7].
                "Mixed_5b" => h = max_pool_same(&h, [2, 2, 2], [2, 2, 2]),
                _ => {}
            }
            h = m.forward(&h);
        }
        // [B, 1024, T/8, 7, 7] -> [B, 1024, T/8 - 1, 1, 1]
        h = h.avg_pool3d([2, 7, 7], [1, 1, 1], [0, 0, 0], false, true, None::<i64>);
        let logits = self.logits.forward(&h); // [B, 400, T', 1, 1]
                                              // [B, 400, T', 1, 1] -> [B, 400, T'] -> [B, 400]
        Ok(logits
            .squeeze_dim(4)
            .squeeze_dim(3)
            .mean_dim(2, false, tch::Kind::Float))
    }
}

/// Frames per clip in the FVD protocol (StyleGAN-V).
pub const FVD_FRAMES: usize = 16;

impl I3d {
    /// FVD features of a video (values in `[0, 1]`, any resolution): its
    /// first [`FVD_FRAMES`] frames, each resized to 224x224 (bilinear,
    /// half-pixel centres), scaled to `[-1, 1]`; the 400 logits.
    pub fn fvd_features(&self, video: &crate::video::Video) -> Result<Vec<f64>> {
        if video.frames < FVD_FRAMES {
            return Err(WorldModelError::input(
                "FVD",
                format!(
                    "a video of {} frames: the FVD protocol needs at least {FVD_FRAMES}",
                    video.frames
                ),
            ));
        }
        let device = self.vs.device();
        let x = video.to_tensor(device, tch::Kind::Float)?; // [1, 3, T, H, W]
        let x = x.narrow(2, 0, FVD_FRAMES as i64); // [1, 3, 16, H, W]
                                                   // [1, 3, 16, H, W] -> [16, 3, H, W] for the 2D resize
        let frames = x.squeeze_dim(0).permute([1, 0, 2, 3]);
        let resized = frames.upsample_bilinear2d([INPUT_SIDE, INPUT_SIDE], false, None, None);
        // [16, 3, 224, 224] -> [1, 3, 16, 224, 224]
        let clip = resized.permute([1, 0, 2, 3]).unsqueeze(0) * 2.0 - 1.0;
        let logits = tch::no_grad(|| self.forward(&clip))?; // [1, 400]
        let logits = logits.to_kind(tch::Kind::Double).view([-1]);
        Vec::<f64>::try_from(&logits).map_err(|e| {
            WorldModelError::input("FVD", format!("reading the I3D logits failed: {e}"))
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn same_padding_matches_tensorflow() {
        // 224 with k7 s2: total 5 -> (2, 3); odd size 7 with k3 s2: 7 % 2 = 1 -> 2 -> (1, 1).
        assert_eq!(same_pad(224, 7, 2), (2, 3));
        assert_eq!(same_pad(7, 3, 2), (1, 1));
        assert_eq!(same_pad(16, 1, 1), (0, 0));
        assert_eq!(same_pad(8, 2, 2), (0, 0));
        assert_eq!(same_pad(9, 3, 1), (1, 1));
    }
}
