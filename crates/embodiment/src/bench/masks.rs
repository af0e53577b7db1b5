//! Mask rendering speed: this rasterizer vs pybullet's `getCameraImage`
//! (TinyRenderer, `scripts/bench/pybullet_masks.py` in the bench venv) on the
//! same URDF (by default pybullet's own `franka_panda/panda.urdf` with its OBJ
//! meshes), joint trajectory and camera, and how well the two agree.

use super::{BenchError, Result};
use crate::camera::{Camera, Intrinsics};
use crate::masks::render_trajectory_label_array;
use crate::robot::{LoadOptions, Robot};
use bridgev2w_io::atomic::write_atomic;
use bridgev2w_io::json::write_json_atomic;
use bridgev2w_io::npy::{read_npy, write_npy};
use bridgev2w_io::peer;
use bridgev2w_io::progress::Progress;
use nalgebra::{Point3, Vector3};
use std::fmt;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

/// What `bench masks` renders and against what (the command's flags).
#[derive(Debug, Clone, PartialEq)]
#[cfg_attr(feature = "clap", derive(clap::Args))]
pub struct MasksBenchOptions {
    /// Frames in the joint trajectory.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = MasksBenchOptions::default().frames))]
    pub frames: usize,
    /// Times the trajectory is rendered (by each renderer).
    #[cfg_attr(feature = "clap", arg(long, default_value_t = MasksBenchOptions::default().repeat))]
    pub repeat: usize,
    /// Image width in pixels.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = MasksBenchOptions::default().width))]
    pub width: u32,
    /// Image height in pixels.
    #[cfg_attr(feature = "clap", arg(long, default_value_t = MasksBenchOptions::default().height))]
    pub height: u32,
    /// Worker processes for pybullet (default: all cores, like this renderer's threads).
    #[cfg_attr(feature = "clap", arg(long))]
    pub workers: Option<usize>,
    /// `--no-pybullet`: only measure this renderer (no Python needed) on the given --urdf.
    #[cfg_attr(feature = "clap", arg(long = "no-pybullet", action = clap::ArgAction::SetFalse))]
    pub pybullet: bool,
    /// URDF to render (default: pybullet's franka_panda/panda.urdf).
    #[cfg_attr(feature = "clap", arg(long))]
    pub urdf: Option<PathBuf>,
    /// Repository root (holds scripts/bench/); default: found from the
    /// current directory.
    #[cfg_attr(feature = "clap", arg(long))]
    pub repo: Option<PathBuf>,
}

impl Default for MasksBenchOptions {
    fn default() -> Self {
        Self {
            frames: 100,
            repeat: 3,
            width: 720,
            height: 480,
            workers: None,
            pybullet: true,
            urdf: None,
            repo: None,
        }
    }
}

/// The measurements of `bench masks`; `Display` prints them as a table.
#[derive(Debug, Clone, PartialEq)]
pub struct MasksBenchReport {
    /// The URDF rendered.
    pub urdf: PathBuf,
    /// Its links.
    pub links: usize,
    /// Its mesh triangles.
    pub triangles: usize,
    /// Seconds to load it.
    pub load_s: f64,
    /// Frames in the trajectory.
    pub frames: usize,
    /// Passes over the trajectory.
    pub repeat: usize,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// This renderer's masks per second.
    pub masks_per_s: f64,
    /// Its threads.
    pub threads: usize,
    /// pybullet's figures, when it ran.
    pub pybullet: Option<PybulletMasks>,
}

/// pybullet's side of the mask bench.
#[derive(Debug, Clone, PartialEq)]
pub struct PybulletMasks {
    /// Masks per second.
    pub masks_per_s: f64,
    /// Worker processes.
    pub workers: usize,
    /// How well its masks match this renderer's.
    pub agreement: MaskAgreement,
}

/// Agreement of the two renderers' robot pixels on the first pass.
#[derive(Debug, Clone, PartialEq)]
pub enum MaskAgreement {
    /// Mean intersection over union of the robot pixels, per frame.
    MeanIou(f64),
    /// pybullet's masks have fewer values than this renderer's.
    SizeMismatch {
        /// Values in pybullet's array.
        values: usize,
        /// Values expected.
        expected: usize,
    },
}

