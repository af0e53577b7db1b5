//! A mask folder from files, as `bridgev2w masks` writes it: a camera JSON
//! (and optionally per-frame poses), a joint or action trajectory, rendered
//! and written as a transaction (a temporary folder beside the output,
//! renamed when complete).
//!
//! The folder holds `masks.npy`, `labels.npy`, `labels.json`, `joints.npy`,
//! per-frame PNGs and `depth.npy` as asked, `ik.json` for actions (IK
//! residuals per frame) and `limits.json` when joints leave their limits.

use crate::actions::{
    actions_to_joints, check_joint_trajectory, write_ik_report, ActionError, FrameResidual,
    Trajectory,
};
use crate::camera::{read_poses_npy, CameraError, CameraTrack, MAX_IMAGE_SIDE};
use crate::embodiment::Embodiment;
use crate::kinematics::IkOptions;
use crate::masks::{
    check_render_size, empty_masks_warning, render_track, render_track_labels, write_outputs,
    WriteError, WriteOptions,
};
use crate::raster::RenderOutput;
use crate::robot::LimitViolation;
use bridgev2w_io::memory::MemoryError;
use bridgev2w_io::npy::{write_npy, NpyError};
use bridgev2w_io::output::{OutputDir, OutputError};
use bridgev2w_io::FileError;
use std::path::{Path, PathBuf};

/// Where a trajectory comes from.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum TrajectoryFile {
    /// Joint positions per frame (JSON array of arrays, CSV or `.npy`), in
    /// the URDF order of the actuated joints.
    Joints(PathBuf),
    /// End-effector actions per frame (7-D `[x, y, z, roll, pitch, yaw,
    /// gripper]` per arm), turned into joints by IK.
    Actions(PathBuf),
}

impl TrajectoryFile {
    /// The file.
    pub fn path(&self) -> &Path {
        match self {
            Self::Joints(p) | Self::Actions(p) => p,
        }
    }
}

