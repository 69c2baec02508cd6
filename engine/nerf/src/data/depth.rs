//! Depth supervision for training views: COLMAP sparse points projected into each view, and
//! dense depth maps from `.npy` or OpenEXR files.

use std::path::{Path, PathBuf};

use super::colmap::Point3D;
use super::npy::read_npy;
use super::{Camera, DataError, Result, Scene};

/// The channel that holds a field's ray-space depth (NDC t for forward-facing scenes, view
/// depth in scene units otherwise). `train --depth-dir` refuses it by name, so a render's depth
/// can never be read as capture-space depth.
pub const RAY_DEPTH_CHANNEL: &str = "T";

/// One depth target: pixel centre coordinates, depth along the viewing axis, confidence in
/// (0, 1] from the point's reprojection error.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct DepthSample {
    /// Pixel x (column) of the pixel the point falls in.
    pub x: u32,
    /// Pixel y (row).
    pub y: u32,
    /// Depth along the viewing axis, in scene units.
    pub depth: f64,
    /// 1 / (1 + (error / 1 px)^2).
    pub confidence: f64,
}

/// Projects the scene's sparse points (already in scene coordinates, see
/// [`Scene::transform_points`]) into `cam`: points behind the camera, outside the image or the
/// camera's depth bounds are dropped; where several land in one pixel the nearest is kept.
pub fn sparse_depth(cam: &Camera, world: &[glam::DVec3], points: &[Point3D]) -> Vec<DepthSample> {
    let mut best: std::collections::HashMap<(u32, u32), DepthSample> =
        std::collections::HashMap::new();
    let (near, far) = cam.bounds.unwrap_or((0.0, f64::INFINITY));
    for (p, src) in world.iter().zip(points) {
        let (u, v, d) = cam.project(*p);
        if !(d > 0.0 && d >= near * 0.5 && d <= far * 2.0)
            || !(u >= 0.0 && v >= 0.0 && u < cam.width as f64 && v < cam.height as f64)
        {
            continue;
        }
        let key = (u as u32, v as u32);
        let s = DepthSample {
            x: key.0,
            y: key.1,
            depth: d,
            confidence: 1.0 / (1.0 + src.error * src.error),
        };
        best.entry(key)
            .and_modify(|b| {
                if d < b.depth {
                    *b = s
                }
            })
            .or_insert(s);
    }
    let mut out: Vec<DepthSample> = best.into_values().collect();
    out.sort_by_key(|s| (s.y, s.x));
    out
}

/// Sparse depth targets for every camera of a scene.
pub fn sparse_depth_all(scene: &Scene, points: &[Point3D]) -> Vec<Vec<DepthSample>> {
    let world = scene.transform_points(points);
    scene
        .cameras
        .iter()
        .map(|c| sparse_depth(c, &world, points))
        .collect()
}

/// Reads a dense depth map (`.npy`, shape (H, W) or (H, W, 1), float32/64) for `cam`, checking
/// its size; non-finite or non-positive values mean "no depth" and become 0.
pub fn read_depth_npy(path: &Path, cam: &Camera) -> Result<Vec<f32>> {
    let a = read_npy(path)?;
    let (h, w) = match a.shape.as_slice() {
        [h, w] | [h, w, 1] => (*h, *w),
        s => {
            return Err(DataError::malformed(
                path,
                format!("depth map shape {s:?}: expected (H, W) or (H, W, 1)"),
            ))
        }
    };
    depth_for_view(path, cam, (w, h), a.data.iter().map(|&v| v as f32))
}

/// Where a dense depth map of `cam` lies in `dir`, named as its image: `<stem>.npy` and
/// `<stem>.exr`, in that order of preference.
pub fn view_depth_paths(dir: &Path, cam: &Camera) -> [PathBuf; 2] {
    let stem = cam
        .image
        .file_stem()
        .map(|s| s.to_string_lossy().to_string())
        .unwrap_or_default();
    [
        dir.join(format!("{stem}.npy")),
        dir.join(format!("{stem}.exr")),
    ]
}

/// The dense depth map of `cam` in `dir` ([`view_depth_paths`]; read as [`read_depth_npy`]
/// and [`read_depth_exr`] do), or `None` when neither file exists.
pub fn read_view_depth(dir: &Path, cam: &Camera) -> Result<Option<Vec<f32>>> {
    let [npy, exr] = view_depth_paths(dir, cam);
    if npy.exists() {
        read_depth_npy(&npy, cam).map(Some)
    } else if exr.exists() {
        read_depth_exr(&exr, cam).map(Some)
    } else {
        Ok(None)
    }
}

/// The unit of nerfstudio's depth files: millimetres (its `depth_unit_scale_factor`, 1e-3,
/// which it applies to `.png` and `.npy` files alike).
pub const NERFSTUDIO_DEPTH_UNIT: f64 = 1e-3;

