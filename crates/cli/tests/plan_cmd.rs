//! The `bridgev2w` planning commands: `plan`, `plan-report` and
//! `plan-fidelity` with the perfect and the shipped models, and their bad
//! options.

use std::path::Path;
use std::process::Output;

use crate::common;

use common::run;

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

#[test]
fn plan_with_the_perfect_model_and_bad_plan_options() {
    let words = |line: &str| run(&line.split_whitespace().collect::<Vec<_>>());
    // A tiny run: 1 trial, 8 samples, 1 iteration, 2 actions, the view
    // limited and traced.
    let tmp = tempfile::tempdir().expect("plan test");
    let trace = tmp.path().join("trace");
    let line = format!(
        "plan --task reach --model perfect --trials 1 --samples 8 --elites 2 --iters 1 \
         --max-steps 2 --waypoints 1 --episode-frames 9 --view-margin 0.1 --trace {}",
        trace.display()
    );
    let out = words(&line);
    let stdout = String::from_utf8_lossy(&out.stdout);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    assert!(
        stdout.contains("reach: planner (perfect)")
            && stdout.contains("random actions")
            && stdout.contains("deg off"),
        "{stdout}"
    );
    assert!(stderr.contains("reach trial 0: planner"), "{stderr}");
    // The trace: a JSON line per trial, a row per executed step, and a
    // filmstrip of 3 frames (96 wide, 2-pixel gaps) by one row per step.
    let jsonl = std::fs::read_to_string(trace.join("trials.jsonl")).expect("trace");
    let t: serde_json::Value = serde_json::from_str(jsonl.trim()).expect("one JSON line");
    assert_eq!(t["trial"], 0);
    assert_eq!(t["task"], "reach");
    let steps = t["steps"].as_array().expect("steps");
    assert!(!steps.is_empty() && steps.len() <= 2, "{t}");
    for s in steps {
        assert!(
            s["observed_cost"].as_f64().is_some_and(f64::is_finite),
            "{s}"
        );
        assert!(s["task_error_m"].as_f64().is_some(), "{s}");
        assert_eq!(s["ee"].as_array().map(Vec::len), Some(7), "{s}");
    }
    assert_eq!(t["goal_tcp_m"].as_array().map(Vec::len), Some(4), "{t}");
    let png = std::fs::read(trace.join("trial-0.png")).expect("filmstrip");
    let (w, h, _) = bridgev2w_io::png::decode_rgb8(&png).expect("PNG");
    let rows = steps.len() as u32;
    assert_eq!((w, h), (3 * 96 + 4, rows * 64 + (rows - 1) * 2));
    // A trace is never overwritten.
    let out = words(&line);
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && e.contains("--trace") && e.contains("already exists"),
        "{e}"
    );
    // A margin that leaves nothing of the image.
    let out = words("plan --task reach --model perfect --trials 1 --view-margin 0.6");
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && e.contains("--view-margin") && e.contains("0.6"),
        "{e}"
    );
    // k > S.
    let out = words("plan --task reach --model perfect --samples 4 --elites 8");
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && e.contains("elite"), "{e}");
    // Unknown task in plan-report.
    let out = words("plan-report --tasks reach,fly --trials 1");
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success() && e.contains("fly"), "{e}");
    // An unknown engine, naming the choices.
    let out = words("plan --task reach --trials 1 --engine physx");
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && e.contains("builtin, mujoco"),
        "{e}"
    );
    // A trained-model folder without its files, before any planning.
    let out = words(&format!(
        "plan-report --tasks reach --trials 1 --trained {}",
        tmp.path().display()
    ));
    let e = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && e.contains("expected backbone/"),
        "{e}"
    );
}

