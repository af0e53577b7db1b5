//! The GPU checklist's dry run (`scripts/gpu/run.sh --dry-run`): the same
//! items as on a GPU, on the CPU at tiny shapes. Every item that can run on
//! the CPU must pass, the CUDA-only ones are reported skipped (not failed),
//! and the summary carries every item's figures: so the checklist cannot
//! rot between the rare GPU loans.

use std::path::Path;
use std::process::Command;

/// `scripts/gpu/run.sh ARGS` with this build's binary, its output in `out`.
fn run_checklist(out: &Path, args: &[&str]) -> std::process::Output {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    Command::new("bash")
        .arg(root.join("scripts/gpu/run.sh"))
        .args(args)
        .env("OUT", out)
        .env("BRIDGEV2W", env!("CARGO_BIN_EXE_bridgev2w"))
        .current_dir(&root)
        .output()
        .expect("run scripts/gpu/run.sh")
}

#[test]
fn the_gpu_checklist_dry_run_passes_on_the_cpu() {
    let out = tempfile::tempdir().expect("tempdir");
    let o = run_checklist(out.path(), &["--dry-run"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    let text = std::fs::read_to_string(out.path().join("summary.json")).expect("summary.json");
    let summary: serde_json::Value = serde_json::from_str(&text).expect("JSON");
    let items = summary["items"].as_array().expect("items");
    let item = |name: &str| {
        items
            .iter()
            .find(|i| i["item"] == name)
            .unwrap_or_else(|| panic!("no item {name} in {text}"))
    };
    for name in [
        "environment",
        "predict-random-tiny",
        "predict-demo-model",
        "train-bf16",
        "distributed-one-rank",
        "bench-model",
        "bench-vae-tiled",
        "bench-flow",
        "planning-cost",
    ] {
        assert_eq!(item(name)["status"], "ok", "{name}: {text}\n{stderr}");
    }
    for name in ["predict-full", "train-step-full", "train-step-flow"] {
        assert_eq!(item(name)["status"], "skipped: no CUDA device", "{name}");
    }
    assert_eq!(summary["environment"]["mode"], "dry-run");
    // The CPU against itself: the same bytes, the same losses.
    assert_eq!(item("predict-random-tiny")["metrics"]["max_abs_diff_u8"], 0);
    assert_eq!(
        item("distributed-one-rank")["metrics"]["max_relative_diff"],
        0.0
    );
    // bf16 autocast against f32: finite and close.
    let bf16 = &item("train-bf16")["metrics"];
    assert_eq!(bf16["finite"], true);
    assert!(
        bf16["max_relative_diff"].as_f64().expect("a number") < 0.05,
        "{bf16}"
    );
    let bench = &item("bench-model")["metrics"];
    assert!(
        bench["transformer_forward_b1_speedup"].as_f64().is_some()
            && bench["vae_decode_speedup"].as_f64().is_some(),
        "{bench}"
    );
    // Both replays of the flow loss's backward, each with its time, its
    // memory (the caching allocator's peak on the CPU), what its record
    // kept and the same loss, and the stepwise one with RAFT.
    let flow = &item("bench-flow")["metrics"];
    for mode in ["recorded", "stepwise", "stepwise_raft"] {
        assert!(
            flow[format!("{mode}_seconds")]
                .as_f64()
                .is_some_and(|s| s > 0.0)
                && flow[format!("{mode}_peak_mib")].as_f64().is_some()
                && flow[format!("{mode}_record_mib")]
                    .as_f64()
                    .is_some_and(|m| m > 0.0)
                // The CUDA allocator's peak: recorded, empty on the CPU.
                && flow
                    .as_object()
                    .is_some_and(|o| o.contains_key(&format!("{mode}_allocator_peak_mib"))),
            "{flow}"
        );
    }
    assert_eq!(flow["recorded_loss"], flow["stepwise_loss"], "{flow}");
    let md = std::fs::read_to_string(out.path().join("summary.md")).expect("summary.md");
    assert!(
        md.contains("| predict-full | skipped: no CUDA device |")
            && md.contains("| train-bf16 | ok |"),
        "{md}"
    );
}

#[test]
fn the_gpu_checklist_refuses_an_unknown_item_and_names_the_items() {
    let out = tempfile::tempdir().expect("tempdir");
    let o = run_checklist(out.path(), &["--dry-run", "planing-cost"]);
    assert_eq!(o.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(
        stderr.contains("planing-cost")
            && stderr.contains("planning-cost")
            && stderr.contains("smoke"),
        "{stderr}"
    );
}
