//! Camera paths to render along (`extranerf render --path`): a file (the `transforms.json`
//! that `extranerf cameras` writes, or a nerfstudio `camera_path.json`) or a named trajectory
//! around the training cameras.
//!
//! The named trajectories are built in the frame of the rig's average pose (as
//! [`crate::cameras`]'s are: mean centre `c`, axes `x`, `y`, `z`; `rx`, `ry` the largest
//! offsets of the training centres from `c` along `x` and `y`; `range` the factor beyond the
//! rig, 1 = its edge), with `n` frames at `t_k = 2 pi k / n`:
//! - `spiral`: LLFF's render path widened by `range`, looking at the focus point
//!   ([`crate::cameras::Trajectory::Spiral`]);
//! - `ellipse`: centres `c + range (rx cos t_k x + ry sin t_k y)`, each looking at the rig's
//!   focus: the point `focus` along the average axis in front of `c` (LLFF's focus depth) where
//!   the cameras have depth bounds, else the point nearest to every training camera's axis;
//! - `line:I,J`: from scene view `I` to scene view `J` (both ends included), centres
//!   interpolated linearly and rotations spherically, with view `I`'s intrinsics;
//! - `sweep`: centres `c + s range rx x` for `s` evenly from -1 to 1, looking along the
//!   average axis: a pass across the rig and past both its ends (extrapolation).
//!
//! Intrinsics are the first training camera's (view `I`'s for a line), resized to the width
//! asked for, if any.

use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DQuat, DVec3};
use serde_json::Value;

use crate::cameras::{
    frame, look_at, virtual_cameras, CameraError, RigFrame, Trajectory, MAX_PATH_CAMERAS,
};
use crate::data::{Camera, DataError};

/// A named trajectory around the training cameras (see the module's documentation).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NamedPath {
    /// LLFF's spiral, widened by the range.
    Spiral,
    /// An ellipse in the rig's plane looking at its focus.
    Ellipse,
    /// From one scene view to another.
    Line(usize, usize),
    /// Across the rig and past both its ends, looking along the average axis.
    Sweep,
}

/// What `render --path` follows.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum PathSource {
    /// A named trajectory.
    Named(NamedPath),
    /// A `transforms.json` or nerfstudio `camera_path.json`.
    File(PathBuf),
}

impl std::str::FromStr for PathSource {
    type Err = String;

    /// `spiral`, `ellipse`, `sweep`, `line:I,J`, or a file.
    fn from_str(s: &str) -> Result<Self, String> {
        Ok(match s {
            "spiral" => PathSource::Named(NamedPath::Spiral),
            "ellipse" => PathSource::Named(NamedPath::Ellipse),
            "sweep" => PathSource::Named(NamedPath::Sweep),
            _ => match s.strip_prefix("line:") {
                Some(ends) => {
                    let parsed: Option<Vec<usize>> =
                        ends.split(',').map(|v| v.trim().parse().ok()).collect();
                    match parsed.as_deref() {
                        Some([a, b]) => PathSource::Named(NamedPath::Line(*a, *b)),
                        _ => {
                            return Err(format!(
                                "`{s}`: a line is line:I,J with two view indices, e.g. line:0,19"
                            ))
                        }
                    }
                }
                None => PathSource::File(PathBuf::from(s)),
            },
        })
    }
}

/// `cam` with `width` pixels across (the height keeps its aspect, at least 1), its intrinsics
/// scaled by the same ratios.
pub fn resized(cam: &Camera, width: u32) -> Camera {
    let w = width.max(1);
    let h = ((cam.height as f64 * w as f64 / cam.width.max(1) as f64).round() as u32).max(1);
    let (sx, sy) = (
        w as f64 / cam.width.max(1) as f64,
        h as f64 / cam.height.max(1) as f64,
    );
    Camera {
        width: w,
        height: h,
        fx: cam.fx * sx,
        fy: cam.fy * sy,
        cx: cam.cx * sx,
        cy: cam.cy * sy,
        ..cam.clone()
    }
}

/// The point nearest (least squares) to every camera's viewing axis; None where the axes are
/// (nearly) parallel.
pub fn nearest_to_axes(cameras: &[Camera]) -> Option<DVec3> {
    let mut a = DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for c in cameras {
        let d = (-c.c2w.z_axis.truncate()).normalize();
        let m = DMat3::IDENTITY - DMat3::from_cols(d * d.x, d * d.y, d * d.z);
        a += m;
        b += m * c.centre();
    }
    // Parallel axes leave the system singular along them (relative to its scale).
    let scale = cameras.len() as f64;
    (a.determinant().abs() > 1e-6 * scale.powi(3)).then(|| a.inverse() * b)
}

