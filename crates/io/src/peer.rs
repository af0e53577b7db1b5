//! Python peers of the benches: the repository root that holds
//! `scripts/bench/`, the Python interpreters (the bench venv with pybullet and
//! scikit-image, the project venv with torch and diffusers), a scratch folder
//! for the arrays handed to a peer, and running a peer script that prints its
//! result as one JSON object on stdout. A bench reports its stages and
//! notes through [`crate::progress::Progress`].

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};

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
