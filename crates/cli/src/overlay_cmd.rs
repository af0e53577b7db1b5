//! `bridgev2w overlay`: rendered masks over a camera's real frames, scored
//! against a ground truth where one is given.

use crate::masks_cmd::{joint_trajectory, progress_bar, RobotArgs};
use anyhow::{bail, Result};
use bridgev2w_data::overlay::{overlay, FrameSource, OverlayOptions};
use bridgev2w_embodiment::camera::{read_poses_npy, CameraTrack};
use bridgev2w_embodiment::kinematics::IkOptions;
use bridgev2w_io::output::OutputDir;
use std::path::{Path, PathBuf};

/// Arguments of `overlay`.
#[derive(Debug, clap::Args)]
#[command(group(clap::ArgGroup::new("input").required(true).args(["joints", "actions"])))]
pub struct OverlayArgs {
    #[command(flatten)]
    robot: RobotArgs,
    /// Camera JSON (the masks format; moving cameras included); its
    /// intrinsics are scaled to the frames' size.
    #[arg(long)]
    camera: PathBuf,
    /// A moving camera's world_from_camera per frame, .npy [T, 4, 4].
    #[arg(long, value_name = "NPY")]
    camera_poses: Option<PathBuf>,
    /// Joint positions per frame (JSON, CSV or .npy), the robot's joint order.
    #[arg(long)]
    joints: Option<PathBuf>,
    /// End-effector actions per frame (7-D per arm; see --ee-link).
    #[arg(long)]
    actions: Option<PathBuf>,
    /// The real frames: an .mp4 video, a .png image or a folder of .png images.
    #[arg(long)]
    frames: PathBuf,
    /// A robot segmentation of the frames (.npy [T, H, W], 0/1 or 0/255): IoU per frame.
    #[arg(long, value_name = "NPY")]
    truth_masks: Option<PathBuf>,
    /// Robot pixels the masks should cover: JSON [{"frame", "u", "v", "name"}].
    #[arg(long, value_name = "JSON")]
    truth_points: Option<PathBuf>,
    /// A truth point within this many pixels of the mask counts as covered.
    #[arg(long, default_value_t = 2.0)]
    point_tolerance_px: f64,
    /// Output folder: overlay/*.png, overlay.gif, labels.npy, scores.json.
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing --out.
    #[arg(long)]
    overwrite: bool,
    /// Render frames whose IK target is out of reach instead of failing.
    #[arg(long)]
    allow_ik_residual: bool,
}

impl OverlayArgs {
    /// The files and folders `overlay` reads (a URDF, the camera, its poses,
    /// the trajectory, the frames, the truths): `--out` equal to, inside or
    /// containing one is refused.
    fn inputs(&self) -> Vec<&Path> {
        let files = [
            &self.camera_poses,
            &self.joints,
            &self.actions,
            &self.truth_masks,
            &self.truth_points,
        ];
        let mut inputs: Vec<&Path> = self.robot.urdf_file().into_iter().collect();
        inputs.extend([self.camera.as_path(), self.frames.as_path()]);
        inputs.extend(files.into_iter().flatten().map(PathBuf::as_path));
        inputs
    }
}

pub fn run(args: &OverlayArgs) -> Result<()> {
    if !(args.point_tolerance_px.is_finite() && args.point_tolerance_px >= 0.0) {
        bail!(
            "--point-tolerance-px {}: expected a distance >= 0 (pixels)",
            args.point_tolerance_px
        );
    }
    let e = args.robot.load()?;
    let mut camera = CameraTrack::from_json_file(&args.camera)?;
    if let Some(p) = &args.camera_poses {
        camera = camera.with_poses(read_poses_npy(p)?);
    }
    let (joints, _) = joint_trajectory(
        &e,
        args.joints.as_deref(),
        args.actions.as_deref(),
        &IkOptions::default(),
        args.allow_ik_residual,
    )?;
    let options = OverlayOptions {
        frames: FrameSource::from_path(&args.frames)?,
        truth_masks: args.truth_masks.clone(),
        truth_points: args.truth_points.clone(),
        point_tolerance_px: args.point_tolerance_px,
        ..OverlayOptions::default()
    };
    let out = OutputDir::create_for(&args.out, args.overwrite, &args.inputs())?;
    let pb = progress_bar(joints.len(), "rendering masks");
    let report = overlay(&e.robot, &camera, &joints, &options, out.path(), &|| {
        pb.inc(1)
    })?;
    pb.finish_and_clear();
    out.commit()?;
    println!(
        "{} frames ({}x{}) of robot \"{}\" over {} in {}",
        report.frames,
        report.size.0,
        report.size.1,
        e.robot.name,
        args.frames.display(),
        args.out.display()
    );
    if let Some(iou) = report.mean_iou {
        println!(
            "mean IoU against {}: {iou:.4}",
            args.truth_masks
                .as_ref()
                .map_or(String::new(), |p| p.display().to_string())
        );
    }
    if report.points > 0 {
        println!(
            "truth points covered by the masks (within {} px): {} of {}",
            report.point_tolerance_px, report.points_inside, report.points
        );
    }
    Ok(())
}
