//! `bridgev2w calibrate`: a fixed camera's calibration from the robot's own
//! motion in one or more episodes; `bridgev2w calibrate-study`: the same on
//! synthetic cameras whose truth is known.

use crate::masks_cmd::RobotArgs;
use anyhow::Result;
use bridgev2w_data::calibrate::droid_study::{
    droid_study_to_folder, DroidStudyOptions, DROID_FY_OVER_FX,
};
use bridgev2w_data::calibrate::marks::Marks;
use bridgev2w_data::calibrate::run::calibrate_to_folder;
use bridgev2w_data::calibrate::study::{synthetic_study_to_folder, StudyOptions};
use bridgev2w_data::calibrate::{pair_inputs, CalibrateOptions, ForegroundOptions, StaticChanges};
use bridgev2w_embodiment::camera::Camera;
use std::path::{Path, PathBuf};

/// Search and fit options shared by `calibrate` and `calibrate-study`.
#[derive(Debug, Clone, clap::Args)]
pub struct FitArgs {
    /// fy / fx of the start (and of the result unless --fit-aspect): 1 for
    /// square pixels (the default), 1.0667 (192/180) for DROID's stretched
    /// 320x192 videos (the default of `calibrate-study --droid`).
    #[arg(long)]
    fy_over_fx: Option<f64>,
    /// A known focal length: fx at the video's size in pixels (fy = fx x
    /// --fy-over-fx), kept fixed: only the pose is fitted.
    #[arg(long, value_name = "PX", conflicts_with = "fit_aspect")]
    focal_px: Option<f64>,
    /// Fit fy / fx too.
    #[arg(long)]
    fit_aspect: bool,
    /// Fit the principal point too (else the image centre).
    #[arg(long)]
    fit_principal_point: bool,
    /// The analysis grid's largest width (the video is reduced by an integer factor).
    #[arg(long, default_value_t = 320)]
    analysis_width: u32,
    /// Coarse search: azimuth step in degrees (all around the workspace).
    #[arg(long, default_value_t = 20.0)]
    azimuth_step_deg: f64,
    /// Nelder-Mead evaluations per refinement round.
    #[arg(long, default_value_t = 250)]
    max_evaluations: usize,
    /// Nelder-Mead evaluations of each re-fit of the valley walk (the camera
    /// moved along an orbit or the dolly-zoom); 0 skips the walk.
    #[arg(long, default_value_t = CalibrateOptions::default().walk_evaluations)]
    walk_evaluations: usize,
    /// Weight of the background-consistency cost beside the silhouette's 1 - IoU (0: the silhouette alone).
    #[arg(long, default_value_t = CalibrateOptions::default().background_weight)]
    background_weight: f64,
    /// Weight of the appearance cost (how well the rendered robot splits the frames' colours) in the last refinement (0: left out).
    #[arg(long, default_value_t = CalibrateOptions::default().appearance_weight)]
    appearance_weight: f64,
    /// Found pixels that keep their colour over the frames around (a moved object at rest, a drift): `score` them or `leave-out` of the score.
    #[arg(long, default_value_t = StaticChanges::Score)]
    static_changes: StaticChanges,
    /// Flag a held-out IoU below this.
    #[arg(long, default_value_t = 0.5)]
    low_iou: f64,
    /// Refuse an episode whose robot surface moves less than this (metres).
    #[arg(long, default_value_t = 0.05)]
    min_motion_m: f64,
}

impl FitArgs {
    fn options(&self, guess: Option<Camera>, default_fy_over_fx: f64) -> CalibrateOptions {
        CalibrateOptions {
            guess,
            fy_over_fx: self.fy_over_fx.unwrap_or(default_fy_over_fx),
            focal_px: self.focal_px,
            fit_aspect: self.fit_aspect,
            fit_principal_point: self.fit_principal_point,
            azimuth_step_deg: self.azimuth_step_deg,
            max_evaluations: self.max_evaluations,
            walk_evaluations: self.walk_evaluations,
            background_weight: self.background_weight,
            appearance_weight: self.appearance_weight,
            low_iou: self.low_iou,
            min_motion_m: self.min_motion_m,
            foreground: ForegroundOptions {
                static_changes: self.static_changes,
                ..ForegroundOptions::default()
            },
            ..CalibrateOptions::default()
        }
        .with_analysis_width(self.analysis_width)
    }
}

/// Arguments of `calibrate`.
#[derive(Debug, clap::Args)]
pub struct CalibrateArgs {
    #[command(flatten)]
    robot: RobotArgs,
    /// An episode's video from the camera (MP4; repeat for several episodes of one camera).
    #[arg(long, required = true, value_name = "MP4")]
    video: Vec<PathBuf>,
    /// Each --video's joint states, in order: a trajectory file (JSON, CSV,
    /// .npy; the robot's joint order) or a DROID annotation JSON (`joints`, or
    /// the 15 Hz `observation.state.*` arrays).
    #[arg(long, required = true, value_name = "FILE")]
    joints: Vec<PathBuf>,
    /// Episodes of the same camera to check the calibration on, not fitted (repeat).
    #[arg(long, value_name = "MP4")]
    check_video: Vec<PathBuf>,
    /// Each --check-video's joint states, in order.
    #[arg(long, value_name = "FILE")]
    check_joints: Vec<PathBuf>,
    /// A rough camera JSON to start from besides the coarse search.
    #[arg(long, value_name = "JSON")]
    guess: Option<PathBuf>,
    /// Hand marks of the tool point (JSON: `{"videos": [{"video": "val/0002/0.mp4", "marks": [[frame, u, v], ...]}]}`, pixels at the video's size; see the calibrate guide): each marked episode's reprojection error is reported; on fitted episodes, 4 or more marks start and pull the fit
    #[arg(long, value_name = "JSON")]
    marks: Option<PathBuf>,
    /// Only measure the --marks, do not fit them: the automatic calibration's error in pixels
    #[arg(long, requires = "marks")]
    marks_only_check: bool,
    #[command(flatten)]
    fit: FitArgs,
    /// Output folder: camera.json, residuals.json, overlay/*.gif.
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing --out.
    #[arg(long)]
    overwrite: bool,
}

