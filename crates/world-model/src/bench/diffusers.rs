//! The diffusers side of `bench model`: `scripts/bench/diffusers_model.py`
//! (in the project venv, with torch and diffusers) times the same operations
//! as [`super::time_model`] on the same configs, shapes, threads and precision.
//! The script reports each operation as it finishes, so a run stopped at a
//! time limit keeps what finished and bounds what did not ([`PeerTime`]).

use super::{torch_threads, BenchError, ModelBenchShape, ModelTimings};
use crate::device::{ComputeDevice, Precision};
use crate::transformer::TransformerConfig;
use crate::vae::VaeConfig;
use bridgev2w_io::json::write_json_atomic;
use bridgev2w_io::peer::{self, PeerError};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

/// The peer script, under `scripts/bench/`.
const SCRIPT: &str = "diffusers_model.py";

/// Where diffusers runs from: a Python with torch and diffusers, and the
/// repository root that holds the peer script.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DiffusersPeer {
    /// The interpreter.
    pub python: PathBuf,
    /// The repository root.
    pub repo: PathBuf,
}

impl DiffusersPeer {
    /// The repository root (`repo`, else found above the current directory)
    /// and `python`, else the project venv's.
    pub fn find(python: Option<&Path>, repo: Option<&Path>) -> Result<Self, PeerError> {
        let repo = peer::find_repo(repo)?;
        let python = match python {
            Some(p) => p.to_path_buf(),
            None => peer::project_python(&repo, " (or pass --python / --no-diffusers)")?,
        };
        Ok(Self { python, repo })
    }

    /// Times diffusers' transformer forward and VAE encode/decode (best of
    /// `repeat` after a warm-up, like [`super::time_model`]); with a
    /// `limit`, a run still going then is stopped and reports what finished.
    #[allow(clippy::too_many_arguments)]
    pub fn time_model(
        &self,
        tf: &TransformerConfig,
        vae: &VaeConfig,
        shape: &ModelBenchShape,
        device: ComputeDevice,
        precision: Precision,
        repeat: usize,
        limit: Option<Duration>,
    ) -> Result<PeerTimings, BenchError> {
        let tmp = peer::scratch_dir()?;
        let (tf_path, vae_path) = (
            tmp.path().join("transformer.json"),
            tmp.path().join("vae.json"),
        );
        write_json_atomic(&tf_path, tf)?;
        write_json_atomic(&vae_path, vae)?;
        let run = peer::run_peer_json_lines(
            Command::new(&self.python)
                .arg(self.repo.join("scripts/bench").join(SCRIPT))
                .arg("--transformer-config")
                .arg(&tf_path)
                .arg("--vae-config")
                .arg(&vae_path)
                .args(["--frames", &shape.frames.to_string()])
                .args(["--height", &shape.height.to_string()])
                .args(["--width", &shape.width.to_string()])
                .args(["--text-len", &shape.text_len.to_string()])
                .args(["--repeat", &repeat.to_string()])
                .args(["--batch", &shape.batch.to_string()])
                .args(["--threads", &torch_threads().to_string()])
                .args([
                    "--dtype",
                    &precision.to_string(),
                    "--device",
                    &device.to_string(),
                ])
                .args(shape.vae_tiling.then_some("--vae-tiling")),
            SCRIPT,
            limit,
        )?;
        PeerTimings::from_lines(&run, repeat)
    }
}

/// One of diffusers' timings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum PeerTime {
    /// Seconds, best of the timed runs.
    Seconds(f64),
    /// Stopped at the time limit while running: one run takes longer than
    /// this many seconds (the time it had run, over its warm-up and timed
    /// runs, shared among them).
    Over(f64),
    /// Not started before the time limit.
    NotRun,
}

impl PeerTime {
    /// The seconds, when the operation finished.
    pub fn seconds(self) -> Option<f64> {
        match self {
            Self::Seconds(s) => Some(s),
            _ => None,
        }
    }
}

/// diffusers' timings of `bench model`'s operations.
#[derive(Debug, Clone, PartialEq)]
pub struct PeerTimings {
    /// One transformer forward at the shape's batch.
    pub transformer_forward: PeerTime,
    /// VAE encode of the clip.
    pub vae_encode: PeerTime,
    /// VAE decode of the clip's latents.
    pub vae_decode: PeerTime,
    /// `Some(seconds)` when the run was stopped at its time limit.
    pub stopped_after_s: Option<f64>,
}

