//! `bridgev2w train` end to end: `bridgev2w synth` a tiny dataset, train three
//! steps on the `random:tiny` backbone, resume to five, and the errors a user meets first.

use crate::common;

use common::{ok, run, s, synth_tiny, TINY_MODEL_TOML};

#[test]
fn synth_then_train_three_steps_then_resume() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let data = d.join("data");
    synth_tiny(&data);
    let run_dir = d.join("run");
    let cfg = format!(
        r#"
{TINY_MODEL_TOML}
[data]
dataset = "{}"
split = "train"

[train]
out = "{}"
max_steps = 3
checkpoint_every = 2
warmup_steps = 2
lr = 1e-4
"#,
        s(&data),
        s(&run_dir)
    );
    let cfg_path = d.join("train.toml");
    std::fs::write(&cfg_path, cfg).expect("write config");
    ok(&run(&["train", s(&cfg_path), "--quiet"]));
    let metrics = std::fs::read_to_string(run_dir.join("metrics.jsonl")).expect("metrics");
    let lines: Vec<serde_json::Value> = metrics
        .lines()
        .map(|l| serde_json::from_str(l).expect("json line"))
        .collect();
    assert_eq!(lines.len(), 3);
    for (i, l) in lines.iter().enumerate() {
        assert_eq!(l["step"].as_u64(), Some(i as u64));
        for key in [
            "loss",
            "diffusion",
            "dynamics",
            "flow",
            "lr",
            "grad_norm",
            "secs",
        ] {
            assert!(l[key].as_f64().is_some_and(f64::is_finite), "{key} in {l}");
        }
        // The CUDA allocator's peaks only on CUDA.
        assert!(l.get("cuda_peak_reserved_mib").is_none(), "{l}");
    }
    assert!(run_dir.join("final/weights.safetensors").is_file());
    assert_eq!(
        std::fs::read_to_string(run_dir.join("checkpoints/latest")).expect("latest"),
        "step-00000003"
    );
    // Resume to 5 steps.
    ok(&run(&[
        "train",
        s(&cfg_path),
        "--quiet",
        "--max-steps",
        "5",
        "--resume",
        s(&run_dir),
    ]));
    let metrics = std::fs::read_to_string(run_dir.join("metrics.jsonl")).expect("metrics");
    assert_eq!(metrics.lines().count(), 5);
    // Score the run per split next to the copy-the-first-frame baseline.
    let json = d.join("scores.json");
    let o = run(&[
        "eval-run",
        s(&cfg_path),
        "--run",
        s(&run_dir),
        "--splits",
        "test,unseen_scene",
        "--steps",
        "2",
        "--max-videos",
        "1",
        "--json",
        s(&json),
        "--segmenter",
        "color",
        "--grids",
        s(&d.join("grids")),
    ]);
    ok(&o);
    // A grid per split: one clip (--max-videos 1) of 9 frames, first frame |
    // masks | prediction | ground truth, each 96x64 shown at twice the size.
    for split in ["test", "unseen_scene"] {
        let gif = d.join("grids").join(format!("{split}.gif"));
        let decoder = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(
            std::fs::File::open(&gif).expect("grid gif"),
        ))
        .expect("a GIF");
        use image::AnimationDecoder;
        let frames = decoder.into_frames().collect_frames().expect("frames");
        assert_eq!(frames.len(), 9, "{}", gif.display());
        assert_eq!(frames[0].buffer().dimensions(), (4 * 96 * 2, 64 * 2));
    }
    let table = String::from_utf8_lossy(&o.stdout);
    assert!(
        table.contains(
            "| split | videos | PSNR | dynamic PSNR | SSIM | Mask-IoU | copy-first-frame PSNR"
        ) && table.contains("| unseen_scene | 1 |"),
        "{table}"
    );
    let v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&json).expect("json")).expect("parse");
    assert_eq!(v["step"].as_u64(), Some(5));
    assert!(v["splits"][0]["psnr"].as_f64().is_some_and(f64::is_finite));
    let iou = v["splits"][0]["segmenter_mask_iou"]
        .as_f64()
        .expect("ceiling");
    assert!(iou > 0.0 && iou <= 1.0, "{v}");
    // The synthetic clips move: every method has a dynamic-region score.
    for key in [
        "dynamic_psnr",
        "baseline_dynamic_psnr",
        "autoencoder_dynamic_psnr",
    ] {
        assert!(
            v["splits"][0][key].as_f64().is_some_and(f64::is_finite),
            "{key}: {v}"
        );
    }
    // PSNR of each predicted frame (8 of the 9), for every method.
    for key in [
        "psnr_per_frame",
        "baseline_psnr_per_frame",
        "autoencoder_psnr_per_frame",
    ] {
        let v = v["splits"][0][key].as_array().expect(key);
        assert_eq!(v.len(), 8, "{key}");
        assert!(v.iter().all(|x| x.as_f64().is_some_and(f64::is_finite)));
    }
    // Side-by-side videos of two runs (here the same run twice): first frame
    // | masks | run 1 | run 2 | ground truth.
    let grids = d.join("docs/results/grids");
    ok(&run(&[
        "eval-grid",
        s(&cfg_path),
        "--run",
        s(&run_dir),
        "--compare",
        s(&cfg_path),
        s(&run_dir),
        "--out",
        s(&grids),
        "--splits",
        "test,unseen_scene",
        "--clips",
        "1",
        "--steps",
        "1",
    ]));
    for split in ["test", "unseen_scene"] {
        let decoder = image::codecs::gif::GifDecoder::new(std::io::BufReader::new(
            std::fs::File::open(grids.join(format!("{split}.gif"))).expect("grid gif"),
        ))
        .expect("a GIF");
        use image::AnimationDecoder;
        let frames = decoder.into_frames().collect_frames().expect("frames");
        assert_eq!(frames[0].buffer().dimensions(), (5 * 96 * 2, 64 * 2));
    }
    // The paper-layout table from the JSON, into a section of results.md
    // that keeps the rest of the file, with its figures next to it.
    let results = d.join("docs/results.md");
    std::fs::write(&results, "# Results\n\nhand-written notes\n").expect("write");
    let entry = format!("BridgeV2W={}", s(&json));
    let stage = format!("bridgev2w={}", s(&run_dir));
    ok(&run(&[
        "eval-report",
        "--entry",
        &entry,
        "--training-run",
        &stage,
        "--grids",
        s(&grids),
        "--out",
        s(&results),
    ]));
    let md = std::fs::read_to_string(&results).expect("results");
    assert!(
        md.contains("hand-written notes")
            && md.contains("<!-- section: video -->")
            && md.contains("***In-Domain*** (1 videos")
            && md.contains("| BridgeV2W (step 5) |")
            && md.contains("![Training loss per stage](results/figures/loss-curves.png)")
            && md.contains("![PSNR per predicted frame](results/figures/psnr-per-frame.png)")
            && md.contains("![test](results/grids/test.gif)"),
        "{md}"
    );
    for (name, size) in [
        ("loss-curves.png", (420, 300)),
        ("psnr-per-frame.png", (840, 300)),
    ] {
        let png = image::open(d.join("docs/results/figures").join(name)).expect(name);
        assert_eq!((png.width(), png.height()), size, "{name}");
    }
    let missing = format!("vae={}", s(&d.join("no-such-run")));
    let o = run(&[
        "eval-report",
        "--entry",
        &entry,
        "--training-run",
        &missing,
        "--out",
        s(&results),
    ]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("no-such-run/metrics.jsonl"), "{err}");
    let o = run(&["eval-report", "--entry", "nofile", "--out", s(&results)]);
    assert!(!o.status.success());
    assert!(String::from_utf8_lossy(&o.stderr).contains("expected NAME=FILE"));
    // Errors name the problem.
    std::fs::write(d.join("bad.toml"), "[train]\nlearning_rate = 1\n").expect("write");
    let o = run(&["train", s(&d.join("bad.toml"))]);
    assert!(!o.status.success());
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(err.contains("learning_rate"), "{err}");

    // A run killed (SIGKILL) mid-way and resumed gives the same loss curve as
    // an uninterrupted run, with every step logged once.
    let cfg_kill = std::fs::read_to_string(&cfg_path)
        .expect("config")
        .replace("max_steps = 3", "max_steps = 10");
    let kill_cfg = d.join("kill.toml");
    std::fs::write(&kill_cfg, cfg_kill).expect("write");
    let full_dir = d.join("full");
    ok(&run(&[
        "train",
        s(&kill_cfg),
        "--quiet",
        "--out",
        s(&full_dir),
    ]));
    let killed_dir = d.join("killed");
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_bridgev2w"))
        .args(["train", s(&kill_cfg), "--quiet", "--out", s(&killed_dir)])
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("spawn");
    let latest = killed_dir.join("checkpoints/latest");
    let t0 = std::time::Instant::now();
    while std::fs::read_to_string(&latest).map_or(true, |l| l.trim() != "step-00000004") {
        assert!(t0.elapsed().as_secs() < 300, "no step-4 checkpoint");
        assert!(
            child.try_wait().expect("wait").is_none(),
            "the run ended before it was killed"
        );
        std::thread::sleep(std::time::Duration::from_millis(20));
    }
    child.kill().expect("kill");
    child.wait().expect("reap");
    assert!(!killed_dir.join("final").exists(), "killed before the end");
    ok(&run(&[
        "train",
        s(&kill_cfg),
        "--quiet",
        "--out",
        s(&killed_dir),
        "--resume",
        s(&killed_dir),
    ]));
    let losses = |dir: &std::path::Path| -> Vec<(u64, f64)> {
        std::fs::read_to_string(dir.join("metrics.jsonl"))
            .expect("metrics")
            .lines()
            .map(|l| {
                let v: serde_json::Value = serde_json::from_str(l).expect("json");
                (
                    v["step"].as_u64().expect("step"),
                    v["loss"].as_f64().expect("loss"),
                )
            })
            .collect()
    };
    let (a, b) = (losses(&full_dir), losses(&killed_dir));
    assert_eq!(a.len(), 10);
    assert_eq!(
        b.iter().map(|x| x.0).collect::<Vec<_>>(),
        (0..10).collect::<Vec<u64>>(),
        "each step once"
    );
    for ((step, x), (_, y)) in a.iter().zip(&b) {
        assert!(
            (x - y).abs() <= 1e-6 * x.abs().max(1.0),
            "step {step}: uninterrupted {x} vs killed+resumed {y}"
        );
    }
}

