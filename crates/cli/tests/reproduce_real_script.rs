//! `scripts/reproduce-real-droid.sh`, the real-video experiment: its stages
//! in order (calibration, conversion with the episode split, the three
//! trainings, evaluations, grids, the results section), its configs valid,
//! and a rerun keeping what is done. Run on a copy of the script with a fake
//! `bridgev2w` that records its calls, over a fake Ctrl-World folder.

use crate::common;

use common::trained;
use std::fs;
use std::os::unix::fs::PermissionsExt;
use std::path::{Path, PathBuf};
use std::process::Command;

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../..")
}

/// A fake `bridgev2w`: appends a line per call to `calls.log` (the whole
/// command line for `convert` and `eval-report`) and makes the files the
/// script reads.
const FAKE: &str = r#"#!/usr/bin/env bash
set -eu
log="$(dirname "$0")/calls.log"
out_of() { while [[ $# -gt 0 ]]; do [[ $1 == --out ]] && echo "$2"; shift; done; }
case $1 in
calibrate)
    out=$(out_of "$@")
    mkdir -p "$out" && echo '{}' >"$out/camera.json"
    echo '{"checked_episodes_mean_iou": 0.5}' >"$out/residuals.json"
    echo "calibrate $(basename "$out") $(grep -o -- '--video [^ ]*' <<<"$*" | wc -l) fit" >>"$log" ;;
convert)
    out=$(out_of "$@")
    mkdir -p "$out/meta" && touch "$out/meta/info.json"
    echo '{"skipped": [1, 2]}' >"$out/skipped.json"
    shift
    echo "convert $*" >>"$log" ;;
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
    out=$(out_of "$@")
    mkdir -p "$out" && touch "$out/test.gif" "$out/unseen_camera.gif"
    echo "eval-grid" >>"$log" ;;
eval-report)
    shift
    echo "eval-report $*" >>"$log" ;;
esac
"#;

/// A copy of the script and the fake binary, a fake DROID folder with the
/// rig's collections (empty files: the fake reads none) and a prior folder.
fn sandbox() -> tempfile::TempDir {
    let root = tempfile::tempdir().expect("tempdir");
    let r = root.path();
    fs::create_dir_all(r.join("scripts/lib")).expect("mkdir");
    for script in ["reproduce-real-droid.sh", "lib/stages.sh"] {
        fs::copy(
            repo().join("scripts").join(script),
            r.join("scripts").join(script),
        )
        .expect("copy script");
    }
    let fake = r.join("bridgev2w");
    fs::write(&fake, FAKE).expect("write fake");
    fs::set_permissions(&fake, fs::Permissions::from_mode(0o755)).expect("chmod");
    let droid = r.join("droid");
    let episodes = [
        ("droid_new_setup", (1..=13).collect::<Vec<_>>()),
        ("droid_new_setup_full/drawer", (0..=4).collect()),
        ("droid_new_setup_full/laptop", (0..=4).collect()),
        ("droid_new_setup_full/pickplace", (0..=9).collect()),
        ("droid_subset", vec![1]),
    ];
    for (collection, ids) in episodes {
        for id in ids {
            let ann = droid.join(collection).join("annotation/val");
            let vid = droid.join(collection).join(format!("videos/val/{id:04}"));
            fs::create_dir_all(&ann).expect("mkdir");
            fs::create_dir_all(&vid).expect("mkdir");
            fs::write(ann.join(format!("{id:04}.json")), "{}").expect("write");
        }
    }
    fs::create_dir_all(r.join("prior")).expect("mkdir");
    root
}

fn run(root: &Path, env: &[(&str, &str)]) -> Vec<String> {
    let (droid, prior) = (root.join("droid"), root.join("prior"));
    let mut all = vec![
        ("DROID", droid.to_str().expect("utf-8")),
        ("PRIOR", prior.to_str().expect("utf-8")),
    ];
    all.extend_from_slice(env);
    common::run_script(root, "reproduce-real-droid.sh", "runs/real", &all)
}

