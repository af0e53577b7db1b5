//! The calibration measured where the truth is known: synthetic episodes
//! (the `test` split's cameras and the `unseen_camera` split's, whose
//! azimuths no training camera has) rendered, encoded as H.264 MP4,
//! decoded, and calibrated from the video and the joints alone; the result
//! compared with the camera that rendered them.

use super::episode::{analysis_factor, reduce_rgb, EpisodeData};
use super::{calibrate, check, CalibrateError, CalibrateOptions};
use crate::synth::{Split, SynthConfig, Task, World};
use crate::video::{Mp4VideoWriter, VideoStream};
use bridgev2w_embodiment::camera::Camera;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// Options of [`synthetic_study`].
#[derive(Debug, Clone, PartialEq)]
pub struct StudyOptions {
    /// Built-in robot of the synthetic world (`franka`, `franka-robotiq`).
    pub robot: String,
    /// Cameras (episodes) per split, for `test` and `unseen_camera` each.
    pub cameras_per_split: usize,
    /// Video width (pixels, even).
    pub width: u32,
    /// Video height (pixels, even).
    pub height: u32,
    /// Frames per episode.
    pub frames: usize,
    /// Dataset seed.
    pub seed: u64,
    /// The calibration's options.
    pub calibrate: CalibrateOptions,
    /// Give each calibration the true camera's focal length (as a user who
    /// knows their camera's intrinsics would), fitting the pose only.
    pub known_focal: bool,
}

impl Default for StudyOptions {
    fn default() -> Self {
        Self {
            robot: "franka".into(),
            cameras_per_split: 10,
            width: 256,
            height: 160,
            frames: 40,
            seed: 7,
            calibrate: CalibrateOptions::default(),
            known_focal: false,
        }
    }
}

impl StudyOptions {
    /// Checks the options; errors name the flag.
    pub fn validate(&self) -> Result<(), CalibrateError> {
        let bad = |field: &'static str, value: String, expected: &str| CalibrateError::Option {
            field,
            value,
            expected: expected.into(),
        };
        if !(1..=1000).contains(&self.cameras_per_split) {
            return Err(bad(
                "--cameras-per-split",
                self.cameras_per_split.to_string(),
                "1..=1000",
            ));
        }
        if !(8..=10_000).contains(&self.frames) {
            return Err(bad("--frames", self.frames.to_string(), "8..=10000"));
        }
        self.calibrate.validate()
    }
}

/// One calibrated synthetic camera.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StudyRow {
    /// `test` or `unseen_camera`.
    pub split: String,
    /// Index in the split.
    pub index: usize,
    /// The episode's task.
    pub task: String,
    /// The true camera's azimuth (degrees).
    pub azimuth_deg: f64,
    /// Its elevation (degrees).
    pub elevation_deg: f64,
    /// Its distance to the workspace (metres).
    pub distance_m: f64,
    /// Position error (centimetres); `null` when refused.
    pub position_error_cm: Option<f64>,
    /// Orientation error (degrees).
    pub angle_error_deg: Option<f64>,
    /// Largest focal-length error of fx and fy (percent).
    pub focal_error_pct: Option<f64>,
    /// Held-out IoU.
    pub held_out_iou: Option<f64>,
    /// The IoU the true camera reaches over all frames (the ceiling the
    /// found robot pixels allow).
    pub truth_iou: f64,
    /// Whether the calibration raised no flag.
    pub reliable: bool,
    /// Flags raised, or the refusal.
    pub flags: Vec<String>,
    /// Seconds the calibration took.
    pub seconds: f64,
}

/// The study's table and its summary.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct StudyTable {
    /// Robot.
    pub robot: String,
    /// Video size.
    pub size: (u32, u32),
    /// Frames per episode.
    pub frames: usize,
    /// Per camera.
    pub rows: Vec<StudyRow>,
    /// Cameras calibrated (not refused).
    pub calibrated: usize,
    /// Median position error (cm) over calibrated cameras.
    pub median_position_cm: f64,
    /// Median angle error (degrees).
    pub median_angle_deg: f64,
    /// Median focal error (percent).
    pub median_focal_pct: f64,
    /// Largest position error (cm).
    pub max_position_cm: f64,
    /// Largest angle error (degrees).
    pub max_angle_deg: f64,
    /// Largest focal error (percent).
    pub max_focal_pct: f64,
    /// Cameras within 2 cm, 1 degree and 2 % focal.
    pub within_target: usize,
}

/// The median of `v` (NaN when empty).
pub(crate) fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    if n % 2 == 1 {
        v[n / 2]
    } else {
        0.5 * (v[n / 2 - 1] + v[n / 2])
    }
}

