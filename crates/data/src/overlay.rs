//! Rendered masks over a camera's real frames, to see and score how well
//! they line up on one's own data (`bridgev2w overlay`): each link's outline
//! drawn on the real image (PNG per frame and a GIF), and, where the user
//! has a ground truth, a number: the IoU against a robot segmentation, and
//! whether known robot points (e.g. a recorded flange position projected
//! through the calibration, or hand-clicked points) fall inside the mask.

use crate::video::{decode_mp4, VideoError};
use bridgev2w_embodiment::camera::{read_poses_npy, CameraTrack};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::kinematics::IkOptions;
use bridgev2w_embodiment::masks::render_track_labels;
use bridgev2w_embodiment::masks_folder::{read_joint_trajectory, MasksJobError, TrajectoryFile};
use bridgev2w_embodiment::overlay::{draw_outlines, write_gif, OverlayError as GifError};
use bridgev2w_embodiment::robot::Robot;
use bridgev2w_io::npy::{read_npy, write_npy, NpyError};
use bridgev2w_io::output::{OutputDir, OutputError};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Errors of [`overlay`]; each names the file and what was expected.
#[derive(Debug, thiserror::Error)]
pub enum OverlayError {
    /// A file could not be read or written.
    #[error("{}: {message}", path.display())]
    File {
        /// The file.
        path: PathBuf,
        /// What went wrong.
        message: String,
    },
    /// The video could not be decoded.
    #[error(transparent)]
    Video(#[from] VideoError),
    /// A `.npy` file could not be read or written.
    #[error(transparent)]
    Npy(#[from] NpyError),
    /// The GIF could not be written.
    #[error(transparent)]
    Gif(#[from] GifError),
    /// The inputs do not fit together (frame counts, sizes, camera).
    #[error("{0}")]
    Mismatch(String),
    /// The camera or the trajectory ([`OverlayJob`]).
    #[error(transparent)]
    Inputs(#[from] MasksJobError),
    /// The output folder ([`OverlayJob`]).
    #[error(transparent)]
    Output(#[from] OutputError),
}

fn file_err(path: &Path, message: impl Into<String>) -> OverlayError {
    OverlayError::File {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// Where the real frames come from.
#[derive(Debug, Clone, PartialEq)]
pub enum FrameSource {
    /// An MP4 file (H.264 or AV1), every frame.
    Video(PathBuf),
    /// Image files (PNG), one per frame, in order.
    Images(Vec<PathBuf>),
}

impl FrameSource {
    /// An `.mp4` file, a `.png` file, or a folder of `.png` files (sorted by
    /// name).
    pub fn from_path(path: &Path) -> Result<Self, OverlayError> {
        let ext = |p: &Path| {
            p.extension()
                .map(|e| e.to_string_lossy().to_lowercase())
                .unwrap_or_default()
        };
        if path.is_dir() {
            let mut files: Vec<PathBuf> = std::fs::read_dir(path)
                .map_err(|e| file_err(path, e.to_string()))?
                .filter_map(Result::ok)
                .map(|e| e.path())
                .filter(|p| p.is_file() && ext(p) == "png")
                .collect();
            files.sort();
            if files.is_empty() {
                return Err(file_err(path, "no .png frames in this folder"));
            }
            return Ok(FrameSource::Images(files));
        }
        match ext(path).as_str() {
            "mp4" => Ok(FrameSource::Video(path.to_path_buf())),
            "png" => Ok(FrameSource::Images(vec![path.to_path_buf()])),
            other => Err(file_err(
                path,
                format!(
                    "frames of type \"{other}\": expected an .mp4 video, a .png image or a folder of .png images"
                ),
            )),
        }
    }

    /// The frames, RGB8 row-major, and their size `(width, height)`.
    pub fn read(&self) -> Result<(usize, usize, Vec<Vec<u8>>), OverlayError> {
        match self {
            FrameSource::Video(p) => {
                let v = decode_mp4(p)?;
                Ok((v.width, v.height, v.frames))
            }
            FrameSource::Images(files) => {
                let mut size = None;
                let mut frames = Vec::with_capacity(files.len());
                for f in files {
                    let bytes = std::fs::read(f).map_err(|e| file_err(f, e.to_string()))?;
                    let (w, h, rgb) = bridgev2w_io::png::decode_rgb8(&bytes)
                        .map_err(|e| file_err(f, format!("not a readable PNG: {e}")))?;
                    let (w, h) = (w as usize, h as usize);
                    if let Some((w0, h0)) = size {
                        if (w, h) != (w0, h0) {
                            return Err(file_err(
                                f,
                                format!("{w}x{h}, but the first frame is {w0}x{h0}: expected frames of one size"),
                            ));
                        }
                    }
                    size = Some((w, h));
                    frames.push(rgb);
                }
                let (w, h) = size.unwrap_or((0, 0));
                Ok((w, h, frames))
            }
        }
    }
}

/// A pixel that shows the robot in a real frame (ground truth for
/// [`overlay`]): e.g. a recorded flange position projected through the
/// calibration, or a point clicked on the robot.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TruthPoint {
    /// Frame index.
    pub frame: usize,
    /// Column (pixels, OpenCV convention: pixel centres at integers).
    pub u: f64,
    /// Row (pixels).
    pub v: f64,
    /// What the point is (optional, copied to the report).
    #[serde(default)]
    pub name: String,
}

/// Options of [`overlay`].
#[derive(Debug, Clone)]
pub struct OverlayOptions {
    /// The real frames.
    pub frames: FrameSource,
    /// A robot segmentation of the real frames (`.npy` `[T, H, W]`, 0/1 or
    /// 0/255) to score the masks against (IoU per frame).
    pub truth_masks: Option<PathBuf>,
    /// Robot pixels (JSON list of [`TruthPoint`]) that the masks should
    /// cover.
    pub truth_points: Option<PathBuf>,
    /// A point within this distance of the mask (pixels) counts as inside.
    pub point_tolerance_px: f64,
    /// Frame rate of `overlay.gif`.
    pub fps: u32,
    /// Opacity of the fill inside the outlines (0..1).
    pub tint: f32,
}

impl Default for OverlayOptions {
    fn default() -> Self {
        Self {
            frames: FrameSource::Images(Vec::new()),
            truth_masks: None,
            truth_points: None,
            point_tolerance_px: 2.0,
            fps: 5,
            tint: 0.25,
        }
    }
}

/// One frame's scores.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FrameScore {
    /// Frame index.
    pub frame: usize,
    /// Rendered robot pixels.
    pub robot_pixels: usize,
    /// IoU against the truth mask, when one is given.
    pub iou: Option<f64>,
}

/// One truth point's result.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PointScore {
    /// The point.
    #[serde(flatten)]
    pub point: TruthPoint,
    /// Distance to the nearest rendered robot pixel (0 inside; `null` when
    /// the frame's mask is empty).
    pub distance_px: Option<f64>,
    /// Within the tolerance.
    pub inside: bool,
}

/// What [`overlay`] wrote and measured (`scores.json`).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct OverlayReport {
    /// Frames.
    pub frames: usize,
    /// Frame size `(width, height)`; the masks are rendered at it.
    pub size: (usize, usize),
    /// How the camera's intrinsics were scaled to the frames (x, y).
    pub intrinsics_scale: (f64, f64),
    /// Mean IoU over frames, when a truth mask is given.
    pub mean_iou: Option<f64>,
    /// Truth points within the tolerance, of all.
    pub points_inside: usize,
    /// Truth points given.
    pub points: usize,
    /// The tolerance used (pixels).
    pub point_tolerance_px: f64,
    /// Per frame.
    pub per_frame: Vec<FrameScore>,
    /// Per truth point.
    pub per_point: Vec<PointScore>,
}

/// Intersection over union of two binary masks (1.0 when both are empty).
pub(crate) fn iou(a: &[u16], b: &[u8]) -> f64 {
    let (mut inter, mut union) = (0usize, 0usize);
    for (&x, &y) in a.iter().zip(b) {
        let (x, y) = (x != 0, y != 0);
        inter += usize::from(x && y);
        union += usize::from(x || y);
    }
    if union == 0 {
        1.0
    } else {
        inter as f64 / union as f64
    }
}

/// Distance from `(u, v)` to the centre of the nearest non-zero pixel.
fn distance_to_mask(labels: &[u16], w: usize, (u, v): (f64, f64)) -> Option<f64> {
    labels
        .iter()
        .enumerate()
        .filter(|(_, &l)| l != 0)
        .map(|(i, _)| {
            let (x, y) = ((i % w) as f64, (i / w) as f64);
            ((x - u).powi(2) + (y - v).powi(2)).sqrt()
        })
        .min_by(f64::total_cmp)
}

/// Renders `joints` of `robot` through `camera` at the real frames' size,
/// draws the outlines over them and scores them against the truth given.
/// Writes into `out` (a folder the caller owns, e.g. an
/// [`bridgev2w_io::output::OutputDir`]): `overlay/NNNNNN.png`,
/// `overlay.gif`, `labels.npy` (uint16 `[T, H, W]`) and `scores.json`.
pub fn overlay(
    robot: &Robot,
    camera: &CameraTrack,
    joints: &[Vec<f64>],
    options: &OverlayOptions,
    out: &Path,
    on_frame: &(dyn Fn() + Sync),
) -> Result<OverlayReport, OverlayError> {
    let (w, h, mut frames) = options.frames.read()?;
    if frames.len() != joints.len() {
        return Err(OverlayError::Mismatch(format!(
            "{} real frames but {} joint/action frames: expected one configuration per frame",
            frames.len(),
            joints.len()
        )));
    }
    let k = &camera.intrinsics;
    let scale = (
        w as f64 / f64::from(k.width),
        h as f64 / f64::from(k.height),
    );
    let track = camera.rescaled(w as u32, h as u32);
    track.intrinsics.validate().map_err(|e| {
        OverlayError::Mismatch(format!("the camera at the frames' size {w}x{h}: {e}"))
    })?;
    track
        .check(robot, joints.len(), "--camera")
        .map_err(|e| OverlayError::Mismatch(e.to_string()))?;
    let labels = render_track_labels(robot, &track, joints, on_frame);

    let truth_masks = match &options.truth_masks {
        None => None,
        Some(p) => {
            let a = read_npy(p)?;
            if a.shape != [frames.len(), h, w] {
                return Err(file_err(
                    p,
                    format!(
                        "shape {:?}: expected [{}, {h}, {w}] (one mask per real frame)",
                        a.shape,
                        frames.len()
                    ),
                ));
            }
            Some(a.binary_mask().map_err(|m| file_err(p, m))?)
        }
    };
    let points: Vec<TruthPoint> = match &options.truth_points {
        None => Vec::new(),
        Some(p) => {
            let text = std::fs::read_to_string(p).map_err(|e| file_err(p, e.to_string()))?;
            let pts: Vec<TruthPoint> = serde_json::from_str(&text).map_err(|e| {
                file_err(
                    p,
                    format!("{e}: expected a JSON list of {{\"frame\", \"u\", \"v\"[, \"name\"]}}"),
                )
            })?;
            if let Some((i, q)) = pts
                .iter()
                .enumerate()
                .find(|(_, q)| q.frame >= frames.len() || !(q.u.is_finite() && q.v.is_finite()))
            {
                return Err(file_err(
                    p,
                    format!(
                        "[{i}]: frame {} at ({}, {}): expected a frame below {} and finite pixel coordinates",
                        q.frame,
                        q.u,
                        q.v,
                        frames.len()
                    ),
                ));
            }
            pts
        }
    };

    let n = w * h;
    let mut per_frame = Vec::with_capacity(frames.len());
    for (t, l) in labels.iter().enumerate() {
        per_frame.push(FrameScore {
            frame: t,
            robot_pixels: l.iter().filter(|&&x| x != 0).count(),
            iou: truth_masks.as_ref().map(|m| iou(l, &m[t * n..(t + 1) * n])),
        });
    }
    let per_point: Vec<PointScore> = points
        .into_iter()
        .map(|point| {
            let d = distance_to_mask(&labels[point.frame], w, (point.u, point.v));
            PointScore {
                inside: d.is_some_and(|d| d <= options.point_tolerance_px),
                distance_px: d,
                point,
            }
        })
        .collect();

    let dir = out.join("overlay");
    std::fs::create_dir_all(&dir).map_err(|e| file_err(&dir, e.to_string()))?;
    for (t, (rgb, l)) in frames.iter_mut().zip(&labels).enumerate() {
        draw_outlines(rgb, l, w, h, options.tint);
        // Truth points as small white crosses.
        for p in per_point.iter().filter(|p| p.point.frame == t) {
            let (cu, cv) = (p.point.u.round() as i64, p.point.v.round() as i64);
            for d in -3i64..=3 {
                for (x, y) in [(cu + d, cv), (cu, cv + d)] {
                    if (0..w as i64).contains(&x) && (0..h as i64).contains(&y) {
                        let i = (y as usize * w + x as usize) * 3;
                        rgb[i..i + 3].copy_from_slice(&[255, 255, 255]);
                    }
                }
            }
        }
        let p = dir.join(format!("{t:06}.png"));
        bridgev2w_io::atomic::write_atomic(
            &p,
            &bridgev2w_io::png::encode_rgb8(w as u32, h as u32, rgb),
        )
        .map_err(|e| file_err(&p, e.to_string()))?;
    }
    write_gif(
        &out.join("overlay.gif"),
        w as u32,
        h as u32,
        &frames,
        options.fps,
    )?;
    let flat: Vec<u16> = labels.concat();
    write_npy(&out.join("labels.npy"), &[labels.len(), h, w], &flat)?;
    let ious: Vec<f64> = per_frame.iter().filter_map(|f| f.iou).collect();
    let report = OverlayReport {
        frames: frames.len(),
        size: (w, h),
        intrinsics_scale: scale,
        mean_iou: (!ious.is_empty()).then(|| ious.iter().sum::<f64>() / ious.len() as f64),
        points_inside: per_point.iter().filter(|p| p.inside).count(),
        points: per_point.len(),
        point_tolerance_px: options.point_tolerance_px,
        per_frame,
        per_point,
    };
    let p = out.join("scores.json");
    let text = serde_json::to_string_pretty(&report).map_err(|e| file_err(&p, e.to_string()))?;
    bridgev2w_io::atomic::write_atomic(&p, text.as_bytes())
        .map_err(|e| file_err(&p, e.to_string()))?;
    Ok(report)
}

/// An overlay from files, as `bridgev2w overlay` makes it: the camera
/// (optionally with per-frame poses), a trajectory, the real frames and
/// any truth, written as a transaction into `out`.
#[derive(Debug, Clone)]
pub struct OverlayJob {
    /// The camera JSON.
    pub camera: PathBuf,
    /// A moving camera's `world_from_camera` per frame (`.npy [T, 4, 4]`).
    pub camera_poses: Option<PathBuf>,
    /// The trajectory (joints, or actions through IK).
    pub trajectory: TrajectoryFile,
    /// Render frames whose IK target is out of reach instead of failing.
    pub allow_ik_residual: bool,
    /// The real frames as the user named them: an `.mp4`, a `.png` or a
    /// folder of PNGs ([`FrameSource::from_path`]); an output overlapping
    /// this path is refused.
    pub frames: PathBuf,
    /// The truth and drawing (its `frames` are replaced by those of `frames`).
    pub options: OverlayOptions,
    /// The output folder.
    pub out: PathBuf,
    /// Replace an existing `out`.
    pub overwrite: bool,
    /// Further inputs `out` must not overlap (e.g. the URDF).
    pub other_inputs: Vec<PathBuf>,
}

impl OverlayJob {
    fn inputs(&self) -> Vec<&Path> {
        let mut inputs: Vec<&Path> = self.other_inputs.iter().map(PathBuf::as_path).collect();
        inputs.push(&self.camera);
        inputs.push(self.trajectory.path());
        inputs.extend(self.camera_poses.as_deref());
        inputs.extend(self.options.truth_masks.as_deref());
        inputs.extend(self.options.truth_points.as_deref());
        inputs.push(&self.frames);
        inputs
    }

    /// Reads and checks the inputs, renders, draws, scores and commits the
    /// folder. `on_frames(n)` is called once the trajectory is known,
    /// `on_frame` per rendered frame.
    pub fn run(
        &self,
        e: &Embodiment,
        on_frames: &dyn Fn(usize),
        on_frame: &(dyn Fn() + Sync),
    ) -> Result<OverlayReport, OverlayError> {
        let tolerance = self.options.point_tolerance_px;
        if !(tolerance.is_finite() && tolerance >= 0.0) {
            return Err(OverlayError::Mismatch(format!(
                "point tolerance {tolerance} px: expected a distance >= 0 (pixels)"
            )));
        }
        let mut camera = CameraTrack::from_json_file(&self.camera)
            .map_err(|e| OverlayError::Inputs(e.into()))?;
        if let Some(p) = &self.camera_poses {
            camera =
                camera.with_poses(read_poses_npy(p).map_err(|e| OverlayError::Inputs(e.into()))?);
        }
        let (joints, _) = read_joint_trajectory(
            e,
            &self.trajectory,
            &IkOptions::default(),
            self.allow_ik_residual,
            &|_| {},
        )?;
        let options = OverlayOptions {
            frames: FrameSource::from_path(&self.frames)?,
            ..self.options.clone()
        };
        let out = OutputDir::create_for(&self.out, self.overwrite, &self.inputs())?;
        on_frames(joints.len());
        let report = overlay(&e.robot, &camera, &joints, &options, out.path(), on_frame)?;
        out.commit()?;
        Ok(report)
    }
}
