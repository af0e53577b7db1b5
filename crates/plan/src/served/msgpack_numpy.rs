//! openpi's msgpack-numpy encoding (`openpi_client.msgpack_numpy`): msgpack
//! maps with string keys, where a numpy array is the map
//! `{b"__ndarray__": true, b"data": <bytes>, b"dtype": "<f4", b"shape": [..]}`
//! (keys as msgpack binaries, the data C-ordered in the dtype's byte order)
//! and a numpy scalar `{b"__npgeneric__": true, b"data": x, b"dtype": ".."}`.

use rmpv::Value;

/// An n-dimensional array as it travels: its numpy dtype string, shape and
/// raw bytes.
#[derive(Debug, Clone, PartialEq)]
pub struct NdArray {
    /// numpy's `dtype.str`, e.g. `<f4`, `<f8`, `|u1`.
    pub dtype: String,
    /// The shape.
    pub shape: Vec<usize>,
    /// C-ordered elements in the dtype's byte order.
    pub data: Vec<u8>,
}

impl NdArray {
    /// A `uint8` array.
    pub fn from_u8(shape: Vec<usize>, data: Vec<u8>) -> Self {
        Self {
            dtype: "|u1".into(),
            shape,
            data,
        }
    }

    /// A little-endian `float32` array.
    pub fn from_f32(shape: Vec<usize>, values: &[f32]) -> Self {
        Self {
            dtype: "<f4".into(),
            shape,
            data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    }

    /// A little-endian `float64` array.
    pub fn from_f64(shape: Vec<usize>, values: &[f64]) -> Self {
        Self {
            dtype: "<f8".into(),
            shape,
            data: values.iter().flat_map(|v| v.to_le_bytes()).collect(),
        }
    }

    /// The elements as `f64`, for the numeric dtypes a policy returns
    /// (little- or big-endian floats of 2 (half), 4, 8 bytes, integers of
    /// 1-8 bytes, booleans); refused: other dtypes, a byte count that is not
    /// the shape's.
    pub fn to_f64(&self) -> Result<Vec<f64>, String> {
        let d = self.dtype.as_bytes();
        if d.len() < 3 {
            return Err(format!("dtype {:?}: not a numpy dtype string", self.dtype));
        }
        let big = d[0] == b'>';
        let kind = d[1];
        if !matches!(kind, b'f' | b'u' | b'b' | b'i') {
            return Err(format!(
                "dtype {}: expected a numeric dtype (float, int, uint, bool)",
                self.dtype
            ));
        }
        let size: usize = self.dtype[2..]
            .parse()
            .map_err(|_| format!("dtype {:?}: not a numpy dtype string", self.dtype))?;
        let n: usize = self.shape.iter().product();
        if self.data.len() != n * size {
            return Err(format!(
                "{} bytes of dtype {} for shape {:?}: expected {}",
                self.data.len(),
                self.dtype,
                self.shape,
                n * size
            ));
        }
        let word = |c: &[u8]| -> u64 {
            let mut b = [0u8; 8];
            if big {
                b[8 - c.len()..].copy_from_slice(c);
                u64::from_be_bytes(b)
            } else {
                b[..c.len()].copy_from_slice(c);
                u64::from_le_bytes(b)
            }
        };
        if !matches!(
            (kind, size),
            (b'f', 2 | 4 | 8) | (b'u' | b'b' | b'i', 1..=8)
        ) {
            return Err(format!(
                "dtype {}: expected a numeric dtype (float, int, uint, bool)",
                self.dtype
            ));
        }
        let value = |c: &[u8]| -> f64 {
            match (kind, size) {
                (b'f', 8) => f64::from_bits(word(c)),
                (b'f', 4) => f64::from(f32::from_bits(word(c) as u32)),
                (b'f', _) => half_to_f64(word(c) as u16),
                (b'i', _) => {
                    let shift = 64 - 8 * c.len() as u32;
                    ((word(c) << shift) as i64 >> shift) as f64
                }
                _ => word(c) as f64,
            }
        };
        Ok(self.data.chunks_exact(size).map(value).collect())
    }
}

/// IEEE half precision to f64.
fn half_to_f64(h: u16) -> f64 {
    let sign = if h & 0x8000 != 0 { -1.0 } else { 1.0 };
    let exp = i32::from((h >> 10) & 0x1f);
    let frac = f64::from(h & 0x3ff);
    sign * match exp {
        0 => frac * 2f64.powi(-24),
        31 if frac == 0.0 => f64::INFINITY,
        31 => f64::NAN,
        e => (1.0 + frac / 1024.0) * 2f64.powi(e - 15),
    }
}

/// A value to send: nested maps of strings to arrays, strings and numbers.
#[derive(Debug, Clone, PartialEq)]
pub enum Packed {
    /// A numpy array.
    Array(NdArray),
    /// A string (e.g. the prompt).
    Str(String),
    /// A float.
    Float(f64),
    /// A map with string keys (insertion order kept).
    Map(Vec<(String, Packed)>),
}

impl Packed {
    /// The msgpack value, arrays in msgpack-numpy's form.
    pub fn to_value(&self) -> Value {
        match self {
            Packed::Array(a) => Value::Map(vec![
                (Value::Binary(b"__ndarray__".to_vec()), Value::Boolean(true)),
                (
                    Value::Binary(b"data".to_vec()),
                    Value::Binary(a.data.clone()),
                ),
                (
                    Value::Binary(b"dtype".to_vec()),
                    Value::from(a.dtype.as_str()),
                ),
                (
                    Value::Binary(b"shape".to_vec()),
                    Value::Array(a.shape.iter().map(|&d| Value::from(d as u64)).collect()),
                ),
            ]),
            Packed::Str(s) => Value::from(s.as_str()),
            Packed::Float(x) => Value::F64(*x),
            Packed::Map(entries) => Value::Map(
                entries
                    .iter()
                    .map(|(k, v)| (Value::from(k.as_str()), v.to_value()))
                    .collect(),
            ),
        }
    }

