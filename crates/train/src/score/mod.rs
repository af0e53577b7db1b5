//! Video metrics between a folder of predicted videos and a folder of
//! ground-truth videos (`bridgev2w eval`): PSNR, SSIM and Mask-IoU per video
//! (averaged over frames, then videos), LPIPS with user-supplied AlexNet +
//! LPIPS v0.1 weights, and FVD with user-supplied I3D weights.
//!
//! A video is one folder of PNG frames (numbered by the digits at the end of
//! their names) or one H.264 `NAME.mp4`; predicted and ground-truth videos
//! are matched by name, and their frames by number. A metric that was asked
//! for but cannot be computed (no masks, no weights, too few videos for FVD)
//! is reported unavailable with the reason, not an error.
//!
//! ```no_run
//! use bridgev2w_io::progress::Silent;
//! use bridgev2w_train::score::{score_videos, ScoreOptions};
//! let report = score_videos(&ScoreOptions::new("pred", "gt"), &Silent)?;
//! print!("{}", report.markdown());
//! # Ok::<(), bridgev2w_train::score::ScoreError>(())
//! ```

mod error;
mod files;
mod networks;
mod per_video;

pub use error::{Result, ScoreError};
pub use files::video_names;
pub use per_video::{score_video, VideoScores};

use bridgev2w_io::progress::Progress;
use bridgev2w_world_model::ComputeDevice;
use rayon::prelude::*;
use std::collections::BTreeMap;
use std::path::PathBuf;

/// A video metric of [`score_videos`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum VideoMetric {
    /// Peak signal-to-noise ratio (dB), per frame on `[0, 1]` RGB.
    Psnr,
    /// Structural similarity, per frame.
    Ssim,
    /// LPIPS (AlexNet, v0.1 heads), per frame.
    Lpips,
    /// Frechet video distance between the two sets of videos.
    Fvd,
    /// IoU of the robot masks, per frame.
    MaskIou,
}

impl VideoMetric {
    /// Every metric, in the paper's column order.
    pub const ALL: [Self; 5] = [
        Self::Psnr,
        Self::Ssim,
        Self::Lpips,
        Self::Fvd,
        Self::MaskIou,
    ];

    /// The name (`psnr`, `ssim`, `lpips`, `fvd`, `mask_iou`): the
    /// [`std::str::FromStr`] spelling and the JSON key.
    pub fn name(self) -> &'static str {
        match self {
            Self::Psnr => "psnr",
            Self::Ssim => "ssim",
            Self::Lpips => "lpips",
            Self::Fvd => "fvd",
            Self::MaskIou => "mask_iou",
        }
    }

    /// The column header of the table.
    pub fn header(self) -> &'static str {
        match self {
            Self::Psnr => "PSNR",
            Self::Ssim => "SSIM",
            Self::Lpips => "LPIPS",
            Self::Fvd => "FVD",
            Self::MaskIou => "Mask-IoU",
        }
    }

    /// The names of [`Self::ALL`].
    pub fn names() -> Vec<&'static str> {
        Self::ALL.iter().map(|m| m.name()).collect()
    }
}

impl std::fmt::Display for VideoMetric {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for VideoMetric {
    type Err = ScoreError;

    /// A metric by [`VideoMetric::name`], ignoring case and surrounding spaces.
    fn from_str(s: &str) -> Result<Self> {
        let name = s.trim().to_ascii_lowercase();
        Self::ALL
            .into_iter()
            .find(|m| m.name() == name)
            .ok_or(ScoreError::UnknownMetric { name })
    }
}

/// The robot-mask folders of Mask-IoU: one folder of PNG masks per video
/// (non-zero = robot), named like the videos.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MaskFolders {
    /// Masks of the predicted videos.
    pub pred: PathBuf,
    /// Masks of the ground-truth videos.
    pub gt: PathBuf,
}

/// What [`score_videos`] scores, and with which networks.
#[derive(Debug, Clone, PartialEq)]
pub struct ScoreOptions {
    /// Predicted videos (called `--pred` in errors).
    pub pred: PathBuf,
    /// Ground-truth videos, matched to `pred` by name (called `--gt` in errors).
    pub gt: PathBuf,
    /// Robot masks of both sides; without them Mask-IoU is unavailable.
    pub masks: Option<MaskFolders>,
    /// The metrics to compute (any order; reported in the paper's order).
    pub metrics: Vec<VideoMetric>,
    /// LPIPS weights (safetensors); without them LPIPS is unavailable.
    pub lpips_weights: Option<PathBuf>,
    /// I3D weights (safetensors); without them FVD is unavailable.
    pub i3d_weights: Option<PathBuf>,
    /// Device of the LPIPS and I3D networks.
    pub device: ComputeDevice,
}

