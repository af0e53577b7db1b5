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
//! - `meta/tasks.parquet`: `task_index`, and the task strings as the pandas
//!   index (`__index_level_0__`), as LeRobot writes it.
//! - `meta/stats.json`: LeRobot's normalisation statistics of every feature.
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

mod columns;
mod error;
mod files;
mod meta;
mod reader;
mod shapes;
mod stats;
mod writer;

pub use error::DatasetError;
pub use meta::{
    check_template_widths, format_template, EpisodeData, EpisodeInfo, FrameRow, Version, VideoRef,
    MAX_TEMPLATE_WIDTH,
};
pub use reader::{read_frames_parquet, LeRobotDataset, StoredMasks};
pub use writer::{write_frames_parquet, LeRobotV3Writer, WriterEpisode};
