//! `bench flow`: the fine-tuning stage's flow loss at a clip size (the decode
//! of the predicted latents, the flow of both videos, the gradient back
//! through the decoder), once per [`FlowBackward`] mode on the same random
//! VAE, latents and video: seconds, peak memory, and each mode's gradient
//! against the first mode's. Autograd through the whole decode is the peer
//! the recorded modes are measured against. The flow is the Lucas-Kanade
//! stand-in or RAFT (small or large) with random weights: its cost, not its
//! flow, is the point. In bf16 each mode runs under bf16 autocast, as the
//! training step runs it.
//!
//! Peak memory is the most memory in use at once above what was in use when
//! the mode started: on the CPU from the caching allocator's counters
//! ([`cpu_cache::memory`], installed by the `bridgev2w` binary; tensors only,
//! not the process), on CUDA from `nvidia-smi` (the device's used memory, so
//! the CUDA caching allocator's reserve is in it) and, exact, from the CUDA
//! caching allocator's own peak of the memory tensors held
//! ([`cuda_memory::memory`]).

use crate::decoded_flow::{decoded_flow, FlowBackward};
use crate::flow::{FlowEstimator, FlowLossConfig, LucasKanade, RaftFlow};
use crate::{Result, TrainError};
use bridgev2w_torch_ext::{autocast, cpu_cache, cuda_memory, AutocastDtype};
use bridgev2w_world_model::bench::gpu_memory::{with_gpu_peak, NVIDIA_SMI};
use bridgev2w_world_model::nets::raft::{Raft, RaftConfig};
use bridgev2w_world_model::vae::{init_like_pytorch, AutoencoderKLCogVideoX, TileSize, VaeConfig};
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::fmt;
use std::time::Instant;
use tch::nn::VarStore;
use tch::{Kind, Tensor};

/// The VAE of `bench flow`: random weights of one of the presets.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FlowBenchVae {
    /// CogVideoX's VAE (2B and 5B share the architecture): 4 blocks of
    /// 128-512 channels, 8x space, 4x time.
    #[default]
    Cogvideox,
    /// The same architecture with a few channels (tests).
    Tiny,
    /// The synthetic proof's `small` (4x space and time).
    Small,
    /// The synthetic proof's `small2x` (2x space, no time compression).
    Small2x,
}
bridgev2w_world_model::named_enum!(FlowBenchVae, TrainError, TrainError::input, "vae", {
    Cogvideox => "cogvideox",
    Tiny => "tiny",
    Small => "small",
    Small2x => "small2x",
});

impl FlowBenchVae {
    /// The preset's config.
    pub fn config(self) -> VaeConfig {
        match self {
            Self::Cogvideox => VaeConfig::cogvideox_5b_i2v(),
            Self::Tiny => VaeConfig::tiny(),
            Self::Small => VaeConfig::small(),
            Self::Small2x => VaeConfig::small_2x(),
        }
    }
}

/// The flow estimator of `bench flow`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum FlowBenchEstimator {
    /// The differentiable Lucas-Kanade stand-in (CPU training's).
    #[default]
    LucasKanade,
    /// RAFT small, random weights.
    RaftSmall,
    /// RAFT large (the paper's), random weights.
    RaftLarge,
}
bridgev2w_world_model::named_enum!(FlowBenchEstimator, TrainError, TrainError::input, "flow", {
    LucasKanade => "lucas_kanade",
    RaftSmall => "raft_small",
    RaftLarge => "raft_large",
});

/// What `bench flow` measures (the command's flags).
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct FlowBenchOptions {
    /// VAE preset with random weights (PyTorch's initialisation, seed 0):
    /// cogvideox (2B and 5B's architecture), tiny, small, small2x.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = FlowBenchOptions::default().vae))]
    pub vae: FlowBenchVae,
    /// Pixel frames (the VAE's 4k + 1 for cogvideox). The defaults run in
    /// about a minute on 2 cores; the full size is `--frames 25 --height 480
    /// --width 720 --tile 240x360 --precision bf16 --device cuda`.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = FlowBenchOptions::default().frames))]
    pub frames: i64,
    /// Pixel height.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = FlowBenchOptions::default().height))]
    pub height: i64,
    /// Pixel width.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = FlowBenchOptions::default().width))]
    pub width: i64,
    /// Spatial tiles of HxW pixels (training and `predict` tile above
    /// 256x256 with the VAE's default tiles, half its sample size); default:
    /// whole frames.
    #[cfg_attr(feature = "clap", arg(long))]
    pub tile: Option<TileSize>,
    /// f32 or bf16.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = FlowBenchOptions::default().precision))]
    pub precision: Precision,
    /// cpu, cuda or cuda:N.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = FlowBenchOptions::default().device))]
    pub device: ComputeDevice,
    /// The modes, comma-separated, in order (the first one's gradient is the reference).
    #[cfg_attr(
        feature = "clap",
        arg(
            long,
            value_delimiter = ',',
            default_value = "autograd,recorded,stepwise"
        )
    )]
    pub modes: Vec<FlowBackward>,
    /// Flow estimator: lucas_kanade (the CPU stand-in), raft_small or
    /// raft_large (random weights: the cost, not the flow, is measured).
    #[cfg_attr(feature = "clap", arg(long = "flow", default_value_t = FlowBenchOptions::default().estimator))]
    pub estimator: FlowBenchEstimator,
    /// RAFT's refinement iterations (torchvision's default 12).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = FlowBenchOptions::default().raft_iterations))]
    pub raft_iterations: usize,
}

