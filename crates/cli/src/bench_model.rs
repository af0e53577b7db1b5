//! `bridgev2w bench model`: the world model's transformer forward and VAE
//! encode/decode against diffusers (`scripts/bench/diffusers_model.py`, the
//! project venv) on the same configs, shapes, threads and precision.

use anyhow::{bail, Context, Result};
use bridgev2w_world_model::bench::{time_model, ModelBenchShape, ModelTimings};
use bridgev2w_world_model::transformer::TransformerConfig;
use bridgev2w_world_model::vae::VaeConfig;
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::PathBuf;
use std::process::Command;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

#[derive(Debug, clap::Args)]
pub struct ModelBench {
    /// Architecture family: `2b` (sin-cos positions) or `5b-i2v` (RoPE, learned positions, I2V input).
    #[arg(long, default_value = "2b")]
    style: String,
    /// Transformer blocks (the full models have 30 / 42).
    #[arg(long, default_value_t = 8)]
    layers: i64,
    /// Pixel frames (4k + 1). The defaults keep a 2-core CPU run near two minutes;
    /// `--frames 25 --height 256 --width 384` is the mid-size setting of the issue
    /// (the full-width VAE then dominates: tens of minutes on 2 cores).
    #[arg(long, default_value_t = 9)]
    frames: i64,
    #[arg(long, default_value_t = 128)]
    height: i64,
    #[arg(long, default_value_t = 192)]
    width: i64,
    /// Transformer batch: 2 times one denoising step with classifier-free
    /// guidance (the pipeline's conditional and unconditional halves).
    #[arg(long, default_value_t = 1)]
    batch: i64,
    /// Timed runs per operation (best is reported), after one warm-up.
    #[arg(long, default_value_t = 1)]
    repeat: usize,
    /// f32 or bf16.
    #[arg(long, default_value = "f32")]
    precision: Precision,
    /// cpu, cuda or cuda:N.
    #[arg(long, default_value = "cpu")]
    device: ComputeDevice,
    /// Skip diffusers (time this crate only).
    #[arg(long)]
    no_diffusers: bool,
    /// Python with torch + diffusers (default: the project venv's).
    #[arg(long)]
    python: Option<PathBuf>,
    /// Repository root (holds scripts/bench/); default: found from the current directory.
    #[arg(long)]
    repo: Option<PathBuf>,
}

