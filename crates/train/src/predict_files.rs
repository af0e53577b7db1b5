//! `predict` from files to a folder, as `bridgev2w predict` and the Python
//! package's `BridgeV2W.predict_files` both run it: the first frame (any
//! image, resized to the model's size), one or more mask files (clips), the
//! model's predictions in batches, and per clip `frames/NNNNNN.png`,
//! `video.npy` (uint8 `[T, H, W, 3]`) and `video.mp4`, with `clips.json`
//! when there are several; written into a temporary folder renamed into
//! place (nothing is left behind when it fails; an existing output is
//! replaced only when asked, never one that is, contains or lies inside an
//! input).
//!
//! Mask files are `.npy` `[T, H, W]` of one of the project's mask kinds,
//! whatever wrote them:
//! - link labels, uint8 or uint16, 0 the background and 1..=254 a link
//!   (`labels/episode_*.npy` of a dataset, `labels.npy` of `bridgev2w
//!   masks`);
//! - binary masks, uint8 or bool, 0/1 or 0/255 (`masks.npy`, image tools);
//!   255 beside other values is a grey (soft) mask, refused.
//!
//! The model decides how it reads them: a binary-coded model takes either
//! as the robot's silhouette; a link-coded one takes labels and refuses
//! binary masks, naming its coding (a label file in which only link 1
//! shows cannot be told from a binary mask, and is refused the same way).

use bridgev2w_data::video::{Mp4VideoWriter, VideoError};
use bridgev2w_io::frame::{u8_from_unit, unit_from_u8, RgbFrame};
use bridgev2w_io::json::write_json_atomic;
use bridgev2w_io::npy::{read_npy, write_atomic, write_npy, NpyError};
use bridgev2w_io::output::{OutputDir, OutputError};
use bridgev2w_io::png::encode_rgb8;
use bridgev2w_io::progress::Progress;
use bridgev2w_io::FileError;
use bridgev2w_world_model::bridge::BridgeV2W;
use bridgev2w_world_model::pipeline::{PredictOptions, SampleOptions, WorldModel};
use bridgev2w_world_model::video::{MaskVideo, Video};
use bridgev2w_world_model::WorldModelError;
use std::path::{Path, PathBuf};