impl FlowBenchOptions {
    /// The decode's tiles in words ("tiles of HxW px" or "whole frames").
    fn tiles(&self) -> String {
        match self.tile {
            Some(size) => format!("tiles of {size} px"),
            None => "whole frames".to_owned(),
        }
    }
}

impl Default for FlowBenchOptions {
    fn default() -> Self {
        Self {
            vae: FlowBenchVae::Cogvideox,
            frames: 17,
            height: 128,
            width: 192,
            tile: None,
            precision: Precision::F32,
            device: ComputeDevice::Cpu,
            modes: vec![
                FlowBackward::Autograd,
                FlowBackward::Recorded,
                FlowBackward::Stepwise,
            ],
            estimator: FlowBenchEstimator::LucasKanade,
            raft_iterations: 12,
        }
    }
}

/// One mode's measurement.
#[derive(Debug, Clone, PartialEq)]
pub struct FlowBenchRow {
    /// The mode.
    pub mode: FlowBackward,
    /// Seconds for the loss and its gradient.
    pub seconds: f64,
    /// Peak memory above the start, MiB (`None` where it cannot be read:
    /// a CPU without the caching allocator, a GPU without `nvidia-smi`).
    pub peak_mib: Option<f64>,
    /// What the recorded decode kept between the decode and the backward,
    /// MiB (`None` for autograd).
    pub record_mib: Option<f64>,
    /// On CUDA: the most memory tensors held at once above what they held
    /// when the mode started, MiB, from the caching allocator (exact, unlike
    /// polling; `None` on the CPU or where it cannot be read).
    pub cuda_allocated_peak_mib: Option<f64>,
    /// The flow loss's value.
    pub loss: f64,
    /// `max |g - g_ref| / max |g_ref|` against the first mode's gradient.
    pub gradient_error: f64,
}

/// The measurements of `bench flow`; `Display` prints them as a table.
#[derive(Debug, Clone, PartialEq)]
pub struct FlowBenchReport {
    /// The options measured.
    pub options: FlowBenchOptions,
    /// The estimator's name (with RAFT's iterations).
    pub estimator: String,
    /// The latents' shape `[B, C, t, h, w]`.
    pub latent_shape: Vec<i64>,
    /// One row per mode, in the options' order.
    pub rows: Vec<FlowBenchRow>,
}

/// Runs every mode of `options` once on the same random VAE, latents and
/// ground-truth video.
/// An out-of-memory (libtorch's error, or an op's panic, caught) is
/// [`TrainError::OutOfMemory`] naming the clip, tiles and modes.
pub fn bench_flow(options: &FlowBenchOptions) -> Result<FlowBenchReport> {
    let o = options;
    crate::guarded(|| bench_flow_unguarded(o)).map_err(|e| {
        e.on_out_of_memory(
            || {
                let modes: Vec<String> = o.modes.iter().map(ToString::to_string).collect();
                format!(
                    "the flow loss's backward ({}; {} frames at {}x{}, {}, {:?} on {:?})",
                    modes.join(", "),
                    o.frames,
                    o.height,
                    o.width,
                    o.tiles(),
                    o.precision,
                    o.device
                )
            },
            crate::BENCH_FLOW_MEMORY_ADVICE,
        )
    })
}

