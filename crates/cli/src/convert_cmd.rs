//! `bridgev2w convert`: raw DROID / AgiBot World episodes to a LeRobot v3.0
//! training dataset with `calc` embodiment masks (one episode per camera).

use crate::masks_cmd::progress_bar;
use anyhow::Result;
use bridgev2w_data::raw::agibot::GripperSource;
use bridgev2w_data::raw::check_camera_list;
use bridgev2w_data::raw::ctrl_world::SplitRule;
use bridgev2w_data::raw::droid_calibration::MissingCalibration;
use bridgev2w_data::raw::request::{ConvertRequest, SourceFormat};
use bridgev2w_data::raw::source::ConvertProgress;
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::robot::LoadOptions;
use std::path::PathBuf;

/// Arguments of `convert`.
#[derive(Debug, clap::Args)]
pub struct ConvertArgs {
    /// Source layout: droid (DROID raw episodes: metadata_*.json,
    /// trajectory.h5, recordings/MP4), agibot (AgiBot World: proprio_stats,
    /// parameters, observations) or ctrl-world (DROID episodes of the
    /// Ctrl-World layout: annotation/<split>/<id>.json,
    /// videos/<split>/<id>/{0,1,2}.mp4; cameras from --camera).
    #[arg(long, value_parser = parse_from_str::<SourceFormat>)]
    format: SourceFormat,
    /// Source: a DROID directory (searched for episodes) or an AgiBot World root.
    src: PathBuf,
    /// Output dataset directory (must not exist unless --overwrite, nor
    /// overlap SRC; written to a temporary folder beside it, then renamed).
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing --out (once the new dataset is complete).
    #[arg(long)]
    overwrite: bool,
    /// Robot: built-in name or URDF file (default: franka-robotiq for DROID, agibot-g1 for AgiBot World).
    #[arg(long)]
    robot: Option<String>,
    /// End-effector link per arm (URDF robots only).
    #[arg(long = "ee-link")]
    ee_links: Vec<String>,
    /// Gripper joint per arm (URDF robots only).
    #[arg(long = "gripper-joint")]
    gripper_joints: Vec<String>,
    /// The robot's names for the recorded joint columns, comma-separated
    /// (default: the dataset's names, which the built-in robots use).
    #[arg(long)]
    joint_names: Option<String>,
    /// Output width (pixels, even).
    #[arg(long, default_value_t = 96)]
    width: usize,
    /// Output height (pixels, even).
    #[arg(long, default_value_t = 64)]
    height: usize,
    /// Frame rate recorded in the dataset (DROID: 15, AgiBot World: 30, ctrl-world: 5).
    #[arg(long)]
    fps: Option<u32>,
    /// DROID: camera intrinsics: DROID's published intrinsics.json
    /// ({"<episode id>": {"<serial>": [fx, cx, fy, cy]}} at 1280x720, scaled to
    /// the video's size) or {"<serial>": {"fx","fy","cx","cy","width","height"}}.
    #[arg(long)]
    intrinsics: Option<PathBuf>,
    /// DROID: extrinsics files, repeatable, earlier first: DROID's published
    /// cam2base_extrinsics.json / cam2base_extrinsic_superset.json
    /// ({"<episode id>": {..., "<serial>": [x,y,z,rx,ry,rz]}}, left image) or
    /// {"<episode id>": {"<serial>_left": [..]}}. Cameras none of them
    /// calibrates use the recorded extrinsics (see --missing-calibration).
    #[arg(long)]
    calibration: Vec<PathBuf>,
    /// DROID: a camera without published extrinsics: "recorded" (use the
    /// extrinsics in trajectory.h5, counted in the report) or "error".
    #[arg(long, default_value = "recorded", value_parser = parse_from_str::<MissingCalibration>)]
    missing_calibration: MissingCalibration,
    /// ctrl-world: ROLE=CAMERA_JSON per exterior camera to convert (ext1 is
    /// 0.mp4, ext2 1.mp4), e.g. the camera.json of `bridgev2w calibrate` on
    /// the rig; repeatable. The layout has no calibration of its own.
    #[arg(long = "camera", value_name = "ROLE=JSON")]
    camera_json: Vec<String>,
    /// ctrl-world: only these episodes, comma-separated collection/split/id
    /// (e.g. droid_new_setup_full/drawer/val/0000).
    #[arg(long)]
    include: Option<String>,
    /// ctrl-world: EPISODE[:ROLE]=SPLIT, the split of the matching views
    /// instead of --split, or - for not converted; EPISODE collection/split/id
    /// or *; first match wins; repeatable (e.g. "*:ext2=-" and
    /// "droid_new_setup/val/0002:ext2=unseen_camera": a held-out view).
    #[arg(long, value_name = "EPISODE[:ROLE]=SPLIT", value_parser = parse_from_str::<SplitRule>)]
    split_rule: Vec<SplitRule>,
    /// Cameras, comma-separated (DROID roles ext1,ext2,wrist; AgiBot names head,hand_left,hand_right).
    #[arg(long)]
    cameras: Option<String>,
    /// AgiBot World: gripper closure from "action" (action/effector/position,
    /// 0..1), "state" (state/effector/position through --gripper-range) or
    /// "auto" (action when recorded, else state).
    #[arg(long, default_value = "auto", value_parser = parse_from_str::<GripperSource>)]
    gripper_source: GripperSource,
    /// AgiBot World: state/effector/position readings when open and closed,
    /// "OPEN,CLOSED"; readings outside are clamped and counted in the report.
    #[arg(long, default_value = "35,120")]
    gripper_range: String,
    /// Split recorded for every episode.
    #[arg(long, default_value = "train")]
    split: String,
    /// Skip episodes/cameras that fail (listed in OUT/skipped.json and
    /// OUT/conversion_report.json) instead of stopping.
    #[arg(long)]
    skip_bad: bool,
    /// Convert at most this many episodes.
    #[arg(long)]
    limit: Option<usize>,
}

