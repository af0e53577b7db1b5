//! Joint trajectories to embodiment masks, and writing them to disk.
//!
//! Every link with visual geometry gets the label `link index + 1` (0 is
//! background); [`link_labels`] names them. Frames are rendered in parallel;
//! the result does not depend on the number of threads.

use crate::camera::{Camera, CameraPose, CameraTrack, MAX_IMAGE_SIDE};
use crate::raster::{Rasterizer, RenderItem, RenderOutput};
use crate::robot::Robot;
use bridgev2w_io::memory::{at_most, bytes, check_fits, MemoryError};
use bridgev2w_io::npy::{write_atomic, write_npy, NpyError};
use nalgebra::Isometry3;
use rayon::prelude::*;
use std::borrow::Cow;
use std::path::{Path, PathBuf};

/// The most frames one render takes (a trajectory's rows; a batch's in
/// all): more than nine hours at 30 frames per second. Memory is checked
/// as well ([`check_render_size`]).
pub const MAX_RENDER_FRAMES: usize = 1_000_000;

/// Bytes per pixel that rendering and writing a frame holds at the least:
/// the label map (u16) and, from it, the binary mask (u8) and the label
/// array written or returned (u16); with depth, the depth map (f32) and its
/// copy written or returned.
const RENDER_BYTES_PER_PIXEL: u64 = 2 + 1 + 2;
/// [`RENDER_BYTES_PER_PIXEL`] with depth maps.
const RENDER_DEPTH_BYTES_PER_PIXEL: u64 = RENDER_BYTES_PER_PIXEL + 4 + 4;

/// A floor of the memory that rendering `frames` frames of `width` x
/// `height` pixels holds (with depth maps if `depth`), all frames at once as
/// `bridgev2w masks` and `bw.render_masks` hold them: 5 bytes a pixel, 13
/// with depth (the label maps, masks and arrays written or returned; the
/// rasterizer's per-thread buffers and PNG encoding not counted).
pub fn render_bytes(frames: usize, width: u32, height: u32, depth: bool) -> u64 {
    let per_pixel = if depth {
        RENDER_DEPTH_BYTES_PER_PIXEL
    } else {
        RENDER_BYTES_PER_PIXEL
    };
    bytes(&[
        frames as u64,
        u64::from(width),
        u64::from(height),
        per_pixel,
    ])
}

/// Checks a render before anything is allocated: `frames` (named
/// `frames_name` in the error: the flag or argument that gave them) at most
/// [`MAX_RENDER_FRAMES`], each side at most [`MAX_IMAGE_SIDE`], and
/// [`render_bytes`] within the memory this machine has.
pub fn check_render_size(
    frames_name: &str,
    frames: usize,
    width: u32,
    height: u32,
    depth: bool,
) -> Result<(), MemoryError> {
    at_most(
        frames_name,
        frames as u64,
        MAX_RENDER_FRAMES as u64,
        "frames",
    )?;
    at_most("image width", width.into(), MAX_IMAGE_SIDE.into(), "pixels")?;
    at_most(
        "image height",
        height.into(),
        MAX_IMAGE_SIDE.into(),
        "pixels",
    )?;
    check_fits(
        &format!(
            "rendering {frames} frames of {width}x{height} pixels{}",
            if depth { " with depth" } else { "" }
        ),
        render_bytes(frames, width, height, depth),
        "render fewer frames at a time (split the trajectory) or smaller images (--width/--height, Camera.rescaled)",
    )
}

/// `(label, link name)` for every link that has geometry.
pub fn link_labels(robot: &Robot) -> Vec<(u16, String)> {
    robot
        .links
        .iter()
        .enumerate()
        .filter(|(_, l)| l.mesh.is_some())
        .map(|(i, l)| (label_of_link(i), l.name.clone()))
        .collect()
}

/// Label of link `i`.
pub fn label_of_link(i: usize) -> u16 {
    u16::try_from(i + 1).unwrap_or(u16::MAX)
}

/// The robot's link meshes placed at `world_from_link` poses (from
/// [`Robot::link_poses`]), labelled by [`label_of_link`]. With
/// `cull_closed`, closed meshes skip their back faces (exact, faster).
pub fn render_items<'a>(
    robot: &'a Robot,
    poses: &[Isometry3<f64>],
    cull_closed: bool,
) -> Vec<RenderItem<'a>> {
    robot
        .links
        .iter()
        .zip(poses)
        .enumerate()
        .filter_map(|(i, (l, pose))| {
            l.mesh.as_ref().map(|m| RenderItem {
                mesh: m,
                world_from_mesh: *pose,
                label: label_of_link(i),
                closed_triangles: if cull_closed {
                    l.mesh_closed_triangles
                } else {
                    0
                },
            })
        })
        .collect()
}

