//! Loading and saving weights in diffusers' safetensors layout.
//!
//! A diffusers component folder (`transformer/`, `vae/`) holds `config.json` and either
//! one `diffusion_pytorch_model.safetensors` or shards listed by
//! `diffusion_pytorch_model.safetensors.index.json` (`{"weight_map": {key: file}}`).
//! Parameters are matched by their exact diffusers key names; a tensor of another
//! shape, a parameter without a tensor and a tensor without a parameter are errors
//! (each can be allowed explicitly, e.g. for the ControlNet/LoRA parameters that a
//! base checkpoint lacks).

use crate::error::{Result, WorldModelError};
use bridgev2w_io::json::read_json;
use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::{Path, PathBuf};
use tch::nn::VarStore;
use tch::Tensor;

/// The file stem diffusers uses for model weights.
pub const DIFFUSERS_WEIGHTS_STEM: &str = "diffusion_pytorch_model";

/// Finds the safetensors file(s) of a component: `DIR/STEM.safetensors`, or the shards
/// named by `DIR/STEM.safetensors.index.json`.
pub fn resolve_weight_files(dir: &Path, stem: &str) -> Result<Vec<PathBuf>> {
    let single = dir.join(format!("{stem}.safetensors"));
    if single.is_file() {
        return Ok(vec![single]);
    }
    let index = dir.join(format!("{stem}.safetensors.index.json"));
    if index.is_file() {
        #[derive(serde::Deserialize)]
        struct Index {
            weight_map: BTreeMap<String, String>,
        }
        let parsed: Index = read_json(&index)?;
        let mut files: Vec<String> = parsed.weight_map.into_values().collect();
        files.sort();
        files.dedup();
        if files.is_empty() {
            return Err(WorldModelError::config(
                &index,
                "weight_map",
                "is empty: expected at least one shard",
            ));
        }
        return files
            .into_iter()
            .map(|f| {
                let path = dir.join(&f);
                if path.is_file() {
                    Ok(path)
                } else {
                    Err(WorldModelError::config(
                        &index,
                        "weight_map",
                        format!(
                            "names shard `{f}`, which does not exist in {}",
                            dir.display()
                        ),
                    ))
                }
            })
            .collect();
    }
    let pickle = dir.join(format!("{stem}.bin"));
    let hint = if pickle.is_file() {
        format!(
            "; found {} (PyTorch pickle): convert it to safetensors first",
            pickle.display()
        )
    } else if dir.join("config.json").is_file() {
        "; the folder has its config.json but not its weights (downloaded without them?)".into()
    } else {
        String::new()
    };
    Err(WorldModelError::io(
        &single,
        std::io::Error::new(
            std::io::ErrorKind::NotFound,
            format!(
                "no weights: expected {stem}.safetensors or {stem}.safetensors.index.json{hint}"
            ),
        ),
    ))
}

/// What [`load_weights`] did.
#[derive(Debug, Default, Clone)]
pub struct LoadReport {
    /// Parameters filled from the files.
    pub loaded: usize,
    /// Parameters without a tensor (allowed by the caller).
    pub missing: Vec<String>,
    /// Tensors without a parameter (allowed by the caller).
    pub unexpected: Vec<String>,
}

/// Reads all tensors of one safetensors file, with errors naming the file.
pub fn read_safetensors(path: &Path) -> Result<Vec<(String, Tensor)>> {
    if !path.is_file() {
        return Err(WorldModelError::io(
            path,
            std::io::Error::new(std::io::ErrorKind::NotFound, "no such file"),
        ));
    }
    check_safetensors(path)?;
    Tensor::read_safetensors(path).map_err(|e| {
        WorldModelError::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("not a valid safetensors file: {e}"),
            ),
        )
    })
}

/// Refuses a floating-point `tensor` holding NaN or infinite values: a
/// [`WorldModelError::NonFiniteWeight`] naming the file `path`, the tensor's
/// `key` and how many values are not finite (a diverged run or a corrupt file).
pub fn check_finite(path: &Path, key: &str, tensor: &Tensor) -> Result<()> {
    if tensor.is_floating_point() {
        let bad = tensor
            .isfinite()
            .logical_not()
            .sum(tch::Kind::Int64)
            .int64_value(&[]);
        if bad > 0 {
            return Err(WorldModelError::NonFiniteWeight {
                path: path.to_path_buf(),
                key: key.to_string(),
                count: bad,
            });
        }
    }
    Ok(())
}

