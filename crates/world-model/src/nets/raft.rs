//! RAFT optical flow (Teed & Deng 2020) with torchvision's architecture and
//! key names (`raft_large`, `raft_small`), frozen, in evaluation mode: batch
//! norms use their running statistics. Used by the flow loss, whose
//! gradients flow through RAFT into its input frames (the weights stay
//! fixed; as in torchvision the coordinates are detached between refinement
//! iterations).
//!
//! Inputs are image pairs `[B, 3, H, W]` in `[-1, 1]` with `H`, `W`
//! divisible by 8 (and at least 128 for the four-level correlation pyramid);
//! the output is the flow from image 1 to image 2 in pixels, `[B, 2, H, W]`
//! (x then y).

use crate::device::ComputeDevice;
use crate::error::{Result, WorldModelError};
use crate::weights::load_weights;
use std::path::PathBuf;
use tch::nn::{self, Module, ModuleT, VarStore};
use tch::{Kind, Tensor};

/// Normalisation after a convolution.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Norm {
    /// `BatchNorm2d` (running statistics; weights `*.1.{weight,bias,running_mean,running_var}`).
    Batch,
    /// `InstanceNorm2d` without affine parameters.
    Instance,
    /// None.
    None,
}

/// Residual block type of an encoder.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BlockKind {
    /// Two 3x3 convolutions (raft_large).
    Residual,
    /// 1x1, 3x3, 1x1 with a quarter of the channels inside (raft_small).
    Bottleneck,
}

/// Architecture of a RAFT model (torchvision's `_raft` arguments).
#[derive(Debug, Clone, PartialEq)]
pub struct RaftConfig {
    /// Feature encoder channels (stem, layer1..3, output).
    pub feature_layers: [i64; 5],
    /// Feature encoder block type.
    pub feature_block: BlockKind,
    /// Feature encoder normalisation.
    pub feature_norm: Norm,
    /// Context encoder channels.
    pub context_layers: [i64; 5],
    /// Context encoder block type.
    pub context_block: BlockKind,
    /// Context encoder normalisation.
    pub context_norm: Norm,
    /// Correlation pyramid levels.
    pub corr_levels: i64,
    /// Correlation lookup radius (infinity norm).
    pub corr_radius: i64,
    /// Motion encoder correlation convolutions (1 or 2 entries).
    pub motion_corr_layers: Vec<i64>,
    /// Motion encoder flow convolutions.
    pub motion_flow_layers: [i64; 2],
    /// Motion encoder output channels (including the 2 flow channels).
    pub motion_out: i64,
    /// Hidden state channels of the recurrent block.
    pub hidden: i64,
    /// Kernel (h, w) and padding (h, w) of each ConvGRU (1 or 2).
    pub gru: Vec<((i64, i64), (i64, i64))>,
    /// Hidden channels of the flow head.
    pub flow_head_hidden: i64,
    /// Convex upsampling with a mask predictor (else bilinear).
    pub mask_predictor: bool,
}

impl RaftConfig {
    /// torchvision `raft_large`.
    pub fn large() -> Self {
        Self {
            feature_layers: [64, 64, 96, 128, 256],
            feature_block: BlockKind::Residual,
            feature_norm: Norm::Instance,
            context_layers: [64, 64, 96, 128, 256],
            context_block: BlockKind::Residual,
            context_norm: Norm::Batch,
            corr_levels: 4,
            corr_radius: 4,
            motion_corr_layers: vec![256, 192],
            motion_flow_layers: [128, 64],
            motion_out: 128,
            hidden: 128,
            gru: vec![((1, 5), (0, 2)), ((5, 1), (2, 0))],
            flow_head_hidden: 256,
            mask_predictor: true,
        }
    }

    /// torchvision `raft_small`.
    pub fn small() -> Self {
        Self {
            feature_layers: [32, 32, 64, 96, 128],
            feature_block: BlockKind::Bottleneck,
            feature_norm: Norm::Instance,
            context_layers: [32, 32, 64, 96, 160],
            context_block: BlockKind::Bottleneck,
            context_norm: Norm::None,
            corr_levels: 4,
            corr_radius: 3,
            motion_corr_layers: vec![96],
            motion_flow_layers: [64, 32],
            motion_out: 82,
            hidden: 96,
            gru: vec![((3, 3), (1, 1))],
            flow_head_hidden: 128,
            mask_predictor: false,
        }
    }

