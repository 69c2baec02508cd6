//! instant-ngp / nerfstudio `transforms.json` scenes (OpenGL camera convention, as written by
//! both tools), and NeRF-synthetic's split files (`transforms_{train,val,test}.json`). Lens
//! distortion is refused rather than ignored: undistort the images first. Of nerfstudio's
//! fields: `camera_model` (the perspective models; fisheye and equirectangular are refused),
//! `applied_transform` (what maps COLMAP's world, and so its points, into the poses' world) and
//! the downscaled `images_N/` twins of `images/` that `ns-process-data` writes.

use std::path::{Path, PathBuf};

use glam::DMat4;
use serde_json::Value;

use super::{read_file, Camera, DataError, Result, Scene, SplitIndices};

/// NeRF-synthetic's split files, in the order [`load_split_transforms`] joins their cameras.
pub const SPLIT_FILES: [&str; 3] = [
    "transforms_train.json",
    "transforms_val.json",
    "transforms_test.json",
];

/// Whether `dir` holds the given protocol's training split file (`transforms_train.json`).
pub fn has_split_files(dir: &Path) -> bool {
    dir.join(SPLIT_FILES[0]).is_file()
}

/// Loads a folder of NeRF-synthetic split files: the cameras of `transforms_train.json`, then
/// of `transforms_val.json` and `transforms_test.json` when present, in that order; the scene's
/// given split trains on the first file's views and tests on the last's (none without a test
/// file). Each file may carry its own intrinsics.
pub fn load_split_transforms(dir: &Path) -> Result<Scene> {
    let train_path = dir.join(SPLIT_FILES[0]);
    if !train_path.is_file() {
        return Err(DataError::malformed(
            dir,
            format!("no {}: not a NeRF-synthetic scene folder", SPLIT_FILES[0]),
        ));
    }
    let mut scene = load_transforms(&train_path)?;
    let n_train = scene.cameras.len();
    let mut test = Vec::new();
    for (k, name) in SPLIT_FILES.iter().enumerate().skip(1) {
        let path = dir.join(name);
        if !path.exists() {
            continue;
        }
        let part = load_transforms(&path)?;
        let first = scene.cameras.len();
        if scene.depth_files.is_empty() != part.depth_files.is_empty() {
            return Err(DataError::malformed(
                &path,
                format!(
                    "its frames {} depth_file_path and those of {} {}: give it in every \
                     split file or in none",
                    if part.depth_files.is_empty() {
                        "lack"
                    } else {
                        "give"
                    },
                    SPLIT_FILES[0],
                    if scene.depth_files.is_empty() {
                        "do not"
                    } else {
                        "do"
                    },
                ),
            ));
        }
        scene.cameras.extend(part.cameras);
        scene.depth_files.extend(part.depth_files);
        if k == 2 {
            test = (first..scene.cameras.len()).collect();
        }
    }
    scene.source = dir.to_path_buf();
    scene.given = Some(SplitIndices {
        train: (0..n_train).collect(),
        test,
    });
    scene.bounded_object = true;
    Ok(scene)
}

const DISTORTION: [&str; 6] = ["k1", "k2", "k3", "k4", "p1", "p2"];

/// nerfstudio's perspective camera models (its `CAMERA_MODEL_TO_TYPE`); their distortion
/// must be zero.
const PERSPECTIVE: [&str; 5] = [
    "SIMPLE_PINHOLE",
    "PINHOLE",
    "SIMPLE_RADIAL",
    "RADIAL",
    "OPENCV",
];

/// Loads a `transforms.json` file; image paths are relative to its folder.
pub fn load_transforms(path: &Path) -> Result<Scene> {
    load_transforms_at(path, 1)
}

/// A matrix of 3 or 4 rows of 4 finite numbers (a missing last row is `0 0 0 1`).
fn matrix(v: &Value) -> Option<DMat4> {
    let rows: Vec<Vec<f64>> = v
        .as_array()?
        .iter()
        .map(|r| {
            r.as_array()
                .map(|r| r.iter().filter_map(Value::as_f64).collect())
                .unwrap_or_default()
        })
        .collect();
    if !(rows.len() == 3 || rows.len() == 4)
        || rows.iter().any(|r| r.len() != 4)
        || rows.iter().flatten().any(|v| !v.is_finite())
    {
        return None;
    }
    let at = |r: usize, c: usize| {
        if r < rows.len() {
            rows[r][c]
        } else if c == 3 {
            1.0
        } else {
            0.0
        }
    };
    Some(DMat4::from_cols_array_2d(&[
        [at(0, 0), at(1, 0), at(2, 0), at(3, 0)],
        [at(0, 1), at(1, 1), at(2, 1), at(3, 1)],
        [at(0, 2), at(1, 2), at(2, 2), at(3, 2)],
        [at(0, 3), at(1, 3), at(2, 3), at(3, 3)],
    ]))
}

