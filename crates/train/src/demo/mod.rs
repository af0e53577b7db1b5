//! `bridgev2w demo`: the built-in Franka doing a pick-and-place, seen from a
//! built-in camera; writes masks, labels, PNGs and an animated GIF overlay
//! ([`run_demo`]). Then the world model ([`prediction`]): the shipped small
//! BridgeV2W (trained on the synthetic world by
//! `scripts/reproduce-synthetic.sh`) predicts the video of a built-in
//! synthetic pick-and-place from its first frame and the masks of its
//! actions: `prediction.mp4` and a side-by-side GIF.
//!
//! Everything is written into a temporary folder and renamed into place at
//! the end ([`OutputDir`]): a failed demo leaves no half-written output.
//! An existing output is replaced without `--overwrite` only when it is an
//! earlier demo's ([`ownership`]: marked, and nothing else in it).

mod ownership;
pub mod prediction;
mod scene;

pub use ownership::{not_an_earlier_demo, DEMO_FILES, DEMO_MARKER};
pub use prediction::PredictionSummary;
pub use scene::{demo_actions, demo_camera};

use bridgev2w_embodiment::actions::{actions_to_joints, write_ik_report};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::IkOptions;
use bridgev2w_embodiment::masks::{
    empty_masks_warning, render_trajectory, write_outputs, WriteOptions,
};
use bridgev2w_embodiment::overlay::{floor_background, overlay, write_gif};
use bridgev2w_io::output::OutputDir;
use bridgev2w_world_model::pipeline::FirstFrame;
use rayon::prelude::*;
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Errors of the demo: each names what failed.
#[derive(Debug, thiserror::Error)]
pub enum DemoError {
    /// The robot, camera, actions or masks.
    #[error(transparent)]
    Embodiment(#[from] bridgev2w_embodiment::embodiment::EmbodimentError),
    /// The built-in camera.
    #[error(transparent)]
    Camera(#[from] bridgev2w_embodiment::camera::CameraError),
    /// The built-in actions or their IK.
    #[error(transparent)]
    Actions(#[from] bridgev2w_embodiment::actions::ActionError),
    /// Writing the masks.
    #[error(transparent)]
    Masks(#[from] bridgev2w_embodiment::masks::WriteError),
    /// The output folder.
    #[error(transparent)]
    Output(#[from] bridgev2w_io::output::OutputError),
    /// The GIF overlay.
    #[error(transparent)]
    Overlay(#[from] bridgev2w_embodiment::overlay::OverlayError),
    /// A file.
    #[error(transparent)]
    File(#[from] bridgev2w_io::FileError),
    /// The synthetic scene of the prediction.
    #[error(transparent)]
    Synth(#[from] bridgev2w_data::synth::SynthError),
    /// The prediction's MP4.
    #[error(transparent)]
    Video(#[from] bridgev2w_data::video::VideoError),
    /// The world model.
    #[error(transparent)]
    Model(#[from] bridgev2w_world_model::WorldModelError),
    /// Scoring the prediction.
    #[error(transparent)]
    Metric(#[from] bridgev2w_eval::MetricError),
    /// A setting with a value it cannot take (the flag, the value, what
    /// was expected).
    #[error("{flag} {value}: {expected}")]
    Option {
        /// The flag.
        flag: &'static str,
        /// Its value.
        value: String,
        /// What was expected.
        expected: String,
    },
    /// A size beyond its maximum or the machine's memory.
    #[error(transparent)]
    Memory(#[from] bridgev2w_io::memory::MemoryError),
    /// The output exists and is not an earlier demo's output.
    #[error("{}: exists and is not an earlier demo's output ({reason}); choose another --out, or pass --overwrite to replace it", path.display())]
    NotADemo {
        /// The output folder.
        path: PathBuf,
        /// Why it is not a demo's.
        reason: String,
    },
    /// The model folder is not a demo model.
    #[error("demo model {}: expected backbone/ (a diffusers CogVideoX I2V folder) and bridgev2w.safetensors; pass --model DIR, or --no-predict for masks only", .0.display())]
    NotAModel(PathBuf),
    /// Loading the model folder failed.
    #[error("loading the demo model from {}", path.display())]
    ModelLoad {
        /// The folder.
        path: PathBuf,
        /// Why.
        #[source]
        source: bridgev2w_world_model::WorldModelError,
    },
}

/// The settings of the demo.
#[derive(Debug, Clone)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct DemoOptions {
    /// Output directory (written to a temporary folder beside it, then
    /// renamed). An earlier demo's output there (a folder marked
    /// `.bridgev2w-demo` holding nothing but the demo's files) is replaced;
    /// any other existing folder is refused unless --overwrite.
    #[cfg_attr(feature = "clap", arg(long, default_value = "demo-out"))]
    pub out: PathBuf,
    /// Replace an existing --out folder that is not an earlier demo's output.
    #[cfg_attr(feature = "clap", arg(long))]
    pub overwrite: bool,
    /// Frames in the trajectory (CogVideoX clips are 49 frames).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DemoOptions::default().frames))]
    pub frames: usize,
    /// The world model for the prediction: a folder with `backbone/` (a
    /// diffusers CogVideoX I2V folder) and `bridgev2w.safetensors`; default:
    /// the shipped demo model (assets/demo-model).
    #[cfg_attr(feature = "clap", arg(long))]
    pub model: Option<PathBuf>,
    /// Skip the world-model prediction (masks and overlay only).
    #[cfg_attr(feature = "clap", arg(long))]
    pub no_predict: bool,
    /// Denoising steps of the prediction (2: chosen on the training split,
    /// see docs/results.md "Fewer denoising steps").
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DemoOptions::default().steps))]
    pub steps: usize,
    /// Sampling seed of the prediction.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DemoOptions::default().seed))]
    pub seed: u64,
    /// The first latent frame of the prediction: `generated` (diffusers'
    /// sampler) or `replaced` by the image latent at every step.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = DemoOptions::default().first_frame))]
    pub first_frame: FirstFrame,
}

impl Default for DemoOptions {
    fn default() -> Self {
        Self {
            out: PathBuf::from("demo-out"),
            overwrite: false,
            frames: 49,
            model: None,
            no_predict: false,
            steps: 2,
            seed: 0,
            first_frame: FirstFrame::default(),
        }
    }
}

impl DemoOptions {
    /// Checks the settings before anything is written or allocated:
    /// `frames` at least 2, and the masks of that many frames of the demo
    /// camera within [`bridgev2w_embodiment::masks::check_render_size`]'s
    /// bounds and the machine's memory.
    pub fn validate(&self) -> Result<(), DemoError> {
        if self.frames < 2 {
            return Err(DemoError::Option {
                flag: "--frames",
                value: self.frames.to_string(),
                expected: "expected at least 2 frames in the trajectory (CogVideoX clips are 49)"
                    .into(),
            });
        }
        let k = demo_camera()?.intrinsics;
        bridgev2w_embodiment::masks::check_render_size(
            "--frames",
            self.frames,
            k.width,
            k.height,
            false,
        )?;
        Ok(())
    }
}

/// What the demo did, for the person who ran it.
#[derive(Debug, Clone)]
pub struct DemoReport {
    /// The output folder.
    pub out: PathBuf,
    /// Frames rendered.
    pub frames: usize,
    /// The largest IK position residual (mm).
    pub max_ik_residual_mm: f64,
    /// Seconds in all.
    pub seconds: f64,
    /// A warning about empty masks, if any.
    pub warning: Option<String>,
    /// The prediction, unless skipped.
    pub prediction: Option<PredictionSummary>,
}

impl DemoReport {
    /// The lines to print: the prediction's, then the masks'.
    pub fn lines(&self) -> Vec<String> {
        let mut lines = self
            .prediction
            .as_ref()
            .map(|p| p.lines(&self.out))
            .unwrap_or_default();
        let out = self.out.as_path();
        let (gif, still) = (out.join("overlay.gif"), out.join("overlay.png"));
        lines.push(format!(
            "demo: {} frames of the Franka pick-and-place at 720x480 (IK max residual {:.4} mm) in {:.2} s",
            self.frames, self.max_ik_residual_mm, self.seconds
        ));
        lines.push(format!(
            "  {}/masks.npy, labels.npy, labels.json, frames/*.png",
            out.display()
        ));
        lines.push(format!(
            "  {}, {}  (colour overlay: animation, middle frame)",
            gif.display(),
            still.display()
        ));
        lines.push(format!(
            "  {}/actions.json + camera.json: re-render with",
            out.display()
        ));
        lines.push(format!(
            "  bridgev2w masks --robot franka --camera {0}/camera.json --actions {0}/actions.json --out OUT",
            out.display()
        ));
        lines
    }
}

/// Runs the demo; `tick` is called once per rendered mask frame. An
/// existing `o.out` is replaced when it is an earlier demo's output (or
/// `o.overwrite`), else refused; an `o.out` that is, is inside or contains
/// the model folder is refused.
pub fn run_demo(o: &DemoOptions, tick: &(dyn Fn() + Sync)) -> Result<DemoReport, DemoError> {
    let start = Instant::now();
    o.validate()?;
    let model = (!o.no_predict).then(|| {
        o.model
            .clone()
            .unwrap_or_else(prediction::default_model_dir)
    });
    let inputs: Vec<&Path> = model.iter().map(PathBuf::as_path).collect();
    // Whether to replace is decided under the output's lock; nothing is
    // replaced before the commit.
    let output = OutputDir::create_for(&o.out, true, &inputs)?;
    ownership::check_replaceable(&o.out, o.overwrite)?;
    ownership::write_marker(output.path())?;
    let e = Embodiment::builtin("franka")?;
    let camera = demo_camera()?;
    let actions = demo_actions(&e, o.frames)?;
    let (joints, residuals) = actions_to_joints(
        &e.robot,
        &e.end_effectors,
        &actions,
        &e.home,
        &IkOptions::default(),
        false,
    )?;
    // Depth as well: the overlay shades the links by it.
    let frames = render_trajectory(&e.robot, &camera, &joints, tick);
    let out = output.path();
    let written = write_outputs(
        out,
        &e.robot,
        &frames,
        WriteOptions {
            pngs: true,
            depth: false,
        },
    )?;
    write_ik_report(out, &residuals)?;
    let write =
        |name: &str, bytes: &[u8]| bridgev2w_io::atomic::write_atomic(&out.join(name), bytes);
    write("camera.json", camera.to_json().as_bytes())?;
    write(
        "actions.json",
        serde_json::to_string(&actions.rows)
            .map_err(|source| bridgev2w_io::FileError::Json {
                path: out.join("actions.json"),
                source,
            })?
            .as_bytes(),
    )?;
    let background = floor_background(&camera);
    let rgb: Vec<Vec<u8>> = frames.par_iter().map(|f| overlay(f, &background)).collect();
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    write_gif(&out.join("overlay.gif"), width, height, &rgb, 10)?;
    let mid = &rgb[rgb.len() / 2];
    write(
        "overlay.png",
        &bridgev2w_io::png::encode_rgb8(width, height, mid),
    )?;
    let warning = empty_masks_warning(&written.empty_frames, frames.len());
    let max_ik_residual_mm = residuals
        .iter()
        .map(|r| r.position_error_m)
        .fold(0.0, f64::max)
        * 1e3;
    let prediction = if o.no_predict {
        None
    } else {
        Some(prediction::predict(o, out)?)
    };
    // Checked again: a file the user put there meanwhile is not lost.
    ownership::check_replaceable(&o.out, o.overwrite)?;
    output.commit()?;
    Ok(DemoReport {
        out: o.out.clone(),
        frames: frames.len(),
        max_ik_residual_mm,
        seconds: start.elapsed().as_secs_f64(),
        warning,
        prediction,
    })
}
