//! The calibration on real video: every exterior camera of DROID episodes
//! in the Ctrl-World layout (`<collection>/annotation/<split>/<id>.json`,
//! `<collection>/videos/<split>/<id>/{0,1,2}.mp4`; `0` and `1` exterior,
//! `2` the wrist), calibrated from each episode alone and scored on its
//! held-out frames. Where episodes share a rig (collections named
//! `droid_new_setup*`: one rig, same cameras), one calibration fitted on a
//! few of them is checked on all the others, and the per-episode cameras are
//! compared with it: a fixed camera calibrated from different episodes
//! should land in the same place.

use super::report::write_outputs;
use super::study::median;
use super::{calibrate, check, load_episode, CalibrateError, CalibrateOptions, EpisodeInput};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_embodiment::embodiment::Embodiment;
use serde::Serialize;
use std::path::{Path, PathBuf};

/// DROID's exterior cameras in the Ctrl-World layout (`0.mp4`, `1.mp4`).
pub const EXTERIOR_CAMERAS: [usize; 2] = [0, 1];

/// fy / fx of the Ctrl-World DROID videos: 320x180 stretched to 320x192.
pub const DROID_FY_OVER_FX: f64 = 192.0 / 180.0;

/// Options of [`droid_study`].
#[derive(Debug, Clone, PartialEq)]
pub struct DroidStudyOptions {
    /// The folder holding the collections (`droid_subset`,
    /// `droid_new_setup`, `droid_new_setup_full/<task>`, ...).
    pub root: PathBuf,
    /// Episodes of the shared rig the rig calibration is fitted on (the
    /// first ones in sorted order); the others are checked.
    pub rig_fit_episodes: usize,
    /// At most this many episodes per collection (`None`: all).
    pub episodes_per_collection: Option<usize>,
    /// The calibration's options (`fy_over_fx` should be
    /// [`DROID_FY_OVER_FX`] for the Ctrl-World videos).
    pub calibrate: CalibrateOptions,
}

impl DroidStudyOptions {
    /// The study of every episode under `root` with DROID's settings.
    pub fn new(root: impl Into<PathBuf>) -> Self {
        Self {
            root: root.into(),
            rig_fit_episodes: 3,
            episodes_per_collection: None,
            calibrate: CalibrateOptions {
                fy_over_fx: DROID_FY_OVER_FX,
                ..CalibrateOptions::default()
            },
        }
    }

    /// Checks the options; errors name the flag.
    pub fn validate(&self) -> Result<(), CalibrateError> {
        if !(1..=50).contains(&self.rig_fit_episodes) {
            return Err(CalibrateError::Option {
                field: "--rig-fit-episodes",
                value: self.rig_fit_episodes.to_string(),
                expected: "1..=50".into(),
            });
        }
        if self.episodes_per_collection == Some(0) {
            return Err(CalibrateError::Option {
                field: "--episodes-per-collection",
                value: "0".into(),
                expected: "at least 1".into(),
            });
        }
        self.calibrate.validate()
    }
}

/// One DROID episode of the Ctrl-World layout (the importer's type).
pub use crate::raw::ctrl_world::CtrlWorldEpisode as DroidEpisode;

/// The input of camera `camera` (`0.mp4` ...) of an episode.
fn input(ep: &DroidEpisode, camera: usize) -> EpisodeInput {
    EpisodeInput {
        video: ep.video(camera),
        joints: ep.annotation.clone(),
    }
}

/// A file-name-safe label: `collection_split_id_camN`.
fn label(ep: &DroidEpisode, camera: usize) -> String {
    format!(
        "{}_{}_{}_cam{camera}",
        ep.collection.replace('/', "_"),
        ep.split,
        ep.id
    )
}

/// Every episode under `root` ([`crate::raw::ctrl_world::find_episodes`]),
/// its error as a calibration error naming the root.
pub fn find_droid_episodes(root: &Path) -> Result<Vec<DroidEpisode>, CalibrateError> {
    crate::raw::ctrl_world::find_episodes(root).map_err(|e| CalibrateError::Episode {
        episode: root.display().to_string(),
        message: e.to_string(),
    })
}