/// Copies the tensors of `files` into the variables of `vs` by name, converting dtype
/// and device to the variable's. `missing_ok(key)` allows a variable without a tensor,
/// `unexpected_ok(key)` a tensor without a variable; anything else not matched, and
/// any shape mismatch, is an error.
pub fn load_weights(
    vs: &VarStore,
    files: &[PathBuf],
    missing_ok: impl Fn(&str) -> bool,
    unexpected_ok: impl Fn(&str) -> bool,
) -> Result<LoadReport> {
    let vars: HashMap<String, Tensor> = vs.variables();
    let mut seen: HashSet<String> = HashSet::new();
    let mut report = LoadReport::default();
    for path in files {
        for (key, tensor) in read_safetensors(path)? {
            let Some(var) = vars.get(&key) else {
                if unexpected_ok(&key) {
                    report.unexpected.push(key);
                    continue;
                }
                return Err(WorldModelError::UnexpectedWeight {
                    path: path.clone(),
                    key,
                });
            };
            if var.size() != tensor.size() {
                return Err(WorldModelError::ShapeMismatch {
                    path: path.clone(),
                    key,
                    expected: var.size(),
                    found: tensor.size(),
                });
            }
            check_finite(path, &key, &tensor)?;
            tch::no_grad(|| {
                let mut var = var.shallow_clone();
                var.f_copy_(&tensor.to_kind(var.kind()).to_device(var.device()))
            })?;
            seen.insert(key);
            report.loaded += 1;
        }
    }
    let mut missing: Vec<&String> = vars.keys().filter(|k| !seen.contains(*k)).collect();
    missing.sort();
    for key in missing {
        if missing_ok(key) {
            report.missing.push(key.clone());
        } else {
            return Err(WorldModelError::MissingWeight {
                key: key.clone(),
                expected: vars[key].size(),
                files: files
                    .iter()
                    .map(|p| p.display().to_string())
                    .collect::<Vec<_>>()
                    .join(", "),
            });
        }
    }
    Ok(report)
}

/// Loads a diffusers component folder's weights (single file or shards) strictly.
pub fn load_component(vs: &VarStore, dir: &Path) -> Result<LoadReport> {
    let files = resolve_weight_files(dir, DIFFUSERS_WEIGHTS_STEM)?;
    load_weights(vs, &files, |_| false, |_| false)
}

/// Writes named tensors to a safetensors file atomically (temporary file in the same
/// directory, then rename), so an interrupted write never leaves a truncated file.
pub fn save_safetensors(named: &[(String, Tensor)], path: &Path) -> Result<()> {
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty());
    let dir = dir.unwrap_or(Path::new("."));
    std::fs::create_dir_all(dir).map_err(|e| WorldModelError::io(dir, e))?;
    let file_name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "weights".to_owned());
    let tmp = bridgev2w_io::atomic::temporary_beside(&dir.join(&file_name));
    let cpu: Vec<(String, Tensor)> = named
        .iter()
        .map(|(k, t)| {
            (
                k.clone(),
                t.detach().to_device(tch::Device::Cpu).contiguous(),
            )
        })
        .collect();
    Tensor::write_safetensors(&cpu, &tmp).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        WorldModelError::io(&tmp, std::io::Error::other(e.to_string()))
    })?;
    std::fs::rename(&tmp, path).map_err(|e| {
        let _ = std::fs::remove_file(&tmp);
        WorldModelError::io(path, e)
    })
}

/// Number of scalar parameters in a var store.
pub fn parameter_count(vs: &VarStore) -> i64 {
    vs.variables().values().map(|t| t.numel() as i64).sum()
}

/// Elements of the learnable variables only (PyTorch's `parameters()`:
/// buffers such as batch-norm statistics or CogVideoX's learned-position
/// buffer excluded).
pub fn learnable_parameter_count(vs: &VarStore) -> i64 {
    vs.trainable_variables()
        .iter()
        .map(|t| t.numel() as i64)
        .sum()
}

/// Reads the header of a safetensors file: `(header JSON, byte offset of the data)`.
fn read_safetensors_header(
    path: &Path,
) -> Result<(serde_json::Map<String, serde_json::Value>, u64)> {
    use std::io::Read;
    let bad = |m: String| {
        WorldModelError::io(
            path,
            std::io::Error::new(std::io::ErrorKind::InvalidData, m),
        )
    };
    let mut f = std::fs::File::open(path).map_err(|e| WorldModelError::io(path, e))?;
    let file_len = f
        .metadata()
        .map_err(|e| WorldModelError::io(path, e))?
        .len();
    let mut len = [0u8; 8];
    f.read_exact(&mut len)
        .map_err(|_| bad("not a safetensors file: shorter than its 8-byte header length".into()))?;
    let n = u64::from_le_bytes(len);
    if n.saturating_add(8) > file_len || n > 100 << 20 {
        return Err(bad(format!(
            "not a safetensors file: header length {n} for a {file_len}-byte file"
        )));
    }
    let mut header = vec![0u8; n as usize];
    f.read_exact(&mut header)
        .map_err(|e| bad(format!("truncated header: {e}")))?;
    if header.first() != Some(&b'{') {
        return Err(bad(
            "safetensors header does not start with '{' (a JSON object)".into(),
        ));
    }
    let UniqueKeys(value) = serde_json::from_slice(&header)
        .map_err(|e| bad(format!("safetensors header is not JSON: {e}")))?;
    match value {
        serde_json::Value::Object(map) => Ok((map, 8 + n)),
        _ => Err(bad("safetensors header is not a JSON object".into())),
    }
}

