//! The figures of the video-prediction report: the training loss of each
//! stage of a run ([`loss_curves`], from each stage's `metrics.jsonl`) and
//! PSNR per predicted frame for each method and split ([`psnr_per_frame`],
//! from the `eval-run --json` files).

use super::{split_order, split_title, ReportError, Result, RunScores};
use bridgev2w_io::plot::lines::{Line, LineFigure, Panel};
use std::path::{Path, PathBuf};

/// The loss terms plotted next to the total when they are not all zero
/// (`recon`, `kl`: the VAE stages; the rest: the diffusion stages).
const TERMS: [&str; 5] = ["diffusion", "dynamics", "flow", "recon", "kl"];

/// One stage's losses read back from its `metrics.jsonl`.
#[derive(Debug, Clone, PartialEq)]
pub struct StageLosses {
    /// The stage's name.
    pub name: String,
    /// Training steps.
    pub steps: Vec<f64>,
    /// `loss` at each step.
    pub loss: Vec<f64>,
    /// The terms that are not all zero, each at every step.
    pub terms: Vec<(String, Vec<f64>)>,
}

/// Reads `dir/metrics.jsonl` (a training run's folder): an error naming the
/// file when the folder or the file is missing, a line is not a step's
/// metrics, or there is no step.
pub fn read_losses(name: &str, dir: &Path) -> Result<StageLosses> {
    let path = dir.join("metrics.jsonl");
    let bad = |message: String| ReportError::Metrics {
        path: path.clone(),
        message,
    };
    if !dir.is_dir() {
        return Err(bad(format!(
            "training run `{name}`: the folder {} does not exist",
            dir.display()
        )));
    }
    let text = std::fs::read_to_string(&path).map_err(|source| ReportError::Read {
        path: path.clone(),
        source,
    })?;
    let mut out = StageLosses {
        name: name.to_string(),
        steps: Vec::new(),
        loss: Vec::new(),
        terms: TERMS.iter().map(|t| (t.to_string(), Vec::new())).collect(),
    };
    for (i, line) in text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty())
    {
        let v: serde_json::Value =
            serde_json::from_str(line).map_err(|e| bad(format!("line {}: {e}", i + 1)))?;
        let number = |key: &str| v.get(key).and_then(serde_json::Value::as_f64);
        let (Some(step), Some(loss)) = (number("step"), number("loss")) else {
            return Err(bad(format!(
                "line {}: expected a step's metrics with `step` and `loss`",
                i + 1
            )));
        };
        out.steps.push(step);
        out.loss.push(loss);
        for (term, values) in &mut out.terms {
            values.push(number(term).unwrap_or(0.0));
        }
    }
    if out.steps.is_empty() {
        return Err(bad(format!("training run `{name}`: no steps recorded")));
    }
    // Terms that say something: not all zero, and not the total itself.
    let loss = out.loss.clone();
    out.terms
        .retain(|(_, v)| v.iter().any(|&x| x != 0.0) && *v != loss);
    Ok(out)
}

/// Trailing moving average over `window` values.
fn smooth(v: &[f64], window: usize) -> Vec<f64> {
    let w = window.max(1);
    let mut sum = 0.0;
    v.iter()
        .enumerate()
        .map(|(i, &x)| {
            sum += x;
            if i >= w {
                sum -= v[i - w];
            }
            sum / (i + 1).min(w) as f64
        })
        .collect()
}

/// A panel per stage: the loss at every step (faint), its moving average
/// and the moving averages of its terms, on a log axis.
pub fn loss_figure(stages: &[StageLosses]) -> LineFigure {
    let panels = stages
        .iter()
        .map(|s| {
            let window = (s.steps.len() / 50).max(1);
            let pts = |v: &[f64]| -> Vec<(f64, f64)> {
                s.steps.iter().copied().zip(smooth(v, window)).collect()
            };
            let mut lines = vec![
                Line {
                    label: None,
                    faint: true,
                    ..Line::new(
                        "",
                        s.steps
                            .iter()
                            .copied()
                            .zip(s.loss.iter().copied())
                            .collect(),
                        0,
                    )
                },
                Line::new(
                    if window > 1 {
                        format!("loss (mean of {window})")
                    } else {
                        "loss".into()
                    },
                    pts(&s.loss),
                    0,
                ),
            ];
            for (k, (term, v)) in s.terms.iter().enumerate() {
                lines.push(Line::new(term.clone(), pts(v), k + 1));
            }
            Panel {
                title: s.name.clone(),
                x_desc: "step".into(),
                y_desc: "loss".into(),
                log_y: true,
                lines,
            }
        })
        .collect();
    LineFigure {
        panels,
        columns: 3,
        panel_size: (420, 300),
    }
}