    /// The msgpack bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut out = Vec::new();
        // Writing into a Vec cannot fail.
        let _ = rmpv::encode::write_value(&mut out, &self.to_value());
        out
    }
}

/// Inserts `value` at a `/`-separated `key` of `map`: `images/cam_high`
/// becomes `{"images": {"cam_high": value}}` (openpi's ALOHA layout) unless
/// the whole key is meant flat (`observation/joint_position` in openpi's
/// DROID example is one key: see [`KeyStyle`]).
pub fn insert(map: &mut Vec<(String, Packed)>, key: &str, value: Packed, style: KeyStyle) {
    let split = match style {
        KeyStyle::Flat => None,
        KeyStyle::Nested => key.split_once('/'),
    };
    match split {
        None => {
            map.retain(|(k, _)| k != key);
            map.push((key.to_string(), value));
        }
        Some((head, rest)) => {
            let pos = map.iter().position(|(k, _)| k == head);
            let i = match pos {
                Some(i) if matches!(map[i].1, Packed::Map(_)) => i,
                _ => {
                    map.retain(|(k, _)| k != head);
                    map.push((head.to_string(), Packed::Map(Vec::new())));
                    map.len() - 1
                }
            };
            if let Packed::Map(inner) = &mut map[i].1 {
                insert(inner, rest, value, style);
            }
        }
    }
}

/// Whether `/` in a key nests maps.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, serde::Deserialize, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum KeyStyle {
    /// Keys are used as written (openpi's DROID example:
    /// `observation/exterior_image_1_left` is one key).
    #[default]
    Flat,
    /// `a/b` is key `b` inside map `a` (openpi's ALOHA example:
    /// `images/cam_high`).
    Nested,
}

/// A received value's entry `key` (a string key, or a binary one as
/// msgpack-numpy writes its own), `/` descending into maps with
/// [`KeyStyle::Nested`].
pub fn lookup<'a>(v: &'a Value, key: &str, style: KeyStyle) -> Option<&'a Value> {
    let entry = |v: &'a Value, k: &str| -> Option<&'a Value> {
        v.as_map()?.iter().find_map(|(mk, mv)| {
            let name = match mk {
                Value::String(s) => s.as_str(),
                Value::Binary(b) => std::str::from_utf8(b).ok(),
                _ => None,
            };
            (name == Some(k)).then_some(mv)
        })
    };
    match style {
        KeyStyle::Flat => entry(v, key),
        KeyStyle::Nested => key.split('/').try_fold(v, entry),
    }
}

/// A received value as an array: a msgpack-numpy array map, or a plain
/// (nested) list of numbers. The error says what was found.
pub fn as_array(v: &Value) -> Result<NdArray, String> {
    if lookup(v, "__ndarray__", KeyStyle::Flat).is_some() {
        let field = |k: &str| {
            lookup(v, k, KeyStyle::Flat).ok_or_else(|| format!("an array without its {k:?}"))
        };
        let data = match field("data")? {
            Value::Binary(b) => b.clone(),
            other => return Err(format!("array data is {}, expected bytes", kind(other))),
        };
        let dtype = match field("dtype")? {
            Value::String(s) => s.as_str().unwrap_or_default().to_string(),
            Value::Binary(b) => String::from_utf8_lossy(b).into_owned(),
            other => return Err(format!("array dtype is {}, expected a string", kind(other))),
        };
        let shape = match field("shape")? {
            Value::Array(dims) => dims
                .iter()
                .map(|d| d.as_u64().map(|d| d as usize))
                .collect::<Option<Vec<_>>>()
                .ok_or("array shape holds a non-integer")?,
            other => return Err(format!("array shape is {}, expected a list", kind(other))),
        };
        return Ok(NdArray { dtype, shape, data });
    }
    // A plain list (of lists) of numbers.
    let mut shape = Vec::new();
    let mut cur = v;
    while let Value::Array(items) = cur {
        shape.push(items.len());
        match items.first() {
            Some(first) => cur = first,
            None => break,
        }
    }
    if shape.is_empty() {
        return Err(format!("{}, expected an array", kind(v)));
    }
    let mut values = Vec::new();
    flatten(v, &mut values)?;
    if values.len() != shape.iter().product::<usize>() {
        return Err(format!(
            "a ragged list (first shape {shape:?}), expected an array"
        ));
    }
    let data: Vec<u8> = values.iter().flat_map(|x| x.to_le_bytes()).collect();
    Ok(NdArray {
        dtype: "<f8".into(),
        shape,
        data,
    })
}

