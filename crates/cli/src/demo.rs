//! `bridgev2w demo`: the built-in Franka doing a pick-and-place (masks,
//! labels, PNGs, a GIF overlay), then the shipped world model's prediction
//! (`bridgev2w_train::demo`).

use crate::masks_cmd::progress_bar;
use anyhow::Result;
use bridgev2w_train::demo::{run_demo, DemoOptions};
use bridgev2w_world_model::pipeline::FirstFrame;
use std::path::PathBuf;

/// Arguments of `demo`.
#[derive(Debug, clap::Args)]
pub struct DemoArgs {
    /// Output directory (written to a temporary folder beside it, then renamed). An earlier
    /// demo's output there is replaced; any other existing folder is refused
    /// unless --overwrite.
    #[arg(long, default_value = "demo-out")]
    pub out: PathBuf,
    /// Replace an existing --out folder that is not an earlier demo's output.
    #[arg(long)]
    pub overwrite: bool,
    /// Frames in the trajectory (CogVideoX clips are 49 frames).
    #[arg(long, default_value_t = 49)]
    pub frames: usize,
    /// The world model for the prediction: a folder with `backbone/` (a
    /// diffusers CogVideoX I2V folder) and `bridgev2w.safetensors`; default:
    /// the shipped demo model (assets/demo-model).
    #[arg(long)]
    pub model: Option<PathBuf>,
    /// Skip the world-model prediction (masks and overlay only).
    #[arg(long)]
    pub no_predict: bool,
    /// Denoising steps of the prediction (2: chosen on the training split,
    /// see docs/results.md "Fewer denoising steps").
    #[arg(long, default_value_t = 2)]
    pub steps: usize,
    /// Sampling seed of the prediction.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// The first latent frame of the prediction: `generated` (diffusers'
    /// sampler) or `replaced` by the image latent at every step.
    #[arg(long, default_value = "generated")]
    pub first_frame: FirstFrame,
}

impl From<&DemoArgs> for DemoOptions {
    fn from(a: &DemoArgs) -> Self {
        Self {
            out: a.out.clone(),
            overwrite: a.overwrite,
            frames: a.frames,
            model: a.model.clone(),
            no_predict: a.no_predict,
            steps: a.steps,
            seed: a.seed,
            first_frame: a.first_frame,
        }
    }
}

pub fn run(args: &DemoArgs) -> Result<()> {
    let options: DemoOptions = args.into();
    options.validate()?;
    let frames = args.frames as u64;
    let pb = progress_bar(frames as usize, "rendering masks");
    let tick = || {
        pb.inc(1);
        if pb.position() >= frames {
            pb.finish_and_clear();
        }
    };
    let report = run_demo(&options, &tick);
    pb.finish_and_clear();
    let report = report?;
    if let Some(w) = &report.warning {
        eprintln!("{w}");
    }
    crate::print_stdout(&(report.lines().join("\n") + "\n"))
}