/// `(position cm, angle deg, focal %)` of `estimate` against `truth` (both
/// at the same image size).
pub fn camera_errors(estimate: &Camera, truth: &Camera) -> (f64, f64, f64) {
    let d = (estimate.world_from_camera.translation.vector
        - truth.world_from_camera.translation.vector)
        .norm();
    let a = estimate
        .world_from_camera
        .rotation
        .angle_to(&truth.world_from_camera.rotation);
    let (e, t) = (&estimate.intrinsics, &truth.intrinsics);
    let f = (e.fx / t.fx - 1.0).abs().max((e.fy / t.fy - 1.0).abs());
    (100.0 * d, a.to_degrees(), 100.0 * f)
}

/// A decoded video on the analysis grid: its width, `(height, width)` and
/// grey frames.
type DecodedVideo = (u32, (usize, usize), Vec<Vec<u8>>);

/// Encodes `rgb` frames as an H.264 MP4 at `path` and decodes it onto the
/// analysis grid: what the calibration would read from a real file.
fn through_video(
    path: &Path,
    rgb: &[Vec<u8>],
    (w, h): (u32, u32),
    analysis_width: u32,
) -> Result<DecodedVideo, CalibrateError> {
    let mut writer = Mp4VideoWriter::new(path, w as usize, h as usize, 10)?;
    for (t, f) in rgb.iter().enumerate() {
        writer.push(f, t == 0)?;
    }
    let bytes = writer.to_bytes()?;
    bridgev2w_io::atomic::write_atomic(path, &bytes).map_err(|e| CalibrateError::Output {
        path: path.to_path_buf(),
        message: e.to_string(),
    })?;
    let mut stream = VideoStream::open(path)?;
    let factor = analysis_factor(w, analysis_width);
    let size = ((w / factor) as usize, (h / factor) as usize);
    let mut frames = Vec::new();
    while let Some(f) = stream.next_frame()? {
        frames.push(reduce_rgb(&f.rgb, w as usize, factor as usize, size));
    }
    Ok((factor, size, frames))
}

