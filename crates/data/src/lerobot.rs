//! LeRobot dataset layouts: a v3.0 writer and a v3.0/v2.1 reader.
//!
//! v3.0 (written here):
//! - `meta/info.json`: `codebase_version` "v3.0", `fps`, `features`,
//!   `data_path`/`video_path` templates, `chunks_size`, totals, `splits`.
//! - `meta/episodes/chunk-000/file-000.parquet`: one row per episode
//!   (`episode_index`, `tasks`, `length`, `dataset_from_index`/`to_index`,
//!   `data/chunk_index`, `data/file_index`, and per video key
//!   `videos/<key>/chunk_index`, `file_index`, `from_timestamp`,
//!   `to_timestamp`), plus the synthetic `split` column.
//! - `meta/tasks.parquet`: `task_index`, `task`.
//! - `data/chunk-000/file-000.parquet`: `index`, `episode_index`,
//!   `frame_index`, `timestamp`, `task_index`, `observation.state`, `action`.
//! - `videos/<key>/chunk-000/file-000.mp4`: H.264, episodes concatenated.
//!
//! Synthetic extras: `meta/calibration/episode_XXXXXX.json` (per video key:
//! intrinsics + `world_from_camera`, the embodiment crate's camera JSON),
//! `masks/episode_XXXXXX.npy` (uint8 `[T, H, W]`, 0/1) and `meta/synth.json`
//! (configuration, split definitions, per-episode split/scene/camera).
//!
//! v2.1 (read): `meta/info.json` (`codebase_version` "v2.1"),
//! `meta/episodes.jsonl`, `meta/tasks.jsonl`,
//! `data/chunk-XXX/episode_XXXXXX.parquet`,
//! `videos/chunk-XXX/<key>/episode_XXXXXX.mp4`.

use crate::video::{decode_mp4, VideoError};
use arrow_array::builder::{ListBuilder, StringBuilder};
use arrow_array::types::Float32Type;
use arrow_array::{
    Array, ArrayRef, FixedSizeListArray, Float32Array, Float64Array, Int32Array, Int64Array,
    LargeListArray, LargeStringArray, ListArray, RecordBatch, StringArray,
};
use arrow_schema::{ArrowError, DataType, Field, Schema};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_embodiment::npy::{read_npy, write_npy};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::properties::WriterProperties;
use serde_json::{json, Value};
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// Dataset errors; each names the file and, where known, the episode and field.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// I/O failure.
    #[error("{path}: {source}")]
    Io {
        /// File.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// Bad JSON / JSONL / metadata.
    #[error("{path}: {message}")]
    Meta {
        /// File.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The parquet file is corrupt or unreadable.
    #[error("{path}: corrupt or unreadable parquet: {message}")]
    Parquet {
        /// File.
        path: PathBuf,
        /// Cause.
        message: String,
    },
    /// A column is missing or has the wrong type or values.
    #[error("{path}: episode {episode}, field \"{field}\": {message}")]
    Field {
        /// File.
        path: PathBuf,
        /// Episode index (or -1 when not tied to one episode).
        episode: i64,
        /// Column / field name.
        field: String,
        /// What is wrong.
        message: String,
    },
    /// A synthetic episode has no camera calibration.
    #[error("{path}: missing camera calibration of episode {episode}")]
    MissingCalibration {
        /// Expected file.
        path: PathBuf,
        /// Episode index.
        episode: i64,
    },
    /// A video could not be read.
    #[error("episode {episode}, video \"{key}\": {source}")]
    Video {
        /// Episode index.
        episode: i64,
        /// Video key.
        key: String,
        /// Cause (names the file).
        source: VideoError,
    },
    /// The layout version is not supported.
    #[error("{path}: unsupported LeRobot codebase_version \"{version}\" (supported: v2.1, v3.0)")]
    Version {
        /// `meta/info.json`.
        path: PathBuf,
        /// The version found.
        version: String,
    },
}

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> DatasetError + '_ {
    move |source| DatasetError::Io {
        path: path.to_path_buf(),
        source,
    }
}

fn pq_err(path: &Path) -> impl Fn(parquet::errors::ParquetError) -> DatasetError + '_ {
    move |e| DatasetError::Parquet {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

fn arrow_err(path: &Path) -> impl Fn(ArrowError) -> DatasetError + '_ {
    move |e| DatasetError::Parquet {
        path: path.to_path_buf(),
        message: e.to_string(),
    }
}