/// `frames` cameras along `path` around the training cameras `train`; `all` are the scene's
/// cameras (a line names two of them), `range` the factor beyond the rig.
pub fn named_path(
    train: &[Camera],
    all: &[Camera],
    path: NamedPath,
    frames: usize,
    range: f64,
) -> Result<Vec<Camera>, CameraError> {
    let bad = |m: String| Err(CameraError(m));
    if frames == 0 || frames > MAX_PATH_CAMERAS {
        return bad(format!("{frames} frames: use 1 to {MAX_PATH_CAMERAS}"));
    }
    let RigFrame {
        x,
        y,
        z,
        centre,
        rx,
        ry,
        ..
    } = RigFrame::beyond(train, range)?;
    let first = &train[0];
    let named = |k: usize, c2w: DMat4| Camera {
        c2w,
        image: format!("frame_{k:04}.png").into(),
        ..first.clone()
    };
    let tau = std::f64::consts::TAU;
    match path {
        NamedPath::Spiral => Ok(virtual_cameras(train, Trajectory::Spiral, frames, range)?
            .into_iter()
            .enumerate()
            .map(|(k, c)| named(k, c.c2w))
            .collect()),
        NamedPath::Ellipse => {
            if rx.max(ry) <= 1e-9 {
                return bad("the training cameras share one centre; an ellipse needs a rig with some extent".into());
            }
            let target = match crate::data::depth_bounds(train) {
                Some((near, far)) => centre - z / (0.25 / near + 0.75 / far),
                None => nearest_to_axes(train).ok_or_else(|| {
                    CameraError("the training cameras' axes are parallel and they have no depth bounds: the ellipse has no point to look at".into())
                })?,
            };
            Ok((0..frames)
                .map(|k| {
                    let t = tau * k as f64 / frames as f64;
                    let p = centre + range * (rx * t.cos() * x + ry * t.sin() * y);
                    named(k, look_at(p, target, y))
                })
                .collect())
        }
        NamedPath::Sweep => {
            if rx <= 1e-9 {
                return bad(
                    "the training cameras have no extent across the rig (x): a sweep needs one"
                        .into(),
                );
            }
            Ok((0..frames)
                .map(|k| {
                    let s = if frames == 1 {
                        0.0
                    } else {
                        2.0 * k as f64 / (frames - 1) as f64 - 1.0
                    };
                    named(k, frame(x, y, z, centre + s * range * rx * x))
                })
                .collect())
        }
        NamedPath::Line(i, j) => {
            let (Some(a), Some(b)) = (all.get(i), all.get(j)) else {
                return bad(format!(
                    "line:{i},{j}: the scene has views 0 to {}",
                    all.len().saturating_sub(1)
                ));
            };
            let rot = |c: &Camera| DQuat::from_mat3(&DMat3::from_mat4(c.c2w)).normalize();
            let (qa, qb) = (rot(a), rot(b));
            Ok((0..frames)
                .map(|k| {
                    let s = if frames == 1 {
                        0.0
                    } else {
                        k as f64 / (frames - 1) as f64
                    };
                    let r = DMat3::from_quat(qa.slerp(qb, s));
                    let p = a.centre().lerp(b.centre(), s);
                    Camera {
                        c2w: frame(r.x_axis, r.y_axis, r.z_axis, p),
                        image: format!("frame_{k:04}.png").into(),
                        ..a.clone()
                    }
                })
                .collect())
        }
    }
}