/// `plan-report --trained DIR`: the shipped model plans and evaluates
/// policies next to the perfect one, each a row / table of its own.
#[test]
fn plan_report_with_the_shipped_trained_model() {
    let tmp = tempfile::tempdir().expect("plan-report test");
    let md = tmp.path().join("results.md");
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo-model");
    // The folder's own weights named as the planning weights: the row says so.
    let line = format!(
        "plan-report --tasks reach --trials 1 --samples 4 --elites 2 --iters 1 --max-steps 1 \
         --waypoints 0 --eval-trials 1 --denoise-steps 1 --plan-clip-frames 3 --trained {} \
         --plan-weights {} --section planning-shipped --out {}",
        model.display(),
        model.join("bridgev2w.safetensors").display(),
        md.display()
    );
    let out = run(&line.split_whitespace().collect::<Vec<_>>());
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-report test");
    // The heading names the planning weights too, as the table does.
    let heading = text
        .lines()
        .find(|l| l.starts_with("## "))
        .expect("a heading");
    assert!(
        heading.contains(": perfect, trained (`") && heading.contains("`, planning weights `"),
        "{heading}"
    );
    assert!(text.contains("| reach | perfect | "), "{text}");
    assert!(
        text.contains("| reach | trained (`") && text.contains("`, planning weights `"),
        "{text}"
    );
    // The planners predicted 3-frame clips (the model trained on 9).
    assert!(
        text.contains("each candidate predicted as a clip of 3 frames"),
        "{text}"
    );
    assert!(text.contains("#### Model: perfect"), "{text}");
    assert!(
        text.contains("#### Model: trained (`")
            && text.contains("(1 denoising steps, shared noise)"),
        "{text}"
    );
    assert!(
        text.contains("| world-model goal progress |")
            && text.contains("Goal progress vs synthetic-world success: MMRV"),
        "{text}"
    );
}

/// `plan-report --plan-weights FILE`: the planner loads that file (a broken
/// one stops the run, named), and it is refused up front where no trained
/// model plans or the file is missing.
#[test]
fn plan_report_plan_weights_are_the_planners() {
    let tmp = tempfile::tempdir().expect("plan-report test");
    let md = tmp.path().join("results.md");
    let model = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../assets/demo-model");
    let broken = tmp.path().join("broken-plan.safetensors");
    std::fs::write(&broken, b"not a safetensors file").expect("plan-report test");
    let missing = tmp.path().join("missing.safetensors");
    let common = "--tasks reach --trials 1 --samples 4 --elites 2 --iters 1 --max-steps 1 \
                  --waypoints 0 --eval-trials 1 --denoise-steps 1";
    for (models, weights, want) in [
        ("trained", &broken, "broken-plan.safetensors"),
        ("trained", &missing, "expected a BridgeV2W weights file"),
        ("perfect", &broken, "only a trained model that plans"),
    ] {
        let trained = match models {
            "trained" => format!("--trained {}", model.display()),
            _ => String::new(),
        };
        let line = format!(
            "plan-report {common} --models {models} {trained} --plan-weights {} --out {}",
            weights.display(),
            md.display()
        );
        let out = run(&line.split_whitespace().collect::<Vec<_>>());
        let e = stderr(&out);
        assert!(!out.status.success() && e.contains(want), "{line}: {e}");
        assert!(
            !md.exists(),
            "{line}: a failed report wrote {}",
            md.display()
        );
    }
}

