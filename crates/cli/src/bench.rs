//! `bridgev2w bench`: speed against peers measured in the same run.

use crate::masks_cmd::progress_bar;
use anyhow::{bail, Context, Result};
use bridgev2w_embodiment::camera::{Camera, Intrinsics};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::{random_q, IkOptions, IkSolver, SplitMix64};
use bridgev2w_embodiment::masks::render_trajectory_label_array;
use bridgev2w_embodiment::npy::{read_npy, write_atomic, write_npy};
use bridgev2w_embodiment::robot::{LoadOptions, Robot};
use nalgebra::{Point3, Vector3};
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

#[derive(Debug, clap::Subcommand)]
pub enum BenchCommand {
    /// Mask rendering: this renderer vs pybullet's getCameraImage (TinyRenderer) on
    /// pybullet's own franka_panda/panda.urdf with its OBJ meshes.
    Masks(MasksBench),
    /// Forward kinematics poses/s and warm-started IK time per solve (built-in Franka).
    Kinematics(KinematicsBench),
    /// PSNR + SSIM frames/s: bridgev2w-eval vs scikit-image on the same frames.
    Metrics(MetricsBench),
    /// One transformer forward and one VAE encode/decode: this crate vs diffusers
    /// on the same configs, shapes, threads and precision (random weights).
    Model(crate::bench_model::ModelBench),
    /// Clip loader throughput (clips/s): decoding + masks (stored, rendered calc,
    /// cached calc) and batch assembly, on a dataset or a generated synthetic one.
    Loader(LoaderBench),
}

#[derive(Debug, clap::Args)]
pub struct LoaderBench {
    /// Dataset (LeRobot with masks/ or calibration); default: a synthetic one generated here.
    #[arg(long)]
    dataset: Option<PathBuf>,
    /// Robot for rendering calc masks (when the dataset has calibration and joint states).
    #[arg(long, default_value = "franka")]
    robot: String,
    /// Episodes of the generated dataset.
    #[arg(long, default_value_t = 8)]
    episodes: usize,
    /// Clip frames.
    #[arg(long, default_value_t = 25)]
    frames: usize,
    /// Clip width and height.
    #[arg(long, default_value_t = 96)]
    width: usize,
    #[arg(long, default_value_t = 64)]
    height: usize,
    /// Batch size and number of batches assembled.
    #[arg(long, default_value_t = 4)]
    batch: usize,
    #[arg(long, default_value_t = 50)]
    steps: usize,
}

