//! `bridgev2w masks`.

pub use crate::progress::progress_bar;
use anyhow::{bail, Context, Result};
use bridgev2w_embodiment::actions::{
    actions_to_joints, check_joint_trajectory, FrameResidual, Trajectory,
};
use bridgev2w_embodiment::camera::{read_poses_npy, CameraTrack};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::IkOptions;
use bridgev2w_embodiment::masks::{render_track, render_track_labels, write_outputs, WriteOptions};
use bridgev2w_embodiment::raster::RenderOutput;
use bridgev2w_embodiment::robot::LoadOptions;
use bridgev2w_io::npy::write_npy;
use bridgev2w_io::output::OutputDir;
use indicatif::ProgressBar;
use std::path::{Path, PathBuf};

/// Which robot, shared by several commands.
#[derive(Debug, Clone, clap::Args)]
pub struct RobotArgs {
    /// Built-in robot (see `robot-info --list`) or a URDF file.
    #[arg(long)]
    pub robot: String,
    /// Directory searched for package:// and relative mesh paths (repeatable).
    #[arg(long = "mesh-path", value_name = "DIR")]
    pub mesh_path: Vec<PathBuf>,
    /// The link each arm's action poses are of (repeat per arm, in action
    /// order): required with a URDF file; with a built-in robot it replaces
    /// its TCP (e.g. the flange panda_link8, whose poses robot logs record).
    #[arg(long = "ee-link", value_name = "LINK")]
    pub ee_link: Vec<String>,
    /// Gripper joint driven by each arm's gripper value (URDF files; same order as --ee-link).
    #[arg(long = "gripper-joint", value_name = "JOINT")]
    pub gripper_joint: Vec<String>,
}

impl RobotArgs {
    /// The URDF file `--robot` names, when it names a file (not a built-in
    /// robot): an input an output must not overlap.
    pub fn urdf_file(&self) -> Option<&Path> {
        let p = Path::new(&self.robot);
        p.is_file().then_some(p)
    }

    pub fn load(&self) -> Result<Embodiment> {
        for d in &self.mesh_path {
            if !d.is_dir() {
                bail!("--mesh-path {}: not a directory", d.display());
            }
        }
        let options = LoadOptions {
            mesh_search_paths: self.mesh_path.clone(),
            use_ros_package_path: true,
            ..LoadOptions::default()
        };
        Ok(Embodiment::load(
            &self.robot,
            &options,
            &self.ee_link,
            &self.gripper_joint,
        )?)
    }
}

/// Arguments of `masks`.
#[derive(Debug, clap::Args)]
#[command(group(clap::ArgGroup::new("input").required(true).args(["joints", "actions"])))]
pub struct MasksArgs {
    #[command(flatten)]
    pub robot: RobotArgs,
    /// Camera JSON: fx, fy, cx, cy, width, height, optional distortion, and
    /// world_from_camera (4x4 row-major), extrinsics_xyz_rpy,
    /// world_from_camera_per_frame (a moving camera) or parent_link (+
    /// link_from_camera: a camera mounted on a robot link).
    #[arg(long)]
    pub camera: PathBuf,
    /// A moving camera's world_from_camera per frame, .npy [T, 4, 4]
    /// (e.g. AgiBot World's camera-to-base extrinsics); replaces the
    /// camera file's pose.
    #[arg(long, value_name = "NPY")]
    pub camera_poses: Option<PathBuf>,
    /// Joint positions per frame (JSON array of arrays, CSV or .npy), URDF order of actuated joints.
    #[arg(long)]
    pub joints: Option<PathBuf>,
    /// End-effector actions per frame: 7-D [x,y,z,roll,pitch,yaw,gripper] per arm.
    #[arg(long)]
    pub actions: Option<PathBuf>,
    /// Output width (the camera intrinsics are rescaled).
    #[arg(long, default_value_t = 720)]
    pub width: u32,
    /// Output height (the camera intrinsics are rescaled).
    #[arg(long, default_value_t = 480)]
    pub height: u32,
    /// Output directory (written to a temporary folder beside it, then renamed; an existing one
    /// is refused unless --overwrite).
    #[arg(long)]
    pub out: PathBuf,
    /// Replace an existing --out folder (as a whole: no earlier file stays).
    #[arg(long)]
    pub overwrite: bool,
    /// Render frames whose IK target is out of reach (flagged in ik.json) instead of failing.
    #[arg(long)]
    pub allow_ik_residual: bool,
    /// IK position tolerance in millimetres.
    #[arg(long, default_value_t = 1.0)]
    pub ik_tol_mm: f64,
    /// IK rotation tolerance in degrees.
    #[arg(long, default_value_t = 0.5)]
    pub ik_tol_deg: f64,
    /// Also write depth.npy (float32 metres, inf = background).
    #[arg(long)]
    pub depth: bool,
    /// Skip the per-frame PNGs.
    #[arg(long)]
    pub no_png: bool,
}

