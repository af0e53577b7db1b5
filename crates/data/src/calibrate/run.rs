//! One calibration from files to an output folder, as `bridgev2w calibrate`
//! and the Python package's `bw.calibrate` both run it: the episodes read,
//! the camera found on the fitted ones, checked on the others, and
//! `camera.json`, `residuals.json` and the overlay GIFs written into a
//! temporary folder renamed into place (nothing is left behind when it
//! fails; an existing output is replaced only when asked, never one that
//! is, contains or lies inside an input).

use super::report::write_outputs;
use super::{
    calibrate, check, load_episode, marks_flags, CalibrateError, CalibrateOptions, Calibration,
};
use super::{EpisodeData, EpisodeInput, EpisodeResidual};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_io::output::OutputDir;
use std::path::{Path, PathBuf};

/// What [`calibrate_to_folder`] found and wrote.
#[derive(Debug, Clone)]
pub struct CalibrationRun {
    /// The camera, its fit and held-out residuals, and its flags.
    pub calibration: Calibration,
    /// The residuals on the checked episodes (not fitted).
    pub checks: Vec<EpisodeResidual>,
    /// The output folder.
    pub out: PathBuf,
}

impl CalibrationRun {
    /// A summary for the terminal: the camera, each episode's held-out IoU,
    /// the flags and what was written.
    pub fn summary(&self) -> String {
        let c = &self.calibration;
        let t = c.camera.world_from_camera.translation.vector;
        let k = &c.camera.intrinsics;
        let mut text = format!(
            "camera {}x{}: fx {:.1} fy {:.1} cx {:.1} cy {:.1}, position ({:.3}, {:.3}, {:.3}) m; held-out IoU {:.3}, fit IoU {:.3} ({} evaluations, {:.0} s)\n",
            k.width, k.height, k.fx, k.fy, k.cx, k.cy, t.x, t.y, t.z, c.held_out_iou, c.fit_iou, c.evaluations, c.seconds
        );
        for r in c.episodes.iter().chain(&self.checks) {
            let kind = if r.fit_frames > 0 {
                "fitted"
            } else {
                "checked"
            };
            let marks = r.marks.as_ref().map_or(String::new(), |m| {
                format!(
                    "; hand marks {:.1} px median, {:.1} max ({} marks)",
                    m.median_px, m.max_px, m.marks
                )
            });
            text.push_str(&format!(
                "  {kind} {}: held-out IoU {:.3} over {} frames{marks}\n",
                r.name, r.held_out_iou, r.held_out_frames
            ));
        }
        for f in &c.flags {
            text.push_str(&format!("warning: {}\n", f.message));
        }
        text.push_str(&format!(
            "wrote {}/camera.json, residuals.json, overlay/\n",
            self.out.display()
        ));
        text
    }
}

/// Calibrates the camera of the `fitted` episodes, checks it on `checked`
/// and writes the outputs to `out` (see the module documentation).
/// `other_inputs` (a URDF, a guess file) are refused as outputs too.
/// `progress` sees each stage's name.
#[allow(clippy::too_many_arguments)]
pub fn calibrate_to_folder(
    embodiment: &Embodiment,
    fitted: &[EpisodeInput],
    checked: &[EpisodeInput],
    options: &CalibrateOptions,
    out: &Path,
    overwrite: bool,
    other_inputs: &[&Path],
    progress: &(dyn Fn(&str) + Sync),
) -> Result<CalibrationRun, CalibrateError> {
    options.validate()?;
    if fitted.is_empty() {
        return Err(CalibrateError::Option {
            field: "--video",
            value: "none".into(),
            expected: "at least one episode to fit".into(),
        });
    }
    let mut inputs: Vec<&Path> = other_inputs.to_vec();
    for i in fitted.iter().chain(checked) {
        inputs.extend([i.video.as_path(), i.joints.as_path()]);
    }
    let output_err = |e: bridgev2w_io::output::OutputError| CalibrateError::Output {
        path: out.to_path_buf(),
        message: e.to_string(),
    };
    let dir = OutputDir::create_for(out, overwrite, &inputs).map_err(output_err)?;
    let load = |list: &[EpisodeInput]| {
        list.iter()
            .map(|i| load_episode(i, embodiment, options.analysis_width))
            .collect::<Result<Vec<_>, _>>()
    };
    if let Some(m) = &options.marks {
        let videos: Vec<&Path> = fitted
            .iter()
            .chain(checked)
            .map(|i| i.video.as_path())
            .collect();
        m.check_some_used(&videos)?;
    }
    let attach = |list: &[EpisodeInput], mut episodes: Vec<EpisodeData>| {
        if let Some(m) = &options.marks {
            for (i, e) in list.iter().zip(&mut episodes) {
                if let Some(v) = m.for_video(&i.video) {
                    e.marks = v.marks.clone();
                }
            }
        }
        episodes
    };
    let episodes = attach(fitted, load(fitted)?);
    let check_episodes = attach(checked, load(checked)?);
    let mut calibration = calibrate(embodiment, &episodes, options, progress)?;
    let checks = if check_episodes.is_empty() {
        Vec::new()
    } else {
        check(embodiment, &calibration.camera, &check_episodes, options)?
    };
    let check_flags = marks_flags(&checks, calibration.camera.intrinsics.width, options);
    if !check_flags.is_empty() {
        calibration.reliable = false;
        calibration.flags.extend(check_flags);
    }
    write_outputs(
        dir.path(),
        &embodiment.robot,
        &calibration,
        &episodes,
        &check_episodes,
        &checks,
        options,
    )?;
    let out = dir.commit().map_err(output_err)?;
    Ok(CalibrationRun {
        calibration,
        checks,
        out,
    })
}
