//! Reading LeRobot v3.0 and v2.1 datasets: the metadata, the frame rows,
//! the videos and the synthetic extras (masks, camera calibration).

use super::columns::{read_batches, Columns};
use super::error::{io_err, meta_err};
use super::meta::{
    check_template_widths, format_template, EpisodeData, EpisodeInfo, FrameRow, Version, VideoRef,
};
use super::shapes::{check_frames_shape, check_row_widths, feature_shape, video_size};
use super::{files, DatasetError};
use crate::video::VideoStream;
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_io::confine::{self, Refusal};
use bridgev2w_io::npy::read_npy;
use serde_json::Value;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// Stored masks: their shape `[T, H, W]` and their 0/1 values.
pub type StoredMasks = (Vec<usize>, Vec<u8>);

/// Per video key: `(key, chunk_index, file_index, from_timestamp, to_timestamp)` columns.
type VideoColumns = (String, Vec<i64>, Vec<i64>, Vec<f64>, Vec<f64>);

/// Reads frame rows from a LeRobot data parquet file.
pub fn read_frames_parquet(path: &Path) -> Result<Vec<FrameRow>, DatasetError> {
    let batches = read_batches(path)?;
    let c = Columns {
        path,
        batches: &batches,
    };
    let index = c.i64s("index")?;
    let episode_index = c.i64s("episode_index")?;
    let frame_index = c.i64s("frame_index")?;
    let timestamp = c.f64s("timestamp")?;
    let task_index = c.i64s("task_index")?;
    let state = c.float_lists("observation.state")?;
    let action = c.float_lists("action")?;
    let n = index.len();
    for (name, len) in [
        ("episode_index", episode_index.len()),
        ("frame_index", frame_index.len()),
        ("timestamp", timestamp.len()),
        ("task_index", task_index.len()),
        ("observation.state", state.len()),
        ("action", action.len()),
    ] {
        if len != n {
            return Err(c.field_err(name, -1, format!("{len} rows but \"index\" has {n}")));
        }
    }
    let mut rows = Vec::with_capacity(n);
    for i in 0..n {
        let ep = episode_index[i];
        for (name, v) in [("observation.state", &state[i]), ("action", &action[i])] {
            if let Some(k) = v.iter().position(|x| !x.is_finite()) {
                return Err(c.field_err(
                    name,
                    ep,
                    format!(
                        "frame {}: value {k} is {} (not finite)",
                        frame_index[i], v[k]
                    ),
                ));
            }
        }
        rows.push(FrameRow {
            index: index[i],
            episode_index: ep,
            frame_index: frame_index[i],
            timestamp: timestamp[i] as f32,
            task_index: task_index[i],
            state: state[i].clone(),
            action: action[i].clone(),
        });
    }
    Ok(rows)
}

/// A LeRobot dataset on disk.
#[derive(Debug, Clone)]
pub struct LeRobotDataset {
    /// Root directory.
    pub root: PathBuf,
    /// Layout version.
    pub version: Version,
    /// `meta/info.json`.
    pub info: Value,
    /// Frames per second.
    pub fps: f64,
    /// Episodes in index order.
    pub episodes: Vec<EpisodeInfo>,
    /// Task strings by task index.
    pub tasks: BTreeMap<i64, String>,
    /// Video feature keys.
    pub video_keys: Vec<String>,
}

fn read_json(path: &Path) -> Result<Value, DatasetError> {
    bridgev2w_io::json::read_json(path).map_err(|e| match e {
        bridgev2w_io::FileError::Io { path, source } => DatasetError::Io { path, source },
        bridgev2w_io::FileError::Json { path, source } => DatasetError::Meta {
            path,
            message: format!("invalid JSON: {source}"),
        },
        bridgev2w_io::FileError::Format { path, message } => DatasetError::Meta { path, message },
    })
}

