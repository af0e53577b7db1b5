//! The video-prediction report (`bridgev2w eval-report`): the tables in the
//! paper's layout (one block per split, a row per method, next to the
//! copy-the-first-frame baseline and the VAE's ceiling) from the JSON files
//! `eval-run --json` writes (a run's [`crate::evaluate::SplitScores`] per
//! split, with the run's step and sampling settings), with its figures
//! ([`figures`]: the training loss of each stage, PSNR per predicted frame)
//! and links to the side-by-side videos (`eval-grid`'s GIFs).

pub mod figures;

use bridgev2w_io::plot::FigureDir;
use std::path::{Path, PathBuf};

/// Errors of the report: each names the entry, split or file.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
    /// Entries that do not fit together, or a malformed entry.
    #[error("{0}")]
    Invalid(String),
    /// A file that could not be read.
    #[error("reading {}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// Why.
        source: std::io::Error,
    },
    /// A training run's `metrics.jsonl` that cannot be plotted.
    #[error("{}: {message}", path.display())]
    Metrics {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A figure that could not be drawn or written.
    #[error(transparent)]
    Plot(#[from] bridgev2w_io::plot::PlotError),
    /// A file that is not an `eval-run --json` file.
    #[error("{}: not an eval-run --json file", path.display())]
    NotRunScores {
        /// The file.
        path: PathBuf,
        /// Where and why.
        source: serde_json::Error,
    },
}

/// Result of this module.
pub type Result<T> = std::result::Result<T, ReportError>;

/// One split's scores as read back from an `eval-run --json` file (the
/// fields of [`crate::evaluate::SplitScores`]; those added later are
/// optional, so older files still parse).
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
pub struct Scores {
    /// Split name.
    pub split: String,
    /// Videos scored.
    pub videos: usize,
    /// Mean PSNR (dB) of the predictions.
    pub psnr: f64,
    /// Mean SSIM of the predictions.
    pub ssim: f64,
    /// Mean PSNR of the copy-the-first-frame baseline.
    pub baseline_psnr: f64,
    /// Mean SSIM of the baseline.
    pub baseline_ssim: f64,
    /// PSNR on the dynamic region (absent in files written before it was scored).
    #[serde(default)]
    pub dynamic_psnr: Option<f64>,
    /// Dynamic-region PSNR of the baseline.
    #[serde(default)]
    pub baseline_dynamic_psnr: Option<f64>,
    /// Dynamic-region PSNR of the ground truth through the VAE.
    #[serde(default)]
    pub autoencoder_dynamic_psnr: Option<f64>,
    /// Mask-IoU of the predictions.
    pub mask_iou: Option<f64>,
    /// Mask-IoU of the baseline.
    pub baseline_mask_iou: Option<f64>,
    /// Mask-IoU of the segmenter on the ground-truth frames (the ceiling).
    pub segmenter_mask_iou: Option<f64>,
    /// PSNR of the ground truth through the run's VAE (absent in files
    /// written before it was scored).
    #[serde(default)]
    pub autoencoder_psnr: Option<f64>,
    /// SSIM of the ground truth through the run's VAE.
    #[serde(default)]
    pub autoencoder_ssim: Option<f64>,
    /// Mask-IoU of the ground truth through the run's VAE.
    #[serde(default)]
    pub autoencoder_mask_iou: Option<f64>,
    /// PSNR of each predicted frame, averaged over the videos (empty in
    /// files written before it was scored).
    #[serde(default)]
    pub psnr_per_frame: Vec<f64>,
    /// The baseline's PSNR of each predicted frame.
    #[serde(default)]
    pub baseline_psnr_per_frame: Vec<f64>,
    /// The VAE ceiling's PSNR of each predicted frame.
    #[serde(default)]
    pub autoencoder_psnr_per_frame: Vec<f64>,
}

/// An `eval-run --json` file: a run's scores per split.
#[derive(Debug, Clone, PartialEq, serde::Deserialize)]
pub struct RunScores {
    /// The run's training step.
    pub step: usize,
    /// The run folder scored (absent in files written before it was recorded).
    #[serde(default)]
    pub run: Option<String>,
    /// Denoising steps per prediction.
    pub sampling_steps: Option<usize>,
    /// The robot segmenter of Mask-IoU (`cnn` or `color`).
    pub segmenter: Option<String>,
    /// Scores per split.
    pub splits: Vec<Scores>,
}

const SPLIT_TITLES: [(&str, &str); 4] = [
    ("test", "In-Domain"),
    ("unseen_camera", "Unseen Camera Viewpoint"),
    ("unseen_scene", "Unseen Scene"),
    ("train", "Training split"),
];

/// The splits of `run` in the paper's order (then the others).
pub(crate) fn split_order(run: &RunScores) -> Vec<&str> {
    let mut order: Vec<&str> = run.splits.iter().map(|s| s.split.as_str()).collect();
    order.sort_by_key(|s| {
        SPLIT_TITLES
            .iter()
            .position(|(k, _)| k == s)
            .unwrap_or(SPLIT_TITLES.len())
    });
    order
}

/// The paper's title of `split` (the name itself for other splits).
pub(crate) fn split_title(split: &str) -> &str {
    SPLIT_TITLES
        .iter()
        .find(|(k, _)| *k == split)
        .map_or(split, |(_, t)| t)
}

/// One row of a split's block.
struct Row {
    name: String,
    psnr: f64,
    dyn_psnr: Option<f64>,
    ssim: f64,
    iou: Option<f64>,
}

/// The markdown of the video-prediction tables (paper Table "droid" layout:
/// one block per split, a row per method).
pub fn video_tables(entries: &[(String, RunScores)]) -> Result<String> {
    let Some((_, first)) = entries.first() else {
        return Err(ReportError::Invalid("eval-report: no --entry given".into()));
    };
    let mut md = String::from(
        "| Methods | PSNR ↑ | Dynamic PSNR ↑ | SSIM ↑ | LPIPS ↓ | FVD ↓ | Mask-IoU ↑ |\n|---|---|---|---|---|---|---|\n",
    );
    for split in split_order(first) {
        let title = split_title(split);
        let base = first
            .splits
            .iter()
            .find(|s| s.split == split)
            .ok_or_else(|| ReportError::Invalid("split vanished".into()))?;
        let mut rows = vec![Row {
            name: "Copy first frame".into(),
            psnr: base.baseline_psnr,
            dyn_psnr: base.baseline_dynamic_psnr,
            ssim: base.baseline_ssim,
            iou: base.baseline_mask_iou,
        }];
        for (name, run) in entries {
            let s = run.splits.iter().find(|s| s.split == split).ok_or_else(|| {
                ReportError::Invalid(format!("entry `{name}` has no scores for split `{split}`; run eval-run with the same --splits for every entry"))
            })?;
            if s.videos != base.videos {
                return Err(ReportError::Invalid(format!(
                    "entry `{name}`, split `{split}`: {} videos, but the first entry has {}; score every method on the same clips",
                    s.videos,
                    base.videos
                )));
            }
            rows.push(Row {
                name: format!("{name} (step {})", run.step),
                psnr: s.psnr,
                dyn_psnr: s.dynamic_psnr,
                ssim: s.ssim,
                iou: s.mask_iou,
            });
        }
        let best = |f: &dyn Fn(&Row) -> Option<f64>| {
            rows.iter().filter_map(f).fold(f64::NEG_INFINITY, f64::max)
        };
        let (bp, bd, bs, bi) = (
            best(&|r| Some(r.psnr)),
            best(&|r| r.dyn_psnr),
            best(&|r| Some(r.ssim)),
            best(&|r| r.iou),
        );
        let mark = |v: f64, best: f64, text: String| {
            if v == best {
                format!("**{text}**")
            } else {
                text
            }
        };
        md += &format!(
            "| ***{title}*** ({} videos; segmenter ceiling Mask-IoU {}) | | | | | | |\n",
            base.videos,
            base.segmenter_mask_iou
                .map_or("-".into(), |v| format!("{:.1}", 100.0 * v))
        );
        for r in &rows {
            md += &format!(
                "| {} | {} | {} | {} | - | - | {} |\n",
                r.name,
                mark(r.psnr, bp, format!("{:.2}", r.psnr)),
                r.dyn_psnr
                    .map_or("-".into(), |v| mark(v, bd, format!("{v:.2}"))),
                mark(r.ssim, bs, format!("{:.3}", r.ssim)),
                r.iou
                    .map_or("-".into(), |v| mark(v, bi, format!("{:.1}", 100.0 * v))),
            );
        }
        // Not a method: the bound of every row that decodes through the VAE.
        if let (Some(p), Some(s)) = (base.autoencoder_psnr, base.autoencoder_ssim) {
            md += &format!(
                "| *Ceiling: ground truth through the VAE* | *{p:.2}* | {} | *{s:.3}* | - | - | {} |\n",
                base.autoencoder_dynamic_psnr
                    .map_or("-".into(), |v| format!("*{v:.2}*")),
                base.autoencoder_mask_iou
                    .map_or("-".into(), |v| format!("*{:.1}*", 100.0 * v)),
            );
        }
    }
    if let Some(steps) = first.sampling_steps {
        md += &format!("\nSampling: {steps} denoising steps per prediction.\n");
    }
    Ok(md)
}

/// Parses `NAME=FILE` (an `eval-run --json` file) and reads the file.
pub fn parse_entry(s: &str) -> Result<(String, RunScores)> {
    let (name, file) = s.split_once('=').ok_or_else(|| {
        ReportError::Invalid(format!(
            "--entry {s:?}: expected NAME=FILE (an eval-run --json file)"
        ))
    })?;
    let path = Path::new(file);
    let text = std::fs::read_to_string(path).map_err(|source| ReportError::Read {
        path: path.to_path_buf(),
        source,
    })?;
    let run: RunScores =
        serde_json::from_str(&text).map_err(|source| ReportError::NotRunScores {
            path: path.to_path_buf(),
            source,
        })?;
    Ok((name.trim().to_string(), run))
}

/// What [`video_report`] puts together.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub struct VideoReportOptions {
    /// `NAME=FILE` per method (rows in this order); the
    /// copy-the-first-frame baseline row comes from the first file.
    pub entries: Vec<String>,
    /// Markdown put before the tables (setup, timings).
    pub preamble: Option<PathBuf>,
    /// `NAME=DIR` per training run (a stage of the proof run) whose
    /// `metrics.jsonl` is drawn as loss curves, in this order.
    pub training_runs: Vec<String>,
    /// `eval-grid`'s folder of side-by-side GIFs (`<split>.gif` for every
    /// split of the entries), drawn with the entries' runs in their order.
    pub grids: Option<PathBuf>,
    /// The results file the section goes to: the figures are written next
    /// to it ([`FigureDir::next_to`]) and every link is relative to it.
    /// `None`: no figures (the grids are then linked from the working folder).
    pub results: Option<PathBuf>,
    /// The results file's section (`video`: the synthetic study's); another
    /// section's figures are named `<section>-*.png`.
    pub section: String,
    /// The section's heading (without `## `).
    pub title: String,
}

