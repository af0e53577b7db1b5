//! Data-parallel `bridgev2w train`: two processes (RANK 0/1, WORLD_SIZE 2,
//! c10d's Gloo on the CPU) train exactly like one process on the same global
//! batch, started by hand, by `torchrun` (static rendezvous, its agent
//! hosting the store) and by `torchrun --standalone`; and the environment
//! errors a user meets first.

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use crate::common;

use common::{ok, s, synth_tiny, TINY_MODEL_TOML};

fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .expect("bind")
        .local_addr()
        .expect("addr")
        .port()
}

fn train_cmd(cfg: &Path, out: &Path, env: &[(&str, String)]) -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_bridgev2w"));
    c.env("RUST_BACKTRACE", "0")
        .env_remove("RANK")
        .env_remove("WORLD_SIZE")
        .env_remove("LOCAL_RANK")
        .args(["train", s(cfg), "--quiet", "--out", s(out)]);
    for (k, v) in env {
        c.env(k, v);
    }
    c
}

fn setup(d: &Path, batch_size: usize) -> std::path::PathBuf {
    let data = d.join("data");
    if !data.exists() {
        synth_tiny(&data);
    }
    let cfg = format!(
        r#"
{TINY_MODEL_TOML}
[data]
dataset = "{}"
split = "train"

[train]
batch_size = {batch_size}
max_steps = 3
checkpoint_every = 0
warmup_steps = 2
lr = 1e-4
"#,
        s(&data)
    );
    let path = d.join(format!("train-b{batch_size}.toml"));
    std::fs::write(&path, cfg).expect("write config");
    path
}

fn metrics(dir: &Path) -> Vec<serde_json::Value> {
    std::fs::read_to_string(dir.join("metrics.jsonl"))
        .expect("metrics")
        .lines()
        .map(|l| serde_json::from_str(l).expect("json line"))
        .collect()
}

fn dist_env(rank: usize, world: usize, port: u16) -> Vec<(&'static str, String)> {
    vec![
        ("RANK", rank.to_string()),
        ("WORLD_SIZE", world.to_string()),
        ("MASTER_ADDR", "127.0.0.1".into()),
        ("MASTER_PORT", port.to_string()),
        ("BRIDGEV2W_DIST_TIMEOUT", "120".into()),
    ]
}

/// The single process's run `single` and the data-parallel run `dp` (rank
/// 0's folder) have the same losses and parameters after their 3 steps.
fn assert_trained_alike(single: &Path, dp: &Path) {
    let (a, b) = (metrics(single), metrics(dp));
    assert_eq!(a.len(), 3);
    assert_eq!(b.len(), 3);
    let secs = |m: &[serde_json::Value]| -> f64 {
        m.iter().filter_map(|l| l["secs"].as_f64()).sum::<f64>() / m.len() as f64
    };
    eprintln!(
        "mean step time: 1 process {:.3} s, 2 processes {:.3} s",
        secs(&a),
        secs(&b)
    );
    for (x, y) in a.iter().zip(&b) {
        for key in ["loss", "diffusion", "dynamics", "grad_norm", "lr"] {
            let (u, v) = (x[key].as_f64().expect(key), y[key].as_f64().expect(key));
            assert!(
                (u - v).abs() <= 1e-5 * u.abs().max(1e-3),
                "step {}: {key} {u} (1 process) vs {v} (2 processes)",
                x["step"]
            );
        }
        assert_eq!(x["dropped"], y["dropped"]);
    }
    // The same parameters after the 3 updates.
    let read = |p: &Path| -> Vec<(String, tch::Tensor)> {
        let mut v =
            tch::Tensor::read_safetensors(p.join("final/weights.safetensors")).expect("weights");
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    };
    let (wa, wb) = (read(single), read(dp));
    assert_eq!(wa.len(), wb.len());
    assert!(!wa.is_empty());
    let mut max_diff = 0f64;
    for ((na, ta), (nb, tb)) in wa.iter().zip(&wb) {
        assert_eq!(na, nb);
        let d = (ta - tb).abs().max().double_value(&[]);
        max_diff = max_diff.max(d);
    }
    assert!(max_diff < 1e-5, "parameters differ by {max_diff}");
    // The updates were not trivially zero: the weights moved from the start.
    let moved = wa
        .iter()
        .any(|(n, t)| n.contains("lora") && t.abs().max().double_value(&[]) > 0.0);
    assert!(moved, "no LoRA weight moved");
}

