//! The safetensors container (8-byte little-endian header length, a JSON header naming each
//! tensor's dtype, shape and byte range, then the data), for f32 tensors: checkpoints and
//! model weights. Writes go to a temporary file that is renamed over the target, so a crash
//! never leaves a half-written file behind.

use std::collections::BTreeMap;
use std::path::Path;

use crate::data::DataError;

/// A named f32 tensor.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    /// Shape (row-major).
    pub shape: Vec<usize>,
    /// `shape.iter().product()` values.
    pub data: Vec<f32>,
}

/// Tensors by name plus the free-form string metadata.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SafeTensors {
    /// The tensors.
    pub tensors: BTreeMap<String, Tensor>,
    /// `__metadata__` entries.
    pub metadata: BTreeMap<String, String>,
}

fn malformed(path: &Path, problem: impl Into<String>) -> DataError {
    DataError::Malformed {
        path: path.to_path_buf(),
        problem: problem.into(),
    }
}

impl SafeTensors {
    /// Parses a safetensors file (F32 tensors only).
    pub fn read(path: &Path) -> Result<SafeTensors, DataError> {
        let bytes = std::fs::read(path).map_err(|e| DataError::io(path, e))?;
        Self::parse(&bytes, path)
    }

    /// Parses safetensors bytes; `path` names the source in errors.
    pub fn parse(bytes: &[u8], path: &Path) -> Result<SafeTensors, DataError> {
        if bytes.len() < 8 {
            return Err(malformed(path, "shorter than the 8-byte header length"));
        }
        let n = u64::from_le_bytes(bytes[..8].try_into().unwrap_or_default());
        let body = &bytes[8..];
        if n > body.len() as u64 {
            return Err(malformed(
                path,
                format!(
                    "header length {n} exceeds the file's {} remaining bytes",
                    body.len()
                ),
            ));
        }
        let (header, data) = body.split_at(n as usize);
        let json: serde_json::Value = serde_json::from_slice(header)
            .map_err(|e| malformed(path, format!("header is not JSON: {e}")))?;
        let obj = json
            .as_object()
            .ok_or_else(|| malformed(path, "header is not a JSON object"))?;
        let mut out = SafeTensors::default();
        for (name, v) in obj {
            if name == "__metadata__" {
                if let Some(m) = v.as_object() {
                    for (k, v) in m {
                        out.metadata
                            .insert(k.clone(), v.as_str().unwrap_or_default().to_string());
                    }
                }
                continue;
            }
            let bad = |p: &str| malformed(path, format!("tensor `{name}`: {p}"));
            let dtype = v.get("dtype").and_then(|d| d.as_str()).unwrap_or("");
            if dtype != "F32" {
                return Err(bad(&format!("dtype `{dtype}` is not supported (F32 only)")));
            }
            let shape: Vec<usize> = v
                .get("shape")
                .and_then(|s| s.as_array())
                .ok_or_else(|| bad("no shape"))?
                .iter()
                .map(|d| d.as_u64().map(|d| d as usize))
                .collect::<Option<_>>()
                .ok_or_else(|| bad("shape entries must be non-negative integers"))?;
            let offs: Vec<u64> = v
                .get("data_offsets")
                .and_then(|s| s.as_array())
                .map(|a| a.iter().filter_map(|d| d.as_u64()).collect())
                .unwrap_or_default();
            let count = shape
                .iter()
                .try_fold(1usize, |a, &d| a.checked_mul(d))
                .ok_or_else(|| bad("shape overflows"))?;
            if offs.len() != 2 || offs[0] > offs[1] || offs[1] > data.len() as u64 {
                return Err(bad(&format!(
                    "data_offsets {offs:?} do not lie inside the {} data bytes",
                    data.len()
                )));
            }
            let need = (count as u64)
                .checked_mul(4)
                .ok_or_else(|| bad(&format!("shape {shape:?} overflows")))?;
            if offs[1] - offs[0] != need {
                return Err(bad(&format!(
                    "{} bytes for shape {shape:?} ({need} expected)",
                    offs[1] - offs[0]
                )));
            }
            let raw = &data[offs[0] as usize..offs[1] as usize];
            let values = raw
                .chunks_exact(4)
                .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
                .collect();
            out.tensors.insert(
                name.clone(),
                Tensor {
                    shape,
                    data: values,
                },
            );
        }
        Ok(out)
    }