/// Per video key: `(key, chunk_index, file_index, from_timestamp, to_timestamp)` columns.
type VideoColumns = (String, Vec<i64>, Vec<i64>, Vec<f64>, Vec<f64>);

/// A written episode: `(index, length, task, first global frame, split)`.
type EpisodeRecord = (i64, usize, String, i64, Option<String>);

/// One frame row of `data/*.parquet`.
#[derive(Debug, Clone, PartialEq)]
pub struct FrameRow {
    /// Global frame index.
    pub index: i64,
    /// Episode index.
    pub episode_index: i64,
    /// Frame index within the episode.
    pub frame_index: i64,
    /// Seconds since the episode start.
    pub timestamp: f32,
    /// Task index.
    pub task_index: i64,
    /// `observation.state`.
    pub state: Vec<f32>,
    /// `action`.
    pub action: Vec<f32>,
}

fn f32_list(rows: impl Iterator<Item = Vec<f32>>) -> ArrayRef {
    Arc::new(ListArray::from_iter_primitive::<Float32Type, _, _>(
        rows.map(|r| Some(r.into_iter().map(Some))),
    ))
}

fn write_batch(path: &Path, batch: &RecordBatch) -> Result<(), DatasetError> {
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
    }
    let file = std::fs::File::create(path).map_err(io_err(path))?;
    let props = WriterProperties::builder()
        .set_compression(Compression::SNAPPY)
        .build();
    let mut w = ArrowWriter::try_new(file, batch.schema(), Some(props)).map_err(pq_err(path))?;
    w.write(batch).map_err(pq_err(path))?;
    w.close().map_err(pq_err(path))?;
    Ok(())
}

/// Writes frame rows as a LeRobot data parquet file.
pub fn write_frames_parquet(path: &Path, rows: &[FrameRow]) -> Result<(), DatasetError> {
    let list = |name: &str| {
        Field::new(
            name,
            DataType::List(Arc::new(Field::new("item", DataType::Float32, true))),
            true,
        )
    };
    let schema = Arc::new(Schema::new(vec![
        list("observation.state"),
        list("action"),
        Field::new("timestamp", DataType::Float32, false),
        Field::new("frame_index", DataType::Int64, false),
        Field::new("episode_index", DataType::Int64, false),
        Field::new("index", DataType::Int64, false),
        Field::new("task_index", DataType::Int64, false),
    ]));
    let i64s = |f: &dyn Fn(&FrameRow) -> i64| -> ArrayRef {
        Arc::new(Int64Array::from(rows.iter().map(f).collect::<Vec<_>>()))
    };
    let batch = RecordBatch::try_new(
        schema,
        vec![
            f32_list(rows.iter().map(|r| r.state.clone())),
            f32_list(rows.iter().map(|r| r.action.clone())),
            Arc::new(Float32Array::from(
                rows.iter().map(|r| r.timestamp).collect::<Vec<_>>(),
            )),
            i64s(&|r| r.frame_index),
            i64s(&|r| r.episode_index),
            i64s(&|r| r.index),
            i64s(&|r| r.task_index),
        ],
    )
    .map_err(arrow_err(path))?;
    write_batch(path, &batch)
}

fn read_batches(path: &Path) -> Result<Vec<RecordBatch>, DatasetError> {
    let file = std::fs::File::open(path).map_err(io_err(path))?;
    let file_len = file.metadata().map_err(io_err(path))?.len();
    // The parquet decoder asserts things of the data it reads (a dictionary
    // page before dictionary-encoded pages, ...): a corrupt file can panic it.
    bridgev2w_embodiment::quiet_panic::catch_quiet(|| {
        let builder = ParquetRecordBatchReaderBuilder::try_new(file).map_err(pq_err(path))?;
        check_column_chunks(path, builder.metadata(), file_len)?;
        let reader = builder.build().map_err(pq_err(path))?;
        reader
            .collect::<Result<Vec<_>, _>>()
            .map_err(arrow_err(path))
    })
    .unwrap_or_else(|panic| {
        Err(DatasetError::Parquet {
            path: path.to_path_buf(),
            message: format!("the parquet reader failed on corrupt data: {panic}"),
        })
    })
}