/// A temp folder with the batch-2 config and the single process's 3-step
/// run of it (the reference of the data-parallel runs).
fn single_process_run() -> (tempfile::TempDir, std::path::PathBuf, std::path::PathBuf) {
    let dir = tempfile::tempdir().expect("tempdir");
    let cfg = setup(dir.path(), 2);
    let single = dir.path().join("single");
    ok(&train_cmd(&cfg, &single, &[]).output().expect("run"));
    (dir, cfg, single)
}

#[test]
fn two_processes_train_like_one_on_the_global_batch() {
    let (dir, cfg, single) = single_process_run();
    let d = dir.path();
    let port = free_port();
    let (dp0, dp1) = (d.join("dp"), d.join("dp-rank1"));
    let r0 = train_cmd(&cfg, &dp0, &dist_env(0, 2, port))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn rank 0");
    let r1 = train_cmd(&cfg, &dp1, &dist_env(1, 2, port))
        .output()
        .expect("run rank 1");
    let r0 = r0.wait_with_output().expect("rank 0");
    ok(&r1);
    ok(&r0);
    // Rank 1 writes nothing; rank 0 writes what a single process writes.
    assert!(!dp1.exists(), "rank 1 wrote {}", dp1.display());
    assert_trained_alike(&single, &dp0);
}

#[test]
fn environment_errors_name_the_variable_and_value() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let cfg = setup(d, 2);
    let out = d.join("out");
    let err = |env: &[(&str, String)], c: &Path| -> String {
        let o = train_cmd(c, &out, env).output().expect("run");
        assert!(!o.status.success(), "succeeded with {env:?}");
        String::from_utf8_lossy(&o.stderr).into_owned()
    };
    let e = err(&[("WORLD_SIZE", "2".into())], &cfg);
    assert!(e.contains("RANK") && e.contains("WORLD_SIZE=2"), "{e}");
    let e = err(&[("RANK", "1".into())], &cfg);
    assert!(e.contains("WORLD_SIZE") && e.contains("RANK=1"), "{e}");
    let e = err(&[("WORLD_SIZE", "2".into()), ("RANK", "2".into())], &cfg);
    assert!(e.contains("RANK=2") && e.contains("0..2"), "{e}");
    let e = err(&dist_env(0, 2, free_port()), &setup(d, 3));
    assert!(
        e.contains("train.batch_size") && e.contains('3') && e.contains("WORLD_SIZE=2"),
        "{e}"
    );
    // Nobody listens: a clear error after the timeout, not a hang.
    let port = free_port();
    let mut env = dist_env(1, 2, port);
    env.retain(|(k, _)| *k != "BRIDGEV2W_DIST_TIMEOUT");
    env.push(("BRIDGEV2W_DIST_TIMEOUT", "1".into()));
    let start = Instant::now();
    let e = err(&env, &cfg);
    assert!(start.elapsed() < Duration::from_secs(60));
    assert!(
        e.contains("MASTER_ADDR=127.0.0.1") && e.contains(&format!("MASTER_PORT={port}")),
        "{e}"
    );
    assert!(!out.exists(), "a failed rank wrote {}", out.display());
}