impl VideoReportOptions {
    /// The synthetic study's section (`video`) and heading.
    pub fn synthetic(entries: Vec<String>) -> Self {
        Self {
            entries,
            preamble: None,
            training_runs: Vec::new(),
            grids: None,
            results: None,
            section: "video".into(),
            title: "Video prediction in the synthetic world".into(),
        }
    }

    /// A figure's file name: `name`, prefixed with the section unless it is
    /// the synthetic study's.
    fn figure_name(&self, name: &str) -> String {
        if self.section == "video" {
            name.to_string()
        } else {
            format!("{}-{name}", self.section)
        }
    }
}

/// Parses `NAME=DIR` (a training run's folder).
pub fn parse_training_run(s: &str) -> Result<(String, PathBuf)> {
    match s.split_once('=') {
        Some((name, dir)) if !name.trim().is_empty() && !dir.is_empty() => {
            Ok((name.trim().to_string(), PathBuf::from(dir)))
        }
        _ => Err(ReportError::Invalid(format!(
            "--training-run {s:?}: expected NAME=DIR (a training run's folder, with metrics.jsonl)"
        ))),
    }
}

/// The figures and the side-by-side videos (markdown), each file written.
fn figures_section(opts: &VideoReportOptions, entries: &[(String, RunScores)]) -> Result<String> {
    let mut md = String::new();
    if let Some(fig) = opts.results.as_deref().map(FigureDir::next_to) {
        let runs = opts
            .training_runs
            .iter()
            .map(|r| parse_training_run(r))
            .collect::<Result<Vec<_>>>()?;
        let mut images = Vec::new();
        if !runs.is_empty() {
            let loss = opts.figure_name("loss-curves.png");
            figures::loss_curves(&runs, &fig.path(&loss))?;
            let names: Vec<&str> = runs.iter().map(|(n, _)| n.as_str()).collect();
            images.push(format!(
                "Training loss of each stage ({}; log scale, a moving average over the faint per-step values):\n\n{}",
                names.join(", "),
                fig.image(&loss, "Training loss per stage")
            ));
        }
        if let Some(psnr) = figures::psnr_figure(entries) {
            let name = opts.figure_name("psnr-per-frame.png");
            bridgev2w_io::plot::write_png(&fig.path(&name), &psnr)?;
            images.push(format!(
                "PSNR of each predicted frame, averaged over the videos, per split (dashed: copying the first frame, and the VAE's ceiling):\n\n{}",
                fig.image(&name, "PSNR per predicted frame")
            ));
        }
        if !images.is_empty() {
            md += &format!("\n### Figures\n\n{}\n", images.join("\n\n"));
        }
    }
    if let (Some(dir), Some((_, first))) = (&opts.grids, entries.first()) {
        // eval-grid draws each run once: entries scoring the same run (e.g.
        // with other sampling options) share the column of the first of them.
        let mut runs_seen = std::collections::HashSet::new();
        let names: Vec<&str> = entries
            .iter()
            .filter(|(_, s)| s.run.as_ref().is_none_or(|r| runs_seen.insert(r.clone())))
            .map(|(n, _)| n.as_str())
            .collect();
        md += &format!(
            "\n### Side-by-side videos\n\nThe first clips of each split, a row each: first frame | masks | {} | ground truth (`bridgev2w eval-grid`).\n\n",
            names.join(" | ")
        );
        let results = opts
            .results
            .clone()
            .unwrap_or_else(|| PathBuf::from("results.md"));
        for split in split_order(first) {
            let gif = dir.join(format!("{split}.gif"));
            if !gif.is_file() {
                return Err(ReportError::Invalid(format!(
                    "--grids: {} does not exist; draw the grids with `bridgev2w eval-grid --out {}` for the entries' splits",
                    gif.display(),
                    dir.display()
                )));
            }
            md += &format!(
                "**{}**\n\n![{split}]({})\n\n",
                split_title(split),
                bridgev2w_io::plot::link_from(&results, &gif)
            );
        }
    }
    Ok(md)
}

