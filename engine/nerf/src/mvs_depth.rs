//! Dense depth for a scene's training views from the project's plane sweep ([`crate::mvs`]):
//! the depth target of scenes that bring none (issue 52). [`compute`] matches the views at a
//! fraction of their resolution and returns maps at their full size; [`cached`] keeps them in
//! a run folder, keyed by the views' paths (relative to the scene), their bytes, their cameras
//! and the settings, so that an unchanged input reuses them and any change recomputes them.

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};

use crate::data::depth::read_depth_exr;
use crate::data::{load_image, Camera, DataError};
use crate::depth_completion::DepthCompletion;
use crate::image_ops::{downscale_rgb, grey};
use crate::mvs::{Mvs, MvsConfig, MvsDepth};
use crate::run_error::{Result, RunError};
use crate::write::write_depth_exr;
use extranerf_gpu::Context;

/// Folder of the cache inside a run folder.
pub const CACHE_DIR: &str = "depth_mvs";
/// The cache's key file, written last.
const KEY_FILE: &str = "key.json";

/// Plane-sweep settings for depth supervision: [`MvsConfig`]'s matching settings, the
/// matching resolution and the depth range.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct MvsDepthSettings {
    /// Match at 1/downscale of the images' resolution (box-filtered).
    pub downscale: u32,
    /// Depth planes, uniform in inverse depth.
    pub planes: u32,
    /// Nearest plane in scene units; `None`: 0.8 x the smallest near bound of the views.
    pub near: Option<f32>,
    /// Farthest plane; `None`: 1.2 x the largest far bound.
    pub far: Option<f32>,
    /// NCC window radius ((2r+1)^2 pixels).
    pub radius: u32,
    /// Sources averaged per plane (the lowest costs).
    pub best_k: u32,
    /// Other views whose depth must agree for a pixel to be kept.
    pub min_agree: u32,
    /// Agreement: reprojection error in pixels at the matching resolution.
    pub px_tol: f32,
    /// Agreement: relative depth difference.
    pub rel_tol: f32,
    /// Jacobi sweeps that fill the pixels the sweep kept no depth for (0: leave them empty):
    /// a colour-guided harmonic fill in inverse depth at the matching resolution; filled
    /// pixels take the confidence [`FILL_CONFIDENCE`].
    #[serde(default)]
    pub fill: u32,
}

/// Confidence (the depth loss's weight) of a pixel the fill gave its depth.
pub const FILL_CONFIDENCE: f32 = 0.25;
/// Colour difference at which a neighbour's weight in the fill falls to 1/e.
const FILL_SIGMA: f32 = 0.1;

impl Default for MvsDepthSettings {
    fn default() -> Self {
        let c = MvsConfig::new(1.0, 2.0);
        MvsDepthSettings {
            downscale: 2,
            planes: c.planes,
            near: None,
            far: None,
            radius: c.radius,
            best_k: c.best_k,
            min_agree: c.min_agree,
            px_tol: c.px_tol,
            rel_tol: c.rel_tol,
            fill: 0,
        }
    }
}

impl MvsDepthSettings {
    /// The depth range: the settings' own, else from the cameras' bounds.
    pub fn range(&self, cams: &[Camera]) -> Result<(f32, f32)> {
        let bounds: Vec<(f64, f64)> = cams.iter().filter_map(|c| c.bounds).collect();
        let missing = || {
            RunError::Config(
                "multi-view stereo: the scene gives no depth bounds; set the nearest and farthest plane"
                    .into(),
            )
        };
        let near = match self.near {
            Some(v) => v,
            None if !bounds.is_empty() => {
                0.8 * bounds.iter().map(|b| b.0).fold(f64::INFINITY, f64::min) as f32
            }
            None => return Err(missing()),
        };
        let far = match self.far {
            Some(v) => v,
            None if !bounds.is_empty() => {
                1.2 * bounds.iter().map(|b| b.1).fold(0.0, f64::max) as f32
            }
            None => return Err(missing()),
        };
        Ok((near, far))
    }