/// `plan-report --models/--section`: the chosen models only, in their own
/// section; bad lists and names are refused before any planning.
#[test]
fn plan_report_models_and_section() {
    let words = |line: &str| run(&line.split_whitespace().collect::<Vec<_>>());
    let tmp = tempfile::tempdir().expect("plan-report test");
    let md = tmp.path().join("results.md");
    let out = words(&format!(
        "plan-report --models perfect --section planning-small --tasks reach --trials 1 \
         --samples 4 --elites 2 --iters 1 --max-steps 1 --waypoints 0 --eval-trials 1 --out {}",
        md.display()
    ));
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-report test");
    assert!(
        text.contains("<!-- section: planning-small -->")
            && !text.contains("<!-- section: planning -->"),
        "{text}"
    );
    assert!(
        text.contains(": perfect\n") && text.contains("| reach | perfect | "),
        "{text}"
    );
    // The section's figures, in the folder named after the results file.
    for name in [
        "planning-small-planner-vs-random.png",
        "planning-small-policy-evaluation.png",
    ] {
        let png = image::open(tmp.path().join("results/figures").join(name)).expect(name);
        assert!(png.width() > 100 && png.height() > 100, "{name}");
        assert!(
            text.contains(&format!("(results/figures/{name})")),
            "{text}"
        );
    }
    // --trials 0: the policy evaluation alone, in its own section.
    let out = words(&format!(
        "plan-report --models perfect --section policies --trials 0 --eval-trials 1 --out {}",
        md.display()
    ));
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-report test");
    let policies = text
        .split("<!-- section: policies -->")
        .nth(1)
        .expect("the policies section");
    assert!(
        policies.contains("## Policy evaluation in the synthetic world: perfect")
            && !policies.contains("Goal-image CEM-MPC")
            && policies.contains("| scripted(offset 50 mm) | "),
        "{text}"
    );
    assert!(text.contains("<!-- section: planning-small -->"), "{text}");
    // --eval-trials 0: the planning alone (no policy table, no policy figure).
    let out = words(&format!(
        "plan-report --models perfect --section plans --tasks reach --trials 1 \
         --samples 4 --elites 2 --iters 1 --max-steps 1 --waypoints 0 --eval-trials 0 --out {}",
        md.display()
    ));
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-report test");
    let plans = text
        .split("<!-- section: plans -->")
        .nth(1)
        .and_then(|s| s.split("<!-- end section: plans -->").next())
        .expect("the plans section");
    assert!(
        plans.contains("## Goal-image planning in the synthetic world: perfect")
            && plans.contains("| reach | perfect | ")
            && !plans.contains("Policy evaluation")
            && !plans.contains("plans-policy-evaluation.png"),
        "{plans}"
    );
    assert!(!tmp
        .path()
        .join("results/figures/plans-policy-evaluation.png")
        .exists());
    let out = words(&format!(
        "plan-report --models perfect --trials 0 --eval-trials 0 --out {}",
        md.display()
    ));
    let e = stderr(&out);
    assert!(
        !out.status.success() && e.contains("nothing to report"),
        "{e}"
    );
    for (line, want) in [
        ("--models trained", "needs --trained"),
        ("--models perfect,fly", "unknown model \"fly\""),
        ("--models perfect,perfect", "named twice"),
        ("--models random", "expected perfect or trained"),
        ("--section a/b", "--section \"a/b\""),
    ] {
        let out = words(&format!(
            "plan-report --tasks reach --trials 1 {line} --out {}",
            md.display()
        ));
        let e = stderr(&out);
        assert!(!out.status.success() && e.contains(want), "{line}: {e}");
    }
}

/// `plan-fidelity`: the perfect model orders candidates exactly as the
/// world does (Spearman 1); bad sizes are refused.
#[test]
fn plan_fidelity_of_the_perfect_model() {
    let words = |line: &str| run(&line.split_whitespace().collect::<Vec<_>>());
    let tmp = tempfile::tempdir().expect("plan-fidelity test");
    let md = tmp.path().join("results.md");
    let out = words(&format!(
        "plan-fidelity --model perfect --trials 2 --candidates 6 --out {}",
        md.display()
    ));
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-fidelity test");
    assert!(
        text.contains("<!-- section: planning-fidelity -->")
            && text.contains("| perfect | 1.00 ± 0.00 | "),
        "{text}"
    );
    assert!(
        stderr(&out).contains("reach trial 1: Spearman"),
        "{}",
        stderr(&out)
    );
    let out = words("plan-fidelity --model perfect --candidates 1");
    assert!(
        !out.status.success() && stderr(&out).contains("--candidates 1"),
        "{}",
        stderr(&out)
    );
    // A diffusion model's goal distances on the image pyramid, said in the
    // section; an unknown goal latent is refused with the choices.
    let out = words(&format!(
        "plan-fidelity --model random --trials 1 --candidates 3 --denoise-steps 1 \
         --goal-latent pyramid --device cpu --out {}",
        md.display()
    ));
    assert!(out.status.success(), "{}", stderr(&out));
    let text = std::fs::read_to_string(&md).expect("plan-fidelity test");
    assert!(
        text.contains("goal distances on a Gaussian pyramid of the image")
            && text.contains("| random | "),
        "{text}"
    );
    // A clip the random model's VAE cannot decode (it compresses time 4x).
    let out = words("plan-fidelity --model random --clip-frames 4 --device cpu");
    let e = stderr(&out);
    assert!(
        !out.status.success() && e.contains("frames") && e.contains("4k + 1"),
        "{e}"
    );
    let out = words("plan-fidelity --model random --goal-latent vae");
    let e = stderr(&out);
    assert!(
        !out.status.success() && e.contains("goal latent") && e.contains("model, pyramid"),
        "{e}"
    );
}