#[test]
fn a_killed_rank_or_a_taken_port_stops_with_an_error() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let cfg = setup(d, 2);
    let long = d.join("long.toml");
    let text = std::fs::read_to_string(&cfg).expect("config");
    std::fs::write(&long, text.replace("max_steps = 3", "max_steps = 100000")).expect("write");
    let port = free_port();
    let env = |rank| {
        let mut e = dist_env(rank, 2, port);
        e.retain(|(k, _)| *k != "BRIDGEV2W_DIST_TIMEOUT");
        e.push(("BRIDGEV2W_DIST_TIMEOUT", "30".into()));
        e
    };
    let out0 = d.join("dp");
    let mut r0 = train_cmd(&long, &out0, &env(0))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn rank 0");
    let mut r1 = train_cmd(&long, &d.join("dp1"), &env(1))
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .expect("spawn rank 1");
    // Both are training once rank 0 has logged a step.
    let start = Instant::now();
    while std::fs::read_to_string(out0.join("metrics.jsonl"))
        .map(|m| m.lines().count())
        .unwrap_or(0)
        < 1
    {
        assert!(
            start.elapsed() < Duration::from_secs(180),
            "no training step within 180 s"
        );
        assert!(
            r0.try_wait().expect("rank 0").is_none(),
            "rank 0 stopped early"
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    r1.kill().expect("kill rank 1");
    let _ = r1.wait();
    let killed = Instant::now();
    while r0.try_wait().expect("rank 0").is_none() {
        if killed.elapsed() > Duration::from_secs(90) {
            let _ = r0.kill();
            panic!("rank 0 still runs 90 s after rank 1 was killed");
        }
        std::thread::sleep(Duration::from_millis(100));
    }
    let o = r0.wait_with_output().expect("rank 0");
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    eprintln!("rank 0 after rank 1 was killed: {e}");
    assert!(
        e.contains("rank 0 of 2") && e.contains("did another rank stop"),
        "{e}"
    );
    // MASTER_PORT taken by another program: rank 0 says so.
    let taken = std::net::TcpListener::bind("0.0.0.0:0").expect("bind");
    let port = taken.local_addr().expect("addr").port();
    let o = train_cmd(&cfg, &d.join("taken"), &dist_env(0, 2, port))
        .output()
        .expect("run");
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    eprintln!("rank 0 on a taken port: {e}");
    assert!(
        e.contains(&format!("MASTER_PORT={port}")) && e.contains("host the store"),
        "{e}"
    );
}

fn torchrun() -> std::path::PathBuf {
    let t = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../.venv/bin/torchrun");
    assert!(
        t.is_file(),
        "{}: no torchrun (scripts/setup-venv.sh installs torch)",
        t.display()
    );
    t
}

/// `torchrun --no-python ... bridgev2w train` with `launch` (the
/// rendezvous flags), the two ranks' output in `out`.
fn torchrun_train(cfg: &Path, out: &Path, launch: &[String]) -> std::process::Output {
    let mut c = Command::new(torchrun());
    c.env("RUST_BACKTRACE", "0")
        .env("BRIDGEV2W_DIST_TIMEOUT", "120")
        .env("OMP_NUM_THREADS", "1")
        .env_remove("RANK")
        .env_remove("WORLD_SIZE")
        .env_remove("LOCAL_RANK")
        .env_remove("MASTER_ADDR")
        .env_remove("MASTER_PORT")
        .args(launch)
        .args(["--nproc-per-node", "2", "--no-python"])
        .arg(env!("CARGO_BIN_EXE_bridgev2w"))
        .args(["train", s(cfg), "--quiet", "--out", s(out)]);
    c.output().expect("run torchrun")
}

#[test]
fn torchrun_static_and_standalone_train_like_one_process() {
    let (dir, cfg, single) = single_process_run();
    let d = dir.path();
    // Static rendezvous: torchrun's agent hosts the TCPStore on MASTER_PORT
    // (TORCHELASTIC_USE_AGENT_STORE=True), which the ranks must not bind.
    let port = free_port();
    let static_out = d.join("static");
    let o = torchrun_train(
        &cfg,
        &static_out,
        &[
            "--nnodes".into(),
            "1".into(),
            "--master-addr".into(),
            "127.0.0.1".into(),
            "--master-port".into(),
            port.to_string(),
        ],
    );
    ok(&o);
    assert_trained_alike(&single, &static_out);
    // --standalone: a c10d rendezvous on a free port of its own.
    let standalone = d.join("standalone");
    ok(&torchrun_train(&cfg, &standalone, &["--standalone".into()]));
    assert_trained_alike(&single, &standalone);
}
