//! A fixed camera's calibration from the robot's own motion (`bridgev2w
//! calibrate`): from one or more episodes' video and joint states, the
//! camera (`world_from_camera`, focal lengths, optionally the aspect and the
//! principal point) whose rendered robot masks match the robot in the video.
//!
//! - The robot's pixels are found from the video itself ([`foreground`]):
//!   what moves against the per-pixel temporal-median background.
//! - A candidate camera predicts that foreground from the joints (where its
//!   rendered robot differs from each pixel's usual look; `objective`),
//!   scored by IoU and, far from the answer, a chamfer
//!   distance.
//! - The camera is found with no start given: a coarse search over poses
//!   all around the workspace, then Nelder-Mead refinement on finer grids
//!   (`search`), with a walk along the objective's valleys (the dolly-zoom:
//!   a near, wide camera against a far, narrow one; the orbits) that
//!   Nelder-Mead rarely follows.
//! - Frames are split into blocks; every fourth block is held out of the
//!   fit and scored after it ([`EpisodeResidual::held_out_iou`]).
//! - Refused with the measured reason ([`CalibrateError`]): a camera that
//!   moves, a robot that hardly moves, too few frames with robot pixels.
//!   Flagged ([`Calibration::flags`]): a low held-out IoU, a fit that other
//!   clearly different cameras match about as well (ambiguous).
//!
//! [`report`] writes `camera.json`, `residuals.json` and overlay GIFs;
//! [`study`] measures the errors against the synthetic world's known
//! cameras.

mod appearance;
mod background;
pub mod droid_study;
pub mod episode;
pub mod foreground;
mod full_grid;
pub mod marks;
mod nelder_mead;
mod objective;
mod options;
mod problem;
pub mod report;
pub mod run;
mod search;
pub mod study;
mod valley;

pub use episode::{load_episode, pair_inputs, EpisodeData, EpisodeInput};
pub use foreground::{
    find_foreground, Foreground, ForegroundOptions, ForegroundStats, StaticChanges,
};
pub use options::CalibrateOptions;

use crate::synth::SynthError;
use crate::video::VideoError;
use bridgev2w_embodiment::camera::{Camera, CameraError};
use bridgev2w_embodiment::embodiment::Embodiment;
use full_grid::refine_on_full_grid;
use objective::reduce_intrinsics;
use problem::{prepare, Prepared};
use search::{
    active_parameters, angle_between, coarse_candidates, distinct, marks_start, refine,
    start_intrinsics, Evaluator,
};
use serde::Serialize;
use std::path::PathBuf;
use valley::{probe, walk_step, PROBES};

