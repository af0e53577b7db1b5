//! `bridgev2w eval` (video metrics between predicted and ground-truth videos)
//! and `bridgev2w eval-policy` (MMRV and Pearson r between real and
//! world-model success rates): arguments, one library call
//! ([`bridgev2w_train::score`], [`bridgev2w_eval::policy_rates`]), printing.

use anyhow::{anyhow, Result};
use bridgev2w_eval::policy_rates::{compare, read_rates};
use bridgev2w_io::json::write_json_atomic;
use bridgev2w_io::output::check_new_file;
use bridgev2w_train::score::{score_videos, MaskFolders, ScoreOptions, VideoMetric};
use clap::Args;
use std::path::PathBuf;

/// Arguments of `eval`.
#[derive(Debug, Args)]
pub struct EvalArgs {
    /// Predicted videos: one folder of PNG frames (000000.png, ...) or one H.264
    /// `NAME.mp4` per video.
    #[arg(long)]
    pub pred: PathBuf,
    /// Ground-truth videos, matched to --pred by name.
    #[arg(long)]
    pub gt: PathBuf,
    /// Robot masks of the predicted videos (one folder of PNG masks per video, non-zero = robot).
    #[arg(long, requires = "masks_gt")]
    pub masks_pred: Option<PathBuf>,
    /// Robot masks of the ground-truth videos (e.g. from the dataset or `bridgev2w masks`).
    #[arg(long, requires = "masks_pred")]
    pub masks_gt: Option<PathBuf>,
    /// Comma-separated metrics: psnr, ssim, lpips, fvd, mask_iou.
    #[arg(
        long,
        value_delimiter = ',',
        default_value = "psnr,ssim,lpips,fvd,mask_iou"
    )]
    pub metrics: Vec<String>,
    /// Also write the results as JSON to this file (atomically; an existing
    /// file is refused unless --overwrite).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Replace an existing --json file.
    #[arg(long)]
    pub overwrite: bool,
    /// LPIPS weights (AlexNet trunk + v0.1 heads, safetensors; see
    /// scripts/convert_reference_weights.py). Without them LPIPS is reported unavailable.
    #[arg(long)]
    pub lpips_weights: Option<PathBuf>,
    /// I3D (Kinetics-400) weights for FVD (safetensors with the PyTorch
    /// `InceptionI3d` key names; see scripts/convert_reference_weights.py).
    /// Without them FVD is reported unavailable.
    #[arg(long)]
    pub i3d_weights: Option<PathBuf>,
    /// Device for the LPIPS and I3D networks: cpu, cuda, cuda:N or auto.
    #[arg(long, default_value = "auto")]
    pub device: bridgev2w_world_model::ComputeDevice,
}

/// Arguments of `eval-policy`.
#[derive(Debug, Args)]
pub struct EvalPolicyArgs {
    /// Real-robot success rates: JSON {"task": {"policy": rate}} or CSV task,policy,success_rate.
    #[arg(long)]
    pub real: PathBuf,
    /// World-model success rates for the same tasks and policies, same formats.
    #[arg(long)]
    pub sim: PathBuf,
    /// Also write the results as JSON to this file (atomically; an existing
    /// file is refused unless --overwrite).
    #[arg(long)]
    pub json: Option<PathBuf>,
    /// Replace an existing --json file.
    #[arg(long)]
    pub overwrite: bool,
}

impl TryFrom<&EvalArgs> for ScoreOptions {
    type Error = anyhow::Error;

    /// Fails on an unknown `--metrics` name.
    fn try_from(a: &EvalArgs) -> Result<Self> {
        let metrics = a
            .metrics
            .iter()
            .map(|m| {
                m.parse::<VideoMetric>()
                    .map_err(|e| anyhow!("--metrics: {e}"))
            })
            .collect::<Result<_>>()?;
        Ok(Self {
            pred: a.pred.clone(),
            gt: a.gt.clone(),
            masks: a
                .masks_pred
                .clone()
                .zip(a.masks_gt.clone())
                .map(|(pred, gt)| MaskFolders { pred, gt }),
            metrics,
            lpips_weights: a.lpips_weights.clone(),
            i3d_weights: a.i3d_weights.clone(),
            device: a.device,
        })
    }
}

/// Refuses, before any work, a `--json` file that exists (unless
/// `--overwrite`) or whose folder does not.
fn check_json_out(json: Option<&std::path::Path>, overwrite: bool) -> Result<()> {
    let Some(path) = json else { return Ok(()) };
    check_new_file(path, overwrite).map_err(|e| anyhow!("--json {e}"))
}

pub fn run_eval(a: &EvalArgs) -> Result<()> {
    check_json_out(a.json.as_deref(), a.overwrite)?;
    let opts = ScoreOptions::try_from(a)?;
    let report = score_videos(&opts, &crate::progress::TerminalProgress::default())?;
    crate::print_stdout(&report.markdown())?;
    if let Some(path) = &a.json {
        write_json_atomic(path, &report.to_json())?;
    }
    Ok(())
}

/// `bridgev2w eval-policy`.
pub fn run_eval_policy(a: &EvalPolicyArgs) -> Result<()> {
    check_json_out(a.json.as_deref(), a.overwrite)?;
    let agreement = compare(&read_rates(&a.real)?, &read_rates(&a.sim)?)?;
    crate::print_stdout(&agreement.markdown())?;
    if let Some(path) = &a.json {
        write_json_atomic(path, &agreement.to_json())?;
    }
    Ok(())
}
