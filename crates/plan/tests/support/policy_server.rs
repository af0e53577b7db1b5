//! A policy server of openpi's websocket protocol for tests
//! (`crates/plan/tests/data/openpi_server.py` in `.venv-policy`, made by
//! `./run test` with `scripts/setup-policy-venv.sh`), killed when dropped.
//! Shared by `crates/plan/tests/served_policy.rs` and
//! `crates/cli/tests/served_policy_cmd.rs` (`#[path]`).

use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

/// A running server.
pub struct Server {
    child: Child,
    /// `ws://127.0.0.1:PORT`.
    pub url: String,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Starts the server in `mode` (see the script) with `extra` arguments.
pub fn server(mode: &str, extra: &[&str]) -> Server {
    let repo = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..");
    let python = repo.join(".venv-policy/bin/python");
    assert!(
        python.is_file(),
        "{}: no policy test venv (./run test makes it: scripts/setup-policy-venv.sh)",
        python.display()
    );
    let mut child = Command::new(python)
        .arg(repo.join("crates/plan/tests/data/openpi_server.py"))
        .args(["--mode", mode])
        .args(extra)
        .stdout(Stdio::piped())
        .spawn()
        .expect("start the policy server");
    let mut line = String::new();
    let stdout = child.stdout.take().expect("stdout");
    BufReader::new(stdout).read_line(&mut line).expect("port");
    let port: u16 = line.trim().parse().expect("the server prints its port");
    Server {
        child,
        url: format!("ws://127.0.0.1:{port}"),
    }
}

/// A port nothing listens on (bound, then freed).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port()
}
