//! `bench model`: this crate's transformer forward and VAE encode/decode
//! against diffusers on the same configs and shapes, with each side's peak
//! GPU memory on CUDA.

use super::diffusers::{PeerTime, PeerTimings};
use super::gpu_memory::{with_gpu_peak, NVIDIA_SMI};
use super::{time_model, torch_threads, BenchError, DiffusersPeer, ModelBenchShape, ModelTimings};
use crate::device::{ComputeDevice, Precision};
use crate::transformer::TransformerConfig;
use crate::vae::VaeConfig;
use bridgev2w_io::progress::Progress;
use std::fmt;
use std::path::PathBuf;
use std::time::Duration;

/// The CogVideoX architecture family `bench model` builds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ModelStyle {
    /// CogVideoX-2B: sin-cos positions, its VAE.
    Cogvideox2b,
    /// CogVideoX-5B-I2V: RoPE, learned positions, the I2V input, its VAE.
    Cogvideox5bI2v,
}
crate::named_enum!(ModelStyle, BenchError, BenchError::input, "--style", {
    Cogvideox2b => "2b",
    Cogvideox5bI2v => "5b-i2v",
});

impl ModelStyle {
    /// The family's transformer and VAE configs (full size).
    pub fn configs(self) -> (TransformerConfig, VaeConfig) {
        match self {
            Self::Cogvideox2b => (TransformerConfig::cogvideox_2b(), VaeConfig::cogvideox_2b()),
            Self::Cogvideox5bI2v => (
                TransformerConfig::cogvideox_5b_i2v(),
                VaeConfig::cogvideox_5b_i2v(),
            ),
        }
    }
}

/// What `bench model` builds and times (the command's flags, but for the
/// precisions and the limit).
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct ModelBenchOptions {
    /// Architecture family: `2b` (sin-cos positions) or `5b-i2v` (RoPE, learned positions, I2V input).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelBenchOptions::default().style))]
    pub style: ModelStyle,
    /// Transformer blocks (the full models have 30 / 42).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelBenchOptions::default().layers))]
    pub layers: i64,
    /// Pixel frames (4k + 1). The defaults keep a 2-core CPU run near two minutes;
    /// `--frames 25 --height 256 --width 384` is the mid-size setting
    /// (the full-width VAE then dominates: tens of minutes on 2 cores).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelBenchOptions::default().frames))]
    pub frames: i64,
    /// Pixel height.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelBenchOptions::default().height))]
    pub height: i64,
    /// Pixel width.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelBenchOptions::default().width))]
    pub width: i64,
    /// Transformer batch: 2 times one denoising step with classifier-free
    /// guidance (the pipeline's conditional and unconditional halves).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelBenchOptions::default().batch))]
    pub batch: i64,
    /// Timed runs per operation (best is reported), after one warm-up.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelBenchOptions::default().repeat))]
    pub repeat: usize,
    /// Precision of weights and activations.
    #[cfg_attr(feature = "clap", arg(skip = Precision::F32))]
    pub precision: Precision,
    /// cpu, cuda or cuda:N.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = ModelBenchOptions::default().device))]
    pub device: ComputeDevice,
    /// `--no-diffusers`: skip diffusers (time this crate only).
    #[cfg_attr(feature = "clap", arg(long = "no-diffusers", action = clap::ArgAction::SetFalse))]
    pub diffusers: bool,
    /// Python with torch + diffusers (default: the project venv's).
    #[cfg_attr(feature = "clap", arg(long))]
    pub python: Option<PathBuf>,
    /// Repository root (holds scripts/bench/); default: found from the
    /// current directory.
    #[cfg_attr(feature = "clap", arg(long))]
    pub repo: Option<PathBuf>,
    /// Time the VAE with spatial tiling on both sides (diffusers'
    /// `enable_tiling()`, default tiles), as `predict` runs it above 256x256.
    #[cfg_attr(feature = "clap", arg(long))]
    pub vae_tiling: bool,
    /// Each of diffusers' operations may run this long from its start (its
    /// warm-up and timed runs); one still running then is stopped and
    /// bounded, and the operations after it run in a new process (`None`:
    /// no limit).
    #[cfg_attr(feature = "clap", arg(skip))]
    pub diffusers_limit: Option<Duration>,
}

