//! Writing the LeRobot v3.0 layout: frame parquet files and the streaming
//! dataset writer (video, tasks, episode index, `info.json`, and the
//! synthetic masks and camera calibration).

use super::error::{arrow_err, io_err, meta_err, pq_err};
use super::meta::{format_template, FrameRow};
use super::DatasetError;
use arrow_array::builder::{ListBuilder, StringBuilder};
use arrow_array::types::Float32Type;
use arrow_array::{
    ArrayRef, Float32Array, Float64Array, Int64Array, ListArray, RecordBatch, StringArray,
};
use arrow_schema::{DataType, Field, Schema};
use bridgev2w_embodiment::camera::Camera;
use bridgev2w_io::npy::write_npy;
use parquet::arrow::ArrowWriter;
use parquet::basic::Compression;
use parquet::file::properties::WriterProperties;
use serde_json::{json, Value};
use std::path::{Path, PathBuf};
use std::sync::Arc;

/// A written episode: `(index, length, task, first global frame, split)`.
type EpisodeRecord = (i64, usize, String, i64, Option<String>);

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
    /// Link labels `[T, H, W]` (0 = background, else the link's label; robot
    /// pixels exactly the masks'), written to `labels/episode_XXXXXX.npy`.
    pub labels: Option<&'a [Vec<u8>]>,
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
    pixels: super::stats::PixelStats,
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
        // The key becomes a folder name (`videos/{video_key}/`): a plain name only.
        bridgev2w_io::confine::check_name(video_key)
            .map_err(|e| meta_err(root, format!("video key {e}")))?;
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
            pixels: super::stats::PixelStats::default(),
            tasks: Vec::new(),
            episodes: Vec::new(),
        })
    }

    /// Writes per-frame `[H, W]` maps (masks or labels) as
    /// `FIELD/episode_XXXXXX.npy`, uint8 `[T, H, W]`.
    fn write_frames_npy(
        &self,
        field: &str,
        index: i64,
        frames: &[Vec<u8>],
    ) -> Result<(), DatasetError> {
        let px = self.width * self.height;
        if let Some((f, m)) = frames.iter().enumerate().find(|(_, m)| m.len() != px) {
            return Err(DatasetError::Field {
                path: self.root.clone(),
                episode: index,
                field: field.into(),
                message: format!(
                    "frame {f} has {} values, the video {}x{} (WxH) has {px} pixels",
                    m.len(),
                    self.width,
                    self.height
                ),
            });
        }
        let path = self.root.join(format!("{field}/episode_{index:06}.npy"));
        if let Some(d) = path.parent() {
            std::fs::create_dir_all(d).map_err(io_err(d))?;
        }
        write_npy(
            &path,
            &[frames.len(), self.height, self.width],
            &frames.concat(),
        )
        .map_err(|e| meta_err(&path, e.to_string()))
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
            self.pixels.add(frame);
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
            self.write_frames_npy("masks", index, masks)?;
        }
        if let Some(labels) = ep.labels {
            self.write_frames_npy("labels", index, labels)?;
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
        self.write_data(&root)?;
        self.write_video(&root)?;
        self.write_tasks(&root)?;
        self.write_episodes(&root)?;
        self.write_stats(&root)?;
        self.write_info(&root, extra_info)?;
        Ok(root)
    }

    /// `data/chunk-000/file-000.parquet`: every frame row.
    fn write_data(&self, root: &Path) -> Result<(), DatasetError> {
        let data_path = root.join(format_template(
            DATA_TPL,
            &[("chunk_index", "0".into()), ("file_index", "0".into())],
        ));
        write_frames_parquet(&data_path, &self.rows)
    }

    /// `videos/<key>/chunk-000/file-000.mp4`: the encoded episodes.
    fn write_video(&self, root: &Path) -> Result<(), DatasetError> {
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
        std::fs::write(&vpath, bytes).map_err(io_err(&vpath))
    }

    /// `meta/stats.json`: LeRobot's normalisation statistics.
    fn write_stats(&self, root: &Path) -> Result<(), DatasetError> {
        let path = root.join("meta/stats.json");
        let stats = super::stats::stats_json(&self.rows, &self.video_key, &self.pixels);
        let text =
            serde_json::to_string_pretty(&stats).map_err(|e| meta_err(&path, e.to_string()))?;
        std::fs::write(&path, text).map_err(io_err(&path))
    }

    /// `meta/tasks.parquet`: the task strings by task index, as LeRobot
    /// writes it (a pandas frame indexed by the task string: the strings in
    /// `__index_level_0__`, named as the index in the `pandas` schema
    /// metadata, which `pandas.read_parquet` and so LeRobot read).
    fn write_tasks(&self, root: &Path) -> Result<(), DatasetError> {
        let tasks_path = root.join("meta/tasks.parquet");
        let pandas = json!({
            "index_columns": ["__index_level_0__"],
            "column_indexes": [{
                "name": null, "field_name": null, "pandas_type": "unicode",
                "numpy_type": "object", "metadata": {"encoding": "UTF-8"}
            }],
            "columns": [
                {"name": "task_index", "field_name": "task_index", "pandas_type": "int64",
                 "numpy_type": "int64", "metadata": null},
                {"name": null, "field_name": "__index_level_0__", "pandas_type": "unicode",
                 "numpy_type": "object", "metadata": null}
            ],
            "attributes": {},
            "creator": {"library": "bridgev2w", "version": env!("CARGO_PKG_VERSION")},
        });
        let schema = Arc::new(Schema::new_with_metadata(
            vec![
                Field::new("task_index", DataType::Int64, false),
                Field::new("__index_level_0__", DataType::Utf8, false),
            ],
            std::collections::HashMap::from([("pandas".to_string(), pandas.to_string())]),
        ));
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
        write_batch(&tasks_path, &batch)
    }

    /// `meta/episodes/chunk-000/file-000.parquet`: one row per episode.
    fn write_episodes(&self, root: &Path) -> Result<(), DatasetError> {
        let ep_path = root.join("meta/episodes/chunk-000/file-000.parquet");
        let fps = f64::from(self.fps);
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
        write_batch(&ep_path, &batch)
    }

    /// `meta/info.json`: [`Self::info_json`] with `extra_info`'s entries merged in.
    fn write_info(&self, root: &Path, extra_info: Value) -> Result<(), DatasetError> {
        let mut info = self.info_json();
        if let (Some(obj), Value::Object(extra)) = (info.as_object_mut(), extra_info) {
            for (k, v) in extra {
                obj.insert(k, v);
            }
        }
        let info_path = root.join("meta/info.json");
        let text =
            serde_json::to_string_pretty(&info).map_err(|e| meta_err(&info_path, e.to_string()))?;
        std::fs::write(&info_path, text).map_err(io_err(&info_path))
    }

    /// The `splits` of `info.json`: `all`, and each run of consecutive
    /// episodes of one split.
    fn splits(&self) -> serde_json::Map<String, Value> {
        let n = self.episodes.len();
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
        splits
    }

    /// The `info.json` of the written episodes (before `extra_info`).
    fn info_json(&self) -> Value {
        let n = self.episodes.len();
        let total_frames = self.rows.len();
        let splits = self.splits();
        let scalar = |dtype: &str| json!({"dtype": dtype, "shape": [1], "names": null});
        json!({
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
        })
    }
}