/// `--frames` within [`bridgev2w_world_model::bridge::MAX_CLIP_FRAMES`],
/// `--height`/`--width` within
/// [`bridgev2w_world_model::bridge::MAX_CLIP_SIDE`], and a floor of the
/// bench's memory within the machine's: the ground-truth clip built on the
/// host (its frames and their concatenation, float RGB: 24 bytes a pixel of
/// every frame).
fn check_sizes(o: &FlowBenchOptions) -> Result<()> {
    use bridgev2w_io::memory::{at_most, bytes, check_fits};
    use bridgev2w_world_model::bridge::{MAX_CLIP_FRAMES, MAX_CLIP_SIDE};
    let size = |v: i64| v.max(0) as u64;
    at_most("--frames", size(o.frames), MAX_CLIP_FRAMES as u64, "frames")?;
    at_most("--height", size(o.height), MAX_CLIP_SIDE as u64, "pixels")?;
    at_most("--width", size(o.width), MAX_CLIP_SIDE as u64, "pixels")?;
    check_fits(
        &format!(
            "the flow bench's clip of {} frames at {}x{}",
            o.frames, o.height, o.width
        ),
        bytes(&[size(o.frames), size(o.height), size(o.width), 24]),
        crate::BENCH_FLOW_MEMORY_ADVICE,
    )?;
    Ok(())
}

fn bench_flow_unguarded(o: &FlowBenchOptions) -> Result<FlowBenchReport> {
    if o.modes.is_empty() {
        return Err(TrainError::input(
            "modes",
            "none given: expected at least one",
        ));
    }
    let cfg = o.vae.config();
    let (kt, s) = (
        cfg.temporal_compression_ratio as i64,
        cfg.spatial_compression(),
    );
    if o.frames < 2 {
        return Err(TrainError::input(
            "frames",
            format!(
                "{}: expected at least 2 (a flow needs two frames)",
                o.frames
            ),
        ));
    }
    if let Some(message) = cfg.frames_error(o.frames as usize) {
        return Err(TrainError::input("frames", message));
    }
    for (name, side) in [("height", o.height), ("width", o.width)] {
        if side < s || side % s != 0 {
            return Err(TrainError::input(
                name,
                format!(
                    "{side}: expected a positive multiple of {s} (the VAE's spatial compression)"
                ),
            ));
        }
    }
    check_sizes(o)?;
    let device = o.device.check_available()?;
    let dev = device.to_tch();
    tch::manual_seed(0);
    let mut vs = VarStore::new(tch::Device::Cpu);
    let mut vae = AutoencoderKLCogVideoX::new(&cfg, vs.root())?;
    init_like_pytorch(&vs);
    if let Some(size) = o.tile {
        vae.enable_tiles(size, "tile")?;
    }
    vs.set_kind(o.precision.kind());
    vs.freeze();
    bridgev2w_world_model::device::move_to_device(&mut vs, dev);
    let latent_shape = vec![
        1,
        cfg.latent_channels,
        (o.frames - 1) / kt + 1,
        o.height / s,
        o.width / s,
    ];
    // Latents from the host generator (the same on every device); a ground
    // truth whose content moves one pixel right per frame, so its flow is
    // not zero.
    let z = Tensor::randn(latent_shape.as_slice(), (Kind::Float, tch::Device::Cpu)).to_device(dev);
    let still = Tensor::rand(
        [1, 3, 1, o.height, o.width],
        (Kind::Float, tch::Device::Cpu),
    );
    let frames: Vec<Tensor> = (0..o.frames).map(|t| still.roll([t], [4])).collect();
    let gt = (Tensor::cat(&frames, 2) * 2.0 - 1.0).to_device(dev);
    let estimator: Box<dyn FlowEstimator> = match o.estimator {
        FlowBenchEstimator::LucasKanade => Box::new(LucasKanade::default()),
        FlowBenchEstimator::RaftSmall | FlowBenchEstimator::RaftLarge => {
            if o.raft_iterations == 0 {
                return Err(TrainError::input(
                    "raft iterations",
                    "0: expected at least 1",
                ));
            }
            let cfg = if o.estimator == FlowBenchEstimator::RaftSmall {
                RaftConfig::small()
            } else {
                RaftConfig::large()
            };
            Box::new(RaftFlow {
                raft: Raft::new(cfg, device)?,
                iterations: o.raft_iterations,
            })
        }
    };
    let estimator_name = match o.estimator {
        FlowBenchEstimator::LucasKanade => estimator.name(),
        _ => format!("{}, {} iterations", estimator.name(), o.raft_iterations),
    };
    // Training runs the flow loss under autocast in bf16.
    let autocast_dtype = (o.precision == Precision::Bf16).then_some(AutocastDtype::BFloat16);
    let flow_cfg = FlowLossConfig::default();
    let gpu = match device {
        ComputeDevice::Cuda(i) => Some(i),
        ComputeDevice::Cpu => None,
    };
    let mut rows = Vec::with_capacity(o.modes.len());
    let mut reference: Option<Tensor> = None;
    for &mode in &o.modes {
        let leaf = z.detach().set_requires_grad(true);
        cpu_cache::reset_peak();
        let live0 = cpu_cache::memory().live_bytes;
        // The CUDA allocator's figures are extra: unreadable, they are left out.
        let cuda0 = gpu.and_then(|i| {
            cuda_memory::reset_peak(i).ok()?;
            Some(cuda_memory::memory(i).ok()??.allocated)
        });
        let t0 = Instant::now();
        let measure = || -> Result<_> {
            let flow = autocast(dev, autocast_dtype, || {
                decoded_flow(&vae, &leaf, &gt, estimator.as_ref(), &flow_cfg, mode)
            })??;
            let grad = Tensor::f_run_backward(&[&flow.loss], &[&leaf], false, false)?.remove(0);
            if let Some(i) = gpu {
                tch::Cuda::synchronize(i as i64);
            }
            Ok((flow.loss.double_value(&[]), grad, flow.record_bytes))
        };
        let ((loss, grad, record_bytes), gpu_peak) = with_gpu_peak(NVIDIA_SMI, gpu, measure)?;
        let seconds = t0.elapsed().as_secs_f64();
        let peak_mib = match gpu {
            Some(_) => gpu_peak.map(|m| m as f64),
            None => cpu_cache::is_active().then(|| {
                (cpu_cache::memory().peak_bytes.saturating_sub(live0)) as f64 / (1 << 20) as f64
            }),
        };
        let cuda_allocated_peak_mib = gpu.zip(cuda0).and_then(|(i, start)| {
            let m = cuda_memory::memory(i).ok()??;
            Some(m.peak_allocated.saturating_sub(start) as f64 / (1 << 20) as f64)
        });
        let grad = grad.to_kind(Kind::Float).to_device(tch::Device::Cpu);
        let gradient_error = match &reference {
            None => 0.0,
            Some(r) => {
                let scale = r.abs().max().double_value(&[]).max(f64::MIN_POSITIVE);
                (&grad - r).abs().max().double_value(&[]) / scale
            }
        };
        if reference.is_none() {
            reference = Some(grad);
        }
        rows.push(FlowBenchRow {
            mode,
            seconds,
            peak_mib,
            record_mib: record_bytes.map(|b| b as f64 / (1 << 20) as f64),
            cuda_allocated_peak_mib,
            loss,
            gradient_error,
        });
    }
    Ok(FlowBenchReport {
        options: o.clone(),
        estimator: estimator_name,
        latent_shape,
        rows,
    })
}

