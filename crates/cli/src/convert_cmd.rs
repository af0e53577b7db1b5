//! `bridgev2w convert`: raw DROID / AgiBot World episodes to a LeRobot v3.0
//! training dataset with `calc` embodiment masks (one episode per camera).

use crate::masks_cmd::progress_bar;
use anyhow::{bail, Result};
use bridgev2w_data::raw::agibot::{AgibotOptions, GripperSource};
use bridgev2w_data::raw::check_camera_list;
use bridgev2w_data::raw::convert::{ConvertOptions, REPORT_FILE};
use bridgev2w_data::raw::ctrl_world::{self, CtrlWorldOptions, SplitRule};
use bridgev2w_data::raw::droid::DroidOptions;
use bridgev2w_data::raw::droid_calibration::MissingCalibration;
use bridgev2w_data::raw::source::{convert_source, ConvertProgress, RawSource};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::robot::LoadOptions;
use std::path::PathBuf;

/// Source layouts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// DROID raw episodes (metadata_*.json, trajectory.h5, recordings/MP4).
    Droid,
    /// AgiBot World (proprio_stats, parameters, observations).
    Agibot,
    /// DROID episodes of the Ctrl-World layout (annotation/<split>/<id>.json,
    /// videos/<split>/<id>/{0,1,2}.mp4), cameras from --camera.
    CtrlWorld,
}

/// Arguments of `convert`.
#[derive(Debug, clap::Args)]
pub struct ConvertArgs {
    /// Source layout.
    #[arg(long, value_enum)]
    format: Format,
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

pub fn run(args: &ConvertArgs) -> Result<()> {
    let cameras = camera_list(&args.cameras)?;
    let options = ConvertOptions {
        width: args.width,
        height: args.height,
        fps: args.fps.unwrap_or(match args.format {
            Format::Droid => 15,
            Format::Agibot => 30,
            Format::CtrlWorld => ctrl_world::FPS,
        }),
        joint_names: list(&args.joint_names),
        skip_bad: args.skip_bad,
        split: Some(args.split.clone()),
        source_format: match args.format {
            Format::Droid => "droid",
            Format::Agibot => "agibot",
            Format::CtrlWorld => "ctrl-world",
        }
        .into(),
        overwrite: args.overwrite,
    };
    options.validate()?;
    let robot = args.robot.clone().unwrap_or_else(|| {
        match args.format {
            Format::Droid | Format::CtrlWorld => "franka-robotiq",
            Format::Agibot => "agibot-g1",
        }
        .to_string()
    });
    let embodiment = Embodiment::load(
        &robot,
        &LoadOptions::default(),
        &args.ee_links,
        &args.gripper_joints,
    )?;
    if args.format != Format::CtrlWorld
        && (!args.camera_json.is_empty() || args.include.is_some() || !args.split_rule.is_empty())
    {
        bail!("--camera/--include/--split-rule apply to --format ctrl-world");
    }
    let source = match args.format {
        Format::CtrlWorld => {
            if args.intrinsics.is_some() || !args.calibration.is_empty() || cameras.is_some() {
                bail!("--intrinsics/--calibration/--cameras apply to raw DROID and AgiBot World; the ctrl-world layout takes --camera ROLE=CAMERA_JSON");
            }
            let cameras = args
                .camera_json
                .iter()
                .map(|c| {
                    c.split_once('=')
                        .map(|(r, p)| (r.trim().to_string(), PathBuf::from(p)))
                        .ok_or_else(|| {
                            anyhow::anyhow!(
                                "--camera {c:?}: expected ROLE=CAMERA_JSON (ROLE ext1 or ext2)"
                            )
                        })
                })
                .collect::<Result<Vec<_>>>()?;
            RawSource::CtrlWorld {
                root: args.src.clone(),
                options: CtrlWorldOptions {
                    cameras,
                    include: list(&args.include),
                    split_rules: args.split_rule.clone(),
                },
            }
        }
        Format::Droid => {
            let intrinsics = args.intrinsics.as_deref().ok_or_else(|| {
                anyhow::anyhow!("--intrinsics FILE is required for DROID: the raw episodes' trajectory.h5 records no intrinsics (DROID publishes them as intrinsics.json)")
            })?;
            let mut opts = DroidOptions::from_calibration_files(intrinsics, &args.calibration)?;
            opts.missing_calibration = args.missing_calibration;
            if let Some(c) = cameras {
                opts.roles = c;
            }
            RawSource::Droid {
                root: args.src.clone(),
                options: opts,
            }
        }
        Format::Agibot => {
            if args.intrinsics.is_some() || !args.calibration.is_empty() {
                bail!("--intrinsics/--calibration apply to DROID; AgiBot World episodes carry their camera parameters");
            }
            let (open, closed) = args
                .gripper_range
                .split_once(',')
                .and_then(|(a, b)| {
                    Some((a.trim().parse::<f64>().ok()?, b.trim().parse::<f64>().ok()?))
                })
                .ok_or_else(|| {
                    anyhow::anyhow!(
                        "--gripper-range {:?}: expected OPEN,CLOSED (two numbers)",
                        args.gripper_range
                    )
                })?;
            let mut opts = AgibotOptions {
                gripper: args.gripper_source,
                gripper_open: open,
                gripper_closed: closed,
                ..AgibotOptions::default()
            };
            if let Some(c) = cameras {
                opts.cameras = c;
            }
            opts.check_cameras().map_err(anyhow::Error::msg)?;
            RawSource::Agibot {
                root: args.src.clone(),
                options: opts,
            }
        }
    };
    let pb = std::sync::OnceLock::new();
    let report = convert_source(
        &source,
        args.limit,
        &embodiment,
        &args.out,
        &options,
        &|p| match p {
            ConvertProgress::Found(n) => {
                let _ = pb.set(progress_bar(n, "converting episodes"));
            }
            ConvertProgress::Done(_) => {
                if let Some(pb) = pb.get() {
                    pb.inc(1);
                }
            }
        },
    );
    if let Some(pb) = pb.get() {
        pb.finish_and_clear();
    }
    let report = report?;
    let mut text = format!(
        "wrote {} (LeRobot v3.0): {} episodes read, {} camera episodes of {}x{} with calc masks, robot {}\n",
        args.out.display(),
        report.episodes,
        report.views_written,
        args.width,
        args.height,
        robot
    );
    if !report.skipped.is_empty() {
        text.push_str(&format!(
            "  skipped {} item(s), listed in {}:\n",
            report.skipped.len(),
            args.out.join("skipped.json").display()
        ));
        for s in &report.skipped {
            text.push_str(&format!("    {}: {}\n", s.item, s.error));
        }
    }
    if !report.ee_frames.is_empty() {
        text.push_str(&format!(
            "  actions: flange poses of {} (meta/info.json bridgev2w_source.ee_frame)\n",
            report.ee_frames.join(", ")
        ));
    }
    for (kind, notes, episodes, warning) in report.note_summary() {
        text.push_str(&format!(
            "  {}{kind}: {notes} in {episodes} episode(s)\n",
            if warning { "warning: " } else { "" }
        ));
    }
    if !report.notes.is_empty() {
        text.push_str(&format!(
            "  details: {}\n",
            args.out.join(REPORT_FILE).display()
        ));
    }
    for v in &report.empty_mask_views {
        text.push_str(&format!("  warning: {v}: the robot is outside the image in every frame (check the calibration)\n"));
    }
    crate::print_stdout(&text)
}
