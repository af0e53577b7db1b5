//! `eval-policy-rollout --policy ws://...`: a policy served over openpi's
//! websocket protocol (`crates/plan/tests/data/openpi_server.py` in
//! `.venv-policy`, made by `./run test`) evaluated beside the scripted
//! policies in the perfect model; a served policy that cannot be reached is
//! reported by name and the others' results are kept.

use crate::common;
use crate::policy_server;
use common::{ok, run, s};
use policy_server::{free_port, server};

#[test]
fn a_served_policy_is_ranked_beside_scripted_ones_and_a_lost_one_is_named() {
    let dir = tempfile::tempdir().expect("tempdir");
    let config = dir.path().join("policy.toml");
    std::fs::write(
        &config,
        "[observation]\nee_pose = \"observation/ee_pose\"\nprompt = \"reach the goal\"\n",
    )
    .expect("write the config");
    let good = server("good", &[]);
    let url = good.url.clone();
    let gone = free_port();
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
        "--json",
        s(&dir.path().join("report.json")),
    ]);
    ok(&o);
    let json: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(dir.path().join("report.json")).expect("report.json"),
    )
    .expect("JSON");
    assert_eq!(json["policies"].as_array().map(Vec::len), Some(3), "{json}");
    assert_eq!(json["policies"][2]["policy"], "served", "{json}");
    assert_eq!(json["not_evaluated"][0]["policy"], "gone", "{json}");
    assert!(json["not_evaluated"][0]["error"]
        .as_str()
        .is_some_and(|e| e.contains("cannot connect")));
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("| served |"), "{out}");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("served: connected to ws://127.0.0.1:")
            && err.contains("\"policy\": \"test\""),
        "{err}"
    );
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