impl fmt::Display for FlowBenchReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let o = &self.options;
        writeln!(
            f,
            "flow loss through the decoder: VAE {}, {} frames at {}x{} ({}), latents {:?}, {:?} on {:?}, flow: {}",
            o.vae, o.frames, o.height, o.width, o.tiles(), self.latent_shape, o.precision, o.device, self.estimator
        )?;
        let memory = match o.device {
            ComputeDevice::Cpu => "peak tensor memory above the start (caching allocator)",
            ComputeDevice::Cuda(_) => "peak device memory above the start (nvidia-smi)",
        };
        writeln!(
            f,
            "| mode | seconds | {memory}, MiB | of which the record kept, MiB | loss | gradient vs {} | CUDA allocator's peak tensor memory above the start, MiB |",
            self.rows[0].mode
        )?;
        writeln!(f, "|---|---|---|---|---|---|---|")?;
        let first_peak = self.rows[0].peak_mib;
        for r in &self.rows {
            let peak = match (r.peak_mib, first_peak) {
                (Some(p), Some(p0)) if p0 > 0.0 => format!("{p:.0} ({:.2}x)", p / p0),
                (Some(p), _) => format!("{p:.0}"),
                (None, _) => "not measured".to_owned(),
            };
            let record = r
                .record_mib
                .map_or_else(|| "-".to_owned(), |m| format!("{m:.1}"));
            let allocator = r
                .cuda_allocated_peak_mib
                .map_or_else(|| "-".to_owned(), |m| format!("{m:.0}"));
            writeln!(
                f,
                "| {} | {:.2} | {peak} | {record} | {:.6} | {:.1e} | {allocator} |",
                r.mode, r.seconds, r.loss, r.gradient_error
            )?;
        }
        if matches!(o.device, ComputeDevice::Cuda(_)) && self.rows.len() > 1 {
            writeln!(
                f,
                "note: on CUDA nvidia-smi's peak is above the device memory in use when a mode \
                 started, which includes what the caching allocator kept from the modes before \
                 it: run one mode per process (--modes NAME) to compare those; the allocator's \
                 own peaks (last column) compare within one process"
            )?;
        }
        Ok(())
    }
}
