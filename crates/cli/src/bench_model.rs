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
    let ours = time_model(&tf, &vae, &shape, a.device, a.precision, a.repeat)?;
    let theirs = if a.no_diffusers {
        None
    } else {
        eprintln!("running diffusers on the same configs...");
        Some(diffusers(a, &tf, &vae)?)
    };
    println!(
        "{:<24} {:>12} {:>12} {:>10}",
        "operation", "bridgev2w s", "diffusers s", "speed-up"
    );
    let rows = [
        (
            "transformer forward",
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
    Ok(())
}
