//! Hand-marked image positions of the robot's tool point in a few frames.
//!
//! A foreground found from motion holds shadows, moved objects and
//! exposure changes, and misses robot parts the colour of the background:
//! on real video its IoU with a correct camera's masks can be as low as a
//! wrong camera's (DROID, `docs/guide/calibrate.md`). A handful of marks,
//! the tool point's pixel in frames where it is visible, measure a
//! calibration independently of that foreground: the reprojection error in
//! pixels. On fitted episodes they also start the search (the camera that
//! projects the tool point onto the marks, found from every coarse-grid
//! pose) and pull the fit ([`MARKS_WEIGHT`]).
//!
//! The file (JSON):
//!
//! ```json
//! {
//!   "link": "robotiq_tcp",
//!   "videos": [
//!     {"video": "droid_new_setup/videos/val/0002/0.mp4",
//!      "marks": [[0, 208.0, 72.0], [10, 193.0, 93.0]]}
//!   ]
//! }
//! ```
//!
//! `link` (optional) is the marked point, a link's origin; the default is
//! the first end effector's link (a built-in robot's TCP: for
//! `franka-robotiq` the point between the fingertips). `video` names a
//! `--video` or `--check-video` by its last path components. Each mark is
//! `[frame, u, v]`: frame index, pixel column and row at the video's own
//! size, (0, 0) the centre of the top-left pixel (OpenCV's convention).

use super::CalibrateError;
use bridgev2w_embodiment::camera::Camera;
use nalgebra::{Point2, Point3};
use serde::{Deserialize, Serialize};
use std::path::{Component, Path, PathBuf};

/// Weight of the marks term in the objective: the RMS reprojection error
/// over the image width, times this (a 5-pixel RMS at 320 wide adds
/// 0.031, about the depth of the silhouette objective's flat valleys on
/// real DROID video).
pub(crate) const MARKS_WEIGHT: f64 = 2.0;

/// Fewest marks on the fitted episodes that start the search (a pose has
/// six degrees of freedom, two per mark).
pub const MIN_MARKS_TO_START: usize = 4;

/// One marked frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Mark {
    /// Frame index in the video.
    pub frame: usize,
    /// Pixel column at the video's own size.
    pub u: f64,
    /// Pixel row at the video's own size.
    pub v: f64,
}

/// The marks of one video.
#[derive(Debug, Clone, PartialEq)]
pub struct MarkedVideo {
    /// The video's last path components, as written in the file.
    pub video: String,
    /// Its marks.
    pub marks: Vec<Mark>,
}

/// A marks file.
#[derive(Debug, Clone, PartialEq)]
pub struct Marks {
    /// Where it was read from.
    pub path: PathBuf,
    /// The marked link (`None`: the first end effector's link).
    pub link: Option<String>,
    /// The marked videos.
    pub videos: Vec<MarkedVideo>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FileVideo {
    video: String,
    marks: Vec<[f64; 3]>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    #[serde(default)]
    link: Option<String>,
    videos: Vec<FileVideo>,
}

fn components(p: &Path) -> Vec<String> {
    p.components()
        .filter_map(|c| match c {
            Component::Normal(s) => Some(s.to_string_lossy().into_owned()),
            _ => None,
        })
        .collect()
}

impl Marks {
    /// Reads and checks a marks file (see the module documentation).
    pub fn read(path: &Path) -> Result<Self, CalibrateError> {
        let bad = |message: String| CalibrateError::Marks {
            path: path.to_path_buf(),
            message,
        };
        let file: File = bridgev2w_io::json::read_json(path).map_err(|e| bad(format!("{e:#}")))?;
        if file.videos.is_empty() {
            return Err(bad(
                "\"videos\" is empty: expected at least one marked video".into(),
            ));
        }
        let mut videos = Vec::new();
        for (i, v) in file.videos.iter().enumerate() {
            if components(Path::new(&v.video)).is_empty() {
                return Err(bad(format!(
                    "videos[{i}].video = {:?}: expected the video's path or its last components",
                    v.video
                )));
            }
            let mut marks: Vec<Mark> = Vec::new();
            for (j, &[frame, u, v_px]) in v.marks.iter().enumerate() {
                let at = format!("videos[{i}].marks[{j}] = [{frame}, {u}, {v_px}]");
                if !(frame.is_finite() && frame >= 0.0 && frame.fract() == 0.0) {
                    return Err(bad(format!("{at}: the frame must be a whole number >= 0")));
                }
                if !(u.is_finite() && v_px.is_finite()) {
                    return Err(bad(format!("{at}: the pixel must be finite")));
                }
                let frame = frame as usize;
                if marks.iter().any(|m| m.frame == frame) {
                    return Err(bad(format!("{at}: frame {frame} is marked twice")));
                }
                marks.push(Mark { frame, u, v: v_px });
            }
            if marks.is_empty() {
                return Err(bad(format!("videos[{i}] ({}) has no marks", v.video)));
            }
            videos.push(MarkedVideo {
                video: v.video.clone(),
                marks,
            });
        }
        Ok(Self {
            path: path.to_path_buf(),
            link: file.link,
            videos,
        })
    }