impl ScoreOptions {
    /// Every metric between `pred` and `gt`, no masks or weights, networks
    /// on [`ComputeDevice::auto`].
    pub fn new(pred: impl Into<PathBuf>, gt: impl Into<PathBuf>) -> Self {
        Self {
            pred: pred.into(),
            gt: gt.into(),
            masks: None,
            metrics: VideoMetric::ALL.to_vec(),
            lpips_weights: None,
            i3d_weights: None,
            device: ComputeDevice::auto(),
        }
    }

    /// Whether `metric` was asked for.
    pub fn wants(&self, metric: VideoMetric) -> bool {
        self.metrics.contains(&metric)
    }
}

/// The result of [`score_videos`].
#[derive(Debug, Clone, PartialEq)]
pub struct VideoScoreReport {
    /// Videos scored.
    pub num_videos: usize,
    /// The metrics asked for, in the paper's column order, with their mean
    /// over videos (FVD: the distance of the two sets); `None` when
    /// unavailable.
    pub values: Vec<(VideoMetric, Option<f64>)>,
    /// Why a metric asked for is unavailable, by [`VideoMetric::name`].
    pub unavailable: BTreeMap<&'static str, String>,
}

impl VideoScoreReport {
    /// The value of `metric` (`None`: not asked for, or unavailable).
    pub fn value(&self, metric: VideoMetric) -> Option<f64> {
        self.values
            .iter()
            .find(|(m, _)| *m == metric)
            .and_then(|(_, v)| *v)
    }

    /// The markdown table (a column per metric asked for; PSNR with 2
    /// decimals, the others 4, `n/a` when unavailable), then a line per
    /// unavailable metric with the reason.
    pub fn markdown(&self) -> String {
        let cols: Vec<&str> = self.values.iter().map(|(m, _)| m.header()).collect();
        let mut text = format!("| videos | {} |\n", cols.join(" | "));
        text.push_str(&format!("|---|{}\n", "---|".repeat(cols.len())));
        let cells: Vec<String> = self
            .values
            .iter()
            .map(|(m, v)| match v {
                Some(v) if *m == VideoMetric::Psnr => format!("{v:.2}"),
                Some(v) => format!("{v:.4}"),
                None => "n/a".into(),
            })
            .collect();
        text.push_str(&format!(
            "| {} | {} |\n",
            self.num_videos,
            cells.join(" | ")
        ));
        for (m, why) in &self.unavailable {
            text.push_str(&format!("\n{m}: unavailable: {why}"));
        }
        if !self.unavailable.is_empty() {
            text.push('\n');
        }
        text
    }

    /// `{"psnr": .., ... (the metrics asked for; null when unavailable),
    /// "num_videos": N, "unavailable": {"metric": "why"}}`.
    pub fn to_json(&self) -> serde_json::Value {
        let mut obj = serde_json::Map::new();
        for (m, v) in &self.values {
            obj.insert(m.name().into(), serde_json::json!(v));
        }
        obj.insert("num_videos".into(), serde_json::json!(self.num_videos));
        obj.insert("unavailable".into(), serde_json::json!(self.unavailable));
        serde_json::Value::Object(obj)
    }
}

/// Why each metric asked for cannot be computed from `opts` and `videos`
/// videos per side.
fn unavailable(opts: &ScoreOptions, videos: usize) -> BTreeMap<&'static str, String> {
    let mut out = BTreeMap::new();
    if opts.wants(VideoMetric::MaskIou) && opts.masks.is_none() {
        out.insert(
            "mask_iou",
            "needs robot masks of both videos: --masks-pred DIR --masks-gt DIR".into(),
        );
    }
    if opts.wants(VideoMetric::Lpips) && opts.lpips_weights.is_none() {
        out.insert(
            "lpips",
            "needs AlexNet + LPIPS v0.1 weights: --lpips-weights FILE".into(),
        );
    }
    if opts.wants(VideoMetric::Fvd) && opts.i3d_weights.is_none() {
        out.insert("fvd", "needs I3D weights: --i3d-weights FILE".into());
    } else if opts.wants(VideoMetric::Fvd) && videos < 2 {
        out.insert(
            "fvd",
            format!("needs at least 2 videos per side to fit the feature Gaussians, got {videos}"),
        );
    }
    out
}

