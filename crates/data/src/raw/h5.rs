//! Numeric datasets from HDF5 files (pure Rust, `hdf5-reader`): whatever the
//! stored type (f32, f64, integers), values come back as `f64` with their
//! shape, and every failure names the file and the dataset path.
//!
//! Sizes come from the file, so they are bounded before anything is
//! allocated: a dataset's dimensions may not exceed its own maximum
//! dimensions (libhdf5's rule), and one dataset may decode to at most
//! [`MAX_DECODED_RATIO`] times the file's size.

use super::RawError;
use bridgev2w_io::confine;
use hdf5_reader::{Dataset, Datatype, Hdf5File, OpenOptions};
use std::path::{Path, PathBuf};

/// The most bytes one dataset's values (as `f64`) may take, as a multiple of
/// the file's size. Robot trajectories (joint and pose states, actions)
/// compress a few times; deflate cannot exceed 1032:1, so a dataset claiming
/// more than this is a corrupt size field, not data. A read holds the
/// decoded dataset and its `f64` copy: at most twice this at its peak.
pub const MAX_DECODED_RATIO: usize = 1024;

/// An open HDF5 file that remembers its path for error messages.
pub struct H5 {
    path: PathBuf,
    file: Hdf5File,
    /// The most bytes one dataset may decode to.
    decoded_limit: usize,
}

impl std::fmt::Debug for H5 {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("H5").field("path", &self.path).finish()
    }
}

/// A numeric dataset read as `f64`, row-major.
#[derive(Debug, Clone, PartialEq)]
pub struct Array {
    /// Dimensions.
    pub shape: Vec<usize>,
    /// Values, row-major.
    pub values: Vec<f64>,
}

impl Array {
    /// The rows of a dataset whose first axis is time: `[T, ...]` flattened to
    /// `T` rows of `prod(shape[1..])` values.
    pub fn rows(&self) -> Vec<Vec<f64>> {
        let t = self.shape.first().copied().unwrap_or(0);
        let width = self.shape.iter().skip(1).product::<usize>();
        if t == 0 {
            return Vec::new();
        }
        self.values
            .chunks(width.max(1))
            .map(<[f64]>::to_vec)
            .collect()
    }
}

impl H5 {
    /// Opens `path`; a missing, truncated or non-HDF5 file is an error naming it.
    /// It must be a regular file of at most [`confine::MAX_DATA_BYTES`],
    /// checked before it is opened (a FIFO or a device is an error, not a hang).
    pub fn open(path: &Path) -> Result<Self, RawError> {
        if let Err(e) = confine::regular_file(path, confine::MAX_DATA_BYTES) {
            return Err(if e.is_missing() {
                RawError::Missing {
                    path: path.to_path_buf(),
                    what: "HDF5 file".into(),
                }
            } else {
                RawError::Refused {
                    path: path.to_path_buf(),
                    message: e.to_string(),
                }
            });
        }
        let file_bytes = std::fs::metadata(path).map_or(0, |m| m.len() as usize);
        let limit = file_bytes.saturating_mul(MAX_DECODED_RATIO).max(1 << 16);
        let options = OpenOptions {
            max_read_bytes: limit,
            max_chunk_bytes: limit.min(hdf5_reader::DEFAULT_MAX_CHUNK_BYTES),
            ..OpenOptions::default()
        };
        let file = Hdf5File::open_with_options(path, options).map_err(|e| RawError::Hdf5 {
            path: path.to_path_buf(),
            field: String::new(),
            message: format!("not a readable HDF5 file (corrupt or truncated?): {e}"),
        })?;
        Ok(Self {
            path: path.to_path_buf(),
            file,
            decoded_limit: limit,
        })
    }

    /// The file's path.
    pub fn path(&self) -> &Path {
        &self.path
    }

    fn err(&self, field: &str, message: String) -> RawError {
        RawError::Hdf5 {
            path: self.path.clone(),
            field: field.to_string(),
            message,
        }
    }

    /// Whether dataset `name` (a `/`-separated path) exists.
    pub fn has(&self, name: &str) -> bool {
        self.file.dataset(name).is_ok()
    }

    /// The member names of group `group` (`""` or `"/"` for the root):
    /// `(groups, datasets)`.
    pub fn members(&self, group: &str) -> Result<(Vec<String>, Vec<String>), RawError> {
        let g = if group.is_empty() || group == "/" {
            self.file.root_group()
        } else {
            self.file.group(group)
        }
        .map_err(|e| self.err(group, format!("no such group: {e}")))?;
        g.member_names()
            .map_err(|e| self.err(group, format!("cannot list the group: {e}")))
    }

    fn dataset(&self, name: &str) -> Result<Dataset, RawError> {
        self.file
            .dataset(name)
            .map_err(|e| self.err(name, format!("missing dataset ({e})")))
    }