/// Every column chunk of the footer must lie inside the file: the parquet
/// reader panics on a negative offset or size (`ColumnChunkMetaData::byte_range`).
fn check_column_chunks(
    path: &Path,
    meta: &parquet::file::metadata::ParquetMetaData,
    file_len: u64,
) -> Result<(), DatasetError> {
    for (g, group) in meta.row_groups().iter().enumerate() {
        for c in group.columns() {
            let start = c.dictionary_page_offset().unwrap_or(c.data_page_offset());
            let len = c.compressed_size();
            let inside = start >= 0
                && len >= 0
                && c.data_page_offset() >= 0
                && (start as u64)
                    .checked_add(len as u64)
                    .is_some_and(|end| end <= file_len);
            if !inside {
                return Err(DatasetError::Parquet {
                    path: path.to_path_buf(),
                    message: format!(
                        "row group {g}, column {:?}: bytes {start}..+{len} lie outside the \
                         file's {file_len} bytes (a corrupt footer)",
                        c.column_path().string()
                    ),
                });
            }
        }
    }
    Ok(())
}

/// Typed access to the columns of parquet batches, with errors naming the file and field.
struct Columns<'a> {
    path: &'a Path,
    batches: &'a [RecordBatch],
}

impl Columns<'_> {
    fn field_err(&self, field: &str, episode: i64, message: impl Into<String>) -> DatasetError {
        DatasetError::Field {
            path: self.path.to_path_buf(),
            episode,
            field: field.into(),
            message: message.into(),
        }
    }

    fn has(&self, name: &str) -> bool {
        self.batches
            .first()
            .is_some_and(|b| b.column_by_name(name).is_some())
    }

    fn columns(&self, name: &str) -> Result<Vec<&ArrayRef>, DatasetError> {
        self.batches
            .iter()
            .map(|b| {
                b.column_by_name(name)
                    .ok_or_else(|| self.field_err(name, -1, "column is missing"))
            })
            .collect()
    }

    fn i64s(&self, name: &str) -> Result<Vec<i64>, DatasetError> {
        let mut out = Vec::new();
        for c in self.columns(name)? {
            if let Some(a) = c.as_any().downcast_ref::<Int64Array>() {
                out.extend(a.iter().map(|v| v.unwrap_or(i64::MIN)));
            } else if let Some(a) = c.as_any().downcast_ref::<Int32Array>() {
                out.extend(a.iter().map(|v| v.map_or(i64::MIN, i64::from)));
            } else {
                return Err(self.field_err(
                    name,
                    -1,
                    format!("expected int64, found {}", c.data_type()),
                ));
            }
        }
        if out.contains(&i64::MIN) {
            return Err(self.field_err(name, -1, "null value"));
        }
        Ok(out)
    }

    fn f64s(&self, name: &str) -> Result<Vec<f64>, DatasetError> {
        let mut out = Vec::new();
        for c in self.columns(name)? {
            if let Some(a) = c.as_any().downcast_ref::<Float32Array>() {
                out.extend(a.iter().map(|v| v.map_or(f64::NAN, f64::from)));
            } else if let Some(a) = c.as_any().downcast_ref::<Float64Array>() {
                out.extend(a.iter().map(|v| v.unwrap_or(f64::NAN)));
            } else {
                return Err(self.field_err(
                    name,
                    -1,
                    format!("expected float, found {}", c.data_type()),
                ));
            }
        }
        Ok(out)
    }

    fn strings(&self, name: &str) -> Result<Vec<String>, DatasetError> {
        let mut out = Vec::new();
        for c in self.columns(name)? {
            if let Some(a) = c.as_any().downcast_ref::<StringArray>() {
                out.extend(a.iter().map(|v| v.unwrap_or_default().to_string()));
            } else if let Some(a) = c.as_any().downcast_ref::<LargeStringArray>() {
                out.extend(a.iter().map(|v| v.unwrap_or_default().to_string()));
            } else {
                return Err(self.field_err(
                    name,
                    -1,
                    format!("expected string, found {}", c.data_type()),
                ));
            }
        }
        Ok(out)
    }

    fn string_lists(&self, name: &str) -> Result<Vec<Vec<String>>, DatasetError> {
        let mut out = Vec::new();
        for c in self.columns(name)? {
            let Some(a) = c.as_any().downcast_ref::<ListArray>() else {
                return Err(self.field_err(
                    name,
                    -1,
                    format!("expected list<string>, found {}", c.data_type()),
                ));
            };
            for i in 0..a.len() {
                let v = a.value(i);
                let s = v
                    .as_any()
                    .downcast_ref::<StringArray>()
                    .ok_or_else(|| self.field_err(name, -1, "list elements are not strings"))?;
                out.push(
                    s.iter()
                        .map(|x| x.unwrap_or_default().to_string())
                        .collect(),
                );
            }
        }
        Ok(out)
    }

    /// A list-of-float column (list, large list or fixed-size list of f32/f64).
    fn float_lists(&self, name: &str) -> Result<Vec<Vec<f32>>, DatasetError> {
        let mut out = Vec::new();
        let values = |v: ArrayRef| -> Result<Vec<f32>, DatasetError> {
            if let Some(a) = v.as_any().downcast_ref::<Float32Array>() {
                Ok(a.iter().map(|x| x.unwrap_or(f32::NAN)).collect())
            } else if let Some(a) = v.as_any().downcast_ref::<Float64Array>() {
                Ok(a.iter().map(|x| x.unwrap_or(f64::NAN) as f32).collect())
            } else {
                Err(self.field_err(
                    name,
                    -1,
                    format!("list elements are {}, expected float", v.data_type()),
                ))
            }
        };
        for c in self.columns(name)? {
            let any = c.as_any();
            if let Some(a) = any.downcast_ref::<ListArray>() {
                for i in 0..a.len() {
                    out.push(values(a.value(i))?);
                }
            } else if let Some(a) = any.downcast_ref::<LargeListArray>() {
                for i in 0..a.len() {
                    out.push(values(a.value(i))?);
                }
            } else if let Some(a) = any.downcast_ref::<FixedSizeListArray>() {
                for i in 0..a.len() {
                    out.push(values(a.value(i))?);
                }
            } else {
                return Err(self.field_err(
                    name,
                    -1,
                    format!("expected a list of floats, found {}", c.data_type()),
                ));
            }
        }
        Ok(out)
    }
}

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