impl Default for ModelBenchOptions {
    fn default() -> Self {
        Self {
            style: ModelStyle::Cogvideox2b,
            layers: 8,
            frames: 9,
            height: 128,
            width: 192,
            batch: 1,
            repeat: 1,
            precision: Precision::F32,
            device: ComputeDevice::Cpu,
            diffusers: true,
            python: None,
            repo: None,
            vae_tiling: false,
            diffusers_limit: None,
        }
    }
}

/// Peak GPU memory above idle of each side, in MiB (`None`: not measured).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct GpuPeakMib {
    /// This crate's run.
    pub bridgev2w: Option<u64>,
    /// diffusers' run.
    pub diffusers: Option<u64>,
}

/// The measurements of `bench model`; `Display` prints them as a table.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelBenchReport {
    /// Architecture family.
    pub style: ModelStyle,
    /// The transformer that was timed.
    pub transformer: TransformerConfig,
    /// The VAE that was timed.
    pub vae: VaeConfig,
    /// The clip shape.
    pub shape: ModelBenchShape,
    /// Precision.
    pub precision: Precision,
    /// Device.
    pub device: ComputeDevice,
    /// libtorch's intra-op threads (diffusers gets the same).
    pub threads: usize,
    /// This crate's timings.
    pub bridgev2w: ModelTimings,
    /// diffusers' timings, when it ran.
    pub diffusers: Option<PeerTimings>,
    /// Peak GPU memory (on CUDA only).
    pub gpu_peak_mib: Option<GpuPeakMib>,
    /// How this crate ran bf16 linear layers and convolutions (bf16 on the
    /// CPU only; diffusers always runs libtorch's own bf16 kernels).
    pub cpu_bf16: Option<crate::cpu_bf16::Bf16Compute>,
    /// How this crate ran linear layers on the CPU (diffusers runs
    /// libtorch's `linear`).
    pub cpu_linear: Option<crate::cpu_linear::CpuLinear>,
    /// How this crate ran bf16 attention on the CPU (diffusers runs
    /// libtorch's `scaled_dot_product_attention`).
    pub cpu_attention: Option<crate::cpu_attention::CpuAttention>,
    /// Calls on this crate's oneDNN paths (linear layers, bf16 attention)
    /// that failed and ran libtorch's op instead (0 unless something is
    /// wrong).
    pub onednn_fallbacks: u64,
}

impl ModelBenchReport {
    /// A report of the default options' 2B shapes on the CPU with
    /// `timings`, diffusers not run: the tests' starting point.
    #[cfg(test)]
    pub(crate) fn example(precision: Precision, batch: i64, timings: ModelTimings) -> Self {
        let (transformer, vae) = bench_configs(&ModelBenchOptions::default()).expect("configs");
        Self {
            style: ModelStyle::Cogvideox2b,
            transformer,
            vae,
            shape: ModelBenchShape {
                frames: 9,
                height: 128,
                width: 192,
                text_len: 226,
                batch,
                vae_tiling: false,
            },
            precision,
            device: ComputeDevice::Cpu,
            threads: 2,
            bridgev2w: timings,
            diffusers: None,
            gpu_peak_mib: None,
            cpu_bf16: None,
            cpu_linear: None,
            cpu_attention: None,
            onednn_fallbacks: 0,
        }
    }