fn parse_from_str<T: std::str::FromStr<Err = String>>(s: &str) -> Result<T, String> {
    s.parse()
}

fn list(s: &Option<String>) -> Option<Vec<String>> {
    s.as_ref().map(|s| {
        s.split(',')
            .map(|x| x.trim().to_string())
            .filter(|x| !x.is_empty())
            .collect()
    })
}

/// The `--cameras` list: refused when it names no camera or one twice
/// (the library's check, which the Python package shares).
fn camera_list(s: &Option<String>) -> Result<Option<Vec<String>>> {
    let Some(c) = list(s) else {
        return Ok(None);
    };
    let text = s.as_deref().unwrap_or_default();
    check_camera_list(&c).map_err(|e| anyhow::anyhow!("--cameras {text:?}: {e}"))?;
    Ok(Some(c))
}

/// `--camera ROLE=JSON` flags as (role, file) pairs.
fn camera_files(flags: &[String]) -> Result<Vec<(String, PathBuf)>> {
    flags
        .iter()
        .map(|c| {
            c.split_once('=')
                .map(|(r, p)| (r.trim().to_string(), PathBuf::from(p)))
                .ok_or_else(|| {
                    anyhow::anyhow!("--camera {c:?}: expected ROLE=CAMERA_JSON (ROLE ext1 or ext2)")
                })
        })
        .collect()
}

/// `--gripper-range OPEN,CLOSED`.
fn gripper_range(text: &str) -> Result<(f64, f64)> {
    text.split_once(',')
        .and_then(|(a, b)| Some((a.trim().parse::<f64>().ok()?, b.trim().parse::<f64>().ok()?)))
        .ok_or_else(|| {
            anyhow::anyhow!("--gripper-range {text:?}: expected OPEN,CLOSED (two numbers)")
        })
}

pub fn run(args: &ConvertArgs) -> Result<()> {
    let request = ConvertRequest {
        overwrite: args.overwrite,
        joint_names: list(&args.joint_names),
        width: args.width,
        height: args.height,
        fps: args.fps,
        intrinsics: args.intrinsics.clone(),
        calibration: args.calibration.clone(),
        missing_calibration: args.missing_calibration,
        cameras: camera_list(&args.cameras)?,
        camera_json: camera_files(&args.camera_json)?,
        include: list(&args.include),
        split_rules: args.split_rule.clone(),
        gripper_source: args.gripper_source,
        gripper_range: gripper_range(&args.gripper_range)?,
        split: args.split.clone(),
        skip_bad: args.skip_bad,
        limit: args.limit,
        ..ConvertRequest::new(args.format, args.src.clone(), args.out.clone())
    };
    let robot = (args.robot.as_deref()).unwrap_or(args.format.default_robot());
    let embodiment = Embodiment::load(
        robot,
        &LoadOptions::default(),
        &args.ee_links,
        &args.gripper_joints,
    )?;
    let pb = std::sync::OnceLock::new();
    let report = request.run(&embodiment, &|p| match p {
        ConvertProgress::Found(n) => {
            let _ = pb.set(progress_bar(n, "converting episodes"));
        }
        ConvertProgress::Done(_) => {
            if let Some(pb) = pb.get() {
                pb.inc(1);
            }
        }
    });
    if let Some(pb) = pb.get() {
        pb.finish_and_clear();
    }
    crate::print_stdout(&report?.summary(&request, robot))
}
