//! Speed of the video metrics against scikit-image, for `bridgev2w bench
//! metrics`: PSNR + SSIM of the same deterministic frame pairs scored here
//! (rayon threads) and by `scripts/bench/skimage_metrics.py` (worker
//! processes, in the bench venv), with the largest difference of the values.

use crate::video::{psnr, ssim};
use crate::MetricError;
use bridgev2w_io::atomic::write_atomic;
use bridgev2w_io::frame::RgbFrame;
use bridgev2w_io::peer::{self, PeerError};
use bridgev2w_io::progress::Progress;
use bridgev2w_io::FileError;
use rayon::prelude::*;
use std::fmt;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// Why the bench could not run.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The options are out of range: says which and what is expected.
    #[error("{0}")]
    Invalid(String),
    /// A metric rejected its input.
    #[error(transparent)]
    Metric(#[from] MetricError),
    /// scikit-image could not be found, run or understood.
    #[error(transparent)]
    Peer(#[from] PeerError),
    /// A frame file for the peer could not be written.
    #[error(transparent)]
    File(#[from] FileError),
}

/// What `bench metrics` scores.
#[derive(Debug, Clone, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct MetricsBenchOptions {
    /// Frame pairs scored.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = MetricsBenchOptions::default().frames))]
    pub frames: usize,
    /// Frame width (at least 11, the SSIM window).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = MetricsBenchOptions::default().width))]
    pub width: usize,
    /// Frame height (at least 11).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = MetricsBenchOptions::default().height))]
    pub height: usize,
    /// Worker processes for scikit-image (default: all cores, like this crate's threads).
    #[cfg_attr(feature = "clap", arg(long))]
    pub workers: Option<usize>,
    /// Repository root (holds scripts/bench/); default: found from the
    /// current directory.
    #[cfg_attr(feature = "clap", arg(long))]
    pub repo: Option<PathBuf>,
}

impl Default for MetricsBenchOptions {
    fn default() -> Self {
        Self {
            frames: 50,
            width: 720,
            height: 480,
            workers: None,
            repo: None,
        }
    }
}

/// The measurements of `bench metrics`; `Display` prints them as a table.
#[derive(Debug, Clone, PartialEq)]
pub struct MetricsBenchReport {
    /// Frame pairs scored.
    pub frames: usize,
    /// Frame width.
    pub width: usize,
    /// Frame height.
    pub height: usize,
    /// This crate's frame pairs per second (PSNR and SSIM each).
    pub frames_per_s: f64,
    /// Its threads.
    pub threads: usize,
    /// scikit-image's frame pairs per second.
    pub peer_frames_per_s: f64,
    /// Its worker processes.
    pub peer_workers: usize,
    /// Largest |SSIM difference| over the frames.
    pub max_ssim_diff: f64,
    /// Largest |PSNR difference| in dB.
    pub max_psnr_diff: f64,
}

impl fmt::Display for MetricsBenchReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "scene: {} frame pairs at {}x{} (RGB, uint8)",
            self.frames, self.width, self.height
        )?;
        writeln!(
            f,
            "bridgev2w-eval PSNR+SSIM  {:>10.2} frames/s  ({} threads)",
            self.frames_per_s, self.threads
        )?;
        writeln!(
            f,
            "scikit-image PSNR+SSIM    {:>10.2} frames/s  ({} processes)",
            self.peer_frames_per_s, self.peer_workers
        )?;
        writeln!(
            f,
            "ratio                     {:>10.1}x",
            self.frames_per_s / self.peer_frames_per_s
        )?;
        writeln!(
            f,
            "agreement: max |SSIM diff| {:.2e}, max |PSNR diff| {:.2e} dB",
            self.max_ssim_diff, self.max_psnr_diff
        )
    }
}

use bridgev2w_io::seed::SplitMix64;

/// Deterministic test frames `[n, h, w, 3]`: smooth colour gradients with
/// texture and noise; the "predicted" frame is a blurred, shifted, noisy
/// copy. Returns `(pred, gt)`.
fn metric_frames(n: usize, w: usize, h: usize) -> (Vec<u8>, Vec<u8>) {
    let mut rng = SplitMix64::new(17);
    let mut noise = || (rng.next_u64() >> 56) as i32 - 128;
    let mut gt = vec![0u8; n * h * w * 3];
    let mut pred = vec![0u8; n * h * w * 3];
    for t in 0..n {
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let i = ((t * h + y) * w + x) * 3 + c;
                    let smooth = (x * (c + 1) * 255 / w + y * 255 / h + t * 3) % 256;
                    let texture = ((x / 8 + y / 8 + c) % 2) as i32 * 40;
                    let g = (smooth as i32 / 2 + texture + noise() / 16).clamp(0, 255);
                    gt[i] = g as u8;
                    pred[i] = (g + 6 + noise() / 8).clamp(0, 255) as u8;
                }
            }
        }
    }
    (pred, gt)
}

/// Largest absolute difference of paired values.
fn max_diff(ours: impl Iterator<Item = f64>, theirs: &[f64]) -> f64 {
    ours.zip(theirs)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max)
}

