//! NumPy `.npy` files: reading numeric arrays, writing arrays atomically.
//!
//! Reading accepts format versions 1.0-3.0, little- and big-endian integer,
//! float and bool dtypes, C or Fortran order; values are returned as `f64`
//! in C (row-major) order. Writing produces version 1.0 (2.0 when the header
//! needs it) files in C order, via a temporary file renamed into place so a
//! crash never leaves a half-written file.

use std::path::{Path, PathBuf};

/// Errors reading or writing `.npy` files; each names the file.
#[derive(Debug, thiserror::Error)]
pub enum NpyError {
    /// I/O failure.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
    /// The bytes are not a valid `.npy` file of a supported dtype.
    #[error("{path}: not a valid .npy file: {message}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
}

/// A numeric array read from `.npy`, values converted to `f64`, C order.
#[derive(Debug, Clone, PartialEq)]
pub struct NpyArray {
    /// Dimensions.
    pub shape: Vec<usize>,
    /// `shape.iter().product()` values, row-major.
    pub data: Vec<f64>,
    /// The file's dtype descriptor, e.g. `<f4`.
    pub descr: String,
}

impl NpyArray {
    /// The values as a binary mask, 0 (background) and 1 (robot): masks are
    /// stored 0/1 (this project's) or 0/255 (image tools'). Any other value
    /// is an error naming it.
    pub fn binary_mask(&self) -> Result<Vec<u8>, String> {
        let on = if self.data.contains(&255.0) {
            255.0
        } else {
            1.0
        };
        if let Some(v) = self.data.iter().find(|&&v| v != 0.0 && v != on) {
            return Err(format!(
                "a value of {v} next to {on}: expected binary masks, 0 (background) and 1 or 255 (robot)"
            ));
        }
        Ok(self.data.iter().map(|&v| u8::from(v != 0.0)).collect())
    }
}

/// Reads a `.npy` file.
pub fn read_npy(path: &Path) -> Result<NpyArray, NpyError> {
    let bytes = std::fs::read(path).map_err(|source| NpyError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse_npy(&bytes).map_err(|message| NpyError::Format {
        path: path.to_path_buf(),
        message,
    })
}

fn header_value<'a>(header: &'a str, key: &str) -> Result<&'a str, String> {
    let pat = format!("'{key}'");
    let at = header
        .find(&pat)
        .ok_or_else(|| format!("header has no '{key}' entry: {header}"))?;
    let rest = header[at + pat.len()..].trim_start();
    let rest = rest
        .strip_prefix(':')
        .ok_or_else(|| format!("header entry '{key}' has no ':'"))?
        .trim_start();
    Ok(rest)
}

