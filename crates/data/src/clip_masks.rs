//! The two mask sources of the clip pipeline (paper: "Embodiment Mask
//! Extraction" and "Training with Uncalibrated Segmentation Masks"):
//!
//! - `calc`: masks rendered from the URDF, the recorded joint positions and
//!   the camera calibration. Datasets written by `bridgev2w synth` or
//!   `bridgev2w convert` carry them (`masks/episode_XXXXXX.npy`); for other
//!   LeRobot datasets with `observation.state` joint vectors and
//!   `meta/calibration/`, [`calc_masks`] renders them and caches them on disk,
//!   keyed by video key, episode and resolution.
//! - `seg`: masks from any segmentation tool (the paper used Grounded SAM
//!   with "robotic arm"), as PNG folders `DIR/episode_XXXXXX/000000.png, ...`
//!   (non-zero = robot) — the path for uncalibrated or human videos.

use crate::lerobot::{DatasetError, LeRobotDataset};
use bridgev2w_embodiment::embodiment::Embodiment;
use bridgev2w_embodiment::masks::render_frame_mask;
use bridgev2w_embodiment::raster::Rasterizer;
use bridgev2w_io::npy::{read_npy, write_npy};
use rayon::prelude::*;
use std::path::{Path, PathBuf};

/// Masks of one episode: `[T, H, W]`, 0/1.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeMasks {
    /// Frames.
    pub frames: usize,
    /// Height.
    pub height: usize,
    /// Width.
    pub width: usize,
    /// Row-major 0/1 values.
    pub data: Vec<u8>,
}

fn field_err(path: &Path, episode: i64, field: &str, message: String) -> DatasetError {
    DatasetError::Field {
        path: path.to_path_buf(),
        episode,
        field: field.to_string(),
        message,
    }
}

/// The cache file of [`calc_masks`]: `cache/<video_key>/episode_XXXXXX_<W>x<H>.npy`
/// (`/` and `\\` in the key as `_`). The key names a folder under `cache`:
/// one that is not then a plain name (`..`, empty, NUL) is refused, naming
/// the cache and the key.
pub fn calc_cache_path(
    cache: &Path,
    video_key: &str,
    episode: i64,
    (w, h): (usize, usize),
) -> Result<PathBuf, DatasetError> {
    let folder = video_key.replace(['/', '\\'], "_");
    bridgev2w_io::confine::check_name(&folder).map_err(|e| {
        field_err(
            cache,
            episode,
            "video_key",
            format!("video key {video_key:?} as the mask cache's folder: {e}"),
        )
    })?;
    Ok(cache
        .join(folder)
        .join(format!("episode_{episode:06}_{w}x{h}.npy")))
}

fn read_cached(
    path: &Path,
    episode: i64,
    (t, w, h): (usize, usize, usize),
) -> Result<Option<EpisodeMasks>, DatasetError> {
    if !path.is_file() {
        return Ok(None);
    }
    let a = read_npy(path).map_err(|e| field_err(path, episode, "masks", e.to_string()))?;
    if a.descr != "|u1" || a.shape != [t, h, w] {
        // A stale or foreign file: render again.
        return Ok(None);
    }
    Ok(Some(EpisodeMasks {
        frames: t,
        height: h,
        width: w,
        data: a.data.iter().map(|&v| u8::from(v != 0.0)).collect(),
    }))
}

/// The `calc` masks of `episode` at the video's `(width, height)` and
/// `frames`: the dataset's own `masks/episode_XXXXXX.npy` when present,
/// otherwise rendered for `embodiment` from `observation.state` (one joint
/// vector of `robot.dof()` values per frame) and the episode's calibration
/// of `video_key`, and cached under `cache` (see [`calc_cache_path`];
/// written atomically, reused when its shape matches).
pub fn calc_masks(
    ds: &LeRobotDataset,
    episode: i64,
    video_key: &str,
    (frames, width, height): (usize, usize, usize),
    embodiment: Option<&Embodiment>,
    cache: &Path,
) -> Result<EpisodeMasks, DatasetError> {
    let stored = ds.root.join(format!("masks/episode_{episode:06}.npy"));
    if let Some((shape, data)) = ds.stored_masks(episode)? {
        return Ok(EpisodeMasks {
            frames: shape[0],
            height: shape[1],
            width: shape[2],
            data,
        });
    }
    let path = calc_cache_path(cache, video_key, episode, (width, height))?;
    if let Some(m) = read_cached(&path, episode, (frames, width, height))? {
        return Ok(m);
    }
    let embodiment = embodiment.ok_or_else(|| {
        field_err(
            &stored,
            episode,
            "masks",
            "missing, and no robot was given to render calc masks from observation.state and the calibration (set data.robot, or use seg masks)".into(),
        )
    })?;
    let robot = &embodiment.robot;
    let rows = ds.read_episode(episode)?.frames;
    if rows.len() != frames {
        return Err(field_err(
            &ds.root,
            episode,
            "observation.state",
            format!("{} state rows for {frames} video frames", rows.len()),
        ));
    }
    let dof = robot.dof();
    if let Some(r) = rows.iter().find(|r| r.state.len() != dof) {
        return Err(field_err(
            &ds.root,
            episode,
            "observation.state",
            format!(
                "{} values per frame, but robot \"{}\" has {dof} actuated joints: calc masks need joint-position states",
                r.state.len(),
                robot.name
            ),
        ));
    }
    let camera = ds
        .read_calibration(episode, video_key)?
        .rescaled(width as u32, height as u32);
    let rasterizer = Rasterizer::new(&camera);
    let per_frame: Vec<Vec<u8>> = rows
        .par_iter()
        .map(|r| {
            let q: Vec<f64> = r.state.iter().map(|&v| f64::from(v)).collect();
            render_frame_mask(robot, &rasterizer, &q)
        })
        .collect();
    let data: Vec<u8> = per_frame.concat();
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(|source| DatasetError::Io {
            path: dir.to_path_buf(),
            source,
        })?;
    }
    write_npy(&path, &[frames, height, width], &data).map_err(|e| {
        field_err(
            &path,
            episode,
            "masks",
            format!("cannot write the mask cache: {e}"),
        )
    })?;
    Ok(EpisodeMasks {
        frames,
        height,
        width,
        data,
    })
}