    /// The tensor `name` with exactly `shape`, or an error naming the file.
    pub fn get(&self, name: &str, shape: &[usize], path: &Path) -> Result<&Tensor, DataError> {
        let t = self
            .tensors
            .get(name)
            .ok_or_else(|| malformed(path, format!("tensor `{name}` is missing")))?;
        if t.shape != shape {
            return Err(malformed(
                path,
                format!(
                    "tensor `{name}` has shape {:?}, expected {shape:?}",
                    t.shape
                ),
            ));
        }
        Ok(t)
    }

    /// The file's bytes.
    pub fn to_bytes(&self) -> Vec<u8> {
        let mut header = serde_json::Map::new();
        if !self.metadata.is_empty() {
            header.insert(
                "__metadata__".into(),
                serde_json::to_value(&self.metadata).unwrap_or_default(),
            );
        }
        let mut at = 0u64;
        for (name, t) in &self.tensors {
            let n = t.data.len() as u64 * 4;
            header.insert(
                name.clone(),
                serde_json::json!({"dtype": "F32", "shape": t.shape, "data_offsets": [at, at + n]}),
            );
            at += n;
        }
        let mut h = serde_json::Value::Object(header).to_string().into_bytes();
        // Pad the header so the data starts 8-byte aligned (the format's recommendation).
        while !h.len().is_multiple_of(8) {
            h.push(b' ');
        }
        let mut out = Vec::with_capacity(8 + h.len() + at as usize);
        out.extend_from_slice(&(h.len() as u64).to_le_bytes());
        out.extend_from_slice(&h);
        for t in self.tensors.values() {
            out.extend_from_slice(bytemuck::cast_slice(&t.data));
        }
        out
    }

    /// Writes atomically: a temporary file beside `path`, synced, then renamed over it.
    pub fn write(&self, path: &Path) -> Result<(), DataError> {
        write_atomic(path, &self.to_bytes())
    }
}

pub use crate::data::write_atomic;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_trip_and_errors() {
        let mut st = SafeTensors::default();
        st.tensors.insert(
            "a".into(),
            Tensor {
                shape: vec![2, 3],
                data: vec![1.0, -2.0, 3.5, f32::MIN_POSITIVE, 0.0, 7.0],
            },
        );
        st.tensors.insert(
            "b".into(),
            Tensor {
                shape: vec![0],
                data: vec![],
            },
        );
        st.metadata.insert("step".into(), "12".into());
        let bytes = st.to_bytes();
        let p = Path::new("mem.safetensors");
        assert_eq!(SafeTensors::parse(&bytes, p).unwrap(), st);
        assert!(st.get("a", &[3, 2], p).is_err());
        assert!(st.get("c", &[1], p).is_err());
        // Truncations at every length fail cleanly.
        for cut in [0, 5, 8, 20, bytes.len() - 1] {
            let e = SafeTensors::parse(&bytes[..cut], p);
            assert!(e.is_err(), "cut at {cut}");
        }
        let mut bad = bytes.clone();
        bad[9] = b'!';
        assert!(SafeTensors::parse(&bad, p).is_err());
        // A shape whose element count fits a u64 but whose bytes do not is refused by name.
        let header = r#"{"t":{"dtype":"F32","shape":[4611686018427387905],"data_offsets":[0,4]}}"#;
        let mut huge = (header.len() as u64).to_le_bytes().to_vec();
        huge.extend(header.as_bytes());
        huge.extend([0u8; 4]);
        let e = SafeTensors::parse(&huge, p).unwrap_err().to_string();
        assert!(
            e.contains("mem.safetensors") && e.contains("overflows"),
            "{e}"
        );
    }

    #[test]
    fn atomic_write_replaces_the_file() {
        let dir = std::env::temp_dir().join(format!("extranerf-st-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("x.safetensors");
        std::fs::write(&path, b"old").unwrap();
        let st = SafeTensors::default();
        st.write(&path).unwrap();
        assert_eq!(SafeTensors::read(&path).unwrap(), st);
        assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 1);
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