/// A JSON value whose objects have no repeated key (serde_json keeps the
/// last; the safetensors library refuses the file with a bare code).
struct UniqueKeys(serde_json::Value);

impl<'de> serde::Deserialize<'de> for UniqueKeys {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        use serde::de::{Error, MapAccess, SeqAccess, Visitor};
        use serde_json::Value;
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Value;
            fn expecting(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
                f.write_str("a JSON value")
            }
            fn visit_bool<E>(self, v: bool) -> std::result::Result<Value, E> {
                Ok(Value::Bool(v))
            }
            fn visit_i64<E>(self, v: i64) -> std::result::Result<Value, E> {
                Ok(v.into())
            }
            fn visit_u64<E>(self, v: u64) -> std::result::Result<Value, E> {
                Ok(v.into())
            }
            fn visit_f64<E>(self, v: f64) -> std::result::Result<Value, E> {
                Ok(v.into())
            }
            fn visit_str<E>(self, v: &str) -> std::result::Result<Value, E> {
                Ok(Value::String(v.to_owned()))
            }
            fn visit_unit<E>(self) -> std::result::Result<Value, E> {
                Ok(Value::Null)
            }
            fn visit_seq<A: SeqAccess<'de>>(
                self,
                mut a: A,
            ) -> std::result::Result<Value, A::Error> {
                let mut out = Vec::new();
                while let Some(UniqueKeys(v)) = a.next_element()? {
                    out.push(v);
                }
                Ok(Value::Array(out))
            }
            fn visit_map<A: MapAccess<'de>>(
                self,
                mut a: A,
            ) -> std::result::Result<Value, A::Error> {
                let mut out = serde_json::Map::new();
                while let Some(k) = a.next_key::<String>()? {
                    let UniqueKeys(v) = a.next_value()?;
                    if out.insert(k.clone(), v).is_some() {
                        return Err(A::Error::custom(format!("key {k:?} appears twice")));
                    }
                }
                Ok(Value::Object(out))
            }
        }
        d.deserialize_any(V).map(UniqueKeys)
    }
}

/// Bytes per element of a safetensors dtype name.
fn safetensors_dtype_size(dtype: &str) -> Option<u64> {
    Some(match dtype {
        "BOOL" | "U8" | "I8" | "F8_E4M3" | "F8_E5M2" => 1,
        "U16" | "I16" | "F16" | "BF16" => 2,
        "U32" | "I32" | "F32" => 4,
        "U64" | "I64" | "F64" => 8,
        _ => return None,
    })
}

