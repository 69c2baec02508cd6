//! COLMAP binary model readers: `cameras.bin` and `points3D.bin`.

use std::path::Path;

use glam::DVec3;

use super::{read_file, DataError, Result};

/// COLMAP camera models with their parameter counts (COLMAP's model ids 0..=10).
const MODELS: [(&str, usize); 11] = [
    ("SIMPLE_PINHOLE", 3),
    ("PINHOLE", 4),
    ("SIMPLE_RADIAL", 4),
    ("RADIAL", 5),
    ("OPENCV", 8),
    ("OPENCV_FISHEYE", 8),
    ("FULL_OPENCV", 12),
    ("FOV", 5),
    ("SIMPLE_RADIAL_FISHEYE", 4),
    ("RADIAL_FISHEYE", 5),
    ("THIN_PRISM_FISHEYE", 12),
];

/// One camera of `cameras.bin`.
#[derive(Clone, Debug, PartialEq)]
pub struct ColmapCamera {
    /// COLMAP camera id.
    pub id: u32,
    /// Model name, e.g. `SIMPLE_RADIAL`.
    pub model: &'static str,
    /// Image width.
    pub width: u64,
    /// Image height.
    pub height: u64,
    /// The model's parameters in COLMAP's order (focal(s), principal point, distortion).
    pub params: Vec<f64>,
}

/// One point of `points3D.bin`.
#[derive(Clone, Debug, PartialEq)]
pub struct Point3D {
    /// COLMAP point id.
    pub id: u64,
    /// Position in COLMAP's world.
    pub xyz: DVec3,
    /// Colour.
    pub rgb: [u8; 3],
    /// Mean reprojection error in pixels.
    pub error: f64,
    /// (image id, 2-D point index) observations.
    pub track: Vec<(u32, u32)>,
}

struct Reader<'a> {
    bytes: &'a [u8],
    at: usize,
    path: &'a Path,
}

impl Reader<'_> {
    fn take(&mut self, n: usize, what: &str) -> Result<&[u8]> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.bytes.len());
        let Some(end) = end else {
            return Err(DataError::malformed(
                self.path,
                format!(
                    "truncated: {what} at byte {} needs {n} bytes, the file has {}",
                    self.at,
                    self.bytes.len()
                ),
            ));
        };
        let s = &self.bytes[self.at..end];
        self.at = end;
        Ok(s)
    }
    fn u64(&mut self, what: &str) -> Result<u64> {
        Ok(u64::from_le_bytes(
            self.take(8, what)?.try_into().expect("8 bytes"),
        ))
    }
    fn u32(&mut self, what: &str) -> Result<u32> {
        Ok(u32::from_le_bytes(
            self.take(4, what)?.try_into().expect("4 bytes"),
        ))
    }
    fn f64(&mut self, what: &str) -> Result<f64> {
        let v = f64::from_le_bytes(self.take(8, what)?.try_into().expect("8 bytes"));
        if !v.is_finite() {
            return Err(DataError::malformed(
                self.path,
                format!("{what} at byte {} is not finite ({v})", self.at - 8),
            ));
        }
        Ok(v)
    }
    /// A count, refused when even the smallest records could not fit in the rest of the file.
    fn count(&mut self, what: &str, min_record: usize) -> Result<usize> {
        let n = self.u64(what)?;
        let left = (self.bytes.len() - self.at) as u64;
        if n.saturating_mul(min_record as u64) > left {
            return Err(DataError::malformed(
                self.path,
                format!("truncated or corrupt: {what} says {n}, but only {left} bytes follow"),
            ));
        }
        Ok(n as usize)
    }
}

/// Reads COLMAP's `cameras.bin`.
pub fn read_cameras_bin(path: &Path) -> Result<Vec<ColmapCamera>> {
    let bytes = read_file(path)?;
    let mut r = Reader {
        bytes: &bytes,
        at: 0,
        path,
    };
    let n = r.count("camera count", 24)?;
    let mut cams = Vec::with_capacity(n);
    for _ in 0..n {
        let id = r.u32("camera id")?;
        let model_id = r.u32("camera model")?;
        let &(model, nparams) = MODELS.get(model_id as usize).ok_or_else(|| {
            DataError::malformed(path, format!("camera {id} has unknown model id {model_id}"))
        })?;
        let width = r.u64("width")?;
        let height = r.u64("height")?;
        let params = (0..nparams)
            .map(|_| r.f64("camera parameter"))
            .collect::<Result<Vec<_>>>()?;
        cams.push(ColmapCamera {
            id,
            model,
            width,
            height,
            params,
        });
    }
    if r.at != bytes.len() {
        return Err(DataError::malformed(
            path,
            format!("{} bytes left after {n} cameras", bytes.len() - r.at),
        ));
    }
    Ok(cams)
}

/// Reads COLMAP's `points3D.bin`.
pub fn read_points3d_bin(path: &Path) -> Result<Vec<Point3D>> {
    let bytes = read_file(path)?;
    let mut r = Reader {
        bytes: &bytes,
        at: 0,
        path,
    };
    let n = r.count("point count", 43)?;
    let mut points = Vec::with_capacity(n);
    for _ in 0..n {
        let id = r.u64("point id")?;
        let xyz = DVec3::new(r.f64("x")?, r.f64("y")?, r.f64("z")?);
        let c = r.take(3, "colour")?;
        let rgb = [c[0], c[1], c[2]];
        let error = r.f64("reprojection error")?;
        let len = r.count("track length", 8)?;
        let track = (0..len)
            .map(|_| Ok((r.u32("track image id")?, r.u32("track point index")?)))
            .collect::<Result<Vec<_>>>()?;
        points.push(Point3D {
            id,
            xyz,
            rgb,
            error,
            track,
        });
    }
    if r.at != bytes.len() {
        return Err(DataError::malformed(
            path,
            format!("{} bytes left after {n} points", bytes.len() - r.at),
        ));
    }
    Ok(points)
}