/// Renders one frame: the robot at `q` seen by the rasterizer's camera.
///
/// # Panics
/// If `q.len() != robot.dof()` (validate with [`Robot::check_q`]).
pub fn render_frame(robot: &Robot, rasterizer: &Rasterizer, q: &[f64], out: &mut RenderOutput) {
    let poses = robot.link_poses(q);
    rasterizer.render_into(&render_items(robot, &poses, true), out);
}

/// The label map (row-major, 0 = background) of the robot at `q` seen by
/// the rasterizer's camera, without depth.
///
/// # Panics
/// If `q.len() != robot.dof()`.
pub fn render_frame_labels(robot: &Robot, rasterizer: &Rasterizer, q: &[f64]) -> Vec<u16> {
    let poses = robot.link_poses(q);
    rasterizer.render_labels(&render_items(robot, &poses, true))
}

/// [`render_frame_labels`] drawn into `labels` (see
/// [`Rasterizer::render_labels_into`]: covered pixels get their link's
/// label, the others keep their value, so `labels` should be all 0).
///
/// # Panics
/// If `q.len() != robot.dof()` or `labels` is not the camera's size.
pub fn render_frame_labels_into(
    robot: &Robot,
    rasterizer: &Rasterizer,
    q: &[f64],
    labels: &mut [u16],
) {
    let poses = robot.link_poses(q);
    rasterizer.render_labels_into(&render_items(robot, &poses, true), labels);
}

/// The 0/1 robot mask (row-major) of [`render_frame_labels`].
///
/// # Panics
/// If `q.len() != robot.dof()`.
pub fn render_frame_mask(robot: &Robot, rasterizer: &Rasterizer, q: &[f64]) -> Vec<u8> {
    render_frame_labels(robot, rasterizer, q)
        .iter()
        .map(|&l| u8::from(l > 0))
        .collect()
}

/// The rasterizer of frame `t` of `track`, with the robot's link poses in
/// that frame: a fixed camera's shared rasterizer, or `base` moved to the
/// frame's pose.
fn frame_rasterizer<'a>(
    robot: &Robot,
    track: &CameraTrack,
    base: &'a Rasterizer,
    t: usize,
    poses: &[Isometry3<f64>],
) -> Cow<'a, Rasterizer> {
    match track.pose {
        CameraPose::Fixed(_) => Cow::Borrowed(base),
        _ => Cow::Owned(base.posed(&track.camera_at(robot, t, poses).world_from_camera)),
    }
}

/// The rasterizer of a track's first frame (its intrinsics, shared by all).
fn base_rasterizer(robot: &Robot, track: &CameraTrack, joints: &[Vec<f64>]) -> Rasterizer {
    let poses = joints
        .first()
        .map(|q| robot.link_poses(q))
        .unwrap_or_default();
    let camera = match (&track.pose, joints.is_empty()) {
        (CameraPose::Mounted { .. }, true) => Camera {
            intrinsics: track.intrinsics,
            world_from_camera: Isometry3::identity(),
        },
        _ => track.camera_at(robot, 0, &poses),
    };
    Rasterizer::new(&camera)
}

/// Renders every frame of a joint trajectory in parallel. `on_frame` is
/// called once per finished frame (for progress bars), from any thread.
///
/// # Panics
/// If a frame has the wrong number of joint values.
pub fn render_trajectory(
    robot: &Robot,
    camera: &Camera,
    joints: &[Vec<f64>],
    on_frame: &(dyn Fn() + Sync),
) -> Vec<RenderOutput> {
    render_track(robot, &CameraTrack::from(camera), joints, on_frame)
}

/// [`render_trajectory`] through a camera that may move: frame `t` is seen
/// by the track's camera of frame `t` (a mounted camera posed by the same
/// forward kinematics as the robot).
///
/// # Panics
/// If a frame has the wrong number of joint values, or the track does not
/// fit the trajectory (check with [`CameraTrack::check`]).
pub fn render_track(
    robot: &Robot,
    track: &CameraTrack,
    joints: &[Vec<f64>],
    on_frame: &(dyn Fn() + Sync),
) -> Vec<RenderOutput> {
    let base = base_rasterizer(robot, track, joints);
    let (w, h) = (track.intrinsics.width, track.intrinsics.height);
    joints
        .par_iter()
        .enumerate()
        .map(|(t, q)| {
            // Empty buffers: render_into sizes and clears them once.
            let mut out = RenderOutput {
                width: w,
                height: h,
                labels: Vec::new(),
                depth_m: Vec::new(),
            };
            let poses = robot.link_poses(q);
            let rasterizer = frame_rasterizer(robot, track, &base, t, &poses);
            rasterizer.render_into(&render_items(robot, &poses, true), &mut out);
            on_frame();
            out
        })
        .collect()
}