    /// The sweep's configuration for a depth range.
    pub fn config(&self, near: f32, far: f32) -> MvsConfig {
        MvsConfig {
            planes: self.planes,
            near,
            far,
            radius: self.radius,
            best_k: self.best_k,
            min_agree: self.min_agree,
            px_tol: self.px_tol,
            rel_tol: self.rel_tol,
        }
    }
}

/// One view's depth at its full size.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewDepth {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Depth along the viewing axis in scene units; 0 where the sweep kept none.
    pub depth: Vec<f32>,
    /// Confidence in [0, 1] (the winning NCC); 0 where no depth.
    pub confidence: Vec<f32>,
}

impl ViewDepth {
    /// Fraction of pixels with a depth.
    pub fn coverage(&self) -> f64 {
        self.depth.iter().filter(|&&d| d > 0.0).count() as f64 / self.depth.len().max(1) as f64
    }
}

/// The sweep's result for a set of views.
#[derive(Clone, Debug)]
pub struct SceneDepth {
    /// Per view at its full size (nearest-neighbour upsampling of `maps`).
    pub views: Vec<ViewDepth>,
    /// Per view at the matching resolution.
    pub maps: Vec<MvsDepth>,
    /// The depth range swept.
    pub near: f32,
    /// See `near`.
    pub far: f32,
    /// Matching resolution.
    pub width: u32,
    /// See `width`.
    pub height: u32,
    /// Seconds of the sweep and the consistency pass (images loaded before).
    pub seconds: f64,
}

/// Plane-sweep depth of `cams` (full-size cameras, one size; their images are read) against
/// each other.
pub fn compute(ctx: &Context, cams: &[Camera], settings: &MvsDepthSettings) -> Result<SceneDepth> {
    if settings.downscale == 0 {
        return Err(RunError::Config(
            "multi-view stereo: downscale must be at least 1".into(),
        ));
    }
    let (near, far) = settings.range(cams)?;
    let mut small = Vec::with_capacity(cams.len());
    let mut greys = Vec::with_capacity(cams.len());
    let mut colours = Vec::with_capacity(cams.len());
    for c in cams {
        let img = load_image(&c.image)?;
        if (img.width, img.height) != (c.width, c.height) {
            return Err(DataError::malformed(
                &c.image,
                format!(
                    "image is {}x{} but its camera says {}x{}",
                    img.width, img.height, c.width, c.height
                ),
            )
            .into());
        }
        let (rgb, w, h) = downscale_rgb(&img.rgb, img.width, img.height, settings.downscale)
            .map_err(|e| DataError::malformed(&c.image, e.to_string()))?;
        let cam = c.downscaled(settings.downscale);
        if (cam.width, cam.height) != (w, h) {
            return Err(RunError::Config(format!(
                "multi-view stereo: {} shrinks to {w}x{h} but its camera to {}x{}",
                c.image.display(),
                cam.width,
                cam.height
            )));
        }
        greys.push(grey(&rgb));
        colours.push(rgb);
        small.push(cam);
    }
    let t = Instant::now();
    let maps = Mvs::new(ctx)?.run(ctx, &small, &greys, &settings.config(near, far))?;
    let dc = DepthCompletion::new(ctx)?;
    let mut views = Vec::with_capacity(cams.len());
    for ((c, m), rgb) in cams.iter().zip(&maps).zip(&colours) {
        let (depth, confidence) = fill_holes(ctx, &dc, m, rgb, (near, far), settings.fill)?;
        views.push(upsample(
            (m.width, m.height),
            &depth,
            &confidence,
            c.width,
            c.height,
            settings.downscale,
        ));
    }
    let seconds = t.elapsed().as_secs_f64();
    Ok(SceneDepth {
        views,
        maps,
        near,
        far,
        width: small.first().map_or(0, |c| c.width),
        height: small.first().map_or(0, |c| c.height),
        seconds,
    })
}