impl LeRobotDataset {
    /// Opens a v3.0 or v2.1 dataset (reads the metadata, not the frames).
    /// Every metadata file must be a regular file of bounded size inside
    /// `root` (links followed); the shapes `meta/info.json` declares for
    /// `observation.state`, `action` and each video must be well-formed
    /// (they are checked against what is read).
    pub fn open(root: &Path) -> Result<Self, DatasetError> {
        let info_path = files::required(root, "meta/info.json", confine::MAX_METADATA_BYTES)?;
        let info = read_json(&info_path)?;
        let version = info
            .get("codebase_version")
            .and_then(Value::as_str)
            .unwrap_or("")
            .to_string();
        let version = match version.as_str() {
            "v3.0" => Version::V30,
            "v2.1" | "v2.0" => Version::V21,
            _ => {
                return Err(DatasetError::Version {
                    path: info_path,
                    version,
                })
            }
        };
        let fps = info
            .get("fps")
            .and_then(Value::as_f64)
            .filter(|f| *f > 0.0)
            .ok_or_else(|| meta_err(&info_path, "\"fps\" is missing or not a positive number"))?;
        let features = info
            .get("features")
            .and_then(Value::as_object)
            .ok_or_else(|| meta_err(&info_path, "\"features\" is missing"))?;
        let video_keys: Vec<String> = features
            .iter()
            .filter(|(_, v)| v.get("dtype").and_then(Value::as_str) == Some("video"))
            .map(|(k, _)| k.clone())
            .collect();
        // Keys are substituted into `video_path` and name parquet columns.
        for key in &video_keys {
            confine::check_name(key).map_err(|e| {
                meta_err(
                    &info_path,
                    format!("field \"features\": video feature key {e}"),
                )
            })?;
        }
        for key in ["observation.state", "action"] {
            feature_shape(&info, &info_path, key)?;
        }
        for key in &video_keys {
            video_size(&info, &info_path, key)?;
        }
        let template = |key: &str| -> Result<String, DatasetError> {
            let tpl = info
                .get(key)
                .and_then(Value::as_str)
                .map(str::to_string)
                .ok_or_else(|| meta_err(&info_path, format!("\"{key}\" is missing")))?;
            check_template_widths(&tpl)
                .map_err(|m| meta_err(&info_path, format!("field \"{key}\" ({tpl:?}): {m}")))?;
            Ok(tpl)
        };
        let data_tpl = template("data_path")?;
        let video_tpl = if video_keys.is_empty() {
            String::new()
        } else {
            template("video_path")?
        };
        let chunks_size = info
            .get("chunks_size")
            .and_then(Value::as_u64)
            .unwrap_or(1000)
            .max(1);
        let (episodes, tasks) = match version {
            Version::V30 => Self::open_v30(root, &data_tpl, &video_tpl, &video_keys)?,
            Version::V21 => {
                Self::open_v21(root, &data_tpl, &video_tpl, &video_keys, chunks_size, fps)?
            }
        };
        Ok(Self {
            root: root.to_path_buf(),
            version,
            info,
            fps,
            episodes,
            tasks,
            video_keys,
        })
    }

    fn open_v30(
        root: &Path,
        data_tpl: &str,
        video_tpl: &str,
        video_keys: &[String],
    ) -> Result<(Vec<EpisodeInfo>, BTreeMap<i64, String>), DatasetError> {
        let tasks_path = files::required(root, "meta/tasks.parquet", confine::MAX_DATA_BYTES)?;
        let batches = read_batches(&tasks_path)?;
        let c = Columns {
            path: &tasks_path,
            batches: &batches,
        };
        let task_col = if c.has("task") {
            "task"
        } else {
            "__index_level_0__"
        };
        let tasks: BTreeMap<i64, String> = c
            .i64s("task_index")?
            .into_iter()
            .zip(c.strings(task_col)?)
            .collect();

        let mut episodes = Vec::new();
        for path in &files::episode_index_files(root)? {
            let batches = read_batches(path)?;
            let c = Columns {
                path,
                batches: &batches,
            };
            let idx = c.i64s("episode_index")?;
            let length = c.i64s("length")?;
            let ep_tasks = c.string_lists("tasks")?;
            let dchunk = c.i64s("data/chunk_index")?;
            let dfile = c.i64s("data/file_index")?;
            let split = if c.has("split") {
                Some(c.strings("split")?)
            } else {
                None
            };
            let mut vids: Vec<VideoColumns> = Vec::new();
            for key in video_keys {
                let col = |s: &str| format!("videos/{key}/{s}");
                vids.push((
                    key.clone(),
                    c.i64s(&col("chunk_index"))?,
                    c.i64s(&col("file_index"))?,
                    c.f64s(&col("from_timestamp"))?,
                    c.f64s(&col("to_timestamp"))?,
                ));
            }
            for i in 0..idx.len() {
                if length[i] < 0 {
                    return Err(c.field_err(
                        "length",
                        idx[i],
                        format!("negative length {}", length[i]),
                    ));
                }
                let data_path = confined_join(
                    root,
                    "data_path",
                    data_tpl,
                    format_template(
                        data_tpl,
                        &[
                            ("chunk_index", dchunk[i].to_string()),
                            ("file_index", dfile[i].to_string()),
                        ],
                    ),
                )?;
                let mut videos = BTreeMap::new();
                for (key, vc, vf, from, to) in &vids {
                    videos.insert(
                        key.clone(),
                        VideoRef {
                            path: confined_join(
                                root,
                                "video_path",
                                video_tpl,
                                format_template(
                                    video_tpl,
                                    &[
                                        ("video_key", key.clone()),
                                        ("chunk_index", vc[i].to_string()),
                                        ("file_index", vf[i].to_string()),
                                    ],
                                ),
                            )?,
                            from_timestamp_s: from[i],
                            to_timestamp_s: to[i],
                        },
                    );
                }
                episodes.push(EpisodeInfo {
                    episode_index: idx[i],
                    length: length[i] as usize,
                    tasks: ep_tasks.get(i).cloned().unwrap_or_default(),
                    data_path,
                    videos,
                    split: split.as_ref().and_then(|s| s.get(i).cloned()),
                });
            }
        }
        episodes.sort_by_key(|e| e.episode_index);
        Ok((episodes, tasks))
    }