/// The downscaled twin of `file` for `factor` > 1, where it exists: the file of that name in
/// `{prefix}_{factor}/` (nerfstudio's layout and lookup: `images_2/`, `depths_2/`).
fn downscaled_twin(dir: &Path, file: &str, prefix: &str, factor: u32) -> Option<PathBuf> {
    if factor <= 1 {
        return None;
    }
    let name = Path::new(file).file_name()?;
    let twin = dir.join(format!("{prefix}_{factor}")).join(name);
    twin.is_file().then_some(twin)
}

/// Loads a `transforms.json` file whose images have twins downscaled `factor` times in
/// `images_{factor}/` (nerfstudio's layout): those are read where they exist, with the
/// intrinsics scaled to their size; where they do not, the images as the file names them.
pub fn load_transforms_at(path: &Path, factor: u32) -> Result<Scene> {
    let bytes = read_file(path)?;
    let root: Value = serde_json::from_slice(&bytes)
        .map_err(|e| DataError::malformed(path, format!("invalid JSON: {e}")))?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let frames = root
        .get("frames")
        .and_then(Value::as_array)
        .ok_or_else(|| DataError::malformed(path, "no `frames` array"))?;
    if frames.is_empty() {
        return Err(DataError::malformed(path, "`frames` is empty"));
    }
    let mut cameras = Vec::with_capacity(frames.len());
    let mut depth_files = Vec::new();
    for (i, f) in frames.iter().enumerate() {
        let bad = |p: String| DataError::malformed(path, format!("frame {i}: {p}"));
        // Per-frame intrinsics override the top-level ones (nerfstudio allows both).
        let num = |key: &str| -> Result<Option<f64>> {
            match f.get(key).or_else(|| root.get(key)) {
                None | Some(Value::Null) => Ok(None),
                Some(v) => v
                    .as_f64()
                    .filter(|x| x.is_finite())
                    .map(Some)
                    .ok_or_else(|| bad(format!("`{key}` is not a finite number"))),
            }
        };
        let model = f.get("camera_model").or_else(|| root.get("camera_model"));
        if let Some(m) = model {
            let name = m.as_str().unwrap_or("");
            if !PERSPECTIVE.contains(&name) {
                return Err(bad(format!(
                    "camera_model {m} is not a perspective camera this loader models ({}); \
                     fisheye and equirectangular captures are not supported",
                    PERSPECTIVE.join(", ")
                )));
            }
        }
        for k in DISTORTION {
            if num(k)?.is_some_and(|v| v != 0.0) {
                return Err(bad(format!(
                    "lens distortion `{k}` is not supported; undistort the images first"
                )));
            }
        }
        let file = f
            .get("file_path")
            .and_then(Value::as_str)
            .ok_or_else(|| bad("no `file_path` string".into()))?;
        let mut image = dir.join(file);
        if image.extension().is_none() {
            // NeRF's synthetic scenes omit the extension.
            image = PathBuf::from(format!("{}.png", image.display()));
        }
        let c2w =
            f.get("transform_matrix")
                .ok_or_else(|| bad("no `transform_matrix`".into()))
                .and_then(|m| {
                    matrix(m).ok_or_else(|| {
                    bad("`transform_matrix` must be 4 rows of 4 finite numbers (3 rows accepted)"
                        .into())
                })
                })?;
        if c2w.determinant().abs() < 1e-12 {
            return Err(bad("`transform_matrix` is singular".into()));
        }
        let dims = || super::image_size(&image);
        let (width, height) = match (num("w")?, num("h")?) {
            (Some(w), Some(h)) if (1.0..=65536.0).contains(&w) && (1.0..=65536.0).contains(&h) => {
                let (w, h) = (w as u32, h as u32);
                // Cameras without images (virtual views to render) keep their size; an image
                // that exists must have it.
                if image.exists() {
                    let (iw, ih) = dims()?;
                    if (iw, ih) != (w, h) {
                        return Err(bad(format!(
                            "`w` x `h` is {w}x{h} but {} is {iw}x{ih}",
                            image.display()
                        )));
                    }
                }
                (w, h)
            }
            (Some(_), Some(_)) => return Err(bad("`w` and `h` must be 1 to 65536".into())),
            _ => dims()?,
        };
        let fx = match (num("fl_x")?, num("camera_angle_x")?) {
            (Some(fx), _) => fx,
            (None, Some(a)) if a > 0.0 && a < std::f64::consts::PI => {
                0.5 * width as f64 / (0.5 * a).tan()
            }
            _ => {
                return Err(bad(
                    "no focal length: give `fl_x` or `camera_angle_x` (0 < angle < pi)".into(),
                ))
            }
        };
        let fy = match (num("fl_y")?, num("camera_angle_y")?) {
            (Some(fy), _) => fy,
            (None, Some(a)) if a > 0.0 && a < std::f64::consts::PI => {
                0.5 * height as f64 / (0.5 * a).tan()
            }
            _ => fx,
        };
        if !(fx > 0.0 && fy > 0.0) {
            return Err(bad(format!(
                "focal lengths must be positive (fl_x {fx}, fl_y {fy})"
            )));
        }
        let cx = num("cx")?.unwrap_or(width as f64 / 2.0);
        let cy = num("cy")?.unwrap_or(height as f64 / 2.0);
        let mut cam = Camera {
            c2w,
            width,
            height,
            fx,
            fy,
            cx,
            cy,
            bounds: None,
            image,
        };
        // nerfstudio's depth_file_path: every frame names one or none does.
        match (f.get("depth_file_path"), depth_files.len() == i) {
            (None | Some(Value::Null), true) if i > 0 => {
                return Err(bad(
                    "no depth_file_path, which the frames before it give: every frame names \
                     its depth file or none does"
                        .into(),
                ))
            }
            (None | Some(Value::Null), _) => {}
            (Some(Value::String(d)), true) => {
                let full = dir.join(d);
                let file = downscaled_twin(dir, d, "depths", factor).unwrap_or(full);
                if !file.is_file() {
                    return Err(bad(format!(
                        "depth_file_path {d}: no such file ({})",
                        file.display()
                    )));
                }
                depth_files.push(file);
            }
            (Some(Value::String(_)), false) => {
                return Err(bad(
                    "depth_file_path, which the frames before it lack: every frame names its \
                     depth file or none does"
                        .into(),
                ))
            }
            (Some(other), _) => {
                return Err(bad(format!(
                    "depth_file_path must be a string, not {other}"
                )))
            }
        }
        if let Some(twin) = downscaled_twin(dir, file, "images", factor) {
            // The intrinsics are the full images'; the twin's own size scales them.
            let (tw, th) = super::image_size(&twin)?;
            let (sx, sy) = (tw as f64 / width as f64, th as f64 / height as f64);
            if (sx - sy).abs() > 0.01 * sx.max(sy) {
                return Err(DataError::malformed(
                    &twin,
                    format!("{tw}x{th} does not have the aspect of the {width}x{height} frame"),
                ));
            }
            cam = Camera {
                width: tw,
                height: th,
                fx: fx * sx,
                fy: fy * sy,
                cx: cx * sx,
                cy: cy * sy,
                image: twin,
                ..cam
            };
        }
        cameras.push(cam);
    }
    // nerfstudio: what was applied to COLMAP's world to make the poses' (and so maps COLMAP's
    // points into it).
    let world_from_source = match root.get("applied_transform") {
        None | Some(Value::Null) => DMat4::IDENTITY,
        Some(m) => matrix(m)
            .filter(|m| m.determinant().abs() > 1e-12)
            .ok_or_else(|| {
                DataError::malformed(
                    path,
                    "`applied_transform` must be 3 rows of 4 finite numbers, invertible",
                )
            })?,
    };
    Ok(Scene {
        source: path.to_path_buf(),
        cameras,
        world_from_source,
        forward_facing: false,
        given: None,
        bounded_object: false,
        depth_files,
    })
}
