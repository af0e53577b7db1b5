//! Reading parquet files into record batches (guarded against corrupt
//! footers and decoder panics) and typed, checked access to their columns.

use super::error::{arrow_err, io_err, pq_err};
use super::DatasetError;
use arrow_array::{
    Array, ArrayRef, FixedSizeListArray, Float32Array, Float64Array, Int32Array, Int64Array,
    LargeListArray, LargeStringArray, ListArray, RecordBatch, StringArray,
};
use bridgev2w_io::confine::{self, Refusal};
use parquet::arrow::arrow_reader::ParquetRecordBatchReaderBuilder;
use std::path::Path;

/// Reads a parquet file whole. It must be a regular file of at most
/// [`confine::MAX_DATA_BYTES`] (checked before it is opened: a FIFO would
/// block the open, a device never end the read).
pub(super) fn read_batches(path: &Path) -> Result<Vec<RecordBatch>, DatasetError> {
    confine::regular_file(path, confine::MAX_DATA_BYTES).map_err(|e| match e {
        Refusal::Unresolved { path, source, .. } => DatasetError::Io { path, source },
        e => DatasetError::Meta {
            path: path.to_path_buf(),
            message: e.to_string(),
        },
    })?;
    let file = std::fs::File::open(path).map_err(io_err(path))?;
    let file_len = file.metadata().map_err(io_err(path))?.len();
    // The parquet decoder asserts things of the data it reads (a dictionary
    // page before dictionary-encoded pages, ...): a corrupt file can panic it.
    bridgev2w_io::quiet_panic::catch_quiet(|| {
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
pub(super) struct Columns<'a> {
    pub(super) path: &'a Path,
    pub(super) batches: &'a [RecordBatch],
}

impl Columns<'_> {
    pub(super) fn field_err(
        &self,
        field: &str,
        episode: i64,
        message: impl Into<String>,
    ) -> DatasetError {
        DatasetError::Field {
            path: self.path.to_path_buf(),
            episode,
            field: field.into(),
            message: message.into(),
        }
    }

    pub(super) fn has(&self, name: &str) -> bool {
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

    pub(super) fn i64s(&self, name: &str) -> Result<Vec<i64>, DatasetError> {
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

    pub(super) fn f64s(&self, name: &str) -> Result<Vec<f64>, DatasetError> {
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

    pub(super) fn strings(&self, name: &str) -> Result<Vec<String>, DatasetError> {
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

    pub(super) fn string_lists(&self, name: &str) -> Result<Vec<Vec<String>>, DatasetError> {
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
    pub(super) fn float_lists(&self, name: &str) -> Result<Vec<Vec<f32>>, DatasetError> {
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
