//! What a dataset declares in `meta/info.json`'s `features` (each
//! feature's `shape`), and the checks of what is read against it: the
//! widths of the state and action rows, the size of the video frames, and
//! the shape of the stored masks and labels (`[T, H, W]`: the episode's
//! length and a declared video size). A mismatch is an error naming the
//! file read, the feature, the declared and the found shape, never data of
//! another shape handed on.

use super::error::meta_err;
use super::DatasetError;
use serde_json::Value;
use std::path::Path;

/// The declared `shape` of feature `key` in `info` (`meta/info.json`, read
/// from `info_path`): `None` when the dataset does not declare the feature;
/// an error naming the feature when its shape is not a list of integers.
pub(super) fn feature_shape(
    info: &Value,
    info_path: &Path,
    key: &str,
) -> Result<Option<Vec<usize>>, DatasetError> {
    let Some(feature) = info.get("features").and_then(|f| f.get(key)) else {
        return Ok(None);
    };
    let bad = || {
        meta_err(
            info_path,
            format!(
                "field \"features.{key}.shape\": {}: expected a list of non-negative integers",
                feature.get("shape").unwrap_or(&Value::Null)
            ),
        )
    };
    let dims = feature
        .get("shape")
        .and_then(Value::as_array)
        .ok_or_else(bad)?;
    dims.iter()
        .map(|d| d.as_u64().and_then(|d| usize::try_from(d).ok()))
        .collect::<Option<Vec<usize>>>()
        .map(Some)
        .ok_or_else(bad)
}

/// The frame size `(height, width)` declared for video `key`: its shape is
/// `[height, width, 3]`, or `[3, height, width]` where its `names` start
/// with `"channels"` (older LeRobot datasets). Anything else is an error
/// naming the feature.
pub(super) fn video_size(
    info: &Value,
    info_path: &Path,
    key: &str,
) -> Result<(usize, usize), DatasetError> {
    let shape = feature_shape(info, info_path, key)?;
    let channels_first = info["features"][key]
        .get("names")
        .and_then(Value::as_array)
        .and_then(|n| n.first())
        .and_then(Value::as_str)
        == Some("channels");
    match shape.as_deref() {
        Some(&[3, h, w]) if channels_first && h > 0 && w > 0 => Ok((h, w)),
        Some(&[h, w, 3]) if !channels_first && h > 0 && w > 0 => Ok((h, w)),
        other => Err(meta_err(
            info_path,
            format!(
                "field \"features.{key}.shape\": {}: expected [height, width, 3] (or [3, height, width] with names [\"channels\", ...]) of a video",
                other.map_or("missing".to_string(), |s| format!("{s:?}"))
            ),
        )),
    }
}

/// Checks that every row of `rows` (the feature `feature` of the frames
/// read from `file`, one per frame) has the width `declared` (the
/// feature's shape in `meta/info.json`) holds: the product of its
/// dimensions. `declared` `None` (not declared) checks nothing.
pub(super) fn check_row_widths<'a>(
    file: &Path,
    episode: i64,
    feature: &str,
    declared: Option<&[usize]>,
    rows: impl Iterator<Item = &'a Vec<f32>>,
) -> Result<(), DatasetError> {
    let Some(declared) = declared else {
        return Ok(());
    };
    let width = declared.iter().product::<usize>();
    for (t, row) in rows.enumerate() {
        if row.len() != width {
            return Err(DatasetError::Field {
                path: file.to_path_buf(),
                episode,
                field: feature.into(),
                message: format!(
                    "frame {t} has {} values (shape [{}]), but meta/info.json declares shape {declared:?}",
                    row.len(),
                    row.len()
                ),
            });
        }
    }
    Ok(())
}

/// Checks the shape `found` of an episode's stored `what` (`masks` or
/// `labels`, read from `file`) against `[length, H, W]`, where `length` is
/// the episode's frame count and `(H, W)` one of `video_sizes` (the
/// declared `(height, width, key)` of the dataset's videos; any size when
/// it declares none).
pub(super) fn check_frames_shape(
    file: &Path,
    episode: i64,
    what: &str,
    found: &[usize],
    length: usize,
    video_sizes: &[(usize, usize, String)],
) -> Result<(), DatasetError> {
    let size_ok = |h: usize, w: usize| {
        video_sizes.is_empty() || video_sizes.iter().any(|v| (v.0, v.1) == (h, w))
    };
    let ok = matches!(found, &[t, h, w] if t == length && size_ok(h, w));
    if ok {
        return Ok(());
    }
    let declared: Vec<String> = video_sizes
        .iter()
        .map(|(h, w, key)| format!("[{length}, {h}, {w}] (features.{key})"))
        .collect();
    let expected = if declared.is_empty() {
        format!("[{length}, H, W]")
    } else {
        declared.join(" or ")
    };
    Err(DatasetError::Field {
        path: file.to_path_buf(),
        episode,
        field: what.into(),
        message: format!(
            "shape {found:?}, but the episode has {length} frames and meta/info.json declares its videos' size: expected {expected}"
        ),
    })
}
