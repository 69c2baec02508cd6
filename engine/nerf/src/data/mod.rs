//! Scene data: cameras in one convention, images, sparse points, and the evaluation splits.
//!
//! Convention: camera-to-world matrices in the OpenGL / NeRF convention (camera x right, y up,
//! looking along -z), world units as the loader leaves them (LLFF: rescaled so the nearest
//! bound is 1 / 0.75, as the original NeRF loader does), pixel centres at +0.5.
//! Every error names the file and the problem.

pub mod colmap;
pub mod colmap_scene;
pub mod depth;
pub mod llff;
pub mod npy;
pub mod scene;
pub mod split;
pub mod transforms;

pub use scene::{Scene, SplitIndices};

use std::path::{Path, PathBuf};

use glam::{DMat4, DVec3};

/// What went wrong reading scene data; always names the file.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// The file or folder is missing or unreadable.
    #[error("{path}: {error}")]
    Io {
        /// The path.
        path: PathBuf,
        /// The OS error (in the message, not a separate source, so a chain does not print it
        /// twice).
        error: std::io::Error,
    },
    /// The file exists but its content is wrong.
    #[error("{path}: {problem}")]
    Malformed {
        /// The path.
        path: PathBuf,
        /// What is wrong.
        problem: String,
    },
    /// An image could not be decoded.
    #[error("{path}: cannot decode image: {problem}")]
    Image {
        /// The path.
        path: PathBuf,
        /// The decoder's message.
        problem: String,
    },
}

impl DataError {
    pub(crate) fn malformed(path: &Path, problem: impl Into<String>) -> DataError {
        DataError::Malformed {
            path: path.to_path_buf(),
            problem: problem.into(),
        }
    }

    pub(crate) fn io(path: &Path, source: std::io::Error) -> DataError {
        DataError::Io {
            path: path.to_path_buf(),
            error: source,
        }
    }
}

/// Result alias of the data module.
pub type Result<T, E = DataError> = std::result::Result<T, E>;

/// A pinhole camera with its image.
#[derive(Clone, Debug, PartialEq)]
pub struct Camera {
    /// Camera to world (OpenGL convention: x right, y up, looking along -z).
    pub c2w: DMat4,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Focal length in pixels, x.
    pub fx: f64,
    /// Focal length in pixels, y.
    pub fy: f64,
    /// Principal point x in pixels.
    pub cx: f64,
    /// Principal point y in pixels.
    pub cy: f64,
    /// Near / far depth bounds along the viewing axis when the format gives them.
    pub bounds: Option<(f64, f64)>,
    /// The image file.
    pub image: PathBuf,
}

impl Camera {
    /// The same camera at 1/`factor` of its resolution (integer division, at least 1 pixel;
    /// intrinsics scaled by the actual size ratio, so the field of view is kept).
    pub fn downscaled(&self, factor: u32) -> Camera {
        let f = factor.max(1);
        let mut c = self.clone();
        c.width = (self.width / f).max(1);
        c.height = (self.height / f).max(1);
        let sx = c.width as f64 / self.width.max(1) as f64;
        let sy = c.height as f64 / self.height.max(1) as f64;
        c.fx = self.fx * sx;
        c.fy = self.fy * sy;
        c.cx = self.cx * sx;
        c.cy = self.cy * sy;
        c
    }

    /// Camera centre in world coordinates.
    pub fn centre(&self) -> DVec3 {
        self.c2w.w_axis.truncate()
    }

    /// The world ray through continuous pixel coordinates (x, y): origin and direction, the
    /// direction scaled to unit depth along the viewing axis.
    pub fn ray(&self, x: f64, y: f64) -> (DVec3, DVec3) {
        let dc = DVec3::new((x - self.cx) / self.fx, -(y - self.cy) / self.fy, -1.0);
        (
            self.c2w.w_axis.truncate(),
            glam::DMat3::from_mat4(self.c2w) * dc,
        )
    }

    /// The world point at ray-space depth `depth` along the ray through (x, y): view depth
    /// for a world-space field, NDC t (near plane 1) for an NDC one. None where the depth has
    /// no world point (NDC t >= 1 is at or beyond infinity, or the ray runs parallel to the
    /// near plane).
    pub fn ray_point(&self, x: f64, y: f64, depth: f64, ndc: bool) -> Option<DVec3> {
        let (o, d) = self.ray(x, y);
        if !ndc {
            return Some(o + d * depth);
        }
        // NDC z = 2t - 1 along any camera ray; world z = 2 / (NDC z - 1) = 1 / (t - 1).
        if depth.is_nan() || depth >= 1.0 || d.z.abs() < 1e-12 {
            return None;
        }
        let z = 1.0 / (depth - 1.0);
        let s = (z - o.z) / d.z;
        Some(o + d * s)
    }

