//! `bridgev2w train CONFIG.toml`: fine-tunes BridgeV2W (ControlNet + LoRA) with
//! the paper's losses; see `bridgev2w_train::config` for the file's fields.

use anyhow::{Context, Result};
use bridgev2w_train::config::TrainConfig;
use bridgev2w_train::distributed::DistEnv;
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
    // torchrun-style data parallelism: RANK / WORLD_SIZE / MASTER_ADDR / MASTER_PORT.
    let dist = DistEnv::from_env()?;
    if let Some(d) = &dist {
        eprintln!(
            "data-parallel: rank {} of {}, rank 0 at {}",
            d.rank,
            d.world,
            d.master()
        );
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
    eprintln!(
        "training {} step(s) ({} per epoch), flow estimator {}, {}, output {}",
        total,
        trainer.steps_per_epoch(),
        trainer.flow_estimator_name(),
        match trainer.autocast_dtype() {
            Some(d) => format!("{:?} autocast", d.kind()),
            None => "f32".to_string(),
        },
        trainer.cfg.train.out.display()
    );
    let primary = trainer.is_primary();
    if let Some(name) = trainer.collective_name() {
        let (rank, world) = trainer.rank_and_world();
        eprintln!(
            "rank {rank} of {world}: {} of {} batch items per step, {name} all-reduce{}",
            trainer.cfg.train.batch_size / world,
            trainer.cfg.train.batch_size,
            if primary {
                ""
            } else {
                " (rank 0 writes the outputs)"
            }
        );
    }
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
        let msg = if m.diffusion == 0.0 && (m.recon > 0.0 || m.kl > 0.0) {
            format!(
                "loss {:.4} (L1 {:.4} KL {:.3}) lr {:.2e} |g| {:.3}",
                m.loss, m.recon, m.kl, m.lr, m.grad_norm
            )
        } else {
            format!(
                "loss {:.4} (diff {:.4} dyn {:.4} flow {:.4}) lr {:.2e} |g| {:.3}",
                m.loss, m.diffusion, m.dynamics, m.flow, m.lr, m.grad_norm
            )
        };
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
    eprintln!(
        "done: {} steps; weights in {}",
        trainer.step,
        trainer
            .cfg
            .train
            .out
            .join("final/weights.safetensors")
            .display()
    );
    Ok(())
}

/// Arguments of `eval-run`.
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
    /// Denoising steps.
    #[arg(long, default_value_t = 20)]
    steps: usize,
    /// Classifier-free guidance scale (1 = off).
    #[arg(long, default_value_t = 1.0)]
    guidance: f64,
    /// At most this many videos per split (0 = all).
    #[arg(long, default_value_t = 0)]
    max_videos: usize,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Also write the scores as JSON.
    #[arg(long)]
    json: Option<PathBuf>,
    /// The first latent frame of the predictions: `generated` (diffusers'
    /// sampler) or `replaced` by the image latent at every step.
    #[arg(long, default_value = "generated")]
    first_frame: bridgev2w_world_model::pipeline::FirstFrame,
    /// The weights to score: `averaged` (the run's moving averages when it
    /// keeps them, `train.ema_decay > 0`; else its parameters) or `raw`.
    #[arg(long, default_value = "averaged")]
    weights: bridgev2w_train::ema::RunWeights,
    /// The robot segmenter of Mask-IoU, trained on the run's training split:
    /// `cnn` (a small dilated CNN, shape-aware) or `color` (a colour classifier).
    #[arg(long, default_value = "cnn")]
    segmenter: bridgev2w_train::segmenter::SegmenterKind,
}