    /// The configuration of a torchvision variant.
    pub fn of(variant: RaftVariant) -> Self {
        match variant {
            RaftVariant::RaftLarge => Self::large(),
            RaftVariant::RaftSmall => Self::small(),
        }
    }

    /// By name: `large` / `raft_large` or `small` / `raft_small`.
    pub fn by_name(name: &str) -> Result<Self> {
        match name {
            "large" | "raft_large" => Ok(Self::large()),
            "small" | "raft_small" => Ok(Self::small()),
            other => Err(WorldModelError::input(
                "RAFT",
                format!("unknown variant `{other}`: expected raft_large or raft_small"),
            )),
        }
    }
}

/// torchvision's RAFT variants, named as its builders (`raft_large`,
/// `raft_small`).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum RaftVariant {
    /// `raft_large` (the paper's flow estimator).
    #[default]
    RaftLarge,
    /// `raft_small`.
    RaftSmall,
}

/// torchvision's `Conv2dNormActivation`: `.0` convolution (bias), `.1` norm
/// when present, then ReLU unless disabled.
#[derive(Debug)]
struct ConvNormAct {
    conv: nn::Conv2D,
    norm: Option<nn::BatchNorm>,
    instance: bool,
    relu: bool,
}

impl ConvNormAct {
    fn new(p: nn::Path, cin: i64, cout: i64, k: i64, stride: i64, norm: Norm, relu: bool) -> Self {
        let conv = nn::conv2d(
            &p / "0",
            cin,
            cout,
            k,
            nn::ConvConfig {
                stride,
                padding: (k - 1) / 2,
                ..Default::default()
            },
        );
        let norm_layer =
            (norm == Norm::Batch).then(|| nn::batch_norm2d(&p / "1", cout, Default::default()));
        Self {
            conv,
            norm: norm_layer,
            instance: norm == Norm::Instance,
            relu,
        }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        let mut y = self.conv.forward(x);
        if let Some(bn) = &self.norm {
            y = bn.forward_t(&y, false);
        }
        if self.instance {
            y = y.instance_norm(
                None::<Tensor>,
                None::<Tensor>,
                None::<Tensor>,
                None::<Tensor>,
                true,
                0.1,
                1e-5,
                false,
            );
        }
        if self.relu {
            y.relu()
        } else {
            y
        }
    }
}

/// A residual or bottleneck block (`convnormrelu1..`, `downsample`).
#[derive(Debug)]
struct Block {
    convs: Vec<ConvNormAct>,
    downsample: Option<ConvNormAct>,
}

impl Block {
    fn new(p: &nn::Path, kind: BlockKind, cin: i64, cout: i64, stride: i64, norm: Norm) -> Self {
        let convs = match kind {
            BlockKind::Residual => vec![
                ConvNormAct::new(p / "convnormrelu1", cin, cout, 3, stride, norm, true),
                ConvNormAct::new(p / "convnormrelu2", cout, cout, 3, 1, norm, true),
            ],
            BlockKind::Bottleneck => vec![
                ConvNormAct::new(p / "convnormrelu1", cin, cout / 4, 1, 1, norm, true),
                ConvNormAct::new(
                    p / "convnormrelu2",
                    cout / 4,
                    cout / 4,
                    3,
                    stride,
                    norm,
                    true,
                ),
                ConvNormAct::new(p / "convnormrelu3", cout / 4, cout, 1, 1, norm, true),
            ],
        };
        // torchvision's ResidualBlock projects only when striding (as does the bottleneck).
        let downsample = (stride != 1)
            .then(|| ConvNormAct::new(p / "downsample", cin, cout, 1, stride, norm, false));
        Self { convs, downsample }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        let y = self
            .convs
            .iter()
            .fold(x.shallow_clone(), |h, c| c.forward(&h));
        let x = self
            .downsample
            .as_ref()
            .map_or_else(|| x.shallow_clone(), |d| d.forward(x));
        (x + y).relu()
    }
}

