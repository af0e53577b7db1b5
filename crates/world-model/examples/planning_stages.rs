//! Where a planning batch's time goes: one batch of candidates through a
//! BridgeV2W model in the stages of `predict_batch` (first-frame encode, the
//! masks' VAE encode, one transformer + ControlNet call, the VAE decode of
//! every frame, and of the last latent-frame batch alone as
//! `--decode-frames last` does), each timed alone, medians of the repeats
//! after a warm-up. The total counts the full decode.
//!
//!     cargo run --release -p bridgev2w-world-model --example planning_stages -- \
//!         MODEL_DIR WEIGHTS [BATCH=16] [REPEATS=5] [f32|bf16]
//!
//! Inputs are random in [-1, 1] at the model's shapes: the times do not
//! depend on the values.

use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::error::Error;
use std::path::Path;
use std::time::Instant;
use tch::{Device, Kind, Tensor};

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() -> Result<(), Box<dyn Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.len() < 2 {
        return Err("usage: planning_stages MODEL_DIR WEIGHTS [BATCH] [REPEATS] [f32|bf16]".into());
    }
    let batch: i64 = args.get(2).map_or(Ok(16), |s| s.parse())?;
    let repeats: usize = args.get(3).map_or(Ok(5), |s| s.parse())?;
    let precision = match args.get(4).map(String::as_str) {
        None | Some("f32") => Precision::F32,
        Some("bf16") => Precision::Bf16,
        Some(other) => return Err(format!("precision {other:?}: expected f32 or bf16").into()),
    };
    let model = BridgeV2W::load(
        Path::new(&args[0]),
        Some(Path::new(&args[1])),
        None,
        BridgeV2WConfig::default(),
        ComputeDevice::auto(),
        precision,
    )?;
    let cfg = model.config();
    let (t, h, w) = (cfg.frames as i64, cfg.height as i64, cfg.width as i64);
    let _guard = tch::no_grad_guard();
    let unit = |shape: &[i64]| Tensor::rand(shape, (Kind::Float, Device::Cpu)) * 2.0 - 1.0;
    let masks = unit(&[batch, 3, t, h, w]);
    let first = unit(&[batch, 3, 1, h, w]);
    let names = [
        "first-frame encode",
        "mask encode",
        "transformer + ControlNet",
        "decode (all frames)",
        "decode (last batch)",
    ];
    let mut times = vec![Vec::new(); names.len()];
    for rep in 0..=repeats {
        let mut stage = Vec::with_capacity(names.len());
        let clock = Instant::now();
        let image = model.encode_latents(&first, Some(0))?; // [B, 1, C, h, w]
        stage.push(clock.elapsed().as_secs_f64());
        let clock = Instant::now();
        let mask_latents = model.encode_latents(&masks, None)?; // [B, t, C, h, w]
        stage.push(clock.elapsed().as_secs_f64());
        let clock = Instant::now();
        let image = image.expand_as(&mask_latents); // [B, t, C, h, w]
        let control = Tensor::cat(&[&mask_latents, &image], 2); // [B, t, 2C, h, w]
        let timestep = Tensor::full([batch], 999, (Kind::Int64, Device::Cpu));
        let velocity = model.velocity_with(&control, &timestep, Some(&control))?;
        stage.push(clock.elapsed().as_secs_f64());
        let clock = Instant::now();
        let _video = model.decode_latents(&velocity)?; // [B, 3, T, H, W]
        stage.push(clock.elapsed().as_secs_f64());
        let clock = Instant::now();
        let _last = model.decode_latents_last(&velocity)?; // [B, 3, T', H, W]
        stage.push(clock.elapsed().as_secs_f64());
        if rep > 0 {
            for (all, s) in times.iter_mut().zip(stage) {
                all.push(s);
            }
        }
    }
    let medians: Vec<f64> = times.into_iter().map(median).collect();
    let total: f64 = medians[..4].iter().sum();
    println!(
        "{batch} candidates, {t} frames at {h}x{w}, {precision:?}, {} threads, median of {repeats}:",
        tch::get_num_threads()
    );
    for (name, s) in names.iter().zip(&medians) {
        println!("  {name:<26} {s:7.3} s  {:5.1}%", 100.0 * s / total);
    }
    println!(
        "  {:<26} {total:7.3} s  ({:.3} s per candidate)",
        "total",
        total / batch as f64
    );
    let last = total - medians[3] + medians[4];
    println!(
        "  {:<26} {last:7.3} s  ({:.3} s per candidate, {:.2}x the total)",
        "total, last batch decoded",
        last / batch as f64,
        last / total
    );
    Ok(())
}
