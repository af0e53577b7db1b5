//! `calibrate`: a fixed camera from the robot's own motion, as `bridgev2w
//! calibrate` does it (the library's `calibrate_to_folder`), with the GIL
//! released.

use super::*;
use bridgev2w_data::calibrate::marks::Marks;
use bridgev2w_data::calibrate::run::calibrate_to_folder;
use bridgev2w_data::calibrate::{
    pair_inputs, CalibrateError, CalibrateOptions, ForegroundOptions, StaticChanges,
};

/// Calibrates the camera of the `videos` (MP4, one per episode) from the
/// robot's joints (`joints`, one file per video: a trajectory file or a
/// DROID annotation JSON), checks it on `check_videos`/`check_joints`, and
/// writes `camera.json`, `residuals.json` and overlay GIFs to `out`.
/// `focal_px`: a known fx at the video's size (only the pose is fitted).
/// Returns a dict: `out`, `camera` (a `Camera`), `held_out_iou`, `fit_iou`,
/// `reliable`, `flags` (`(code, message)` pairs), `episodes` (per fitted
/// and checked episode: `(name, held_out_iou, held_out_frames, fitted)`),
/// `marks` (per episode with hand marks: `(name, median_px, max_px,
/// marks)`), `summary` (the CLI's text).
#[pyfunction]
#[pyo3(signature = (robot, videos, joints, out, check_videos, check_joints, focal_px, fy_over_fx, analysis_width, max_evaluations, walk_evaluations, marks, static_changes, background_weight, appearance_weight, overwrite))]
#[allow(clippy::too_many_arguments)]
pub(crate) fn calibrate<'py>(
    py: Python<'py>,
    robot: &Robot,
    videos: Vec<PathBuf>,
    joints: Vec<PathBuf>,
    out: PathBuf,
    check_videos: Vec<PathBuf>,
    check_joints: Vec<PathBuf>,
    focal_px: Option<f64>,
    fy_over_fx: f64,
    analysis_width: u32,
    max_evaluations: usize,
    walk_evaluations: usize,
    marks: Option<PathBuf>,
    static_changes: &str,
    background_weight: f64,
    appearance_weight: f64,
    overwrite: bool,
) -> PyResult<Bound<'py, PyDict>> {
    let static_changes: StaticChanges = static_changes
        .parse()
        .map_err(|e: String| PyValueError::new_err(format!("static_changes: {e}")))?;
    let value_err = |e: CalibrateError| match e {
        CalibrateError::Option { .. } => PyValueError::new_err(e.to_string()),
        e => err(e),
    };
    let fitted = pair_inputs(&videos, &joints, ("videos", "joints")).map_err(value_err)?;
    let checked = pair_inputs(
        &check_videos,
        &check_joints,
        ("check_videos", "check_joints"),
    )
    .map_err(value_err)?;
    for i in fitted.iter().chain(&checked) {
        for p in [&i.video, &i.joints] {
            if !p.is_file() {
                return Err(PyFileNotFoundError::new_err(format!(
                    "{}: no such file",
                    p.display()
                )));
            }
        }
    }
    if let Some(p) = marks.as_ref().filter(|p| !p.is_file()) {
        return Err(PyFileNotFoundError::new_err(format!(
            "{}: no such file",
            p.display()
        )));
    }
    let marks = marks
        .as_deref()
        .map(Marks::read)
        .transpose()
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    let options = CalibrateOptions {
        focal_px,
        fy_over_fx,
        max_evaluations,
        walk_evaluations,
        background_weight,
        appearance_weight,
        marks,
        foreground: ForegroundOptions {
            static_changes,
            ..ForegroundOptions::default()
        },
        ..CalibrateOptions::default()
    }
    .with_analysis_width(analysis_width);
    options.validate().map_err(value_err)?;
    let embodiment = &robot.inner;
    let run = py
        .detach(|| {
            no_panic("calibrate", || {
                Ok(calibrate_to_folder(
                    embodiment,
                    &fitted,
                    &checked,
                    &options,
                    &out,
                    overwrite,
                    &[],
                    &|_| {},
                ))
            })
        })?
        .map_err(value_err)?;
    let c = &run.calibration;
    let d = PyDict::new(py);
    d.set_item("out", run.out.to_string_lossy().into_owned())?;
    d.set_item(
        "camera",
        Bound::new(
            py,
            Camera {
                inner: (&c.camera).into(),
            },
        )?,
    )?;
    d.set_item("held_out_iou", c.held_out_iou)?;
    d.set_item("fit_iou", c.fit_iou)?;
    d.set_item("reliable", c.reliable)?;
    let flags: Vec<(String, String)> = c
        .flags
        .iter()
        .map(|f| (f.code.to_string(), f.message.clone()))
        .collect();
    d.set_item("flags", flags)?;
    let episodes: Vec<(String, f64, usize, bool)> = c
        .episodes
        .iter()
        .chain(&run.checks)
        .map(|r| {
            (
                r.name.clone(),
                r.held_out_iou,
                r.held_out_frames,
                r.fit_frames > 0,
            )
        })
        .collect();
    d.set_item("episodes", episodes)?;
    let marks: Vec<(String, f64, f64, usize)> = c
        .episodes
        .iter()
        .chain(&run.checks)
        .filter_map(|r| {
            let m = r.marks.as_ref()?;
            Some((r.name.clone(), m.median_px, m.max_px, m.marks))
        })
        .collect();
    d.set_item("marks", marks)?;
    d.set_item("summary", run.summary())?;
    Ok(d)
}