#[derive(Debug, clap::Args)]
pub struct MetricsBench {
    /// Frame pairs scored.
    #[arg(long, default_value_t = 50)]
    frames: usize,
    #[arg(long, default_value_t = 720)]
    width: usize,
    #[arg(long, default_value_t = 480)]
    height: usize,
    /// Worker processes for scikit-image (default: all cores, like this crate's threads).
    #[arg(long)]
    workers: Option<usize>,
    /// Repository root (holds scripts/bench/); default: found from the current directory.
    #[arg(long)]
    repo: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub struct MasksBench {
    /// Frames in the joint trajectory.
    #[arg(long, default_value_t = 100)]
    frames: usize,
    /// Times the trajectory is rendered (by each renderer).
    #[arg(long, default_value_t = 3)]
    repeat: usize,
    #[arg(long, default_value_t = 720)]
    width: u32,
    #[arg(long, default_value_t = 480)]
    height: u32,
    /// Worker processes for pybullet (default: all cores, like this renderer's threads).
    #[arg(long)]
    workers: Option<usize>,
    /// Only measure this renderer (no Python needed) on the given URDF.
    #[arg(long)]
    no_pybullet: bool,
    /// URDF to render (default: pybullet's franka_panda/panda.urdf).
    #[arg(long)]
    urdf: Option<PathBuf>,
    /// Repository root (holds scripts/bench/); default: found from the current directory.
    #[arg(long)]
    repo: Option<PathBuf>,
}

#[derive(Debug, clap::Args)]
pub struct KinematicsBench {
    /// Forward-kinematics evaluations.
    #[arg(long, default_value_t = 2_000_000)]
    fk: usize,
    /// Warm-started IK solves along a smooth trajectory.
    #[arg(long, default_value_t = 20_000)]
    ik: usize,
}

pub fn run(cmd: &BenchCommand) -> Result<()> {
    match cmd {
        BenchCommand::Masks(a) => masks(a),
        BenchCommand::Kinematics(a) => kinematics(a),
        BenchCommand::Metrics(a) => metrics(a),
        BenchCommand::Model(a) => crate::bench_model::run(a),
        BenchCommand::Loader(a) => loader(a),
    }
}

fn loader(a: &LoaderBench) -> Result<()> {
    use bridgev2w_train::data::{ClipDataset, MaskKind, SourceSpec};
    let tmp = tempfile::tempdir()?;
    let root = match &a.dataset {
        Some(d) => d.clone(),
        None => {
            let out = tmp.path().join("synth");
            let cfg = bridgev2w_data::synth::SynthConfig {
                frames: a.frames,
                width: a.width as u32,
                height: a.height as u32,
                episodes_per_split: [a.episodes, 0, 0, 0],
                ..Default::default()
            };
            cfg.validate()?;
            let pb = progress_bar(a.episodes, "generating a synthetic dataset");
            bridgev2w_data::synth::write_dataset(&cfg, &out, &|| pb.inc(1))?;
            pb.finish_and_clear();
            out
        }
    };
    let spec = |masks: MaskKind| SourceSpec {
        root: root.clone(),
        split: "train".into(),
        video_key: None,
        masks,
        weight: 1.0,
    };
    let cache = tmp.path().join("mask-cache");
    let mut text = format!(
        "clip loader on {} ({} threads)\n",
        root.display(),
        rayon::current_num_threads()
    );
    let mut open = |label: &str, masks: MaskKind| -> Result<ClipDataset> {
        let t0 = Instant::now();
        let d = ClipDataset::open_sources(&[spec(masks)], a.frames, a.height, a.width, 20)?;
        let s = t0.elapsed().as_secs_f64();
        text.push_str(&format!(
            "  open ({label}): {} videos in {s:.2} s = {:.1} videos/s\n",
            d.episodes.len(),
            d.episodes.len() as f64 / s
        ));
        Ok(d)
    };
    let stored = open(
        "decode + stored masks",
        MaskKind::Calc {
            robot: None,
            cache: cache.clone(),
        },
    )?;
    if a.dataset.is_none() {
        // The same dataset without masks/: calc masks rendered, then read from the cache.
        std::fs::rename(root.join("masks"), tmp.path().join("masks.off"))?;
        let calc = MaskKind::Calc {
            robot: Some(a.robot.clone()),
            cache: cache.clone(),
        };
        open("decode + render calc masks", calc.clone())?;
        open("decode + cached calc masks", calc)?;
    }
    let t0 = Instant::now();
    for step in 0..a.steps {
        stored.batch(
            0,
            step,
            a.batch,
            bridgev2w_world_model::ComputeDevice::Cpu.to_tch(),
        )?;
    }
    let s = t0.elapsed().as_secs_f64();
    let clips = a.steps * a.batch;
    text.push_str(&format!(
        "  batches: {clips} clips of {}x{}x{} in {s:.2} s = {:.1} clips/s\n",
        a.frames,
        a.height,
        a.width,
        clips as f64 / s
    ));
    crate::print_stdout(&text)
}

pub(crate) fn find_repo(explicit: Option<&Path>) -> Result<PathBuf> {
    if let Some(r) = explicit {
        return Ok(r.to_path_buf());
    }
    let cwd = std::env::current_dir()?;
    cwd.ancestors()
        .find(|d| d.join("scripts/bench/pybullet_masks.py").is_file())
        .map(Path::to_path_buf)
        .context("cannot find scripts/bench/pybullet_masks.py above the current directory: run from the repository or pass --repo")
}

/// Runs a peer script and returns the last JSON object it printed on stdout,
/// with errors naming the script (its stderr on failure).
pub(crate) fn run_peer_json(cmd: &mut Command, script: &str) -> Result<serde_json::Value> {
    let out = cmd
        .output()
        .with_context(|| format!("running scripts/bench/{script}"))?;
    if !out.status.success() {
        bail!("{script} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    }
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout
        .lines()
        .rev()
        .find(|l| l.trim_start().starts_with('{'))
        .with_context(|| format!("{script} printed no JSON result"))?;
    Ok(serde_json::from_str(line)?)
}

fn bench_python(repo: &Path) -> Result<PathBuf> {
    let python = repo.join(".venv-bench/bin/python");
    let status = Command::new("bash")
        .arg(repo.join("scripts/bench/setup-venv.sh"))
        .current_dir(repo)
        .stdout(std::process::Stdio::null())
        .status()
        .context("running scripts/bench/setup-venv.sh")?;
    if !status.success() || !python.is_file() {
        bail!("scripts/bench/setup-venv.sh failed: cannot install pybullet into .venv-bench (use --no-pybullet to bench this renderer alone)");
    }
    Ok(python)
}

/// The bench trajectory: every actuated joint sweeps a sine within its limits.
fn sweep(robot: &Robot, frames: usize) -> Vec<Vec<f64>> {
    let limits = robot.dof_limits();
    (0..frames)
        .map(|f| {
            let s = f as f64 / frames.max(1) as f64;
            limits
                .iter()
                .enumerate()
                .map(|(i, &(lo, hi))| {
                    let (lo, hi) = (lo.max(-2.5), hi.min(2.5));
                    let mid = 0.5 * (lo + hi);
                    let amp = 0.35 * (hi - lo);
                    mid + amp * (std::f64::consts::TAU * s + i as f64).sin()
                })
                .collect()
        })
        .collect()
}

fn bench_camera(width: u32, height: u32) -> Result<Camera> {
    let intr = Intrinsics::centered(560.0, 720, 480);
    let cam = Camera::look_at(
        intr,
        Point3::new(1.5, 0.9, 0.9),
        Point3::new(0.2, 0.0, 0.4),
        Vector3::z(),
    )?;
    Ok(cam.rescaled(width, height))
}

fn masks(a: &MasksBench) -> Result<()> {
    if a.frames == 0 || a.repeat == 0 {
        bail!("--frames and --repeat must be positive");
    }
    let threads = rayon::current_num_threads();
    let workers = a.workers.unwrap_or(threads);
    let (repo, python) = if a.no_pybullet {
        (None, None)
    } else {
        let repo = find_repo(a.repo.as_deref())?;
        let py = bench_python(&repo)?;
        (Some(repo), Some(py))
    };
    let urdf = match (&a.urdf, &python, &repo) {
        (Some(u), _, _) => u.clone(),
        (None, Some(py), Some(repo)) => {
            let out = Command::new(py)
                .arg(repo.join("scripts/bench/pybullet_masks.py"))
                .args([
                    "--urdf",
                    "pybullet:franka_panda/panda.urdf",
                    "--print-urdf-path",
                ])
                .output()
                .context("running pybullet_masks.py --print-urdf-path")?;
            if !out.status.success() {
                bail!(
                    "pybullet_masks.py --print-urdf-path failed: {}",
                    String::from_utf8_lossy(&out.stderr)
                );
            }
            PathBuf::from(String::from_utf8_lossy(&out.stdout).trim())
        }
        _ => bail!("--no-pybullet needs --urdf PATH"),
    };
    let t0 = Instant::now();
    let robot = Robot::from_urdf_file(&urdf, &LoadOptions::default())?;
    let load_s = t0.elapsed().as_secs_f64();
    let triangles: usize = robot
        .links
        .iter()
        .filter_map(|l| l.mesh.as_ref())
        .map(|m| m.triangles.len())
        .sum();
    let camera = bench_camera(a.width, a.height)?;
    let joints = sweep(&robot, a.frames);
    println!(
        "scene: {} ({} links, {triangles} triangles, loaded in {load_s:.3} s), {} frames x {} repeats at {}x{}",
        urdf.display(),
        robot.links.len(),
        a.frames,
        a.repeat,
        a.width,
        a.height
    );

    // This renderer: warm-up pass, then timed passes. Like pybullet's
    // segmentation output, per-pixel link labels (no depth maps), into one
    // [T, H, W] array (as pybullet_masks.py's).
    let mut ours = render_trajectory_label_array(&robot, &camera, &joints, &|| {});
    let pb = progress_bar(a.frames * a.repeat, "bridgev2w renderer");
    let mut ours_s = 0.0;
    for _ in 0..a.repeat {
        // Freeing the previous pass's masks is not rendering: untimed.
        drop(std::mem::take(&mut ours));
        let t0 = Instant::now();
        ours = render_trajectory_label_array(&robot, &camera, &joints, &|| pb.inc(1));
        ours_s += t0.elapsed().as_secs_f64();
    }
    pb.finish_and_clear();
    let ours_rate = (a.frames * a.repeat) as f64 / ours_s;
    println!("bridgev2w rasterizer      {ours_rate:>10.1} masks/s  ({threads} threads)");

    let (Some(python), Some(repo)) = (python, repo) else {
        return Ok(());
    };
    let tmp = tempfile::tempdir()?;
    let cam_path = tmp.path().join("camera.json");
    write_atomic(&cam_path, camera.to_json().as_bytes())?;
    let joints_path = tmp.path().join("joints.npy");
    let flat: Vec<f64> = joints.iter().flatten().copied().collect();
    write_npy(&joints_path, &[joints.len(), robot.dof()], &flat)?;
    let names_path = tmp.path().join("joint_names.json");
    write_atomic(
        &names_path,
        serde_json::to_string(&robot.dof_names())?.as_bytes(),
    )?;
    let masks_path = tmp.path().join("pybullet_masks.npy");
    eprintln!(
        "running pybullet getCameraImage (TinyRenderer) with {workers} worker process(es)..."
    );
    let v = run_peer_json(
        Command::new(&python)
            .arg(repo.join("scripts/bench/pybullet_masks.py"))
            .arg("--urdf")
            .arg(&urdf)
            .arg("--joints")
            .arg(&joints_path)
            .arg("--joint-names")
            .arg(&names_path)
            .arg("--camera")
            .arg(&cam_path)
            .args([
                "--workers",
                &workers.to_string(),
                "--repeat",
                &a.repeat.to_string(),
            ])
            .arg("--out")
            .arg(&masks_path),
        "pybullet_masks.py",
    )?;
    let py_rate = v["masks_per_s"]
        .as_f64()
        .context("pybullet result has no masks_per_s")?;
    println!("pybullet TinyRenderer     {py_rate:>10.1} masks/s  ({workers} processes)");
    println!("ratio                     {:>10.1}x", ours_rate / py_rate);

    // Agreement: the two renderers should draw the same robot.
    let theirs = read_npy(&masks_path)?;
    let hw = (a.width * a.height) as usize;
    // pybullet saves every repeat; the first pass is compared.
    let frames = ours.len() / hw.max(1);
    if theirs.data.len() >= ours.len() {
        let mut iou_sum = 0.0;
        for (t, f) in ours.chunks(hw.max(1)).enumerate() {
            let (mut inter, mut uni) = (0usize, 0usize);
            for (i, &l) in f.iter().enumerate() {
                let a = l != 0;
                let b = theirs.data[t * hw + i] != 0.0;
                inter += usize::from(a && b);
                uni += usize::from(a || b);
            }
            iou_sum += if uni == 0 {
                1.0
            } else {
                inter as f64 / uni as f64
            };
        }
        println!(
            "mask agreement (mean IoU) {:>10.4}",
            iou_sum / frames as f64
        );
    } else {
        eprintln!(
            "warning: pybullet masks have {} values, expected {}",
            theirs.data.len(),
            ours.len()
        );
    }
    ours.clear();
    Ok(())
}

fn kinematics(a: &KinematicsBench) -> Result<()> {
    let e = Embodiment::builtin("franka")?;
    let r = &e.robot;
    let mut rng = SplitMix64::new(1);
    let qs: Vec<Vec<f64>> = (0..1024).map(|_| random_q(r, &mut rng)).collect();
    let mut buf = Vec::with_capacity(r.links.len());
    let mut sink = 0.0;
    let t0 = Instant::now();
    for i in 0..a.fk {
        r.link_poses_into(&qs[i % qs.len()], &mut buf);
        sink += buf[buf.len() - 1].translation.x;
    }
    let fk_s = t0.elapsed().as_secs_f64();
    println!(
        "forward kinematics  {:>12.0} poses/s per core  ({} links per pose; checksum {sink:.3})",
        a.fk as f64 / fk_s,
        r.links.len()
    );

    let tcp = r.link_index("panda_hand_tcp").context("no tcp")?;
    let solver = IkSolver::new(r, tcp, None);
    let opts = IkOptions::default();
    // A smooth joint path; targets from FK; each solve warm-started from the previous solution.
    let mut q = e.home.clone();
    let targets: Vec<_> = (0..a.ik)
        .map(|i| {
            let s = i as f64 * 0.01;
            let mut qt = e.home.clone();
            qt[0] = 0.8 * s.sin();
            qt[1] = -0.5 + 0.4 * (0.7 * s).sin();
            qt[3] = -2.0 + 0.5 * (0.5 * s).cos();
            qt[5] = 1.6 + 0.4 * (0.3 * s).sin();
            r.link_pose(tcp, &qt)
        })
        .collect();
    let (mut reached, mut iters) = (0usize, 0usize);
    let t0 = Instant::now();
    for t in &targets {
        let sol = solver.solve(t, &q, &opts);
        reached += usize::from(sol.reached);
        iters += sol.iterations;
        q = sol.q;
    }
    let ik_s = t0.elapsed().as_secs_f64();
    println!(
        "inverse kinematics  {:>12.2} us per warm-started solve  ({reached}/{} reached, {:.2} iterations on average)",
        ik_s / a.ik as f64 * 1e6,
        a.ik,
        iters as f64 / a.ik as f64
    );
    Ok(())
}

/// Deterministic test frames: smooth colour gradients with texture and
/// noise; the "predicted" frame is a blurred, shifted, noisy copy.
fn metric_frames(n: usize, w: usize, h: usize) -> (Vec<u8>, Vec<u8>) {
    let mut rng = SplitMix64::new(17);
    let mut noise = || (rng.next_u64() >> 56) as i32 - 128;
    let mut gt = vec![0u8; n * h * w * 3];
    let mut pred = vec![0u8; n * h * w * 3];
    for t in 0..n {
        for y in 0..h {
            for x in 0..w {
                for c in 0..3 {
                    let i = ((t * h + y) * w + x) * 3 + c;
                    let smooth = (x * (c + 1) * 255 / w + y * 255 / h + t * 3) % 256;
                    let texture = ((x / 8 + y / 8 + c) % 2) as i32 * 40;
                    let g = (smooth as i32 / 2 + texture + noise() / 16).clamp(0, 255);
                    gt[i] = g as u8;
                    pred[i] = (g + 6 + noise() / 8).clamp(0, 255) as u8;
                }
            }
        }
    }
    (pred, gt)
}

fn metrics(a: &MetricsBench) -> Result<()> {
    use bridgev2w_eval::video::{psnr, ssim, Frame};
    use rayon::prelude::*;
    let (w, h, n) = (a.width, a.height, a.frames);
    if n == 0 || w < 11 || h < 11 {
        bail!("--frames must be >= 1 and --width/--height >= 11 (the SSIM window)");
    }
    let (pred, gt) = metric_frames(n, w, h);
    let frame_len = w * h * 3;
    let threads = rayon::current_num_threads();
    println!("scene: {n} frame pairs at {w}x{h} (RGB, uint8)");
    // Conversion to [0, 1] floats is part of the timed work on both sides.
    let t0 = Instant::now();
    let ours: Vec<(f64, f64)> = (0..n)
        .into_par_iter()
        .map(|t| -> Result<(f64, f64)> {
            let r = t * frame_len..(t + 1) * frame_len;
            let p = Frame::from_rgb8(w, h, &pred[r.clone()])?;
            let g = Frame::from_rgb8(w, h, &gt[r])?;
            Ok((psnr(&p, &g)?, ssim(&p, &g)?))
        })
        .collect::<Result<_>>()?;
    let ours_s = t0.elapsed().as_secs_f64();
    let ours_rate = n as f64 / ours_s;
    println!("bridgev2w-eval PSNR+SSIM  {ours_rate:>10.2} frames/s  ({threads} threads)");
    let repo = find_repo(a.repo.as_deref())?;
    let python = bench_python(&repo)?;
    let workers = a.workers.unwrap_or(threads).max(1);
    let tmp = tempfile::tempdir()?;
    let (pred_path, gt_path) = (tmp.path().join("pred.npy"), tmp.path().join("gt.npy"));
    write_npy(&pred_path, &[n, h, w, 3], &pred)?;
    write_npy(&gt_path, &[n, h, w, 3], &gt)?;
    eprintln!("running scikit-image with {workers} worker process(es)...");
    let v = run_peer_json(
        Command::new(&python)
            .arg(repo.join("scripts/bench/skimage_metrics.py"))
            // One core per worker process, like one rayon thread per core.
            .envs([("OMP_NUM_THREADS", "1"), ("OPENBLAS_NUM_THREADS", "1")])
            .arg("--pred")
            .arg(&pred_path)
            .arg("--gt")
            .arg(&gt_path)
            .args(["--workers", &workers.to_string()]),
        "skimage_metrics.py",
    )?;
    let seconds = v["seconds"]
        .as_f64()
        .context("scikit-image result has no seconds")?;
    let values = |key: &str| -> Result<Vec<f64>> {
        v[key]
            .as_array()
            .context("scikit-image result lacks per-frame values")?
            .iter()
            .map(|x| x.as_f64().context("non-numeric value"))
            .collect()
    };
    let (their_psnr, their_ssim) = (values("psnr")?, values("ssim")?);
    let py_rate = n as f64 / seconds;
    println!("scikit-image PSNR+SSIM    {py_rate:>10.2} frames/s  ({workers} processes)");
    println!("ratio                     {:>10.1}x", ours_rate / py_rate);
    let max_diff = |ours: &mut dyn Iterator<Item = f64>, theirs: &[f64]| {
        ours.zip(theirs)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max)
    };
    println!(
        "agreement: max |SSIM diff| {:.2e}, max |PSNR diff| {:.2e} dB",
        max_diff(&mut ours.iter().map(|o| o.1), &their_ssim),
        max_diff(&mut ours.iter().map(|o| o.0), &their_psnr)
    );
    Ok(())
}