/// The markdown of the results file's `video` section: the heading, the
/// preamble, [`video_tables`] and the notes on how each column was scored.
pub fn video_report(opts: &VideoReportOptions) -> Result<String> {
    let entries = opts
        .entries
        .iter()
        .map(|e| parse_entry(e))
        .collect::<Result<Vec<_>>>()?;
    let mut md = format!("## {}\n\n", opts.title);
    if let Some(p) = &opts.preamble {
        md += &std::fs::read_to_string(p).map_err(|source| ReportError::Read {
            path: p.clone(),
            source,
        })?;
        md += "\n\n";
    }
    md += &video_tables(&entries)?;
    let segmenter = match entries[0].1.segmenter.as_deref() {
        Some("color") => "a colour classifier",
        _ => "a small dilated CNN",
    };
    md += &format!("\nPSNR and SSIM per frame on [0, 1] RGB, averaged over the predicted frames 1..T, then videos (frame 0 is every method's input: copying it would score 100 dB there, and until 2026-11-25 that frame was counted, which put the copy baseline about 8 dB higher). Dynamic PSNR: PSNR pooled over the pixels the motion changes (in frames 1..T, a channel differs from the true first frame by more than 8/255; dilated by 2 px), where copying the first frame knows nothing; averaged over videos. Mask-IoU (x100): the robot segmented in each predicted frame by {segmenter} trained on the training split's frames and ground-truth masks (the paper uses Grounded SAM), against the ground-truth masks; the segmenter's ceiling is its score on the ground-truth frames.");
    md += " LPIPS and FVD need the pretrained AlexNet and I3D weights, which cannot be downloaded here (`bridgev2w eval` computes them from user-supplied weights).\n";
    md += &figures_section(opts, &entries)?;
    Ok(md)
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn run(psnr: f64, iou: f64, videos: usize) -> RunScores {
        RunScores {
            run: None,
            step: 10,
            sampling_steps: Some(20),
            segmenter: Some("cnn".into()),
            splits: ["unseen_camera", "test"]
                .iter()
                .map(|s| Scores {
                    split: (*s).into(),
                    videos,
                    psnr,
                    ssim: 0.5,
                    baseline_psnr: 20.0,
                    baseline_ssim: 0.6,
                    dynamic_psnr: Some(psnr - 4.0),
                    baseline_dynamic_psnr: Some(15.0),
                    autoencoder_dynamic_psnr: Some(psnr),
                    mask_iou: Some(iou),
                    baseline_mask_iou: Some(0.3),
                    segmenter_mask_iou: Some(0.9),
                    autoencoder_psnr: Some(psnr + 5.0),
                    autoencoder_ssim: Some(0.7),
                    autoencoder_mask_iou: None,
                    psnr_per_frame: vec![psnr + 2.0, psnr, psnr - 2.0],
                    baseline_psnr_per_frame: vec![22.0, 20.0, 18.0],
                    autoencoder_psnr_per_frame: vec![psnr + 5.0; 3],
                })
                .collect(),
        }
    }

    #[test]
    fn tables_follow_the_paper_layout_and_mark_the_best() {
        let md = video_tables(&[
            ("A".into(), run(25.0, 0.5, 3)),
            ("B".into(), run(22.0, 0.6, 3)),
        ])
        .unwrap();
        // Splits in the paper's order, whatever the files' order.
        assert!(md.find("In-Domain").unwrap() < md.find("Unseen Camera").unwrap());
        assert!(
            md.contains("| Copy first frame | 20.00 | 15.00 | **0.600** | - | - | 30.0 |"),
            "{md}"
        );
        assert!(
            md.contains("| A (step 10) | **25.00** | **21.00** | 0.500 | - | - | 50.0 |"),
            "{md}"
        );
        assert!(
            md.contains("| B (step 10) | 22.00 | 18.00 | 0.500 | - | - | **60.0** |"),
            "{md}"
        );
        assert!(md.contains("segmenter ceiling Mask-IoU 90.0"), "{md}");
        // The VAE ceiling (first entry's) is a row of its own, never marked best.
        assert!(
            md.contains(
                "| *Ceiling: ground truth through the VAE* | *30.00* | *25.00* | *0.700* | - | - | - |"
            ),
            "{md}"
        );
        let e = video_tables(&[
            ("A".into(), run(25.0, 0.5, 3)),
            ("B".into(), run(22.0, 0.6, 2)),
        ])
        .unwrap_err()
        .to_string();
        assert!(e.contains("2 videos, but the first entry has 3"), "{e}");
    }

    #[test]
    fn files_without_the_vae_ceiling_still_parse_and_omit_its_row() {
        let tmp = tempfile::tempdir().unwrap();
        let f = tmp.path().join("old.json");
        std::fs::write(
            &f,
            r#"{"step": 5, "splits": [{"split": "test", "videos": 2, "psnr": 21.0, "ssim": 0.5,
                "baseline_psnr": 30.0, "baseline_ssim": 0.9, "mask_iou": null,
                "baseline_mask_iou": null, "segmenter_mask_iou": null}]}"#,
        )
        .unwrap();
        let entry = parse_entry(&format!("Old={}", f.display())).unwrap();
        let md = video_tables(&[entry]).unwrap();
        assert!(
            md.contains("| Old (step 5) | 21.00 | - | 0.500 | - | - | - |"),
            "{md}"
        );
        assert!(!md.contains("Ceiling"), "{md}");
    }

    #[test]
    fn the_section_draws_and_links_its_figures_and_grids() {
        let tmp = tempfile::tempdir().unwrap();
        let d = tmp.path();
        let scores = |name: &str, psnr: f64, run_dir: &str| {
            let r = run(psnr, 0.5, 3);
            let splits: Vec<serde_json::Value> = r
                .splits
                .iter()
                .map(|s| {
                    serde_json::json!({
                        "split": s.split, "videos": s.videos, "psnr": s.psnr, "ssim": s.ssim,
                        "baseline_psnr": s.baseline_psnr, "baseline_ssim": s.baseline_ssim,
                        "mask_iou": null, "baseline_mask_iou": null, "segmenter_mask_iou": null,
                        "autoencoder_psnr": s.autoencoder_psnr, "autoencoder_ssim": s.autoencoder_ssim,
                        "psnr_per_frame": s.psnr_per_frame,
                        "baseline_psnr_per_frame": s.baseline_psnr_per_frame,
                        "autoencoder_psnr_per_frame": s.autoencoder_psnr_per_frame,
                    })
                })
                .collect();
            let f = d.join(format!("{name}.json"));
            std::fs::write(
                &f,
                serde_json::json!({"step": 10, "run": run_dir, "splits": splits}).to_string(),
            )
            .unwrap();
            format!("{name}={}", f.display())
        };
        let stage = |name: &str| {
            let dir = d.join("runs").join(name);
            std::fs::create_dir_all(&dir).unwrap();
            let lines: String = (0..20)
                .map(|i| {
                    format!(
                        "{{\"step\":{i},\"loss\":{},\"diffusion\":{},\"dynamics\":0.1}}\n",
                        1.0 / (i + 1) as f64 + 0.1,
                        1.0 / (i + 1) as f64
                    )
                })
                .collect();
            std::fs::write(dir.join("metrics.jsonl"), lines).unwrap();
            format!("{name}={}", dir.display())
        };
        let grids = d.join("grids");
        std::fs::create_dir_all(&grids).unwrap();
        for split in ["test", "unseen_camera"] {
            std::fs::write(grids.join(format!("{split}.gif")), b"GIF89a").unwrap();
        }
        let results = d.join("docs/results.md");
        let mut opts = VideoReportOptions {
            // A2 scores A's run another way: one column in the grids.
            entries: vec![
                scores("A", 25.0, "runs/a"),
                scores("A2", 24.0, "runs/a"),
                scores("B", 22.0, "runs/b"),
            ],
            preamble: None,
            training_runs: vec![stage("prior"), stage("bridgev2w")],
            grids: Some(grids.clone()),
            results: Some(results.clone()),
            ..VideoReportOptions::synthetic(Vec::new())
        };
        let md = video_report(&opts).unwrap();
        assert!(md.starts_with("## Video prediction in the synthetic world\n"));
        let figs = d.join("docs/results/figures");
        // Two stages: one row of two 420x300 panels; two splits likewise.
        for (name, size) in [
            ("loss-curves.png", (840, 300)),
            ("psnr-per-frame.png", (840, 300)),
        ] {
            let (got, share) = bridgev2w_io::plot::ink_share(&figs.join(name)).unwrap();
            assert_eq!(got, size, "{name}");
            assert!(share > 0.01, "{name}: {share}");
            assert!(md.contains(&format!("(results/figures/{name})")), "{md}");
        }
        assert!(
            md.contains("first frame | masks | A | B | ground truth"),
            "{md}"
        );
        assert!(md.contains("![test](../grids/test.gif)"), "{md}");
        assert!(md.find("In-Domain**").unwrap() < md.find("Unseen Camera Viewpoint**").unwrap());
        // Another section: its own heading, its figures named after it
        // (the synthetic study's are not overwritten).
        let other = VideoReportOptions {
            section: "real-video".into(),
            title: "Video prediction on real DROID video".into(),
            ..opts.clone()
        };
        let md = video_report(&other).unwrap();
        assert!(md.starts_with("## Video prediction on real DROID video\n"));
        assert!(figs.join("real-video-loss-curves.png").is_file());
        assert!(
            md.contains("(results/figures/real-video-psnr-per-frame.png)"),
            "{md}"
        );
        // Bad input names the file.
        std::fs::remove_file(grids.join("test.gif")).unwrap();
        let e = video_report(&opts).unwrap_err().to_string();
        assert!(e.contains("test.gif") && e.contains("eval-grid"), "{e}");
        opts.grids = None;
        opts.training_runs
            .push(format!("vae={}", d.join("runs/vae").display()));
        let e = video_report(&opts).unwrap_err().to_string();
        assert!(
            e.contains("vae/metrics.jsonl") && e.contains("does not exist"),
            "{e}"
        );
        opts.training_runs = vec!["vae".into()];
        let e = video_report(&opts).unwrap_err().to_string();
        assert!(e.contains("expected NAME=DIR"), "{e}");
    }
}