fn configs(a: &ModelBench) -> Result<(TransformerConfig, VaeConfig)> {
    let mut tf = match a.style.as_str() {
        "2b" => TransformerConfig::cogvideox_2b(),
        "5b-i2v" => TransformerConfig::cogvideox_5b_i2v(),
        other => bail!("--style {other}: expected 2b or 5b-i2v"),
    };
    if a.layers < 1 {
        bail!("--layers {}: expected >= 1", a.layers);
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
    let vae = if a.style == "2b" {
        VaeConfig::cogvideox_2b()
    } else {
        VaeConfig::cogvideox_5b_i2v()
    };
    Ok((tf, vae))
}

fn diffusers(a: &ModelBench, tf: &TransformerConfig, vae: &VaeConfig) -> Result<ModelTimings> {
    let repo = crate::bench::find_repo(a.repo.as_deref())?;
    let python = match &a.python {
        Some(p) => p.clone(),
        None => {
            let p = repo.join(".venv/bin/python");
            if !p.is_file() {
                bail!(
                    "{} not found: run scripts/setup-venv.sh (or pass --python / --no-diffusers)",
                    p.display()
                );
            }
            p
        }
    };
    let tmp = tempfile::tempdir()?;
    let (tf_path, vae_path) = (
        tmp.path().join("transformer.json"),
        tmp.path().join("vae.json"),
    );
    std::fs::write(&tf_path, serde_json::to_vec(tf)?)?;
    std::fs::write(&vae_path, serde_json::to_vec(vae)?)?;
    let device = match a.device {
        ComputeDevice::Cpu => "cpu".to_owned(),
        ComputeDevice::Cuda(i) => format!("cuda:{i}"),
    };
    let dtype = match a.precision {
        Precision::F32 => "f32",
        Precision::Bf16 => "bf16",
    };
    let v = crate::bench::run_peer_json(
        Command::new(&python)
            .arg(repo.join("scripts/bench/diffusers_model.py"))
            .arg("--transformer-config")
            .arg(&tf_path)
            .arg("--vae-config")
            .arg(&vae_path)
            .args(["--frames", &a.frames.to_string()])
            .args(["--height", &a.height.to_string()])
            .args(["--width", &a.width.to_string()])
            .args(["--text-len", &tf.max_text_seq_length.to_string()])
            .args(["--repeat", &a.repeat.to_string()])
            .args(["--batch", &a.batch.to_string()])
            .args(["--threads", &tch_threads().to_string()])
            .args(["--dtype", dtype, "--device", &device]),
        "diffusers_model.py",
    )?;
    let get = |k: &str| {
        v[k].as_f64()
            .with_context(|| format!("diffusers result lacks {k}"))
    };
    Ok(ModelTimings {
        transformer_forward_s: get("transformer_forward_s")?,
        vae_encode_s: get("vae_encode_s")?,
        vae_decode_s: get("vae_decode_s")?,
    })
}

fn tch_threads() -> usize {
    bridgev2w_world_model::bench::torch_threads()
}

pub fn run(a: &ModelBench) -> Result<()> {
    let (tf, vae) = configs(a)?;
    let shape = ModelBenchShape {
        frames: a.frames,
        height: a.height,
        width: a.width,
        text_len: tf.max_text_seq_length,
        batch: a.batch,
    };
    println!(
        "model: {} style, {} layers ({} heads x {}), VAE {:?}; {} frames at {}x{}, {:?} on {:?}, {} threads",
        a.style,
        tf.num_layers,
        tf.num_attention_heads,
        tf.attention_head_dim,
        vae.block_out_channels,
        a.frames,
        a.height,
        a.width,
        a.precision,
        a.device,
        tch_threads()
    );
    let gpu = match a.device {
        ComputeDevice::Cuda(i) => Some(i),
        ComputeDevice::Cpu => None,
    };
    let (ours, our_peak) = with_gpu_peak(NVIDIA_SMI, gpu, || {
        Ok(time_model(
            &tf,
            &vae,
            &shape,
            a.device,
            a.precision,
            a.repeat,
        )?)
    })?;
    let (theirs, their_peak) = if a.no_diffusers {
        (None, None)
    } else {
        eprintln!("running diffusers on the same configs...");
        let (t, p) = with_gpu_peak(NVIDIA_SMI, gpu, || diffusers(a, &tf, &vae))?;
        (Some(t), p)
    };
    println!(
        "{:<24} {:>12} {:>12} {:>10}",
        "operation", "bridgev2w s", "diffusers s", "speed-up"
    );
    let forward = format!("transformer forward (b{})", a.batch);
    let rows = [
        (
            forward.as_str(),
            ours.transformer_forward_s,
            theirs.as_ref().map(|t| t.transformer_forward_s),
        ),
        (
            "VAE encode",
            ours.vae_encode_s,
            theirs.as_ref().map(|t| t.vae_encode_s),
        ),
        (
            "VAE decode",
            ours.vae_decode_s,
            theirs.as_ref().map(|t| t.vae_decode_s),
        ),
    ];
    for (name, o, t) in rows {
        match t {
            Some(t) => println!("{name:<24} {o:>12.3} {t:>12.3} {:>9.2}x", t / o),
            None => println!("{name:<24} {o:>12.3} {:>12} {:>10}", "-", "-"),
        }
    }
    if gpu.is_some() {
        let show = |p: Option<u64>| p.map_or("n/a".to_owned(), |m| format!("{m} MiB"));
        println!(
            "peak GPU memory above idle (nvidia-smi, whole run): bridgev2w {}, diffusers {}",
            show(our_peak),
            if a.no_diffusers {
                "-".to_owned()
            } else {
                show(their_peak)
            }
        );
        if our_peak.is_none() {
            println!("  (n/a: `{NVIDIA_SMI}` could not be queried on this machine)");
        }
    }
    Ok(())
}

/// The tool that reports the GPU's used memory.
const NVIDIA_SMI: &str = "nvidia-smi";

/// Used memory of GPU `gpu` in MiB, from `nvidia-smi --query-gpu=memory.used`;
/// `None` when the tool is missing or prints something else.
fn gpu_used_mib(program: &str, gpu: usize) -> Option<u64> {
    let out = Command::new(program)
        .args([
            "--query-gpu=memory.used",
            "--format=csv,noheader,nounits",
            "-i",
            &gpu.to_string(),
        ])
        .output()
        .ok()?;
    if !out.status.success() {
        return None;
    }
    parse_used_mib(&String::from_utf8_lossy(&out.stdout))
}

/// The first line of `nvidia-smi --format=csv,noheader,nounits` as MiB.
fn parse_used_mib(text: &str) -> Option<u64> {
    text.lines().next()?.trim().parse().ok()
}

/// Runs `f` while a thread polls the used memory of `gpu` every 20 ms; returns
/// `f`'s result and the peak above the memory used before it started (`None`
/// on CPU, or when the GPU cannot be queried). Both sides of the bench are
/// measured this way (the same libtorch caching allocator on each), so the
/// figures compare; the process's CUDA context is included in both.
fn with_gpu_peak<T>(
    program: &str,
    gpu: Option<usize>,
    f: impl FnOnce() -> Result<T>,
) -> Result<(T, Option<u64>)> {
    let Some(gpu) = gpu else {
        return Ok((f()?, None));
    };
    let Some(idle) = gpu_used_mib(program, gpu) else {
        return Ok((f()?, None));
    };
    let stop = Arc::new(AtomicBool::new(false));
    let poller = {
        let (stop, program) = (Arc::clone(&stop), program.to_owned());
        std::thread::spawn(move || {
            let mut peak = idle;
            loop {
                if let Some(m) = gpu_used_mib(&program, gpu) {
                    peak = peak.max(m);
                }
                if stop.load(Ordering::Relaxed) {
                    return peak;
                }
                std::thread::sleep(Duration::from_millis(20));
            }
        })
    };
    let result = f();
    stop.store(true, Ordering::Relaxed);
    let peak = poller.join().ok();
    Ok((result?, peak.map(|p| p.saturating_sub(idle))))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_nvidia_smi_memory_lines() {
        assert_eq!(parse_used_mib("81234\n"), Some(81234));
        assert_eq!(parse_used_mib(" 17 \n4\n"), Some(17));
        assert_eq!(parse_used_mib("[N/A]\n"), None);
        assert_eq!(parse_used_mib(""), None);
    }

    #[test]
    fn peak_probe_reports_the_rise_above_idle_and_passes_errors_on() {
        // A stand-in for nvidia-smi whose reading rises by 100 MiB per call.
        let dir = tempfile::tempdir().expect("tempdir");
        let counter = dir.path().join("n");
        let fake = dir.path().join("fake-smi");
        std::fs::write(
            &fake,
            format!(
                "#!/bin/sh\nn=$(cat {c} 2>/dev/null || echo 0)\necho $((n + 1)) > {c}\necho $((1000 + 100 * n))\n",
                c = counter.display()
            ),
        )
        .expect("write");
        let status = Command::new("chmod").arg("+x").arg(&fake).status();
        assert!(status.is_ok_and(|s| s.success()));
        let prog = fake.to_str().expect("utf-8 path");
        let (v, peak) = with_gpu_peak(prog, Some(0), || {
            std::thread::sleep(Duration::from_millis(200));
            Ok(7)
        })
        .expect("probe");
        assert_eq!(v, 7);
        let peak = peak.expect("a peak");
        assert!(peak >= 100, "peak {peak}: the readings rose above idle");
        // CPU: no probe; a missing tool: no figure, the closure still runs.
        assert_eq!(with_gpu_peak(prog, None, || Ok(1)).expect("cpu").1, None);
        let missing = dir.path().join("absent");
        let r = with_gpu_peak(missing.to_str().expect("utf-8"), Some(0), || Ok(2));
        assert_eq!(r.expect("missing tool").1, None);
        // The closure's error comes back (and the poller is stopped).
        let e = with_gpu_peak(prog, Some(0), || -> Result<()> { bail!("boom") });
        assert!(e.is_err_and(|e| e.to_string().contains("boom")));
    }
}