/// One exterior camera of one episode.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DroidRow {
    /// `collection/split/id`.
    pub episode: String,
    /// 0 or 1.
    pub camera: usize,
    /// Frames used (video and joints).
    pub frames: usize,
    /// The episode's own calibration: held-out IoU (`None`: refused).
    pub held_out_iou: Option<f64>,
    /// Its IoU on the fitted frames.
    pub fit_iou: Option<f64>,
    /// Whether it raised no flag.
    pub reliable: bool,
    /// Flags raised, or the refusal.
    pub flags: Vec<String>,
    /// The camera's position in the robot's base frame (metres).
    pub position_m: Option<[f64; 3]>,
    /// Its fx at the video's size (pixels).
    pub fx_px: Option<f64>,
    /// Distance of this camera to the rig's calibration of the same camera
    /// (metres; shared-rig episodes only).
    pub distance_to_rig_m: Option<f64>,
    /// The rig calibration's IoU on this episode: held out for the
    /// episodes it was fitted on, every frame for the others.
    pub rig_iou: Option<f64>,
    /// Whether the rig calibration was fitted on this episode.
    pub rig_fitted: bool,
    /// Seconds the episode's calibration took.
    pub seconds: f64,
}

/// The rig calibration of one camera.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct RigResult {
    /// 0 or 1.
    pub camera: usize,
    /// The episodes it was fitted on.
    pub fitted_on: Vec<String>,
    /// Its held-out IoU over the fitted episodes.
    pub held_out_iou: f64,
    /// Median IoU over the episodes it was checked on.
    pub median_check_iou: f64,
    /// Lowest IoU over the checked episodes.
    pub min_check_iou: f64,
    /// Episodes checked.
    pub checked: usize,
    /// Median distance of the episodes' own reliable calibrations to it (m).
    pub median_distance_m: f64,
    /// Reliable episode calibrations compared.
    pub compared: usize,
    /// Its position (metres) and fx (pixels).
    pub position_m: [f64; 3],
    /// fx at the video's size.
    pub fx_px: f64,
    /// Whether it raised no flag, and the flags.
    pub reliable: bool,
    /// Flags raised.
    pub flags: Vec<String>,
}

/// The study's results.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DroidStudyTable {
    /// Per episode and exterior camera.
    pub rows: Vec<DroidRow>,
    /// Per exterior camera of the shared rig.
    pub rigs: Vec<RigResult>,
    /// Cameras calibrated (not refused).
    pub calibrated: usize,
    /// Calibrations without a flag.
    pub reliable: usize,
    /// Median held-out IoU over calibrated cameras.
    pub median_held_out_iou: f64,
}

fn position(c: &Camera) -> [f64; 3] {
    let t = c.world_from_camera.translation.vector;
    [t.x, t.y, t.z]
}

fn distance(a: [f64; 3], b: [f64; 3]) -> f64 {
    a.iter()
        .zip(&b)
        .map(|(x, y)| (x - y).powi(2))
        .sum::<f64>()
        .sqrt()
}

