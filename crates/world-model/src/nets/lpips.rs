//! LPIPS v0.1 with the AlexNet trunk (Zhang et al. 2018), as the `lpips`
//! package computes it:
//!
//! 1. inputs in `[-1, 1]`, the scaling layer `(x - shift) / scale` with
//!    shift `[-0.030, -0.088, -0.188]`, scale `[0.458, 0.448, 0.450]`;
//! 2. torchvision AlexNet `features`, tapped after relu1..relu5;
//! 3. each tap normalised to unit length over channels (`x / (|x| + 1e-10)`);
//! 4. squared difference, a 1x1 convolution without bias (`lin{k}`), spatial
//!    mean, summed over the five taps.
//!
//! Key names: `features.{0,3,6,8,10}.{weight,bias}` (torchvision
//! `alexnet-owt-7be5be79.pth`) and `lin{0..4}.model.1.weight` (the package's
//! `weights/v0.1/alex.pth`), in one safetensors file or several.

use crate::device::ComputeDevice;
use crate::error::{Result, WorldModelError};
use crate::video::{image_to_tensor, Video};
use crate::weights::load_weights;
use bridgev2w_io::frame::RgbFrame;
use std::path::PathBuf;
use tch::nn::{self, Module, VarStore};
use tch::{Kind, Tensor};

/// Channels of the five AlexNet taps.
pub const TAP_CHANNELS: [i64; 5] = [64, 192, 384, 256, 256];
const SHIFT: [f32; 3] = [-0.030, -0.088, -0.188];
const SCALE: [f32; 3] = [0.458, 0.448, 0.450];
/// Smallest input side: AlexNet's first convolution and pools need it.
pub const MIN_SIDE: usize = 32;

/// torchvision AlexNet `features` up to relu5 (the LPIPS trunk).
#[derive(Debug)]
pub struct AlexNetFeatures {
    convs: Vec<nn::Conv2D>,
}

impl AlexNetFeatures {
    /// Layers `features.{0,3,6,8,10}` under `p`.
    pub fn new(p: nn::Path) -> Self {
        // (index, in, out, kernel, stride, padding) of torchvision's AlexNet.
        let spec = [
            (0, 3, 64, 11, 4, 2),
            (3, 64, 192, 5, 1, 2),
            (6, 192, 384, 3, 1, 1),
            (8, 384, 256, 3, 1, 1),
            (10, 256, 256, 3, 1, 1),
        ];
        let convs = spec
            .iter()
            .map(|&(i, cin, cout, k, stride, padding)| {
                nn::conv2d(
                    &p / i.to_string(),
                    cin,
                    cout,
                    k,
                    nn::ConvConfig {
                        stride,
                        padding,
                        ..Default::default()
                    },
                )
            })
            .collect();
        Self { convs }
    }

    /// The five relu taps of `x` `[B, 3, H, W]` (already scaled).
    pub fn taps(&self, x: &Tensor) -> Vec<Tensor> {
        let mut taps = Vec::with_capacity(5);
        let mut h = x.shallow_clone();
        for (i, conv) in self.convs.iter().enumerate() {
            // Max-pools (3, stride 2) precede conv 3 and conv 6 (features.2, .5).
            if i == 1 || i == 2 {
                h = h.max_pool2d([3, 3], [2, 2], [0, 0], [1, 1], false);
            }
            h = conv.forward(&h).relu();
            taps.push(h.shallow_clone());
        }
        taps
    }
}

/// The LPIPS v0.1 distance with the AlexNet trunk.
#[derive(Debug)]
pub struct Lpips {
    vs: VarStore,
    trunk: AlexNetFeatures,
    lins: Vec<Tensor>,
}

impl Lpips {
    /// The network with uninitialised (random) weights on `device`.
    pub fn new(device: ComputeDevice) -> Result<Self> {
        let device = device.check_available()?;
        let vs = VarStore::new(device.to_tch());
        let root = vs.root();
        let trunk = AlexNetFeatures::new(&root / "features");
        let lins = TAP_CHANNELS
            .iter()
            .enumerate()
            .map(|(k, &c)| {
                (&root / format!("lin{k}") / "model" / "1").var(
                    "weight",
                    &[1, c, 1, 1],
                    nn::Init::Const(0.0),
                )
            })
            .collect();
        Ok(Self { vs, trunk, lins })
    }

