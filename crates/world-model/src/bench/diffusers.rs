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
use bridgev2w_io::peer::{self, PeerError, PeerLimit};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Duration;

/// The peer script, under `scripts/bench/`.
const SCRIPT: &str = "diffusers_model.py";

/// The key of the script's progress line `{"starting": OP}`.
const STARTING: &str = "starting";

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
    /// `repeat` after a warm-up, like [`super::time_model`]). With a
    /// `limit`, an operation still running `limit` after it started (or
    /// after the process started, before the first) is stopped: what
    /// finished is kept, the stopped operation bounded, and the operations
    /// after it run in a new process.
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
        let per_op = limit.map(|l| PeerLimit::per_step(l, STARTING));
        let run = |ops: &[&str]| {
            peer::run_peer_json_lines(
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
                    .args(["--ops", &ops.join(",")])
                    .args(shape.vae_tiling.then_some("--vae-tiling")),
                SCRIPT,
                per_op,
            )
        };
        // One process for the operations left; after a stop, the next
        // operation in a new one.
        let mut runs = Vec::new();
        let mut left = &PeerTimings::OPS[..];
        while !left.is_empty() {
            let r = run(left)?;
            let done = match r.stopped {
                None => left.len(),
                // Through the operation it was stopped in (or the first,
                // stopped before it started).
                Some(_) => PeerTimings::last_started(&r)
                    .and_then(|(_, op)| left.iter().position(|o| *o == op))
                    .map_or(1, |i| i + 1),
            };
            runs.push((&left[..done], r));
            left = &left[done..];
        }
        PeerTimings::from_runs(&runs, repeat, limit)
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
    /// far after each operation), from the runs that timed each operation
    /// (each run with the operations it was given), under each operation's
    /// time `limit`.
    fn from_runs(
        runs: &[(&[&str], peer::PeerLines)],
        repeat: usize,
        limit: Option<Duration>,
    ) -> Result<Self, BenchError> {
        let time = |op: &str| {
            runs.iter()
                .find(|(ops, _)| ops.contains(&op))
                .map_or(Ok(PeerTime::NotRun), |(_, run)| {
                    Self::op_time(run, op, repeat)
                })
        };
        let [transformer_forward, vae_encode, vae_decode] = Self::OPS.map(time);
        Ok(Self {
            transformer_forward: transformer_forward?,
            vae_encode: vae_encode?,
            vae_decode: vae_decode?,
            stopped_after_s: limit
                .filter(|_| runs.iter().any(|(_, run)| run.stopped.is_some()))
                .map(|l| l.as_secs_f64()),
        })
    }

    /// The last operation a run started, and when.
    fn last_started(run: &peer::PeerLines) -> Option<(Duration, &str)> {
        run.lines
            .iter()
            .rev()
            .find_map(|(at, v)| Some((*at, v.get(STARTING)?.as_str()?)))
    }

    /// Operation `op` of one run: a finished run must have timed it; in a
    /// stopped one, it finished, or it is bounded by the time since it
    /// started over the `1 + repeat` runs it makes when it was the last one
    /// started, or it did not run.
    fn op_time(run: &peer::PeerLines, op: &str, repeat: usize) -> Result<PeerTime, BenchError> {
        let key = format!("{op}_s");
        let result = run.last_where(|v| v.get(STARTING).is_none());
        let Some(stopped_at) = run.stopped else {
            let r = result.ok_or_else(|| PeerError::NoJson {
                script: SCRIPT.into(),
            })?;
            return Ok(PeerTime::Seconds(r.number(&key)?));
        };
        if let Some(s) = result.and_then(|r| r.value().get(&key)?.as_f64()) {
            return Ok(PeerTime::Seconds(s));
        }
        // The operation it was in: the last one started.
        Ok(match Self::last_started(run) {
            Some((at, last)) if last == op => {
                let ran = stopped_at.saturating_sub(at).as_secs_f64();
                PeerTime::Over(ran / (1 + repeat.max(1)) as f64)
            }
            _ => PeerTime::NotRun,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    const ALL: &[&str] = &PeerTimings::OPS;

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
        let limit = Some(Duration::from_secs(90));
        // Stopped at 100 s, 90 s into the encode's warm-up and 2 runs.
        let t = PeerTimings::from_runs(&[(ALL, lines(Some(100), &progress))], 2, limit)
            .expect("timings");
        assert_eq!(t.transformer_forward, PeerTime::Seconds(3.5));
        assert_eq!(t.vae_encode, PeerTime::Over(30.0));
        assert_eq!(t.vae_decode, PeerTime::NotRun);
        assert_eq!(t.stopped_after_s, Some(90.0));
        // Stopped before anything finished.
        let t = PeerTimings::from_runs(&[(ALL, lines(Some(50), &progress[..1]))], 1, limit)
            .expect("timings");
        assert_eq!(t.transformer_forward, PeerTime::Over(24.5));
        assert_eq!(t.vae_encode.seconds(), None);
        // The decode in a run of its own after the stop.
        let decode = [
            (2, r#"{"starting": "vae_decode"}"#),
            (9, r#"{"vae_decode_s": 3.0}"#),
        ];
        let t = PeerTimings::from_runs(
            &[
                (&ALL[..2], lines(Some(100), &progress)),
                (&ALL[2..], lines(None, &decode)),
            ],
            2,
            limit,
        )
        .expect("timings");
        assert_eq!(
            [t.transformer_forward, t.vae_encode, t.vae_decode],
            [
                PeerTime::Seconds(3.5),
                PeerTime::Over(30.0),
                PeerTime::Seconds(3.0)
            ]
        );
        // A finished run needs all three; the last result counts.
        let mut done = progress.to_vec();
        done.push((
            20,
            r#"{"transformer_forward_s": 3.5, "vae_encode_s": 2.0, "vae_decode_s": 4.0}"#,
        ));
        let t = PeerTimings::from_runs(&[(ALL, lines(None, &done))], 1, None).expect("timings");
        assert_eq!(
            [t.transformer_forward, t.vae_encode, t.vae_decode].map(PeerTime::seconds),
            [Some(3.5), Some(2.0), Some(4.0)]
        );
        assert_eq!(t.stopped_after_s, None);
        let e = PeerTimings::from_runs(&[(ALL, lines(None, &progress))], 1, None)
            .expect_err("unfinished");
        assert_eq!(
            e.to_string(),
            "diffusers_model.py result has no number `vae_encode_s`"
        );
    }

    /// With a limit, each operation has it from its own start: the one
    /// still running then is stopped and bounded, and the ones after it run
    /// in a new process (a stand-in peer that hangs in the encode while the
    /// file `hang` exists, and logs each call's `--ops`).
    #[test]
    fn each_operation_has_its_own_limit_and_the_next_runs_after_a_stop() {
        let repo = tempfile::tempdir().expect("tempdir");
        let bench = repo.path().join("scripts/bench");
        std::fs::create_dir_all(&bench).expect("mkdir");
        let (calls, hang) = (repo.path().join("calls"), repo.path().join("hang"));
        let script = format!(
            r#"while [ $# -gt 0 ]; do [ "$1" = --ops ] && ops=$2; shift; done
echo "$ops" >> '{calls}'
out='"threads": 1'
for op in $(echo "$ops" | tr , ' '); do
  echo "{{\"starting\": \"$op\"}}"
  sleep 1
  [ "$op" = vae_encode ] && [ -e '{hang}' ] && exec sleep 60
  out="$out, \"${{op}}_s\": 2.5"
  echo "{{$out}}"
done"#,
            calls = calls.display(),
            hang = hang.display()
        );
        std::fs::write(bench.join(SCRIPT), script).expect("script");
        std::fs::write(&hang, "").expect("hang");
        let peer = DiffusersPeer {
            python: "sh".into(),
            repo: repo.path().to_path_buf(),
        };
        let shape = ModelBenchShape {
            frames: 1,
            height: 16,
            width: 16,
            text_len: 8,
            batch: 1,
            vae_tiling: false,
        };
        let (tf, vae) = (TransformerConfig::tiny(), VaeConfig::tiny());
        let time = |limit| {
            peer.time_model(
                &tf,
                &vae,
                &shape,
                ComputeDevice::Cpu,
                Precision::F32,
                1,
                limit,
            )
        };
        // Each operation takes 1 s: more than 2 s in all before the encode
        // hangs, so only a limit per operation lets the transformer finish.
        let t0 = std::time::Instant::now();
        let t = time(Some(Duration::from_secs(2))).expect("timings");
        assert!(t0.elapsed() < Duration::from_secs(30), "not stopped");
        assert_eq!(t.transformer_forward, PeerTime::Seconds(2.5));
        assert_eq!(t.vae_encode, PeerTime::Over(1.0), "{t:?}");
        assert_eq!(t.vae_decode, PeerTime::Seconds(2.5), "ran after the stop");
        assert_eq!(t.stopped_after_s, Some(2.0));
        let log = std::fs::read_to_string(&calls).expect("calls");
        assert_eq!(
            log.lines().collect::<Vec<_>>(),
            ["transformer_forward,vae_encode,vae_decode", "vae_decode"]
        );
        // Nothing stopped: one process for all three, with or without a limit.
        std::fs::remove_file(&hang).expect("rm");
        for limit in [None, Some(Duration::from_secs(20))] {
            let t = time(limit).expect("timings");
            assert_eq!(
                [t.transformer_forward, t.vae_encode, t.vae_decode],
                [PeerTime::Seconds(2.5); 3]
            );
            assert_eq!(t.stopped_after_s, None);
        }
        let log = std::fs::read_to_string(&calls).expect("calls");
        assert_eq!(log.lines().count(), 4, "{log}");
    }
}