/// Reads a nerfstudio `camera_path.json`: each entry of `camera_path` is a camera to world
/// (16 numbers, row-major, OpenGL convention, in the scene's world), a vertical field of view
/// `fov` in degrees and an `aspect` (width / height); the frames are `render_height` pixels
/// high. Returns the cameras and the path's `fps` (None where it gives none).
pub fn read_camera_path(path: &Path) -> Result<(Vec<Camera>, Option<f64>), DataError> {
    let bytes = std::fs::read(path).map_err(|e| DataError::io(path, e))?;
    let root: Value = serde_json::from_slice(&bytes)
        .map_err(|e| DataError::malformed(path, format!("invalid JSON: {e}")))?;
    let entries = root
        .get("camera_path")
        .and_then(Value::as_array)
        .ok_or_else(|| DataError::malformed(path, "no `camera_path` array"))?;
    if entries.is_empty() {
        return Err(DataError::malformed(path, "`camera_path` is empty"));
    }
    let num = |v: Option<&Value>, what: &str| -> Result<f64, DataError> {
        v.and_then(Value::as_f64)
            .filter(|x| x.is_finite())
            .ok_or_else(|| DataError::malformed(path, format!("`{what}` must be a finite number")))
    };
    let height = num(root.get("render_height"), "render_height")?;
    if !(1.0..=65536.0).contains(&height) {
        return Err(DataError::malformed(
            path,
            format!("render_height {height}: use 1 to 65536"),
        ));
    }
    let fps = match root.get("fps") {
        None | Some(Value::Null) => None,
        v => Some(num(v, "fps")?).filter(|f| *f > 0.0),
    };
    let mut cameras = Vec::with_capacity(entries.len());
    for (k, e) in entries.iter().enumerate() {
        let what = |f: &str| format!("camera_path[{k}].{f}");
        let m: Option<Vec<f64>> = e
            .get("camera_to_world")
            .and_then(Value::as_array)
            .map(|a| a.iter().filter_map(Value::as_f64).collect());
        let m = match m {
            Some(m) if m.len() == 16 && m.iter().all(|v| v.is_finite()) => m,
            _ => {
                return Err(DataError::malformed(
                    path,
                    format!("{}: expected 16 finite numbers", what("camera_to_world")),
                ))
            }
        };
        let c2w = DMat4::from_cols_slice(&m).transpose();
        if DMat3::from_mat4(c2w).determinant().abs() < 1e-9 {
            return Err(DataError::malformed(
                path,
                format!("{}: the rotation is singular", what("camera_to_world")),
            ));
        }
        let fov = num(e.get("fov"), &what("fov"))?;
        let aspect = num(e.get("aspect"), &what("aspect"))?;
        if !(fov > 0.0 && fov < 180.0 && aspect > 0.0) {
            return Err(DataError::malformed(
                path,
                format!(
                    "{}: fov {fov} must be in (0, 180) degrees and aspect {aspect} positive",
                    what("fov")
                ),
            ));
        }
        let width = (height * aspect).round().max(1.0);
        let f = 0.5 * height / (0.5 * fov.to_radians()).tan();
        cameras.push(Camera {
            c2w,
            width: width as u32,
            height: height as u32,
            fx: f,
            fy: f,
            cx: width / 2.0,
            cy: height / 2.0,
            bounds: None,
            image: format!("frame_{k:04}.png").into(),
        });
    }
    Ok((cameras, fps))
}

/// Writes `cameras` as a nerfstudio `camera_path.json` at `fps` (which
/// [`read_camera_path`] and nerfstudio's `ns-render camera-path` read), atomically. The
/// frames' size is the first camera's; each keeps its vertical field of view and aspect.
pub fn write_camera_path(path: &Path, cameras: &[Camera], fps: f64) -> Result<(), DataError> {
    let Some(first) = cameras.first() else {
        return Err(DataError::malformed(path, "no cameras to write"));
    };
    let entries: Vec<Value> = cameras
        .iter()
        .map(|c| {
            serde_json::json!({
                "camera_to_world": c.c2w.transpose().to_cols_array().to_vec(),
                "fov": 2.0 * (0.5 * c.height as f64 / c.fy).atan().to_degrees(),
                "aspect": c.width as f64 / c.height as f64,
            })
        })
        .collect();
    let doc = serde_json::json!({
        "camera_type": "perspective",
        "render_height": first.height,
        "render_width": first.width,
        "fps": fps,
        "seconds": cameras.len() as f64 / fps,
        "camera_path": entries,
    });
    let text = serde_json::to_string_pretty(&doc)
        .map_err(|e| DataError::malformed(path, format!("cannot encode JSON: {e}")))?;
    crate::safetensors::write_atomic(path, text.as_bytes())
}

/// The cameras of a path file: a nerfstudio `camera_path.json` (it has `camera_path`) or a
/// `transforms.json` (its frames, as `extranerf cameras` writes them), with the path's fps
/// where it gives one.
pub fn read_path_file(path: &Path) -> Result<(Vec<Camera>, Option<f64>), DataError> {
    let bytes = std::fs::read(path).map_err(|e| DataError::io(path, e))?;
    let root: Value = serde_json::from_slice(&bytes)
        .map_err(|e| DataError::malformed(path, format!("invalid JSON: {e}")))?;
    if root.get("camera_path").is_some() {
        read_camera_path(path)
    } else if root.get("frames").is_some() {
        let scene = crate::data::transforms::load_transforms_at(path, 1)?;
        Ok((scene.cameras, None))
    } else {
        Err(DataError::malformed(
            path,
            "not a camera path: expected nerfstudio's `camera_path` or a transforms.json's `frames`",
        ))
    }
}
