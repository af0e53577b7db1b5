//! Raw episodes to a training dataset: every camera of every episode becomes
//! one LeRobot v3.0 episode (one view-trajectory pair) with frames resized to
//! the model resolution, `calc` embodiment masks rendered from the recorded
//! joints and the calibration, the recorded states and the end-effector
//! actions. With `skip_bad`, an episode or view that fails is recorded in the
//! report (and `skipped.json`) and the conversion goes on; nothing is dropped
//! silently. Everything changed on the way (frames aligned, intrinsics
//! scaled, gripper readings clamped, joints outside the model's limits,
//! calibration fallbacks) is a [`Note`] in the report, written whole to
//! [`REPORT_FILE`]. The actions are flange poses: the dataset's
//! `meta/info.json` names the link of each arm (`bridgev2w_source.ee_frame`).

use super::align::align_frames;
use super::report::{EpisodeNote, Note};
use super::{RawEpisode, RawError, RawView};
use crate::lerobot::{DatasetError, LeRobotV3Writer, WriterEpisode};
use crate::video::{VideoError, VideoStream};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::masks::render_frame_labels;
use bridgev2w_embodiment::raster::Rasterizer;
use bridgev2w_io::npy::write_atomic;
use rayon::prelude::*;
use serde_json::json;
use std::path::{Path, PathBuf};

/// Conversion settings.
#[derive(Debug, Clone)]
pub struct ConvertOptions {
    /// Output width (pixels, even).
    pub width: usize,
    /// Output height (pixels, even).
    pub height: usize,
    /// Frame rate written to the dataset.
    pub fps: u32,
    /// Robot-specific names for the recorded joint columns (default: the
    /// dataset's own names, which are the built-in robots' names).
    pub joint_names: Option<Vec<String>>,
    /// Record failing episodes/views and go on instead of stopping.
    pub skip_bad: bool,
    /// Split recorded for every written episode (e.g. `train`).
    pub split: Option<String>,
    /// The source format's name (recorded in `meta/info.json`).
    pub source_format: String,
    /// Replace an existing output ([`crate::raw::source::convert_source`]
    /// replaces it when the new one is complete, not before).
    pub overwrite: bool,
}

/// The highest frame rate a converted dataset may record (frames per second;
/// its MP4 time base is `fps * 1000` ticks per second, a `u32`).
pub const MAX_FPS: u32 = 1000;

impl ConvertOptions {
    /// Checks the output size (even, 2..=[`crate::synth::MAX_SIDE`] pixels a
    /// side, for H.264) and the frame rate (1..=[`MAX_FPS`]: the LeRobot
    /// reader refuses a dataset whose `fps` is not positive), before any
    /// file is read or written.
    pub fn validate(&self) -> Result<(), ConvertError> {
        let max = crate::synth::MAX_SIDE as usize;
        if !(1..=max).contains(&self.width)
            || !(1..=max).contains(&self.height)
            || self.width % 2 != 0
            || self.height % 2 != 0
        {
            return Err(ConvertError::Options(format!(
                "output size {}x{}: expected even width and height of 2..={max} pixels (H.264)",
                self.width, self.height
            )));
        }
        if !(1..=MAX_FPS).contains(&self.fps) {
            return Err(ConvertError::Options(format!(
                "--fps {}: expected a frame rate of 1..={MAX_FPS} frames per second (a dataset's fps must be positive)",
                self.fps
            )));
        }
        Ok(())
    }
}

/// One item that was skipped, and why.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct Skipped {
    /// Episode id or path, and camera when the failure is one view's.
    pub item: String,
    /// The error.
    pub error: String,
}

/// The conversion report's file in the output dataset (the whole
/// [`ConvertReport`]); `skipped.json` keeps its four summary fields.
pub const REPORT_FILE: &str = "conversion_report.json";

/// What a conversion did.
#[derive(Debug, Clone, Default, serde::Serialize)]
pub struct ConvertReport {
    /// Episodes read successfully.
    pub episodes: usize,
    /// LeRobot episodes written (one per view).
    pub views_written: usize,
    /// Items skipped with `skip_bad`.
    pub skipped: Vec<Skipped>,
    /// Views whose masks are empty in every frame (robot never in view):
    /// written, but listed because it usually means bad calibration.
    pub empty_mask_views: Vec<String>,
    /// Per arm, the link the actions are poses of (from the episodes).
    pub ee_frames: Vec<String>,
    /// Everything changed or missing in the converted episodes.
    pub notes: Vec<EpisodeNote>,
}