/// Errors of [`PredictJob`]: each names the file or option.
#[derive(Debug, thiserror::Error)]
pub enum PredictFilesError {
    /// An input that does not fit: the file or option, the value and what
    /// was expected.
    #[error("{what}: {message}")]
    Input {
        /// The file or option.
        what: String,
        /// Why.
        message: String,
    },
    /// The output folder.
    #[error(transparent)]
    Output(#[from] OutputError),
    /// A file read or written.
    #[error(transparent)]
    File(#[from] FileError),
    /// A `.npy` file.
    #[error(transparent)]
    Npy(#[from] NpyError),
    /// The MP4 writer.
    #[error(transparent)]
    Video(#[from] VideoError),
    /// The model.
    #[error(transparent)]
    Model(#[from] WorldModelError),
}

type Result<T> = std::result::Result<T, PredictFilesError>;

fn input(what: impl Into<String>, message: impl Into<String>) -> PredictFilesError {
    PredictFilesError::Input {
        what: what.into(),
        message: message.into(),
    }
}

/// One clip of a job: its mask file and the subfolder of the output it goes
/// to (`None`: the output itself, the single-clip layout).
#[derive(Debug, Clone, PartialEq)]
pub struct MaskClip {
    /// Subfolder name.
    pub name: Option<String>,
    /// The mask file.
    pub masks: PathBuf,
}

/// What to predict and where: the inputs of `bridgev2w predict`.
#[derive(Debug, Clone)]
pub struct PredictJob {
    /// The first frame (PNG, JPEG, ...).
    pub image: PathBuf,
    /// Mask files, or folders of them (their `.npy` files by name).
    pub masks: Vec<PathBuf>,
    /// The output folder.
    pub out: PathBuf,
    /// Replace an existing output.
    pub overwrite: bool,
    /// Clips per batch.
    pub batch_size: usize,
    /// Sampling.
    pub sample: SampleOptions,
    /// Other inputs (weights, embeddings) an output must not touch.
    pub other_inputs: Vec<PathBuf>,
}

/// A job whose options, clips and output folder were checked: the model is
/// loaded after this (it takes long), then [`PreparedJob::run`].
#[derive(Debug)]
pub struct PreparedJob {
    job: PredictJob,
    clips: Vec<MaskClip>,
    out: OutputDir,
}

/// What [`PreparedJob::run`] wrote.
#[derive(Debug, Clone, PartialEq)]
pub struct PredictRun {
    /// The output folder.
    pub out: PathBuf,
    /// The clips, in order.
    pub clips: Vec<MaskClip>,
    /// Frames per clip.
    pub frames: usize,
    /// Wall time of the predictions and writes (seconds).
    pub seconds: f64,
}

impl PredictRun {
    /// The line the CLI prints.
    pub fn summary(&self) -> String {
        let what = match self.clips.len() {
            1 => format!("{} frames", self.frames),
            n => format!("{n} clips of {} frames", self.frames),
        };
        format!(
            "wrote {what} to {} ({:.1} s)",
            self.out.display(),
            self.seconds
        )
    }
}

impl PredictJob {
    /// Checks the options and the clips and creates the output folder (a
    /// temporary one, renamed into place by [`PreparedJob::run`]).
    pub fn prepare(self) -> Result<PreparedJob> {
        bridgev2w_world_model::bridge::check_predict_batch("--batch-size", self.batch_size)?;
        self.sample.validate()?;
        let clips = mask_clips(&self.masks)?;
        // An output equal to, inside or containing an input would delete it.
        let inputs: Vec<&Path> = self
            .masks
            .iter()
            .map(PathBuf::as_path)
            .chain([self.image.as_path()])
            .chain(self.other_inputs.iter().map(PathBuf::as_path))
            .collect();
        let out = OutputDir::create_for(&self.out, self.overwrite, &inputs)?;
        Ok(PreparedJob {
            job: self,
            clips,
            out,
        })
    }
}

impl PreparedJob {
    /// The clips, in order.
    pub fn clips(&self) -> &[MaskClip] {
        &self.clips
    }

    /// Reads the first frame and every clip's masks (all checked before the
    /// first prediction), predicts them in batches and writes the output.
    pub fn run(self, model: &BridgeV2W, progress: &dyn Progress) -> Result<PredictRun> {
        let res = model.resolution();
        let frames = model.clip_frames();
        let (image, resized) = read_first_frame(&self.job.image, res)?;
        if let Some((w, h)) = resized {
            progress.note(&format!(
                "resizing {} from {w}x{h} to the model's {}x{} (WxH)",
                self.job.image.display(),
                res.1,
                res.0
            ));
        }
        for clip in &self.clips {
            let m = read_mask_file(&clip.masks, frames, res)?;
            model
                .config()
                .mask_coding
                .check_values(&m.data, &clip.masks.display().to_string())?;
        }
        let opts = PredictOptions {
            sample: self.job.sample.clone(),
            max_batch: None,
            ..PredictOptions::default()
        };
        let batches = self.clips.len().div_ceil(self.job.batch_size);
        let t0 = std::time::Instant::now();
        for (b, batch) in self.clips.chunks(self.job.batch_size).enumerate() {
            if batches > 1 {
                progress.note(&format!("batch {}/{batches}", b + 1));
            }
            let masks = batch
                .iter()
                .map(|c| read_mask_file(&c.masks, frames, res))
                .collect::<Result<Vec<_>>>()?;
            let first = vec![image.clone(); batch.len()];
            let videos = model.predict_batch_with_progress(&first, &masks, &opts, progress)?;
            for (clip, video) in batch.iter().zip(&videos) {
                let dir = match &clip.name {
                    Some(name) => self.out.path().join(name),
                    None => self.out.path().to_path_buf(),
                };
                write_clip(&dir, video)?;
            }
        }
        if self.clips.iter().any(|c| c.name.is_some()) {
            let list: Vec<serde_json::Value> = self
                .clips
                .iter()
                .map(|c| serde_json::json!({"name": c.name, "masks": c.masks}))
                .collect();
            write_json_atomic(
                &self.out.path().join("clips.json"),
                &serde_json::json!({
                    "seed": self.job.sample.seed,
                    "steps": self.job.sample.steps,
                    "clips": list
                }),
            )?;
        }
        let seconds = t0.elapsed().as_secs_f64();
        let out = self.out.commit()?;
        Ok(PredictRun {
            out,
            clips: self.clips,
            frames,
            seconds,
        })
    }
}

/// Reads an image as the model's first frame, resized to `(h, w)` when it
/// has another size; returns its own size `(w, h)` when it was resized.
pub fn read_first_frame(
    path: &Path,
    (h, w): (usize, usize),
) -> Result<(RgbFrame, Option<(u32, u32)>)> {
    let img = image::open(path)
        .map_err(|e| {
            input(
                format!("--image {}", path.display()),
                format!("not a readable image: {e}"),
            )
        })?
        .to_rgb8();
    let own = img.dimensions();
    let img = if own != (w as u32, h as u32) {
        image::imageops::resize(
            &img,
            w as u32,
            h as u32,
            image::imageops::FilterType::Triangle,
        )
    } else {
        img
    };
    let frame = RgbFrame {
        width: w,
        height: h,
        rgb: img.as_raw().iter().map(|&v| unit_from_u8(v)).collect(),
    };
    Ok((frame, (own != (w as u32, h as u32)).then_some(own)))
}

/// Reads a mask file `[frames, h, w]` (see the module documentation):
/// link labels of either width as they are, 0/255 binary masks as 0/1.
pub fn read_mask_file(path: &Path, frames: usize, (h, w): (usize, usize)) -> Result<MaskVideo> {
    let what = || format!("--masks {}", path.display());
    let arr = read_npy(path)?;
    let [t, mh, mw] = arr.shape[..] else {
        return Err(input(
            what(),
            format!("shape {:?}, expected [T, H, W]", arr.shape),
        ));
    };
    if (t, mh, mw) != (frames, h, w) {
        return Err(input(
            what(),
            format!(
                "shape [{t}, {mh}, {mw}] but the model takes [{frames}, {h}, {w}] \
                 (render them with `bridgev2w masks ... --width {w} --height {h}` over {frames} frames)"
            ),
        ));
    }
    // Soft (float) masks would be read as "non-zero = robot" without a
    // word: refused.
    if !matches!(arr.descr.as_str(), "|u1" | "|b1" | "<u2" | ">u2") {
        return Err(input(
            what(),
            format!(
                "dtype {}, expected link labels (uint8 or uint16, 0 background, 1..=255 links: labels/ of a dataset, labels.npy of `bridgev2w masks`) or binary masks (uint8 or bool, 0/1 or 0/255: masks.npy)",
                arr.descr
            ),
        ));
    }
    if let Some(v) = arr.data.iter().find(|&&v| v > 255.0) {
        return Err(input(
            what(),
            format!("link label {v}, expected labels up to 254"),
        ));
    }
    // 0/255: an image tool's binary mask. 255 beside other values is a
    // grey (soft, anti-aliased) mask, not labels: refused, not thresholded.
    let binary_255 = arr.data.iter().all(|&v| v == 0.0 || v == 255.0);
    if !binary_255 && arr.data.contains(&255.0) {
        let other = arr
            .data
            .iter()
            .find(|&&v| v != 0.0 && v != 255.0)
            .copied()
            .unwrap_or_default();
        return Err(input(
            what(),
            format!(
                "a value of {other} next to 255: a grey (soft) mask? expected binary masks (0/1 or 0/255) or link labels (1..=254)"
            ),
        ));
    }
    let data = arr
        .data
        .iter()
        .map(|&v| {
            if binary_255 {
                u8::from(v != 0.0)
            } else {
                v as u8
            }
        })
        .collect();
    Ok(MaskVideo {
        frames,
        height: h,
        width: w,
        data,
    })
}

/// The clips of `masks`: files as given, folders as their `.npy` files by
/// name. One file keeps the single-clip layout; otherwise each clip is
/// named by its file's stem (`NNN-STEM`, numbered in order, when stems
/// repeat).
pub fn mask_clips(masks: &[PathBuf]) -> Result<Vec<MaskClip>> {
    let mut files = Vec::new();
    for m in masks {
        if m.is_dir() {
            let mut found: Vec<PathBuf> = std::fs::read_dir(m)
                .map_err(|e| FileError::io(m, e))?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| {
                    p.is_file() && p.extension().is_some_and(|e| e.eq_ignore_ascii_case("npy"))
                })
                .collect();
            if found.is_empty() {
                return Err(input(
                    format!("--masks {}", m.display()),
                    "no .npy files in this folder (expected [T, H, W] masks or link labels as `bridgev2w masks` writes)",
                ));
            }
            found.sort();
            files.extend(found);
        } else {
            files.push(m.clone());
        }
    }
    if let ([one], [file]) = (masks, files.as_slice()) {
        if one == file {
            return Ok(vec![MaskClip {
                name: None,
                masks: file.clone(),
            }]);
        }
    }
    // A clip's name is its mask file's stem, and becomes a folder under the
    // output: it must be a plain name (`...npy` has the stem `..`).
    let stems: Vec<String> = files
        .iter()
        .map(|f| {
            let stem = f
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_else(|| "clip".to_owned());
            bridgev2w_io::confine::check_name(&stem).map_err(|e| {
                input(
                    format!("--masks {}", f.display()),
                    format!("the clip name taken from this file's name is {e}"),
                )
            })?;
            Ok(stem)
        })
        .collect::<Result<_>>()?;
    let unique = stems
        .iter()
        .collect::<std::collections::BTreeSet<_>>()
        .len()
        == stems.len();
    Ok(files
        .into_iter()
        .zip(stems)
        .enumerate()
        .map(|(i, (masks, stem))| MaskClip {
            name: Some(if unique {
                stem
            } else {
                format!("{i:03}-{stem}")
            }),
            masks,
        })
        .collect())
}

/// Writes one predicted clip into `dir`: `frames/NNNNNN.png`, `video.npy`
/// and `video.mp4` (8 frames per second, CogVideoX's rate).
pub fn write_clip(dir: &Path, video: &Video) -> Result<()> {
    let bytes: Vec<u8> = video.data.iter().map(|&v| u8_from_unit(v)).collect();
    let frames_dir = dir.join("frames");
    std::fs::create_dir_all(&frames_dir).map_err(|e| FileError::io(&frames_dir, e))?;
    let frame_len = video.height * video.width * 3;
    for (i, frame) in bytes.chunks(frame_len).enumerate() {
        let path = frames_dir.join(format!("{i:06}.png"));
        write_atomic(
            &path,
            &encode_rgb8(video.width as u32, video.height as u32, frame),
        )
        .map_err(|e| FileError::io(&path, e))?;
    }
    write_npy(
        &dir.join("video.npy"),
        &[video.frames, video.height, video.width, 3],
        &bytes,
    )?;
    let mp4 = dir.join("video.mp4");
    let mut writer = Mp4VideoWriter::new(&mp4, video.width, video.height, 8)?;
    for (i, frame) in bytes.chunks(frame_len).enumerate() {
        writer.push(frame, i == 0)?;
    }
    write_atomic(&mp4, &writer.to_bytes()?).map_err(|e| FileError::io(&mp4, e))?;
    Ok(())
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    fn npy(dir: &Path, name: &str, shape: &[usize], data: &[u8]) -> PathBuf {
        let p = dir.join(name);
        write_npy(&p, shape, data).unwrap();
        p
    }

    #[test]
    fn labels_of_either_width_and_binary_masks_are_read_as_the_model_needs() {
        let dir = tempfile::tempdir().unwrap();
        let u8_labels = npy(dir.path(), "u8.npy", &[1, 1, 4], &[0, 3, 7, 12]);
        let m = read_mask_file(&u8_labels, 1, (1, 4)).unwrap();
        assert_eq!(m.data, [0, 3, 7, 12]);
        let u16_labels = dir.path().join("u16.npy");
        write_npy(&u16_labels, &[1, 1, 4], &[0u16, 3, 7, 12]).unwrap();
        assert_eq!(
            read_mask_file(&u16_labels, 1, (1, 4)).unwrap().data,
            [0, 3, 7, 12]
        );
        let b255 = npy(dir.path(), "b.npy", &[1, 1, 4], &[0, 255, 255, 0]);
        assert_eq!(read_mask_file(&b255, 1, (1, 4)).unwrap().data, [0, 1, 1, 0]);
        let big = dir.path().join("big.npy");
        write_npy(&big, &[1, 1, 2], &[0u16, 300]).unwrap();
        let e = read_mask_file(&big, 1, (1, 2)).unwrap_err().to_string();
        assert!(e.contains("big.npy") && e.contains("link label 300"), "{e}");
        let float = dir.path().join("f.npy");
        write_npy(&float, &[1, 1, 2], &[0f32, 0.5]).unwrap();
        let e = read_mask_file(&float, 1, (1, 2)).unwrap_err().to_string();
        assert!(e.contains("f.npy") && e.contains("dtype <f4"), "{e}");
        let grey = npy(dir.path(), "g.npy", &[1, 1, 4], &[0, 128, 255, 0]);
        let e = read_mask_file(&grey, 1, (1, 4)).unwrap_err().to_string();
        assert!(
            e.contains("g.npy") && e.contains("a value of 128 next to 255"),
            "{e}"
        );
        let e = read_mask_file(&u8_labels, 2, (1, 4))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("shape [1, 1, 4] but the model takes [2, 1, 4]"),
            "{e}"
        );
    }
}