#[test]
fn training_logs_read_back_with_tensorboards_own_reader() {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let data = d.join("data");
    synth_tiny(&data);
    let run_dir = d.join("run");
    let cfg_path = d.join("train.toml");
    std::fs::write(
        &cfg_path,
        format!(
            r#"
{TINY_MODEL_TOML}
[data]
dataset = "{}"

[train]
max_steps = 2
checkpoint_every = 1
preview_steps = 2
warmup_steps = 1
lr = 1e-4
"#,
            s(&data)
        ),
    )
    .expect("write config");
    ok(&run(&[
        "train",
        s(&cfg_path),
        "--quiet",
        "--out",
        s(&run_dir),
    ]));
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
    let o = std::process::Command::new(root.join(".venv/bin/python"))
        .arg(root.join("scripts/fixtures/read_tensorboard.py"))
        .arg(run_dir.join("tensorboard"))
        .output()
        .expect("run read_tensorboard.py");
    ok(&o);
    let tb: serde_json::Value = serde_json::from_slice(&o.stdout).expect("json");
    let metrics: Vec<serde_json::Value> = std::fs::read_to_string(run_dir.join("metrics.jsonl"))
        .expect("metrics")
        .lines()
        .map(|l| serde_json::from_str(l).expect("json line"))
        .collect();
    // Every metric, every step, as metrics.jsonl has it (float32 in the log).
    for key in [
        "loss",
        "diffusion",
        "dynamics",
        "flow",
        "lr",
        "grad_norm",
        "secs",
    ] {
        let series = tb["scalars"][format!("train/{key}")]
            .as_array()
            .unwrap_or_else(|| panic!("no train/{key} in {tb}"));
        assert_eq!(series.len(), metrics.len(), "train/{key}");
        for (point, m) in series.iter().zip(&metrics) {
            assert_eq!(point[0], m["step"], "train/{key}");
            let (got, want) = (
                point[1].as_f64().expect("value"),
                m[key].as_f64().expect(key),
            );
            assert!(
                (got - want).abs() <= 1e-6 * want.abs().max(1e-6),
                "train/{key} at step {}: {got} vs {want}",
                m["step"]
            );
        }
    }
    // A preview at each checkpoint: truth over prediction, 9 frames of 96x64.
    let images = tb["images"]["preview/truth_over_prediction"]
        .as_array()
        .unwrap_or_else(|| panic!("no preview in {tb}"));
    assert_eq!(images.len(), 2);
    for img in images {
        assert_eq!(
            (img[1].as_u64(), img[2].as_u64()),
            (Some(9 * 96), Some(2 * 64))
        );
    }
}