#[test]
fn eval_drift_with_the_perfect_model_is_exact_and_bad_sizes_are_refused() {
    // The perfect model is the world: no drift at any chunk, while copying
    // the first frame falls behind.
    let o = run(&[
        "eval-drift",
        "--task",
        "pick_place",
        "--trials",
        "2",
        "--chunks",
        "5",
        "--model",
        "perfect",
    ]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    let rows: Vec<&str> = out
        .lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("| chunk"))
        .collect();
    assert_eq!(rows.len(), 5, "{out}");
    for (k, row) in rows.iter().enumerate() {
        let cells: Vec<&str> = row.split('|').map(str::trim).collect();
        assert_eq!(cells[1], (k + 1).to_string(), "{row}");
        assert_eq!(cells[2], ((k + 1) * 8).to_string(), "{row}");
        assert_eq!((cells[3], cells[4]), ("100.00", "1.000"), "{row}");
        let copy: f64 = cells[6].parse().expect("copying's PSNR");
        assert!(copy < 40.0, "{row}");
        // Mask-IoU: the model's frame is the world's, so it scores the
        // segmenter's ceiling, which finds most of the robot.
        assert_eq!(cells[5], cells[8], "{row}");
        let ceiling: f64 = cells[8].parse().expect("the segmenter's ceiling");
        assert!(ceiling > 0.5, "{row}");
    }
    // By the last chunk the arm has left where it started: copying the
    // first frame finds less of it than the model.
    let last: Vec<&str> = rows[4].split('|').map(str::trim).collect();
    let copy_iou: f64 = last[7].parse().expect("copying's Mask-IoU");
    let iou: f64 = last[5].parse().expect("Mask-IoU");
    assert!(copy_iou < iou, "{}", rows[4]);
    assert!(out.contains("colour segmenter"), "{out}");
    let o = run(&["eval-drift", "--model", "perfect", "--chunks", "0"]);
    assert!(
        !o.status.success() && stderr(&o).contains("--chunks: 0: expected 1..=50 chunks"),
        "{}",
        stderr(&o)
    );
}

/// `eval-policy-rollout --calibrate-judge N`: the perfect model's rollouts
/// of the expert end on the goal image, so the floor is 0 and the judge
/// (and every rate) is the fixed one's; the calibration is printed and
/// written to the JSON; with --labels, or a quantile outside (0, 1], it is
/// refused.
#[test]
fn a_calibrated_judge_keeps_the_fixed_judge_for_the_perfect_model() {
    let d = tempfile::tempdir().expect("tmp");
    let json = d.path().join("rates.json");
    let args = |extra: &[&str]| {
        let mut a = vec![
            "eval-policy-rollout",
            "--task",
            "reach",
            "--trials",
            "2",
            "--episode-frames",
            "9",
            "--offsets-mm",
            "0,50",
        ];
        a.extend_from_slice(extra);
        run(&a)
    };
    let table = |o: &Output| -> Vec<String> {
        String::from_utf8_lossy(&o.stdout)
            .lines()
            .filter(|l| l.starts_with("| scripted"))
            .map(String::from)
            .collect()
    };
    let fixed = args(&[]);
    assert!(fixed.status.success(), "{}", stderr(&fixed));
    let calibrated = args(&[
        "--calibrate-judge",
        "2",
        "--json",
        json.to_str().expect("utf-8"),
    ]);
    assert!(calibrated.status.success(), "{}", stderr(&calibrated));
    assert_eq!(table(&fixed), table(&calibrated));
    assert_eq!(table(&fixed).len(), 2);
    let out = String::from_utf8_lossy(&calibrated.stdout);
    assert!(
        out.contains("judged above a floor of 0.000 (the 0.8 quantile")
            && out.contains("in 2 train episodes): ratio 0.500"),
        "{out}"
    );
    let j: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("parse");
    assert_eq!(j["judge_calibration"]["episodes"], 2);
    assert_eq!(j["judge_calibration"]["floor"], 0.0);
    let labels = d.path().join("labels.csv");
    std::fs::write(&labels, "policy,trial,success\n").expect("labels");
    let o = args(&[
        "--calibrate-judge",
        "2",
        "--labels",
        labels.to_str().expect("utf-8"),
    ]);
    assert!(
        !o.status.success()
            && stderr(&o).contains("--calibrate-judge")
            && stderr(&o).contains("--labels"),
        "{}",
        stderr(&o)
    );
    let o = args(&["--calibrate-judge", "2", "--calibration-quantile", "0"]);
    assert!(
        !o.status.success()
            && stderr(&o).contains("--calibration-quantile: 0: expected a quantile in (0, 1]"),
        "{}",
        stderr(&o)
    );
}