/// Parses the bytes of a `.npy` file.
pub fn parse_npy(bytes: &[u8]) -> Result<NpyArray, String> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("missing the \\x93NUMPY magic".into());
    }
    let major = bytes[6];
    let (header_len, start): (usize, usize) = match major {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 => {
            if bytes.len() < 12 {
                return Err("truncated header".into());
            }
            (
                u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
                12,
            )
        }
        v => return Err(format!("unsupported format version {v}")),
    };
    let end = start
        .checked_add(header_len)
        .filter(|&e| e <= bytes.len())
        .ok_or("header length runs past the end of the file")?;
    let header = std::str::from_utf8(&bytes[start..end]).map_err(|_| "header is not text")?;

    let descr_v = header_value(header, "descr")?;
    let descr = descr_v
        .strip_prefix('\'')
        .and_then(|s| s.split('\'').next())
        .ok_or_else(|| format!("cannot read 'descr' in header: {header}"))?
        .to_string();
    let fortran = header_value(header, "fortran_order")?.starts_with("True");
    let shape_v = header_value(header, "shape")?;
    let inner = shape_v
        .strip_prefix('(')
        .and_then(|s| s.split(')').next())
        .ok_or_else(|| format!("cannot read 'shape' in header: {header}"))?;
    let shape = inner
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| format!("bad shape entry '{s}'"))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let count = shape
        .iter()
        .try_fold(1usize, |acc, &d| acc.checked_mul(d))
        .ok_or("shape overflows")?;

    let (endian, kind) = descr.split_at(1.min(descr.len()));
    let big = match endian {
        "<" | "|" | "=" => false,
        ">" => true,
        _ => return Err(format!("unsupported dtype '{descr}'")),
    };
    let size: usize = match kind {
        "f8" | "i8" | "u8" => 8,
        "f4" | "i4" | "u4" => 4,
        "f2" | "i2" | "u2" => 2,
        "i1" | "u1" | "b1" => 1,
        _ => {
            return Err(format!(
                "unsupported dtype '{descr}' (expected float, integer or bool)"
            ))
        }
    };
    let body = &bytes[end..];
    let needed = count.checked_mul(size).ok_or("shape overflows")?;
    if body.len() < needed {
        return Err(format!(
            "shape {shape:?} of '{descr}' needs {needed} data bytes but the file has {}",
            body.len()
        ));
    }
    let mut data = Vec::with_capacity(count);
    for chunk in body[..needed].chunks_exact(size) {
        let mut b = [0u8; 8];
        b[..size].copy_from_slice(chunk);
        if big {
            b[..size].reverse();
        }
        let v = match kind {
            "f8" => f64::from_le_bytes(b),
            "f4" => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            "f2" => f16_to_f64(u16::from_le_bytes([b[0], b[1]])),
            "i8" => i64::from_le_bytes(b) as f64,
            "u8" => u64::from_le_bytes(b) as f64,
            "i4" => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            "u4" => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            "i2" => i16::from_le_bytes([b[0], b[1]]) as f64,
            "u2" => u16::from_le_bytes([b[0], b[1]]) as f64,
            "i1" => b[0] as i8 as f64,
            _ => b[0] as f64,
        };
        data.push(v);
    }
    if fortran && shape.len() > 1 {
        // Column-major -> row-major.
        let mut c = vec![0.0; count];
        let mut strides_f = vec![1usize; shape.len()];
        for k in 1..shape.len() {
            strides_f[k] = strides_f[k - 1] * shape[k - 1];
        }
        let mut idx = vec![0usize; shape.len()];
        for slot in c.iter_mut() {
            let off: usize = idx.iter().zip(&strides_f).map(|(i, s)| i * s).sum();
            *slot = data[off];
            for k in (0..shape.len()).rev() {
                idx[k] += 1;
                if idx[k] < shape[k] {
                    break;
                }
                idx[k] = 0;
            }
        }
        data = c;
    }
    Ok(NpyArray { shape, data, descr })
}

fn f16_to_f64(h: u16) -> f64 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = ((h >> 10) & 0x1f) as i32;
    let frac = (h & 0x3ff) as f64;
    match exp {
        0 => sign * frac * 2f64.powi(-24),
        31 if frac == 0.0 => sign * f64::INFINITY,
        31 => f64::NAN,
        e => sign * (1.0 + frac / 1024.0) * 2f64.powi(e - 15),
    }
}

/// An element type that can be written to `.npy`.
pub trait NpyElement: Copy {
    /// dtype descriptor.
    const DESCR: &'static str;
    /// Appends the little-endian bytes.
    fn put(self, out: &mut Vec<u8>);
}

macro_rules! npy_element {
    ($t:ty, $d:literal) => {
        impl NpyElement for $t {
            const DESCR: &'static str = $d;
            // Inlined into the caller's loop (another crate's, without LTO).
            #[inline]
            fn put(self, out: &mut Vec<u8>) {
                out.extend_from_slice(&self.to_le_bytes());
            }
        }
    };
}
npy_element!(u8, "|u1");
npy_element!(u16, "<u2");
npy_element!(i32, "<i4");
npy_element!(f32, "<f4");
npy_element!(f64, "<f8");

/// Encodes an array as `.npy` bytes.
///
/// # Panics
/// If `data.len()` differs from the product of `shape` (a programming error).
pub fn encode_npy<T: NpyElement>(shape: &[usize], data: &[T]) -> Vec<u8> {
    assert_eq!(
        shape.iter().product::<usize>(),
        data.len(),
        "npy shape/data mismatch"
    );
    let shape_s = match shape {
        [n] => format!("({n},)"),
        _ => format!(
            "({})",
            shape
                .iter()
                .map(|d| d.to_string())
                .collect::<Vec<_>>()
                .join(", ")
        ),
    };
    let mut header = format!(
        "{{'descr': '{}', 'fortran_order': False, 'shape': {shape_s}, }}",
        T::DESCR
    );
    // Pad so that the data starts on a 64-byte boundary; header ends with '\n'.
    let (version, prefix) = if header.len() + 11 < 65535 {
        (1u8, 10)
    } else {
        (2u8, 12)
    };
    let total = (prefix + header.len() + 1).div_ceil(64) * 64;
    header.push_str(&" ".repeat(total - prefix - header.len() - 1));
    header.push('\n');
    let mut out = Vec::with_capacity(total + std::mem::size_of_val(data));
    out.extend_from_slice(b"\x93NUMPY");
    out.push(version);
    out.push(0);
    if version == 1 {
        out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    } else {
        out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    }
    out.extend_from_slice(header.as_bytes());
    for &v in data {
        v.put(&mut out);
    }
    out
}

