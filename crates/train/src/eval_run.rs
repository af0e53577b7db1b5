//! `eval-run`: a trained run's predictions scored per split (PSNR, dynamic
//! PSNR, SSIM, Mask-IoU) next to copying the first frame and the VAE's
//! ceiling, as a table and as the JSON that `eval-report` reads.

use crate::ema::RunWeights;
use crate::evaluate::{color_segmenter, evaluate_split, EvalOptions, SplitScores};
use crate::segmenter::{CnnSegmenter, SegmenterKind, SegmenterOptions};
use crate::trainer::Trainer;
use crate::{Result, TrainError};
use bridgev2w_eval::segment::RobotSegmenter;
use bridgev2w_io::progress::Progress;
use std::path::PathBuf;

/// What to score.
#[derive(Debug, Clone)]
pub struct EvalRunOptions {
    /// The run's training configuration (TOML).
    pub config: PathBuf,
    /// The run folder (its latest checkpoint) or a checkpoint folder.
    pub run: PathBuf,
    /// Splits of the run's dataset to score.
    pub splits: Vec<String>,
    /// Sampling.
    pub sampling: EvalOptions,
    /// Which weights.
    pub weights: RunWeights,
    /// The robot segmenter of Mask-IoU.
    pub segmenter: SegmenterKind,
}

/// The scores of a run.
#[derive(Debug, Clone)]
pub struct RunEvaluation {
    /// The settings.
    pub options: EvalRunOptions,
    /// The checkpoint's step.
    pub step: usize,
    /// The run's stage.
    pub stage: crate::config::Stage,
    /// Whether the run conditions on masks (`ablation.mask_action`).
    pub mask_action: bool,
    /// A row per split.
    pub rows: Vec<SplitScores>,
}

/// Loads the run and scores every split. `progress` sees the segmenter's
/// training and each split's scoring as stages of unknown length (total 0),
/// a tick per scored video, and notes (which weights, the segmenter's loss).
pub fn evaluate_run(o: &EvalRunOptions, progress: &dyn Progress) -> Result<RunEvaluation> {
    let (trainer, averaged) = Trainer::load_run(&o.config, &o.run, o.weights)?;
    progress.note(&format!(
        "weights: {}",
        if averaged {
            format!(
                "moving averages (train.ema_decay = {})",
                trainer.cfg.train.ema_decay
            )
        } else {
            "parameters".to_string()
        }
    ));
    let segmenter: Option<Box<dyn RobotSegmenter>> = match o.segmenter {
        SegmenterKind::Cnn => {
            progress.start(0, "training the robot segmenter");
            let s = CnnSegmenter::fit(&trainer.data, &SegmenterOptions::default())
                .map_err(TrainError::context("training the robot segmenter".into()));
            progress.finish();
            let s = s?;
            if let Some(s) = &s {
                progress.note(&format!(
                    "robot segmenter: CNN, final BCE {:.4}",
                    s.final_loss
                ));
            }
            s.map(|s| Box::new(s) as Box<dyn RobotSegmenter>)
        }
        SegmenterKind::Color => color_segmenter(&trainer.data)
            .map_err(TrainError::context("fitting the robot segmenter".into()))?
            .map(|s| Box::new(s) as Box<dyn RobotSegmenter>),
    };
    if segmenter.is_none() {
        progress.note("note: the training split has no masks; Mask-IoU is not measured");
    }
    let mut rows = Vec::new();
    for split in &o.splits {
        progress.start(0, &format!("scoring {split}"));
        let scores = evaluate_split(&trainer, split, &o.sampling, segmenter.as_deref(), &|| {
            progress.tick()
        })
        .map_err(TrainError::context(format!("split {split}")));
        progress.finish();
        rows.push(scores?);
    }
    Ok(RunEvaluation {
        options: o.clone(),
        step: trainer.step,
        stage: trainer.cfg.train.stage,
        mask_action: trainer.cfg.ablation.mask_action,
        rows,
    })
}

impl RunEvaluation {
    /// The scores as a markdown table with a line naming the run.
    pub fn markdown(&self) -> String {
        let o = &self.options;
        let mut text = format!(
            "run {} (step {}, stage {}), {} steps, guidance {}; scored on the predicted frames (all but frame 0, the input)\n\n| split | videos | PSNR | dynamic PSNR | SSIM | Mask-IoU | copy-first-frame PSNR | copy-first-frame dynamic PSNR | copy-first-frame SSIM | copy-first-frame Mask-IoU | segmenter ceiling | VAE ceiling PSNR | VAE ceiling dynamic PSNR | VAE ceiling SSIM |\n|---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
            o.run.display(),
            self.step,
            self.stage,
            o.sampling.steps,
            o.sampling.guidance
        );
        for r in &self.rows {
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
        text
    }

    /// The scores as the JSON `eval-report` reads.
    pub fn to_json(&self) -> serde_json::Value {
        let o = &self.options;
        serde_json::json!({
            "run": o.run,
            "step": self.step,
            "stage": self.stage,
            "mask_action": self.mask_action,
            "sampling_steps": o.sampling.steps,
            "guidance": o.sampling.guidance,
            "seed": o.sampling.seed,
            "segmenter": o.segmenter.to_string(),
            "splits": self.rows,
        })
    }
}
