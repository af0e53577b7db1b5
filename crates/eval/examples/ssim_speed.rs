//! Profiling harness: PSNR + SSIM of one 720x480 frame pair, ten times, on
//! one thread. Usage: `cargo run --release -p bridgev2w-eval --example ssim_speed`.

use bridgev2w_eval::video::{psnr, ssim};
use bridgev2w_io::frame::RgbFrame;

fn main() -> Result<(), bridgev2w_eval::MetricError> {
    let (w, h) = (720, 480);
    let mut state = 1u64;
    let mut next = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 56) as u8
    };
    let a: Vec<u8> = (0..w * h * 3)
        .map(|i| ((i % w) as u8 / 2).wrapping_add(next() / 8))
        .collect();
    let b: Vec<u8> = a.iter().map(|&v| v.saturating_add(next() / 16)).collect();
    let (fa, fb) = (
        RgbFrame::from_rgb8(w, h, &a)?,
        RgbFrame::from_rgb8(w, h, &b)?,
    );
    let t = std::time::Instant::now();
    let mut checksum = 0.0;
    for _ in 0..10 {
        checksum += ssim(&fa, &fb)? + psnr(&fa, &fb)?;
    }
    println!(
        "{:.2} ms/frame (checksum {checksum})",
        t.elapsed().as_secs_f64() * 100.0
    );
    Ok(())
}