impl MasksBenchReport {
    /// Problems to show beside the table (on stderr in the command-line tool).
    pub fn warnings(&self) -> Vec<String> {
        match self.pybullet.as_ref().map(|p| &p.agreement) {
            Some(MaskAgreement::SizeMismatch { values, expected }) => vec![format!(
                "warning: pybullet masks have {values} values, expected {expected}"
            )],
            _ => Vec::new(),
        }
    }
}

impl fmt::Display for MasksBenchReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "scene: {} ({} links, {} triangles, loaded in {:.3} s), {} frames x {} repeats at {}x{}",
            self.urdf.display(),
            self.links,
            self.triangles,
            self.load_s,
            self.frames,
            self.repeat,
            self.width,
            self.height
        )?;
        writeln!(
            f,
            "bridgev2w rasterizer      {:>10.1} masks/s  ({} threads)",
            self.masks_per_s, self.threads
        )?;
        let Some(py) = &self.pybullet else {
            return Ok(());
        };
        writeln!(
            f,
            "pybullet TinyRenderer     {:>10.1} masks/s  ({} processes)",
            py.masks_per_s, py.workers
        )?;
        writeln!(
            f,
            "ratio                     {:>10.1}x",
            self.masks_per_s / py.masks_per_s
        )?;
        if let MaskAgreement::MeanIou(iou) = py.agreement {
            writeln!(f, "mask agreement (mean IoU) {iou:>10.4}")?;
        }
        Ok(())
    }
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

/// The bench camera: looking at the robot from the front right.
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

/// pybullet's own `franka_panda/panda.urdf`, as the peer script finds it.
fn pybullet_panda(python: &Path, repo: &Path) -> Result<PathBuf> {
    let what = "pybullet_masks.py --print-urdf-path";
    let out = peer::run_peer_text(
        Command::new(python)
            .arg(repo.join("scripts/bench/pybullet_masks.py"))
            .args([
                "--urdf",
                "pybullet:franka_panda/panda.urdf",
                "--print-urdf-path",
            ]),
        what,
    )?;
    Ok(PathBuf::from(out.trim()))
}

