//! Python peers of the benches: the repository root that holds
//! `scripts/bench/`, the Python interpreters (the bench venv with pybullet and
//! scikit-image, the project venv with torch and diffusers), a scratch folder
//! for the arrays handed to a peer, and running a peer script that prints its
//! result as one JSON object on stdout. A bench reports its stages and
//! notes through [`crate::progress::Progress`].

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// The file that marks the repository root (the benches' peer scripts).
pub const REPO_MARKER: &str = "scripts/bench/pybullet_masks.py";

/// A peer could not be found, started, or gave no usable result.
#[derive(Debug, thiserror::Error)]
pub enum PeerError {
    /// No repository root above the current directory.
    #[error("{}: not inside a bridgev2w repository (no folder above it holds {REPO_MARKER}, which marks the root that holds the benches' Python peers): run from the repository or pass --repo", cwd.display())]
    NoRepo {
        /// The directory searched from.
        cwd: PathBuf,
    },
    /// The current directory cannot be read.
    #[error("current directory: {0}")]
    CurrentDir(#[source] std::io::Error),
    /// A temporary folder could not be created.
    #[error("creating a temporary folder: {0}")]
    Scratch(#[source] std::io::Error),
    /// A program could not be started.
    #[error("running {what}")]
    Spawn {
        /// The program or script.
        what: String,
        /// Why it did not start.
        #[source]
        source: std::io::Error,
    },
    /// A program exited with an error.
    #[error("{what} failed:\n{stderr}")]
    Failed {
        /// The program or script.
        what: String,
        /// Its standard error.
        stderr: String,
    },
    /// `scripts/bench/setup-venv.sh` did not leave a working bench venv.
    #[error("scripts/bench/setup-venv.sh failed: cannot install pybullet into .venv-bench (use --no-pybullet to bench this renderer alone)")]
    BenchVenv,
    /// An interpreter that should exist does not.
    #[error("{} not found: {hint}", path.display())]
    NoPython {
        /// The interpreter looked for.
        path: PathBuf,
        /// How to get one.
        hint: String,
    },
    /// A script printed no JSON object on stdout.
    #[error("{script} printed no JSON result")]
    NoJson {
        /// The script.
        script: String,
    },
    /// A script's last JSON line does not parse.
    #[error("{script} printed invalid JSON: {source}")]
    BadJson {
        /// The script.
        script: String,
        /// Where and why.
        #[source]
        source: serde_json::Error,
    },
    /// A script's result lacks a value, or has one of the wrong type.
    #[error("{script} result has no {what} `{key}`")]
    Missing {
        /// The script.
        script: String,
        /// The key.
        key: String,
        /// What was expected under it.
        what: &'static str,
    },
}

/// Result of this module.
pub type Result<T> = std::result::Result<T, PeerError>;

/// The repository root: `explicit` if given, else the nearest folder above
/// the current directory that holds [`REPO_MARKER`].
pub fn find_repo(explicit: Option<&Path>) -> Result<PathBuf> {
    if let Some(r) = explicit {
        return Ok(r.to_path_buf());
    }
    let cwd = std::env::current_dir().map_err(PeerError::CurrentDir)?;
    cwd.ancestors()
        .find(|d| d.join(REPO_MARKER).is_file())
        .map(Path::to_path_buf)
        .ok_or(PeerError::NoRepo { cwd: cwd.clone() })
}

/// The bench venv's python (`.venv-bench`, with pybullet, numpy and
/// scikit-image), created or checked by `scripts/bench/setup-venv.sh`.
pub fn bench_python(repo: &Path) -> Result<PathBuf> {
    let python = repo.join(".venv-bench/bin/python");
    let status = Command::new("bash")
        .arg(repo.join("scripts/bench/setup-venv.sh"))
        .current_dir(repo)
        .stdout(Stdio::null())
        .status()
        .map_err(|source| PeerError::Spawn {
            what: "scripts/bench/setup-venv.sh".into(),
            source,
        })?;
    if !status.success() || !python.is_file() {
        return Err(PeerError::BenchVenv);
    }
    Ok(python)
}

/// The project venv's python (`.venv`, with torch and diffusers, made by
/// `scripts/setup-venv.sh`); `hint` says what else the caller may do.
pub fn project_python(repo: &Path, hint: &str) -> Result<PathBuf> {
    let path = repo.join(".venv/bin/python");
    if !path.is_file() {
        return Err(PeerError::NoPython {
            path,
            hint: format!("run scripts/setup-venv.sh{hint}"),
        });
    }
    Ok(path)
}

/// A temporary folder for the files exchanged with a peer (removed on drop).
pub fn scratch_dir() -> Result<tempfile::TempDir> {
    tempfile::tempdir().map_err(PeerError::Scratch)
}

/// Runs `cmd` and returns its stdout; `what` names it in errors (with its
/// stderr when it fails).
pub fn run_peer_text(cmd: &mut Command, what: &str) -> Result<String> {
    let out = cmd.output().map_err(|source| PeerError::Spawn {
        what: what.to_owned(),
        source,
    })?;
    if !out.status.success() {
        return Err(PeerError::Failed {
            what: what.to_owned(),
            stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
        });
    }
    Ok(String::from_utf8_lossy(&out.stdout).into_owned())
}

/// Runs the peer script `scripts/bench/{script}` (`cmd` holds the
/// interpreter and arguments) and returns the last JSON object it printed on
/// stdout.
pub fn run_peer_json(cmd: &mut Command, script: &str) -> Result<PeerOutput> {
    let out = cmd.output().map_err(|source| PeerError::Spawn {
        what: format!("scripts/bench/{script}"),
        source,
    })?;
    if !out.status.success() {
        return Err(PeerError::Failed {
            what: script.to_owned(),
            stderr: String::from_utf8_lossy(&out.stderr).into_owned(),
        });
    }
    PeerOutput::parse(script, &String::from_utf8_lossy(&out.stdout))
}

/// What a peer run under [`run_peer_json_lines`] printed: every JSON
/// object on its stdout with when it arrived, and whether the run was
/// stopped at its time limit.
#[derive(Debug, Clone, PartialEq)]
pub struct PeerLines {
    script: String,
    /// The objects in order, each with the time since the start.
    pub lines: Vec<(Duration, serde_json::Value)>,
    /// `Some(t)` when the peer was still running at its time limit and was
    /// stopped there, `t` after its start (`lines` then holds what it
    /// printed until then).
    pub stopped: Option<Duration>,
}

impl PeerLines {
    /// The last object for which `keep` holds, as a result.
    pub fn last_where(&self, keep: impl Fn(&serde_json::Value) -> bool) -> Option<PeerOutput> {
        self.lines
            .iter()
            .rev()
            .find(|(_, v)| keep(v))
            .map(|(_, v)| PeerOutput {
                script: self.script.clone(),
                value: v.clone(),
            })
    }
}

/// How long a peer read by [`run_peer_json_lines`] may run.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PeerLimit {
    /// The time allowed.
    pub time: Duration,
    /// With a key, the time counts from the last object that has it (a
    /// peer's progress line, such as `{"starting": OP}`), so that each step
    /// has `time` of its own; before the first such object, from the start.
    pub per_step: Option<&'static str>,
}

impl PeerLimit {
    /// `time` for the whole run.
    pub fn whole(time: Duration) -> Self {
        Self {
            time,
            per_step: None,
        }
    }