pub fn run(args: &CalibrateArgs) -> Result<()> {
    let e = args.robot.load()?;
    let guess = args
        .guess
        .as_deref()
        .map(Camera::from_json_file)
        .transpose()?;
    let mut options = args.fit.options(guess, 1.0);
    options.marks = args.marks.as_deref().map(Marks::read).transpose()?;
    options.fit_marks = !args.marks_only_check;
    let fitted = pair_inputs(&args.video, &args.joints, ("--video", "--joints"))?;
    let checked = pair_inputs(
        &args.check_video,
        &args.check_joints,
        ("--check-video", "--check-joints"),
    )?;
    let mut inputs: Vec<&Path> = args.robot.urdf_file().into_iter().collect();
    inputs.extend(args.guess.as_deref());
    inputs.extend(args.marks.as_deref());
    let run = calibrate_to_folder(
        &e,
        &fitted,
        &checked,
        &options,
        &args.out,
        args.overwrite,
        &inputs,
        &|stage| eprintln!("calibrate: {stage}"),
    )?;
    crate::print_stdout(&run.summary())
}

/// Arguments of `calibrate-study`.
#[derive(Debug, clap::Args)]
pub struct CalibrateStudyArgs {
    /// Study real DROID video instead of the synthetic world: every exterior
    /// camera of every episode under DIR (the Ctrl-World layout), and the
    /// shared rig's cameras (`droid_new_setup*`) from a few episodes,
    /// checked on the others.
    #[arg(long, value_name = "DIR", conflicts_with_all = ["robot", "cameras_per_split", "width", "height", "frames", "seed"])]
    droid: Option<PathBuf>,
    /// --droid: shared-rig episodes the rig calibration is fitted on.
    #[arg(long, default_value_t = 3, requires = "droid")]
    rig_fit_episodes: usize,
    /// --droid: at most this many episodes per collection.
    #[arg(long, requires = "droid")]
    episodes_per_collection: Option<usize>,
    /// Built-in robot of the synthetic world (franka, franka-robotiq).
    #[arg(long, default_value = "franka")]
    robot: String,
    /// Cameras per split (test and unseen_camera each).
    #[arg(long, default_value_t = 10)]
    cameras_per_split: usize,
    /// Video width (even).
    #[arg(long, default_value_t = 256)]
    width: u32,
    /// Video height (even).
    #[arg(long, default_value_t = 160)]
    height: u32,
    /// Frames per episode.
    #[arg(long, default_value_t = 40)]
    frames: usize,
    /// Dataset seed.
    #[arg(long, default_value_t = 7)]
    seed: u64,
    /// Give each calibration the true camera's focal length (fit the pose
    /// only), as a user who knows their camera's intrinsics would.
    #[arg(long, conflicts_with = "droid")]
    known_focal: bool,
    #[command(flatten)]
    fit: FitArgs,
    /// Output folder: study.json, study.md, and videos/*.mp4 (synthetic) or
    /// a calibration folder per camera (--droid).
    #[arg(long)]
    out: PathBuf,
    /// Replace an existing --out.
    #[arg(long)]
    overwrite: bool,
}

pub fn run_study(args: &CalibrateStudyArgs) -> Result<()> {
    let progress = |line: &str| eprintln!("{line}");
    let (md, dir) = if let Some(root) = &args.droid {
        let options = DroidStudyOptions {
            rig_fit_episodes: args.rig_fit_episodes,
            episodes_per_collection: args.episodes_per_collection,
            calibrate: args.fit.options(None, DROID_FY_OVER_FX),
            ..DroidStudyOptions::new(root)
        };
        let e = bridgev2w_embodiment::embodiment::Embodiment::builtin("franka-robotiq")?;
        let (table, dir) =
            droid_study_to_folder(&e, &options, &args.out, args.overwrite, &progress)?;
        (table.to_markdown(), dir)
    } else {
        let options = StudyOptions {
            robot: args.robot.clone(),
            cameras_per_split: args.cameras_per_split,
            width: args.width,
            height: args.height,
            frames: args.frames,
            seed: args.seed,
            calibrate: args.fit.options(None, 1.0),
            known_focal: args.known_focal,
        };
        let (table, dir) =
            synthetic_study_to_folder(&options, &args.out, args.overwrite, &progress)?;
        (table.to_markdown(), dir)
    };
    crate::print_stdout(&format!(
        "{md}wrote {}/study.md, study.json and the calibrations' files\n",
        dir.display()
    ))
}