/// The feature / context encoder: stride-8 features.
#[derive(Debug)]
struct Encoder {
    stem: ConvNormAct,
    layers: Vec<Block>,
    conv: nn::Conv2D,
}

impl Encoder {
    fn new(p: nn::Path, layers: [i64; 5], kind: BlockKind, norm: Norm) -> Self {
        let strides = [2, 1, 2, 2];
        let stem = ConvNormAct::new(&p / "convnormrelu", 3, layers[0], 7, strides[0], norm, true);
        let mut blocks = Vec::new();
        for l in 0..3 {
            let lp = &p / format!("layer{}", l + 1);
            blocks.push(Block::new(
                &(&lp / "0"),
                kind,
                layers[l],
                layers[l + 1],
                strides[l + 1],
                norm,
            ));
            blocks.push(Block::new(
                &(&lp / "1"),
                kind,
                layers[l + 1],
                layers[l + 1],
                1,
                norm,
            ));
        }
        let conv = nn::conv2d(&p / "conv", layers[3], layers[4], 1, Default::default());
        Self {
            stem,
            layers: blocks,
            conv,
        }
    }

    fn forward(&self, x: &Tensor) -> Tensor {
        let h = self
            .layers
            .iter()
            .fold(self.stem.forward(x), |h, b| b.forward(&h));
        self.conv.forward(&h)
    }
}

/// A convolutional GRU (`convz`, `convr`, `convq`).
#[derive(Debug)]
struct ConvGru {
    convz: nn::Conv<[i64; 2]>,
    convr: nn::Conv<[i64; 2]>,
    convq: nn::Conv<[i64; 2]>,
}

impl ConvGru {
    fn new(p: nn::Path, input: i64, hidden: i64, kernel: (i64, i64), padding: (i64, i64)) -> Self {
        let conv = |name: &str| {
            nn::conv(
                &p / name,
                hidden + input,
                hidden,
                [kernel.0, kernel.1],
                nn::ConvConfigND::<[i64; 2]> {
                    padding: [padding.0, padding.1],
                    ..Default::default()
                },
            )
        };
        Self {
            convz: conv("convz"),
            convr: conv("convr"),
            convq: conv("convq"),
        }
    }

    fn forward(&self, h: &Tensor, x: &Tensor) -> Tensor {
        let hx = Tensor::cat(&[h, x], 1);
        let z = self.convz.forward(&hx).sigmoid();
        let r = self.convr.forward(&hx).sigmoid();
        let q = self.convq.forward(&Tensor::cat(&[&(&r * h), x], 1)).tanh();
        (1.0 - &z) * h + z * q
    }
}

/// Motion encoder, recurrent block and flow head.
#[derive(Debug)]
struct UpdateBlock {
    convcorr: Vec<ConvNormAct>,
    convflow1: ConvNormAct,
    convflow2: ConvNormAct,
    conv: ConvNormAct,
    grus: Vec<ConvGru>,
    head1: nn::Conv2D,
    head2: nn::Conv2D,
}

