//! `bridgev2w train CONFIG.toml`: fine-tunes BridgeV2W (ControlNet + LoRA) with
//! the paper's losses; see `bridgev2w_train::config` for the file's fields.

use anyhow::{Context, Result};
use bridgev2w_train::config::TrainConfig;
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
    let mut trainer = Trainer::new(cfg).context("setting up training")?;
    if let Some(r) = &args.resume {
        trainer
            .resume(r)
            .with_context(|| format!("resuming from {}", r.display()))?;
        eprintln!("resumed at step {}", trainer.step);
    }
    let total = trainer.total_steps();
    eprintln!(
        "training {} step(s) ({} per epoch), flow estimator {}, output {}",
        total,
        trainer.steps_per_epoch(),
        trainer.flow_estimator_name(),
        trainer.cfg.train.out.display()
    );
    let pb = if args.quiet {
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
    let quiet = args.quiet;
    let result = trainer.run(&mut |m| {
        let msg = format!(
            "loss {:.4} (diff {:.4} dyn {:.4} flow {:.4}) lr {:.2e} |g| {:.3}",
            m.loss, m.diffusion, m.dynamics, m.flow, m.lr, m.grad_norm
        );
        if quiet {
            eprintln!("step {} {msg} {:.2} it/s", m.step, 1.0 / m.secs.max(1e-9));
        }
        pb.set_message(msg);
        pb.inc(1);
    });
    pb.finish();
    result?;
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