    /// Reads numeric dataset `name` as `f64` and checks that every value is
    /// finite (a NaN or infinite state is an error naming the element).
    pub fn read(&self, name: &str) -> Result<Array, RawError> {
        let ds = self.dataset(name)?;
        if let Some(max) = ds.max_dims() {
            let over = ds
                .shape()
                .iter()
                .zip(max)
                .position(|(&d, &m)| m != u64::MAX && d > m);
            if let Some(axis) = over {
                return Err(self.err(
                    name,
                    format!(
                        "shape {:?} exceeds the dataset's maximum shape {max:?} on axis {axis}: \
                         a corrupt dataspace",
                        ds.shape()
                    ),
                ));
            }
        }
        let elements = ds.num_elements().unwrap_or(u64::MAX);
        let bytes = elements.saturating_mul(8);
        if bytes > self.decoded_limit as u64 {
            return Err(self.err(
                name,
                format!(
                    "shape {:?} is {elements} values ({bytes} bytes as f64), more than \
                     {MAX_DECODED_RATIO} times the file's size ({} bytes allowed): a corrupt \
                     dataspace",
                    ds.shape(),
                    self.decoded_limit
                ),
            ));
        }
        let shape: Vec<usize> = ds.shape().iter().map(|&d| d as usize).collect();
        let values = self.read_values(&ds, name)?;
        if let Some(i) = values.iter().position(|v| !v.is_finite()) {
            return Err(self.err(
                name,
                format!(
                    "element {} (flat index {i}) is {}: expected finite values",
                    unravel(i, &shape),
                    values[i]
                ),
            ));
        }
        Ok(Array { shape, values })
    }

    /// [`H5::read`] and a check that the shape is `[frames?, dims...]`:
    /// `expected[i] = None` accepts any size on axis `i`.
    pub fn read_shaped(&self, name: &str, expected: &[Option<usize>]) -> Result<Array, RawError> {
        let a = self.read(name)?;
        let ok = a.shape.len() == expected.len()
            && a.shape
                .iter()
                .zip(expected)
                .all(|(&s, e)| e.is_none_or(|e| e == s));
        if !ok {
            let want: Vec<String> = expected
                .iter()
                .map(|e| e.map_or("T".to_string(), |d| d.to_string()))
                .collect();
            return Err(self.err(
                name,
                format!("shape {:?}, expected [{}]", a.shape, want.join(", ")),
            ));
        }
        Ok(a)
    }

    fn read_values(&self, ds: &Dataset, name: &str) -> Result<Vec<f64>, RawError> {
        let wrap =
            |e: hdf5_reader::error::Error| self.err(name, format!("cannot read the values: {e}"));
        Ok(match ds.dtype() {
            Datatype::FloatingPoint { size: 8, .. } => ds
                .read_array::<f64>()
                .map_err(wrap)?
                .iter()
                .copied()
                .collect(),
            Datatype::FloatingPoint { size: 4, .. } => ds
                .read_array::<f32>()
                .map_err(wrap)?
                .iter()
                .map(|&v| f64::from(v))
                .collect(),
            Datatype::FixedPoint { size, signed, .. } => match (size, signed) {
                (1, false) => collect_f64(ds.read_array::<u8>().map_err(wrap)?.iter().copied()),
                (1, true) => collect_f64(ds.read_array::<i8>().map_err(wrap)?.iter().copied()),
                (2, false) => collect_f64(ds.read_array::<u16>().map_err(wrap)?.iter().copied()),
                (2, true) => collect_f64(ds.read_array::<i16>().map_err(wrap)?.iter().copied()),
                (4, false) => collect_f64(ds.read_array::<u32>().map_err(wrap)?.iter().copied()),
                (4, true) => collect_f64(ds.read_array::<i32>().map_err(wrap)?.iter().copied()),
                (8, true) => ds
                    .read_array::<i64>()
                    .map_err(wrap)?
                    .iter()
                    .map(|&v| v as f64)
                    .collect(),
                (8, false) => ds
                    .read_array::<u64>()
                    .map_err(wrap)?
                    .iter()
                    .map(|&v| v as f64)
                    .collect(),
                _ => {
                    return Err(self.err(
                        name,
                        format!("integer of {size} bytes: expected 1, 2, 4 or 8 bytes"),
                    ))
                }
            },
            other => {
                return Err(self.err(
                    name,
                    format!("datatype {other:?}: expected a numeric (float or integer) dataset"),
                ))
            }
        })
    }
}

fn collect_f64<T: Into<f64>>(it: impl Iterator<Item = T>) -> Vec<f64> {
    it.map(Into::into).collect()
}

fn unravel(mut i: usize, shape: &[usize]) -> String {
    let mut idx = vec![0usize; shape.len()];
    for (k, &d) in shape.iter().enumerate().rev() {
        if d > 0 {
            idx[k] = i % d;
            i /= d;
        }
    }
    format!("{idx:?}")
}