/// The cells of `bench flow`'s row for `mode`.
fn flow_row(text: &str, mode: &str) -> Vec<String> {
    let line = text
        .lines()
        .find(|l| l.starts_with(&format!("| {mode} |")))
        .unwrap_or_else(|| panic!("no {mode} row in {text}"));
    line.trim_matches('|')
        .split('|')
        .map(|c| c.trim().to_owned())
        .collect()
}

/// `bench flow` on the tiny VAE: every replay of the flow loss's backward
/// gives autograd's loss and gradient (to float rounding), the batch-by-batch
/// replay in less memory than autograd through the whole decode, and the
/// unit-by-unit one in less again (the caching allocator's peaks).
#[test]
fn bench_flow_replays_give_autograds_gradient_in_less_memory() {
    let o = common::run(&[
        "bench", "flow", "--vae", "tiny", "--frames", "17", "--height", "64", "--width", "96",
    ]);
    common::ok(&o);
    let text = String::from_utf8_lossy(&o.stdout).to_string();
    let row = |mode: &str| flow_row(&text, mode);
    let peak = |mode: &str| -> f64 {
        row(mode)[2]
            .split_whitespace()
            .next()
            .and_then(|p| p.parse().ok())
            .unwrap_or_else(|| panic!("{text}"))
    };
    assert_eq!(row("autograd")[3], "-", "autograd keeps no record: {text}");
    for mode in ["recorded", "stepwise"] {
        assert_eq!(row(mode)[4], row("autograd")[4], "the same loss: {text}");
        let err: f64 = row(mode)[5].parse().expect("gradient error");
        assert!(err < 1e-5, "{mode}: gradient error {err}: {text}");
        let kept: f64 = row(mode)[3].parse().expect("record MiB");
        assert!(kept > 0.0 && kept < peak(mode), "{mode}: {text}");
        // The CUDA allocator's peak only on CUDA.
        assert_eq!(row(mode)[6], "-", "{text}");
    }
    assert!(
        peak("stepwise") < peak("recorded") && peak("recorded") < peak("autograd"),
        "{text}"
    );
}

