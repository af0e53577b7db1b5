//! `bridgev2w overlay`: rendered masks over a camera's real frames, scored
//! against a ground truth where one is given.

use crate::masks_cmd::{progress_bar, trajectory_file, RobotArgs};
use anyhow::Result;
use bridgev2w_data::overlay::{FrameSource, OverlayJob, OverlayOptions};
use indicatif::ProgressBar;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

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

pub fn run(args: &OverlayArgs) -> Result<()> {
    let e = args.robot.load()?;
    let job = OverlayJob {
        camera: args.camera.clone(),
        camera_poses: args.camera_poses.clone(),
        trajectory: trajectory_file(args.joints.as_deref(), args.actions.as_deref())?,
        allow_ik_residual: args.allow_ik_residual,
        frames: args.frames.clone(),
        options: OverlayOptions {
            frames: FrameSource::Images(Vec::new()),
            truth_masks: args.truth_masks.clone(),
            truth_points: args.truth_points.clone(),
            point_tolerance_px: args.point_tolerance_px,
            ..OverlayOptions::default()
        },
        out: args.out.clone(),
        overwrite: args.overwrite,
        other_inputs: args
            .robot
            .urdf_file()
            .map(Path::to_path_buf)
            .into_iter()
            .collect(),
    };
    let pb = OnceLock::new();
    let report = job.run(
        &e,
        &|n| {
            let _ = pb.set(progress_bar(n, "rendering masks"));
        },
        &|| pb.get().into_iter().for_each(|b: &ProgressBar| b.inc(1)),
    );
    if let Some(b) = pb.get() {
        b.finish_and_clear();
    }
    let report = report?;
    println!(
        "{} frames ({}x{}) of robot \"{}\" over {} in {}",
        report.frames,
        report.size.0,
        report.size.1,
        e.robot.name,
        args.frames.display(),
        args.out.display()
    );
    if let (Some(iou), Some(p)) = (report.mean_iou, &args.truth_masks) {
        println!("mean IoU against {}: {iou:.4}", p.display());
    }
    if report.points > 0 {
        println!(
            "truth points covered by the masks (within {} px): {} of {}",
            report.point_tolerance_px, report.points_inside, report.points
        );
    }
    Ok(())
}
