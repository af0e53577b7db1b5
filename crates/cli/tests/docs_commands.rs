//! Documentation that cannot rot: the commands the docs show run here.
//!
//! - Every ```` ```sh ```` block of a guide (`docs/guide/*.md`) runs, in the
//!   guide's order, in a sandbox of its own (`bridgev2w` on `PATH`, the
//!   repository's `assets/` and `configs/` linked in, and the example inputs
//!   a guide names but does not make, e.g. the world-model guide's
//!   `first.png`): each must succeed.
//! - A ```` ```sh needs-data ```` block (raw datasets that cannot be
//!   downloaded here) runs command by command: each must stop with the
//!   program's own error (exit status 1), not with a usage error (2), so its
//!   command and flags still exist.
//! - Every `bridgev2w COMMAND ...` in any block or code span of the README,
//!   ARCHITECTURE.md and the docs names a real command, and each of its
//!   `--flags` is in that command's `--help`.
//! - The README's `./run X` commands are `run`'s own subcommands (`./run
//!   demo` is what `cli.rs`'s demo tests run, `./run test` what CI runs).
//! - `configs/train.example.toml` is what the training guide shows.

use crate::common;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../..")
        .canonicalize()
        .expect("repository root")
}

const FENCE: &str = "```";

/// A fenced block: its info string and its text.
struct Block {
    info: String,
    body: String,
}

fn blocks(text: &str) -> Vec<Block> {
    let mut out = Vec::new();
    let mut open: Option<Block> = None;
    for line in text.lines() {
        let t = line.trim_start();
        match (&mut open, t.strip_prefix(FENCE)) {
            (None, Some(info)) => {
                open = Some(Block {
                    info: info.trim().to_string(),
                    body: String::new(),
                })
            }
            (Some(_), Some(_)) => out.push(open.take().expect("open block")),
            (Some(b), None) => {
                b.body.push_str(line);
                b.body.push('\n');
            }
            (None, None) => {}
        }
    }
    out
}

/// The inline code spans outside fenced blocks (a span may wrap lines).
fn code_spans(text: &str) -> Vec<String> {
    let mut prose = String::new();
    let mut fenced = false;
    for line in text.lines() {
        if line.trim_start().starts_with(FENCE) {
            fenced = !fenced;
            continue;
        }
        if !fenced {
            prose.push_str(line);
            prose.push('\n');
        }
    }
    prose
        .split('`')
        .enumerate()
        .filter(|(i, _)| i % 2 == 1)
        .map(|(_, s)| s.replace('\n', " "))
        .collect()
}

/// The shell commands of a block: continuation lines joined, comments and
/// heredoc bodies dropped.
fn commands(body: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut current = String::new();
    let mut heredoc: Option<String> = None;
    for line in body.lines() {
        if let Some(end) = &heredoc {
            if line.trim() == end {
                heredoc = None;
            }
            continue;
        }
        let t = line.trim();
        if current.is_empty() && (t.is_empty() || t.starts_with('#')) {
            continue;
        }
        if let Some(at) = t.find("<<'") {
            heredoc = Some(t[at + 3..].trim_end_matches('\'').to_string());
        }
        match t.strip_suffix('\\') {
            Some(part) => {
                current.push_str(part);
                current.push(' ');
            }
            None => {
                current.push_str(t);
                out.push(std::mem::take(&mut current));
            }
        }
    }
    out
}

fn bridgev2w() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_bridgev2w"));
    c.env("RUST_BACKTRACE", "0");
    c
}