    /// The marks of `video` (matched by the file's last path components).
    pub fn for_video(&self, video: &Path) -> Option<&MarkedVideo> {
        let have = components(video);
        self.videos.iter().find(|m| {
            let want = components(Path::new(&m.video));
            have.ends_with(&want)
        })
    }

    /// Refuses a marks file none of whose videos is one of `videos` (a
    /// typo would otherwise leave a calibration silently unchecked); one
    /// file may mark more videos than a calibration uses (several cameras
    /// of a dataset).
    pub fn check_some_used(&self, videos: &[&Path]) -> Result<(), CalibrateError> {
        if videos.iter().any(|v| self.for_video(v).is_some()) {
            return Ok(());
        }
        let given: Vec<String> = videos.iter().map(|v| v.display().to_string()).collect();
        let marked: Vec<&str> = self.videos.iter().map(|m| m.video.as_str()).collect();
        Err(CalibrateError::Marks {
            path: self.path.clone(),
            message: format!(
                "none of its videos ({}) is one of the episodes given ({}): expected the last components of a --video or --check-video path",
                marked.join(", "),
                given.join(", ")
            ),
        })
    }
}

/// A mark ready to score: the marked point's world position at its frame
/// and its pixel on the analysis grid.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct PlacedMark {
    pub world: Point3<f64>,
    pub pixel: Point2<f64>,
}

/// The marks' pixels moved from the video's size to an analysis grid
/// reduced by `factor` (pixel centres kept).
pub(crate) fn to_analysis(u: f64, v: f64, factor: f64) -> Point2<f64> {
    Point2::new((u + 0.5) / factor - 0.5, (v + 0.5) / factor - 0.5)
}

/// Each mark's reprojection error through `camera` (analysis-grid
/// pixels); a point behind the camera counts as the image width.
pub(crate) fn errors_px(marks: &[PlacedMark], camera: &Camera) -> Vec<f64> {
    let w = f64::from(camera.intrinsics.width);
    marks
        .iter()
        .map(|m| {
            camera
                .project(&m.world)
                .map_or(w, |p| (p - m.pixel).norm().min(w))
        })
        .collect()
}

/// RMS of [`errors_px`] (`None` without marks).
pub(crate) fn rms_px(marks: &[PlacedMark], camera: &Camera) -> Option<f64> {
    let e = errors_px(marks, camera);
    (!e.is_empty()).then(|| (e.iter().map(|x| x * x).sum::<f64>() / e.len() as f64).sqrt())
}

/// How well a calibration reprojects one episode's marks (the video's own
/// pixels).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct MarksResidual {
    /// Marks scored.
    pub marks: usize,
    /// Median reprojection error (pixels).
    pub median_px: f64,
    /// Largest reprojection error (pixels).
    pub max_px: f64,
}