    fn open_v21(
        root: &Path,
        data_tpl: &str,
        video_tpl: &str,
        video_keys: &[String],
        chunks_size: u64,
        fps: f64,
    ) -> Result<(Vec<EpisodeInfo>, BTreeMap<i64, String>), DatasetError> {
        let jsonl = |name: &str| -> Result<Vec<(usize, Value)>, DatasetError> {
            let path = files::required(root, &format!("meta/{name}"), confine::MAX_METADATA_BYTES)?;
            let text = std::fs::read_to_string(&path).map_err(io_err(&path))?;
            text.lines()
                .enumerate()
                .filter(|(_, l)| !l.trim().is_empty())
                .map(|(n, l)| {
                    serde_json::from_str(l)
                        .map(|v| (n + 1, v))
                        .map_err(|e| meta_err(&path, format!("line {}: invalid JSON: {e}", n + 1)))
                })
                .collect()
        };
        let tasks_path = root.join("meta/tasks.jsonl");
        let mut tasks = BTreeMap::new();
        for (line, v) in jsonl("tasks.jsonl")? {
            let i = v.get("task_index").and_then(Value::as_i64);
            let t = v.get("task").and_then(Value::as_str);
            match (i, t) {
                (Some(i), Some(t)) => {
                    tasks.insert(i, t.to_string());
                }
                _ => {
                    return Err(meta_err(
                        &tasks_path,
                        format!("line {line}: needs \"task_index\" and \"task\""),
                    ))
                }
            }
        }
        let eps_path = root.join("meta/episodes.jsonl");
        let mut episodes = Vec::new();
        for (line, v) in jsonl("episodes.jsonl")? {
            let bad = |f: &str| {
                meta_err(
                    &eps_path,
                    format!("line {line}: \"{f}\" is missing or invalid"),
                )
            };
            let ep = v
                .get("episode_index")
                .and_then(Value::as_i64)
                .ok_or_else(|| bad("episode_index"))?;
            let length = v
                .get("length")
                .and_then(Value::as_u64)
                .ok_or_else(|| bad("length"))? as usize;
            let ep_tasks = v
                .get("tasks")
                .and_then(Value::as_array)
                .map(|a| {
                    a.iter()
                        .filter_map(Value::as_str)
                        .map(str::to_string)
                        .collect()
                })
                .unwrap_or_default();
            let chunk = (ep as u64 / chunks_size).to_string();
            let data_path = confined_join(
                root,
                "data_path",
                data_tpl,
                format_template(
                    data_tpl,
                    &[
                        ("episode_chunk", chunk.clone()),
                        ("episode_index", ep.to_string()),
                    ],
                ),
            )?;
            let videos = video_keys
                .iter()
                .map(|key| {
                    let path = confined_join(
                        root,
                        "video_path",
                        video_tpl,
                        format_template(
                            video_tpl,
                            &[
                                ("episode_chunk", chunk.clone()),
                                ("video_key", key.clone()),
                                ("episode_index", ep.to_string()),
                            ],
                        ),
                    )?;
                    Ok((
                        key.clone(),
                        VideoRef {
                            path,
                            from_timestamp_s: 0.0,
                            to_timestamp_s: length as f64 / fps,
                        },
                    ))
                })
                .collect::<Result<_, DatasetError>>()?;
            episodes.push(EpisodeInfo {
                episode_index: ep,
                length,
                tasks: ep_tasks,
                data_path,
                videos,
                split: None,
            });
        }
        episodes.sort_by_key(|e| e.episode_index);
        Ok((episodes, tasks))
    }