    /// Projects a world point: (pixel x, pixel y, depth along the viewing axis). Depth <= 0
    /// means the point is behind the camera.
    pub fn project(&self, p: DVec3) -> (f64, f64, f64) {
        let c = self.c2w.inverse().transform_point3(p);
        let depth = -c.z;
        (
            self.cx + self.fx * c.x / depth,
            self.cy - self.fy * c.y / depth,
            depth,
        )
    }
}

/// The nearest near bound and the farthest far bound of `cameras` (those that give bounds);
/// `None` when none does, or they do not satisfy 0 < near < far.
pub fn depth_bounds(cameras: &[Camera]) -> Option<(f64, f64)> {
    let near = cameras
        .iter()
        .filter_map(|c| c.bounds.map(|b| b.0))
        .fold(f64::INFINITY, f64::min);
    let far = cameras
        .iter()
        .filter_map(|c| c.bounds.map(|b| b.1))
        .fold(0.0f64, f64::max);
    (near.is_finite() && near > 0.0 && far > near).then_some((near, far))
}

/// An RGB image as linear-in-file f32 values in [0, 1], row-major, 3 channels, with its alpha
/// when the file has one (straight, not premultiplied: NeRF-synthetic's RGBA PNGs).
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
    /// `width * height * 3` values.
    pub rgb: Vec<f32>,
    /// `width * height` coverage values in [0, 1]; `None`: opaque.
    pub alpha: Option<Vec<f32>>,
}

impl Image {
    /// An opaque image.
    pub fn opaque(width: u32, height: u32, rgb: Vec<f32>) -> Image {
        Image {
            width,
            height,
            rgb,
            alpha: None,
        }
    }

    /// The image composited over a uniform `background` (rgb * alpha + background *
    /// (1 - alpha)), opaque; an opaque image comes back unchanged.
    pub fn over(self, background: [f32; 3]) -> Image {
        let Some(alpha) = self.alpha else {
            return self;
        };
        let rgb = self
            .rgb
            .chunks_exact(3)
            .zip(&alpha)
            .flat_map(|(c, &a)| (0..3).map(move |k| c[k] * a + background[k] * (1.0 - a)))
            .collect();
        Image::opaque(self.width, self.height, rgb)
    }
}

/// Decodes an image file (PNG or JPEG; 16-bit scaled) to RGB f32, keeping an alpha channel
/// when the file has one that is not everywhere 1.
pub fn load_image(path: &Path) -> Result<Image> {
    let img = image::open(path).map_err(|e| match e {
        image::ImageError::IoError(io) => DataError::io(path, io),
        e => DataError::Image {
            path: path.to_path_buf(),
            problem: e.to_string(),
        },
    })?;
    let (width, height) = (img.width(), img.height());
    if !img.color().has_alpha() {
        return Ok(Image::opaque(width, height, img.into_rgb32f().into_raw()));
    }
    // One conversion, split into colour and alpha.
    let rgba = img.into_rgba32f().into_raw();
    let rgb = rgba
        .chunks_exact(4)
        .flat_map(|p| [p[0], p[1], p[2]])
        .collect();
    let alpha: Vec<f32> = rgba.chunks_exact(4).map(|p| p[3]).collect();
    Ok(Image {
        width,
        height,
        rgb,
        alpha: alpha.iter().any(|&v| v < 1.0).then_some(alpha),
    })
}

/// A value in [0, 1] (clamped) as 8 bits, rounded to nearest: what PNG writers and the
/// training pixel store keep (WGSL's `pack4x8unorm` per channel).
pub fn unorm8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// [`load_image`] composited over `background` (what a render with that background is
/// compared with).
pub fn load_image_over(path: &Path, background: [f32; 3]) -> Result<Image> {
    Ok(load_image(path)?.over(background))
}

/// The width and height of the image file at `path`, from its header.
pub(crate) fn image_size(path: &Path) -> Result<(u32, u32)> {
    image::image_dimensions(path).map_err(|e| match e {
        image::ImageError::IoError(io) => DataError::io(path, io),
        e => DataError::Image {
            path: path.to_path_buf(),
            problem: e.to_string(),
        },
    })
}

/// Reads a whole file, naming it in the error.
pub(crate) fn read_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| DataError::io(path, e))
}

/// Image files (png, jpg, jpeg; any case) in a folder, sorted by name.
pub(crate) fn list_images(dir: &Path) -> Result<Vec<PathBuf>> {
    let rd = std::fs::read_dir(dir).map_err(|e| DataError::io(dir, e))?;
    let mut out = Vec::new();
    for entry in rd {
        let p = entry.map_err(|e| DataError::io(dir, e))?.path();
        let ext = p
            .extension()
            .and_then(|e| e.to_str())
            .map(str::to_ascii_lowercase);
        if matches!(ext.as_deref(), Some("png" | "jpg" | "jpeg")) {
            out.push(p);
        }
    }
    out.sort();
    Ok(out)
}

/// Writes `bytes` to `path` atomically ([`extranerf_gpu::files::write_atomic`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> std::result::Result<(), DataError> {
    extranerf_gpu::files::write_atomic(path, bytes).map_err(|e| DataError::io(path, e))
}
