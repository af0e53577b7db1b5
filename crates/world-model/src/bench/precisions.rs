//! `bench model --precision f32,bf16`: the same bench at several precisions
//! in one run, each precision's table, then every speed-up over diffusers
//! side by side (the six ratios of f32 and bf16 in one place).

use super::compare::{bench_model, speed_up, ModelBenchOptions, ModelBenchReport};
use super::BenchError;
use crate::device::Precision;
use bridgev2w_io::progress::Progress;
use std::fmt;

/// One [`ModelBenchReport`] per precision, in the order asked for.
#[derive(Debug, Clone, PartialEq)]
pub struct ModelBenchSeries {
    /// The reports, one per precision.
    pub reports: Vec<ModelBenchReport>,
}

/// Runs [`bench_model`] once per precision in `precisions` (each at most
/// once), with `options`' other settings; `options.precision` is ignored.
pub fn bench_model_precisions(
    options: &ModelBenchOptions,
    precisions: &[Precision],
    progress: &dyn Progress,
) -> Result<ModelBenchSeries, BenchError> {
    let list = || {
        precisions
            .iter()
            .map(Precision::to_string)
            .collect::<Vec<_>>()
            .join(",")
    };
    if precisions.is_empty() {
        return Err(BenchError::input(
            "--precision",
            "no precision given: expected f32, bf16 or f32,bf16",
        ));
    }
    for (i, p) in precisions.iter().enumerate() {
        if precisions[..i].contains(p) {
            return Err(BenchError::input(
                "--precision",
                format!(
                    "{}: {p} is named twice; expected each precision once",
                    list()
                ),
            ));
        }
    }
    let mut reports = Vec::with_capacity(precisions.len());
    for (i, &precision) in precisions.iter().enumerate() {
        if precisions.len() > 1 {
            progress.note(&format!(
                "bench model: {precision} ({} of {})",
                i + 1,
                precisions.len()
            ));
        }
        let options = ModelBenchOptions {
            precision,
            ..options.clone()
        };
        reports.push(bench_model(&options, progress)?);
    }
    Ok(ModelBenchSeries { reports })
}

impl fmt::Display for ModelBenchSeries {
    /// Each report's table; with several precisions and diffusers timed,
    /// then a table of the speed-ups, a row per precision.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, report) in self.reports.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{report}")?;
        }
        let Some(first) = self.reports.first() else {
            return Ok(());
        };
        if self.reports.len() < 2 || self.reports.iter().all(|r| r.diffusers.is_none()) {
            return Ok(());
        }
        writeln!(
            f,
            "\nspeed-up over diffusers (diffusers' seconds / bridgev2w's), same run:"
        )?;
        write!(f, "{:<10}", "precision")?;
        for (name, _, _) in first.rows() {
            write!(f, " {name:>26}")?;
        }
        writeln!(f)?;
        for report in &self.reports {
            write!(f, "{:<10}", report.precision.to_string())?;
            for (_, ours, theirs) in report.rows() {
                write!(f, " {:>26}", speed_up(ours, theirs))?;
            }
            writeln!(f)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::bench::diffusers::{PeerTime, PeerTimings};
    use crate::bench::ModelTimings;

    fn report(precision: Precision, diffusers: Option<PeerTimings>) -> ModelBenchReport {
        let timings = ModelTimings {
            transformer_forward_s: 2.0,
            vae_encode_s: 10.0,
            vae_decode_s: 20.0,
        };
        ModelBenchReport {
            diffusers,
            ..ModelBenchReport::example(precision, 1, timings)
        }
    }

    #[test]
    fn several_precisions_print_each_table_then_every_speed_up() {
        let f32_peer = PeerTimings::finished(&ModelTimings {
            transformer_forward_s: 3.0,
            vae_encode_s: 13.0,
            vae_decode_s: 25.0,
        });
        let bf16_peer = PeerTimings {
            transformer_forward: PeerTime::Seconds(12.0),
            vae_encode: PeerTime::Over(300.0),
            vae_decode: PeerTime::NotRun,
            stopped_after_s: Some(1500.0),
        };
        let series = ModelBenchSeries {
            reports: vec![
                report(Precision::F32, Some(f32_peer)),
                report(Precision::Bf16, Some(bf16_peer)),
            ],
        };
        let text = series.to_string();
        // Both tables, each with its own header line.
        assert_eq!(text.matches("model: 2b style").count(), 2, "{text}");
        assert!(
            text.contains(", F32 on Cpu") && text.contains(", Bf16 on Cpu"),
            "{text}"
        );
        let summary: Vec<&str> = text
            .split("speed-up over diffusers")
            .nth(1)
            .expect("a speed-up table")
            .lines()
            .collect();
        assert!(summary[1].starts_with("precision") && summary[1].contains("VAE decode"));
        let cells = |line: &str| {
            line.split("  ")
                .map(str::trim)
                .filter(|c| !c.is_empty())
                .map(str::to_owned)
                .collect::<Vec<_>>()
        };
        assert_eq!(
            cells(summary[2]),
            ["f32", "1.50x", "1.30x", "1.25x"],
            "{text}"
        );
        assert_eq!(
            cells(summary[3]),
            ["bf16", "6.00x", "> 30.0x", "-"],
            "{text}"
        );
        // One precision prints its table alone, as before.
        let one = ModelBenchSeries {
            reports: vec![series.reports[0].clone()],
        };
        assert_eq!(one.to_string(), series.reports[0].to_string());
        // Without diffusers there is nothing to compare.
        let ours_only = ModelBenchSeries {
            reports: vec![report(Precision::F32, None), report(Precision::Bf16, None)],
        };
        assert!(!ours_only.to_string().contains("speed-up over"));
    }

    #[test]
    fn a_precision_named_twice_or_none_is_refused_before_anything_runs() {
        let o = ModelBenchOptions::default();
        let progress = bridgev2w_io::progress::Silent;
        let e = bench_model_precisions(
            &o,
            &[Precision::F32, Precision::Bf16, Precision::F32],
            &progress,
        )
        .expect_err("twice");
        assert_eq!(
            e.to_string(),
            "--precision: f32,bf16,f32: f32 is named twice; expected each precision once"
        );
        let e = bench_model_precisions(&o, &[], &progress).expect_err("none");
        assert!(
            e.to_string().starts_with("--precision: no precision given"),
            "{e}"
        );
    }
}
