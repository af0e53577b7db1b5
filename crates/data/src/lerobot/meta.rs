//! The records the reader and writer share: frame rows, the episode index
//! entries, the layout version and the path templates.

use std::collections::BTreeMap;
use std::path::PathBuf;

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

/// The widest field a path template may pad to (`{name:0Nd}`): a width
/// read from `meta/info.json` is allocated when the template is filled.
pub const MAX_TEMPLATE_WIDTH: usize = 32;

/// Checks the widths of a path template's fields (`{name:0Nd}`): each at
/// most [`MAX_TEMPLATE_WIDTH`]. The error says which field and width.
pub fn check_template_widths(template: &str) -> Result<(), String> {
    let mut rest = template;
    while let Some(open) = rest.find('{') {
        let Some(close) = rest[open..].find('}') else {
            break;
        };
        let inner = &rest[open + 1..open + close];
        if let Some((name, spec)) = inner.split_once(':') {
            let digits = spec.trim_start_matches('0').trim_end_matches('d');
            if !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit()) {
                let ok = digits
                    .parse::<usize>()
                    .is_ok_and(|w| w <= MAX_TEMPLATE_WIDTH);
                if !ok {
                    return Err(format!(
                        "field {{{name}}} has width {digits}: expected at most {MAX_TEMPLATE_WIDTH}"
                    ));
                }
            }
        }
        rest = &rest[open + close + 1..];
    }
    Ok(())
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