/// Reads every `NAME=DIR` training run and draws [`loss_figure`] to `path`.
pub fn loss_curves(runs: &[(String, PathBuf)], path: &Path) -> Result<()> {
    let stages = runs
        .iter()
        .map(|(name, dir)| read_losses(name, dir))
        .collect::<Result<Vec<_>>>()?;
    bridgev2w_io::plot::write_png(path, &loss_figure(&stages))?;
    Ok(())
}

/// A panel per split: PSNR of each predicted frame for each entry, the
/// copy-the-first-frame baseline and the VAE ceiling (the first entry's);
/// `None` when no entry has per-frame scores (files written before them).
pub fn psnr_figure(entries: &[(String, RunScores)]) -> Option<LineFigure> {
    let (_, first) = entries.first()?;
    let frames = |v: &[f64]| -> Vec<(f64, f64)> {
        v.iter()
            .enumerate()
            .map(|(t, &p)| ((t + 1) as f64, p))
            .collect()
    };
    let panels: Vec<Panel> = split_order(first)
        .into_iter()
        .filter_map(|split| {
            let base = first.splits.iter().find(|s| s.split == split)?;
            let mut lines: Vec<Line> = entries
                .iter()
                .enumerate()
                .filter_map(|(k, (name, run))| {
                    let s = run.splits.iter().find(|s| s.split == split)?;
                    (!s.psnr_per_frame.is_empty()).then(|| Line {
                        markers: true,
                        ..Line::new(name.clone(), frames(&s.psnr_per_frame), k)
                    })
                })
                .collect();
            if lines.is_empty() {
                return None;
            }
            for (label, v, color) in [
                ("copy first frame", &base.baseline_psnr_per_frame, 7),
                ("ceiling: VAE", &base.autoencoder_psnr_per_frame, 9),
            ] {
                if !v.is_empty() {
                    lines.push(Line {
                        dashed: true,
                        ..Line::new(label, frames(v), color)
                    });
                }
            }
            Some(Panel {
                title: split_title(split).to_string(),
                x_desc: "predicted frame".into(),
                y_desc: "PSNR (dB)".into(),
                log_y: false,
                lines,
            })
        })
        .collect();
    (!panels.is_empty()).then(|| LineFigure {
        columns: panels.len().min(3),
        panels,
        panel_size: (420, 300),
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn losses_keep_the_informative_terms_and_errors_name_the_file() {
        let tmp = tempfile::tempdir().unwrap();
        let dir = tmp.path().join("vae");
        std::fs::create_dir(&dir).unwrap();
        std::fs::write(
            dir.join("metrics.jsonl"),
            "{\"step\":0,\"loss\":2.0,\"recon\":1.5,\"kl\":0.5,\"diffusion\":0.0}\n{\"step\":1,\"loss\":1.0,\"recon\":0.8,\"kl\":0.2,\"diffusion\":0.0}\n",
        )
        .unwrap();
        let s = read_losses("vae", &dir).unwrap();
        assert_eq!(s.steps, [0.0, 1.0]);
        let names: Vec<&str> = s.terms.iter().map(|(t, _)| t.as_str()).collect();
        assert_eq!(names, ["recon", "kl"]);
        std::fs::write(dir.join("metrics.jsonl"), "").unwrap();
        let e = read_losses("vae", &dir).unwrap_err().to_string();
        assert!(e.contains("metrics.jsonl") && e.contains("no steps"), "{e}");
        std::fs::write(dir.join("metrics.jsonl"), "{\"step\":0}\n").unwrap();
        let e = read_losses("vae", &dir).unwrap_err().to_string();
        assert!(e.contains("metrics.jsonl") && e.contains("line 1"), "{e}");
        let e = read_losses("prior", &tmp.path().join("prior"))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("prior/metrics.jsonl") && e.contains("does not exist"),
            "{e}"
        );
        assert_eq!(smooth(&[1.0, 3.0, 5.0], 2), [1.0, 2.0, 4.0]);
    }
}
