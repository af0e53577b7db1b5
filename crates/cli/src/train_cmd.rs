//! `bridgev2w train CONFIG.toml`: fine-tunes BridgeV2W (ControlNet + LoRA) with
//! the paper's losses; see `bridgev2w_train::config` for the file's fields.

use anyhow::{Context, Result};
use bridgev2w_train::config::TrainConfig;
use bridgev2w_train::distributed::DistEnv;
use bridgev2w_train::eval_run::{evaluate_run, EvalRunOptions};
use bridgev2w_train::evaluate::EvalOptions;
use bridgev2w_train::trainer::Trainer;
use indicatif::{ProgressBar, ProgressStyle};
use std::path::PathBuf;

/// Arguments of `train`.
#[derive(Debug, clap::Args)]
pub struct TrainArgs {
    /// The training configuration (TOML; paper defaults for missing fields).
    config: PathBuf,
    /// Continue a run: a checkpoint folder, or a run folder (its latest checkpoint).
    #[arg(long)]
    resume: Option<PathBuf>,
    /// Replace the run that `train.out` already holds (its config, metrics,
    /// checkpoints and final weights); without it such a folder is refused.
    #[arg(long, conflicts_with = "resume")]
    overwrite: bool,
    /// Override `train.max_steps`.
    #[arg(long)]
    max_steps: Option<usize>,
    /// Override `train.out`.
    #[arg(long)]
    out: Option<PathBuf>,
    /// No progress bar (one line per step on stderr instead).
    #[arg(long)]
    quiet: bool,
}

pub fn run(args: &TrainArgs) -> Result<()> {
    let mut cfg = TrainConfig::from_file(&args.config)?;
    if let Some(n) = args.max_steps {
        cfg.train.max_steps = n;
    }
    if let Some(o) = &args.out {
        cfg.train.out = o.clone();
    }
    // Data parallelism from torchrun's variables: RANK / WORLD_SIZE / MASTER_ADDR / MASTER_PORT.
    let dist = DistEnv::from_env()?;
    if let Some(d) = &dist {
        eprintln!("{}", d.describe());
    }
    let mut trainer = Trainer::new_distributed(cfg, dist).context("setting up training")?;
    if args.overwrite {
        trainer.overwrite_existing_run();
    }
    if let Some(r) = &args.resume {
        trainer
            .resume(r)
            .with_context(|| format!("resuming from {}", r.display()))?;
        eprintln!("resumed at step {}", trainer.step);
    }
    let total = trainer.total_steps();
    for line in trainer.describe() {
        eprintln!("{line}");
    }
    let primary = trainer.is_primary();
    let pb = if args.quiet || !primary {
        ProgressBar::hidden()
    } else {
        let pb = ProgressBar::new(total as u64);
        pb.set_style(
            ProgressStyle::with_template("train [{bar:30}] {pos}/{len} {per_sec} eta {eta} {msg}")
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
        );
        pb.set_position(trainer.step as u64);
        pb
    };
    let quiet = args.quiet && primary;
    let result = trainer.run(&mut |m| {
        let msg = m.summary();
        if quiet {
            eprintln!("step {} {msg} {:.2} it/s", m.step, 1.0 / m.secs.max(1e-9));
        }
        pb.set_message(msg);
        pb.inc(1);
    });
    pb.finish();
    result?;
    if !primary {
        eprintln!(
            "done: {} steps (rank {})",
            trainer.step,
            trainer.rank_and_world().0
        );
        return Ok(());
    }
    let weights = trainer.cfg.train.out.join("final/weights.safetensors");
    eprintln!(
        "done: {} steps; weights in {}",
        trainer.step,
        weights.display()
    );
    Ok(())
}

/// The sampling flags of `eval-run` and `eval-grid`.
#[derive(Debug, clap::Args)]
pub struct SamplingArgs {
    /// Denoising steps.
    #[arg(long, default_value_t = 20)]
    steps: usize,
    /// Classifier-free guidance scale (1 = off).
    #[arg(long, default_value_t = 1.0)]
    guidance: f64,
    /// Sampling seed.
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// The first latent frame of the predictions: `generated` (diffusers'
    /// sampler) or `replaced` by the image latent at every step.
    #[arg(long, default_value = "generated")]
    first_frame: bridgev2w_world_model::pipeline::FirstFrame,
    /// Where sampling starts, in (0, 1]: 1 from pure noise; s < 1 from the
    /// first frame's latent in every frame, noised to the level a fraction s
    /// from the end of the steps (only the last ceil(s * steps) steps run).
    #[arg(long, default_value_t = 1.0)]
    strength: f64,
    /// Keep the static scene (beyond the paper): outside the region the
    /// robot's masks have swept so far, dilated by this many pixels, each
    /// predicted frame is the first frame. Off when not given.
    #[arg(long, value_name = "MARGIN_PX")]
    keep_static: Option<u32>,
}