/// Where one episode's video lies.
#[derive(Debug, Clone, PartialEq)]
pub struct VideoRef {
    /// MP4 file.
    pub path: PathBuf,
    /// First frame time in the file (seconds).
    pub from_timestamp_s: f64,
    /// End time in the file (seconds, exclusive).
    pub to_timestamp_s: f64,
}

/// One episode's entry in the episode index.
#[derive(Debug, Clone, PartialEq)]
pub struct EpisodeInfo {
    /// Episode index.
    pub episode_index: i64,
    /// Frames.
    pub length: usize,
    /// Task strings.
    pub tasks: Vec<String>,
    /// The data parquet holding its frames.
    pub data_path: PathBuf,
    /// Videos per key.
    pub videos: BTreeMap<String, VideoRef>,
    /// The synthetic split, when recorded.
    pub split: Option<String>,
}

/// Everything read for one episode.
#[derive(Debug, Clone)]
pub struct EpisodeData {
    /// Frame rows in frame order.
    pub frames: Vec<FrameRow>,
}

/// The layout version.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Version {
    /// LeRobot v2.1 (one parquet/MP4 per episode).
    V21,
    /// LeRobot v3.0 (concatenated files).
    V30,
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

/// Fills a Python-style template: `{name}` and `{name:03d}`.
pub fn format_template(template: &str, values: &[(&str, String)]) -> String {
    let mut out = String::new();
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        out.push_str(&rest[..open]);
        let Some(close) = rest[open..].find('}') else {
            out.push_str(&rest[open..]);
            return out;
        };
        let inner = &rest[open + 1..open + close];
        let (name, spec) = inner.split_once(':').unwrap_or((inner, ""));
        match values.iter().find(|(n, _)| *n == name) {
            Some((_, v)) => {
                let width: usize = spec
                    .trim_start_matches('0')
                    .trim_end_matches('d')
                    .parse()
                    .unwrap_or(0);
                if spec.starts_with('0') && v.len() < width {
                    out.push_str(&"0".repeat(width - v.len()));
                }
                out.push_str(v);
            }
            None => out.push_str(&rest[open..=open + close]),
        }
        rest = &rest[open + close + 1..];
    }
    out.push_str(rest);
    out
}