    /// The three timed operations: each one's name as the table prints it,
    /// this crate's seconds and diffusers' time (`None`: diffusers did not
    /// run).
    pub fn rows(&self) -> [(String, f64, Option<PeerTime>); 3] {
        let (ours, theirs) = (&self.bridgev2w, self.diffusers.as_ref());
        let tiled = if self.shape.vae_tiling {
            " (tiled)"
        } else {
            ""
        };
        [
            (
                format!("transformer forward (b{})", self.shape.batch),
                ours.transformer_forward_s,
                theirs.map(|t| t.transformer_forward),
            ),
            (
                format!("VAE encode{tiled}"),
                ours.vae_encode_s,
                theirs.map(|t| t.vae_encode),
            ),
            (
                format!("VAE decode{tiled}"),
                ours.vae_decode_s,
                theirs.map(|t| t.vae_decode),
            ),
        ]
    }
}

/// diffusers' time over this crate's `ours` seconds as the tables print
/// it: `1.32x`, `> 22.2x` (diffusers stopped while running it: a lower
/// bound) or `-` (diffusers did not run it).
pub fn speed_up(ours: f64, theirs: Option<PeerTime>) -> String {
    match theirs {
        Some(PeerTime::Seconds(t)) => format!("{:.2}x", t / ours),
        Some(PeerTime::Over(t)) => format!("> {:.1}x", t / ours),
        Some(PeerTime::NotRun) | None => "-".to_owned(),
    }
}

impl fmt::Display for ModelBenchReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let (tf, s) = (&self.transformer, &self.shape);
        writeln!(
            f,
            "model: {} style, {} layers ({} heads x {}), VAE {:?}; {} frames at {}x{}, {:?} on {:?}, {} threads",
            self.style,
            tf.num_layers,
            tf.num_attention_heads,
            tf.attention_head_dim,
            self.vae.block_out_channels,
            s.frames,
            s.height,
            s.width,
            self.precision,
            self.device,
            self.threads
        )?;
        match self.cpu_bf16 {
            Some(crate::cpu_bf16::Bf16Compute::F32) => writeln!(
                f,
                "bf16 linear layers and convolutions: bridgev2w widens them to f32 (the default \
                 without AVX512-BF16, and on an Intel CPU without AMX; {}=native for libtorch's own), diffusers runs libtorch's",
                crate::cpu_bf16::ENV
            )?,
            Some(mode) => writeln!(
                f,
                "bf16 linear layers and convolutions: {mode} on both sides ({})",
                crate::cpu_bf16::ENV
            )?,
            None => {}
        }
        let on_onednn = self.cpu_linear.is_some_and(|m| {
            m == crate::cpu_linear::CpuLinear::OneDnn
                || (m == crate::cpu_linear::CpuLinear::OneDnnBf16
                    && self.precision == Precision::Bf16)
        });
        match self.cpu_linear {
            Some(crate::cpu_linear::CpuLinear::OneDnnBf16) if !on_onednn => writeln!(
                f,
                "linear layers: libtorch's linear on both sides (MKL's sgemm, at its best on \
                 this Intel CPU; bf16 ones run on oneDNN; {}=onednn for oneDNN in f32 too)",
                crate::cpu_linear::ENV
            )?,
            Some(_) if on_onednn => writeln!(
                f,
                "linear layers: bridgev2w runs them on oneDNN with weights packed at the \
                 first forward (the warm-up) and the GELU fused ({}=aten for libtorch's \
                 linear), diffusers on libtorch's linear",
                crate::cpu_linear::ENV
            )?,
            Some(mode) => writeln!(
                f,
                "linear layers: libtorch's linear on both sides ({}={mode})",
                crate::cpu_linear::ENV
            )?,
            None => {}
        }
        match self.cpu_attention {
            Some(crate::cpu_attention::CpuAttention::OneDnn) => writeln!(
                f,
                "attention: bridgev2w runs it on oneDNN's bf16 micro-kernel ({}=aten for \
                 libtorch's), diffusers on libtorch's scaled_dot_product_attention",
                crate::cpu_attention::ENV
            )?,
            Some(mode) => writeln!(
                f,
                "attention: libtorch's scaled_dot_product_attention on both sides ({}={mode})",
                crate::cpu_attention::ENV
            )?,
            None => {}
        }
        if self.onednn_fallbacks > 0 {
            writeln!(
                f,
                "warning: {} oneDNN calls failed and ran libtorch's op instead (timings mixed)",
                self.onednn_fallbacks
            )?;
        }
        writeln!(
            f,
            "{:<24} {:>12} {:>12} {:>10}",
            "operation", "bridgev2w s", "diffusers s", "speed-up"
        )?;
        for (name, ours, theirs) in self.rows() {
            let t = match theirs {
                Some(PeerTime::Seconds(t)) => format!("{t:.3}"),
                Some(PeerTime::Over(t)) => format!("> {t:.1}"),
                Some(PeerTime::NotRun) => "not run".to_owned(),
                None => "-".to_owned(),
            };
            let ratio = speed_up(ours, theirs);
            writeln!(f, "{name:<24} {ours:>12.3} {t:>12} {ratio:>10}")?;
        }
        let theirs = self.diffusers.as_ref();
        if let Some(limit) = theirs.and_then(|t| t.stopped_after_s) {
            writeln!(
                f,
                "diffusers was stopped at --diffusers-limit {limit:.0} (a limit for each \
                 operation): `>` bounds an operation from below (the time it had run, shared \
                 among its warm-up and timed runs); `not run`: not started"
            )?;
        }
        let Some(peak) = self.gpu_peak_mib else {
            return Ok(());
        };
        let show = |p: Option<u64>| p.map_or("n/a".to_owned(), |m| format!("{m} MiB"));
        writeln!(
            f,
            "peak GPU memory above idle (nvidia-smi, whole run): bridgev2w {}, diffusers {}",
            show(peak.bridgev2w),
            if theirs.is_none() {
                "-".to_owned()
            } else {
                show(peak.diffusers)
            }
        )?;
        if peak.bridgev2w.is_none() {
            writeln!(
                f,
                "  (n/a: `{NVIDIA_SMI}` could not be queried on this machine)"
            )?;
        }
        Ok(())
    }
}