impl UpdateBlock {
    fn new(p: nn::Path, cfg: &RaftConfig) -> Self {
        let me = &p / "motion_encoder";
        let corr_channels = cfg.corr_levels * (2 * cfg.corr_radius + 1).pow(2);
        let mut convcorr = vec![ConvNormAct::new(
            &me / "convcorr1",
            corr_channels,
            cfg.motion_corr_layers[0],
            1,
            1,
            Norm::None,
            true,
        )];
        if let Some(&c2) = cfg.motion_corr_layers.get(1) {
            convcorr.push(ConvNormAct::new(
                &me / "convcorr2",
                cfg.motion_corr_layers[0],
                c2,
                3,
                1,
                Norm::None,
                true,
            ));
        }
        let corr_out = *cfg.motion_corr_layers.last().unwrap_or(&corr_channels);
        let [f1, f2] = cfg.motion_flow_layers;
        let convflow1 = ConvNormAct::new(&me / "convflow1", 2, f1, 7, 1, Norm::None, true);
        let convflow2 = ConvNormAct::new(&me / "convflow2", f1, f2, 3, 1, Norm::None, true);
        let conv = ConvNormAct::new(
            &me / "conv",
            corr_out + f2,
            cfg.motion_out - 2,
            3,
            1,
            Norm::None,
            true,
        );
        let rb = &p / "recurrent_block";
        let context = cfg.context_layers[4] - cfg.hidden;
        let grus = cfg
            .gru
            .iter()
            .enumerate()
            .map(|(i, &(k, pad))| {
                ConvGru::new(
                    &rb / format!("convgru{}", i + 1),
                    cfg.motion_out + context,
                    cfg.hidden,
                    k,
                    pad,
                )
            })
            .collect();
        let fh = &p / "flow_head";
        let head = |name: &str, cin, cout| {
            nn::conv2d(
                &fh / name,
                cin,
                cout,
                3,
                nn::ConvConfig {
                    padding: 1,
                    ..Default::default()
                },
            )
        };
        Self {
            convcorr,
            convflow1,
            convflow2,
            conv,
            grus,
            head1: head("conv1", cfg.hidden, cfg.flow_head_hidden),
            head2: head("conv2", cfg.flow_head_hidden, 2),
        }
    }

    /// (new hidden state, delta flow).
    fn forward(
        &self,
        hidden: &Tensor,
        context: &Tensor,
        corr: &Tensor,
        flow: &Tensor,
    ) -> (Tensor, Tensor) {
        let c = self
            .convcorr
            .iter()
            .fold(corr.shallow_clone(), |h, l| l.forward(&h));
        let f = self.convflow2.forward(&self.convflow1.forward(flow));
        let motion = Tensor::cat(
            &[
                self.conv.forward(&Tensor::cat(&[c, f], 1)),
                flow.shallow_clone(),
            ],
            1,
        );
        let x = Tensor::cat(&[context, &motion], 1);
        let h = self
            .grus
            .iter()
            .fold(hidden.shallow_clone(), |h, g| g.forward(&h, &x));
        let delta = self.head2.forward(&self.head1.forward(&h).relu());
        (h, delta)
    }
}

/// `[B, 2, h, w]` grid of (x, y) pixel coordinates.
fn coords_grid(b: i64, h: i64, w: i64, device: tch::Device) -> Tensor {
    let ys = Tensor::arange(h, (Kind::Float, device))
        .view([h, 1])
        .expand([h, w], false);
    let xs = Tensor::arange(w, (Kind::Float, device))
        .view([1, w])
        .expand([h, w], false);
    Tensor::stack(&[xs, ys], 0)
        .unsqueeze(0)
        .repeat([b, 1, 1, 1]) // [B, 2, h, w]
}

/// A frozen RAFT model.
#[derive(Debug)]
pub struct Raft {
    cfg: RaftConfig,
    vs: VarStore,
    feature_encoder: Encoder,
    context_encoder: Encoder,
    update_block: UpdateBlock,
    mask_predictor: Option<(ConvNormAct, nn::Conv2D)>,
}

impl Raft {
    /// The model with random weights on `device`.
    pub fn new(cfg: RaftConfig, device: ComputeDevice) -> Result<Self> {
        let device = device.check_available()?;
        let vs = VarStore::new(device.to_tch());
        let root = vs.root();
        let feature_encoder = Encoder::new(
            &root / "feature_encoder",
            cfg.feature_layers,
            cfg.feature_block,
            cfg.feature_norm,
        );
        let context_encoder = Encoder::new(
            &root / "context_encoder",
            cfg.context_layers,
            cfg.context_block,
            cfg.context_norm,
        );
        let update_block = UpdateBlock::new(&root / "update_block", &cfg);
        let mask_predictor = cfg.mask_predictor.then(|| {
            let mp = &root / "mask_predictor";
            (
                ConvNormAct::new(&mp / "convrelu", cfg.hidden, 256, 3, 1, Norm::None, true),
                nn::conv2d(&mp / "conv", 256, 8 * 8 * 9, 1, Default::default()),
            )
        });
        Ok(Self {
            cfg,
            vs,
            feature_encoder,
            context_encoder,
            update_block,
            mask_predictor,
        })
    }