impl ConvertReport {
    /// Per note kind (in first-seen order): the kind, how many notes, how
    /// many episodes they concern, and whether they are warnings.
    pub fn note_summary(&self) -> Vec<(&'static str, usize, usize, bool)> {
        let mut out: Vec<(&'static str, usize, Vec<&str>, bool)> = Vec::new();
        for n in &self.notes {
            let kind = n.note.kind();
            let i = match out.iter().position(|o| o.0 == kind) {
                Some(i) => i,
                None => {
                    out.push((kind, 0, Vec::new(), n.note.is_warning()));
                    out.len() - 1
                }
            };
            out[i].1 += 1;
            if !out[i].2.contains(&n.episode.as_str()) {
                out[i].2.push(&n.episode);
            }
        }
        out.into_iter()
            .map(|(k, n, eps, w)| (k, n, eps.len(), w))
            .collect()
    }
}

/// Conversion errors.
#[derive(Debug, thiserror::Error)]
pub enum ConvertError {
    /// Reading a raw episode failed.
    #[error(transparent)]
    Raw(#[from] RawError),
    /// Writing the dataset failed.
    #[error(transparent)]
    Dataset(#[from] DatasetError),
    /// A video could not be decoded.
    #[error("episode {episode}, camera \"{camera}\": {source}")]
    Video {
        /// Episode id.
        episode: String,
        /// Camera name.
        camera: String,
        /// Cause (names the file).
        source: Box<VideoError>,
    },
    /// Options are invalid.
    #[error("{0}")]
    Options(String),
}

/// Area-weighted resampling of an RGB8 image `sw x sh` to `dw x dh`: each
/// output pixel is the average of the source pixels under its footprint
/// (exact box filter; anti-aliased when shrinking).
pub fn resize_rgb(src: &[u8], (sw, sh): (usize, usize), (dw, dh): (usize, usize)) -> Vec<u8> {
    if (sw, sh) == (dw, dh) {
        return src.to_vec();
    }
    // Per output coordinate: (first source index, weights) covering
    // [o * s / d, (o + 1) * s / d).
    let taps = |s: usize, d: usize| -> Vec<(usize, Vec<f32>)> {
        (0..d)
            .map(|o| {
                let a = o as f64 * s as f64 / d as f64;
                let b = (o + 1) as f64 * s as f64 / d as f64;
                let first = a.floor() as usize;
                let last = (b.ceil() as usize).min(s);
                let w: Vec<f32> = (first..last)
                    .map(|i| ((b.min(i as f64 + 1.0) - a.max(i as f64)) / (b - a)) as f32)
                    .collect();
                (first, w)
            })
            .collect()
    };
    let (tx, ty) = (taps(sw, dw), taps(sh, dh));
    // Horizontal pass: [sh, dw, 3] floats.
    let mut mid = vec![0f32; sh * dw * 3];
    for y in 0..sh {
        for (x, (first, w)) in tx.iter().enumerate() {
            for c in 0..3 {
                mid[(y * dw + x) * 3 + c] = w
                    .iter()
                    .enumerate()
                    .map(|(k, &wk)| wk * f32::from(src[(y * sw + first + k) * 3 + c]))
                    .sum();
            }
        }
    }
    let mut out = vec![0u8; dh * dw * 3];
    for (y, (first, w)) in ty.iter().enumerate() {
        for x in 0..dw {
            for c in 0..3 {
                let v: f32 = w
                    .iter()
                    .enumerate()
                    .map(|(k, &wk)| wk * mid[((first + k) * dw + x) * 3 + c])
                    .sum();
                out[(y * dw + x) * 3 + c] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    out
}

/// One view of an episode at the output size: frames, masks and cameras,
/// one per written frame, and the state each frame belongs to.
#[derive(Debug, Clone)]
pub struct ViewClip {
    /// RGB8 frames `width * height * 3`.
    pub rgb: Vec<Vec<u8>>,
    /// 0/1 masks `width * height`.
    pub masks: Vec<Vec<u8>>,
    /// Link labels `width * height` (0 = background; robot pixels exactly
    /// the masks'), as `bridgev2w synth` writes them.
    pub labels: Vec<Vec<u8>>,
    /// Cameras per frame at the output size.
    pub cameras: Vec<Camera>,
    /// The episode's state index of each frame (all states, in order, unless
    /// the video's frame count differed; see [`align_frames`]).
    pub states: Vec<usize>,
    /// What was changed (frames aligned, intrinsics scaled).
    pub notes: Vec<Note>,
}

/// Decodes `view`'s video, skips the leading frames its edit list hides
/// ([`crate::video::VideoInfo::hidden_by_edit_list`], noted), aligns the
/// frames it shows with the episode's states
/// (refusing counts that differ by more than
/// [`super::align::MAX_FRAME_DIFFERENCE`]), scales the intrinsics to the
/// video's size (noted when they differ), resizes the frames and renders the
/// `calc` masks of `q` (one configuration per state).
pub fn render_view(
    episode: &RawEpisode,
    view: &RawView,
    embodiment: &Embodiment,
    q: &[Vec<f64>],
    (width, height): (usize, usize),
) -> Result<ViewClip, ConvertError> {
    let video_err = |e| ConvertError::Video {
        episode: episode.id.clone(),
        camera: view.name.clone(),
        source: Box::new(e),
    };
    // Streamed: only the resized frames are held, never the whole video.
    let mut stream = VideoStream::open(&view.video).map_err(video_err)?;
    let video = stream.info().clone();
    // The frames a player shows: the edit list may hide leading ones.
    let hidden = video.hidden_by_edit_list();
    let shown = video.frames - hidden;
    if shown == 0 {
        return Err(ConvertError::Raw(RawError::Inconsistent {
            episode: episode.id.clone(),
            message: format!(
                "video {}: its edit list hides all {} frames",
                view.video.display(),
                video.frames
            ),
        }));
    }
    let alignment = align_frames(episode, view, shown)?;
    let mut notes: Vec<Note> = Vec::new();
    if hidden > 0 {
        notes.push(Note::EditListSkipped {
            video: view.video.clone(),
            video_frames: video.frames,
            hidden,
        });
    }
    notes.extend(alignment.note);
    let k = &view.intrinsics;
    let (vw, vh) = (video.width as u32, video.height as u32);
    if (k.width, k.height) != (vw, vh) {
        let scale = [
            f64::from(vw) / f64::from(k.width),
            f64::from(vh) / f64::from(k.height),
        ];
        notes.push(Note::IntrinsicsScaled {
            from: [k.width, k.height],
            to: [vw, vh],
            scale,
            uniform: (scale[0] / scale[1] - 1.0).abs() <= 0.01,
        });
    }
    let pairs = alignment.pairs;
    // Intrinsics at the video's size, then at the output size (one rescale:
    // the two compose exactly).
    let cameras: Vec<Camera> = pairs
        .iter()
        .map(|&(_, s)| view.camera(s).rescaled(width as u32, height as u32))
        .collect();
    let robot = &embodiment.robot;
    // Link labels as `bridgev2w synth` writes them (u8, 0 = background),
    // for link-coded models, and the 0/1 masks they imply.
    let labels: Vec<Vec<u8>> = pairs
        .par_iter()
        .zip(&cameras)
        .map(|(&(_, s), cam)| {
            render_frame_labels(robot, &Rasterizer::new(cam), &q[s])
                .iter()
                .map(|&l| l.min(255) as u8)
                .collect()
        })
        .collect();
    let masks: Vec<Vec<u8>> = labels
        .iter()
        .map(|l| l.iter().map(|&v| u8::from(v != 0)).collect())
        .collect();
    // The slot of each shown frame in the clip (frames the alignment drops
    // have none); frames are resized in parallel chunks as they come.
    let mut slot_of = vec![None; shown];
    for (slot, &(v, _)) in pairs.iter().enumerate() {
        slot_of[v] = Some(slot);
    }
    let mut rgb = vec![Vec::new(); pairs.len()];
    let mut chunk: Vec<(usize, Vec<u8>)> = Vec::new();
    let resize = |chunk: &mut Vec<(usize, Vec<u8>)>, rgb: &mut [Vec<u8>]| {
        let resized: Vec<(usize, Vec<u8>)> = chunk
            .par_drain(..)
            .map(|(slot, f)| {
                (
                    slot,
                    resize_rgb(&f, (video.width, video.height), (width, height)),
                )
            })
            .collect();
        for (slot, f) in resized {
            rgb[slot] = f;
        }
    };
    while let Some(frame) = stream.next_frame().map_err(video_err)? {
        let Some(shown_index) = frame.index.checked_sub(hidden) else {
            continue; // hidden by the edit list
        };
        if let Some(slot) = slot_of.get(shown_index).copied().flatten() {
            chunk.push((slot, frame.rgb));
            if chunk.len() >= 32 {
                resize(&mut chunk, &mut rgb);
            }
        }
    }
    resize(&mut chunk, &mut rgb);
    if let Some(slot) = rgb.iter().position(Vec::is_empty) {
        return Err(ConvertError::Raw(RawError::Inconsistent {
            episode: episode.id.clone(),
            message: format!(
                "video {}: frame {} of {} was not decoded",
                view.video.display(),
                pairs[slot].0 + hidden,
                video.frames
            ),
        }));
    }
    Ok(ViewClip {
        rgb,
        masks,
        labels,
        cameras,
        states: pairs.iter().map(|p| p.1).collect(),
        notes,
    })
}

/// Converts `episodes` (id, read result) into a LeRobot v3.0 dataset at `out`.
/// `on_item` is called after each episode (for progress bars).
pub fn convert(
    episodes: impl IntoIterator<Item = (String, Result<RawEpisode, RawError>)>,
    embodiment: &Embodiment,
    out: &Path,
    options: &ConvertOptions,
    on_item: &dyn Fn(&str),
) -> Result<ConvertReport, ConvertError> {
    convert_listing(episodes, Vec::new(), embodiment, out, options, on_item)
}

/// [`convert`], with items the reader already set aside (e.g. repeated
/// episodes) listed first among the report's skipped items.
pub fn convert_listing(
    episodes: impl IntoIterator<Item = (String, Result<RawEpisode, RawError>)>,
    set_aside: Vec<Skipped>,
    embodiment: &Embodiment,
    out: &Path,
    options: &ConvertOptions,
    on_item: &dyn Fn(&str),
) -> Result<ConvertReport, ConvertError> {
    options.validate()?;
    let arms = embodiment.end_effectors.len();
    let names = |prefix: &str, n: usize| (0..n).map(|i| format!("{prefix}{i}")).collect();
    let state_dim = embodiment.robot.dof();
    let mut writer = LeRobotV3Writer::new(
        out,
        &embodiment.robot.name,
        options.fps,
        "observation.images.main",
        (options.width, options.height),
        embodiment
            .robot
            .dof_names()
            .iter()
            .map(|s| s.to_string())
            .collect(),
        names("ee_", 7 * arms),
    )?;
    let mut report = ConvertReport {
        skipped: set_aside,
        ..ConvertReport::default()
    };
    for (item, result) in episodes {
        let outcome = (|| -> Result<Vec<(String, ConvertError)>, ConvertError> {
            let ep = result?;
            if ep.arms() != arms {
                return Err(ConvertError::Raw(RawError::Embodiment {
                    episode: ep.id.clone(),
                    message: format!(
                        "{} arm(s) recorded but robot \"{}\" has {arms}",
                        ep.arms(),
                        embodiment.robot.name
                    ),
                }));
            }
            if !report.ee_frames.is_empty() && report.ee_frames != ep.ee_frames {
                return Err(ConvertError::Raw(RawError::Inconsistent {
                    episode: ep.id.clone(),
                    message: format!(
                        "actions are poses of {:?}, but earlier episodes' of {:?} (one dataset, one frame)",
                        ep.ee_frames, report.ee_frames
                    ),
                }));
            }
            let jt = ep.joint_trajectory(embodiment, options.joint_names.as_deref())?;
            let q = jt.q;
            let mut notes = ep.notes.clone();
            notes.extend(jt.notes.into_iter().map(|note| EpisodeNote {
                episode: ep.id.clone(),
                camera: None,
                note,
            }));
            let to_f32 = |rows: &[Vec<f64>]| -> Vec<Vec<f32>> {
                rows.iter()
                    .map(|r| r.iter().map(|&v| v as f32).collect())
                    .collect()
            };
            let (states, actions) = (to_f32(&q), to_f32(&ep.ee_actions));
            debug_assert!(states.iter().all(|s| s.len() == state_dim));
            let pick = |rows: &[Vec<f32>], idx: &[usize]| -> Vec<Vec<f32>> {
                idx.iter().map(|&i| rows[i].clone()).collect()
            };
            let task = ep.task.clone().unwrap_or_default();
            let mut view_errors = Vec::new();
            for view in &ep.views {
                let clip =
                    match render_view(&ep, view, embodiment, &q, (options.width, options.height)) {
                        Ok(c) => c,
                        Err(e) if options.skip_bad => {
                            view_errors.push((format!("{} camera {}", ep.id, view.name), e));
                            continue;
                        }
                        Err(e) => return Err(e),
                    };
                if clip.masks.iter().all(|m| m.iter().all(|&v| v == 0)) {
                    report
                        .empty_mask_views
                        .push(format!("{} camera {}", ep.id, view.name));
                }
                notes.extend(clip.notes.iter().map(|note| EpisodeNote {
                    episode: ep.id.clone(),
                    camera: Some(view.name.clone()),
                    note: note.clone(),
                }));
                writer.add_episode(WriterEpisode {
                    task: &task,
                    split: view.split.as_deref().or(options.split.as_deref()),
                    states: pick(&states, &clip.states),
                    actions: pick(&actions, &clip.states),
                    rgb: &clip.rgb,
                    masks: Some(&clip.masks),
                    labels: Some(&clip.labels),
                    camera: view.is_static().then_some(&clip.cameras[0]),
                })?;
                report.views_written += 1;
            }
            report.episodes += 1;
            report.notes.extend(notes);
            if report.ee_frames.is_empty() {
                report.ee_frames = ep.ee_frames.clone();
            }
            Ok(view_errors)
        })();
        match outcome {
            Ok(view_errors) => report
                .skipped
                .extend(view_errors.into_iter().map(|(item, e)| Skipped {
                    item,
                    error: e.to_string(),
                })),
            Err(e) if options.skip_bad => report.skipped.push(Skipped {
                item: item.clone(),
                error: e.to_string(),
            }),
            Err(e) => return Err(e),
        }
        on_item(&item);
    }
    if report.views_written == 0 {
        return Err(ConvertError::Options(format!(
            "no episode could be converted ({} skipped){}",
            report.skipped.len(),
            report.skipped.first().map_or(String::new(), |s| format!(
                "; first: {}: {}",
                s.item, s.error
            ))
        )));
    }
    writer.finish(json!({
        "bridgev2w_source": {
            "format": options.source_format,
            "episodes": report.episodes,
            "skipped": report.skipped.len(),
            "ee_frame": report.ee_frames,
            "action": "per arm [x, y, z, roll, pitch, yaw, gripper]: the pose of the ee_frame link \
                       (a flange, not a TCP) in the robot base frame, metres and extrinsic XYZ \
                       Euler angles (radians); gripper 0 open .. 1 closed",
            "report": REPORT_FILE,
        }
    }))?;
    let skipped = json!({
        "episodes": report.episodes,
        "views_written": report.views_written,
        "skipped": report.skipped,
        "empty_mask_views": report.empty_mask_views,
    });
    for (name, text) in [
        (REPORT_FILE, serde_json::to_string_pretty(&report)),
        ("skipped.json", serde_json::to_string_pretty(&skipped)),
    ] {
        let path: PathBuf = out.join(name);
        let text = text.map_err(|e| ConvertError::Options(format!("{name}: {e}")))?;
        write_atomic(&path, text.as_bytes()).map_err(|source| {
            ConvertError::Dataset(DatasetError::Io {
                path: path.clone(),
                source,
            })
        })?;
    }
    Ok(report)
}
