//! `bridgev2w masks`.

pub use crate::progress::progress_bar;
use anyhow::{bail, Result};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::masks::WriteOptions;
use bridgev2w_embodiment::masks_folder::{MasksJob, MasksProgress, TrajectoryFile};
use bridgev2w_embodiment::robot::LoadOptions;
use indicatif::ProgressBar;
use std::path::{Path, PathBuf};
use std::sync::Mutex;

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

/// `--joints` or `--actions` as a trajectory file.
pub fn trajectory_file(joints: Option<&Path>, actions: Option<&Path>) -> Result<TrajectoryFile> {
    match (joints, actions) {
        (Some(p), _) => Ok(TrajectoryFile::Joints(p.to_path_buf())),
        (None, Some(p)) => Ok(TrajectoryFile::Actions(p.to_path_buf())),
        (None, None) => bail!("give --joints or --actions"),
    }
}

/// Progress of a masks job on the terminal: a spinner for IK, a bar for rendering.
pub fn masks_progress() -> impl Fn(MasksProgress) + Sync {
    let bar: Mutex<Option<ProgressBar>> = Mutex::new(None);
    move |p| {
        let mut bar = bar.lock().unwrap_or_else(|e| e.into_inner());
        match p {
            MasksProgress::Ik(n) => {
                *bar = Some(crate::progress::spinner(&format!(
                    "inverse kinematics for {n} frames"
                )))
            }
            MasksProgress::Rendering(n) => {
                if let Some(b) = bar.take() {
                    b.finish_and_clear();
                }
                *bar = Some(progress_bar(n, "rendering masks"));
            }
            MasksProgress::Rendered => {
                if let Some(b) = bar.as_ref() {
                    b.inc(1);
                }
            }
            MasksProgress::RenderDone => {
                if let Some(b) = bar.take() {
                    b.finish_and_clear();
                }
            }
        }
    }
}

pub fn run(args: &MasksArgs) -> Result<()> {
    let e = args.robot.load()?;
    let job = MasksJob {
        camera: args.camera.clone(),
        camera_poses: args.camera_poses.clone(),
        trajectory: trajectory_file(args.joints.as_deref(), args.actions.as_deref())?,
        width: args.width,
        height: args.height,
        out: args.out.clone(),
        overwrite: args.overwrite,
        allow_ik_residual: args.allow_ik_residual,
        ik_tol_mm: args.ik_tol_mm,
        ik_tol_deg: args.ik_tol_deg,
        write: WriteOptions {
            pngs: !args.no_png,
            depth: args.depth,
        },
        other_inputs: args
            .robot
            .urdf_file()
            .map(Path::to_path_buf)
            .into_iter()
            .collect(),
    };
    let run = job.run(&e, &masks_progress())?;
    for w in run.warnings() {
        eprintln!("{w}");
    }
    println!("{}", run.summary());
    Ok(())
}