/// The label maps of [`render_trajectory`] alone (row-major, 0 =
/// background), without depth maps: faster when only masks and labels are
/// needed. `on_frame` as for [`render_trajectory`].
///
/// # Panics
/// If a frame has the wrong number of joint values.
pub fn render_trajectory_labels(
    robot: &Robot,
    camera: &Camera,
    joints: &[Vec<f64>],
    on_frame: &(dyn Fn() + Sync),
) -> Vec<Vec<u16>> {
    render_track_labels(robot, &CameraTrack::from(camera), joints, on_frame)
}

/// [`render_trajectory_labels`] through a camera that may move (see
/// [`render_track`]).
///
/// # Panics
/// As [`render_track`].
pub fn render_track_labels(
    robot: &Robot,
    track: &CameraTrack,
    joints: &[Vec<f64>],
    on_frame: &(dyn Fn() + Sync),
) -> Vec<Vec<u16>> {
    let base = base_rasterizer(robot, track, joints);
    joints
        .par_iter()
        .enumerate()
        .map(|(t, q)| {
            let poses = robot.link_poses(q);
            let rasterizer = frame_rasterizer(robot, track, &base, t, &poses);
            let labels = rasterizer.render_labels(&render_items(robot, &poses, true));
            on_frame();
            labels
        })
        .collect()
}

/// The label maps of [`render_trajectory_labels`] as one row-major array
/// `[T, H, W]` (the layout of `labels.npy`), rendered in parallel into a
/// single zeroed allocation: only pages where the robot is drawn are ever
/// written, which for a large trajectory saves most of the cost of fresh
/// memory (the operating system's page zeroing, or `calloc`'s memset).
/// Same values as [`render_trajectory_labels`], for any number of threads.
/// `on_frame` as for [`render_trajectory`].
///
/// # Panics
/// If a frame has the wrong number of joint values.
pub fn render_trajectory_label_array(
    robot: &Robot,
    camera: &Camera,
    joints: &[Vec<f64>],
    on_frame: &(dyn Fn() + Sync),
) -> Vec<u16> {
    render_track_label_array(robot, &CameraTrack::from(camera), joints, on_frame)
}

/// [`render_trajectory_label_array`] through a camera that may move (see
/// [`render_track`]).
///
/// # Panics
/// As [`render_track`].
pub fn render_track_label_array(
    robot: &Robot,
    track: &CameraTrack,
    joints: &[Vec<f64>],
    on_frame: &(dyn Fn() + Sync),
) -> Vec<u16> {
    let base = base_rasterizer(robot, track, joints);
    let n = track.intrinsics.width as usize * track.intrinsics.height as usize;
    let mut labels = vec![0u16; n * joints.len()];
    if n == 0 {
        joints.iter().for_each(|_| on_frame());
        return labels;
    }
    labels
        .par_chunks_mut(n)
        .zip(joints)
        .enumerate()
        .for_each(|(t, (frame, q))| {
            let poses = robot.link_poses(q);
            let rasterizer = frame_rasterizer(robot, track, &base, t, &poses);
            rasterizer.render_labels_into(&render_items(robot, &poses, true), frame);
            on_frame();
        });
    labels
}