    /// `path` (an episode's data or video file, formatted from the template
    /// `field` of `meta/info.json`) checked to resolve inside the root, links
    /// followed, to a regular file of at most `max_bytes`. A missing file is
    /// an I/O error on `path`, as opening it would give.
    fn confined(
        &self,
        episode: i64,
        field: &str,
        path: &Path,
        max_bytes: u64,
    ) -> Result<PathBuf, DatasetError> {
        confine::confined_under(&self.root, path, max_bytes).map_err(|e| match e {
            Refusal::Unresolved { path, source, .. }
                if source.kind() == std::io::ErrorKind::NotFound =>
            {
                DatasetError::Io { path, source }
            }
            e => DatasetError::Field {
                path: self.root.join("meta/info.json"),
                episode,
                field: field.into(),
                message: e.to_string(),
            },
        })
    }

    /// The episode entry with index `episode`.
    pub fn episode(&self, episode: i64) -> Result<&EpisodeInfo, DatasetError> {
        self.episodes
            .iter()
            .find(|e| e.episode_index == episode)
            .ok_or_else(|| meta_err(&self.root, format!("no episode {episode}")))
    }

    /// Reads an episode's frame rows (state, action, ...), checking count and order.
    pub fn read_episode(&self, episode: i64) -> Result<EpisodeData, DatasetError> {
        let info = self.episode(episode)?;
        let data_path = self.confined(
            episode,
            "data_path",
            &info.data_path,
            confine::MAX_DATA_BYTES,
        )?;
        let mut frames: Vec<FrameRow> = read_frames_parquet(&data_path)?
            .into_iter()
            .filter(|r| r.episode_index == episode)
            .collect();
        frames.sort_by_key(|r| r.frame_index);
        let field = |f: &str, m: String| DatasetError::Field {
            path: info.data_path.clone(),
            episode,
            field: f.into(),
            message: m,
        };
        if frames.len() != info.length {
            return Err(field(
                "episode_index",
                format!(
                    "{} frames in the data file but the episode index says {}",
                    frames.len(),
                    info.length
                ),
            ));
        }
        for (i, r) in frames.iter().enumerate() {
            if r.frame_index != i as i64 {
                return Err(field(
                    "frame_index",
                    format!("expected {i}, found {}", r.frame_index),
                ));
            }
        }
        let info_path = self.root.join("meta/info.json");
        let state = feature_shape(&self.info, &info_path, "observation.state")?;
        let rows = frames.iter().map(|r| &r.state);
        check_row_widths(
            &data_path,
            episode,
            "observation.state",
            state.as_deref(),
            rows,
        )?;
        let action = feature_shape(&self.info, &info_path, "action")?;
        let rows = frames.iter().map(|r| &r.action);
        check_row_widths(&data_path, episode, "action", action.as_deref(), rows)?;
        Ok(EpisodeData { frames })
    }

    /// The frame size `(height, width)` `meta/info.json` declares for video
    /// `key` (its `shape`, `[height, width, 3]` or channels first); an
    /// error names the feature when it declares none.
    pub fn video_size(&self, key: &str) -> Result<(usize, usize), DatasetError> {
        video_size(&self.info, &self.root.join("meta/info.json"), key)
    }

    /// Decodes an episode's frames of video `key` (interleaved RGB8),
    /// checking the frame size against the declared shape (before decoding)
    /// and the frame count against the episode's length.
    pub fn read_video(&self, episode: i64, key: &str) -> Result<Vec<Vec<u8>>, DatasetError> {
        let info = self.episode(episode)?;
        let v = info.videos.get(key).ok_or_else(|| DatasetError::Field {
            path: self.root.join("meta"),
            episode,
            field: key.into(),
            message: format!("no such video key (keys: {})", self.video_keys.join(", ")),
        })?;
        let path = self.confined(episode, "video_path", &v.path, confine::MAX_VIDEO_BYTES)?;
        let video_err = |source| DatasetError::Video {
            episode,
            key: key.into(),
            source,
        };
        let stream = VideoStream::open(&path).map_err(video_err)?;
        let (h, w) = self.video_size(key)?;
        let found = (stream.info().height, stream.info().width);
        if found != (h, w) {
            return Err(DatasetError::Field {
                path: v.path.clone(),
                episode,
                field: key.into(),
                message: format!(
                    "frames of shape [{}, {}, 3] (height, width, channels), but meta/info.json's features.{key}.shape declares [{h}, {w}, 3]",
                    found.0, found.1
                ),
            });
        }
        let video = stream.read_all().map_err(video_err)?;
        let half = 0.5 / self.fps;
        let frames: Vec<Vec<u8>> = video
            .frames
            .into_iter()
            .zip(&video.timestamps_s)
            .filter(|(_, &t)| t >= v.from_timestamp_s - half && t < v.to_timestamp_s - half)
            .map(|(f, _)| f)
            .collect();
        if frames.len() != info.length {
            return Err(DatasetError::Field {
                path: v.path.clone(),
                episode,
                field: key.into(),
                message: format!(
                    "video has {} frames in [{:.3}, {:.3}) s but the episode has {} states",
                    frames.len(),
                    v.from_timestamp_s,
                    v.to_timestamp_s,
                    info.length
                ),
            });
        }
        Ok(frames)
    }