/// The transformer and VAE configs of `options`: the style's, with
/// `options.layers` blocks and positions sized for the clip.
pub fn bench_configs(
    options: &ModelBenchOptions,
) -> Result<(TransformerConfig, VaeConfig), BenchError> {
    let a = options;
    let (mut tf, vae) = a.style.configs();
    if a.layers < 1 {
        return Err(BenchError::Invalid(format!(
            "--layers {}: expected >= 1",
            a.layers
        )));
    }
    tf.num_layers = a.layers;
    let s = 8;
    if tf.use_learned_positional_embeddings
        && (a.height / s != tf.sample_height || a.width / s != tf.sample_width)
    {
        // Learned positions exist for one resolution only: size them for this one.
        tf.sample_height = a.height / s;
        tf.sample_width = a.width / s;
    }
    tf.sample_frames = tf.sample_frames.max(a.frames);
    Ok((tf, vae))
}

/// Times this crate's model, then (unless `options.diffusers` is off)
/// diffusers' on the same configs, each under a GPU memory probe on CUDA.
pub fn bench_model(
    options: &ModelBenchOptions,
    progress: &dyn Progress,
) -> Result<ModelBenchReport, BenchError> {
    let a = options;
    let (tf, vae) = bench_configs(a)?;
    let shape = ModelBenchShape {
        frames: a.frames,
        height: a.height,
        width: a.width,
        text_len: tf.max_text_seq_length,
        batch: a.batch,
        vae_tiling: a.vae_tiling,
    };
    let gpu = match a.device {
        ComputeDevice::Cuda(i) => Some(i),
        ComputeDevice::Cpu => None,
    };
    let (ours, our_peak) = with_gpu_peak(NVIDIA_SMI, gpu, || {
        time_model(&tf, &vae, &shape, a.device, a.precision, a.repeat)
    })?;
    let (theirs, their_peak) = if a.diffusers {
        if a.precision == Precision::Bf16
            && a.device == ComputeDevice::Cpu
            && crate::cpu_bf16::libtorch_bf16_conv_is_scalar()
        {
            progress.note(&format!(
                "note: this CPU has no AVX-512 (nor AVX-NE-CONVERT), so diffusers' bf16 VAE runs \
                 libtorch's scalar slow_conv3d: hours at these shapes where this crate (widened \
                 to f32) takes seconds; {}",
                match a.diffusers_limit {
                    Some(l) => format!("each diffusers operation is stopped after {} s", l.as_secs()),
                    None => "--diffusers-limit SECONDS stops each operation then and reports what finished".into(),
                }
            ));
        }
        progress.note("running diffusers on the same configs...");
        let (t, p) = with_gpu_peak(NVIDIA_SMI, gpu, || {
            DiffusersPeer::find(a.python.as_deref(), a.repo.as_deref())?.time_model(
                &tf,
                &vae,
                &shape,
                a.device,
                a.precision,
                a.repeat,
                a.diffusers_limit,
            )
        })?;
        (Some(t), p)
    } else {
        (None, None)
    };
    Ok(ModelBenchReport {
        style: a.style,
        transformer: tf,
        vae,
        shape,
        precision: a.precision,
        device: a.device,
        threads: torch_threads(),
        bridgev2w: ours,
        diffusers: theirs,
        gpu_peak_mib: gpu.map(|_| GpuPeakMib {
            bridgev2w: our_peak,
            diffusers: their_peak,
        }),
        cpu_bf16: (a.precision == Precision::Bf16 && a.device == ComputeDevice::Cpu)
            .then(crate::cpu_bf16::mode),
        cpu_linear: (a.device == ComputeDevice::Cpu).then(crate::cpu_linear::mode),
        cpu_attention: (a.precision == Precision::Bf16 && a.device == ComputeDevice::Cpu)
            .then(crate::cpu_attention::mode),
        onednn_fallbacks: crate::cpu_linear::fallbacks() + crate::cpu_attention::fallbacks(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn configs_check_the_style_and_layers() {
        let e = "x".parse::<ModelStyle>().expect_err("style").to_string();
        assert_eq!(e, "--style: \"x\": expected one of 2b, 5b-i2v");
        assert_eq!(
            "5b-i2v".parse::<ModelStyle>().ok(),
            Some(ModelStyle::Cogvideox5bI2v)
        );
        let mut o = ModelBenchOptions::default();
        assert_eq!(o.style.to_string(), "2b");
        o.layers = 0;
        let e = bench_configs(&o).expect_err("layers");
        assert_eq!(e.to_string(), "--layers 0: expected >= 1");
        o.style = ModelStyle::Cogvideox5bI2v;
        o.layers = 2;
        let (tf, _) = bench_configs(&o).expect("5b");
        assert_eq!(
            (tf.num_layers, tf.sample_height, tf.sample_width),
            (2, 16, 24)
        );
    }

    #[test]
    fn report_prints_dashes_without_diffusers_and_memory_only_on_cuda() {
        let t = ModelTimings {
            transformer_forward_s: 2.0,
            vae_encode_s: 1.0,
            vae_decode_s: 4.0,
        };
        let mut report = ModelBenchReport::example(Precision::F32, 2, t.clone());
        let text = report.to_string();
        assert_eq!(text.lines().count(), 5, "{text}");
        assert!(text.contains("transformer forward (b2)        2.000            -          -"));
        report.diffusers = Some(PeerTimings::finished(&ModelTimings {
            vae_decode_s: 8.0,
            ..t.clone()
        }));
        report.gpu_peak_mib = Some(GpuPeakMib {
            bridgev2w: None,
            diffusers: Some(12),
        });
        let text = report.to_string();
        assert!(
            text.contains("VAE decode                      4.000        8.000      2.00x"),
            "{text}"
        );
        assert!(text.contains("bridgev2w n/a, diffusers 12 MiB"), "{text}");
        report.shape.vae_tiling = true;
        let text = report.to_string();
        assert!(
            text.contains("VAE decode (tiled)              4.000        8.000      2.00x"),
            "{text}"
        );
        assert!(
            text.ends_with("could not be queried on this machine)\n"),
            "{text}"
        );
        // bf16 on the CPU says how this crate computed it.
        report.cpu_bf16 = Some(crate::cpu_bf16::Bf16Compute::F32);
        let text = report.to_string();
        assert!(
            text.lines()
                .nth(1)
                .is_some_and(|l| l.contains("widens them to f32")),
            "{text}"
        );
        report.cpu_bf16 = Some(crate::cpu_bf16::Bf16Compute::Native);
        assert!(report.to_string().contains("native on both sides"));
        // The CPU says which kernels ran the linear layers.
        report.cpu_bf16 = None;
        report.cpu_linear = Some(crate::cpu_linear::CpuLinear::OneDnn);
        let text = report.to_string();
        assert!(
            text.lines()
                .nth(1)
                .is_some_and(|l| l.contains("on oneDNN with weights packed")),
            "{text}"
        );
        report.cpu_linear = Some(crate::cpu_linear::CpuLinear::Aten);
        assert!(report
            .to_string()
            .contains("libtorch's linear on both sides (BRIDGEV2W_CPU_LINEAR=aten)"));
        // On an Intel CPU f32 layers stay on MKL, bf16 ones go to oneDNN.
        report.cpu_linear = Some(crate::cpu_linear::CpuLinear::OneDnnBf16);
        let (precision, text) = (report.precision, report.to_string());
        assert_eq!(
            text.contains("on oneDNN with weights packed"),
            precision == Precision::Bf16,
            "{text}"
        );
        report.precision = if precision == Precision::Bf16 {
            Precision::F32
        } else {
            Precision::Bf16
        };
        let flipped = report.to_string();
        assert_eq!(
            flipped.contains("on oneDNN with weights packed"),
            report.precision == Precision::Bf16,
            "{flipped}"
        );
        assert!(
            [&text, &flipped]
                .iter()
                .any(|t| t.contains("MKL's sgemm, at its best on this Intel CPU")),
            "{text}{flipped}"
        );
        report.precision = precision;
        // bf16 on the CPU says which kernel ran the attention.
        report.cpu_linear = None;
        report.cpu_attention = Some(crate::cpu_attention::CpuAttention::OneDnn);
        let text = report.to_string();
        assert!(
            text.lines()
                .nth(1)
                .is_some_and(|l| l.contains("oneDNN's bf16 micro-kernel")),
            "{text}"
        );
        report.cpu_attention = Some(crate::cpu_attention::CpuAttention::Aten);
        assert!(report
            .to_string()
            .contains("scaled_dot_product_attention on both sides (BRIDGEV2W_CPU_ATTENTION=aten)"));
        assert!(!report.to_string().contains("warning"));
        report.onednn_fallbacks = 3;
        assert!(report
            .to_string()
            .contains("warning: 3 oneDNN calls failed and ran libtorch's op instead"));
        // diffusers stopped at its limit: a bound where it was, `not run` after.
        report.diffusers = Some(PeerTimings {
            transformer_forward: PeerTime::Seconds(3.0),
            vae_encode: PeerTime::Over(600.0),
            vae_decode: PeerTime::NotRun,
            stopped_after_s: Some(1800.0),
        });
        let text = report.to_string();
        assert!(
            text.contains("transformer forward (b2)        2.000        3.000      1.50x"),
            "{text}"
        );
        assert!(
            text.contains("VAE encode (tiled)              1.000      > 600.0   > 600.0x"),
            "{text}"
        );
        assert!(
            text.contains("VAE decode (tiled)              4.000      not run          -"),
            "{text}"
        );
        assert!(
            text.contains("diffusers was stopped at --diffusers-limit 1800 (a limit for each"),
            "{text}"
        );
    }
}
