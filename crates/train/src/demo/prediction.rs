//! The world-model half of the demo: the model predicts the video of a
//! built-in synthetic pick-and-place (an unseen camera) from its first frame
//! and masks; the prediction is written as MP4 and as a GIF of panels
//! (first frame | masks | prediction | ground truth) and scored against the
//! ground truth next to copying the first frame.

use super::{DemoError, DemoOptions};
use bridgev2w_data::synth::{Split, SynthConfig, Task, World};
use bridgev2w_data::video::Mp4VideoWriter;
use bridgev2w_embodiment::overlay::{mask_rgb, side_by_side, upscale, write_gif};
use bridgev2w_eval::clip::{compare_with_copy, ClipComparison, ClipScore};
use bridgev2w_eval::MetricError;
use bridgev2w_io::atomic::write_atomic;
use bridgev2w_io::frame::{u8_from_unit, RgbFrame};
use bridgev2w_io::FileError;
use bridgev2w_world_model::bridge::{BridgeV2W, BridgeV2WConfig};
use bridgev2w_world_model::pipeline::{PredictOptions, SampleOptions, WorldModel};
use bridgev2w_world_model::video::MaskVideo;
use bridgev2w_world_model::{ComputeDevice, Precision};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// The shipped demo model: `assets/demo-model` under the working directory,
/// else in the source tree the binary was built from.
pub fn default_model_dir() -> PathBuf {
    let local = PathBuf::from("assets/demo-model");
    if local.is_dir() {
        local
    } else {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo-model")
    }
}

/// What the prediction did.
#[derive(Debug, Clone)]
pub struct PredictionSummary {
    /// The model folder.
    pub model: PathBuf,
    /// Predicted frames.
    pub frames: usize,
    /// Width (pixels).
    pub width: usize,
    /// Height (pixels).
    pub height: usize,
    /// Denoising steps.
    pub steps: usize,
    /// Seconds.
    pub seconds: f64,
    /// The scores against the ground truth, next to copying the first frame.
    pub scores: ClipComparison,
}

impl PredictionSummary {
    /// The lines to print; `out` is the demo's output folder.
    pub fn lines(&self, out: &Path) -> Vec<String> {
        let dynamic = |s: &ClipScore| {
            s.dynamic_psnr
                .map_or_else(|| "-".to_owned(), |v| format!("{v:.2} dB"))
        };
        let s = &self.scores;
        vec![
            format!(
                "  against the ground truth: PSNR {:.2} dB, SSIM {:.3}, dynamic-region PSNR {} (copying the first frame: {:.2} dB, {:.3}, {})",
                s.prediction.psnr,
                s.prediction.ssim,
                dynamic(&s.prediction),
                s.copy_first_frame.psnr,
                s.copy_first_frame.ssim,
                dynamic(&s.copy_first_frame),
            ),
            format!(
                "  world model ({}): {} frames at {}x{} predicted from the first frame and the masks of a built-in pick-and-place (unseen camera), {} steps, in {:.1} s",
                self.model.display(),
                self.frames,
                self.width,
                self.height,
                self.steps,
                self.seconds
            ),
            format!(
                "  the prediction: {0}/prediction.mp4 (H.264) and {0}/prediction.gif (first frame | masks | prediction | ground truth); {0}/prediction-actions.json, {0}/prediction-scores.json",
                out.display()
            ),
            "  side-by-side videos of the proof run per split (first frame | masks | BridgeV2W | ablation | ground truth): docs/results/grids/<split>.gif, linked from docs/results.md (bridgev2w eval-grid)".to_string(),
        ]
    }
}

/// JSON text of `value`, or an error naming `path`.
fn json_text(
    path: &Path,
    value: &impl serde::Serialize,
    pretty: bool,
) -> Result<String, FileError> {
    let r = if pretty {
        serde_json::to_string_pretty(value)
    } else {
        serde_json::to_string(value)
    };
    r.map_err(|source| FileError::Json {
        path: path.to_path_buf(),
        source,
    })
}

