//! The image and depth files a run writes: 8-bit PNG and f32 OpenEXR, each atomically.

use std::path::Path;

use image::ImageEncoder;

use crate::data::{unorm8, Camera};
use crate::run_error::{Result, RunError};
use crate::safetensors::write_atomic;

/// Writes an RGB f32 image (values clamped to [0, 1]) as an 8-bit PNG, atomically.
pub fn write_png(path: &Path, width: u32, height: u32, rgb: &[f32]) -> Result<()> {
    if rgb.len() != width as usize * height as usize * 3 {
        return Err(RunError::Config(format!(
            "{}: {} values for a {width}x{height} RGB image",
            path.display(),
            rgb.len()
        )));
    }
    let bytes: Vec<u8> = rgb.iter().map(|&v| unorm8(v)).collect();
    write_png_bytes(path, width, height, &bytes, image::ExtendedColorType::Rgb8)
}

/// Encodes 8-bit pixels as PNG and writes them atomically.
fn write_png_bytes(
    path: &Path,
    width: u32,
    height: u32,
    bytes: &[u8],
    colour: image::ExtendedColorType,
) -> Result<()> {
    let mut png = Vec::new();
    image::codecs::png::PngEncoder::new(&mut png)
        .write_image(bytes, width, height, colour)
        .map_err(|e| RunError::Config(format!("{}: cannot encode PNG: {e}", path.display())))?;
    write_atomic(path, &png)?;
    Ok(())
}

/// Writes a straight-alpha RGBA image (colour and alpha clamped to [0, 1]) as an 8-bit PNG,
/// atomically.
pub fn write_png_rgba(
    path: &Path,
    width: u32,
    height: u32,
    rgb: &[f32],
    alpha: &[f32],
) -> Result<()> {
    let px = width as usize * height as usize;
    if rgb.len() != px * 3 || alpha.len() != px {
        return Err(RunError::Config(format!(
            "{}: {} colour and {} alpha values for a {width}x{height} RGBA image",
            path.display(),
            rgb.len(),
            alpha.len()
        )));
    }
    let bytes: Vec<u8> = rgb
        .chunks_exact(3)
        .zip(alpha)
        .flat_map(|(c, &a)| [unorm8(c[0]), unorm8(c[1]), unorm8(c[2]), unorm8(a)])
        .collect();
    write_png_bytes(path, width, height, &bytes, image::ExtendedColorType::Rgba8)
}

/// Writes a view-depth map in the capture's units (what `train --depth-dir` reads) as a
/// single-channel f32 OpenEXR file (channel `Z`).
pub fn write_depth_exr(path: &Path, width: u32, height: u32, depth: &[f32]) -> Result<()> {
    write_exr_channels(path, width, height, &[("Z", depth)])
}

pub use crate::data::depth::RAY_DEPTH_CHANNEL;

/// Writes a field's ray-space depth (renders, visibility) as a single-channel f32 OpenEXR
/// file (channel [`RAY_DEPTH_CHANNEL`]).
pub fn write_ray_depth_exr(path: &Path, width: u32, height: u32, depth: &[f32]) -> Result<()> {
    write_exr_channels(path, width, height, &[(RAY_DEPTH_CHANNEL, depth)])
}

/// A ray-space depth map of `cam` (NDC t when `ndc`) as view depth in the capture's units
/// (`world_scale`: the scene's `world_from_source` scale); 0 where there is no world point.
pub fn ray_depth_to_view_depth(
    cam: &Camera,
    depth: &[f32],
    ndc: bool,
    world_scale: f64,
) -> Vec<f32> {
    depth
        .iter()
        .enumerate()
        .map(|(i, &t)| {
            let (x, y) = (
                (i as u32 % cam.width) as f64 + 0.5,
                (i as u32 / cam.width) as f64 + 0.5,
            );
            match cam.ray_point(x, y, t as f64, ndc) {
                Some(p) => {
                    let z = cam.project(p).2;
                    if z > 0.0 && z.is_finite() {
                        (z / world_scale) as f32
                    } else {
                        0.0
                    }
                }
                None => 0.0,
            }
        })
        .collect()
}

/// Writes named f32 channels of one image as an OpenEXR file, atomically.
pub fn write_exr_channels(
    path: &Path,
    width: u32,
    height: u32,
    channels: &[(&str, &[f32])],
) -> Result<()> {
    use exr::prelude::*;
    let mut list = SmallVec::new();
    for (name, data) in channels {
        if data.len() != width as usize * height as usize {
            return Err(RunError::Config(format!(
                "{}: {} values in channel {name} for {width}x{height}",
                path.display(),
                data.len()
            )));
        }
        list.push(AnyChannel::new(*name, FlatSamples::F32(data.to_vec())));
    }
    let layer = Layer::new(
        (width as usize, height as usize),
        LayerAttributes::named("image"),
        Encoding::FAST_LOSSLESS,
        AnyChannels::sort(list),
    );
    // Encoded in memory, then written like every other output (synced temp file + rename).
    let mut bytes = Vec::new();
    exr::image::Image::from_layer(layer)
        .write()
        .to_buffered(std::io::Cursor::new(&mut bytes))
        .map_err(|e| RunError::Config(format!("{}: cannot encode EXR: {e}", path.display())))?;
    write_atomic(path, &bytes)?;
    Ok(())
}