/// [`droid_study`] into a new folder `out` (never one overlapping the
/// DROID folder): a calibration folder per camera, `study.md` and
/// `study.json`, written as a transaction (an existing `out` is refused
/// unless `overwrite`). Returns the table and the folder.
pub fn droid_study_to_folder(
    embodiment: &Embodiment,
    options: &DroidStudyOptions,
    out: &Path,
    overwrite: bool,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<(DroidStudyTable, PathBuf), CalibrateError> {
    options.validate()?;
    super::report::study_folder(
        out,
        overwrite,
        &[options.root.as_path()],
        |dir| droid_study(embodiment, options, dir, progress),
        DroidStudyTable::to_markdown,
    )
}

/// Calibrates every exterior camera of every episode under
/// `options.root` (DROID's robot: `franka-robotiq`), then the shared rig's cameras from a few episodes,
/// checked on the others. Each calibration's `camera.json`,
/// `residuals.json` and overlay GIFs go to `out_dir/<label>/` (a folder the
/// caller owns); `progress` hears each result.
pub fn droid_study(
    embodiment: &Embodiment,
    options: &DroidStudyOptions,
    out_dir: &Path,
    progress: &(dyn Fn(&str) + Sync),
) -> Result<DroidStudyTable, CalibrateError> {
    options.validate()?;
    let mut episodes = find_droid_episodes(&options.root)?;
    if let Some(n) = options.episodes_per_collection {
        let mut kept = Vec::new();
        for e in episodes {
            if kept
                .iter()
                .filter(|k: &&DroidEpisode| k.collection == e.collection)
                .count()
                < n
            {
                kept.push(e);
            }
        }
        episodes = kept;
    }
    let o = &options.calibrate;
    let mut rows = Vec::new();
    for ep in &episodes {
        for camera in EXTERIOR_CAMERAS {
            let label = label(ep, camera);
            let data = load_episode(&input(ep, camera), embodiment, o.analysis_width)?;
            let mut row = DroidRow {
                episode: ep.name(),
                camera,
                frames: data.frames.len(),
                held_out_iou: None,
                fit_iou: None,
                reliable: false,
                flags: Vec::new(),
                position_m: None,
                fx_px: None,
                distance_to_rig_m: None,
                rig_iou: None,
                rig_fitted: false,
                seconds: 0.0,
            };
            let started = std::time::Instant::now();
            match calibrate(embodiment, std::slice::from_ref(&data), o, &|_| {}) {
                Ok(c) => {
                    let dir = out_dir.join(&label);
                    create_dir(&dir)?;
                    write_outputs(
                        &dir,
                        &embodiment.robot,
                        &c,
                        std::slice::from_ref(&data),
                        &[],
                        &[],
                        o,
                    )?;
                    row.held_out_iou = Some(c.held_out_iou);
                    row.fit_iou = Some(c.fit_iou);
                    row.reliable = c.reliable;
                    row.flags = c.flags.iter().map(|f| f.code.to_string()).collect();
                    row.position_m = Some(position(&c.camera));
                    row.fx_px = Some(c.camera.intrinsics.fx);
                }
                Err(e) => row.flags.push(format!("refused: {e}")),
            }
            row.seconds = started.elapsed().as_secs_f64();
            progress(&format!(
                "{} camera {camera}: held-out IoU {} (fit {}) {} [{:.0} s]",
                row.episode,
                fmt(row.held_out_iou, 3),
                fmt(row.fit_iou, 3),
                row.flags.join(" "),
                row.seconds
            ));
            rows.push(row);
        }
    }
    let rig: Vec<&DroidEpisode> = episodes.iter().filter(|e| e.shared_rig()).collect();
    let mut rigs = Vec::new();
    if rig.len() > options.rig_fit_episodes {
        for camera in EXTERIOR_CAMERAS {
            rigs.push(rig_calibration(
                embodiment, &rig, camera, options, out_dir, &mut rows, progress,
            )?);
        }
    }
    let held: Vec<f64> = rows.iter().filter_map(|r| r.held_out_iou).collect();
    Ok(DroidStudyTable {
        calibrated: held.len(),
        reliable: rows.iter().filter(|r| r.reliable).count(),
        median_held_out_iou: median(held),
        rows,
        rigs,
    })
}

fn create_dir(dir: &Path) -> Result<(), CalibrateError> {
    std::fs::create_dir_all(dir).map_err(|e| CalibrateError::Output {
        path: dir.to_path_buf(),
        message: e.to_string(),
    })
}

/// One camera of the shared rig: fitted on the first
/// `options.rig_fit_episodes` episodes, checked on the others; fills the
/// rows' rig columns.
fn rig_calibration(
    embodiment: &Embodiment,
    rig: &[&DroidEpisode],
    camera: usize,
    options: &DroidStudyOptions,
    out_dir: &Path,
    rows: &mut [DroidRow],
    progress: &(dyn Fn(&str) + Sync),
) -> Result<RigResult, CalibrateError> {
    let o = &options.calibrate;
    let (fit, rest) = rig.split_at(options.rig_fit_episodes);
    let load = |eps: &[&DroidEpisode]| {
        eps.iter()
            .map(|e| load_episode(&input(e, camera), embodiment, o.analysis_width))
            .collect::<Result<Vec<_>, _>>()
    };
    let fitted = load(fit)?;
    let checked = load(rest)?;
    progress(&format!(
        "rig camera {camera}: fitting on {} episodes, checking on {}",
        fitted.len(),
        checked.len()
    ));
    let c = calibrate(embodiment, &fitted, o, &|_| {})?;
    let checks = check(embodiment, &c.camera, &checked, o)?;
    let dir = out_dir.join(format!("rig_cam{camera}"));
    create_dir(&dir)?;
    write_outputs(&dir, &embodiment.robot, &c, &fitted, &checked, &checks, o)?;
    let rig_position = position(&c.camera);
    for (ep, r) in fit.iter().zip(&c.episodes) {
        set_rig(rows, ep, camera, r.held_out_iou, true, rig_position);
    }
    for (ep, r) in rest.iter().zip(&checks) {
        set_rig(rows, ep, camera, r.held_out_iou, false, rig_position);
    }
    let check_ious: Vec<f64> = checks.iter().map(|r| r.held_out_iou).collect();
    let distances: Vec<f64> = rows
        .iter()
        .filter(|r| r.camera == camera && r.reliable)
        .filter_map(|r| r.distance_to_rig_m)
        .collect();
    let result = RigResult {
        camera,
        fitted_on: fit.iter().map(|e| e.name()).collect(),
        held_out_iou: c.held_out_iou,
        median_check_iou: median(check_ious.clone()),
        min_check_iou: check_ious.iter().copied().fold(f64::NAN, f64::min),
        checked: check_ious.len(),
        compared: distances.len(),
        median_distance_m: median(distances),
        position_m: rig_position,
        fx_px: c.camera.intrinsics.fx,
        reliable: c.reliable,
        flags: c.flags.iter().map(|f| f.code.to_string()).collect(),
    };
    progress(&format!(
        "rig camera {camera}: held-out IoU {:.3} on the fitted episodes, median {:.3} (lowest {:.3}) on {} others; own calibrations median {:.3} m away",
        result.held_out_iou, result.median_check_iou, result.min_check_iou, result.checked, result.median_distance_m
    ));
    Ok(result)
}

fn set_rig(
    rows: &mut [DroidRow],
    ep: &DroidEpisode,
    camera: usize,
    iou: f64,
    fitted: bool,
    rig_position: [f64; 3],
) {
    let name = ep.name();
    if let Some(r) = rows
        .iter_mut()
        .find(|r| r.episode == name && r.camera == camera)
    {
        r.rig_iou = Some(iou);
        r.rig_fitted = fitted;
        r.distance_to_rig_m = r.position_m.map(|p| distance(p, rig_position));
    }
}

fn fmt(v: Option<f64>, digits: usize) -> String {
    v.map_or_else(|| "-".into(), |v| format!("{v:.digits$}"))
}

impl DroidStudyTable {
    /// The table as Markdown: a row per episode and camera, the rig's
    /// calibrations, then the summary.
    pub fn to_markdown(&self) -> String {
        let mut s = String::from(
            "| episode | camera | frames | held-out IoU | fit IoU | position (m) | fx (px) | flags | rig IoU | to rig (m) |\n|---|---|---|---|---|---|---|---|---|---|\n",
        );
        for r in &self.rows {
            let flags: Vec<String> = r
                .flags
                .iter()
                .map(|f| {
                    if f.starts_with("refused") {
                        refusal_kind(f)
                    } else {
                        f.clone()
                    }
                })
                .collect();
            s.push_str(&format!(
                "| {} | {} | {} | {} | {} | {} | {} | {} | {}{} | {} |\n",
                r.episode,
                r.camera,
                r.frames,
                fmt(r.held_out_iou, 3),
                fmt(r.fit_iou, 3),
                r.position_m.map_or_else(
                    || "-".into(),
                    |p| format!("{:.2}, {:.2}, {:.2}", p[0], p[1], p[2])
                ),
                fmt(r.fx_px, 0),
                flags.join(", "),
                fmt(r.rig_iou, 3),
                if r.rig_fitted { " (fitted)" } else { "" },
                fmt(r.distance_to_rig_m, 2),
            ));
        }
        for g in &self.rigs {
            s.push_str(&format!(
                "\nShared rig (`droid_new_setup*`), camera {}: fitted on {}; held-out IoU {:.3} on them, median {:.3} (lowest {:.3}) on the {} other episodes; position ({:.2}, {:.2}, {:.2}) m, fx {:.0} px{}; the episodes' own reliable calibrations are a median {:.2} m from it ({} compared).\n",
                g.camera,
                g.fitted_on.join(", "),
                g.held_out_iou,
                g.median_check_iou,
                g.min_check_iou,
                g.checked,
                g.position_m[0],
                g.position_m[1],
                g.position_m[2],
                g.fx_px,
                if g.reliable { String::new() } else { format!(", flags: {}", g.flags.join(", ")) },
                g.median_distance_m,
                g.compared
            ));
        }
        s.push_str(&format!(
            "\n{} of {} exterior cameras calibrated, {} without a flag; median held-out IoU {:.3}.\n",
            self.calibrated,
            self.rows.len(),
            self.reliable,
            self.median_held_out_iou
        ));
        s
    }
}

/// A refusal's kind in a few words (the full text is in `study.json`).
fn refusal_kind(text: &str) -> String {
    for (needle, kind) in [
        ("the camera moves", "refused: camera moves"),
        ("hardly moves", "refused: robot still"),
        ("sees too little", "refused: too little robot"),
        ("no camera found", "refused: no camera found"),
    ] {
        if text.contains(needle) {
            return kind.into();
        }
    }
    "refused".into()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn episodes_are_found_in_the_ctrl_world_layout_and_a_missing_one_is_an_error() {
        let d = tempfile::tempdir().expect("test setup");
        let c = d.path().join("droid_new_setup_full/drawer");
        std::fs::create_dir_all(c.join("videos/val/0001")).expect("test setup");
        std::fs::create_dir_all(c.join("annotation/val")).expect("test setup");
        std::fs::write(c.join("videos/val/0001/0.mp4"), b"x").expect("test setup");
        std::fs::write(c.join("annotation/val/0001.json"), b"{}").expect("test setup");
        // A video folder without its annotation is skipped.
        std::fs::create_dir_all(c.join("videos/val/0002")).expect("test setup");
        std::fs::write(c.join("videos/val/0002/0.mp4"), b"x").expect("test setup");
        let found = find_droid_episodes(d.path()).expect("test setup");
        assert_eq!(found.len(), 1);
        assert_eq!(found[0].name(), "droid_new_setup_full/drawer/val/0001");
        assert!(found[0].shared_rig());
        assert_eq!(
            label(&found[0], 1),
            "droid_new_setup_full_drawer_val_0001_cam1"
        );
        // The collection itself as the root: named by its folder.
        let one = find_droid_episodes(&c).expect("test setup");
        assert_eq!(one[0].name(), "drawer/val/0001");
        let empty = tempfile::tempdir().expect("test setup");
        let e = find_droid_episodes(empty.path())
            .expect_err("refused")
            .to_string();
        assert!(
            e.contains("missing DROID episode of the Ctrl-World layout"),
            "{e}"
        );
    }
}