    /// A file of the dataset at a fixed place (`rel` under the root, e.g.
    /// `labels/episode_000000.npy`) when one is there: a regular file of at
    /// most `max_bytes` inside the root (links followed), or an error naming
    /// the path (a FIFO, a device, a folder, a link out); `None` when
    /// nothing is there.
    pub fn stored_file(&self, rel: &str, max_bytes: u64) -> Result<Option<PathBuf>, DatasetError> {
        files::optional(&self.root, rel, max_bytes)
    }

    /// The declared `(height, width, key)` of every video, for checking
    /// per-frame arrays stored beside them.
    fn video_sizes(&self) -> Result<Vec<(usize, usize, String)>, DatasetError> {
        self.video_keys
            .iter()
            .map(|k| self.video_size(k).map(|(h, w)| (h, w, k.clone())))
            .collect()
    }

    /// The stored ground-truth masks of an episode (`masks/episode_XXXXXX.npy`)
    /// when the dataset has them: `(shape [T, H, W], 0/1 data)`, uint8 (0/1
    /// or 0/255), `T` the episode's length and `H, W` a declared video size.
    pub fn stored_masks(&self, episode: i64) -> Result<Option<StoredMasks>, DatasetError> {
        let length = self.episode(episode)?.length;
        let rel = format!("masks/episode_{episode:06}.npy");
        let Some(path) = self.stored_file(&rel, confine::MAX_DATA_BYTES)? else {
            return Ok(None);
        };
        let a = read_npy(&path).map_err(|e| meta_err(&path, e.to_string()))?;
        if a.shape.len() != 3 || a.descr != "|u1" || a.shape.contains(&0) {
            return Err(meta_err(
                &path,
                format!(
                    "expected uint8 [T,H,W] masks with no empty dimension, found {} {:?}",
                    a.descr, a.shape
                ),
            ));
        }
        check_frames_shape(
            &path,
            episode,
            "masks",
            &a.shape,
            length,
            &self.video_sizes()?,
        )?;
        let masks = a.binary_mask().map_err(|m| meta_err(&path, m))?;
        Ok(Some((a.shape, masks)))
    }

    /// The synthetic ground-truth masks of an episode: [`Self::stored_masks`],
    /// a missing file being an I/O error naming it.
    pub fn read_masks(&self, episode: i64) -> Result<(Vec<usize>, Vec<u8>), DatasetError> {
        self.stored_masks(episode)?.ok_or_else(|| {
            let path = self.root.join(format!("masks/episode_{episode:06}.npy"));
            DatasetError::Io {
                path,
                source: std::io::ErrorKind::NotFound.into(),
            }
        })
    }

    /// The synthetic camera calibration of an episode's video `key`.
    pub fn read_calibration(&self, episode: i64, key: &str) -> Result<Camera, DatasetError> {
        let rel = format!("meta/calibration/episode_{episode:06}.json");
        let Some(path) = self.stored_file(&rel, confine::MAX_METADATA_BYTES)? else {
            return Err(DatasetError::MissingCalibration {
                path: self.root.join(rel),
                episode,
            });
        };
        let v = read_json(&path)?;
        let cam = v.get(key).ok_or_else(|| DatasetError::Field {
            path: path.clone(),
            episode,
            field: key.into(),
            message: "no calibration for this camera".into(),
        })?;
        Camera::from_json_str(&cam.to_string(), &path.display().to_string()).map_err(|e| {
            DatasetError::Field {
                path: path.clone(),
                episode,
                field: key.into(),
                message: e.to_string(),
            }
        })
    }
}

/// `root` joined with `rel`, the path the template `field` (`template`) of
/// `meta/info.json` formats to, checked to be relative without `..` (the
/// files are checked when read, in [`LeRobotDataset::read_episode`] and
/// [`LeRobotDataset::read_video`]).
fn confined_join(
    root: &Path,
    field: &str,
    template: &str,
    rel: String,
) -> Result<PathBuf, DatasetError> {
    confine::check_relative(root, &rel).map_err(|e| {
        meta_err(
            &root.join("meta/info.json"),
            format!("field \"{field}\" ({template:?}) formats to {e}"),
        )
    })?;
    Ok(root.join(rel))
}
