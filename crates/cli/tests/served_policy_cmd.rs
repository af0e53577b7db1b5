//! `eval-policy-rollout --policy ws://...`: a policy served over openpi's
//! websocket protocol (`crates/plan/tests/data/openpi_server.py` in
//! `.venv-policy`, made by `./run test`) evaluated beside the scripted
//! policies in the perfect model; a served policy that cannot be reached is
//! reported by name and the others' results are kept.

mod common;
use common::{ok, run, s};
use std::io::{BufRead, BufReader};
use std::path::PathBuf;
use std::process::{Child, Command, Stdio};

struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// Starts the test server in `mode`; its URL.
fn server(mode: &str) -> (Server, String) {
    let python = repo().join(".venv-policy/bin/python");
    assert!(
        python.is_file(),
        "{}: no policy test venv (./run test makes it: scripts/setup-policy-venv.sh)",
        python.display()
    );
    let mut child = Command::new(python)
        .arg(repo().join("crates/plan/tests/data/openpi_server.py"))
        .args(["--mode", mode])
        .stdout(Stdio::piped())
        .spawn()
        .expect("start the policy server");
    let mut line = String::new();
    let out = child.stdout.take().expect("stdout");
    BufReader::new(out).read_line(&mut line).expect("port");
    let port = line.trim().to_string();
    (Server(child), format!("ws://127.0.0.1:{port}"))
}

#[test]
fn a_served_policy_is_ranked_beside_scripted_ones_and_a_lost_one_is_named() {
    let dir = tempfile::tempdir().expect("tempdir");
    let config = dir.path().join("policy.toml");
    std::fs::write(
        &config,
        "[observation]\nee_pose = \"observation/ee_pose\"\nprompt = \"reach the goal\"\n",
    )
    .expect("write the config");
    let (_good, url) = server("good");
    let gone = std::net::TcpListener::bind("127.0.0.1:0")
        .and_then(|l| l.local_addr())
        .expect("a free port")
        .port();
    let o = run(&[
        "eval-policy-rollout",
        "--task",
        "reach",
        "--trials",
        "2",
        "--episode-frames",
        "9",
        "--offsets-mm",
        "0,50",
        "--policy",
        &format!("served={url}"),
        "--policy",
        &format!("gone=ws://127.0.0.1:{gone}"),
        "--policy-config",
        s(&config),
    ]);
    ok(&o);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("| served |"), "{out}");
    assert!(
        out.contains("| scripted(offset 0 mm) | ") && out.contains("| scripted(offset 50 mm) | "),
        "{out}"
    );
    assert!(
        out.contains("Not evaluated: gone: policy gone: ws://127.0.0.1:")
            && out.contains("cannot connect"),
        "{out}"
    );
    // A config naming an unknown field is refused before any rollout.
    std::fs::write(&config, "[action]\nlayot = \"ee_delta\"\n").expect("write");
    let o = run(&[
        "eval-policy-rollout",
        "--task",
        "reach",
        "--policy",
        &url,
        "--offsets-mm",
        "0",
        "--policy-config",
        s(&config),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("--policy-config") && err.contains("layot"),
        "{err}"
    );
    // A malformed --policy is refused by clap with the expected form.
    let o = run(&[
        "eval-policy-rollout",
        "--task",
        "reach",
        "--policy",
        "localhost:8000",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && err.contains("[NAME=]ws://HOST:PORT"),
        "{err}"
    );
}