    /// Loads torchvision weights (safetensors, keys unchanged; batch-norm
    /// `num_batches_tracked` counters are ignored) and freezes them.
    pub fn load(cfg: RaftConfig, files: &[PathBuf], device: ComputeDevice) -> Result<Self> {
        let mut me = Self::new(cfg, device)?;
        load_weights(
            &me.vs,
            files,
            |_| false,
            |k| k.ends_with(".num_batches_tracked"),
        )?;
        me.vs.freeze();
        Ok(me)
    }

    /// The variables.
    pub fn var_store(&self) -> &VarStore {
        &self.vs
    }

    /// The architecture.
    pub fn config(&self) -> &RaftConfig {
        &self.cfg
    }

    /// Correlation features `[B, levels * (2r+1)^2, h, w]` of the pyramid at
    /// `coords` `[B, 2, h, w]` (bilinear, zero outside, align_corners).
    fn lookup(&self, pyramid: &[Tensor], coords: &Tensor) -> Tensor {
        let r = self.cfg.corr_radius;
        let side = 2 * r + 1;
        let device = coords.device();
        let d = Tensor::linspace(-(r as f64), r as f64, side, (Kind::Float, device));
        // delta[i, j] = (d[i], d[j]): the first offset moves x.
        let delta = Tensor::stack(
            &[
                d.view([side, 1]).expand([side, side], false),
                d.view([1, side]).expand([side, side], false),
            ],
            -1,
        )
        .view([1, side, side, 2]);
        let (b, h, w) = (coords.size()[0], coords.size()[2], coords.size()[3]);
        // [B, 2, h, w] -> [B*h*w, 1, 1, 2]
        let mut centroids = coords.permute([0, 2, 3, 1]).reshape([b * h * w, 1, 1, 2]);
        let mut out = Vec::with_capacity(pyramid.len());
        for level in pyramid {
            let (lh, lw) = (level.size()[2], level.size()[3]);
            let grid = &centroids + &delta; // [N, side, side, 2] absolute pixels
            let gx = grid.narrow(-1, 0, 1) * (2.0 / (lw - 1) as f64) - 1.0;
            let gy = if lh > 1 {
                grid.narrow(-1, 1, 1) * (2.0 / (lh - 1) as f64) - 1.0
            } else {
                grid.narrow(-1, 1, 1)
            };
            let sampled = level.grid_sampler(&Tensor::cat(&[gx, gy], -1), 0, 0, true); // [N, 1, side, side]
            out.push(sampled.view([b, h, w, -1]));
            // Not in place: the previous level's grid was built from it.
            centroids = &centroids / 2.0;
        }
        Tensor::cat(&out, -1).permute([0, 3, 1, 2]).contiguous() // [B, C, h, w]
    }