/// Checks a safetensors file's header against its size before any tensor is
/// read: every entry's dtype, shape and byte range, in words (the library's
/// errors are codes such as `InvalidOffset`).
pub fn check_safetensors(path: &Path) -> Result<()> {
    let (header, data_start) = read_safetensors_header(path)?;
    let file_len = std::fs::metadata(path)
        .map_err(|e| WorldModelError::io(path, e))?
        .len();
    let data_len = file_len - data_start;
    let bad = |key: &str, m: String| {
        WorldModelError::io(
            path,
            std::io::Error::new(
                std::io::ErrorKind::InvalidData,
                format!("not a valid safetensors file: tensor `{key}`: {m}"),
            ),
        )
    };
    let mut ranges: Vec<(u64, u64, &str)> = Vec::new();
    for (key, entry) in &header {
        if key == "__metadata__" {
            if !entry
                .as_object()
                .is_some_and(|m| m.values().all(serde_json::Value::is_string))
            {
                return Err(bad(key, "expected a map of strings".into()));
            }
            continue;
        }
        let dtype = entry.get("dtype").and_then(|d| d.as_str()).unwrap_or("");
        let size = safetensors_dtype_size(dtype).ok_or_else(|| {
            bad(
                key,
                format!("dtype {:?} is not a safetensors dtype", entry.get("dtype")),
            )
        })?;
        let shape: Option<Vec<u64>> = entry
            .get("shape")
            .and_then(|s| s.as_array())
            .and_then(|a| a.iter().map(|d| d.as_u64()).collect());
        let shape = shape.ok_or_else(|| bad(key, "no shape of non-negative integers".into()))?;
        let numel = shape
            .iter()
            .try_fold(1u64, |n, &d| n.checked_mul(d))
            .ok_or_else(|| bad(key, format!("shape {shape:?} overflows")))?;
        let offsets: Option<Vec<u64>> = entry
            .get("data_offsets")
            .and_then(|s| s.as_array())
            .and_then(|a| a.iter().map(|d| d.as_u64()).collect());
        let (begin, end) = match offsets.as_deref() {
            Some(&[b, e]) => (b, e),
            _ => return Err(bad(key, "no data_offsets [begin, end]".into())),
        };
        if begin > end || end > data_len {
            return Err(bad(
                key,
                format!("bytes {begin}..{end} lie outside the {data_len} data bytes of the file (truncated?)"),
            ));
        }
        if Some(end - begin) != numel.checked_mul(size) {
            return Err(bad(
                key,
                format!(
                    "{} bytes for a {dtype} tensor of shape {shape:?} ({numel} values of {size} bytes)",
                    end - begin
                ),
            ));
        }
        ranges.push((begin, end, key));
    }
    // The tensors tile the data bytes, in order, without gaps or overlaps.
    ranges.sort_unstable();
    let mut at = 0;
    for (begin, end, key) in ranges {
        if begin != at {
            return Err(bad(
                key,
                format!("its bytes start at {begin}, but the tensors before it end at {at} (overlapping or with a gap)"),
            ));
        }
        at = end;
    }
    if at != data_len {
        return Err(bad(
            "*",
            format!("the tensors end at byte {at} of {data_len} data bytes"),
        ));
    }
    Ok(())
}

/// The `__metadata__` string map of a safetensors file (empty when absent).
pub fn read_safetensors_metadata(path: &Path) -> Result<BTreeMap<String, String>> {
    let (header, _) = read_safetensors_header(path)?;
    let mut out = BTreeMap::new();
    if let Some(serde_json::Value::Object(meta)) = header.get("__metadata__") {
        for (k, v) in meta {
            if let Some(s) = v.as_str() {
                out.insert(k.clone(), s.to_owned());
            }
        }
    }
    Ok(out)
}

/// As [`save_safetensors`], with a `__metadata__` string map in the header (as
/// the `safetensors` library's `metadata=`), written atomically.
pub fn save_safetensors_with_metadata(
    named: &[(String, Tensor)],
    metadata: &BTreeMap<String, String>,
    path: &Path,
) -> Result<()> {
    use std::io::{Seek, SeekFrom, Write};
    let dir = path.parent().filter(|p| !p.as_os_str().is_empty());
    let dir = dir.unwrap_or(Path::new("."));
    let file_name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "weights".to_owned());
    let plain = dir.join(format!(".{file_name}.plain-{}", std::process::id()));
    save_safetensors(named, &plain)?;
    let result = (|| -> Result<()> {
        let (mut header, data_start) = read_safetensors_header(&plain)?;
        header.insert(
            "__metadata__".to_owned(),
            serde_json::Value::Object(
                metadata
                    .iter()
                    .map(|(k, v)| (k.clone(), serde_json::Value::String(v.clone())))
                    .collect(),
            ),
        );
        let mut json = serde_json::to_vec(&header).map_err(|e| WorldModelError::Json {
            path: path.to_path_buf(),
            error: e,
        })?;
        // Pad with spaces so the data starts 8-byte aligned, as the library does.
        while (json.len() + 8) % 8 != 0 {
            json.push(b' ');
        }
        let tmp = bridgev2w_io::atomic::temporary_beside(&dir.join(&file_name));
        let io = |e| WorldModelError::io(&tmp, e);
        let mut src = std::fs::File::open(&plain).map_err(|e| WorldModelError::io(&plain, e))?;
        src.seek(SeekFrom::Start(data_start))
            .map_err(|e| WorldModelError::io(&plain, e))?;
        let mut dst = std::io::BufWriter::new(std::fs::File::create(&tmp).map_err(io)?);
        dst.write_all(&(json.len() as u64).to_le_bytes())
            .map_err(io)?;
        dst.write_all(&json).map_err(io)?;
        std::io::copy(&mut src, &mut dst).map_err(io)?;
        dst.into_inner()
            .map_err(|e| io(e.into_error()))?
            .sync_all()
            .map_err(io)?;
        std::fs::rename(&tmp, path).map_err(|e| {
            let _ = std::fs::remove_file(&tmp);
            WorldModelError::io(path, e)
        })
    })();
    let _ = std::fs::remove_file(&plain);
    result
}
