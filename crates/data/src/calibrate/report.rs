//! A calibration's files: `camera.json` (the project's camera format at the
//! video's resolution), `residuals.json` (IoU per episode, fitted and held
//! out, flags, the foreground measurements) and an overlay GIF per episode
//! (the rendered robot's link outlines, and the found foreground's outline
//! in magenta, over the video).

use super::objective::{reduce_intrinsics, render_masks};
use super::{
    find_foreground, CalibrateError, CalibrateOptions, Calibration, EpisodeData, EpisodeResidual,
};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_embodiment::masks::render_frame_labels;
use bridgev2w_embodiment::overlay::{draw_outlines, write_gif};
use bridgev2w_embodiment::raster::Rasterizer;
use bridgev2w_embodiment::robot::Robot;
use serde_json::json;
use std::path::{Path, PathBuf};

/// Most frames in an overlay GIF (spread over the episode).
const MAX_GIF_FRAMES: usize = 60;

fn out_err(path: &Path, message: impl ToString) -> CalibrateError {
    CalibrateError::Output {
        path: path.to_path_buf(),
        message: message.to_string(),
    }
}

fn write_text(path: &Path, text: &str) -> Result<(), CalibrateError> {
    bridgev2w_io::atomic::write_atomic(path, text.as_bytes()).map_err(|e| out_err(path, e))
}

/// A study's output folder as a transaction: `fill` writes its files
/// (videos, a calibration folder per camera) into the temporary folder and
/// returns the table; `study.md` (`markdown` of it) and `study.json` go
/// beside them and the folder is renamed into place. An existing `out` is
/// refused unless `overwrite`, one that is, contains or is inside one of
/// `inputs` always. Returns the table and the folder.
pub(super) fn study_folder<T: serde::Serialize>(
    out: &Path,
    overwrite: bool,
    inputs: &[&Path],
    fill: impl FnOnce(&Path) -> Result<T, CalibrateError>,
    markdown: impl Fn(&T) -> String,
) -> Result<(T, PathBuf), CalibrateError> {
    let dir = bridgev2w_io::output::OutputDir::create_for(out, overwrite, inputs)
        .map_err(|e| out_err(out, e))?;
    let table = fill(dir.path())?;
    write_text(&dir.path().join("study.md"), &markdown(&table))?;
    let json = serde_json::to_string_pretty(&table).map_err(|e| out_err(out, e))?;
    write_text(&dir.path().join("study.json"), &json)?;
    let path = dir.commit().map_err(|e| out_err(out, e))?;
    Ok((table, path))
}

/// The `residuals.json` document of `calibration`, with the residuals of
/// episodes only checked (`checks`).
pub fn residuals_json(calibration: &Calibration, checks: &[EpisodeResidual]) -> serde_json::Value {
    let c = calibration;
    let k = &c.camera.intrinsics;
    let t = c.camera.world_from_camera.translation.vector;
    let check_iou = (!checks.is_empty())
        .then(|| checks.iter().map(|r| r.held_out_iou).sum::<f64>() / checks.len() as f64);
    json!({
        "reliable": c.reliable,
        "flags": c.flags,
        "held_out_iou": c.held_out_iou,
        "fit_iou": c.fit_iou,
        "checked_episodes_mean_iou": check_iou,
        "iou_is_of": "the change predicted from the rendered robot (where it appears over, or leaves, each pixel's usual background) vs the pixels found to differ from the video's temporal-median background, pooled over frames (pixels where the robot shows over itself left out)",
        "camera": {
            "fx": k.fx, "fy": k.fy, "cx": k.cx, "cy": k.cy,
            "width": k.width, "height": k.height,
            "position_m": [t.x, t.y, t.z],
        },
        "fitted": c.fitted,
        "ambiguity": c.ambiguity,
        "episodes": c.episodes,
        "checked_episodes": checks,
        "search": {
            "candidates": c.candidates,
            "evaluations": c.evaluations,
            "seconds": c.seconds,
        },
    })
}

/// The file name of an episode's overlay: `NN_<last folders of its name>.gif`.
fn gif_name(index: usize, name: &str) -> String {
    let parts: Vec<String> = Path::new(name)
        .with_extension("")
        .components()
        .rev()
        .take(2)
        .map(|c| {
            c.as_os_str()
                .to_string_lossy()
                .chars()
                .map(|ch| if ch.is_ascii_alphanumeric() { ch } else { '_' })
                .collect()
        })
        .collect();
    let tail: Vec<String> = parts.into_iter().rev().collect();
    format!("{index:02}_{}.gif", tail.join("_"))
}

/// Draws the outline of a 0/1 mask in magenta.
fn draw_mask_outline(rgb: &mut [u8], mask: &[u8], w: usize, h: usize) {
    for y in 0..h {
        for x in 0..w {
            if mask[y * w + x] == 0 {
                continue;
            }
            let edge = x == 0
                || y == 0
                || x + 1 == w
                || y + 1 == h
                || mask[y * w + x - 1] == 0
                || mask[y * w + x + 1] == 0
                || mask[(y - 1) * w + x] == 0
                || mask[(y + 1) * w + x] == 0;
            if edge {
                rgb[(y * w + x) * 3..(y * w + x) * 3 + 3].copy_from_slice(&[255, 0, 255]);
            }
        }
    }
}