    /// `time` for each step the peer starts with an object that has `key`.
    pub fn per_step(time: Duration, key: &'static str) -> Self {
        Self {
            time,
            per_step: Some(key),
        }
    }
}

/// Runs the peer script `scripts/bench/{script}` as [`run_peer_json`] does,
/// reading the JSON objects it prints line by line as they come (a peer
/// that reports its progress so); with a `limit`, a peer still running
/// then (at the end of the whole run's time, or of its step's) is stopped
/// (killed) and what it printed so far returned, marked
/// [`PeerLines::stopped`]. Lines that are not JSON objects are passed over;
/// a peer that exits with an error is [`PeerError::Failed`] with its stderr.
pub fn run_peer_json_lines(
    cmd: &mut Command,
    script: &str,
    limit: Option<PeerLimit>,
) -> Result<PeerLines> {
    let what = format!("scripts/bench/{script}");
    let mut child = cmd
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|source| PeerError::Spawn {
            what: what.clone(),
            source,
        })?;
    let start = Instant::now();
    let (Some(stdout), Some(mut stderr)) = (child.stdout.take(), child.stderr.take()) else {
        let _ = child.kill();
        return Err(PeerError::Spawn {
            what,
            source: std::io::Error::other("no pipes to its stdout and stderr"),
        });
    };
    // stderr in its own thread, so that a chatty peer never blocks on it.
    let errors = std::thread::spawn(move || {
        let mut text = String::new();
        let _ = std::io::Read::read_to_string(&mut stderr, &mut text);
        text
    });
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout)
            .lines()
            .map_while(std::io::Result::ok)
        {
            if tx.send((start.elapsed(), line)).is_err() {
                break;
            }
        }
    });
    let mut lines: Vec<(Duration, serde_json::Value)> = Vec::new();
    let mut stopped = None;
    // When the time allowed ends, after the start.
    let deadline = |lines: &[(Duration, serde_json::Value)], limit: PeerLimit| {
        let step = limit.per_step.and_then(|key| {
            lines
                .iter()
                .rev()
                .find_map(|(at, v)| v.get(key).map(|_| *at))
        });
        step.unwrap_or(Duration::ZERO) + limit.time
    };
    loop {
        let next = match limit {
            Some(l) => rx.recv_timeout(deadline(&lines, l).saturating_sub(start.elapsed())),
            None => rx.recv().map_err(|_| mpsc::RecvTimeoutError::Disconnected),
        };
        match next {
            Ok((at, line)) => {
                if line.trim_start().starts_with('{') {
                    match serde_json::from_str(&line) {
                        Ok(value) => lines.push((at, value)),
                        Err(source) => {
                            // Not left running behind the error.
                            let _ = child.kill();
                            let _ = child.wait();
                            return Err(PeerError::BadJson {
                                script: script.to_owned(),
                                source,
                            });
                        }
                    }
                }
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {
                // Killing a peer that has just exited fails harmlessly.
                let _ = child.kill();
                stopped = limit.map(|l| deadline(&lines, l));
                break;
            }
            Err(mpsc::RecvTimeoutError::Disconnected) => break,
        }
    }
    let status = child.wait().map_err(|source| PeerError::Spawn {
        what: what.clone(),
        source,
    })?;
    // A stopped peer's stderr is not waited for (a process it started may
    // still hold the pipe).
    if stopped.is_none() && !status.success() {
        return Err(PeerError::Failed {
            what: script.to_owned(),
            stderr: errors.join().unwrap_or_default(),
        });
    }
    Ok(PeerLines {
        script: script.to_owned(),
        lines,
        stopped,
    })
}

