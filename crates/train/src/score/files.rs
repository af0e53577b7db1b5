//! The video folders of [`crate::score`]: which videos a folder holds (one
//! folder of PNG frames or one H.264 `NAME.mp4` per video), the frame files
//! of a video with their numbers, and frames and masks read from them.

use super::error::{invalid, Result, ScoreError};
use bridgev2w_io::frame::RgbFrame;
use bridgev2w_world_model::video::Video;
use std::path::{Path, PathBuf};

/// The video names of folder `dir` (called `what` in errors), sorted:
/// sub-folders of PNG frames, and `NAME.mp4` files (H.264) named by their
/// stem. Hidden entries are skipped; a name that is both a folder and an
/// `.mp4` is an error, and so is a folder without videos.
pub fn video_names(dir: &Path, what: &str) -> Result<Vec<String>> {
    let entries = std::fs::read_dir(dir).map_err(|source| ScoreError::Io {
        context: format!("{what} directory {}", dir.display()),
        source,
    })?;
    let mut names = Vec::new();
    for e in entries {
        let e = e.map_err(|source| ScoreError::Io {
            context: format!("reading {what} directory {}", dir.display()),
            source,
        })?;
        let path = e.path();
        let name = e.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') {
            continue;
        }
        if path.is_dir() {
            names.push(name);
        } else if is_mp4(&path) {
            let stem = path
                .file_stem()
                .map(|s| s.to_string_lossy().into_owned())
                .unwrap_or_default();
            if dir.join(&stem).is_dir() {
                return invalid!(
                    "{what} directory {}: video \"{stem}\" is both a folder and {name}: keep one",
                    dir.display()
                );
            }
            names.push(stem);
        }
    }
    if names.is_empty() {
        return invalid!(
            "{what} directory {} holds no videos (expected one folder of PNG frames or one .mp4 per video)",
            dir.display()
        );
    }
    names.sort();
    Ok(names)
}

/// Whether `path` is a file with the extension `.mp4` (any case).
fn is_mp4(path: &Path) -> bool {
    path.is_file()
        && path
            .extension()
            .is_some_and(|x| x.eq_ignore_ascii_case("mp4"))
}

/// The frames of video `name` under `dir`, by frame number:
/// `dir/name/*.png` (numbered by the digits at the end of their names) or
/// `dir/name.mp4` (numbered from 0).
pub fn load_frames(dir: &Path, name: &str) -> Result<Vec<(u64, RgbFrame)>> {
    let mp4 = dir.join(format!("{name}.mp4"));
    if is_mp4(&mp4) {
        let video = bridgev2w_data::video::decode_mp4(&mp4)?;
        return video
            .frames
            .iter()
            .enumerate()
            .map(|(i, f)| {
                RgbFrame::from_rgb8(video.width, video.height, f)
                    .map(|f| (i as u64, f))
                    .map_err(|source| ScoreError::MetricAt {
                        context: format!("{}: frame {i}", mp4.display()),
                        source: source.into(),
                    })
            })
            .collect();
    }
    frame_files(&dir.join(name))?
        .into_iter()
        .map(|(i, f)| Ok((i, read_frame(&f)?)))
        .collect()
}

/// The PNG files of one video folder with their frame numbers (the digits
/// at the end of the file's stem: `000007.png`, `7.png` and `frame_7.png`
/// are frame 7), in frame order. A file without a number, or two files of
/// one number, is an error.
pub fn frame_files(dir: &Path) -> Result<Vec<(u64, PathBuf)>> {
    let mut files: Vec<(u64, PathBuf)> = std::fs::read_dir(dir)
        .map_err(|source| ScoreError::Io {
            context: format!("video folder {}", dir.display()),
            source,
        })?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x.eq_ignore_ascii_case("png")))
        .map(|p| Ok((frame_number(&p)?, p)))
        .collect::<Result<_>>()?;
    if files.is_empty() {
        return invalid!("video folder {} has no PNG frames", dir.display());
    }
    files.sort();
    if let Some(w) = files.windows(2).find(|w| w[0].0 == w[1].0) {
        return invalid!(
            "{} and {} are both frame {}: one file per frame number",
            w[0].1.display(),
            w[1].1.display(),
            w[0].0
        );
    }
    Ok(files)
}