/// Scores the videos of `opts.pred` against those of `opts.gt` (same
/// names) with the metrics `opts` asks for; `progress` sees each pass as a
/// stage: "evaluating" (PSNR, SSIM and Mask-IoU, a step per video, ticked
/// from several threads), "LPIPS" (a step per video) and "FVD" (a step per
/// video and side).
pub fn score_videos(opts: &ScoreOptions, progress: &dyn Progress) -> Result<VideoScoreReport> {
    let names = video_names(&opts.pred, "--pred")?;
    let gt_names = video_names(&opts.gt, "--gt")?;
    let missing: Vec<&String> = names.iter().filter(|n| !gt_names.contains(n)).collect();
    let extra: Vec<&String> = gt_names.iter().filter(|n| !names.contains(n)).collect();
    if !missing.is_empty() || !extra.is_empty() {
        return Err(ScoreError::Invalid(format!(
            "--pred and --gt videos must match by name: missing in --gt: {missing:?}; missing in --pred: {extra:?}"
        )));
    }
    let unavailable = unavailable(opts, names.len());
    progress.start(names.len(), "evaluating");
    let scores = names
        .par_iter()
        .map(|n| {
            let r = score_video(opts, n);
            progress.tick();
            r
        })
        .collect::<Result<Vec<_>>>()?;
    progress.finish();
    let lpips = match (&opts.lpips_weights, opts.wants(VideoMetric::Lpips)) {
        (Some(weights), true) => Some(networks::lpips_scores(
            &opts.pred,
            &opts.gt,
            weights,
            opts.device,
            &names,
            progress,
        )?),
        _ => None,
    };
    // FVD is computed exactly when it was asked for and not ruled unavailable.
    let fvd = match &opts.i3d_weights {
        Some(weights) if opts.wants(VideoMetric::Fvd) && !unavailable.contains_key("fvd") => Some(
            networks::fvd_score(&opts.pred, &opts.gt, weights, opts.device, &names, progress)?,
        ),
        _ => None,
    };
    let mean = |f: fn(&VideoScores) -> Option<f64>| -> Option<f64> {
        let v: Vec<f64> = scores.iter().filter_map(f).collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    let value = |m: VideoMetric| match m {
        VideoMetric::Psnr => mean(|s| s.psnr),
        VideoMetric::Ssim => mean(|s| s.ssim),
        VideoMetric::Lpips => lpips
            .as_ref()
            .map(|v| v.iter().sum::<f64>() / v.len() as f64),
        VideoMetric::Fvd => fvd,
        VideoMetric::MaskIou => mean(|s| s.mask_iou),
    };
    Ok(VideoScoreReport {
        num_videos: names.len(),
        values: VideoMetric::ALL
            .into_iter()
            .filter(|m| opts.wants(*m))
            .map(|m| (m, value(m)))
            .collect(),
        unavailable,
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use std::path::Path;

    fn write_png(path: &Path, value: u8) {
        std::fs::create_dir_all(path.parent().unwrap()).unwrap();
        image::RgbImage::from_pixel(16, 12, image::Rgb([value, value / 2, 200]))
            .save(path)
            .unwrap();
    }

    #[test]
    fn metric_names_parse_and_unknown_ones_list_the_choices() {
        assert_eq!(
            " Mask_IoU".parse::<VideoMetric>().unwrap(),
            VideoMetric::MaskIou
        );
        let e = "bleu".parse::<VideoMetric>().unwrap_err().to_string();
        assert_eq!(
            e,
            "unknown metric \"bleu\" (expected some of psnr, ssim, lpips, fvd, mask_iou)"
        );
    }

    #[test]
    fn identical_folders_score_perfectly_and_missing_inputs_are_unavailable() {
        let tmp = tempfile::tempdir().unwrap();
        for side in ["pred", "gt"] {
            for v in ["a", "b"] {
                for t in 0..2u8 {
                    write_png(&tmp.path().join(format!("{side}/{v}/{t}.png")), 10 * t);
                }
            }
        }
        let mut opts = ScoreOptions::new(tmp.path().join("pred"), tmp.path().join("gt"));
        opts.metrics = vec![VideoMetric::MaskIou, VideoMetric::Ssim, VideoMetric::Psnr];
        let report = score_videos(&opts, &bridgev2w_io::progress::Silent).unwrap();
        assert_eq!(report.num_videos, 2);
        assert_eq!(report.value(VideoMetric::Psnr), Some(100.0));
        assert_eq!(report.value(VideoMetric::MaskIou), None);
        assert_eq!(
            report.markdown(),
            "| videos | PSNR | SSIM | Mask-IoU |\n|---|---|---|---|\n| 2 | 100.00 | 1.0000 | n/a |\n\nmask_iou: unavailable: needs robot masks of both videos: --masks-pred DIR --masks-gt DIR\n"
        );
        let json = report.to_json();
        assert_eq!(json["psnr"], 100.0);
        assert!(json["mask_iou"].is_null() && json["unavailable"]["mask_iou"].is_string());
        std::fs::remove_dir_all(tmp.path().join("gt/b")).unwrap();
        let e = score_videos(&opts, &bridgev2w_io::progress::Silent)
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing in --gt: [\"b\"]"), "{e}");
    }
}
