//! Training logs in TensorBoard's format: an event file
//! (`events.out.tfevents.<seconds>.<host>.bridgev2w`) of TFRecord records,
//! each a length, its masked CRC-32C, an `Event` protocol buffer and the
//! buffer's masked CRC-32C. An event carries the wall time, the step and a
//! `Summary` of scalar values (`simple_value`) or PNG images; the first
//! one names the file version (`brain.Event:2`). The protocol buffers are
//! written by hand: four messages, a few fields each (field numbers from
//! TensorFlow's `event.proto` and `summary.proto`).

use crate::{Result, TrainError};
use std::io::Write;
use std::path::{Path, PathBuf};

/// CRC-32C (Castagnoli) of `data`, bitwise (records are small and few).
fn crc32c(data: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in data {
        crc ^= u32::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0x82F6_3B78
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

/// TFRecord's masked CRC: rotated right by 15 bits, plus a constant.
fn masked_crc(data: &[u8]) -> u32 {
    let c = crc32c(data);
    c.rotate_right(15).wrapping_add(0xA282_EAD8)
}

fn varint(out: &mut Vec<u8>, mut v: u64) {
    while v >= 0x80 {
        out.push((v as u8) | 0x80);
        v >>= 7;
    }
    out.push(v as u8);
}

/// A field key: `(number << 3) | wire type`.
fn key(out: &mut Vec<u8>, field: u64, wire: u64) {
    varint(out, (field << 3) | wire);
}

fn bytes_field(out: &mut Vec<u8>, field: u64, bytes: &[u8]) {
    key(out, field, 2);
    varint(out, bytes.len() as u64);
    out.extend_from_slice(bytes);
}

/// One value of a `Summary`.
#[derive(Debug, Clone, PartialEq)]
pub enum SummaryValue {
    /// A scalar (`simple_value`, a float).
    Scalar(f64),
    /// A PNG image of `width` x `height` RGB pixels.
    Png {
        /// Pixels across.
        width: u32,
        /// Pixels down.
        height: u32,
        /// The encoded PNG.
        png: Vec<u8>,
    },
}

/// `Event { wall_time = 1; step = 2; file_version = 3 | summary = 5 }`.
fn event(wall_time: f64, step: i64, body: EventBody<'_>) -> Vec<u8> {
    let mut e = Vec::new();
    key(&mut e, 1, 1);
    e.extend_from_slice(&wall_time.to_le_bytes());
    key(&mut e, 2, 0);
    varint(&mut e, step as u64);
    match body {
        EventBody::FileVersion(v) => bytes_field(&mut e, 3, v.as_bytes()),
        EventBody::Summary(values) => {
            let mut summary = Vec::new();
            for (tag, value) in values {
                // Summary.Value { tag = 1; simple_value = 2 | image = 4 }
                let mut v = Vec::new();
                bytes_field(&mut v, 1, tag.as_bytes());
                match value {
                    SummaryValue::Scalar(x) => {
                        key(&mut v, 2, 5);
                        v.extend_from_slice(&(*x as f32).to_le_bytes());
                    }
                    SummaryValue::Png { width, height, png } => {
                        // Summary.Image { height = 1; width = 2; colorspace = 3; encoded = 4 }
                        let mut img = Vec::new();
                        key(&mut img, 1, 0);
                        varint(&mut img, u64::from(*height));
                        key(&mut img, 2, 0);
                        varint(&mut img, u64::from(*width));
                        key(&mut img, 3, 0);
                        varint(&mut img, 3); // RGB
                        bytes_field(&mut img, 4, png);
                        bytes_field(&mut v, 4, &img);
                    }
                }
                bytes_field(&mut summary, 1, &v);
            }
            bytes_field(&mut e, 5, &summary);
        }
    }
    e
}

enum EventBody<'a> {
    FileVersion(&'a str),
    Summary(&'a [(String, SummaryValue)]),
}

/// Appends events to one TensorBoard event file (rank 0 of a run).
#[derive(Debug)]
pub struct EventWriter {
    path: PathBuf,
    file: std::fs::File,
}

fn wall_time() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs_f64())
        .unwrap_or(0.0)
}

impl EventWriter {
    /// A new event file in `dir` (created), named as TensorFlow names them,
    /// starting with the file-version event. A resumed run starts a new
    /// file; TensorBoard reads every file of the folder.
    pub fn create(dir: &Path) -> Result<Self> {
        let err = |p: &Path, e: std::io::Error| {
            TrainError::input(p.display().to_string(), format!("cannot write: {e}"))
        };
        std::fs::create_dir_all(dir).map_err(|e| err(dir, e))?;
        let host = std::fs::read_to_string("/etc/hostname")
            .map(|h| h.trim().to_string())
            .ok()
            .filter(|h| !h.is_empty() && !h.contains('/'))
            .unwrap_or_else(|| "localhost".into());
        let t = wall_time();
        let mut n = 0;
        let path = loop {
            let p = dir.join(format!(
                "events.out.tfevents.{}.{host}.bridgev2w{}",
                t as u64,
                if n == 0 {
                    String::new()
                } else {
                    format!(".{n}")
                }
            ));
            if !p.exists() {
                break p;
            }
            n += 1;
        };
        let file = std::fs::OpenOptions::new()
            .create_new(true)
            .write(true)
            .open(&path)
            .map_err(|e| err(&path, e))?;
        let mut w = Self { path, file };
        w.record(&event(t, 0, EventBody::FileVersion("brain.Event:2")))?;
        Ok(w)
    }

    /// The event file.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn record(&mut self, data: &[u8]) -> Result<()> {
        let len = (data.len() as u64).to_le_bytes();
        let mut rec = Vec::with_capacity(data.len() + 16);
        rec.extend_from_slice(&len);
        rec.extend_from_slice(&masked_crc(&len).to_le_bytes());
        rec.extend_from_slice(data);
        rec.extend_from_slice(&masked_crc(data).to_le_bytes());
        self.file
            .write_all(&rec)
            .and_then(|()| self.file.flush())
            .map_err(|e| {
                TrainError::input(
                    self.path.display().to_string(),
                    format!("cannot write: {e}"),
                )
            })
    }

    /// One event at `step` holding `values` (tag, value).
    pub fn write(&mut self, step: usize, values: &[(String, SummaryValue)]) -> Result<()> {
        self.record(&event(wall_time(), step as i64, EventBody::Summary(values)))
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn crc32c_and_varints_match_their_definitions() {
        // RFC 3720's check value of CRC-32C.
        assert_eq!(crc32c(b"123456789"), 0xE306_9283);
        let mut v = Vec::new();
        varint(&mut v, 300);
        assert_eq!(v, vec![0xAC, 0x02]);
    }

    #[test]
    fn records_are_framed_with_their_lengths_and_checksums() {
        let dir = tempfile::tempdir().unwrap();
        let mut w = EventWriter::create(dir.path()).unwrap();
        w.write(3, &[("loss".into(), SummaryValue::Scalar(0.5))])
            .unwrap();
        let bytes = std::fs::read(w.path()).unwrap();
        let mut pos = 0;
        let mut n = 0;
        while pos < bytes.len() {
            let len = u64::from_le_bytes(bytes[pos..pos + 8].try_into().unwrap()) as usize;
            let len_crc = u32::from_le_bytes(bytes[pos + 8..pos + 12].try_into().unwrap());
            assert_eq!(len_crc, masked_crc(&bytes[pos..pos + 8]));
            let data = &bytes[pos + 12..pos + 12 + len];
            let crc = u32::from_le_bytes(bytes[pos + 12 + len..pos + 16 + len].try_into().unwrap());
            assert_eq!(crc, masked_crc(data));
            pos += 16 + len;
            n += 1;
        }
        assert_eq!((n, pos), (2, bytes.len()));
        // A second writer in the same second gets a file of its own.
        let w2 = EventWriter::create(dir.path()).unwrap();
        assert_ne!(w2.path(), w.path());
    }
}