impl SamplingArgs {
    /// The evaluation's sampling options (no grid, all videos).
    pub fn eval_options(&self) -> EvalOptions {
        EvalOptions {
            steps: self.steps,
            guidance: self.guidance,
            seed: self.seed,
            first_frame: self.first_frame,
            strength: self.strength,
            keep_static_margin_px: self.keep_static,
            ..EvalOptions::default()
        }
    }
}

/// The split names of a `--splits` flag (comma-separated, blanks around
/// names ignored): refused when it names no split or one twice.
pub(crate) fn split_list(text: &str) -> Result<Vec<String>> {
    let splits: Vec<String> = text
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(String::from)
        .collect();
    if splits.is_empty() {
        anyhow::bail!("--splits {text:?}: expected at least one split name, comma-separated (e.g. test,unseen_camera,unseen_scene)");
    }
    for (i, name) in splits.iter().enumerate() {
        if splits[..i].contains(name) {
            anyhow::bail!(
                "--splits {text:?}: split {name:?} is named twice: expected distinct names"
            );
        }
    }
    Ok(splits)
}

#[derive(Debug, clap::Args)]
pub struct EvalRunArgs {
    /// The run's training configuration (TOML).
    config: PathBuf,
    /// The run folder (its latest checkpoint) or a checkpoint folder.
    #[arg(long)]
    run: PathBuf,
    /// Splits of the run's dataset to score, comma-separated.
    #[arg(long, default_value = "test,unseen_camera,unseen_scene")]
    splits: String,
    #[command(flatten)]
    sampling: SamplingArgs,
    /// At most this many videos per split (0 = all).
    #[arg(long, default_value_t = 0)]
    max_videos: usize,
    /// Also write the scores as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
    /// Replace an existing --json file.
    #[arg(long, requires = "json")]
    overwrite: bool,
    /// The weights to score: `averaged` (the run's moving averages when it
    /// keeps them, `train.ema_decay > 0`; else its parameters) or `raw`.
    #[arg(long, default_value = "averaged")]
    weights: bridgev2w_train::ema::RunWeights,
    /// The robot segmenter of Mask-IoU, trained on the run's training split:
    /// `cnn` (a small dilated CNN, shape-aware) or `color` (a colour classifier).
    #[arg(long, default_value = "cnn")]
    segmenter: bridgev2w_train::segmenter::SegmenterKind,
    /// Also write DIR/<split>.gif: the first --grid-clips clips of each split,
    /// a row each, first frame | masks | prediction | ground truth.
    #[arg(long, value_name = "DIR")]
    grids: Option<PathBuf>,
    /// Clips per grid.
    #[arg(long, default_value_t = 4)]
    grid_clips: usize,
}

/// `bridgev2w eval-run`: PSNR/SSIM of a trained run's predictions per split,
/// next to the copy-the-first-frame baseline.
pub fn run_eval_run(args: &EvalRunArgs) -> Result<()> {
    let splits = split_list(&args.splits)?;
    if let Some(path) = &args.json {
        bridgev2w_io::output::check_new_file(path, args.overwrite)
            .map_err(|e| anyhow::anyhow!("--json {e}"))?;
    }
    let o = EvalRunOptions {
        config: args.config.clone(),
        run: args.run.clone(),
        splits,
        sampling: EvalOptions {
            max_videos: args.max_videos,
            grid_dir: args.grids.clone(),
            grid_clips: args.grid_clips,
            ..args.sampling.eval_options()
        },
        weights: args.weights,
        segmenter: args.segmenter,
    };
    let evaluation = evaluate_run(&o, &crate::progress::TerminalProgress::default())?;
    if let Some(path) = &args.json {
        bridgev2w_io::json::write_json_atomic(path, &evaluation.to_json())?;
    }
    crate::print_stdout(&evaluation.markdown())
}