/// `bridgev2w eval-run`: PSNR/SSIM of a trained run's predictions per split,
/// next to the copy-the-first-frame baseline.
pub fn run_eval_run(args: &EvalRunArgs) -> Result<()> {
    use bridgev2w_eval::segment::RobotSegmenter;
    use bridgev2w_train::evaluate::{color_segmenter, evaluate_split, EvalOptions};
    use bridgev2w_train::segmenter::{CnnSegmenter, SegmenterKind, SegmenterOptions};
    let cfg = TrainConfig::from_file(&args.config)?;
    let mut trainer = Trainer::new(cfg).context("setting up the run's model")?;
    trainer
        .resume(&args.run)
        .with_context(|| format!("loading the run {}", args.run.display()))?;
    let averaged = args.weights == bridgev2w_train::ema::RunWeights::Averaged
        && trainer.use_averaged_weights();
    eprintln!(
        "weights: {}",
        if averaged {
            format!(
                "moving averages (train.ema_decay = {})",
                trainer.cfg.train.ema_decay
            )
        } else {
            "parameters".to_string()
        }
    );
    let opts = EvalOptions {
        steps: args.steps,
        guidance: args.guidance,
        seed: args.seed,
        max_videos: args.max_videos,
        first_frame: args.first_frame,
    };
    let segmenter: Option<Box<dyn RobotSegmenter>> = match args.segmenter {
        SegmenterKind::Cnn => {
            let pb = ProgressBar::new_spinner().with_message("training the robot segmenter");
            pb.enable_steady_tick(std::time::Duration::from_millis(200));
            let s = CnnSegmenter::fit(&trainer.data, &SegmenterOptions::default())
                .context("training the robot segmenter")?;
            pb.finish_and_clear();
            if let Some(s) = &s {
                eprintln!("robot segmenter: CNN, final BCE {:.4}", s.final_loss);
            }
            s.map(|s| Box::new(s) as Box<dyn RobotSegmenter>)
        }
        SegmenterKind::Color => color_segmenter(&trainer.data)
            .context("fitting the robot segmenter")?
            .map(|s| Box::new(s) as Box<dyn RobotSegmenter>),
    };
    if segmenter.is_none() {
        eprintln!("note: the training split has no masks; Mask-IoU is not measured");
    }
    let mut rows = Vec::new();
    for split in args
        .splits
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
    {
        let pb = ProgressBar::new_spinner().with_message(format!("scoring {split}"));
        let scores = evaluate_split(&trainer, split, &opts, segmenter.as_deref(), &|| pb.tick())
            .with_context(|| format!("split {split}"))?;
        pb.finish_and_clear();
        rows.push(scores);
    }
    let mut text = format!(
        "run {} (step {}, stage {}), {} steps, guidance {}; scored on the predicted frames (all but frame 0, the input)\n\n| split | videos | PSNR | dynamic PSNR | SSIM | Mask-IoU | copy-first-frame PSNR | copy-first-frame dynamic PSNR | copy-first-frame SSIM | copy-first-frame Mask-IoU | segmenter ceiling | VAE ceiling PSNR | VAE ceiling dynamic PSNR | VAE ceiling SSIM |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
        args.run.display(),
        trainer.step,
        trainer.cfg.train.stage,
        args.steps,
        args.guidance
    );
    for r in &rows {
        let iou = |v: Option<f64>| v.map_or("-".to_string(), |x| format!("{:.1}", 100.0 * x));
        let db = |v: Option<f64>| v.map_or("-".to_string(), |x| format!("{x:.2}"));
        text.push_str(&format!(
            "| {} | {} | {:.2} | {} | {:.4} | {} | {:.2} | {} | {:.4} | {} | {} | {:.2} | {} | {:.4} |\n",
            r.split,
            r.videos,
            r.psnr,
            db(r.dynamic_psnr),
            r.ssim,
            iou(r.mask_iou),
            r.baseline_psnr,
            db(r.baseline_dynamic_psnr),
            r.baseline_ssim,
            iou(r.baseline_mask_iou),
            iou(r.segmenter_mask_iou),
            r.autoencoder_psnr,
            db(r.autoencoder_dynamic_psnr),
            r.autoencoder_ssim
        ));
    }
    if let Some(path) = &args.json {
        let body = serde_json::to_string_pretty(&serde_json::json!({
            "run": args.run,
            "step": trainer.step,
            "stage": trainer.cfg.train.stage,
            "mask_action": trainer.cfg.ablation.mask_action,
            "sampling_steps": args.steps,
            "guidance": args.guidance,
            "seed": args.seed,
            "segmenter": args.segmenter.to_string(),
            "splits": rows,
        }))?;
        bridgev2w_embodiment::npy::write_atomic(path, body.as_bytes())
            .with_context(|| format!("writing {}", path.display()))?;
    }
    crate::print_stdout(&text)
}