impl PeerTimings {
    /// The operations, in the order the script runs them, by their keys.
    const OPS: [&'static str; 3] = ["transformer_forward", "vae_encode", "vae_decode"];

    /// Every operation finished, as this crate's timings are.
    pub fn finished(t: &ModelTimings) -> Self {
        Self {
            transformer_forward: PeerTime::Seconds(t.transformer_forward_s),
            vae_encode: PeerTime::Seconds(t.vae_encode_s),
            vae_decode: PeerTime::Seconds(t.vae_decode_s),
            stopped_after_s: None,
        }
    }

    /// The script's progress lines (`{"starting": OP}`, then the result so
    /// far after each operation): a finished run needs every operation; a
    /// stopped one bounds the operation it was in by the time since it
    /// started, over the `1 + repeat` runs it makes.
    fn from_lines(run: &peer::PeerLines, repeat: usize) -> Result<Self, BenchError> {
        let result = run.last_where(|v| v.get("starting").is_none());
        let Some(limit) = run.stopped else {
            let r = result.ok_or_else(|| PeerError::NoJson {
                script: SCRIPT.into(),
            })?;
            let [transformer_forward, vae_encode, vae_decode] =
                Self::OPS.map(|op| r.number(&format!("{op}_s")).map(PeerTime::Seconds));
            return Ok(Self {
                transformer_forward: transformer_forward?,
                vae_encode: vae_encode?,
                vae_decode: vae_decode?,
                stopped_after_s: None,
            });
        };
        let mut times = Self::OPS.map(|op| {
            result
                .as_ref()
                .and_then(|r| r.value().get(format!("{op}_s"))?.as_f64())
                .map_or(PeerTime::NotRun, PeerTime::Seconds)
        });
        // The operation it was in: the last one started.
        let started = run
            .lines
            .iter()
            .rev()
            .find_map(|(at, v)| Some((*at, v.get("starting")?.as_str()?)));
        if let Some((at, op)) = started {
            if let Some(i) = Self::OPS.iter().position(|o| *o == op) {
                if times[i] == PeerTime::NotRun {
                    let ran = limit.saturating_sub(at).as_secs_f64();
                    times[i] = PeerTime::Over(ran / (1 + repeat.max(1)) as f64);
                }
            }
        }
        let [transformer_forward, vae_encode, vae_decode] = times;
        Ok(Self {
            transformer_forward,
            vae_encode,
            vae_decode,
            stopped_after_s: Some(limit.as_secs_f64()),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    fn lines(stopped: Option<u64>, lines: &[(u64, &str)]) -> peer::PeerLines {
        // A peer that prints `lines` (at the given seconds) and is stopped.
        let script = lines
            .iter()
            .map(|(_, l)| format!("echo '{l}'"))
            .collect::<Vec<_>>()
            .join("; ");
        let mut run =
            peer::run_peer_json_lines(Command::new("sh").args(["-c", &script]), SCRIPT, None)
                .expect("sh");
        for ((at, _), (t, _)) in run.lines.iter_mut().zip(lines) {
            *at = Duration::from_secs(*t);
        }
        run.stopped = stopped.map(Duration::from_secs);
        run
    }

    #[test]
    fn a_stopped_peer_keeps_what_finished_and_bounds_what_it_was_in() {
        let progress = [
            (1, r#"{"starting": "transformer_forward"}"#),
            (10, r#"{"threads": 2, "transformer_forward_s": 3.5}"#),
            (10, r#"{"starting": "vae_encode"}"#),
        ];
        // Stopped at 100 s, 90 s into the encode's warm-up and 2 runs.
        let t = PeerTimings::from_lines(&lines(Some(100), &progress), 2).expect("timings");
        assert_eq!(t.transformer_forward, PeerTime::Seconds(3.5));
        assert_eq!(t.vae_encode, PeerTime::Over(30.0));
        assert_eq!(t.vae_decode, PeerTime::NotRun);
        assert_eq!(t.stopped_after_s, Some(100.0));
        // Stopped before anything finished.
        let t = PeerTimings::from_lines(&lines(Some(50), &progress[..1]), 1).expect("timings");
        assert_eq!(t.transformer_forward, PeerTime::Over(24.5));
        assert_eq!(t.vae_encode.seconds(), None);
        // A finished run needs all three; the last result counts.
        let mut done = progress.to_vec();
        done.push((
            20,
            r#"{"transformer_forward_s": 3.5, "vae_encode_s": 2.0, "vae_decode_s": 4.0}"#,
        ));
        let t = PeerTimings::from_lines(&lines(None, &done), 1).expect("timings");
        assert_eq!(
            [t.transformer_forward, t.vae_encode, t.vae_decode].map(PeerTime::seconds),
            [Some(3.5), Some(2.0), Some(4.0)]
        );
        let e = PeerTimings::from_lines(&lines(None, &progress), 1).expect_err("unfinished");
        assert_eq!(
            e.to_string(),
            "diffusers_model.py result has no number `vae_encode_s`"
        );
    }
}
