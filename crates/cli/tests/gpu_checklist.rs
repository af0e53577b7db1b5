//! The GPU checklist's dry run (`scripts/gpu/run.sh --dry-run`): the same
//! items as on a GPU, on the CPU at tiny shapes. Every item that can run on
//! the CPU must pass, the CUDA-only ones are reported skipped (not failed),
//! and the summary carries every item's figures: so the checklist cannot
//! rot between the rare GPU loans.

use std::path::Path;
use std::process::Command;

/// `PROGRAM scripts/gpu/SCRIPT ARGS` from the repository root with this
/// build's binary, the checklist's output in `out`.
fn gpu_script(program: &str, script: &str, out: &Path, args: &[&str]) -> std::process::Output {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    Command::new(program)
        .arg(root.join("scripts/gpu").join(script))
        .args(args)
        .env("OUT", out)
        .env("BRIDGEV2W", env!("CARGO_BIN_EXE_bridgev2w"))
        .current_dir(&root)
        .output()
        .unwrap_or_else(|e| panic!("run scripts/gpu/{script}: {e}"))
}

/// `scripts/gpu/run.sh ARGS`.
fn run_checklist(out: &Path, args: &[&str]) -> std::process::Output {
    gpu_script("bash", "run.sh", out, args)
}

/// `scripts/gpu/checklist.py ARGS` (its helpers read and write `out`).
fn checklist_py(out: &Path, args: &[&str]) -> std::process::Output {
    gpu_script("python3", "checklist.py", out, args)
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
    for name in [
        "predict-full",
        "train-step-full",
        "train-step-flow",
        "train-step-flow-tiles",
    ] {
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

#[test]
fn the_flow_step_in_smaller_tiles_runs_only_when_the_default_does_not_fit_80_gb() {
    let out = tempfile::tempdir().expect("tempdir");
    // Training steps as `train` logs them on CUDA: the caching allocator's
    // peaks (MiB) per step.
    let steps = |reserved: [f64; 3]| {
        reserved
            .iter()
            .enumerate()
            .map(|(i, r)| {
                format!(
                    "{{\"step\": {i}, \"loss\": 0.5, \"secs\": 9.0, \"flow_weight\": 0.05, \
                     \"cuda_peak_allocated_mib\": {}, \"cuda_peak_reserved_mib\": {r}}}\n",
                    r - 2000.0
                )
            })
            .collect::<String>()
    };
    for (name, reserved, fits) in [
        ("small", [60000.0, 71000.0, 70500.0], true),
        // Reserved + 1 GiB for the context against an 80 GB card's 81,080 MiB.
        ("just", [70000.0, 80000.0, 79000.0], true),
        ("over", [70000.0, 80100.0, 79000.0], false),
        ("large", [90000.0, 98000.0, 98000.0], false),
    ] {
        let log = out.path().join(format!("{name}.jsonl"));
        std::fs::write(&log, steps(reserved)).expect("write");
        let o = checklist_py(
            out.path(),
            &["step-seconds", log.to_str().expect("utf-8"), name],
        );
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        let m: serde_json::Value = serde_json::from_str(
            &std::fs::read_to_string(out.path().join(format!("metrics/{name}.json")))
                .expect("metrics"),
        )
        .expect("JSON");
        assert_eq!(m["fits_80gb"], fits, "{name}: {m}");
        assert_eq!(m["cuda_peak_reserved_mib"], reserved[1], "{name}: {m}");
        let o = checklist_py(out.path(), &["fits-80gb", name]);
        let said = String::from_utf8_lossy(&o.stdout);
        assert_eq!(o.status.success(), fits, "{name}: {said}");
        if fits {
            assert!(
                said.contains("fits an 80 GB GPU")
                    && said.contains(&format!("{:.0} MiB", reserved[1])),
                "{said}"
            );
        }
    }
    // No figures (the flow step failed or did not run): not shown to fit.
    let o = checklist_py(out.path(), &["fits-80gb", "absent"]);
    assert!(!o.status.success());
    // Figures without CUDA's peaks (the CPU): unknown, so not shown to fit.
    let log = out.path().join("cpu.jsonl");
    std::fs::write(&log, "{\"step\": 0, \"loss\": 0.5, \"secs\": 1.0}\n").expect("write");
    let o = checklist_py(
        out.path(),
        &["step-seconds", log.to_str().expect("utf-8"), "cpu"],
    );
    assert!(o.status.success());
    assert!(!checklist_py(out.path(), &["fits-80gb", "cpu"])
        .status
        .success());
}

#[test]
fn the_gpu_checklist_keeps_to_its_budget_and_still_writes_the_summary() {
    let items = |out: &Path| -> Vec<(String, String)> {
        let text = std::fs::read_to_string(out.join("summary.json")).expect("summary.json");
        let summary: serde_json::Value = serde_json::from_str(&text).expect("JSON");
        summary["items"]
            .as_array()
            .expect("items")
            .iter()
            .map(|i| {
                (
                    i["item"].as_str().expect("name").to_string(),
                    i["status"].as_str().expect("status").to_string(),
                )
            })
            .collect()
    };
    // 20 s: less than the 15 s kept for the summary plus the 30 s an item
    // needs at least, so no item starts; the CUDA-only one still says why.
    let out = tempfile::tempdir().expect("tempdir");
    let o = run_checklist(
        out.path(),
        &[
            "--dry-run",
            "--budget",
            "20",
            "environment",
            "predict-full",
            "bench-model",
        ],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let got = items(out.path());
    assert_eq!(got.len(), 3, "{got:?}");
    assert_eq!(got[1].1, "skipped: no CUDA device");
    for (name, status) in [&got[0], &got[2]] {
        assert!(
            status.starts_with("skipped: not started: ")
                && status.contains("of the --budget 20s left")
                && status.contains("its limit: "),
            "{name}: {status}"
        );
    }
    // Enough for the item (the setup before it, importing torch, took over two
    // minutes on a machine loaded by other work): it runs and passes.
    let out = tempfile::tempdir().expect("tempdir");
    let o = run_checklist(out.path(), &["--dry-run", "--budget", "300", "environment"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");
    assert_eq!(
        items(out.path()),
        [("environment".to_string(), "ok".to_string())]
    );
    assert!(stderr.contains("== environment (at most "), "{stderr}");
    // A budget that is not whole seconds is refused before anything runs.
    for bad in [&["--budget", "ten"][..], &["--budget", "0"], &["--budget"]] {
        let out = tempfile::tempdir().expect("tempdir");
        let o = run_checklist(out.path(), &[&["--dry-run"][..], bad].concat());
        assert_eq!(o.status.code(), Some(2), "{bad:?}");
        let stderr = String::from_utf8_lossy(&o.stderr);
        assert!(
            stderr.contains("--budget") && stderr.contains("whole seconds"),
            "{stderr}"
        );
        assert!(!out.path().join("summary.json").exists());
    }
}