/// Predicts, writes the prediction's files into `out` and scores it.
pub fn predict(o: &DemoOptions, out: &Path) -> Result<PredictionSummary, DemoError> {
    let t0 = Instant::now();
    let dir = o.model.clone().unwrap_or_else(default_model_dir);
    let (backbone, weights) = (dir.join("backbone"), dir.join("bridgev2w.safetensors"));
    if !backbone.is_dir() || !weights.is_file() {
        return Err(DemoError::NotAModel(dir));
    }
    let model = BridgeV2W::load(
        &backbone,
        Some(&weights),
        None,
        BridgeV2WConfig::paper(),
        ComputeDevice::auto(),
        Precision::F32,
    )
    .map_err(|source| DemoError::ModelLoad {
        path: dir.clone(),
        source,
    })?;
    let (h, w) = model.resolution();
    let frames = model.clip_frames();
    // The built-in scene: a pick-and-place of the synthetic world, seen from
    // a camera region the model never trained on.
    let world = World::new(&SynthConfig {
        frames: 2 * frames - 1,
        width: w as u32,
        height: h as u32,
        seed: 2026,
        tasks: vec![Task::PickPlace],
        episodes_per_split: [0, 0, 1, 0],
        ..SynthConfig::default()
    })?;
    let episode = world.generate(Split::UnseenCamera, 0, Task::PickPlace)?;
    let image = RgbFrame::from_rgb8(w, h, &episode.rgb[0]).map_err(MetricError::from)?;
    let masks = MaskVideo {
        frames,
        height: h,
        width: w,
        // Link labels: the binary coding reads them as the silhouette.
        data: episode.labels[..frames].concat(),
    };
    let opts = PredictOptions {
        sample: SampleOptions {
            steps: o.steps,
            guidance_scale: 1.0,
            dynamic_cfg: false,
            seed: o.seed,
            first_frame: o.first_frame,
            ..SampleOptions::default()
        },
        max_batch: None,
        ..PredictOptions::default()
    };
    let video = model.predict(&image, &masks, &opts)?;
    let px = h * w * 3;
    let pred: Vec<Vec<u8>> = video
        .data
        .chunks(px)
        .map(|f| f.iter().map(|&v| u8_from_unit(v)).collect())
        .collect();
    let mut writer = Mp4VideoWriter::new(&out.join("prediction.mp4"), w, h, 10)?;
    for (i, f) in pred.iter().enumerate() {
        writer.push(f, i == 0)?;
    }
    write_atomic(&out.join("prediction.mp4"), &writer.to_bytes()?)?;
    // first frame | masks | prediction | ground truth, 3x upscaled
    let k = 3;
    let first = upscale(&episode.rgb[0], w, h, k);
    let gif: Vec<Vec<u8>> = (0..frames)
        .map(|t| {
            let mask = upscale(&mask_rgb(&episode.masks[t]), w, h, k);
            let p = upscale(&pred[t], w, h, k);
            let g = upscale(&episode.rgb[t], w, h, k);
            side_by_side(&[&first, &mask, &p, &g], w * k, h * k)
        })
        .collect();
    write_gif(
        &out.join("prediction.gif"),
        (4 * w * k) as u32,
        (h * k) as u32,
        &gif,
        5,
    )?;
    let actions_path = out.join("prediction-actions.json");
    write_atomic(
        &actions_path,
        json_text(&actions_path, &&episode.actions[..frames], false)?.as_bytes(),
    )?;
    // The prediction against the ground truth, next to copying the first frame.
    let to_frames = |clip: &[Vec<u8>]| -> Result<Vec<RgbFrame>, DemoError> {
        Ok(clip
            .iter()
            .map(|f| RgbFrame::from_rgb8(w, h, f).map_err(MetricError::from))
            .collect::<Result<_, _>>()?)
    };
    let scores = compare_with_copy(&to_frames(&pred)?, &to_frames(&episode.rgb[..frames])?)?;
    let json = |s: &ClipScore| serde_json::json!({"psnr": s.psnr, "ssim": s.ssim, "dynamic_psnr": s.dynamic_psnr});
    let scores_path = out.join("prediction-scores.json");
    let value = serde_json::json!({
        "prediction": json(&scores.prediction),
        "copy_first_frame": json(&scores.copy_first_frame),
    });
    write_atomic(
        &scores_path,
        json_text(&scores_path, &value, true)?.as_bytes(),
    )?;
    Ok(PredictionSummary {
        model: dir,
        frames,
        width: w,
        height: h,
        steps: o.steps,
        seconds: t0.elapsed().as_secs_f64(),
        scores,
    })
}