/// `iterations` Jacobi sweeps of the colour-guided harmonic fill ([`DepthCompletion`]) over
/// the pixels of `m` without depth, in inverse depth (in which a plane is affine across the
/// image, so the fill reproduces one), guided by the matching-resolution colour `rgb`; filled
/// depths are clamped to the sweep's range and take [`FILL_CONFIDENCE`]. Returns the depth and
/// confidence (as kept where `iterations` is 0 or nothing or everything was kept).
pub fn fill_holes(
    ctx: &Context,
    dc: &DepthCompletion,
    m: &MvsDepth,
    rgb: &[f32],
    (near, far): (f32, f32),
    iterations: u32,
) -> Result<(Vec<f32>, Vec<f32>)> {
    let known: Vec<u32> = m.depth.iter().map(|&d| u32::from(d > 0.0)).collect();
    let kept = known.iter().filter(|&&k| k != 0).count();
    if iterations == 0 || kept == 0 || kept == known.len() {
        return Ok((m.depth.clone(), m.confidence.clone()));
    }
    let mean_inv = m
        .depth
        .iter()
        .filter(|&&d| d > 0.0)
        .map(|&d| 1.0 / d as f64)
        .sum::<f64>()
        / kept as f64;
    let inv: Vec<f32> = m
        .depth
        .iter()
        .map(|&d| if d > 0.0 { 1.0 / d } else { mean_inv as f32 })
        .collect();
    let guide: Vec<[f32; 4]> = rgb
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2], 0.0])
        .collect();
    let filled = dc.run(
        ctx, m.width, m.height, &inv, &known, &guide, FILL_SIGMA, iterations,
    )?;
    let mut depth = m.depth.clone();
    let mut confidence = m.confidence.clone();
    for (i, &k) in known.iter().enumerate() {
        if k == 0 && filled[i] > 0.0 && filled[i].is_finite() {
            depth[i] = (1.0 / filled[i]).clamp(near, far);
            confidence[i] = FILL_CONFIDENCE;
        }
    }
    Ok((depth, confidence))
}

/// A matching-resolution map (`depth`, `confidence` of `size`) at `width` x `height` (nearest
/// neighbour; the pixels past the last whole block take the last row or column).
fn upsample(
    (mw, mh): (u32, u32),
    src_depth: &[f32],
    src_confidence: &[f32],
    width: u32,
    height: u32,
    factor: u32,
) -> ViewDepth {
    let mut depth = Vec::with_capacity((width * height) as usize);
    let mut confidence = Vec::with_capacity((width * height) as usize);
    for y in 0..height {
        let sy = (y / factor).min(mh - 1);
        for x in 0..width {
            let sx = (x / factor).min(mw - 1);
            let k = (sy * mw + sx) as usize;
            depth.push(src_depth[k]);
            confidence.push(src_confidence[k]);
        }
    }
    ViewDepth {
        width,
        height,
        depth,
        confidence,
    }
}

/// What [`cached`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CacheUse {
    /// The run folder's maps matched the views and settings.
    Reused,
    /// The maps were computed (none cached, or the views or settings changed).
    Computed,
}

/// The cache key of `cams` (whose images lie under `scene_dir`) and `settings`: the SHA-256 of
/// the views' paths relative to the scene, their bytes, their cameras (pose, intrinsics and
/// depth bounds) and the settings.
pub fn cache_key(scene_dir: &Path, cams: &[Camera], settings: &MvsDepthSettings) -> Result<String> {
    let doc = serde_json::json!({ "views": views_doc(scene_dir, cams)?, "settings": settings });
    Ok(sha256_hex(doc.to_string().as_bytes()))
}

/// The SHA-256 of `cams` (whose images lie under `scene_dir`): their paths relative to the
/// scene, their bytes, poses, intrinsics and depth bounds. A scene's identity, whatever
/// folder it is read from.
pub fn views_key(scene_dir: &Path, cams: &[Camera]) -> Result<String> {
    let doc = serde_json::json!({ "views": views_doc(scene_dir, cams)? });
    Ok(sha256_hex(doc.to_string().as_bytes()))
}