/// Scores the bench frames here (conversion to `[0, 1]` floats included,
/// as on the peer's side), then with scikit-image in the bench venv.
pub fn bench_metrics(
    options: &MetricsBenchOptions,
    progress: &dyn Progress,
) -> Result<MetricsBenchReport, BenchError> {
    let (w, h, n) = (options.width, options.height, options.frames);
    if n == 0 || w < 11 || h < 11 {
        return Err(BenchError::Invalid(
            "--frames must be >= 1 and --width/--height >= 11 (the SSIM window)".into(),
        ));
    }
    // The predicted and ground-truth frames (RGB8) and their .npy copies
    // for the peer: 12 bytes a pixel of every frame, checked before any is made.
    let estimate = bridgev2w_io::memory::bytes(&[n as u64, w as u64, h as u64, 12]);
    bridgev2w_io::memory::check_fits(
        &format!("the metrics bench's {n} frames of {w}x{h}"),
        estimate,
        "lower --frames or --width/--height",
    )
    .map_err(|e| BenchError::Invalid(e.to_string()))?;
    let (pred, gt) = metric_frames(n, w, h);
    let frame_len = w * h * 3;
    let threads = rayon::current_num_threads();
    let t0 = Instant::now();
    let ours: Vec<(f64, f64)> = (0..n)
        .into_par_iter()
        .map(|t| -> Result<(f64, f64), MetricError> {
            let r = t * frame_len..(t + 1) * frame_len;
            let p = RgbFrame::from_rgb8(w, h, &pred[r.clone()])?;
            let g = RgbFrame::from_rgb8(w, h, &gt[r])?;
            Ok((psnr(&p, &g)?, ssim(&p, &g)?))
        })
        .collect::<Result<_, _>>()?;
    let frames_per_s = n as f64 / t0.elapsed().as_secs_f64();

    let repo = peer::find_repo(options.repo.as_deref())?;
    let python = peer::bench_python(&repo)?;
    let workers = options.workers.unwrap_or(threads).max(1);
    let tmp = peer::scratch_dir()?;
    let (pred_path, gt_path) = (tmp.path().join("pred.npy"), tmp.path().join("gt.npy"));
    write_atomic(
        &pred_path,
        &bridgev2w_io::npy::encode_npy(&[n, h, w, 3], &pred),
    )?;
    write_atomic(&gt_path, &bridgev2w_io::npy::encode_npy(&[n, h, w, 3], &gt))?;
    progress.note(&format!(
        "running scikit-image with {workers} worker process(es)..."
    ));
    let result = run_skimage(&python, &repo, &pred_path, &gt_path, workers)?;
    let seconds = result.number("seconds")?;
    let (their_psnr, their_ssim) = (result.numbers("psnr")?, result.numbers("ssim")?);
    Ok(MetricsBenchReport {
        frames: n,
        width: w,
        height: h,
        frames_per_s,
        threads,
        peer_frames_per_s: n as f64 / seconds,
        peer_workers: workers,
        max_ssim_diff: max_diff(ours.iter().map(|o| o.1), &their_ssim),
        max_psnr_diff: max_diff(ours.iter().map(|o| o.0), &their_psnr),
    })
}

fn run_skimage(
    python: &Path,
    repo: &Path,
    pred: &Path,
    gt: &Path,
    workers: usize,
) -> Result<peer::PeerOutput, PeerError> {
    peer::run_peer_json(
        Command::new(python)
            .arg(repo.join("scripts/bench/skimage_metrics.py"))
            // One core per worker process, like one rayon thread per core.
            .envs([("OMP_NUM_THREADS", "1"), ("OPENBLAS_NUM_THREADS", "1")])
            .arg("--pred")
            .arg(pred)
            .arg("--gt")
            .arg(gt)
            .args(["--workers", &workers.to_string()]),
        "skimage_metrics.py",
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_frame_stream_is_splitmix64_from_seed_17() {
        // Reference values of SplitMix64 (seed 17).
        let mut rng = SplitMix64::new(17);
        let first: Vec<u64> = (0..2).map(|_| rng.next_u64()).collect();
        assert_eq!(first, [SPLITMIX_17[0], SPLITMIX_17[1]]);
        let (pred, gt) = metric_frames(2, 16, 12);
        assert_eq!((pred.len(), gt.len()), (2 * 12 * 16 * 3, 2 * 12 * 16 * 3));
        assert_ne!(pred, gt);
    }

    /// The first outputs of `bridgev2w_embodiment::kinematics::SplitMix64::new(17)`.
    const SPLITMIX_17: [u64; 2] = [0x8084_75f0_2ee3_7363, 0x6434_ff62_b4e8_edd1];

    #[test]
    fn small_frames_are_refused_before_any_peer_runs() {
        let options = MetricsBenchOptions {
            width: 10,
            ..MetricsBenchOptions::default()
        };
        let e = bench_metrics(&options, &bridgev2w_io::progress::Silent).expect_err("too small");
        assert_eq!(
            e.to_string(),
            "--frames must be >= 1 and --width/--height >= 11 (the SSIM window)"
        );
    }
}