impl MasksArgs {
    /// The files `masks` reads (a URDF, the camera, its poses, the
    /// trajectory): `--out` equal to, inside or containing one is refused.
    pub fn inputs(&self) -> Vec<&Path> {
        let files = [&self.camera_poses, &self.joints, &self.actions];
        let mut inputs: Vec<&Path> = self.robot.urdf_file().into_iter().collect();
        inputs.push(&self.camera);
        inputs.extend(files.into_iter().flatten().map(PathBuf::as_path));
        inputs
    }
}

pub fn load_camera(path: &Path, width: u32, height: u32) -> Result<CameraTrack> {
    let max = bridgev2w_embodiment::camera::MAX_IMAGE_SIDE;
    if !(1..=max).contains(&width) || !(1..=max).contains(&height) {
        bail!("--width {width} --height {height}: expected sizes of 1..={max} pixels");
    }
    let camera = CameraTrack::from_json_file(path)?;
    let camera = camera.rescaled(width, height);
    camera
        .intrinsics
        .validate()
        .with_context(|| format!("{} at --width {width} --height {height}", path.display()))?;
    Ok(camera)
}

/// Joint trajectory from `--joints` or `--actions`, with IK residuals for actions.
pub fn joint_trajectory(
    e: &Embodiment,
    joints: Option<&Path>,
    actions: Option<&Path>,
    ik: &IkOptions,
    allow_residual: bool,
) -> Result<(Vec<Vec<f64>>, Vec<FrameResidual>)> {
    if let Some(p) = joints {
        let t = Trajectory::read(p)?;
        if t.dim() != e.robot.dof() {
            bail!(
                "{}: {} values per frame but robot \"{}\" has {} actuated joints ({}); see `bridgev2w robot-info --robot {}`{}",
                p.display(),
                t.dim(),
                e.robot.name,
                e.robot.dof(),
                e.robot.dof_names().join(", "),
                e.robot.source_name,
                if t.dim() == e.action_dim() { "; these look like end-effector actions: use --actions" } else { "" }
            );
        }
        check_joint_trajectory(&e.robot, &t)?;
        return Ok((t.rows, Vec::new()));
    }
    let Some(p) = actions else {
        bail!("give --joints or --actions")
    };
    let t = Trajectory::read(p)?;
    let spinner = ProgressBar::new_spinner()
        .with_message(format!("inverse kinematics for {} frames", t.len()));
    let result = actions_to_joints(&e.robot, &e.end_effectors, &t, &e.home, ik, allow_residual);
    spinner.finish_and_clear();
    Ok(result?)
}

/// Renders every frame of `joints` from `camera` with a progress bar:
/// labels and depth maps with `depth`, else labels alone (`depth_m` left
/// empty), the faster path when only masks and labels are written.
pub fn render_with_progress(
    e: &Embodiment,
    camera: &CameraTrack,
    joints: &[Vec<f64>],
    depth: bool,
) -> Vec<RenderOutput> {
    let pb = progress_bar(joints.len(), "rendering masks");
    let tick = || pb.inc(1);
    let frames = if depth {
        render_track(&e.robot, camera, joints, &tick)
    } else {
        let (width, height) = (camera.intrinsics.width, camera.intrinsics.height);
        render_track_labels(&e.robot, camera, joints, &tick)
            .into_iter()
            .map(|labels| RenderOutput {
                width,
                height,
                labels,
                depth_m: Vec::new(),
            })
            .collect()
    };
    pb.finish_and_clear();
    frames
}