    /// Loads the trunk and heads from safetensors files (strict: every
    /// weight must be present; AlexNet's `classifier.*` and `features.*`
    /// tensors past relu5 are ignored).
    pub fn load(files: &[PathBuf], device: ComputeDevice) -> Result<Self> {
        let mut me = Self::new(device)?;
        load_weights(&me.vs, files, |_| false, |k| k.starts_with("classifier."))?;
        me.vs.freeze();
        Ok(me)
    }

    /// The variables (for tests and converters).
    pub fn var_store(&self) -> &VarStore {
        &self.vs
    }

    /// Per-pair distances of `a`, `b` `[B, 3, H, W]` in `[-1, 1]`: `[B]`.
    pub fn forward(&self, a: &Tensor, b: &Tensor) -> Result<Tensor> {
        let (sa, sb) = (a.size(), b.size());
        if sa != sb || sa.len() != 4 || sa[1] != 3 {
            return Err(WorldModelError::input(
                "LPIPS",
                format!("inputs {sa:?} and {sb:?}: expected two [B, 3, H, W] tensors of one shape"),
            ));
        }
        if sa[2] < MIN_SIDE as i64 || sa[3] < MIN_SIDE as i64 {
            return Err(WorldModelError::input(
                "LPIPS",
                format!(
                    "frames of {}x{}: expected at least {MIN_SIDE}x{MIN_SIDE}",
                    sa[3], sa[2]
                ),
            ));
        }
        let device = self.vs.device();
        let shift = Tensor::from_slice(&SHIFT)
            .view([1, 3, 1, 1])
            .to_device(device);
        let scale = Tensor::from_slice(&SCALE)
            .view([1, 3, 1, 1])
            .to_device(device);
        let prep = |x: &Tensor| (x.to_device(device).to_kind(Kind::Float) - &shift) / &scale;
        let (ta, tb) = (self.trunk.taps(&prep(a)), self.trunk.taps(&prep(b)));
        let mut total = Tensor::zeros([sa[0]], (Kind::Float, device));
        for ((fa, fb), lin) in ta.iter().zip(&tb).zip(&self.lins) {
            let unit = |f: &Tensor| {
                let norm = f
                    .pow_tensor_scalar(2)
                    .sum_dim_intlist(1, true, Kind::Float)
                    .sqrt();
                f / (norm + 1e-10)
            };
            let diff = (unit(fa) - unit(fb)).pow_tensor_scalar(2); // [B, C, h, w]
            let weighted = diff.conv2d(lin, None::<Tensor>, [1, 1], [0, 0], [1, 1], 1); // [B, 1, h, w]
            total += weighted.mean_dim([1i64, 2, 3].as_slice(), false, Kind::Float);
            // [B]
        }
        Ok(total)
    }

    /// Distance of two images (values in `[0, 1]`).
    pub fn distance(&self, a: &RgbFrame, b: &RgbFrame) -> Result<f64> {
        let device = self.vs.device();
        let (ta, tb) = (
            image_to_tensor(a, device, Kind::Float)?,
            image_to_tensor(b, device, Kind::Float)?,
        );
        let d = tch::no_grad(|| self.forward(&ta, &tb))?;
        Ok(d.double_value(&[0]))
    }

    /// Mean distance over the frames of two videos of one shape, computed in
    /// batches of `batch` frames.
    pub fn video_distance(&self, a: &Video, b: &Video, batch: usize) -> Result<f64> {
        if (a.frames, a.height, a.width) != (b.frames, b.height, b.width) {
            return Err(WorldModelError::input(
                "LPIPS",
                format!(
                    "videos of {}x{}x{} and {}x{}x{} frames: shapes must match",
                    a.frames, a.width, a.height, b.frames, b.width, b.height
                ),
            ));
        }
        let device = self.vs.device();
        // [1, 3, T, H, W] -> [T, 3, H, W]
        let frames = |v: &Video| -> Result<Tensor> {
            Ok(v.to_tensor(device, Kind::Float)?
                .squeeze_dim(0)
                .permute([1, 0, 2, 3]))
        };
        let (fa, fb) = (frames(a)?, frames(b)?);
        let mut sum = 0.0;
        let t = a.frames as i64;
        let step = batch.max(1) as i64;
        for start in (0..t).step_by(step as usize) {
            let n = step.min(t - start);
            let d =
                tch::no_grad(|| self.forward(&fa.narrow(0, start, n), &fb.narrow(0, start, n)))?;
            sum += d.sum(Kind::Double).double_value(&[]);
        }
        Ok(sum / t as f64)
    }
}