/// Renders the bench trajectory `repeat` times with this rasterizer (after
/// an untimed warm-up pass), then, unless `options.pybullet` is off, with
/// pybullet, and compares the two renderers' first passes.
pub fn bench_masks(
    options: &MasksBenchOptions,
    progress: &dyn Progress,
) -> Result<MasksBenchReport> {
    let a = options;
    if a.frames == 0 || a.repeat == 0 {
        return Err(BenchError::Invalid(
            "--frames and --repeat must be positive".into(),
        ));
    }
    // One [T, H, W] label array per pass, the peer's masks beside it.
    crate::masks::check_render_size("--frames", a.frames, a.width, a.height, false)?;
    let threads = rayon::current_num_threads();
    let workers = a.workers.unwrap_or(threads);
    let peer = if a.pybullet {
        let repo = peer::find_repo(a.repo.as_deref())?;
        let python = peer::bench_python(&repo)?;
        Some((repo, python))
    } else {
        None
    };
    let urdf = match (&a.urdf, &peer) {
        (Some(u), _) => u.clone(),
        (None, Some((repo, python))) => pybullet_panda(python, repo)?,
        (None, None) => {
            return Err(BenchError::Invalid(
                "--no-pybullet needs --urdf PATH".into(),
            ));
        }
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

    // This renderer: warm-up pass, then timed passes. Like pybullet's
    // segmentation output, per-pixel link labels (no depth maps), into one
    // [T, H, W] array (as pybullet_masks.py's).
    let mut ours = render_trajectory_label_array(&robot, &camera, &joints, &|| {});
    progress.start(a.frames * a.repeat, "bridgev2w renderer");
    let mut ours_s = 0.0;
    for _ in 0..a.repeat {
        // Freeing the previous pass's masks is not rendering: untimed.
        drop(std::mem::take(&mut ours));
        let t0 = Instant::now();
        ours = render_trajectory_label_array(&robot, &camera, &joints, &|| progress.tick());
        ours_s += t0.elapsed().as_secs_f64();
    }
    progress.finish();
    let mut report = MasksBenchReport {
        urdf: urdf.clone(),
        links: robot.links.len(),
        triangles,
        load_s,
        frames: a.frames,
        repeat: a.repeat,
        width: a.width,
        height: a.height,
        masks_per_s: (a.frames * a.repeat) as f64 / ours_s,
        threads,
        pybullet: None,
    };
    let Some((repo, python)) = peer else {
        return Ok(report);
    };

    let tmp = peer::scratch_dir()?;
    let cam_path = tmp.path().join("camera.json");
    write_atomic(&cam_path, camera.to_json().as_bytes())?;
    let joints_path = tmp.path().join("joints.npy");
    let flat: Vec<f64> = joints.iter().flatten().copied().collect();
    write_npy(&joints_path, &[joints.len(), robot.dof()], &flat)?;
    let names_path = tmp.path().join("joint_names.json");
    write_json_atomic(&names_path, &robot.dof_names())?;
    let masks_path = tmp.path().join("pybullet_masks.npy");
    progress.note(&format!(
        "running pybullet getCameraImage (TinyRenderer) with {workers} worker process(es)..."
    ));
    let result = peer::run_peer_json(
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
    let masks_per_s = result.number("masks_per_s")?;
    // pybullet saves every repeat; the first pass is compared.
    let theirs = read_npy(&masks_path)?;
    let agreement = mean_iou(&ours, &theirs.data, (a.width * a.height) as usize);
    report.pybullet = Some(PybulletMasks {
        masks_per_s,
        workers,
        agreement,
    });
    Ok(report)
}

/// Mean over frames of the IoU of the robot pixels (label != 0) of `ours`
/// (`[T, H, W]`, `hw` = H * W) and the first `T` frames of `theirs`.
fn mean_iou(ours: &[u16], theirs: &[f64], hw: usize) -> MaskAgreement {
    if theirs.len() < ours.len() {
        return MaskAgreement::SizeMismatch {
            values: theirs.len(),
            expected: ours.len(),
        };
    }
    let frames = ours.len() / hw.max(1);
    let mut iou_sum = 0.0;
    for (t, f) in ours.chunks(hw.max(1)).enumerate() {
        let (mut inter, mut uni) = (0usize, 0usize);
        for (i, &l) in f.iter().enumerate() {
            let a = l != 0;
            let b = theirs[t * hw + i] != 0.0;
            inter += usize::from(a && b);
            uni += usize::from(a || b);
        }
        iou_sum += if uni == 0 {
            1.0
        } else {
            inter as f64 / uni as f64
        };
    }
    MaskAgreement::MeanIou(iou_sum / frames as f64)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn iou_counts_robot_pixels_per_frame_and_flags_short_peer_output() {
        // Two 2x2 frames: the first agrees fully, the second on 1 of 3 pixels.
        let ours = [1u16, 0, 0, 0, 2, 2, 0, 0];
        let theirs = [3.0, 0.0, 0.0, 0.0, 1.0, 0.0, 1.0, 0.0, 9.0];
        assert_eq!(
            mean_iou(&ours, &theirs, 4),
            MaskAgreement::MeanIou(2.0 / 3.0)
        );
        let short = mean_iou(&ours, &theirs[..4], 4);
        assert_eq!(
            short,
            MaskAgreement::SizeMismatch {
                values: 4,
                expected: 8
            }
        );
    }

    #[test]
    fn renderer_only_bench_reports_and_needs_a_urdf() {
        let mut options = MasksBenchOptions {
            frames: 2,
            repeat: 1,
            width: 48,
            height: 32,
            pybullet: false,
            ..MasksBenchOptions::default()
        };
        let e = bench_masks(&options, &bridgev2w_io::progress::Silent).expect_err("no urdf");
        assert_eq!(e.to_string(), "--no-pybullet needs --urdf PATH");
        options.urdf =
            Some(Path::new(env!("CARGO_MANIFEST_DIR")).join("robots/franka/franka.urdf"));
        let report = bench_masks(&options, &bridgev2w_io::progress::Silent).expect("bench");
        assert!(report.masks_per_s > 0.0 && report.pybullet.is_none());
        let text = report.to_string();
        assert!(text.starts_with("scene: "), "{text}");
        assert!(text.contains("2 frames x 1 repeats at 48x32"), "{text}");
        assert_eq!(text.lines().count(), 2, "{text}");
        assert!(report.warnings().is_empty());
        options.repeat = 0;
        let e = bench_masks(&options, &bridgev2w_io::progress::Silent).expect_err("repeat 0");
        assert_eq!(e.to_string(), "--frames and --repeat must be positive");
    }
}