/// A failure of [`MasksJob::run`] or [`read_joint_trajectory`].
#[derive(Debug, thiserror::Error)]
pub enum MasksJobError {
    /// A bad option (named, with its value and what was expected).
    #[error("{0}")]
    Option(String),
    /// A joint file whose width is not the robot's number of joints (the
    /// message names the file, both widths, the joints and a hint).
    #[error("{0}")]
    JointWidth(String),
    /// The trajectory file.
    #[error(transparent)]
    Action(#[from] ActionError),
    /// The camera file or its poses.
    #[error(transparent)]
    Camera(#[from] CameraError),
    /// More than memory allows.
    #[error(transparent)]
    Memory(#[from] MemoryError),
    /// The output folder.
    #[error(transparent)]
    Output(#[from] OutputError),
    /// Writing masks or labels.
    #[error(transparent)]
    Write(#[from] WriteError),
    /// Writing `joints.npy`.
    #[error(transparent)]
    Npy(#[from] NpyError),
    /// Writing `ik.json` or `limits.json`.
    #[error(transparent)]
    File(#[from] FileError),
}

/// What a mask folder is made from.
#[derive(Debug, Clone)]
pub struct MasksJob {
    /// The camera JSON (intrinsics at its own size; rescaled to `width` x `height`).
    pub camera: PathBuf,
    /// A moving camera's `world_from_camera` per frame, `.npy [T, 4, 4]`,
    /// replacing the camera file's pose.
    pub camera_poses: Option<PathBuf>,
    /// The trajectory.
    pub trajectory: TrajectoryFile,
    /// Output width in pixels.
    pub width: u32,
    /// Output height in pixels.
    pub height: u32,
    /// The output folder.
    pub out: PathBuf,
    /// Replace an existing `out` as a whole.
    pub overwrite: bool,
    /// Render frames whose IK target is out of reach (flagged in `ik.json`)
    /// instead of failing.
    pub allow_ik_residual: bool,
    /// IK position tolerance, millimetres.
    pub ik_tol_mm: f64,
    /// IK rotation tolerance, degrees.
    pub ik_tol_deg: f64,
    /// PNGs and depth.
    pub write: WriteOptions,
    /// Further files the output must not overlap (e.g. the URDF).
    pub other_inputs: Vec<PathBuf>,
}

/// A stage of [`MasksJob::run`], for progress displays.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MasksProgress {
    /// Inverse kinematics of this many frames begins.
    Ik(usize),
    /// Rendering of this many frames begins.
    Rendering(usize),
    /// One frame rendered.
    Rendered,
    /// Rendering finished.
    RenderDone,
}

/// What [`MasksJob::run`] wrote.
#[derive(Debug, Clone)]
pub struct MasksRun {
    /// The committed folder.
    pub out: PathBuf,
    /// Frames written.
    pub frames: usize,
    /// Their size.
    pub width: u32,
    /// Their size.
    pub height: u32,
    /// The robot's name.
    pub robot: String,
    /// Frames whose mask is empty.
    pub empty_frames: Vec<usize>,
    /// Joints outside their limits (rendered as given, listed in `limits.json`).
    pub violations: Vec<LimitViolation>,
    /// Frames whose IK target was not reached within tolerance.
    pub ik_missed: Vec<usize>,
}

impl MasksRun {
    /// The warnings to show (limits, IK misses, empty masks), one per line.
    pub fn warnings(&self) -> Vec<String> {
        let mut lines: Vec<String> = self
            .violations
            .iter()
            .map(|v| {
                format!(
                    "warning: {v}; rendered as given, not clamped (see {})",
                    self.out.join("limits.json").display()
                )
            })
            .collect();
        if !self.ik_missed.is_empty() {
            lines.push(format!(
                "warning: IK did not reach the target within tolerance in {} frame(s) (first: {:?}); see {}",
                self.ik_missed.len(),
                &self.ik_missed[..self.ik_missed.len().min(10)],
                self.out.join("ik.json").display()
            ));
        }
        lines.extend(empty_masks_warning(&self.empty_frames, self.frames));
        lines
    }

    /// The one-line summary.
    pub fn summary(&self) -> String {
        format!(
            "wrote {} frames ({}x{}) of robot \"{}\" to {}",
            self.frames,
            self.width,
            self.height,
            self.robot,
            self.out.display()
        )
    }
}

/// The camera of `path` rescaled to `width` x `height`, its intrinsics
/// checked at that size.
pub fn load_camera(path: &Path, width: u32, height: u32) -> Result<CameraTrack, MasksJobError> {
    let max = MAX_IMAGE_SIDE;
    if !(1..=max).contains(&width) || !(1..=max).contains(&height) {
        return Err(MasksJobError::Option(format!(
            "width {width}, height {height}: expected sizes of 1..={max} pixels"
        )));
    }
    let camera = CameraTrack::from_json_file(path)?.rescaled(width, height);
    camera.intrinsics.validate().map_err(|e| {
        MasksJobError::Option(format!("{} at {width}x{height}: {e}", path.display()))
    })?;
    Ok(camera)
}

/// The joint trajectory of `file` for `e`, with IK residuals per frame for
/// actions (empty for joints). `on_ik` is called before IK runs.
pub fn read_joint_trajectory(
    e: &Embodiment,
    file: &TrajectoryFile,
    ik: &IkOptions,
    allow_residual: bool,
    on_ik: &dyn Fn(usize),
) -> Result<(Vec<Vec<f64>>, Vec<FrameResidual>), MasksJobError> {
    let t = Trajectory::read(file.path())?;
    match file {
        TrajectoryFile::Joints(p) => {
            if t.dim() != e.robot.dof() {
                let hint = if t.dim() == e.action_dim() {
                    "; these look like end-effector actions: give them as actions"
                } else {
                    ""
                };
                return Err(MasksJobError::JointWidth(format!(
                    "{}: {} values per frame but robot \"{}\" has {} actuated joints ({}); see `bridgev2w robot-info --robot {}`{hint}",
                    p.display(),
                    t.dim(),
                    e.robot.name,
                    e.robot.dof(),
                    e.robot.dof_names().join(", "),
                    e.robot.source_name,
                )));
            }
            check_joint_trajectory(&e.robot, &t)?;
            Ok((t.rows, Vec::new()))
        }
        TrajectoryFile::Actions(_) => {
            on_ik(t.len());
            let r = actions_to_joints(&e.robot, &e.end_effectors, &t, &e.home, ik, allow_residual)?;
            Ok(r)
        }
    }
}

/// Renders every frame of `joints` from `camera`: labels and depth maps
/// with `depth`, else labels alone (`depth_m` left empty), the faster path
/// when only masks and labels are written. `tick` is called per frame.
pub fn render_frames(
    e: &Embodiment,
    camera: &CameraTrack,
    joints: &[Vec<f64>],
    depth: bool,
    tick: &(dyn Fn() + Sync),
) -> Vec<RenderOutput> {
    if depth {
        return render_track(&e.robot, camera, joints, tick);
    }
    let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
    render_track_labels(&e.robot, camera, joints, tick)
        .into_iter()
        .map(|labels| RenderOutput {
            width,
            height,
            labels,
            depth_m: Vec::new(),
        })
        .collect()
}

impl MasksJob {
    /// The files the job reads: `out` equal to, inside or containing one is refused.
    pub fn inputs(&self) -> Vec<&Path> {
        let mut inputs: Vec<&Path> = self.other_inputs.iter().map(PathBuf::as_path).collect();
        inputs.push(&self.camera);
        inputs.extend(self.camera_poses.as_deref());
        inputs.push(self.trajectory.path());
        inputs
    }

    /// Reads, checks, renders and writes the folder (nothing is written
    /// before every input has been checked).
    pub fn run(
        &self,
        e: &Embodiment,
        progress: &(dyn Fn(MasksProgress) + Sync),
    ) -> Result<MasksRun, MasksJobError> {
        let mut camera = load_camera(&self.camera, self.width, self.height)?;
        if let Some(p) = &self.camera_poses {
            camera = camera.with_poses(read_poses_npy(p)?);
        }
        if !(self.ik_tol_mm > 0.0 && self.ik_tol_deg > 0.0) {
            return Err(MasksJobError::Option(format!(
                "IK tolerances {} mm, {} deg: expected positive tolerances",
                self.ik_tol_mm, self.ik_tol_deg
            )));
        }
        let ik = IkOptions {
            position_tolerance_m: self.ik_tol_mm * 1e-3,
            rotation_tolerance_rad: self.ik_tol_deg.to_radians(),
            ..IkOptions::default()
        };
        let (joints, residuals) =
            read_joint_trajectory(e, &self.trajectory, &ik, self.allow_ik_residual, &|n| {
                progress(MasksProgress::Ik(n))
            })?;
        let origin = self.camera_poses.as_deref().unwrap_or(&self.camera);
        camera.check(&e.robot, joints.len(), &origin.display().to_string())?;
        let frames_name = format!("{}: frames", self.trajectory.path().display());
        check_render_size(
            &frames_name,
            joints.len(),
            self.width,
            self.height,
            self.write.depth,
        )?;
        let violations = e.robot.limit_violations(&joints, 1e-6);
        let out = OutputDir::create_for(&self.out, self.overwrite, &self.inputs())?;
        progress(MasksProgress::Rendering(joints.len()));
        let frames = render_frames(e, &camera, &joints, self.write.depth, &|| {
            progress(MasksProgress::Rendered)
        });
        progress(MasksProgress::RenderDone);
        let written = write_outputs(out.path(), &e.robot, &frames, self.write)?;
        let flat: Vec<f64> = joints.iter().flatten().copied().collect();
        let shape = [joints.len(), e.robot.dof()];
        write_npy(&out.path().join("joints.npy"), &shape, &flat)?;
        if !residuals.is_empty() {
            write_ik_report(out.path(), &residuals)?;
        }
        if !violations.is_empty() {
            let p = out.path().join("limits.json");
            let text = serde_json::to_string_pretty(&violations)
                .map_err(|e| MasksJobError::Option(format!("{}: {e}", p.display())))?;
            bridgev2w_io::atomic::write_atomic(&p, text.as_bytes())?;
        }
        out.commit()?;
        Ok(MasksRun {
            out: self.out.clone(),
            frames: frames.len(),
            width: self.width,
            height: self.height,
            robot: e.robot.name.clone(),
            empty_frames: written.empty_frames,
            violations,
            ik_missed: residuals
                .iter()
                .filter(|r| !r.reached)
                .map(|r| r.frame)
                .collect(),
        })
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use crate::camera::{Camera, Intrinsics};
    use nalgebra::{Point3, Vector3};

    fn fixture(dir: &Path, rows: &[Vec<f64>]) -> MasksJob {
        let k = Intrinsics::centered(80.0, 64, 48);
        let eye = Point3::new(1.6, 0.0, 0.8);
        let up = Vector3::z();
        let cam = Camera::look_at(k, eye, Point3::new(0.0, 0.0, 0.4), up).unwrap();
        std::fs::write(dir.join("camera.json"), cam.to_json()).unwrap();
        let text = serde_json::to_string(rows).unwrap();
        std::fs::write(dir.join("joints.json"), text).unwrap();
        MasksJob {
            camera: dir.join("camera.json"),
            camera_poses: None,
            trajectory: TrajectoryFile::Joints(dir.join("joints.json")),
            width: 64,
            height: 48,
            out: dir.join("out"),
            overwrite: false,
            allow_ik_residual: false,
            ik_tol_mm: 1.0,
            ik_tol_deg: 0.5,
            write: WriteOptions {
                pngs: true,
                depth: false,
            },
            other_inputs: Vec::new(),
        }
    }

    #[test]
    fn a_job_writes_the_folder_and_refuses_to_replace_it() {
        let e = Embodiment::builtin("franka").unwrap();
        let tmp = tempfile::tempdir().unwrap();
        let job = fixture(tmp.path(), &[e.home.clone(), e.home.clone()]);
        let run = job.run(&e, &|_| {}).unwrap();
        assert_eq!((run.frames, run.width, run.height), (2, 64, 48));
        assert!(run.empty_frames.is_empty(), "the arm is in view");
        for f in [
            "masks.npy",
            "labels.npy",
            "labels.json",
            "joints.npy",
            "frames/000001.png",
        ] {
            assert!(tmp.path().join("out").join(f).is_file(), "{f}");
        }
        assert!(!tmp.path().join("out/ik.json").exists());
        let e2 = job.run(&e, &|_| {}).unwrap_err().to_string();
        assert!(e2.contains("already exists"), "{e2}");
    }

    #[test]
    fn actions_given_as_joints_are_refused_with_a_hint() {
        let e = Embodiment::builtin("franka").unwrap();
        let tmp = tempfile::tempdir().unwrap();
        let rows = vec![vec![0.4, 0.0, 0.4, 3.1, 0.0, 0.0, 0.0]; 2];
        assert_eq!(rows[0].len(), e.action_dim());
        let job = fixture(tmp.path(), &rows);
        let err = job.run(&e, &|_| {}).unwrap_err().to_string();
        assert!(
            err.contains("joints.json: 7 values per frame")
                && err.contains("look like end-effector actions"),
            "{err}"
        );
        assert!(!tmp.path().join("out").exists(), "nothing written");
    }
}
