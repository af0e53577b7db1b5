//! `bench loader`: clip-loader throughput of [`crate::data::ClipDataset`]
//! (batches per second, videos opened per second), on a given dataset or a
//! synthetic one generated in a temporary folder.

use crate::data::{ClipDataset, MaskKind, SourceSpec};
use crate::{Result, TrainError};
use bridgev2w_io::progress::Progress;
use std::fmt;
use std::path::PathBuf;
use std::time::Instant;

/// What `bench loader` loads (the command's flags).
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct LoaderBenchOptions {
    /// Dataset (LeRobot with masks/ or calibration); default: a synthetic
    /// one generated in a temporary folder.
    #[cfg_attr(feature = "clap", arg(long))]
    pub dataset: Option<PathBuf>,
    /// Robot for rendering calc masks (when the dataset has calibration and joint states).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = LoaderBenchOptions::default().robot))]
    pub robot: String,
    /// Episodes of the generated dataset.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = LoaderBenchOptions::default().episodes))]
    pub episodes: usize,
    /// Clip frames.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = LoaderBenchOptions::default().frames))]
    pub frames: usize,
    /// Clip width.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = LoaderBenchOptions::default().width))]
    pub width: usize,
    /// Clip height.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = LoaderBenchOptions::default().height))]
    pub height: usize,
    /// Clips per batch.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = LoaderBenchOptions::default().batch))]
    pub batch: usize,
    /// Batches assembled.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = LoaderBenchOptions::default().steps))]
    pub steps: usize,
}

impl Default for LoaderBenchOptions {
    fn default() -> Self {
        Self {
            dataset: None,
            robot: "franka".to_owned(),
            episodes: 8,
            frames: 25,
            width: 96,
            height: 64,
            batch: 4,
            steps: 50,
        }
    }
}

/// One timed opening of the dataset.
#[derive(Debug, Clone, PartialEq)]
pub struct OpenTiming {
    /// How the masks were obtained.
    pub label: String,
    /// Videos loaded.
    pub videos: usize,
    /// Seconds.
    pub seconds: f64,
}

/// The measurements of `bench loader`; `Display` prints them.
#[derive(Debug, Clone, PartialEq)]
pub struct LoaderBenchReport {
    /// The dataset root.
    pub root: PathBuf,
    /// rayon's threads.
    pub threads: usize,
    /// The openings: stored masks, then (synthetic dataset) rendered and cached calc masks.
    pub opens: Vec<OpenTiming>,
    /// Clips assembled into batches.
    pub clips: usize,
    /// Clip shape `(frames, height, width)`.
    pub clip_shape: (usize, usize, usize),
    /// Seconds to assemble them.
    pub batch_seconds: f64,
}

impl fmt::Display for LoaderBenchReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "clip loader on {} ({} threads)",
            self.root.display(),
            self.threads
        )?;
        for o in &self.opens {
            writeln!(
                f,
                "  open ({}): {} videos in {:.2} s = {:.1} videos/s",
                o.label,
                o.videos,
                o.seconds,
                o.videos as f64 / o.seconds
            )?;
        }
        let (t, h, w) = self.clip_shape;
        writeln!(
            f,
            "  batches: {} clips of {t}x{h}x{w} in {:.2} s = {:.1} clips/s",
            self.clips,
            self.batch_seconds,
            self.clips as f64 / self.batch_seconds
        )
    }
}