/// The dataset's link labels of `episode` (`labels/episode_XXXXXX.npy`,
/// uint8 `[T, H, W]`, 0 = background, else the link's label, as `bridgev2w
/// synth` and `convert` write them; uint16 labels up to 255, as `bridgev2w
/// masks` writes its `labels.npy`, are read too), when it has them. They must have `masks`' shape and
/// cover exactly its robot pixels; anything else (a FIFO, a folder or a
/// link out of the dataset in its place included) is an error naming the file.
pub fn read_link_labels(
    ds: &LeRobotDataset,
    episode: i64,
    masks: &EpisodeMasks,
) -> Result<Option<Vec<u8>>, DatasetError> {
    let rel = format!("labels/episode_{episode:06}.npy");
    let Some(path) = ds.stored_file(&rel, bridgev2w_io::confine::MAX_DATA_BYTES)? else {
        return Ok(None);
    };
    let a = read_npy(&path).map_err(|e| field_err(&path, episode, "labels", e.to_string()))?;
    let shape = [masks.frames, masks.height, masks.width];
    if !matches!(a.descr.as_str(), "|u1" | "<u2" | ">u2") || a.shape != shape {
        return Err(field_err(
            &path,
            episode,
            "labels",
            format!(
                "{} {:?}: expected uint8 or uint16 link labels of the masks' shape {shape:?}",
                a.descr, a.shape
            ),
        ));
    }
    // uint16 (as `bridgev2w masks` writes labels.npy): a link-coded model
    // reads labels up to 255.
    if let Some(v) = a.data.iter().find(|&&v| v > 255.0) {
        return Err(field_err(
            &path,
            episode,
            "labels",
            format!("link label {v}: expected labels up to 255"),
        ));
    }
    let labels: Vec<u8> = a.data.iter().map(|&v| v as u8).collect();
    if let Some(i) = labels
        .iter()
        .zip(&masks.data)
        .position(|(&l, &m)| (l != 0) != (m != 0))
    {
        let px = masks.height * masks.width;
        return Err(field_err(
            &path,
            episode,
            "labels",
            format!(
                "frame {} pixel ({}, {}) (x, y): label {} but mask {}: the labels must cover exactly the masks' robot pixels",
                i / px,
                i % masks.width,
                (i % px) / masks.width,
                labels[i],
                masks.data[i]
            ),
        ));
    }
    Ok(Some(labels))
}

/// The `seg` masks of `episode`: the PNG frames of `dir/episode_XXXXXX/`
/// (sorted by name, any bit depth or colour type; non-zero = robot), which
/// must number `frames` and share one size.
pub fn seg_masks(dir: &Path, episode: i64, frames: usize) -> Result<EpisodeMasks, DatasetError> {
    let folder = dir.join(format!("episode_{episode:06}"));
    if !folder.is_dir() {
        return Err(field_err(
            &folder,
            episode,
            "seg masks",
            "missing folder of PNG masks (000000.png, ...)".into(),
        ));
    }
    let mut files: Vec<PathBuf> = std::fs::read_dir(&folder)
        .map_err(|source| DatasetError::Io {
            path: folder.clone(),
            source,
        })?
        .filter_map(Result::ok)
        .map(|e| e.path())
        .filter(|p| p.extension().is_some_and(|x| x.eq_ignore_ascii_case("png")))
        .collect();
    files.sort();
    if files.len() != frames {
        return Err(field_err(
            &folder,
            episode,
            "seg masks",
            format!("{} PNG masks for {frames} video frames", files.len()),
        ));
    }
    let mut size = None;
    let mut data = Vec::new();
    for f in &files {
        let img = image::open(f)
            .map_err(|e| field_err(f, episode, "seg masks", format!("unreadable PNG: {e}")))?
            .into_luma16();
        let s = (img.width() as usize, img.height() as usize);
        if *size.get_or_insert(s) != s {
            return Err(field_err(
                f,
                episode,
                "seg masks",
                format!(
                    "{}x{}, but the first mask is {}x{}",
                    s.0,
                    s.1,
                    size.map_or(0, |x| x.0),
                    size.map_or(0, |x| x.1)
                ),
            ));
        }
        data.extend(img.as_raw().iter().map(|&v| u8::from(v != 0)));
    }
    let (width, height) = size.unwrap_or((0, 0));
    Ok(EpisodeMasks {
        frames,
        height,
        width,
        data,
    })
}