/// Tiled, the stepwise replay keeps no tile's conv caches between the decode
/// and the backward (each tile's are computed again at its replay): its
/// record is a fraction of the batch-by-batch one's, for the same loss.
#[test]
fn bench_flow_tiled_stepwise_record_keeps_no_caches() {
    let o = common::run(&[
        "bench",
        "flow",
        "--vae",
        "tiny",
        "--frames",
        "17",
        "--height",
        "64",
        "--width",
        "96",
        "--tile",
        "48x40",
        "--modes",
        "recorded,stepwise",
    ]);
    common::ok(&o);
    let text = String::from_utf8_lossy(&o.stdout).to_string();
    let cells = |mode: &str| flow_row(&text, mode);
    let kept = |mode: &str| -> f64 { cells(mode)[3].parse().expect("record MiB") };
    assert!(text.contains("tiles of 48x40 px"), "{text}");
    assert_eq!(cells("recorded")[4], cells("stepwise")[4], "{text}");
    assert!(
        kept("stepwise") > 0.0 && kept("stepwise") * 2.0 < kept("recorded"),
        "{text}"
    );
}

/// Sizes no machine gives inside `bench flow`: clean errors naming the
/// sizes and what lowers the memory; no panic, no backtrace.
#[test]
fn bench_flow_out_of_memory_is_a_clean_error_naming_the_shapes() {
    // Beyond the largest side: refused by name.
    let o = common::run(&[
        "bench", "flow", "--vae", "tiny", "--frames", "17", "--height", "16777216", "--width",
        "16777216", "--modes", "stepwise",
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{e}");
    assert!(
        e.contains("--height 16777216: at most 8192 pixels is supported"),
        "{e}"
    );
    assert!(!e.contains("panicked") && !e.contains("frame #"), "{e}");
    // Within it but beyond this machine's memory: refused up front with the
    // estimate, what is available and what lowers it (libtorch's own
    // out-of-memory, reachable on a GPU, maps to the same kind of error).
    let o = common::run(&[
        "bench", "flow", "--vae", "tiny", "--frames", "17", "--height", "8192", "--width", "8192",
        "--modes", "stepwise",
    ]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success(), "{e}");
    assert!(
        e.contains("the flow bench's clip of 17 frames at 8192x8192 needs at least")
            && e.contains("is available")
            && e.contains("--tile"),
        "{e}"
    );
    assert!(!e.contains("panicked") && !e.contains("frame #"), "{e}");
}

/// A clip the causal VAE cannot return at its length (an even count of
/// latent frames decodes to more frames) is refused before any work, by the
/// VAE's own rule (`VaeConfig::frames_error`), as the model refuses it.
#[test]
fn bench_flow_refuses_frames_the_vae_does_not_round_trip() {
    for (frames, expected) in [
        (
            "5",
            "frames: 5: 2 latent frames, an even count, which the causal VAE decodes to 8 frames",
        ),
        ("6", "frames: 6: expected 4k + 1"),
        ("1", "frames: 1: expected at least 2"),
    ] {
        let o = common::run(&["bench", "flow", "--vae", "tiny", "--frames", frames]);
        let e = String::from_utf8_lossy(&o.stderr);
        assert!(!o.status.success() && e.contains(expected), "{frames}: {e}");
        assert!(
            !e.contains("panicked") && !e.contains("flow loss: videos"),
            "{e}"
        );
    }
}

#[test]
fn bench_flow_refuses_tiles_that_do_not_join() {
    let o = common::run(&["bench", "flow", "--vae", "tiny", "--tile", "64x96"]);
    assert!(!o.status.success());
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        e.contains("`tile`: 64x96 px") && e.contains("would not join") && e.contains("240x360"),
        "{e}"
    );
    let o = common::run(&["bench", "flow", "--tile", "240"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("HEIGHTxWIDTH"), "{e}");
    let o = common::run(&["bench", "flow", "--flow", "raft"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("\"raft\"") && e.contains("raft_large"),
        "{e}"
    );
}