/// The number at the end of a frame file's stem.
fn frame_number(path: &Path) -> Result<u64> {
    let stem = path.file_stem().and_then(|s| s.to_str()).unwrap_or("");
    let digits = stem.len() - stem.trim_end_matches(|c: char| c.is_ascii_digit()).len();
    stem[stem.len() - digits..].parse().map_err(|_| {
        ScoreError::Invalid(format!(
            "frame {}: expected a frame number at the end of its name (e.g. 000007.png)",
            path.display()
        ))
    })
}

/// Checks that predicted and ground-truth frames (or masks: `what`) of
/// video `name` have the same numbers (pairs are made by number, not by
/// position).
pub fn check_numbers(name: &str, what: &str, pred: &[u64], gt: &[u64]) -> Result<()> {
    if pred == gt {
        return Ok(());
    }
    let missing = |from: &[u64], to: &[u64]| from.iter().find(|i| !to.contains(i)).copied();
    let detail = match (missing(gt, pred), missing(pred, gt)) {
        (Some(i), _) => format!("ground-truth {what} {i} has no predicted one"),
        (None, Some(i)) => format!("predicted {what} {i} has no ground-truth one"),
        (None, None) => String::new(),
    };
    invalid!(
        "video \"{name}\": {} predicted {what} vs {} ground-truth {what}; {detail}: {what} are paired by frame number",
        pred.len(),
        gt.len()
    )
}

/// An RGB frame from an image file.
fn read_frame(path: &Path) -> Result<RgbFrame> {
    let img = image::open(path)
        .map_err(|source| ScoreError::Image {
            what: "frame",
            path: path.to_path_buf(),
            source,
        })?
        .to_rgb8();
    let (w, h) = img.dimensions();
    Ok(RgbFrame::from_rgb8(w as usize, h as usize, img.as_raw())
        .map_err(bridgev2w_eval::MetricError::from)?)
}

/// A mask (grey values, non-zero = robot) from an image file: width,
/// height and the values.
pub fn read_mask(path: &Path) -> Result<(u32, u32, Vec<u8>)> {
    let img = image::open(path)
        .map_err(|source| ScoreError::Image {
            what: "mask",
            path: path.to_path_buf(),
            source,
        })?
        .to_luma8();
    let (w, h) = img.dimensions();
    Ok((w, h, img.into_raw()))
}

/// Video `name` under `dir` as one clip (every frame the same size) and
/// its frame numbers.
pub fn read_video(dir: &Path, name: &str) -> Result<(Vec<u64>, Video)> {
    let frames = load_frames(dir, name)?;
    let mut data = Vec::new();
    let mut size = None;
    for (i, frame) in &frames {
        let s = (frame.width, frame.height);
        if *size.get_or_insert(s) != s {
            return invalid!(
                "video \"{name}\" in {}: frame {i} is {}x{}, earlier frames {}x{}",
                dir.display(),
                s.0,
                s.1,
                size.map_or(0, |x| x.0),
                size.map_or(0, |x| x.1)
            );
        }
        data.extend_from_slice(&frame.rgb);
    }
    let (width, height) = size.unwrap_or((0, 0));
    let numbers = frames.iter().map(|f| f.0).collect();
    Ok((
        numbers,
        Video {
            frames: frames.len(),
            height,
            width,
            data,
        },
    ))
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn frame_numbers_come_from_the_end_of_the_name() {
        assert_eq!(frame_number(Path::new("a/000007.png")).unwrap(), 7);
        assert_eq!(frame_number(Path::new("frame_12.png")).unwrap(), 12);
        let e = frame_number(Path::new("last.png")).unwrap_err().to_string();
        assert!(e.contains("expected a frame number"), "{e}");
    }

    #[test]
    fn mismatched_numbers_name_the_first_missing_frame() {
        check_numbers("v", "frames", &[0, 1], &[0, 1]).unwrap();
        let e = check_numbers("v", "frames", &[0, 2], &[0, 1, 2])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("video \"v\": 2 predicted frames vs 3 ground-truth frames; ground-truth frames 1 has no predicted one"),
            "{e}"
        );
        let e = check_numbers("v", "masks", &[0, 3], &[0])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("predicted masks 3 has no ground-truth one"),
            "{e}"
        );
    }
}