/// [`synthetic_study`] into a new folder `out`: `videos/*.mp4`, `study.md`
/// and `study.json`, written as a transaction (an existing `out` is
/// refused unless `overwrite`). Returns the table and the folder.
pub fn synthetic_study_to_folder(
    options: &StudyOptions,
    out: &Path,
    overwrite: bool,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<(StudyTable, PathBuf), CalibrateError> {
    options.validate()?;
    super::report::study_folder(
        out,
        overwrite,
        &[],
        |dir| synthetic_study(options, &dir.join("videos"), progress),
        StudyTable::to_markdown,
    )
}

/// Calibrates `cameras_per_split` synthetic cameras of the `test` and
/// `unseen_camera` splits each from their videos (written to `work_dir`)
/// and joints, and compares them with the truth. `progress` hears each
/// camera's result.
pub fn synthetic_study(
    options: &StudyOptions,
    work_dir: &Path,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<StudyTable, CalibrateError> {
    options.validate()?;
    let config = SynthConfig {
        robot: options.robot.clone(),
        frames: options.frames,
        width: options.width,
        height: options.height,
        seed: options.seed,
        tasks: Task::GENERATED.to_vec(),
        episodes_per_split: [0, options.cameras_per_split, options.cameras_per_split, 0],
        ..SynthConfig::default()
    };
    let world = World::new(&config)?;
    std::fs::create_dir_all(work_dir).map_err(|e| CalibrateError::Output {
        path: work_dir.to_path_buf(),
        message: e.to_string(),
    })?;
    let mut rows = Vec::new();
    for split in [Split::Test, Split::UnseenCamera] {
        for index in 0..options.cameras_per_split {
            let task = Task::GENERATED[rows.len() % Task::GENERATED.len()];
            let episode = world.generate(split, index, task)?;
            let path = work_dir.join(format!("{}_{index:03}.mp4", split.name()));
            let (factor, size, frames) = through_video(
                &path,
                &episode.rgb,
                (options.width, options.height),
                options.calibrate.analysis_width,
            )?;
            let data = EpisodeData::new(
                &path.display().to_string(),
                (options.width, options.height),
                factor,
                size,
                frames,
                episode.joints.clone(),
            )?;
            let truth_iou = check(
                &world.embodiment,
                &episode.camera,
                std::slice::from_ref(&data),
                &options.calibrate,
            )?[0]
                .held_out_iou;
            let m = &episode.meta;
            let mut row = StudyRow {
                split: split.name().into(),
                index,
                task: task.name().into(),
                azimuth_deg: m.camera_azimuth_deg,
                elevation_deg: m.camera_elevation_deg,
                distance_m: m.camera_distance_m,
                position_error_cm: None,
                angle_error_deg: None,
                focal_error_pct: None,
                held_out_iou: None,
                truth_iou,
                reliable: false,
                flags: Vec::new(),
                seconds: 0.0,
            };
            let calibrate_options = CalibrateOptions {
                focal_px: if options.known_focal {
                    Some(episode.camera.intrinsics.fx)
                } else {
                    options.calibrate.focal_px
                },
                ..options.calibrate.clone()
            };
            match calibrate(&world.embodiment, &[data], &calibrate_options, &|_| {}) {
                Ok(c) => {
                    let (p, a, f) = camera_errors(&c.camera, &episode.camera);
                    row.position_error_cm = Some(p);
                    row.angle_error_deg = Some(a);
                    row.focal_error_pct = Some(f);
                    row.held_out_iou = Some(c.held_out_iou);
                    row.reliable = c.reliable;
                    row.flags = c.flags.iter().map(|f| f.code.to_string()).collect();
                    row.seconds = c.seconds;
                }
                Err(e) => row.flags.push(format!("refused: {e}")),
            }
            progress(&format!(
                "{} {:>3} {:<10} position {} cm, angle {} deg, focal {} %, held-out IoU {} (truth {:.3}) {}",
                row.split,
                index,
                row.task,
                fmt(row.position_error_cm, 2),
                fmt(row.angle_error_deg, 2),
                fmt(row.focal_error_pct, 2),
                fmt(row.held_out_iou, 3),
                row.truth_iou,
                row.flags.join(" ")
            ));
            rows.push(row);
        }
    }
    Ok(summarize(options, rows))
}

fn fmt(v: Option<f64>, digits: usize) -> String {
    v.map_or_else(|| "-".into(), |v| format!("{v:.digits$}"))
}

fn summarize(options: &StudyOptions, rows: Vec<StudyRow>) -> StudyTable {
    let col = |f: fn(&StudyRow) -> Option<f64>| rows.iter().filter_map(f).collect::<Vec<f64>>();
    let (p, a, f) = (
        col(|r| r.position_error_cm),
        col(|r| r.angle_error_deg),
        col(|r| r.focal_error_pct),
    );
    let max = |v: &[f64]| v.iter().copied().fold(f64::NAN, f64::max);
    let within_target = rows
        .iter()
        .filter(|r| {
            r.position_error_cm.is_some_and(|v| v <= 2.0)
                && r.angle_error_deg.is_some_and(|v| v <= 1.0)
                && r.focal_error_pct.is_some_and(|v| v <= 2.0)
        })
        .count();
    StudyTable {
        robot: options.robot.clone(),
        size: (options.width, options.height),
        frames: options.frames,
        calibrated: p.len(),
        median_position_cm: median(p.clone()),
        median_angle_deg: median(a.clone()),
        median_focal_pct: median(f.clone()),
        max_position_cm: max(&p),
        max_angle_deg: max(&a),
        max_focal_pct: max(&f),
        within_target,
        rows,
    }
}

impl StudyTable {
    /// The table as Markdown: a row per camera, then the medians.
    pub fn to_markdown(&self) -> String {
        let mut s = String::from(
            "| split | # | task | azimuth deg | elevation deg | distance m | position cm | angle deg | focal % | held-out IoU | true camera's IoU | flags |\n|---|---|---|---|---|---|---|---|---|---|---|---|\n",
        );
        for r in &self.rows {
            s.push_str(&format!(
                "| {} | {} | {} | {:.0} | {:.0} | {:.2} | {} | {} | {} | {} | {:.3} | {} |\n",
                r.split,
                r.index,
                r.task,
                r.azimuth_deg,
                r.elevation_deg,
                r.distance_m,
                fmt(r.position_error_cm, 2),
                fmt(r.angle_error_deg, 2),
                fmt(r.focal_error_pct, 2),
                fmt(r.held_out_iou, 3),
                r.truth_iou,
                r.flags.join(", ")
            ));
        }
        s.push_str(&format!(
            "\n{} of {} cameras calibrated ({} {}x{}, {} frames each); median position {:.2} cm, angle {:.2} deg, focal {:.2} % (largest {:.2} cm, {:.2} deg, {:.2} %); {} within 2 cm, 1 deg and 2 %.\n",
            self.calibrated,
            self.rows.len(),
            self.robot,
            self.size.0,
            self.size.1,
            self.frames,
            self.median_position_cm,
            self.median_angle_deg,
            self.median_focal_pct,
            self.max_position_cm,
            self.max_angle_deg,
            self.max_focal_pct,
            self.within_target
        ));
        s
    }
}
