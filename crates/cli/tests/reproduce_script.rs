//! `scripts/reproduce-synthetic.sh`, the CPU proof run: rerunning it keeps
//! the stages made from the same inputs, redoes (after moving aside) every
//! stage whose inputs changed and the stages downstream of it, and exports a
//! demo config whose paths are relative to the repository root. Run on a copy
//! of the script with a fake `bridgev2w` that records its calls.

use crate::common;

use common::trained;
use std::fs;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::Command;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// A fake `bridgev2w`: appends `COMMAND NAME` to `calls.log` (`train NAME
/// --resume` for a resumed run, `synth --engine mujoco`, `eval-report
/// --grids DIR --section NAME`, `plan-report --engine E --section NAME`) and makes the
/// files the script checks (`synth`'s `meta/info.json`, `train`'s
/// `final/weights.safetensors`, `final/backbone/` and `checkpoints/`,
/// `eval-grid`'s GIFs).
const FAKE: &str = r#"#!/usr/bin/env bash
set -eu
log="$(dirname "$0")/calls.log"
case $1 in
synth)
    out=$3
    mkdir -p "$out/meta" "$out/labels" && touch "$out/meta/info.json"
    engine=""
    [[ " $* " == *" --engine mujoco --robot franka-robotiq "* ]] && engine=" --engine mujoco"
    echo "synth$engine" >>"$log" ;;
train)
    out=$(sed -n 's/^out = "\(.*\)"$/\1/p' "$2")
    mkdir -p "$out/final/backbone" "$out/checkpoints" && touch "$out/final/weights.safetensors"
    resume=""
    [[ " $* " == *" --resume "* ]] && resume=" --resume"
    echo "train $(basename "$out")$resume" >>"$log" ;;