/// Writes the residual report `ik.json`.
pub fn write_ik_report(dir: &Path, residuals: &[FrameResidual]) -> Result<()> {
    Ok(bridgev2w_embodiment::actions::write_ik_report(
        dir, residuals,
    )?)
}

pub fn run(args: &MasksArgs) -> Result<()> {
    let e = args.robot.load()?;
    let mut camera = load_camera(&args.camera, args.width, args.height)?;
    if let Some(p) = &args.camera_poses {
        camera = camera.with_poses(read_poses_npy(p)?);
    }
    if !(args.ik_tol_mm > 0.0 && args.ik_tol_deg > 0.0) {
        bail!(
            "--ik-tol-mm {} --ik-tol-deg {}: expected positive tolerances",
            args.ik_tol_mm,
            args.ik_tol_deg
        );
    }
    let ik = IkOptions {
        position_tolerance_m: args.ik_tol_mm * 1e-3,
        rotation_tolerance_rad: args.ik_tol_deg.to_radians(),
        ..IkOptions::default()
    };
    let (joints, residuals) = joint_trajectory(
        &e,
        args.joints.as_deref(),
        args.actions.as_deref(),
        &ik,
        args.allow_ik_residual,
    )?;
    let camera_origin = args
        .camera_poses
        .as_deref()
        .unwrap_or(&args.camera)
        .display()
        .to_string();
    camera.check(&e.robot, joints.len(), &camera_origin)?;
    let source = match (&args.joints, &args.actions) {
        (Some(p), _) => format!("--joints {}: frames", p.display()),
        (None, Some(p)) => format!("--actions {}: frames", p.display()),
        (None, None) => "frames".to_owned(),
    };
    bridgev2w_embodiment::masks::check_render_size(
        &source,
        joints.len(),
        args.width,
        args.height,
        args.depth,
    )?;
    let violations = e.robot.limit_violations(&joints, 1e-6);
    let out = OutputDir::create_for(&args.out, args.overwrite, &args.inputs())?;
    let frames = render_with_progress(&e, &camera, &joints, args.depth);
    let written = write_outputs(
        out.path(),
        &e.robot,
        &frames,
        WriteOptions {
            pngs: !args.no_png,
            depth: args.depth,
        },
    )?;
    let flat: Vec<f64> = joints.iter().flatten().copied().collect();
    write_npy(
        &out.path().join("joints.npy"),
        &[joints.len(), e.robot.dof()],
        &flat,
    )?;
    if !residuals.is_empty() {
        write_ik_report(out.path(), &residuals)?;
    }
    if !violations.is_empty() {
        let text = serde_json::to_string_pretty(&violations)?;
        bridgev2w_io::atomic::write_atomic(&out.path().join("limits.json"), text.as_bytes())?;
    }
    out.commit()?;
    for v in &violations {
        eprintln!(
            "warning: {v}; rendered as given, not clamped (see {})",
            args.out.join("limits.json").display()
        );
    }
    if !residuals.is_empty() {
        let missed: Vec<usize> = residuals
            .iter()
            .filter(|r| !r.reached)
            .map(|r| r.frame)
            .collect();
        if !missed.is_empty() {
            eprintln!(
                "warning: IK did not reach the target within tolerance in {} frame(s) (first: {:?}); see {}",
                missed.len(),
                &missed[..missed.len().min(10)],
                args.out.join("ik.json").display()
            );
        }
    }
    report_empty(&written.empty_frames, frames.len());
    println!(
        "wrote {} frames ({}x{}) of robot \"{}\" to {}",
        frames.len(),
        args.width,
        args.height,
        e.robot.name,
        args.out.display()
    );
    Ok(())
}

pub fn report_empty(empty: &[usize], total: usize) {
    if let Some(w) = bridgev2w_embodiment::masks::empty_masks_warning(empty, total) {
        eprintln!("{w}");
    }
}