/// The JSON result of a peer script.
#[derive(Debug, Clone, PartialEq)]
pub struct PeerOutput {
    script: String,
    value: serde_json::Value,
}

impl PeerOutput {
    /// The last line of `stdout` that starts with `{`, parsed.
    pub fn parse(script: &str, stdout: &str) -> Result<Self> {
        let line = stdout
            .lines()
            .rev()
            .find(|l| l.trim_start().starts_with('{'))
            .ok_or_else(|| PeerError::NoJson {
                script: script.to_owned(),
            })?;
        let value = serde_json::from_str(line).map_err(|source| PeerError::BadJson {
            script: script.to_owned(),
            source,
        })?;
        Ok(Self {
            script: script.to_owned(),
            value,
        })
    }

    /// The whole result.
    pub fn value(&self) -> &serde_json::Value {
        &self.value
    }

    /// The number under `key`.
    pub fn number(&self, key: &str) -> Result<f64> {
        self.value[key]
            .as_f64()
            .ok_or_else(|| self.missing(key, "number"))
    }

    /// The list of numbers under `key`.
    pub fn numbers(&self, key: &str) -> Result<Vec<f64>> {
        self.value[key]
            .as_array()
            .and_then(|a| a.iter().map(serde_json::Value::as_f64).collect())
            .ok_or_else(|| self.missing(key, "list of numbers"))
    }