/// Reads a depth file a capture names for `cam` (nerfstudio's `depth_file_path`): a greyscale
/// PNG of 16 (or 8) bits or a `.npy` array of shape (H, W) or (H, W, 1), both in millimetres
/// as nerfstudio reads them, returned in the capture's units ([`NERFSTUDIO_DEPTH_UNIT`]). A map
/// of another size with the view's aspect is resampled to it (the nearest sample, as
/// nerfstudio does); 0, non-finite and negative values mean "no depth".
pub fn read_capture_depth(path: &Path, cam: &Camera) -> Result<Vec<f32>> {
    let ext = path
        .extension()
        .map(|e| e.to_string_lossy().to_ascii_lowercase());
    let (w, h, mm): (usize, usize, Vec<f64>) = match ext.as_deref() {
        Some("png") => {
            let bytes = std::fs::read(path).map_err(|e| DataError::io(path, e))?;
            let img = image::load_from_memory_with_format(&bytes, image::ImageFormat::Png)
                .map_err(|e| DataError::Image {
                    path: path.to_path_buf(),
                    problem: e.to_string(),
                })?;
            let (w, h) = (img.width() as usize, img.height() as usize);
            let v = match img {
                image::DynamicImage::ImageLuma16(g) => {
                    g.into_raw().into_iter().map(f64::from).collect()
                }
                image::DynamicImage::ImageLuma8(g) => {
                    g.into_raw().into_iter().map(f64::from).collect()
                }
                other => {
                    return Err(DataError::malformed(
                        path,
                        format!(
                            "a depth PNG holds one grey channel (millimetres, 16 bits); this \
                             one is {:?}",
                            other.color()
                        ),
                    ))
                }
            };
            (w, h, v)
        }
        Some("npy") => {
            let a = read_npy(path)?;
            match a.shape.as_slice() {
                [h, w] | [h, w, 1] => (*w, *h, a.data),
                s => {
                    return Err(DataError::malformed(
                        path,
                        format!("depth map shape {s:?}: expected (H, W) or (H, W, 1)"),
                    ))
                }
            }
        }
        _ => {
            return Err(DataError::malformed(
                path,
                "a capture's depth file is a .png (16-bit millimetres) or a .npy",
            ))
        }
    };
    let (vw, vh) = (cam.width as usize, cam.height as usize);
    let values: Vec<f32> = if (w, h) == (vw, vh) {
        mm.iter()
            .map(|&v| (v * NERFSTUDIO_DEPTH_UNIT) as f32)
            .collect()
    } else {
        let (sx, sy) = (w as f64 / vw as f64, h as f64 / vh as f64);
        if w == 0 || h == 0 || (sx - sy).abs() > 0.01 * sx.max(sy) {
            return Err(DataError::malformed(
                path,
                format!(
                    "depth map is {w}x{h}, which does not have the aspect of its {vw}x{vh} view"
                ),
            ));
        }
        let mut out = Vec::with_capacity(vw * vh);
        for y in 0..vh {
            let sy_i = (((y as f64 + 0.5) * sy) as usize).min(h - 1);
            for x in 0..vw {
                let sx_i = (((x as f64 + 0.5) * sx) as usize).min(w - 1);
                out.push((mm[sy_i * w + sx_i] * NERFSTUDIO_DEPTH_UNIT) as f32);
            }
        }
        out
    };
    depth_for_view(path, cam, (vw, vh), values.into_iter())
}

/// Channel names taken as depth, in order of preference.
const DEPTH_CHANNELS: [&str; 6] = ["Z", "depth", "Depth", "D", "Y", "R"];

/// Reads a dense depth map from an OpenEXR file for `cam`: the first layer's `Z` (or `depth`,
/// `D`, `Y`, `R`, or its only) channel, any sample type; non-finite or non-positive values
/// become 0 ("no depth").
pub fn read_depth_exr(path: &Path, cam: &Camera) -> Result<Vec<f32>> {
    std::fs::metadata(path).map_err(|e| DataError::io(path, e))?;
    let img = exr::prelude::read_first_flat_layer_from_file(path)
        .map_err(|e| DataError::malformed(path, format!("cannot read as OpenEXR: {e}")))?;
    let layer = img.layer_data;
    let (w, h) = (layer.size.width(), layer.size.height());
    let channels = &layer.channel_data.list;
    let names: Vec<String> = channels.iter().map(|c| c.name.to_string()).collect();
    let pick = DEPTH_CHANNELS
        .iter()
        .find_map(|want| names.iter().position(|n| n == want))
        .or((channels.len() == 1 && names[0] != RAY_DEPTH_CHANNEL).then_some(0));
    if pick.is_none() && names.iter().any(|n| n == RAY_DEPTH_CHANNEL) {
        return Err(DataError::malformed(
            path,
            "holds a field's ray-space depth (channel T: NDC t for forward-facing scenes, as \
             `render` and `visibility` write it), not view depth in the capture's units; \
             `visibility --complete-depth` also writes NAME_view_depth.exr (channel Z) for this",
        ));
    }
    let Some(i) = pick else {
        return Err(DataError::malformed(
            path,
            format!("no depth channel among {names:?}; name it Z or depth"),
        ));
    };
    match &channels[i].sample_data {
        exr::prelude::FlatSamples::F16(v) => {
            depth_for_view(path, cam, (w, h), v.iter().map(|x| x.to_f32()))
        }
        exr::prelude::FlatSamples::F32(v) => depth_for_view(path, cam, (w, h), v.iter().copied()),
        exr::prelude::FlatSamples::U32(v) => {
            depth_for_view(path, cam, (w, h), v.iter().map(|&x| x as f32))
        }
    }
}

/// Checks a decoded depth map's size against its view and turns non-finite or non-positive
/// values into 0 ("no depth").
fn depth_for_view(
    path: &Path,
    cam: &Camera,
    (w, h): (usize, usize),
    values: impl Iterator<Item = f32>,
) -> Result<Vec<f32>> {
    if (w as u32, h as u32) != (cam.width, cam.height) {
        return Err(DataError::malformed(
            path,
            format!(
                "depth map is {w}x{h}, its view is {}x{}",
                cam.width, cam.height
            ),
        ));
    }
    Ok(values
        .map(|v| if v.is_finite() && v > 0.0 { v } else { 0.0 })
        .collect())
}
