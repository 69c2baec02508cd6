//! A reader for NumPy `.npy` files holding little-endian f64 or f32 arrays (C order), as LLFF's
//! `poses_bounds.npy` and depth maps are written.

use std::path::Path;

use super::{read_file, DataError, Result};

/// An array read from `.npy`, as f64.
#[derive(Clone, Debug, PartialEq)]
pub struct NpyArray {
    /// Dimensions.
    pub shape: Vec<usize>,
    /// Values in C (row-major) order.
    pub data: Vec<f64>,
}

/// Writes a little-endian f64 `.npy` file (format 1.0, C order), atomically.
pub fn write_npy_f64(path: &Path, shape: &[usize], data: &[f64]) -> Result<()> {
    if shape.iter().product::<usize>() != data.len() {
        return Err(DataError::malformed(
            path,
            format!("{} values for shape {shape:?}", data.len()),
        ));
    }
    let dims: Vec<String> = shape.iter().map(|d| d.to_string()).collect();
    let tuple = if dims.len() == 1 {
        format!("({},)", dims[0])
    } else {
        format!("({})", dims.join(", "))
    };
    let mut header = format!("{{'descr': '<f8', 'fortran_order': False, 'shape': {tuple}, }}");
    while (10 + header.len() + 1) % 64 != 0 {
        header.push(' ');
    }
    header.push('\n');
    let mut out = b"\x93NUMPY\x01\x00".to_vec();
    out.extend_from_slice(&(header.len() as u16).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    for v in data {
        out.extend_from_slice(&v.to_le_bytes());
    }
    super::write_atomic(path, &out)
}

/// Reads a `.npy` file with dtype `<f8` or `<f4` in C order.
pub fn read_npy(path: &Path) -> Result<NpyArray> {
    parse_npy(&read_file(path)?, path)
}

/// Parses `.npy` bytes; `path` only names the source in errors.
pub fn parse_npy(bytes: &[u8], path: &Path) -> Result<NpyArray> {
    let bad = |p: &str| DataError::malformed(path, format!("not a valid .npy file: {p}"));
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err(bad("missing the \\x93NUMPY magic"));
    }
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        v => return Err(bad(&format!("unsupported format version {v}"))),
    };
    let header = bytes
        .get(start..start + header_len)
        .ok_or_else(|| bad("header runs past the end of the file"))?;
    let header = std::str::from_utf8(header).map_err(|_| bad("header is not text"))?;
    let field = |name: &str| -> Option<&str> {
        let at = header.find(&format!("'{name}'"))?;
        let rest = header[at + name.len() + 2..]
            .trim_start()
            .strip_prefix(':')?
            .trim_start();
        Some(rest)
    };
    let descr = field("descr")
        .and_then(|r| r.strip_prefix('\''))
        .and_then(|r| r.split('\'').next())
        .ok_or_else(|| bad("no 'descr' in the header"))?;
    let width = match descr {
        "<f8" | "=f8" => 8,
        "<f4" | "=f4" => 4,
        other => {
            return Err(DataError::malformed(
                path,
                format!(
                    "dtype {other} is not supported (expected little-endian float64 or float32)"
                ),
            ))
        }
    };
    if field("fortran_order").is_some_and(|r| r.starts_with("True")) {
        return Err(DataError::malformed(
            path,
            "Fortran-order arrays are not supported; save with np.ascontiguousarray",
        ));
    }
    let shape_txt = field("shape")
        .and_then(|r| r.strip_prefix('('))
        .and_then(|r| r.split(')').next())
        .ok_or_else(|| bad("no 'shape' in the header"))?;
    let shape = shape_txt
        .split(',')
        .map(str::trim)
        .filter(|s| !s.is_empty())
        .map(|s| {
            s.parse::<usize>()
                .map_err(|_| bad(&format!("bad shape entry `{s}`")))
        })
        .collect::<Result<Vec<_>>>()?;
    let count = shape
        .iter()
        .try_fold(1usize, |a, &d| a.checked_mul(d))
        .ok_or_else(|| bad("shape overflows"))?;
    let body = &bytes[start + header_len..];
    let need = count
        .checked_mul(width)
        .ok_or_else(|| bad(&format!("shape {shape:?} overflows")))?;
    if body.len() != need {
        return Err(DataError::malformed(
            path,
            format!(
                "shape {shape:?} needs {need} bytes of data, the file has {}",
                body.len()
            ),
        ));
    }
    let data = if width == 8 {
        body.chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect()
    } else {
        body.chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")) as f64)
            .collect()
    };
    Ok(NpyArray { shape, data })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn npy(descr: &str, shape: &str, body: &[u8]) -> Vec<u8> {
        let mut h = format!("{{'descr': '{descr}', 'fortran_order': False, 'shape': {shape}, }}");
        while (10 + h.len() + 1) % 64 != 0 {
            h.push(' ');
        }
        h.push('\n');
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend((h.len() as u16).to_le_bytes());
        b.extend(h.as_bytes());
        b.extend(body);
        b
    }

    #[test]
    fn parses_f8_and_f4() {
        let body: Vec<u8> = [1.5f64, -2.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let a = parse_npy(&npy("<f8", "(2,)", &body), Path::new("x.npy")).unwrap();
        assert_eq!((a.shape, a.data), (vec![2], vec![1.5, -2.0]));
        let body: Vec<u8> = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0]
            .iter()
            .flat_map(|v| v.to_le_bytes())
            .collect();
        let a = parse_npy(&npy("<f4", "(2, 3)", &body), Path::new("x.npy")).unwrap();
        assert_eq!(a.shape, vec![2, 3]);
        assert_eq!(a.data[5], 6.0);
    }

    #[test]
    fn malformed_files_are_named_errors() {
        let p = Path::new("poses_bounds.npy");
        let cases: Vec<(Vec<u8>, &str)> = vec![
            (b"garbage".to_vec(), "magic"),
            (npy("<i4", "(1,)", &[0; 4]), "dtype <i4"),
            (npy("<f8", "(3,)", &[0; 16]), "needs 24 bytes"),
            (npy("<f8", "(a,)", &[]), "bad shape"),
            (b"\x93NUMPY\x01\x00\xff\x00{".to_vec(), "past the end"),
            // The element count fits a usize but its bytes do not (once a multiplication that
            // overflowed, a panic in debug builds and a wrong size check in release).
            (npy("<f8", "(4611686018427387904,)", &[]), "overflows"),
            (npy("<f8", "(4294967296, 4294967296)", &[]), "overflows"),
        ];
        for (bytes, want) in cases {
            let e = parse_npy(&bytes, p).unwrap_err().to_string();
            assert!(e.contains("poses_bounds.npy") && e.contains(want), "{e}");
        }
    }
}