/// Errors writing mask outputs.
#[derive(Debug, thiserror::Error)]
pub enum WriteError {
    /// A `.npy` write failed.
    #[error(transparent)]
    Npy(#[from] NpyError),
    /// Any other file failed.
    #[error("{path}: {message}")]
    File {
        /// The file.
        path: PathBuf,
        /// What failed.
        message: String,
    },
}

/// What [`write_outputs`] wrote.
#[derive(Debug, Clone, Default)]
pub struct WrittenFiles {
    /// Paths written, in order.
    pub files: Vec<PathBuf>,
    /// Frames whose mask is empty (the robot is not in view).
    pub empty_frames: Vec<usize>,
}

/// Options for [`write_outputs`].
#[derive(Debug, Clone, Copy)]
pub struct WriteOptions {
    /// Write `frames/000000.png`... (mask as 0/255 grayscale).
    pub pngs: bool,
    /// Write `depth.npy` (float32 metres, `inf` = background).
    pub depth: bool,
}

/// Writes `masks.npy` (uint8 `[T,H,W]`, 0/1), `labels.npy` (uint16
/// `[T,H,W]`), `labels.json` and, per options, `frames/*.png` and
/// `depth.npy` into `dir` (created if needed). Every file is written
/// atomically.
pub fn write_outputs(
    dir: &Path,
    robot: &Robot,
    frames: &[RenderOutput],
    options: WriteOptions,
) -> Result<WrittenFiles, WriteError> {
    let file_err = |path: &Path, message: String| WriteError::File {
        path: path.to_path_buf(),
        message,
    };
    std::fs::create_dir_all(dir)
        .map_err(|e| file_err(dir, format!("cannot create directory: {e}")))?;
    let (w, h) = frames
        .first()
        .map_or((0, 0), |f| (f.width as usize, f.height as usize));
    let shape = [frames.len(), h, w];
    let mut written = WrittenFiles::default();

    let masks: Vec<u8> = frames
        .iter()
        .flat_map(|f| f.labels.iter().map(|&l| u8::from(l != 0)))
        .collect();
    let p = dir.join("masks.npy");
    write_npy(&p, &shape, &masks)?;
    written.files.push(p);

    let labels: Vec<u16> = frames
        .iter()
        .flat_map(|f| f.labels.iter().copied())
        .collect();
    let p = dir.join("labels.npy");
    write_npy(&p, &shape, &labels)?;
    written.files.push(p);

    let names = serde_json::json!({
        "background": 0,
        "robot": robot.name,
        "labels": link_labels(robot)
            .into_iter()
            .map(|(label, link)| serde_json::json!({"label": label, "link": link}))
            .collect::<Vec<_>>(),
    });
    let p = dir.join("labels.json");
    let text = serde_json::to_string_pretty(&names).map_err(|e| file_err(&p, e.to_string()))?;
    write_atomic(&p, text.as_bytes()).map_err(|e| file_err(&p, e.to_string()))?;
    written.files.push(p);

    if options.depth {
        let depth: Vec<f32> = frames
            .iter()
            .flat_map(|f| f.depth_m.iter().copied())
            .collect();
        let p = dir.join("depth.npy");
        write_npy(&p, &shape, &depth)?;
        written.files.push(p);
    }

    if options.pngs {
        let fdir = dir.join("frames");
        std::fs::create_dir_all(&fdir)
            .map_err(|e| file_err(&fdir, format!("cannot create directory: {e}")))?;
        let pngs: Result<Vec<PathBuf>, WriteError> = frames
            .par_iter()
            .enumerate()
            .map(|(t, f)| {
                let p = fdir.join(format!("{t:06}.png"));
                let gray: Vec<u8> = f
                    .labels
                    .iter()
                    .map(|&l| if l != 0 { 255 } else { 0 })
                    .collect();
                let bytes = bridgev2w_io::png::encode_gray8(f.width, f.height, &gray);
                write_atomic(&p, &bytes).map_err(|e| file_err(&p, e.to_string()))?;
                Ok(p)
            })
            .collect();
        written.files.extend(pngs?);
    }
    written.empty_frames = frames
        .iter()
        .enumerate()
        .filter(|(_, f)| f.coverage() == 0)
        .map(|(t, _)| t)
        .collect();
    Ok(written)
}

/// The warning for empty masks (robot out of view), if any: every mask
/// empty points at the camera's extrinsics.
pub fn empty_masks_warning(empty: &[usize], total: usize) -> Option<String> {
    if empty.len() == total && total > 0 {
        Some("warning: every mask is empty: the robot is not in view; check the camera extrinsics (world_from_camera maps camera to robot-base coordinates; OpenCV axes: x right, y down, z forward)".into())
    } else if !empty.is_empty() {
        Some(format!(
            "warning: {} of {total} masks are empty (robot out of view), first frames: {:?}",
            empty.len(),
            &empty[..empty.len().min(10)]
        ))
    } else {
        None
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn a_render_beyond_its_bounds_or_the_machine_is_refused_before_any_allocation() {
        assert_eq!(render_bytes(10, 4, 2, false), 10 * 4 * 2 * 5);
        assert_eq!(render_bytes(10, 4, 2, true), 10 * 4 * 2 * 13);
        assert!(check_render_size("frames", 49, 720, 480, true).is_ok());
        let e = check_render_size("--joints", MAX_RENDER_FRAMES + 1, 64, 64, false).unwrap_err();
        assert!(
            e.to_string()
                .starts_with("--joints 1000001: at most 1000000 frames"),
            "{e}"
        );
        let e = check_render_size("frames", 2, 100_000, 64, false).unwrap_err();
        assert!(e.to_string().contains("image width 100000"), "{e}");
        // 10000 frames of 16384x16384: 13 TB, beyond any machine this runs on.
        let e = check_render_size("joints", 10_000, 16_384, 16_384, false).unwrap_err();
        let text = e.to_string();
        if bridgev2w_io::memory::available_bytes().is_some() {
            assert!(matches!(e, MemoryError::Exceeds { .. }), "{text}");
            assert!(
                text.contains(
                    "rendering 10000 frames of 16384x16384 pixels needs at least 12500.0 GiB"
                ),
                "{text}"
            );
            assert!(text.contains("is available"), "{text}");
        }
    }
}