    /// Flow estimates after each of `iterations` refinements, each `[B, 2, H, W]`.
    pub fn forward_all(
        &self,
        image1: &Tensor,
        image2: &Tensor,
        iterations: usize,
    ) -> Result<Vec<Tensor>> {
        let (s1, s2) = (image1.size(), image2.size());
        if s1 != s2 || s1.len() != 4 || s1[1] != 3 {
            return Err(WorldModelError::input(
                "RAFT",
                format!("images {s1:?} and {s2:?}: expected two [B, 3, H, W] tensors of one shape"),
            ));
        }
        let min = 8 * 2 * (1 << (self.cfg.corr_levels - 1));
        if s1[2] % 8 != 0 || s1[3] % 8 != 0 || s1[2] < min || s1[3] < min {
            return Err(WorldModelError::input(
                "RAFT",
                format!(
                    "frames of {}x{}: expected sides divisible by 8 and at least {min}",
                    s1[3], s1[2]
                ),
            ));
        }
        if iterations == 0 {
            return Err(WorldModelError::input(
                "RAFT",
                "0 refinement iterations: expected at least 1",
            ));
        }
        let device = self.vs.device();
        let (image1, image2) = (
            image1.to_device(device).to_kind(Kind::Float),
            image2.to_device(device).to_kind(Kind::Float),
        );
        let b = s1[0];
        let fmaps = self
            .feature_encoder
            .forward(&Tensor::cat(&[&image1, &image2], 0));
        let (f1, f2) = (fmaps.narrow(0, 0, b), fmaps.narrow(0, b, b));
        let (c, h, w) = (f1.size()[1], f1.size()[2], f1.size()[3]);
        // All-pairs correlation: [B, c, h*w]^T x [B, c, h*w] -> [B*h*w, 1, h, w]
        let corr = f1
            .view([b, c, h * w])
            .transpose(1, 2)
            .matmul(&f2.view([b, c, h * w]))
            / (c as f64).sqrt();
        let mut pyramid = vec![corr.reshape([b * h * w, 1, h, w])];
        for _ in 1..self.cfg.corr_levels {
            let last = pyramid
                .last()
                .map(|t| t.avg_pool2d([2, 2], [2, 2], [0, 0], false, true, None::<i64>));
            pyramid.extend(last);
        }
        let context_out = self.context_encoder.forward(&image1);
        let hidden_size = self.cfg.hidden;
        let parts =
            context_out.split_with_sizes([hidden_size, context_out.size()[1] - hidden_size], 1);
        let (mut hidden, context) = (parts[0].tanh(), parts[1].relu());
        let coords0 = coords_grid(b, h, w, device);
        let mut coords1 = coords0.copy();
        let mut flows = Vec::with_capacity(iterations);
        for _ in 0..iterations {
            coords1 = coords1.detach();
            let corr = self.lookup(&pyramid, &coords1);
            let flow = &coords1 - &coords0;
            let (h_new, delta) = self.update_block.forward(&hidden, &context, &corr, &flow);
            hidden = h_new;
            // Not in place: autograd saw the previous coordinates.
            coords1 = &coords1 + delta;
            let low = &coords1 - &coords0;
            flows.push(match &self.mask_predictor {
                Some((convrelu, conv)) => {
                    let mask = conv.forward(&convrelu.forward(&hidden)) * 0.25;
                    convex_upsample(&low, &mask)
                }
                None => {
                    low.upsample_bilinear2d([h * 8, w * 8], true, None::<f64>, None::<f64>) * 8.0
                }
            });
        }
        Ok(flows)
    }

    /// The final flow estimate `[B, 2, H, W]` after `iterations` refinements.
    pub fn forward(&self, image1: &Tensor, image2: &Tensor, iterations: usize) -> Result<Tensor> {
        let mut all = self.forward_all(image1, image2, iterations)?;
        all.pop()
            .ok_or_else(|| WorldModelError::input("RAFT", "no flow computed"))
    }
}

/// RAFT's convex upsampling by 8: each fine pixel is a softmax-weighted
/// combination of the 3x3 coarse neighbourhood of 8 x flow.
fn convex_upsample(flow: &Tensor, mask: &Tensor) -> Tensor {
    let (b, c, h, w) = (
        flow.size()[0],
        flow.size()[1],
        flow.size()[2],
        flow.size()[3],
    );
    let mask = mask
        .view([b, 1, 9, 8, 8, h, w].as_slice())
        .softmax(2, Kind::Float); // [B, 1, 9, 8, 8, h, w]
    let patches = (flow * 8.0)
        .im2col([3, 3], [1, 1], [1, 1], [1, 1])
        .view([b, c, 9, 1, 1, h, w].as_slice()); // [B, C, 9, 1, 1, h, w]
    let up = (mask * patches).sum_dim_intlist(2, false, Kind::Float); // [B, C, 8, 8, h, w]
    up.permute([0, 1, 4, 2, 5, 3]).reshape([b, c, h * 8, w * 8]) // [B, C, h, 8, w, 8] -> [B, C, 8h, 8w]
}