fn show(o: &Output) -> String {
    format!(
        "status {:?}\nstdout:\n{}\nstderr:\n{}",
        o.status.code(),
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// `bridgev2w WORDS... --help`, cached.
fn help(cache: &mut BTreeMap<Vec<String>, Option<String>>, words: &[String]) -> Option<String> {
    cache
        .entry(words.to_vec())
        .or_insert_with(|| {
            let o = bridgev2w()
                .args(words)
                .arg("--help")
                .output()
                .expect("run bridgev2w --help");
            o.status
                .success()
                .then(|| String::from_utf8_lossy(&o.stdout).into_owned())
        })
        .clone()
}

/// The `--flag` tokens of a command line (`--a|--b`, `[--c]`, `--d=1`).
fn flags(command: &str) -> Vec<String> {
    command
        .split(|c: char| c.is_whitespace() || "[]()|=".contains(c))
        .filter(|w| w.starts_with("--") && w.len() > 2)
        .map(|w| {
            w.trim_end_matches(|c: char| !(c.is_ascii_alphanumeric()))
                .to_string()
        })
        .collect()
}

#[test]
fn every_documented_command_and_flag_exists() {
    let mut cache = BTreeMap::new();
    let mut checked = 0;
    let mut problems = Vec::new();
    for file in common::markdown_files() {
        let text = std::fs::read_to_string(&file).expect("read markdown");
        let mut lines: Vec<String> = code_spans(&text);
        for b in blocks(&text) {
            lines.extend(commands(&b.body));
        }
        for line in lines {
            // `bridgev2w CMD ...` anywhere in the line (after `VAR=x`, `&&`, ...).
            let Some(at) = line.find("bridgev2w ") else {
                continue;
            };
            if at > 0 && !line[..at].ends_with([' ', '(', '`']) {
                continue;
            }
            // Python's `import bridgev2w as bw` names the package, not a command.
            if line[..at].trim_end().ends_with("import") {
                continue;
            }
            let words: Vec<&str> = line[at..].split_whitespace().collect();
            let Some(cmd) = words.get(1) else { continue };
            if !cmd.chars().all(|c| c.is_ascii_lowercase() || c == '-') {
                continue;
            }
            let mut path = vec![cmd.to_string()];
            let Some(mut text) = help(&mut cache, &path) else {
                problems.push(format!("{}: `{line}`: no command `{cmd}`", file.display()));
                continue;
            };
            // A subcommand of the command (`bench model`).
            if let Some(sub) = words.get(2) {
                if text.contains("Commands:") && !sub.starts_with('-') {
                    path.push(sub.to_string());
                    match help(&mut cache, &path) {
                        Some(t) => text = t,
                        None => {
                            problems.push(format!(
                                "{}: `{line}`: no command `{cmd} {sub}`",
                                file.display()
                            ));
                            continue;
                        }
                    }
                }
            }
            for flag in flags(&line[at..]) {
                let known = text
                    .split(|c: char| c.is_whitespace() || c == ',' || c == '[' || c == ']')
                    .any(|w| w == flag);
                if !known {
                    problems.push(format!(
                        "{}: `{line}`: `bridgev2w {}` has no {flag}",
                        file.display(),
                        path.join(" ")
                    ));
                }
            }
            checked += 1;
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
    assert!(checked > 30, "only {checked} documented commands found");
}

#[test]
fn the_readme_run_commands_are_the_run_script_s() {
    let root = repo();
    let readme = std::fs::read_to_string(root.join("README.md")).expect("README");
    let script = std::fs::read_to_string(root.join("run")).expect("run");
    let mut found = 0;
    for b in blocks(&readme) {
        for c in commands(&b.body) {
            let Some(rest) = c.strip_prefix("./run ") else {
                continue;
            };
            let sub = rest.split_whitespace().next().expect("a subcommand");
            assert!(
                script.contains(&format!("\n  {sub})")),
                "README: `{c}`: `run` has no `{sub}`"
            );
            found += 1;
        }
    }
    assert!(found >= 2, "the README shows {found} ./run commands");
    // The README's test command is what CI runs.
    let ci = std::fs::read_to_string(root.join(".ci/run")).expect(".ci/run");
    assert!(
        readme.contains("./run test") && ci.contains("./run test"),
        "CI must call the README's test command"
    );
}

#[test]
fn the_example_config_is_the_training_guide_s_and_parses() {
    let root = repo();
    let file = std::fs::read_to_string(root.join("configs/train.example.toml")).expect("config");
    let guide = std::fs::read_to_string(root.join("docs/guide/training.md")).expect("guide");
    let shown: Vec<Block> = blocks(&guide)
        .into_iter()
        .filter(|b| b.info == "toml")
        .collect();
    assert_eq!(shown.len(), 1, "the training guide shows one TOML block");
    assert_eq!(
        shown[0].body, file,
        "the guide's TOML differs from the file"
    );
    bridgev2w_train::config::TrainConfig::from_toml(&file).expect("a valid config");
}

/// A sandbox for a guide's examples: `bridgev2w` on `PATH`, the
/// repository's `assets/` and `configs/`, and `inputs` written by the test.
fn sandbox(inputs: impl FnOnce(&Path)) -> (tempfile::TempDir, String) {
    let dir = tempfile::tempdir().expect("tempdir");
    let d = dir.path();
    let bin = d.join(".bin");
    std::fs::create_dir(&bin).expect("mkdir");
    std::os::unix::fs::symlink(env!("CARGO_BIN_EXE_bridgev2w"), bin.join("bridgev2w"))
        .expect("link bridgev2w");
    for shared in ["assets", "configs"] {
        std::os::unix::fs::symlink(repo().join(shared), d.join(shared)).expect("link");
    }
    inputs(d);
    let path = format!(
        "{}:{}",
        bin.display(),
        std::env::var("PATH").unwrap_or_default()
    );
    (dir, path)
}

/// Runs a guide's ```` ```sh ```` blocks in order in a sandbox prepared by
/// `inputs`; checks its `needs-data` blocks; returns the sandbox.
fn run_guide(name: &str, inputs: impl FnOnce(&Path)) -> tempfile::TempDir {
    let file = repo().join("docs/guide").join(name);
    let text = std::fs::read_to_string(&file).expect("guide");
    let (dir, path) = sandbox(inputs);
    let mut ran = 0;
    for b in blocks(&text) {
        let shell = |script: &str| {
            Command::new("bash")
                .args(["-euo", "pipefail", "-c", script])
                .current_dir(dir.path())
                .env("PATH", &path)
                .env("RUST_BACKTRACE", "0")
                .output()
                .expect("run bash")
        };
        match b.info.as_str() {
            "sh" | "bash" => {
                let o = shell(&b.body);
                assert!(
                    o.status.success(),
                    "{name}: this block failed:\n{}\n{}",
                    b.body,
                    show(&o)
                );
                ran += 1;
            }
            "sh needs-data" => {
                for c in commands(&b.body) {
                    let o = shell(&c);
                    assert_eq!(
                        o.status.code(),
                        Some(1),
                        "{name}: `{c}` should stop at its missing data:\n{}",
                        show(&o)
                    );
                    assert!(!String::from_utf8_lossy(&o.stderr).contains("Usage:"));
                }
                ran += 1;
            }
            _ => {}
        }
    }
    assert!(ran > 0, "{name} has no command block");
    dir
}

/// 9 frames at 96x64: a gradient with a square moving across it.
fn frames(shift: u8) -> Vec<image::RgbImage> {
    (0..9u32)
        .map(|t| {
            image::RgbImage::from_fn(96, 64, |x, y| {
                let inside = (10 + 4 * t..26 + 4 * t).contains(&x) && (20..36).contains(&y);
                if inside {
                    image::Rgb([220, 40, 40])
                } else {
                    image::Rgb([(x * 2) as u8, (y * 3) as u8, 90u8.wrapping_add(shift)])
                }
            })
        })
        .collect()
}

fn write_video(dir: &Path, video: &[image::RgbImage]) {
    std::fs::create_dir_all(dir).expect("mkdir");
    for (i, f) in video.iter().enumerate() {
        f.save(dir.join(format!("{i:06}.png"))).expect("png");
    }
}

#[test]
fn the_data_guide_runs() {
    let d = run_guide("data.md", |_| {});
    assert!(d.path().join("data/meta/info.json").is_file());
}

#[test]
fn the_masks_guide_runs() {
    let d = run_guide("masks.md", |_| {});
    let masks = std::fs::read(d.path().join("masks/masks.npy")).expect("masks.npy");
    // The camera sees the arm: some pixels of every frame are robot.
    assert!(masks.iter().rev().take(192 * 128).any(|&v| v == 1));
}

#[test]
fn the_world_model_guide_runs() {
    let d = run_guide("world-model.md", |d| {
        frames(0)[0].save(d.join("first.png")).expect("png");
        // Link labels (uint16, as `bridgev2w masks` writes them; the shipped
        // model is link-coded): a block of two links, 3 above 4, moving right.
        let mut masks = vec![0u16; 9 * 64 * 96];
        for t in 0..9 {
            for y in 20..44 {
                for x in 30 + 2 * t..50 + 2 * t {
                    masks[(t * 64 + y) * 96 + x] = if y < 32 { 3 } else { 4 };
                }
            }
        }
        bridgev2w_io::npy::write_npy(&d.join("labels.npy"), &[9, 64, 96], &masks).expect("npy");
        // The batch example's folder: the same masks, and an arm moving back.
        std::fs::create_dir_all(d.join("clips")).expect("clips");
        bridgev2w_io::npy::write_npy(&d.join("clips/reach.npy"), &[9, 64, 96], &masks)
            .expect("npy");
        let wave: Vec<u16> = (0..9)
            .rev()
            .flat_map(|t| masks[t * 64 * 96..(t + 1) * 64 * 96].to_vec())
            .collect();
        bridgev2w_io::npy::write_npy(&d.join("clips/wave.npy"), &[9, 64, 96], &wave).expect("npy");
    });
    let video = |p: &str| {
        bridgev2w_io::npy::read_npy(&d.path().join(p))
            .expect(p)
            .data
    };
    let single = video("prediction/video.npy");
    let batched = video("predictions/reach/video.npy");
    let diff = single
        .iter()
        .zip(&batched)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0, f64::max);
    assert!(
        diff <= 1.0,
        "a batched clip is {diff} uint8 levels from its single prediction"
    );
    assert!(d.path().join("predictions/wave/video.mp4").is_file());
}

#[test]
fn the_evaluation_guide_runs() {
    let d = run_guide("evaluation.md", |d| {
        write_video(&d.join("predictions/clip"), &frames(6));
        write_video(&d.join("truth/clip"), &frames(0));
    });
    let scores: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(d.path().join("scores.json")).expect("scores"),
    )
    .expect("json");
    assert!(
        scores["psnr"].as_f64().is_some_and(|p| p > 20.0),
        "{scores}"
    );
    // The figures and the grid, next to results.md and linked from it.
    let results = std::fs::read_to_string(d.path().join("results.md")).expect("results");
    for file in [
        "results/figures/loss-curves.png",
        "results/figures/psnr-per-frame.png",
        "results/grids/test.gif",
    ] {
        assert!(d.path().join(file).is_file(), "{file}");
        assert!(results.contains(&format!("]({file})")), "{file}: {results}");
    }
}

#[test]
fn the_training_guide_runs() {
    let d = run_guide("training.md", |_| {});
    assert!(d
        .path()
        .join("runs/example/final/weights.safetensors")
        .is_file());
    let results = std::fs::read_to_string(d.path().join("results.md")).expect("results");
    assert!(results.contains("BridgeV2W"), "{results}");
}

#[test]
fn the_distributed_guide_runs() {
    // The guide runs the project venv's torchrun.
    let d = run_guide("distributed.md", |d| {
        std::os::unix::fs::symlink(repo().join(".venv"), d.join(".venv")).expect("link .venv");
    });
    for run in ["runs/dp", "runs/dp-hand"] {
        assert!(d
            .path()
            .join(run)
            .join("final/weights.safetensors")
            .is_file());
    }
}

#[test]
fn the_planning_guide_runs() {
    run_guide("planning.md", |_| {});
}

#[test]
fn the_calibrate_guide_runs() {
    let d = run_guide("calibrate.md", |_| {});
    let study =
        std::fs::read_to_string(d.path().join("calibrate-quick/study.json")).expect("study.json");
    let v: serde_json::Value = serde_json::from_str(&study).expect("JSON");
    assert_eq!(v["rows"].as_array().map(Vec::len), Some(2), "{study}");
}