/// Writes an array to `path` atomically.
pub fn write_npy<T: NpyElement>(path: &Path, shape: &[usize], data: &[T]) -> Result<(), NpyError> {
    write_atomic(path, &encode_npy(shape, data)).map_err(|source| NpyError::Io {
        path: path.to_path_buf(),
        source,
    })
}

/// Writes `bytes` to a temporary file beside `path`, syncs it and renames it
/// over `path`, so readers see either the old or the new file, never a part
/// (the project's one atomic write, [`crate::atomic`]).
pub use crate::atomic::write_atomic_io as write_atomic;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_u8_u16_f32() {
        let a = encode_npy(&[2, 3], &[0u8, 1, 2, 3, 4, 255]);
        let p = parse_npy(&a).expect("parse");
        assert_eq!(p.shape, vec![2, 3]);
        assert_eq!(p.data, vec![0.0, 1.0, 2.0, 3.0, 4.0, 255.0]);
        assert_eq!(p.descr, "|u1");
        // Data starts on a 64-byte boundary.
        assert_eq!((a.len() - 6) % 64, 0);
        let b = encode_npy(&[3], &[1u16, 65535, 7]);
        assert_eq!(parse_npy(&b).expect("parse").data, vec![1.0, 65535.0, 7.0]);
        let c = encode_npy(&[1, 2], &[1.5f32, -2.25]);
        assert_eq!(parse_npy(&c).expect("parse").data, vec![1.5, -2.25]);
    }

    #[test]
    fn reads_numpy_written_fortran_and_big_endian() {
        // Header as numpy writes it, for a 2x3 big-endian int16 in Fortran order.
        let header = "{'descr': '>i2', 'fortran_order': True, 'shape': (2, 3), }";
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        bytes.extend_from_slice(&(header.len() as u16).to_le_bytes());
        bytes.extend_from_slice(header.as_bytes());
        // Column-major: a[0,0], a[1,0], a[0,1], a[1,1], a[0,2], a[1,2]
        for v in [1i16, 4, 2, 5, 3, -6] {
            bytes.extend_from_slice(&v.to_be_bytes());
        }
        let p = parse_npy(&bytes).expect("parse");
        assert_eq!(p.data, vec![1.0, 2.0, 3.0, 4.0, 5.0, -6.0]);
    }

    #[test]
    fn rejects_garbage_and_truncation() {
        assert!(parse_npy(b"hello").is_err());
        let a = encode_npy(&[4], &[1.0f64, 2.0, 3.0, 4.0]);
        let err = parse_npy(&a[..a.len() - 3]).expect_err("truncated");
        assert!(err.contains("needs 32 data bytes"), "{err}");
        let header = "{'descr': '<c16', 'fortran_order': False, 'shape': (1,), }";
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend_from_slice(&(header.len() as u16).to_le_bytes());
        b.extend_from_slice(header.as_bytes());
        b.extend_from_slice(&[0; 16]);
        assert!(parse_npy(&b).expect_err("complex").contains("c16"));
    }

    #[test]
    fn atomic_write_replaces_file() {
        let dir = tempfile::tempdir().expect("tempdir");
        let p = dir.path().join("x.npy");
        write_npy(&p, &[2], &[1u8, 2]).expect("write");
        write_npy(&p, &[3], &[1u8, 2, 3]).expect("write");
        assert_eq!(read_npy(&p).expect("read").shape, vec![3]);
        let names: Vec<_> = std::fs::read_dir(dir.path()).expect("ls").collect();
        assert_eq!(names.len(), 1, "no temporary files left behind");
    }
}
