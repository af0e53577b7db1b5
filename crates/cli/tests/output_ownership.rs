//! Outputs never touch what the tool did not create (issue 69): `demo`
//! replaces only an earlier demo's output, and an output that is, is inside
//! or contains one of a command's inputs is refused before anything is
//! written.

#![allow(clippy::unwrap_used, clippy::expect_used)]

use crate::common;

use common::{run, s};
use std::path::Path;
use std::process::Output;

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

fn write(dir: &Path, name: &str, text: &str) -> String {
    let p = dir.join(name);
    std::fs::write(&p, text).expect("write");
    p.display().to_string()
}

/// The shape of an `.npy` file.
fn npy_shape(path: &Path) -> Vec<usize> {
    bridgev2w_io::npy::read_npy(path).expect("npy").shape
}

const CAMERA: &str = r#"{"fx": 300, "fy": 300, "cx": 159.5, "cy": 119.5, "width": 320, "height": 240,
  "world_from_camera": [[-0.3939, 0.3019, -0.8682, 1.7],
                        [0.9191, 0.1294, -0.3721, 0.6],
                        [0.0, -0.9445, -0.3284, 1.0],
                        [0, 0, 0, 1]]}"#;

const HOME: [f64; 8] = [0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785, 0.04];

/// `demo --out` replaces only an earlier demo's output (issue 69): a folder
/// that merely holds the demo's file names, or a demo's output with a file
/// the user added, is refused without `--overwrite`, untouched; a real
/// earlier demo is replaced (twice in a row works). Masks only: fast.
#[test]
fn demo_replaces_an_earlier_demo_but_no_folder_with_a_user_file() {
    let tmp = tempfile::tempdir().expect("demo test");
    let out = tmp.path().join("demo-out");
    let demo = |frames: &str, extra: &[&str]| {
        let mut line = vec!["demo", "--no-predict", "--frames", frames];
        line.extend_from_slice(extra);
        line.extend_from_slice(&["--out", s(&out)]);
        run(&line)
    };
    // The names an earlier version recognised, and the user's file.
    std::fs::create_dir(&out).expect("demo test");
    for f in ["overlay.gif", "camera.json", "actions.json", "masks.npy"] {
        std::fs::write(out.join(f), "x").expect("demo test");
    }
    std::fs::write(out.join("notes.txt"), "mine").expect("demo test");
    let o = demo("3", &[]);
    let e = stderr(&o);
    assert!(
        !o.status.success()
            && e.contains("not an earlier demo's output")
            && e.contains(".bridgev2w-demo")
            && e.contains("--overwrite"),
        "{e}"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("notes.txt")).expect("kept"),
        "mine"
    );
    // Asked for: replaced whole.
    let o = demo("3", &["--overwrite"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(!out.join("notes.txt").exists());
    assert!(out.join(".bridgev2w-demo").is_file());
    // A second demo replaces the first's output.
    let o = demo("4", &[]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_eq!(npy_shape(&out.join("masks.npy")), vec![4, 480, 720]);
    // A file the user added to a demo's output: refused, kept.
    std::fs::write(out.join("frames/mine.png"), "mine").expect("demo test");
    let o = demo("3", &[]);
    assert!(
        !o.status.success() && stderr(&o).contains("frames"),
        "{}",
        stderr(&o)
    );
    assert!(out.join("frames/mine.png").is_file());
    assert_eq!(npy_shape(&out.join("masks.npy")), vec![4, 480, 720]);
    // The demo model is an input: an output inside it is refused.
    let model = tmp.path().join("model");
    std::fs::create_dir(&model).expect("demo test");
    let o = run(&[
        "demo",
        "--frames",
        "3",
        "--model",
        s(&model),
        "--out",
        s(&model.join("out")),
    ]);
    assert!(
        !o.status.success() && stderr(&o).contains("is inside the input"),
        "{}",
        stderr(&o)
    );
    assert!(!model.join("out").exists());
}

/// Outputs equal to, inside or containing an input are refused before
/// anything is written (issue 69): `masks` against its camera and
/// trajectory files, `overlay` against its frames folder and truths,
/// `plan --trace` against the model folder; the inputs are kept.
#[test]
fn outputs_overlapping_an_input_are_refused() {
    let d = tempfile::tempdir().expect("tmp");
    let p = |n: &str| d.path().join(n).display().to_string();
    let camera = write(d.path(), "camera.json", CAMERA);
    let joints = write(
        d.path(),
        "joints.json",
        &serde_json::to_string(&vec![HOME; 2]).unwrap(),
    );
    let masks = |out: &str| {
        run(&[
            "masks",
            "--robot",
            "franka",
            "--camera",
            &camera,
            "--joints",
            &joints,
            "--width",
            "64",
            "--height",
            "48",
            "--out",
            out,
            "--overwrite",
        ])
    };
    for (out, how) in [
        (camera.clone(), "is the input"),
        (d.path().display().to_string(), "contains the input"),
        (p("joints.json/x"), "is inside the input"),
    ] {
        let o = masks(&out);
        let e = stderr(&o);
        assert!(!o.status.success() && e.contains(how), "{out}: {e}");
    }
    assert_eq!(std::fs::read_to_string(&camera).expect("kept"), CAMERA);
    let o = masks(&p("m"));
    assert!(o.status.success(), "{}", stderr(&o));
    // overlay over the masks' own PNG frames.
    let overlay = |out: &str| {
        run(&[
            "overlay",
            "--robot",
            "franka",
            "--camera",
            &camera,
            "--joints",
            &joints,
            "--frames",
            &p("m/frames"),
            "--truth-masks",
            &p("m/masks.npy"),
            "--out",
            out,
            "--overwrite",
        ])
    };
    for (out, how) in [
        (p("m/frames"), "is the input"),
        (p("m/frames/o"), "is inside the input"),
        (p("m"), "contains the input"),
    ] {
        let o = overlay(&out);
        let e = stderr(&o);
        assert!(!o.status.success() && e.contains(how), "{out}: {e}");
    }
    assert_eq!(npy_shape(&d.path().join("m/masks.npy")), vec![2, 48, 64]);
    assert!(d.path().join("m/frames/000001.png").is_file());
    let o = overlay(&p("o"));
    assert!(o.status.success(), "{}", stderr(&o));
    // plan --trace inside the model folder: refused before the model loads.
    std::fs::create_dir(d.path().join("model")).expect("model");
    let o = run(&[
        "plan",
        "--task",
        "reach",
        "--trials",
        "1",
        "--model",
        &p("model"),
        "--trace",
        &p("model/trace"),
    ]);
    let e = stderr(&o);
    assert!(
        !o.status.success() && e.contains("--trace") && e.contains("is inside the input"),
        "{e}"
    );
    assert!(!d.path().join("model/trace").exists());
}

/// `eval-run --json FILE` refuses an existing file before the run is
/// opened (its scores are minutes of work); `--overwrite` gets past the
/// check (and then the missing run is named).
#[test]
fn eval_run_refuses_an_existing_json_file() {
    let d = tempfile::tempdir().expect("tmp");
    let json = write(d.path(), "scores.json", "{\"mine\": 1}");
    let run_dir = d.path().join("no-run").display().to_string();
    let args = |extra: &[&str]| {
        let mut a = vec!["eval-run", "no-config.toml", "--run", &run_dir, "--json"];
        a.push(&json);
        a.extend_from_slice(extra);
        run(&a)
    };
    let o = args(&[]);
    let e = stderr(&o);
    assert!(
        !o.status.success() && e.contains("--json") && e.contains("already exists"),
        "{e}"
    );
    assert_eq!(std::fs::read_to_string(&json).unwrap(), "{\"mine\": 1}");
    let o = args(&["--overwrite"]);
    let e = stderr(&o);
    assert!(
        !o.status.success() && !e.contains("already exists") && e.contains("no-config.toml"),
        "{e}"
    );
    assert_eq!(std::fs::read_to_string(&json).unwrap(), "{\"mine\": 1}");
}