    fn missing(&self, key: &str, what: &'static str) -> PeerError {
        PeerError::Missing {
            script: self.script.clone(),
            key: key.to_owned(),
            what,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_repository_names_the_folder_and_the_way_out() {
        let e = PeerError::NoRepo {
            cwd: PathBuf::from("/tmp/elsewhere"),
        };
        let msg = e.to_string();
        assert!(
            msg.starts_with("/tmp/elsewhere: not inside a bridgev2w repository"),
            "{msg}"
        );
        assert!(
            msg.contains(REPO_MARKER) && msg.ends_with("pass --repo"),
            "{msg}"
        );
        // An explicit root is taken as given.
        assert_eq!(
            find_repo(Some(Path::new("/r"))).expect("explicit"),
            PathBuf::from("/r")
        );
    }

    #[test]
    fn peer_output_is_the_last_json_line() {
        let out = PeerOutput::parse(
            "s.py",
            "banner\n{\"a\": 1}\n  {\"a\": 2, \"v\": [1, 2.5]}\nbye\n",
        )
        .expect("json");
        assert_eq!(out.number("a").expect("a"), 2.0);
        assert_eq!(out.numbers("v").expect("v"), vec![1.0, 2.5]);
        let e = out.number("b").expect_err("no b");
        assert_eq!(e.to_string(), "s.py result has no number `b`");
        assert!(out.numbers("a").is_err());
        let e = PeerOutput::parse("s.py", "nothing\n").expect_err("no json");
        assert_eq!(e.to_string(), "s.py printed no JSON result");
        assert!(matches!(
            PeerOutput::parse("s.py", "{oops\n"),
            Err(PeerError::BadJson { .. })
        ));
    }

    #[test]
    fn failing_peers_name_the_script_and_pass_stderr_on() {
        let mut cmd = Command::new("sh");
        cmd.args(["-c", "echo bad input >&2; exit 3"]);
        let e = run_peer_json(&mut cmd, "x.py").expect_err("fails");
        assert_eq!(e.to_string(), "x.py failed:\nbad input\n");
        let mut cmd = Command::new("sh");
        cmd.args(["-c", "echo '{\"k\": 4}'"]);
        let out = run_peer_json(&mut cmd, "x.py").expect("runs");
        assert_eq!(out.number("k").expect("k"), 4.0);
        let text = run_peer_text(Command::new("sh").args(["-c", "echo hi"]), "sh").expect("sh");
        assert_eq!(text, "hi\n");
        let e = run_peer_text(&mut Command::new("/nonexistent/peer"), "peer").expect_err("spawn");
        assert_eq!(e.to_string(), "running peer");
    }

    #[test]
    fn a_peer_read_line_by_line_is_stopped_at_its_limit_with_what_it_printed() {
        let mut cmd = Command::new("sh");
        cmd.args([
            "-c",
            "echo '{\"starting\": \"a\"}'; echo '{\"a_s\": 1}'; echo noise; \
             echo '{\"starting\": \"b\"}'; exec sleep 30",
        ]);
        let t0 = Instant::now();
        let run = run_peer_json_lines(
            &mut cmd,
            "x.py",
            Some(PeerLimit::whole(Duration::from_millis(1500))),
        )
        .expect("stopped, not failed");
        assert!(t0.elapsed() < Duration::from_secs(20), "not killed");
        assert_eq!(run.stopped, Some(Duration::from_millis(1500)));
        assert_eq!(run.lines.len(), 3, "{run:?}");
        let result = run
            .last_where(|v| v.get("starting").is_none())
            .expect("a result");
        assert_eq!(result.number("a_s").expect("a"), 1.0);
        assert!(run
            .lines
            .iter()
            .all(|(at, _)| *at < Duration::from_millis(1500)));
        // Run to the end: every object, not stopped; a failure names the script.
        let mut cmd = Command::new("sh");
        cmd.args(["-c", "echo '{\"k\": 4}'; echo '{\"k\": 5}'"]);
        let run = run_peer_json_lines(
            &mut cmd,
            "x.py",
            Some(PeerLimit::whole(Duration::from_secs(60))),
        )
        .expect("runs");
        assert_eq!((run.lines.len(), run.stopped), (2, None));
        assert_eq!(
            run.last_where(|_| true)
                .expect("last")
                .number("k")
                .expect("k"),
            5.0
        );
        let mut cmd = Command::new("sh");
        cmd.args(["-c", "echo '{\"k\": 4}'; echo broken >&2; exit 2"]);
        let e = run_peer_json_lines(&mut cmd, "x.py", None).expect_err("fails");
        assert_eq!(e.to_string(), "x.py failed:\nbroken\n");
        let mut cmd = Command::new("sh");
        cmd.args(["-c", "echo '{oops'; exec sleep 30"]);
        let t0 = Instant::now();
        assert!(matches!(
            run_peer_json_lines(&mut cmd, "x.py", None),
            Err(PeerError::BadJson { .. })
        ));
        assert!(t0.elapsed() < Duration::from_secs(20), "left running");
    }

    #[test]
    fn a_per_step_limit_counts_from_each_step_s_start() {
        // Two steps of 0.7 s each, under a limit of 1.5 s a step: the
        // whole run (1.4 s and more) would not matter; the third step hangs.
        let mut cmd = Command::new("sh");
        cmd.args([
            "-c",
            "echo '{\"starting\": \"a\"}'; sleep 0.7; echo '{\"starting\": \"b\"}'; \
             sleep 0.7; echo '{\"starting\": \"c\"}'; exec sleep 30",
        ]);
        let t0 = Instant::now();
        let limit = PeerLimit::per_step(Duration::from_millis(1500), "starting");
        let run = run_peer_json_lines(&mut cmd, "x.py", Some(limit)).expect("stopped");
        assert!(t0.elapsed() < Duration::from_secs(20), "not killed");
        assert_eq!(run.lines.len(), 3, "{run:?}");
        let stopped = run.stopped.expect("stopped");
        // 1.5 s after the third step started, not 1.5 s after the start.
        assert_eq!(stopped, run.lines[2].0 + Duration::from_millis(1500));
        assert!(stopped > Duration::from_millis(2500), "{stopped:?}");
    }

    #[test]
    fn an_explicit_repo_is_taken_as_given_and_a_missing_python_is_named() {
        let dir = tempfile::tempdir().expect("tempdir");
        assert_eq!(find_repo(Some(dir.path())).expect("repo"), dir.path());
        let e = project_python(dir.path(), " (or pass --python)").expect_err("no venv");
        assert_eq!(
            e.to_string(),
            format!(
                "{} not found: run scripts/setup-venv.sh (or pass --python)",
                dir.path().join(".venv/bin/python").display()
            )
        );
    }
}