fn flatten(v: &Value, out: &mut Vec<f64>) -> Result<(), String> {
    match v {
        Value::Array(items) => items.iter().try_for_each(|i| flatten(i, out)),
        Value::F64(x) => {
            out.push(*x);
            Ok(())
        }
        Value::F32(x) => {
            out.push(f64::from(*x));
            Ok(())
        }
        Value::Integer(i) => {
            out.push(i.as_f64().unwrap_or(f64::NAN));
            Ok(())
        }
        other => Err(format!("a list holding {}, expected numbers", kind(other))),
    }
}

/// A value's kind in words, for errors.
pub fn kind(v: &Value) -> &'static str {
    match v {
        Value::Nil => "nil",
        Value::Boolean(_) => "a boolean",
        Value::Integer(_) => "an integer",
        Value::F32(_) | Value::F64(_) => "a float",
        Value::String(_) => "a string",
        Value::Binary(_) => "bytes",
        Value::Array(_) => "a list",
        Value::Map(_) => "a map",
        Value::Ext(..) => "a msgpack extension",
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used)]
mod tests {
    use super::*;

    #[test]
    fn arrays_round_trip_through_msgpack() {
        let a = NdArray::from_f32(vec![2, 3], &[1.0, -2.5, 3.0, 0.0, 1e-3, 7.0]);
        let mut map = Vec::new();
        insert(
            &mut map,
            "images/cam",
            Packed::Array(a.clone()),
            KeyStyle::Nested,
        );
        insert(
            &mut map,
            "prompt",
            Packed::Str("pick".into()),
            KeyStyle::Nested,
        );
        let bytes = Packed::Map(map).to_bytes();
        let v = rmpv::decode::read_value(&mut bytes.as_slice()).unwrap();
        let back = as_array(lookup(&v, "images/cam", KeyStyle::Nested).unwrap()).unwrap();
        assert_eq!(back, a);
        assert_eq!(back.to_f64().unwrap()[1], -2.5);
        assert!(lookup(&v, "images/cam", KeyStyle::Flat).is_none());
    }

    #[test]
    fn dtypes_decode_by_their_numpy_strings() {
        let arr = |dtype: &str, data: Vec<u8>| NdArray {
            dtype: dtype.into(),
            shape: vec![data.len() / (dtype[2..].parse::<usize>().unwrap())],
            data,
        };
        assert_eq!(
            arr(">f8", 1.5f64.to_be_bytes().to_vec()).to_f64().unwrap(),
            [1.5]
        );
        assert_eq!(
            arr("<i2", (-3i16).to_le_bytes().to_vec()).to_f64().unwrap(),
            [-3.0]
        );
        assert_eq!(arr("<f2", vec![0x00, 0x3c]).to_f64().unwrap(), [1.0]);
        assert_eq!(arr("|b1", vec![1, 0]).to_f64().unwrap(), [1.0, 0.0]);
        let e = arr("<U4", vec![0; 4]).to_f64().unwrap_err();
        assert!(e.contains("<U4") && e.contains("numeric"), "{e}");
        let short = NdArray {
            dtype: "<f4".into(),
            shape: vec![3],
            data: vec![0; 8],
        };
        assert!(short.to_f64().unwrap_err().contains("8 bytes"));
    }

    #[test]
    fn plain_lists_are_arrays_and_ragged_ones_are_refused() {
        let v = Value::Array(vec![
            Value::Array(vec![Value::from(1.0), Value::from(2)]),
            Value::Array(vec![Value::from(3.0), Value::from(4.0)]),
        ]);
        let a = as_array(&v).unwrap();
        assert_eq!(a.shape, [2, 2]);
        assert_eq!(a.to_f64().unwrap(), [1.0, 2.0, 3.0, 4.0]);
        let ragged = Value::Array(vec![
            Value::Array(vec![Value::from(1.0)]),
            Value::Array(vec![Value::from(3.0), Value::from(4.0)]),
        ]);
        assert!(as_array(&ragged).unwrap_err().contains("ragged"));
        assert!(as_array(&Value::from("x"))
            .unwrap_err()
            .contains("a string"));
    }
}