eval-run)
    shift
    while [[ $# -gt 0 ]]; do [[ $1 == --json ]] && echo '{}' >"$2"; shift; done
    echo "eval-run" >>"$log" ;;
eval-grid)
    shift
    while [[ $# -gt 0 ]]; do
        [[ $1 == --out ]] && mkdir -p "$2" && for s in test unseen_camera unseen_scene; do touch "$2/$s.gif"; done
        shift
    done
    echo "eval-grid" >>"$log" ;;
eval-report)
    shift
    grids="" section=""
    while [[ $# -gt 0 ]]; do
        [[ $1 == --grids ]] && grids=" --grids $2"
        [[ $1 == --section ]] && section=" --section $2"
        shift
    done
    echo "eval-report$grids$section" >>"$log" ;;
plan-report)
    engine="" section=""
    while [[ $# -gt 0 ]]; do
        [[ $1 == --engine ]] && engine=" --engine $2"
        [[ $1 == --section ]] && section=" --section $2"
        shift
    done
    echo "plan-report$engine$section" >>"$log" ;;
esac
"#;

fn sandbox() -> tempfile::TempDir {
    let root = tempfile::tempdir().expect("tempdir");
    fs::create_dir_all(root.path().join("scripts/lib")).expect("mkdir");
    for script in ["reproduce-synthetic.sh", "export-demo.sh", "lib/stages.sh"] {
        fs::copy(
            repo().join("scripts").join(script),
            root.path().join("scripts").join(script),
        )
        .expect("copy script");
    }
    let fake = root.path().join("bridgev2w");
    fs::write(&fake, FAKE).expect("write fake");
    fs::set_permissions(&fake, fs::Permissions::from_mode(0o755)).expect("chmod");
    root
}

/// Runs the script in `root` with `env`; returns the fake's calls of this run.
fn run(root: &Path, env: &[(&str, &str)]) -> Vec<String> {
    common::run_script(root, "reproduce-synthetic.sh", "runs/r", env)
}

fn evaluated(calls: &[String]) -> usize {
    calls.iter().filter(|c| *c == "eval-run").count()
}

#[test]
fn reruns_keep_what_is_done_and_redo_what_changed() {
    let root = sandbox();
    let r = root.path();
    let first = run(r, &[]);
    assert_eq!(first[0], "synth");
    assert_eq!(
        trained(&first),
        [
            "vae-image",
            "vae",
            "prior",
            "vae-decoder",
            "bridgev2w",
            "ablation-action-mlp",
            "bridgev2w-short"
        ]
    );
    // The planning model continues the fine-tuned weights on 3-frame clips;
    // a larger budget of its own continues it alone from its checkpoints.
    let short = fs::read_to_string(r.join("runs/r/configs/bridgev2w-short.toml")).expect("config");
    for line in [
        "init_weights = \"runs/r/bridgev2w/final/weights.safetensors\"",
        "backbone = \"runs/r/vae-decoder/final/backbone\"",
        "frames = 3",
        "max_steps = 400",
    ] {
        assert!(short.contains(&format!("\n{line}\n")), "{line}: {short}");
    }
    bridgev2w_train::config::TrainConfig::from_toml(&short).expect("a valid config");
    assert_eq!(
        trained(&run(r, &[("SHORT_STEPS", "500")])),
        ["bridgev2w-short --resume"]
    );
    // The results' preamble describes the planning stage with its budget.
    let preamble = fs::read_to_string(r.join("runs/r/preamble.md")).expect("preamble");
    assert!(
        preamble.contains("(stage `bridgev2w-short`")
            && preamble.contains("continued 500 steps on 3-frame clips"),
        "{preamble}"
    );
    // Back to the default, smaller budget: it starts over.
    assert_eq!(trained(&run(r, &[])), ["bridgev2w-short"]);
    // BridgeV2W with the static scene kept (the default KEEP_STATIC=0) and
    // with every pixel generated, then the ablation.
    assert_eq!(evaluated(&first), 3, "{first:?}");
    // The side-by-side GIFs once, next to the results file, and linked.
    let grids = |calls: &[String]| calls.iter().filter(|c| *c == "eval-grid").count();
    assert_eq!(grids(&first), 1, "{first:?}");
    assert_eq!(
        first.last().map(String::as_str),
        Some("eval-report --grids results/grids --section video"),
        "{first:?}"
    );
    // Same inputs: nothing is trained or evaluated again.
    let second = run(r, &[]);
    assert!(!second.contains(&"synth".to_string()), "{second:?}");
    assert!(trained(&second).is_empty(), "{second:?}");
    assert_eq!(evaluated(&second), 0, "{second:?}");
    assert_eq!(grids(&second), 0, "{second:?}");
    // Another evaluation budget: only the evaluations and grids are redone.
    let more = run(r, &[("EVAL_STEPS", "3")]);
    assert!(trained(&more).is_empty(), "{more:?}");
    assert_eq!(evaluated(&more), 3, "{more:?}");
    assert_eq!(grids(&more), 1, "{more:?}");
    // Another results file: its own grids are drawn (the grids of the
    // other file's folder are not taken for them), nothing else is redone.
    let elsewhere = run(r, &[("EVAL_STEPS", "3"), ("RESULTS", "other.md")]);
    assert!(trained(&elsewhere).is_empty(), "{elsewhere:?}");
    assert_eq!(evaluated(&elsewhere), 0, "{elsewhere:?}");
    assert_eq!(grids(&elsewhere), 1, "{elsewhere:?}");
    // Without keeping the static scene: the two kept evaluations and the
    // grids are redone, the row of every pixel generated is not needed.
    let plain = run(r, &[("EVAL_STEPS", "3"), ("KEEP_STATIC", "")]);
    assert!(trained(&plain).is_empty(), "{plain:?}");
    assert_eq!(evaluated(&plain), 2, "{plain:?}");
    assert_eq!(grids(&plain), 1, "{plain:?}");
    // A larger decoder budget: the decoder stage continues from its
    // checkpoints; the fine-tunings (trained over the prior's backbone) are
    // kept, every evaluation and the grids (made with its decoder) redone,
    // and the planning model (trained over the decoder stage's backbone).
    let decoder = run(
        r,
        &[
            ("EVAL_STEPS", "3"),
            ("KEEP_STATIC", ""),
            ("DECODER_STEPS", "500"),
        ],
    );
    assert_eq!(
        trained(&decoder),
        ["vae-decoder --resume", "bridgev2w-short"],
        "{decoder:?}"
    );
    assert_eq!(evaluated(&decoder), 2, "{decoder:?}");
    assert_eq!(grids(&decoder), 1, "{decoder:?}");
    let eval_cfg = fs::read_to_string(r.join("runs/r/configs/bridgev2w-eval.toml")).expect("eval");
    assert!(
        eval_cfg.contains("backbone = \"runs/r/vae-decoder/final/backbone\"")
            && !eval_cfg.contains("prior/final"),
        "{eval_cfg}"
    );
    let dec_cfg = fs::read_to_string(r.join("runs/r/configs/vae-decoder.toml")).expect("decoder");
    assert!(
        dec_cfg.contains("backbone = \"runs/r/prior/final/backbone\"")
            && dec_cfg.contains("vae_parts = \"decoder\""),
        "{dec_cfg}"
    );
    // Another prior budget: the prior and both fine-tunings are redone, the
    // autoencoders kept; the old prior is moved aside, not deleted.
    let third = run(r, &[("PRIOR_STEPS", "7")]);
    assert_eq!(
        trained(&third),
        [
            "prior",
            "vae-decoder",
            "bridgev2w",
            "ablation-action-mlp",
            "bridgev2w-short"
        ]
    );
    assert_eq!(evaluated(&third), 3, "{third:?}");
    // The wall-time table keeps the stages kept from earlier runs, once each.
    let timings = fs::read_to_string(r.join("runs/r/timings.tsv")).expect("timings");
    let stages: Vec<&str> = timings
        .lines()
        .filter_map(|l| l.split('\t').next())
        .collect();
    for name in ["synth", "vae-image", "vae", "prior", "bridgev2w"] {
        assert_eq!(
            stages.iter().filter(|s| **s == name).count(),
            1,
            "{timings}"
        );
    }
    let stale: Vec<String> = fs::read_dir(r.join("runs/r"))
        .expect("ls")
        .filter_map(|e| e.ok()?.file_name().into_string().ok())
        .filter(|n| n.contains(".stale-"))
        .collect();
    assert!(
        stale.iter().any(|n| n.starts_with("prior.stale-"))
            && stale.iter().any(|n| n.starts_with("bridgev2w.stale-")),
        "{stale:?}"
    );
    // A larger prior budget: the prior continues from its checkpoints (not
    // moved aside), the fine-tunings downstream are redone.
    let stale_priors = || {
        fs::read_dir(r.join("runs/r"))
            .expect("ls")
            .filter_map(|e| e.ok()?.file_name().into_string().ok())
            .filter(|n| n.starts_with("prior.stale-"))
            .count()
    };
    let before = stale_priors();
    let longer = run(r, &[("PRIOR_STEPS", "9")]);
    assert_eq!(
        trained(&longer),
        [
            "prior --resume",
            "vae-decoder",
            "bridgev2w",
            "ablation-action-mlp",
            "bridgev2w-short"
        ]
    );
    assert_eq!(stale_priors(), before, "the prior was moved aside");
    // A smaller one cannot continue: the prior is redone from scratch.
    let shorter = run(r, &[("PRIOR_STEPS", "8")]);
    assert_eq!(
        trained(&shorter),
        [
            "prior",
            "vae-decoder",
            "bridgev2w",
            "ablation-action-mlp",
            "bridgev2w-short"
        ]
    );
    // The default recipe: the wide transformer (a fresh one for the prior,
    // model.transformer) and link-coded masks for BridgeV2W only.
    let prior = fs::read_to_string(r.join("runs/r/configs/prior.toml")).expect("prior config");
    assert!(
        prior.contains("\ntransformer = \"small2x-wide\"\nlora_rank"),
        "{prior}"
    );
    let bw = || fs::read_to_string(r.join("runs/r/configs/bridgev2w.toml")).expect("config");
    let ablation =
        || fs::read_to_string(r.join("runs/r/configs/ablation-action-mlp.toml")).expect("ablation");
    assert!(bw().contains("\nmask_coding = \"links\"\n"), "{}", bw());
    assert!(!ablation().contains("mask_coding"), "{}", ablation());
    // Another transformer width: the autoencoders (the same VAE) are kept,
    // the prior of small2x keeps its backbone's own transformer.
    let narrow = [("PRIOR_STEPS", "8"), ("PRESET", "small2x")];
    let run_narrow = |coding: &str| run(r, &[narrow[0], narrow[1], ("MASK_CODING", coding)]);
    assert_eq!(
        trained(&run_narrow("links")),
        [
            "prior",
            "vae-decoder",
            "bridgev2w",
            "ablation-action-mlp",
            "bridgev2w-short"
        ]
    );
    let prior = fs::read_to_string(r.join("runs/r/configs/prior.toml")).expect("prior config");
    assert!(!prior.contains("transformer ="), "{prior}");
    // The paper's binary masks: only BridgeV2W is fine-tuned again (the
    // ablation has no masks), and its config has no coding line (the
    // fingerprints of runs made before the setting existed).
    let binary = run_narrow("binary");
    assert_eq!(
        trained(&binary),
        ["bridgev2w", "bridgev2w-short"],
        "{binary:?}"
    );
    assert!(!bw().contains("mask_coding"), "{}", bw());
    assert_eq!(
        trained(&run_narrow("links")),
        ["bridgev2w", "bridgev2w-short"]
    );
    // A dataset written before synth stored link labels is written again
    // (same arguments, same episodes): nothing trained on it is redone.
    fs::remove_dir_all(r.join("runs/r/synth/labels")).expect("rm labels");
    let rewritten = run_narrow("links");
    assert_eq!(rewritten[0], "synth", "{rewritten:?}");
    assert!(trained(&rewritten).is_empty(), "{rewritten:?}");
    // An unknown coding is refused before anything runs.
    let o = Command::new("bash")
        .arg(r.join("scripts/reproduce-synthetic.sh"))
        .arg("runs/r")
        .env("BRIDGEV2W", r.join("bridgev2w"))
        .env("MASK_CODING", "depth")
        .output()
        .expect("run bash");
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("MASK_CODING=depth"));
    // Another dataset: everything is redone.
    let fourth = run(r, &[("PRIOR_STEPS", "7"), ("EPISODES", "9,1,1,1")]);
    assert_eq!(fourth[0], "synth");
    assert_eq!(trained(&fourth).len(), 7, "{fourth:?}");
}

#[test]
fn the_exported_demo_config_names_repository_paths() {
    let root = sandbox();
    let r = root.path();
    // The fake's weights are empty files: kept as they are, not halved.
    run(r, &[("EXPORT_DEMO", "1"), ("HALF_WEIGHTS", "0")]);
    let cfg = fs::read_to_string(r.join("assets/demo-model/train-config.toml")).expect("config");
    assert!(
        cfg.contains("backbone = \"assets/demo-model/backbone\""),
        "{cfg}"
    );
    assert!(cfg.contains("dataset = \"runs/r/synth\""), "{cfg}");
    assert!(!cfg.contains(&r.display().to_string()), "{cfg}");
    // It parses as a training config as it stands.
    bridgev2w_train::config::TrainConfig::from_toml(&cfg).expect("a valid config");
    assert!(r.join("assets/demo-model/backbone").is_dir());
    // The planning model with its config, paths as the fine-tuning's.
    assert!(r
        .join("assets/demo-model/bridgev2w-plan.safetensors")
        .is_file());
    let plan = fs::read_to_string(r.join("assets/demo-model/plan-config.toml")).expect("config");
    assert!(
        plan.contains("backbone = \"assets/demo-model/backbone\"")
            && plan.contains("frames = 3")
            && !plan.contains(&r.display().to_string()),
        "{plan}"
    );
    bridgev2w_train::config::TrainConfig::from_toml(&plan).expect("a valid config");
}

/// `ENGINE=mujoco` (issue 72): the dataset from `synth --engine mujoco`
/// with the real-mesh robot, the table and GIFs in their own places, and
/// the planning stages in MuJoCo (the perfect model, then the run's own
/// model exported to OUT/model), kept on a rerun and redone when their
/// budget changes.
#[test]
fn the_mujoco_study_synthesises_and_plans_in_mujoco() {
    let root = sandbox();
    let r = root.path();
    let env = [
        ("ENGINE", "mujoco"),
        ("BRIDGEV2W_MUJOCO_PYTHON", "/no/such/python"),
        ("PLAN_TRIALS", "2"),
    ];
    let first = run(r, &env);
    assert_eq!(first[0], "synth --engine mujoco", "{first:?}");
    let planned: Vec<&String> = first
        .iter()
        .filter(|c| c.starts_with("plan-report"))
        .collect();
    assert_eq!(
        planned,
        [
            "plan-report --engine mujoco --section planning-mujoco",
            "plan-report --engine mujoco --section planning-mujoco-trained"
        ],
        "{first:?}"
    );
    assert!(
        first.contains(
            &"eval-report --grids results/grids-mujoco --section video-mujoco".to_string()
        ),
        "{first:?}"
    );
    // The run's model, as a model folder, its config naming its backbone.
    let config = fs::read_to_string(r.join("runs/r/model/train-config.toml")).expect("config");
    assert!(config.contains("\"runs/r/model/backbone\""), "{config}");
    assert!(r.join("runs/r/model/bridgev2w-plan.safetensors").is_file());
    // The preamble names the engine.
    let preamble = fs::read_to_string(r.join("runs/r/preamble.md")).expect("preamble");
    assert!(
        preamble.contains("simulated and rendered by MuJoCo"),
        "{preamble}"
    );
    // Rerun: nothing again; a larger budget: both planning stages again.
    let second = run(r, &env);
    assert!(
        !second
            .iter()
            .any(|c| c.starts_with("plan-report") || c.starts_with("synth")),
        "{second:?}"
    );
    let more = run(r, &[env[0], env[1], ("PLAN_TRIALS", "3")]);
    assert_eq!(
        more.iter().filter(|c| c.starts_with("plan-report")).count(),
        2,
        "{more:?}"
    );
    // The built-in world's run plans nothing unless asked.
    let builtin = sandbox();
    let calls = run(builtin.path(), &[]);
    assert!(
        !calls.iter().any(|c| c.starts_with("plan-report")),
        "{calls:?}"
    );
}