/// The residual of `marks` through the analysis-grid `camera`, in the
/// video's pixels (`factor` = video / analysis grid).
pub(crate) fn residual(
    marks: &[PlacedMark],
    camera: &Camera,
    factor: f64,
) -> Option<MarksResidual> {
    let mut e: Vec<f64> = errors_px(marks, camera)
        .iter()
        .map(|x| x * factor)
        .collect();
    if e.is_empty() {
        return None;
    }
    e.sort_by(f64::total_cmp);
    let n = e.len();
    let median_px = if n % 2 == 1 {
        e[n / 2]
    } else {
        (e[n / 2 - 1] + e[n / 2]) / 2.0
    };
    Some(MarksResidual {
        marks: n,
        median_px,
        max_px: e[n - 1],
    })
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;
    use bridgev2w_embodiment::camera::Intrinsics;

    fn write(dir: &Path, text: &str) -> PathBuf {
        let p = dir.join("marks.json");
        std::fs::write(&p, text).unwrap();
        p
    }

    #[test]
    fn reads_marks_and_matches_videos_by_their_last_components() {
        let dir = tempfile::tempdir().unwrap();
        let p = write(
            dir.path(),
            r#"{"videos": [{"video": "val/0002/0.mp4", "marks": [[0, 208, 72], [10, 193.5, 93]]}]}"#,
        );
        let m = Marks::read(&p).unwrap();
        assert_eq!(m.link, None);
        assert_eq!(
            m.videos[0].marks[1],
            Mark {
                frame: 10,
                u: 193.5,
                v: 93.0
            }
        );
        assert!(m
            .for_video(Path::new("/data/droid/videos/val/0002/0.mp4"))
            .is_some());
        assert!(m
            .for_video(Path::new("/data/droid/videos/val/0002/1.mp4"))
            .is_none());
        assert!(m
            .for_video(Path::new("/data/droid/videos/train/0002/0.mp4"))
            .is_none());
        m.check_some_used(&[Path::new("x/val/0002/0.mp4"), Path::new("x/val/0003/0.mp4")])
            .unwrap();
        let e = m
            .check_some_used(&[Path::new("x/val/0003/0.mp4")])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("val/0002/0.mp4") && e.contains("x/val/0003/0.mp4"),
            "{e}"
        );
    }

    #[test]
    fn bad_marks_are_refused_by_name() {
        let dir = tempfile::tempdir().unwrap();
        for (text, expect) in [
            (r#"{"videos": []}"#, "\"videos\" is empty"),
            (
                r#"{"videos": [{"video": "a.mp4", "marks": []}]}"#,
                "has no marks",
            ),
            (
                r#"{"videos": [{"video": "a.mp4", "marks": [[1.5, 2, 3]]}]}"#,
                "videos[0].marks[0] = [1.5, 2, 3]: the frame must be a whole number",
            ),
            (
                r#"{"videos": [{"video": "a.mp4", "marks": [[-1, 2, 3]]}]}"#,
                "whole number >= 0",
            ),
            (
                r#"{"videos": [{"video": "a.mp4", "marks": [[1, 2, 3], [1, 4, 5]]}]}"#,
                "frame 1 is marked twice",
            ),
            (
                r#"{"videos": [{"video": "", "marks": [[1, 2, 3]]}]}"#,
                "videos[0].video = \"\"",
            ),
            (
                r#"{"videos": [{"video": "a.mp4", "marks": [[1, 2]]}]}"#,
                "marks.json",
            ),
            (
                r#"{"videos": [{"video": "a.mp4", "marks": [[1, 2, 3]]}], "point": 1}"#,
                "unknown field",
            ),
        ] {
            let p = write(dir.path(), text);
            let e = Marks::read(&p).unwrap_err().to_string();
            assert!(
                e.contains(expect) && e.contains("marks.json"),
                "{text}: {e}"
            );
        }
    }

    #[test]
    fn reprojection_errors_are_measured_in_the_videos_pixels() {
        let k = Intrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 79.5,
            cy: 47.5,
            width: 160,
            height: 96,
            distortion: None,
        };
        let camera = Camera::look_at(
            k,
            Point3::new(1.0, 0.0, 0.5),
            Point3::new(0.0, 0.0, 0.5),
            nalgebra::Vector3::z(),
        )
        .unwrap();
        let world = Point3::new(0.0, 0.1, 0.6);
        let exact = camera.project(&world).unwrap();
        let marks = [
            PlacedMark {
                world,
                pixel: exact,
            },
            PlacedMark {
                world,
                pixel: exact + nalgebra::Vector2::new(3.0, 4.0),
            },
            PlacedMark {
                world: Point3::new(2.0, 0.0, 0.5),
                pixel: exact,
            },
        ];
        let e = errors_px(&marks, &camera);
        assert!(e[0] < 1e-9 && (e[1] - 5.0).abs() < 1e-9, "{e:?}");
        assert_eq!(e[2], 160.0, "behind the camera: the image width");
        let r = residual(&marks[..2], &camera, 2.0).unwrap();
        assert_eq!(r.marks, 2);
        assert!(
            (r.median_px - 5.0).abs() < 1e-9 && (r.max_px - 10.0).abs() < 1e-9,
            "{r:?}"
        );
        let a = to_analysis(3.0, 1.0, 2.0);
        assert!((a.x - 1.25).abs() < 1e-12 && (a.y - 0.25).abs() < 1e-12);
    }
}