fn read_json(path: &Path) -> Result<Value, DatasetError> {
    let text = std::fs::read_to_string(path).map_err(io_err(path))?;
    serde_json::from_str(&text).map_err(|e| DatasetError::Meta {
        path: path.to_path_buf(),
        message: format!("invalid JSON: {e}"),
    })
}

fn meta_err(path: &Path, message: impl Into<String>) -> DatasetError {
    DatasetError::Meta {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

impl LeRobotDataset {
    /// Opens a v3.0 or v2.1 dataset (reads the metadata, not the frames).
    pub fn open(root: &Path) -> Result<Self, DatasetError> {
        let info_path = root.join("meta/info.json");
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
        let template = |key: &str| -> Result<String, DatasetError> {
            info.get(key)
                .and_then(Value::as_str)
                .map(str::to_string)
                .ok_or_else(|| meta_err(&info_path, format!("\"{key}\" is missing")))
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
        let tasks_path = root.join("meta/tasks.parquet");
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

        let dir = root.join("meta/episodes");
        let mut files = Vec::new();
        for chunk in std::fs::read_dir(&dir).map_err(io_err(&dir))? {
            let chunk = chunk.map_err(io_err(&dir))?.path();
            if chunk.is_dir() {
                for f in std::fs::read_dir(&chunk).map_err(io_err(&chunk))? {
                    let f = f.map_err(io_err(&chunk))?.path();
                    if f.extension().is_some_and(|e| e == "parquet") {
                        files.push(f);
                    }
                }
            }
        }
        files.sort();
        if files.is_empty() {
            return Err(meta_err(
                &dir,
                "no episode parquet files (meta/episodes/chunk-*/file-*.parquet)",
            ));
        }
        let mut episodes = Vec::new();
        for path in &files {
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
                let data_path = root.join(format_template(
                    data_tpl,
                    &[
                        ("chunk_index", dchunk[i].to_string()),
                        ("file_index", dfile[i].to_string()),
                    ],
                ));
                let mut videos = BTreeMap::new();
                for (key, vc, vf, from, to) in &vids {
                    videos.insert(
                        key.clone(),
                        VideoRef {
                            path: root.join(format_template(
                                video_tpl,
                                &[
                                    ("video_key", key.clone()),
                                    ("chunk_index", vc[i].to_string()),
                                    ("file_index", vf[i].to_string()),
                                ],
                            )),
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
            let path = root.join("meta").join(name);
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
            let data_path = root.join(format_template(
                data_tpl,
                &[
                    ("episode_chunk", chunk.clone()),
                    ("episode_index", ep.to_string()),
                ],
            ));
            let videos = video_keys
                .iter()
                .map(|key| {
                    (
                        key.clone(),
                        VideoRef {
                            path: root.join(format_template(
                                video_tpl,
                                &[
                                    ("episode_chunk", chunk.clone()),
                                    ("video_key", key.clone()),
                                    ("episode_index", ep.to_string()),
                                ],
                            )),
                            from_timestamp_s: 0.0,
                            to_timestamp_s: length as f64 / fps,
                        },
                    )
                })
                .collect();
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
        let mut frames: Vec<FrameRow> = read_frames_parquet(&info.data_path)?
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
        Ok(EpisodeData { frames })
    }

    /// Decodes an episode's frames of video `key` (interleaved RGB8), checking the frame count.
    pub fn read_video(&self, episode: i64, key: &str) -> Result<Vec<Vec<u8>>, DatasetError> {
        let info = self.episode(episode)?;
        let v = info.videos.get(key).ok_or_else(|| DatasetError::Field {
            path: self.root.join("meta"),
            episode,
            field: key.into(),
            message: format!("no such video key (keys: {})", self.video_keys.join(", ")),
        })?;
        let video = decode_mp4(&v.path).map_err(|source| DatasetError::Video {
            episode,
            key: key.into(),
            source,
        })?;
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

    /// The synthetic ground-truth masks of an episode: `(shape [T, H, W], 0/1 data)`.
    pub fn read_masks(&self, episode: i64) -> Result<(Vec<usize>, Vec<u8>), DatasetError> {
        let path = self.root.join(format!("masks/episode_{episode:06}.npy"));
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
        let masks = a.binary_mask().map_err(|m| meta_err(&path, m))?;
        Ok((a.shape, masks))
    }

    /// The synthetic camera calibration of an episode's video `key`.
    pub fn read_calibration(&self, episode: i64, key: &str) -> Result<Camera, DatasetError> {
        let path = self
            .root
            .join(format!("meta/calibration/episode_{episode:06}.json"));
        if !path.is_file() {
            return Err(DatasetError::MissingCalibration { path, episode });
        }
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

/// Per-episode record given to [`LeRobotV3Writer::add_episode`].
#[derive(Debug)]
pub struct WriterEpisode<'a> {
    /// Task string.
    pub task: &'a str,
    /// Split name (synthetic extra), if any.
    pub split: Option<&'a str>,
    /// `observation.state` per frame.
    pub states: Vec<Vec<f32>>,
    /// `action` per frame.
    pub actions: Vec<Vec<f32>>,
    /// RGB8 frames of the single video key.
    pub rgb: &'a [Vec<u8>],
    /// Masks `[T, H, W]` (0/1), written to `masks/episode_XXXXXX.npy`.
    pub masks: Option<&'a [Vec<u8>]>,
    /// Camera calibration (synthetic extra).
    pub camera: Option<&'a Camera>,
}

/// Streams episodes into the LeRobot v3.0 layout (one chunk, one file per
/// kind; the video is encoded as episodes arrive).
#[derive(Debug)]
pub struct LeRobotV3Writer {
    root: PathBuf,
    fps: u32,
    video_key: String,
    width: usize,
    height: usize,
    state_names: Vec<String>,
    action_names: Vec<String>,
    robot_type: String,
    video: crate::video::Mp4VideoWriter,
    rows: Vec<FrameRow>,
    tasks: Vec<String>,
    episodes: Vec<EpisodeRecord>,
}

const DATA_TPL: &str = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet";
const VIDEO_TPL: &str = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4";

impl LeRobotV3Writer {
    /// A writer into `root` (created) for one camera `video_key`
    /// (e.g. `observation.images.main`) of `width` x `height` at `fps`.
    pub fn new(
        root: &Path,
        robot_type: &str,
        fps: u32,
        video_key: &str,
        (width, height): (usize, usize),
        state_names: Vec<String>,
        action_names: Vec<String>,
    ) -> Result<Self, DatasetError> {
        std::fs::create_dir_all(root).map_err(io_err(root))?;
        let vpath = root.join(format_template(
            VIDEO_TPL,
            &[
                ("video_key", video_key.into()),
                ("chunk_index", "0".into()),
                ("file_index", "0".into()),
            ],
        ));
        let video =
            crate::video::Mp4VideoWriter::new(&vpath, width, height, fps).map_err(|source| {
                DatasetError::Video {
                    episode: -1,
                    key: video_key.into(),
                    source,
                }
            })?;
        Ok(Self {
            root: root.to_path_buf(),
            fps,
            video_key: video_key.into(),
            width,
            height,
            state_names,
            action_names,
            robot_type: robot_type.into(),
            video,
            rows: Vec::new(),
            tasks: Vec::new(),
            episodes: Vec::new(),
        })
    }

    /// Appends one episode; returns its index.
    pub fn add_episode(&mut self, ep: WriterEpisode<'_>) -> Result<i64, DatasetError> {
        let index = self.episodes.len() as i64;
        let t = ep.rgb.len();
        let bad = |field: &str, message: String| DatasetError::Field {
            path: self.root.clone(),
            episode: index,
            field: field.into(),
            message,
        };
        if ep.states.len() != t || ep.actions.len() != t || t == 0 {
            return Err(bad(
                "observation.state",
                format!(
                    "{} states, {} actions, {t} video frames: counts must match and be > 0",
                    ep.states.len(),
                    ep.actions.len()
                ),
            ));
        }
        let task_index = match self.tasks.iter().position(|x| x == ep.task) {
            Some(i) => i as i64,
            None => {
                self.tasks.push(ep.task.into());
                self.tasks.len() as i64 - 1
            }
        };
        let start = self.rows.len() as i64;
        for (f, frame) in ep.rgb.iter().enumerate() {
            self.video
                .push(frame, f == 0)
                .map_err(|source| DatasetError::Video {
                    episode: index,
                    key: self.video_key.clone(),
                    source,
                })?;
            self.rows.push(FrameRow {
                index: start + f as i64,
                episode_index: index,
                frame_index: f as i64,
                timestamp: (f as f64 / f64::from(self.fps)) as f32,
                task_index,
                state: ep.states[f].clone(),
                action: ep.actions[f].clone(),
            });
        }
        if let Some(masks) = ep.masks {
            let mut flat = Vec::with_capacity(t * self.width * self.height);
            for m in masks {
                flat.extend_from_slice(m);
            }
            let path = self.root.join(format!("masks/episode_{index:06}.npy"));
            if let Some(d) = path.parent() {
                std::fs::create_dir_all(d).map_err(io_err(d))?;
            }
            if flat.len() != masks.len() * self.width * self.height {
                return Err(bad(
                    "masks",
                    "mask frames do not match the video size".into(),
                ));
            }
            write_npy(&path, &[masks.len(), self.height, self.width], &flat)
                .map_err(|e| meta_err(&path, e.to_string()))?;
        }
        if let Some(cam) = ep.camera {
            let path = self
                .root
                .join(format!("meta/calibration/episode_{index:06}.json"));
            if let Some(d) = path.parent() {
                std::fs::create_dir_all(d).map_err(io_err(d))?;
            }
            let cam_json: Value =
                serde_json::from_str(&cam.to_json()).map_err(|e| meta_err(&path, e.to_string()))?;
            let text = serde_json::to_string_pretty(&json!({ self.video_key.clone(): cam_json }))
                .map_err(|e| meta_err(&path, e.to_string()))?;
            std::fs::write(&path, text).map_err(io_err(&path))?;
        }
        self.episodes.push((
            index,
            t,
            ep.task.to_string(),
            start,
            ep.split.map(str::to_string),
        ));
        Ok(index)
    }

    /// Writes the parquet files, the video and `meta/info.json`; `extra_info`
    /// entries are merged into `info.json`.
    pub fn finish(self, extra_info: Value) -> Result<PathBuf, DatasetError> {
        let root = self.root.clone();
        let data_path = root.join(format_template(
            DATA_TPL,
            &[("chunk_index", "0".into()), ("file_index", "0".into())],
        ));
        write_frames_parquet(&data_path, &self.rows)?;

        let vpath = root.join(format_template(
            VIDEO_TPL,
            &[
                ("video_key", self.video_key.clone()),
                ("chunk_index", "0".into()),
                ("file_index", "0".into()),
            ],
        ));
        let bytes = self
            .video
            .to_bytes()
            .map_err(|source| DatasetError::Video {
                episode: -1,
                key: self.video_key.clone(),
                source,
            })?;
        if let Some(d) = vpath.parent() {
            std::fs::create_dir_all(d).map_err(io_err(d))?;
        }
        std::fs::write(&vpath, bytes).map_err(io_err(&vpath))?;

        // Tasks.
        let tasks_path = root.join("meta/tasks.parquet");
        let schema = Arc::new(Schema::new(vec![
            Field::new("task_index", DataType::Int64, false),
            Field::new("task", DataType::Utf8, false),
        ]));
        let batch = RecordBatch::try_new(
            schema,
            vec![
                Arc::new(Int64Array::from(
                    (0..self.tasks.len() as i64).collect::<Vec<_>>(),
                )),
                Arc::new(StringArray::from(self.tasks.clone())),
            ],
        )
        .map_err(arrow_err(&tasks_path))?;
        write_batch(&tasks_path, &batch)?;

        // Episodes.
        let ep_path = root.join("meta/episodes/chunk-000/file-000.parquet");
        let fps = f64::from(self.fps);
        let n = self.episodes.len();
        let mut tasks_b = ListBuilder::new(StringBuilder::new());
        for e in &self.episodes {
            tasks_b.values().append_value(&e.2);
            tasks_b.append(true);
        }
        let i64col = |f: &dyn Fn(&EpisodeRecord) -> i64| -> ArrayRef {
            Arc::new(Int64Array::from(
                self.episodes.iter().map(f).collect::<Vec<_>>(),
            ))
        };
        let f64col = |f: &dyn Fn(&EpisodeRecord) -> f64| -> ArrayRef {
            Arc::new(Float64Array::from(
                self.episodes.iter().map(f).collect::<Vec<_>>(),
            ))
        };
        let vk = &self.video_key;
        let mut fields = vec![
            Field::new("episode_index", DataType::Int64, false),
            Field::new(
                "tasks",
                DataType::List(Arc::new(Field::new("item", DataType::Utf8, true))),
                true,
            ),
            Field::new("length", DataType::Int64, false),
            Field::new("data/chunk_index", DataType::Int64, false),
            Field::new("data/file_index", DataType::Int64, false),
            Field::new("dataset_from_index", DataType::Int64, false),
            Field::new("dataset_to_index", DataType::Int64, false),
            Field::new(format!("videos/{vk}/chunk_index"), DataType::Int64, false),
            Field::new(format!("videos/{vk}/file_index"), DataType::Int64, false),
            Field::new(
                format!("videos/{vk}/from_timestamp"),
                DataType::Float64,
                false,
            ),
            Field::new(
                format!("videos/{vk}/to_timestamp"),
                DataType::Float64,
                false,
            ),
            Field::new("meta/episodes/chunk_index", DataType::Int64, false),
            Field::new("meta/episodes/file_index", DataType::Int64, false),
        ];
        let mut cols: Vec<ArrayRef> = vec![
            i64col(&|e| e.0),
            Arc::new(tasks_b.finish()),
            i64col(&|e| e.1 as i64),
            i64col(&|_| 0),
            i64col(&|_| 0),
            i64col(&|e| e.3),
            i64col(&|e| e.3 + e.1 as i64),
            i64col(&|_| 0),
            i64col(&|_| 0),
            f64col(&|e| e.3 as f64 / fps),
            f64col(&|e| (e.3 + e.1 as i64) as f64 / fps),
            i64col(&|_| 0),
            i64col(&|_| 0),
        ];
        if self.episodes.iter().any(|e| e.4.is_some()) {
            fields.push(Field::new("split", DataType::Utf8, true));
            cols.push(Arc::new(StringArray::from(
                self.episodes
                    .iter()
                    .map(|e| e.4.clone())
                    .collect::<Vec<_>>(),
            )));
        }
        let batch = RecordBatch::try_new(Arc::new(Schema::new(fields)), cols)
            .map_err(arrow_err(&ep_path))?;
        write_batch(&ep_path, &batch)?;

        // info.json
        let total_frames = self.rows.len();
        let mut splits = serde_json::Map::new();
        splits.insert("all".into(), json!(format!("0:{n}")));
        let mut start = 0usize;
        while start < n {
            let s = &self.episodes[start].4;
            let mut end = start;
            while end < n && &self.episodes[end].4 == s {
                end += 1;
            }
            if let Some(name) = s {
                splits.insert(name.clone(), json!(format!("{start}:{end}")));
            }
            start = end;
        }
        let scalar = |dtype: &str| json!({"dtype": dtype, "shape": [1], "names": null});
        let mut info = json!({
            "codebase_version": "v3.0",
            "robot_type": self.robot_type,
            "total_episodes": n,
            "total_frames": total_frames,
            "total_tasks": self.tasks.len(),
            "chunks_size": 1000,
            "data_files_size_in_mb": 100,
            "video_files_size_in_mb": 500,
            "fps": self.fps,
            "splits": splits,
            "data_path": DATA_TPL,
            "video_path": VIDEO_TPL,
            "features": {
                self.video_key.clone(): {
                    "dtype": "video",
                    "shape": [self.height, self.width, 3],
                    "names": ["height", "width", "channels"],
                    "info": {
                        "video.height": self.height,
                        "video.width": self.width,
                        "video.codec": "h264",
                        "video.pix_fmt": "yuv420p",
                        "video.is_depth_map": false,
                        "video.fps": self.fps,
                        "video.channels": 3,
                        "has_audio": false
                    }
                },
                "observation.state": {"dtype": "float32", "shape": [self.state_names.len()], "names": self.state_names},
                "action": {"dtype": "float32", "shape": [self.action_names.len()], "names": self.action_names},
                "timestamp": scalar("float32"),
                "frame_index": scalar("int64"),
                "episode_index": scalar("int64"),
                "index": scalar("int64"),
                "task_index": scalar("int64"),
            }
        });
        if let (Some(obj), Value::Object(extra)) = (info.as_object_mut(), extra_info) {
            for (k, v) in extra {
                obj.insert(k, v);
            }
        }
        let info_path = root.join("meta/info.json");
        let text =
            serde_json::to_string_pretty(&info).map_err(|e| meta_err(&info_path, e.to_string()))?;
        std::fs::write(&info_path, text).map_err(io_err(&info_path))?;
        Ok(root)
    }
}