/// `--frames` within [`bridgev2w_world_model::bridge::MAX_CLIP_FRAMES`],
/// `--width`/`--height` within
/// [`bridgev2w_world_model::bridge::MAX_CLIP_SIDE`], `--batch` within
/// [`bridgev2w_world_model::bridge::MAX_PREDICT_BATCH`], and a batch of
/// clips (video and masks as floats, 16 bytes a pixel of every frame: a
/// floor) within the machine's memory.
fn check_sizes(a: &LoaderBenchOptions) -> Result<()> {
    use bridgev2w_io::memory::{at_most, bytes, check_fits};
    use bridgev2w_world_model::bridge::{MAX_CLIP_FRAMES, MAX_CLIP_SIDE, MAX_PREDICT_BATCH};
    at_most(
        "--frames",
        a.frames as u64,
        MAX_CLIP_FRAMES as u64,
        "frames",
    )?;
    at_most("--width", a.width as u64, MAX_CLIP_SIDE as u64, "pixels")?;
    at_most("--height", a.height as u64, MAX_CLIP_SIDE as u64, "pixels")?;
    at_most("--batch", a.batch as u64, MAX_PREDICT_BATCH as u64, "clips")?;
    check_fits(
        &format!(
            "the loader bench's batch of {} clips of {} frames at {}x{}",
            a.batch, a.frames, a.height, a.width
        ),
        bytes(&[
            a.batch as u64,
            a.frames as u64,
            a.height as u64,
            a.width as u64,
            16,
        ]),
        "lower --batch, --frames or --width/--height",
    )?;
    Ok(())
}

/// Opens the dataset (with stored masks; for the generated dataset also
/// with calc masks rendered, then read from the cache) and assembles
/// `options.steps` batches on the CPU.
pub fn bench_loader(
    options: &LoaderBenchOptions,
    progress: &dyn Progress,
) -> Result<LoaderBenchReport> {
    let a = options;
    check_sizes(a)?;
    let io = |path: &std::path::Path| {
        let path = path.to_path_buf();
        move |error| TrainError::Io { path, error }
    };
    let tmp = tempfile::tempdir().map_err(io(&std::env::temp_dir()))?;
    let root = match &a.dataset {
        Some(d) => d.clone(),
        None => {
            let out = tmp.path().join("synth");
            let cfg = bridgev2w_data::synth::SynthConfig {
                frames: a.frames,
                width: a.width as u32,
                height: a.height as u32,
                episodes_per_split: [a.episodes, 0, 0, 0],
                ..Default::default()
            };
            cfg.validate()?;
            progress.start(a.episodes, "generating a synthetic dataset");
            bridgev2w_data::synth::write_dataset(&cfg, &out, &|| progress.tick())?;
            progress.finish();
            out
        }
    };
    let spec = |masks: MaskKind| SourceSpec {
        root: root.clone(),
        split: "train".into(),
        video_key: None,
        masks,
        weight: 1.0,
    };
    let cache = tmp.path().join("mask-cache");
    let mut opens = Vec::new();
    let mut open = |label: &str, masks: MaskKind| -> Result<ClipDataset> {
        let t0 = Instant::now();
        let d = ClipDataset::open_sources(&[spec(masks)], a.frames, a.height, a.width, 20)?;
        opens.push(OpenTiming {
            label: label.to_owned(),
            videos: d.episodes.len(),
            seconds: t0.elapsed().as_secs_f64(),
        });
        Ok(d)
    };
    let stored = open(
        "decode + stored masks",
        MaskKind::Calc {
            robot: None,
            cache: cache.clone(),
        },
    )?;
    if a.dataset.is_none() {
        // The same dataset without masks/: calc masks rendered, then read from the cache.
        std::fs::rename(root.join("masks"), tmp.path().join("masks.off"))
            .map_err(io(&root.join("masks")))?;
        let calc = MaskKind::Calc {
            robot: Some(a.robot.clone()),
            cache: cache.clone(),
        };
        open("decode + render calc masks", calc.clone())?;
        open("decode + cached calc masks", calc)?;
    }
    let t0 = Instant::now();
    for step in 0..a.steps {
        stored.batch(
            0,
            step,
            a.batch,
            bridgev2w_world_model::ComputeDevice::Cpu.to_tch(),
        )?;
    }
    Ok(LoaderBenchReport {
        root,
        threads: rayon::current_num_threads(),
        opens,
        clips: a.steps * a.batch,
        clip_shape: (a.frames, a.height, a.width),
        batch_seconds: t0.elapsed().as_secs_f64(),
    })
}