/// Each view's image (relative path, size, SHA-256 of its bytes) and camera.
fn views_doc(scene_dir: &Path, cams: &[Camera]) -> Result<Vec<serde_json::Value>> {
    let mut views = Vec::with_capacity(cams.len());
    for c in cams {
        let bytes = std::fs::read(&c.image).map_err(|e| DataError::io(&c.image, e))?;
        let rel = c.image.strip_prefix(scene_dir).unwrap_or(&c.image);
        views.push(serde_json::json!({
            "image": rel.to_string_lossy(),
            "size": [c.width, c.height],
            "sha256": sha256_hex(&bytes),
            // The pose, intrinsics and bounds: re-registered images give other maps.
            "c2w": c.c2w.to_cols_array(),
            "intrinsics": [c.fx, c.fy, c.cx, c.cy],
            "bounds": c.bounds,
        }));
    }
    Ok(views)
}

/// The SHA-256 of `bytes` in hexadecimal (the cache keys here, and the fingerprints of an
/// extrapolate run's stages).
pub fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes)
        .iter()
        .map(|b| format!("{b:02x}"))
        .collect()
}

/// The cache's files for view `k`: depth and confidence.
fn cache_files(dir: &Path, k: usize) -> (PathBuf, PathBuf) {
    (
        dir.join(format!("view_{k:03}_depth.exr")),
        dir.join(format!("view_{k:03}_confidence.exr")),
    )
}

/// [`compute`] through the cache in `run_dir/depth_mvs`: reuses the maps when the key matches
/// (and every file reads back at the views' sizes), else computes and writes them, the key
/// last (an interrupted write leaves no key, so the next run recomputes).
pub fn cached(
    ctx: &Context,
    scene_dir: &Path,
    cams: &[Camera],
    settings: &MvsDepthSettings,
    run_dir: &Path,
) -> Result<(Vec<ViewDepth>, CacheUse)> {
    let dir = run_dir.join(CACHE_DIR);
    let key = cache_key(scene_dir, cams, settings)?;
    let key_path = dir.join(KEY_FILE);
    let stored = std::fs::read_to_string(&key_path)
        .ok()
        .and_then(|s| serde_json::from_str::<serde_json::Value>(&s).ok());
    if stored.as_ref().and_then(|v| v["key"].as_str()) == Some(key.as_str()) {
        let read = || -> Result<Vec<ViewDepth>> {
            cams.iter()
                .enumerate()
                .map(|(k, c)| {
                    let (dp, cp) = cache_files(&dir, k);
                    Ok(ViewDepth {
                        width: c.width,
                        height: c.height,
                        depth: read_depth_exr(&dp, c)?,
                        confidence: read_depth_exr(&cp, c)?,
                    })
                })
                .collect()
        };
        // A damaged cache is recomputed, not an error.
        if let Ok(views) = read() {
            return Ok((views, CacheUse::Reused));
        }
    }
    let scene = compute(ctx, cams, settings)?;
    if dir.exists() {
        std::fs::remove_dir_all(&dir).map_err(|e| DataError::io(&dir, e))?;
    }
    std::fs::create_dir_all(&dir).map_err(|e| DataError::io(&dir, e))?;
    for (k, v) in scene.views.iter().enumerate() {
        let (dp, cp) = cache_files(&dir, k);
        write_depth_exr(&dp, v.width, v.height, &v.depth)?;
        write_depth_exr(&cp, v.width, v.height, &v.confidence)?;
    }
    let doc = serde_json::json!({
        "key": key,
        "settings": settings,
        "views": cams.iter().map(|c| c.image.strip_prefix(scene_dir).unwrap_or(&c.image).to_string_lossy().to_string()).collect::<Vec<_>>(),
        "near": scene.near,
        "far": scene.far,
        "matching_size": [scene.width, scene.height],
        "seconds": scene.seconds,
        "coverage": scene.views.iter().map(ViewDepth::coverage).collect::<Vec<_>>(),
    });
    crate::data::write_atomic(&key_path, format!("{doc:#}\n").as_bytes())?;
    Ok((scene.views, CacheUse::Computed))
}
