//! `meta/stats.json` as LeRobot writes and expects it (its normalisation
//! statistics): for every feature `min`, `max`, `mean`, `std` (population),
//! `count` and the quantiles `q01`, `q10`, `q50`, `q90`, `q99`, one value per
//! dimension; for a video feature one value per channel, shaped `[3][1][1]`,
//! on pixel values scaled to `[0, 1]`, over every frame written.

use super::meta::FrameRow;
use serde_json::{json, Map, Value};

/// The quantiles LeRobot reports, with their keys.
const QUANTILES: [(&str, f64); 5] = [
    ("q01", 0.01),
    ("q10", 0.10),
    ("q50", 0.50),
    ("q90", 0.90),
    ("q99", 0.99),
];

/// Per-channel pixel statistics of a video feature, accumulated frame by
/// frame (a histogram per channel: exact min, max, mean, std and quantiles
/// at 1/255 resolution without keeping the frames).
#[derive(Debug, Clone)]
pub(crate) struct PixelStats {
    hist: [[u64; 256]; 3],
    frames: u64,
}

impl Default for PixelStats {
    fn default() -> Self {
        Self {
            hist: [[0; 256]; 3],
            frames: 0,
        }
    }
}

impl PixelStats {
    /// Adds one interleaved RGB8 frame.
    pub(crate) fn add(&mut self, rgb: &[u8]) {
        for px in rgb.chunks_exact(3) {
            for (c, &v) in px.iter().enumerate() {
                self.hist[c][usize::from(v)] += 1;
            }
        }
        self.frames += 1;
    }

    /// The feature's statistics, each value shaped `[[v]]` per channel.
    fn json(&self) -> Value {
        let per_channel = |f: &dyn Fn(&[u64; 256]) -> f64| -> Value {
            Value::Array(self.hist.iter().map(|h| json!([[f(h)]])).collect())
        };
        let total = |h: &[u64; 256]| h.iter().sum::<u64>().max(1) as f64;
        let mean = |h: &[u64; 256]| {
            h.iter()
                .enumerate()
                .map(|(v, &n)| v as f64 / 255.0 * n as f64)
                .sum::<f64>()
                / total(h)
        };
        let std = |h: &[u64; 256]| {
            let m = mean(h);
            (h.iter()
                .enumerate()
                .map(|(v, &n)| (v as f64 / 255.0 - m).powi(2) * n as f64)
                .sum::<f64>()
                / total(h))
            .sqrt()
        };
        let quantile = |h: &[u64; 256], q: f64| {
            let target = q * (total(h) - 1.0);
            let mut seen = 0u64;
            for (v, &n) in h.iter().enumerate() {
                seen += n;
                if n > 0 && seen as f64 > target {
                    return v as f64 / 255.0;
                }
            }
            1.0
        };
        let min = |h: &[u64; 256]| h.iter().position(|&n| n > 0).unwrap_or(0) as f64 / 255.0;
        let max = |h: &[u64; 256]| h.iter().rposition(|&n| n > 0).unwrap_or(0) as f64 / 255.0;
        let mut m = Map::new();
        m.insert("min".into(), per_channel(&min));
        m.insert("max".into(), per_channel(&max));
        m.insert("mean".into(), per_channel(&mean));
        m.insert("std".into(), per_channel(&std));
        m.insert("count".into(), json!([self.frames]));
        for (key, q) in QUANTILES {
            m.insert(key.into(), per_channel(&|h| quantile(h, q)));
        }
        Value::Object(m)
    }
}

/// The statistics of the columns of `values` (rows of equal length).
fn vector_json(values: &[Vec<f64>]) -> Value {
    let dims = values.first().map_or(0, Vec::len);
    let n = values.len();
    let mut columns: Vec<Vec<f64>> = (0..dims)
        .map(|d| values.iter().map(|r| r[d]).collect())
        .collect();
    for c in &mut columns {
        c.sort_by(f64::total_cmp);
    }
    let each = |f: &dyn Fn(&[f64]) -> f64| -> Value {
        Value::Array(columns.iter().map(|c| json!(f(c))).collect())
    };
    let mean = |c: &[f64]| c.iter().sum::<f64>() / c.len().max(1) as f64;
    let mut m = Map::new();
    m.insert("min".into(), each(&|c| c.first().copied().unwrap_or(0.0)));
    m.insert("max".into(), each(&|c| c.last().copied().unwrap_or(0.0)));
    m.insert("mean".into(), each(&mean));
    m.insert(
        "std".into(),
        each(&|c| {
            let mu = mean(c);
            (c.iter().map(|v| (v - mu).powi(2)).sum::<f64>() / c.len().max(1) as f64).sqrt()
        }),
    );
    m.insert("count".into(), json!([n]));
    for (key, q) in QUANTILES {
        // Linear interpolation between the order statistics around q (n - 1).
        m.insert(
            key.into(),
            each(&|c| {
                if c.is_empty() {
                    return 0.0;
                }
                let pos = q * (c.len() - 1) as f64;
                let (lo, hi) = (pos.floor() as usize, pos.ceil() as usize);
                c[lo] + (c[hi] - c[lo]) * (pos - lo as f64)
            }),
        );
    }
    Value::Object(m)
}

/// `meta/stats.json` of the frame rows and the video feature `video_key`.
pub(crate) fn stats_json(rows: &[FrameRow], video_key: &str, pixels: &PixelStats) -> Value {
    let column =
        |f: &dyn Fn(&FrameRow) -> Vec<f64>| -> Vec<Vec<f64>> { rows.iter().map(f).collect() };
    let mut m = Map::new();
    m.insert(
        "observation.state".into(),
        vector_json(&column(&|r| {
            r.state.iter().map(|&v| f64::from(v)).collect()
        })),
    );
    m.insert(
        "action".into(),
        vector_json(&column(&|r| {
            r.action.iter().map(|&v| f64::from(v)).collect()
        })),
    );
    m.insert(
        "timestamp".into(),
        vector_json(&column(&|r| vec![f64::from(r.timestamp)])),
    );
    for (key, get) in [
        (
            "frame_index",
            (|r: &FrameRow| r.frame_index) as fn(&FrameRow) -> i64,
        ),
        ("episode_index", |r| r.episode_index),
        ("index", |r| r.index),
        ("task_index", |r| r.task_index),
    ] {
        m.insert(key.into(), vector_json(&column(&|r| vec![get(r) as f64])));
    }
    m.insert(video_key.into(), pixels.json());
    Value::Object(m)
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn vector_and_pixel_statistics_match_closed_forms() {
        let v = vector_json(&[
            vec![1.0, 10.0],
            vec![2.0, 10.0],
            vec![3.0, 10.0],
            vec![4.0, 10.0],
        ]);
        assert_eq!(v["min"], json!([1.0, 10.0]));
        assert_eq!(v["max"], json!([4.0, 10.0]));
        assert_eq!(v["mean"], json!([2.5, 10.0]));
        let std = v["std"][0].as_f64().unwrap();
        assert!((std - 1.25f64.sqrt()).abs() < 1e-12);
        assert_eq!(v["q50"], json!([2.5, 10.0]));
        assert_eq!(v["count"], json!([4]));
        let mut p = PixelStats::default();
        p.add(&[0, 255, 51, 255, 255, 51]);
        let j = p.json();
        assert_eq!(j["mean"], json!([[[0.5]], [[1.0]], [[0.2]]]));
        assert_eq!(j["std"][0], json!([[0.5]]));
        assert_eq!(j["min"][0], json!([[0.0]]));
        assert_eq!(j["max"][0], json!([[1.0]]));
        assert_eq!(j["count"], json!([1]));
    }
}