/// Errors of the calibration; each names the input and the measured value.
#[derive(Debug, thiserror::Error)]
pub enum CalibrateError {
    /// An option is out of range.
    #[error("calibrate: {field} = {value}: expected {expected}")]
    Option {
        /// The option (its command-line flag).
        field: &'static str,
        /// The value given.
        value: String,
        /// What is expected.
        expected: String,
    },
    /// The video could not be read.
    #[error(transparent)]
    Video(#[from] VideoError),
    /// The joint file could not be read or does not fit the robot.
    #[error("{}: {message}", path.display())]
    Joints {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The episode's inputs do not fit together.
    #[error("episode {episode}: {message}")]
    Episode {
        /// The episode (its video).
        episode: String,
        /// What is wrong.
        message: String,
    },
    /// The camera moves: most of its image changes.
    #[error("episode {episode}: the camera moves: the median difference to the background is {noise_level:.1} (fixed-camera limit {max_noise_level}) and {unstable_percent:.0}% of the image differs from it in most frames (limit {max_unstable_percent:.0}%); the fixed-camera calibrator refuses it (a wrist or head camera is posed by forward kinematics instead: see `bridgev2w masks`)")]
    MovingCamera {
        /// The episode.
        episode: String,
        /// Measured [`ForegroundStats::noise_level`].
        noise_level: f64,
        /// Its limit.
        max_noise_level: f64,
        /// Measured [`ForegroundStats::unstable_fraction`], percent.
        unstable_percent: f64,
        /// Its limit, percent.
        max_unstable_percent: f64,
    },
    /// The robot hardly moves: no motion to find it by.
    #[error("episode {episode}: the robot hardly moves: its surface travels at most {range_m:.3} m, below the {min_m} m needed to find it against the background")]
    StillRobot {
        /// The episode.
        episode: String,
        /// Measured motion range (metres).
        range_m: f64,
        /// The minimum (metres).
        min_m: f64,
    },
    /// Too few frames show robot pixels.
    #[error("episode {episode}: the camera sees too little of the robot: {frames_with_robot} of {frames} frames ({percent:.0}%) show robot pixels, expected at least {min_frames} frames and {min_percent:.0}%")]
    TooLittleRobot {
        /// The episode.
        episode: String,
        /// Frames with robot pixels.
        frames_with_robot: usize,
        /// Frames.
        frames: usize,
        /// Their share, percent.
        percent: f64,
        /// Minimum frames.
        min_frames: usize,
        /// Minimum share, percent.
        min_percent: f64,
    },
    /// No candidate camera sees the robot's motion.
    #[error("no camera found: {0}")]
    NoCamera(String),
    /// A camera (guess or result) is invalid.
    #[error(transparent)]
    Camera(#[from] CameraError),
    /// An output could not be written.
    #[error("{}: {message}", path.display())]
    Output {
        /// The file.
        path: PathBuf,
        /// What failed.
        message: String,
    },
    /// A marks file is unreadable or does not fit the episodes.
    #[error("{}: {message}", path.display())]
    Marks {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The synthetic world failed (the study).
    #[error(transparent)]
    Synth(#[from] SynthError),
}

/// At most this many steps of the valley walk after the middle-grid
/// refinement (each from the best camera so far, while it improves).
const MAX_WALK_STEPS: usize = 8;

/// A calibration's residuals on one episode.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct EpisodeResidual {
    /// The episode.
    pub name: String,
    /// Frames.
    pub frames: usize,
    /// Frames fitted (0 for an episode only checked).
    pub fit_frames: usize,
    /// Frames held out (all, for an episode only checked).
    pub held_out_frames: usize,
    /// IoU of predicted and found foreground over the fitted frames
    /// (pooled), when any.
    pub fit_iou: Option<f64>,
    /// The same over the held-out frames.
    pub held_out_iou: f64,
    /// Mean of the held-out frames' own IoUs (frames with any foreground).
    pub held_out_iou_frame_mean: f64,
    /// Mean chamfer distance over held-out frames (analysis-grid pixels).
    pub held_out_chamfer_px: f64,
    /// The robot's motion range (metres).
    pub motion_range_m: f64,
    /// Foreground measurements.
    pub foreground: ForegroundStats,
    /// What was adapted reading the episode.
    pub notes: Vec<String>,
    /// The reprojection error of its hand marks, when it has any.
    pub marks: Option<marks::MarksResidual>,
}

/// Something about a calibration that makes it less than trustworthy.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Flag {
    /// `low_held_out_iou`, `ambiguous`, `marks_disagree`.
    pub code: &'static str,
    /// With the measured values.
    pub message: String,
}

/// How much the best refined alternatives disagree with the result.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Ambiguity {
    /// Alternatives within the objective margin.
    pub alternatives: usize,
    /// Their largest position difference (metres).
    pub max_position_m: f64,
    /// Their largest angle difference (degrees).
    pub max_angle_deg: f64,
    /// Their largest focal-length difference (fraction).
    pub max_focal_fraction: f64,
    /// The smallest rise of the objective when the camera is moved by
    /// `ambiguous_position_m` (orbit or dolly-zoom) and the rest re-fitted.
    pub probe_rise: f64,
    /// Along which direction.
    pub probe_direction: &'static str,
}

/// A calibration.
#[derive(Debug, Clone, PartialEq)]
pub struct Calibration {
    /// The camera at the video's own resolution.
    pub camera: Camera,
    /// Parameters fitted.
    pub fitted: Vec<&'static str>,
    /// Pooled IoU over all fitted frames.
    pub fit_iou: f64,
    /// Pooled IoU over all held-out frames.
    pub held_out_iou: f64,
    /// No flag raised.
    pub reliable: bool,
    /// What makes it less trustworthy.
    pub flags: Vec<Flag>,
    /// The refined alternatives' disagreement.
    pub ambiguity: Ambiguity,
    /// Per episode.
    pub episodes: Vec<EpisodeResidual>,
    /// Coarse-search candidates that saw the robot.
    pub candidates: usize,
    /// Objective evaluations (renders of the scored frames).
    pub evaluations: usize,
    /// Wall time (seconds).
    pub seconds: f64,
}

const PARAMETER_NAMES: [&str; 10] = [
    "x", "y", "z", "rx", "ry", "rz", "focal", "fy/fx", "cx", "cy",
];

/// Checks that episodes share their analysis grid and finds each one's
/// foreground, refusing moving cameras and episodes that show too little
/// robot motion (see [`CalibrateError`]).
fn prepare_all(
    embodiment: &Embodiment,
    episodes: &[EpisodeData],
    options: &CalibrateOptions,
    factors: &[usize],
    refuse: bool,
) -> Result<Vec<Prepared>, CalibrateError> {
    let Some(first) = episodes.first() else {
        return Err(CalibrateError::NoCamera("no episodes given".into()));
    };
    let mark_link = marked_link(embodiment, options)?;
    let mut out = Vec::with_capacity(episodes.len());
    for e in episodes {
        if (e.video_size, e.factor, e.width, e.height)
            != (first.video_size, first.factor, first.width, first.height)
        {
            return Err(CalibrateError::Episode {
                episode: e.name.clone(),
                message: format!(
                    "video {}x{} but {} is {}x{}: one camera's episodes share a size",
                    e.video_size.0,
                    e.video_size.1,
                    first.name,
                    first.video_size.0,
                    first.video_size.1
                ),
            });
        }
        let fg = find_foreground(e, &options.foreground);
        let s = &fg.stats;
        let p = prepare(
            &embodiment.robot,
            e,
            &fg,
            factors,
            options.held_out_every,
            options.mode_frames,
        );
        let p = Prepared {
            marks: place_marks(e, &p.poses, mark_link, options)?,
            ..p
        };
        if refuse {
            if s.noise_level >= options.moving_noise_level
                && s.unstable_fraction >= options.moving_unstable_fraction
            {
                return Err(CalibrateError::MovingCamera {
                    episode: e.name.clone(),
                    noise_level: s.noise_level,
                    max_noise_level: options.moving_noise_level,
                    unstable_percent: 100.0 * s.unstable_fraction,
                    max_unstable_percent: 100.0 * options.moving_unstable_fraction,
                });
            }
            if p.motion.range_m < options.min_motion_m {
                return Err(CalibrateError::StillRobot {
                    episode: e.name.clone(),
                    range_m: p.motion.range_m,
                    min_m: options.min_motion_m,
                });
            }
            if s.frames_with_robot < options.min_robot_frames
                || s.robot_frame_fraction < options.min_robot_frame_fraction
            {
                return Err(CalibrateError::TooLittleRobot {
                    episode: e.name.clone(),
                    frames_with_robot: s.frames_with_robot,
                    frames: s.frames,
                    percent: 100.0 * s.robot_frame_fraction,
                    min_frames: options.min_robot_frames,
                    min_percent: 100.0 * options.min_robot_frame_fraction,
                });
            }
        }
        out.push(p);
    }
    Ok(out)
}

/// The robot link whose origin the marks show: the marks file's `link`,
/// else the first end effector's link.
fn marked_link(
    embodiment: &Embodiment,
    options: &CalibrateOptions,
) -> Result<usize, CalibrateError> {
    let robot = &embodiment.robot;
    match options
        .marks
        .as_ref()
        .and_then(|m| m.link.as_deref().map(|l| (m, l)))
    {
        Some((m, name)) => robot.link_index(name).ok_or_else(|| CalibrateError::Marks {
            path: m.path.clone(),
            message: format!(
                "link {name:?} is not a link of {}: expected one of {}",
                robot.name,
                robot
                    .links
                    .iter()
                    .map(|l| l.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        }),
        None => Ok(embodiment.end_effectors.first().map_or(0, |e| e.link)),
    }
}

/// `episode`'s marks placed for scoring: the marked link's origin at each
/// marked frame and the mark on the analysis grid.
fn place_marks(
    episode: &EpisodeData,
    poses: &[Vec<nalgebra::Isometry3<f64>>],
    link: usize,
    options: &CalibrateOptions,
) -> Result<Vec<marks::PlacedMark>, CalibrateError> {
    let mut out = Vec::with_capacity(episode.marks.len());
    for m in &episode.marks {
        let Some(pose) = poses.get(m.frame) else {
            let path = options
                .marks
                .as_ref()
                .map(|f| f.path.clone())
                .unwrap_or_default();
            return Err(CalibrateError::Marks {
                path,
                message: format!(
                    "{}: frame {} is marked but the episode has {} frames (0..{})",
                    episode.name,
                    m.frame,
                    poses.len(),
                    poses.len()
                ),
            });
        };
        out.push(marks::PlacedMark {
            world: nalgebra::Point3::from(pose[link].translation.vector),
            pixel: marks::to_analysis(m.u, m.v, f64::from(episode.factor)),
        });
    }
    Ok(out)
}

/// The level factors (analysis grid, middle, coarse) for a grid `width` wide.
fn level_factors(width: usize, options: &CalibrateOptions) -> Vec<usize> {
    let f = |target: u32| width.div_ceil(target as usize).max(1);
    vec![1, f(options.mid_width), f(options.coarse_width)]
}

/// Residuals of `camera` (analysis grid) on each prepared episode: fitted
/// frames (when `fitted`) and held-out frames at the analysis grid.
fn residuals(
    embodiment: &Embodiment,
    prepared: &[Prepared],
    episodes: &[EpisodeData],
    camera: &Camera,
    fitted: bool,
) -> Vec<EpisodeResidual> {
    let robot = &embodiment.robot;
    let held: Vec<Vec<usize>> = prepared
        .iter()
        .map(|p| {
            if fitted {
                p.held.clone()
            } else {
                (0..p.poses.len()).collect()
            }
        })
        .collect();
    let held_detail = Evaluator::new(robot, prepared, 0, held.clone()).detail(camera);
    let fit_detail = fitted.then(|| {
        Evaluator::new(
            robot,
            prepared,
            0,
            prepared.iter().map(|p| p.fit.clone()).collect(),
        )
        .detail(camera)
    });
    prepared
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let (s, per_frame) = &held_detail[i];
            EpisodeResidual {
                name: p.name.clone(),
                frames: p.poses.len(),
                fit_frames: if fitted { p.fit.len() } else { 0 },
                held_out_frames: held[i].len(),
                fit_iou: fit_detail.as_ref().map(|d| d[i].0.iou()),
                held_out_iou: s.iou(),
                held_out_iou_frame_mean: per_frame.iter().sum::<f64>()
                    / per_frame.len().max(1) as f64,
                held_out_chamfer_px: s.chamfer / s.frames.max(1) as f64,
                motion_range_m: p.motion.range_m,
                foreground: p.foreground.clone(),
                notes: episodes[i].notes.clone(),
                marks: marks::residual(&p.marks, camera, f64::from(episodes[i].factor)),
            }
        })
        .collect()
}

/// Calibrates the fixed camera that filmed `episodes` (see the module
/// documentation). `progress` hears each stage.
pub fn calibrate(
    embodiment: &Embodiment,
    episodes: &[EpisodeData],
    options: &CalibrateOptions,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<Calibration, CalibrateError> {
    let started = std::time::Instant::now();
    options.validate()?;
    let factors = level_factors(episodes.first().map_or(1, |e| e.width), options);
    let scored = prepare_all(embodiment, episodes, options, &factors, true)?;
    // Marks only checked: the fit does not see them, the residuals do.
    let unmarked: Vec<Prepared>;
    let prepared: &[Prepared] = if options.fit_marks {
        &scored
    } else {
        unmarked = scored
            .iter()
            .map(|p| Prepared {
                marks: Vec::new(),
                ..p.clone()
            })
            .collect();
        &unmarked
    };
    let first = &episodes[0];
    let (w, h) = (first.width as u32, first.height as u32);
    let robot = &embodiment.robot;
    // The motion centroid over episodes, weighted by frames.
    let frames: usize = prepared.iter().map(|p| p.poses.len()).sum();
    let target = nalgebra::Point3::from(
        prepared
            .iter()
            .map(|p| p.motion.centroid.coords * p.poses.len() as f64)
            .sum::<nalgebra::Vector3<f64>>()
            / frames.max(1) as f64,
    );
    let coarse = Evaluator::fit(robot, prepared, 2, options.coarse_frames).coarse();
    progress("coarse search");
    // A known focal length on the analysis grid.
    let focal = options.focal_px.map(|f| f / f64::from(first.factor));
    let mut candidates = coarse_candidates(&coarse, target, (w, h), options, focal);
    let found = candidates.len();
    if candidates.is_empty() {
        return Err(CalibrateError::NoCamera(
            "no camera around the workspace puts the robot's motion in view".into(),
        ));
    }
    let screened = distinct(&candidates, options.screened);
    progress(&format!(
        "screening {} of {} candidates on the coarse grid",
        screened.len(),
        candidates.len()
    ));
    let mut screened: Vec<(Camera, f64)> = screened
        .iter()
        .map(|(c, _)| {
            refine(
                &coarse,
                c,
                target,
                &active_parameters(options, false),
                1.0,
                options.screen_evaluations,
                1,
            )
        })
        .collect();
    screened.sort_by(|a, b| a.1.total_cmp(&b.1));
    let mut starts = distinct(&screened, options.starts);
    if let Some(g) = &options.guess {
        let (vw, vh) = first.video_size;
        let g = g.rescaled(vw, vh);
        let k = reduce_intrinsics(&g.intrinsics, f64::from(first.factor), w, h);
        let mut g = Camera::new(k, g.world_from_camera)?;
        if let Some(f) = focal {
            g.intrinsics.fx = f;
            g.intrinsics.fy = f * options.fy_over_fx;
        }
        let v = coarse.value(&g);
        starts.push((g.clone(), v));
        candidates.push((g, v));
    }
    let fitted_marks: usize = prepared.iter().map(|p| p.marks.len()).sum();
    if fitted_marks >= marks::MIN_MARKS_TO_START {
        progress(&format!("fitting a start to {fitted_marks} hand marks"));
        let k = start_intrinsics((w, h), options, focal);
        if let Some((c, _)) = marks_start(prepared, k, target, options, focal) {
            let v = coarse.value(&c);
            starts.push((c.clone(), v));
            candidates.push((c, v));
        }
    }
    let fit = Evaluator::fit(robot, prepared, 2, options.fit_frames).coarse();
    progress(&format!(
        "refining {} starts on the coarse grid",
        starts.len()
    ));
    let basic = active_parameters(options, false);
    let mut refined: Vec<(Camera, f64)> = starts
        .iter()
        .map(|(c, _)| refine(&fit, c, target, &basic, 1.0, options.max_evaluations, 2))
        .collect();
    refined.sort_by(|a, b| a.1.total_cmp(&b.1));
    let all = active_parameters(options, true);
    let mid = Evaluator::fit(robot, prepared, 1, options.fit_frames);
    progress(&format!(
        "refining {} on the middle grid",
        options.finalists.min(refined.len())
    ));
    let mut finalists: Vec<(Camera, f64)> = refined
        .iter()
        .take(options.finalists)
        .map(|(c, _)| refine(&mid, c, target, &all, 0.4, options.max_evaluations, 2))
        .collect();
    finalists.sort_by(|a, b| a.1.total_cmp(&b.1));
    let walk_steps = if options.walk_evaluations == 0 {
        0
    } else {
        progress("walking the orbit and dolly-zoom valleys");
        MAX_WALK_STEPS
    };
    for _ in 0..walk_steps {
        let Some((moved, _, _)) = walk_step(
            &mid,
            &finalists[0].0,
            target,
            &all,
            options.walk_evaluations,
            &PROBES,
        ) else {
            break;
        };
        let step = refine(&mid, &moved, target, &all, 0.4, options.max_evaluations, 1);
        finalists.insert(0, step);
        finalists.sort_by(|a, b| a.1.total_cmp(&b.1));
    }
    let (best_mid, best_value) = finalists[0].clone();
    let mut ambiguity = Ambiguity {
        alternatives: 0,
        max_position_m: 0.0,
        max_angle_deg: 0.0,
        max_focal_fraction: 0.0,
        probe_rise: f64::INFINITY,
        probe_direction: "",
    };
    for (c, v) in &finalists[1..] {
        if *v > best_value + options.ambiguous_margin {
            continue;
        }
        ambiguity.alternatives += 1;
        let d = (c.world_from_camera.translation.vector
            - best_mid.world_from_camera.translation.vector)
            .norm();
        ambiguity.max_position_m = ambiguity.max_position_m.max(d);
        ambiguity.max_angle_deg = ambiguity
            .max_angle_deg
            .max(angle_between(c, &best_mid).to_degrees());
        let df = (c.intrinsics.fx / best_mid.intrinsics.fx - 1.0).abs();
        ambiguity.max_focal_fraction = ambiguity.max_focal_fraction.max(df);
    }
    let (camera, full_evaluations) =
        refine_on_full_grid(robot, prepared, &finalists, target, options, progress);
    progress("probing how well the camera is pinned down");
    let basic = active_parameters(options, false);
    let (rise, direction) = probe(
        &mid,
        &camera,
        target,
        &basic,
        options.ambiguous_position_m,
        options.probe_evaluations,
    );
    ambiguity.probe_rise = rise;
    ambiguity.probe_direction = direction;
    let evaluations =
        coarse.evaluations() + fit.evaluations() + mid.evaluations() + full_evaluations;
    let episode_residuals = residuals(embodiment, &scored, episodes, &camera, true);
    let pooled = |held: bool| {
        let ev = Evaluator::new(
            robot,
            prepared,
            0,
            prepared
                .iter()
                .map(|p| if held { p.held.clone() } else { p.fit.clone() })
                .collect(),
        );
        ev.score(&camera).iou()
    };
    let (fit_iou, held_out_iou) = (pooled(false), pooled(true));
    let mut flags = Vec::new();
    if held_out_iou < options.low_iou {
        flags.push(Flag {
            code: "low_held_out_iou",
            message: format!(
                "held-out IoU {held_out_iou:.3} is below {}: the rendered robot does not match the video's; do not trust this camera",
                options.low_iou
            ),
        });
    }
    flags.extend(marks_flags(&episode_residuals, first.video_size.0, options));
    if rise < options.ambiguous_margin {
        flags.push(Flag {
            code: "ambiguous",
            message: format!(
                "moving the camera {} m by {direction} and re-fitting the rest worsens the fit by only {rise:.4} (below {}): the video does not pin the camera down (more of the robot in view, more motion, or more episodes help)",
                options.ambiguous_position_m, options.ambiguous_margin
            ),
        });
    } else if ambiguity.max_position_m > options.ambiguous_position_m
        || ambiguity.max_angle_deg > options.ambiguous_angle_deg
        || ambiguity.max_focal_fraction > options.ambiguous_focal_fraction
    {
        flags.push(Flag {
            code: "ambiguous",
            message: format!(
                "{} other refined camera(s) score within {} of this one but differ by up to {:.3} m, {:.1} deg, {:.1}% focal: the video does not pin the camera down (more of the robot in view, more motion, or more episodes help)",
                ambiguity.alternatives,
                options.ambiguous_margin,
                ambiguity.max_position_m,
                ambiguity.max_angle_deg,
                100.0 * ambiguity.max_focal_fraction
            ),
        });
    }
    let (vw, vh) = first.video_size;
    let native = reduce_intrinsics(&camera.intrinsics, 1.0 / f64::from(first.factor), vw, vh);
    let camera = Camera::new(native, camera.world_from_camera)?;
    Ok(Calibration {
        camera,
        fitted: all.iter().map(|&i| PARAMETER_NAMES[i]).collect(),
        fit_iou,
        held_out_iou,
        reliable: flags.is_empty(),
        flags,
        ambiguity,
        episodes: episode_residuals,
        candidates: found,
        evaluations,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// A `marks_disagree` flag for each episode whose hand marks' median
/// reprojection error exceeds `max_marks_error_fraction` of the width
/// (`width` pixels, the video's).
pub fn marks_flags(
    residuals: &[EpisodeResidual],
    width: u32,
    options: &CalibrateOptions,
) -> Vec<Flag> {
    let limit = options.max_marks_error_fraction * f64::from(width);
    residuals
        .iter()
        .filter_map(|r| {
            let m = r.marks.as_ref()?;
            (m.median_px > limit).then(|| Flag {
                code: "marks_disagree",
                message: format!(
                    "{}: the tool point lands a median {:.1} px (largest {:.1}) from its {} hand marks, above {limit:.1} px ({:.0}% of the width): the camera is off",
                    r.name,
                    m.median_px,
                    m.max_px,
                    m.marks,
                    100.0 * options.max_marks_error_fraction
                ),
            })
        })
        .collect()
}

/// Scores a calibrated `camera` (any image size: rescaled to the videos')
/// on episodes it was not fitted on: every frame is held out.
pub fn check(
    embodiment: &Embodiment,
    camera: &Camera,
    episodes: &[EpisodeData],
    options: &CalibrateOptions,
) -> Result<Vec<EpisodeResidual>, CalibrateError> {
    options.validate()?;
    let prepared = prepare_all(embodiment, episodes, options, &[1], false)?;
    let first = &episodes[0];
    let (vw, vh) = first.video_size;
    let c = camera.rescaled(vw, vh);
    let k = reduce_intrinsics(
        &c.intrinsics,
        f64::from(first.factor),
        first.width as u32,
        first.height as u32,
    );
    let c = Camera::new(k, c.world_from_camera)?;
    Ok(residuals(embodiment, &prepared, episodes, &c, false))
}