#[test]
fn the_real_video_experiment_runs_its_stages_in_order_and_resumes() {
    let root = sandbox();
    let r = root.path();
    let first = run(r, &[]);
    assert_eq!(first[0], "calibrate calibrate-ext1 3 fit");
    assert_eq!(first[1], "calibrate calibrate-ext2 3 fit");
    let convert = first[2].as_str();
    assert!(
        convert.starts_with("convert --format ctrl-world "),
        "{convert}"
    );
    // Every rig episode (not droid_subset), the held-out ones as test
    // (camera 1) and unseen_camera (camera 2), camera 2 of the rest not
    // converted.
    for part in [
        "--split train",
        "droid_new_setup_full/pickplace/val/0009",
        "--split-rule droid_new_setup/val/0002:ext1=test",
        "--split-rule droid_new_setup/val/0002:ext2=unseen_camera",
        "--split-rule *:ext2=-",
        "--width 96 --height 64",
    ] {
        assert!(convert.contains(part), "{part}: {convert}");
    }
    assert!(!convert.contains("droid_subset"), "{convert}");
    assert_eq!(
        trained(&first),
        [
            "bridgev2w",
            "ablation-action-mlp",
            "scratch-vae-image",
            "scratch-vae",
            "scratch-prior",
            "bridgev2w-scratch"
        ]
    );
    // BridgeV2W kept-static and every pixel generated, the ablation, and
    // BridgeV2W from scratch; then the grids and the section.
    assert_eq!(first.iter().filter(|c| *c == "eval-run").count(), 4);
    let report = first.last().expect("calls");
    for part in [
        "--section real-video",
        "--grids results/grids-real",
        "BridgeV2W from scratch (real frames only)=",
    ] {
        assert!(report.contains(part), "{part}: {report}");
    }
    // The configs are valid training configs.
    for name in [
        "bridgev2w",
        "ablation-action-mlp",
        "scratch-vae-image",
        "scratch-vae",
        "scratch-prior",
        "bridgev2w-scratch",
    ] {
        let text =
            fs::read_to_string(r.join(format!("runs/real/configs/{name}.toml"))).expect("config");
        bridgev2w_train::config::TrainConfig::from_toml(&text)
            .unwrap_or_else(|e| panic!("{name}: {e}\n{text}"));
    }
    let preamble = fs::read_to_string(r.join("runs/real/preamble.md")).expect("preamble");
    assert!(preamble.contains("0.500 (camera 1)"), "{preamble}");
    assert!(
        preamble.contains("the 33 DROID episodes") && preamble.contains("31 distinct"),
        "{preamble}"
    );
    // The grids draw every trained arm.
    assert!(first.iter().any(|c| c == "eval-grid"), "{first:?}");
    // Same inputs: nothing is calibrated, converted, trained or evaluated
    // again; only the section is rewritten.
    let second = run(r, &[]);
    assert_eq!(second.len(), 1, "{second:?}");
    assert!(second[0].starts_with("eval-report"), "{second:?}");
    // A larger fine-tuning budget continues the fine-tunings from their
    // checkpoints; without the scratch arm its stages are not run.
    let more = run(r, &[("FT_STEPS", "2500"), ("SCRATCH", "0")]);
    assert_eq!(
        trained(&more),
        ["bridgev2w --resume", "ablation-action-mlp --resume"],
        "{more:?}"
    );
    assert!(!more.last().expect("calls").contains("from scratch"));
    // A missing DROID folder is refused by name.
    let o = Command::new("bash")
        .arg(r.join("scripts/reproduce-real-droid.sh"))
        .env("BRIDGEV2W", r.join("bridgev2w"))
        .env("DROID", r.join("absent"))
        .output()
        .expect("run bash");
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("absent is not a folder"));
}