/// Writes the overlay GIF of `episode` through `camera` (any image size)
/// to `path`: frames spread over the episode, rendered robot outlines by
/// link, found foreground outlined in magenta.
pub fn write_overlay(
    robot: &Robot,
    camera: &Camera,
    episode: &EpisodeData,
    options: &CalibrateOptions,
    path: &Path,
) -> Result<(), CalibrateError> {
    let (w, h) = (episode.width, episode.height);
    let (vw, vh) = episode.video_size;
    let c = camera.rescaled(vw, vh);
    let k = reduce_intrinsics(&c.intrinsics, f64::from(episode.factor), w as u32, h as u32);
    let c = Camera::new(k, c.world_from_camera)?;
    let foreground = find_foreground(episode, &options.foreground);
    let n = episode.frames.len();
    let picked: Vec<usize> = super::problem::spread(&(0..n).collect::<Vec<_>>(), MAX_GIF_FRAMES);
    let rasterizer = Rasterizer::new(&c);
    let frames: Vec<Vec<u8>> = picked
        .iter()
        .map(|&t| {
            let mut rgb = episode.frames[t].clone();
            draw_mask_outline(&mut rgb, &foreground.masks[t], w, h);
            let labels = render_frame_labels(robot, &rasterizer, &episode.joints[t]);
            draw_outlines(&mut rgb, &labels, w, h, 0.2);
            rgb
        })
        .collect();
    write_gif(path, w as u32, h as u32, &frames, 5).map_err(|e| out_err(path, e))
}

/// Writes `camera.json`, `residuals.json` and `overlay/NN_<episode>.gif`
/// (fitted episodes, then checked ones) into `dir` (a folder the caller
/// owns, e.g. an [`bridgev2w_io::output::OutputDir`]); returns the files.
pub fn write_outputs(
    dir: &Path,
    robot: &Robot,
    calibration: &Calibration,
    episodes: &[EpisodeData],
    checked: &[EpisodeData],
    checks: &[EpisodeResidual],
    options: &CalibrateOptions,
) -> Result<Vec<PathBuf>, CalibrateError> {
    let mut files = Vec::new();
    let p = dir.join("camera.json");
    write_text(&p, &calibration.camera.to_json())?;
    files.push(p);
    let p = dir.join("residuals.json");
    let text = serde_json::to_string_pretty(&residuals_json(calibration, checks))
        .map_err(|e| out_err(&p, e))?;
    write_text(&p, &text)?;
    files.push(p);
    let overlay = dir.join("overlay");
    std::fs::create_dir_all(&overlay).map_err(|e| out_err(&overlay, e))?;
    for (i, e) in episodes.iter().chain(checked).enumerate() {
        let p = overlay.join(gif_name(i, &e.name));
        write_overlay(robot, &calibration.camera, e, options, &p)?;
        files.push(p);
    }
    Ok(files)
}

/// The robot's 0/1 masks of every frame of `episode` through `camera` (any
/// image size), on the episode's analysis grid.
pub fn rendered_masks(
    robot: &Robot,
    camera: &Camera,
    episode: &EpisodeData,
) -> Result<Vec<Vec<u8>>, CalibrateError> {
    let (vw, vh) = episode.video_size;
    let c = camera.rescaled(vw, vh);
    let k = reduce_intrinsics(
        &c.intrinsics,
        f64::from(episode.factor),
        episode.width as u32,
        episode.height as u32,
    );
    let c = Camera::new(k, c.world_from_camera)?;
    let poses: Vec<_> = episode.joints.iter().map(|q| robot.link_poses(q)).collect();
    let all: Vec<usize> = (0..poses.len()).collect();
    Ok(render_masks(robot, &poses, &c, &all))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn overlay_names_keep_the_episode_folders() {
        assert_eq!(
            gif_name(3, "/d/droid_new_setup/videos/val/0007/1.mp4"),
            "03_0007_1.gif"
        );
        assert_eq!(gif_name(0, "cam.mp4"), "00_cam.gif");
    }

    #[test]
    fn a_study_folder_is_a_transaction() {
        let tmp = tempfile::tempdir().unwrap();
        let out = tmp.path().join("study");
        let md = |t: &Vec<u32>| format!("| n |\n| {} |\n", t.len());
        let fill = |dir: &Path| {
            std::fs::write(dir.join("videos.txt"), "v").unwrap();
            Ok(vec![1u32, 2])
        };
        let (table, dir) = study_folder(&out, false, &[], fill, md).unwrap();
        assert_eq!((table, dir.clone()), (vec![1, 2], out.clone()));
        assert_eq!(
            std::fs::read_to_string(out.join("study.md")).unwrap(),
            "| n |\n| 2 |\n"
        );
        assert_eq!(
            std::fs::read_to_string(out.join("study.json")).unwrap(),
            "[\n  1,\n  2\n]"
        );
        assert!(out.join("videos.txt").is_file());
        // An existing folder is refused before anything is filled.
        let e = study_folder(
            &out,
            false,
            &[],
            |_| -> Result<Vec<u32>, _> { panic!("filled") },
            md,
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("already exists"), "{e}");
        // A study that fails leaves the earlier folder as it was.
        let failing = |dir: &Path| {
            std::fs::write(dir.join("half.txt"), "h").unwrap();
            Err(CalibrateError::Output {
                path: dir.to_path_buf(),
                message: "stopped".into(),
            })
        };
        let e = study_folder::<Vec<u32>>(&out, true, &[], failing, md).unwrap_err();
        assert!(e.to_string().contains("stopped"), "{e}");
        assert!(out.join("videos.txt").is_file() && !out.join("half.txt").exists());
        // An output inside an input is refused.
        let e = study_folder(&out.join("inner"), true, &[out.as_path()], fill, md)
            .unwrap_err()
            .to_string();
        assert!(e.contains("inside the input"), "{e}");
    }
}
