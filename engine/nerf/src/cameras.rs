//! Virtual cameras beyond the input rig (ExtraNeRF's extrapolated views), and writing cameras
//! as an instant-ngp / nerfstudio `transforms.json` (which `data::transforms` reads back).
//!
//! All trajectories are built in the frame of the rig's average pose (NeRF's `poses_avg`:
//! mean centre, mean viewing axis, mean up). Let `rx`, `ry` be the largest offsets of the
//! training centres from the mean along that frame's x and y axes, and `range` the factor
//! beyond the rig (1 = at its edge, 2 = twice as far out):
//! - `outward`: centres on the ellipse `range * (rx cos t, ry sin t)` in the rig's plane,
//!   looking along the average axis;
//! - `spiral`: LLFF's render path, widened. Centres at
//!   `range * (rx cos t, ry sin t, rz sin(t / 2))`, with `rz` the largest offset along the axis,
//!   each looking at the focus point (LLFF's focus depth from the near and far bounds);
//! - `rotate`: the mean centre, turned about the rig's up axis through `range` times the
//!   largest yaw between a training view and the average axis (both ways).
//!
//! Intrinsics are the first training camera's.

use std::path::Path;

use glam::{DMat4, DVec3, DVec4};

use crate::data::llff::average_pose;
use crate::data::{Camera, DataError};

/// The kind of extrapolated trajectory.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Trajectory {
    /// Translated outward in the rig's plane.
    Outward,
    /// A widened LLFF spiral looking at the focus point.
    Spiral,
    /// Turned about the up axis beyond the captured yaw.
    Rotate,
}

impl std::str::FromStr for Trajectory {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "outward" => Ok(Trajectory::Outward),
            "spiral" => Ok(Trajectory::Spiral),
            "rotate" => Ok(Trajectory::Rotate),
            o => Err(format!("trajectory `{o}`: use outward, spiral or rotate")),
        }
    }
}

/// Why no cameras could be made.
#[derive(Debug, thiserror::Error, PartialEq)]
#[error("virtual cameras: {0}")]
pub struct CameraError(pub String);

/// The most cameras a trajectory or a camera path holds.
pub const MAX_PATH_CAMERAS: usize = 100_000;

/// `count` cameras on `trajectory`, `range` times beyond the rig of `train`.
pub fn virtual_cameras(
    train: &[Camera],
    trajectory: Trajectory,
    count: usize,
    range: f64,
) -> Result<Vec<Camera>, CameraError> {
    let bad = |m: String| Err(CameraError(m));
    if count == 0 || count > MAX_PATH_CAMERAS {
        return bad(format!("count {count}: use 1 to {MAX_PATH_CAMERAS}"));
    }
    let RigFrame {
        x,
        y,
        z,
        centre,
        rx,
        ry,
        rz,
    } = RigFrame::beyond(train, range)?;
    let tau = std::f64::consts::TAU;
    let mut out = Vec::with_capacity(count);
    for k in 0..count {
        let t = tau * k as f64 / count as f64;
        let c2w = match trajectory {
            Trajectory::Outward => {
                if rx.max(ry) <= 1e-9 {
                    return bad("the training cameras share one centre; outward translation needs a rig with some extent (use rotate)".into());
                }
                let p = centre + range * (rx * t.cos() * x + ry * t.sin() * y);
                frame(x, y, z, p)
            }
            Trajectory::Spiral => {
                if rx.max(ry) <= 1e-9 {
                    return bad("the training cameras share one centre; a spiral needs a rig with some extent (use rotate)".into());
                }
                let focus = focus_depth(train)?;
                let p = centre
                    + range * (rx * t.cos() * x + ry * t.sin() * y + rz * (0.5 * t).sin() * z);
                let target = centre - focus * z;
                look_at(p, target, y)
            }
            Trajectory::Rotate => {
                let yaw = train
                    .iter()
                    .map(|c| {
                        let d = -c.c2w.z_axis.truncate();
                        d.dot(x).atan2(-d.dot(z)).abs()
                    })
                    .fold(0.0, f64::max);
                if yaw <= 1e-9 {
                    return bad("the training cameras all look the same way; there is no captured yaw to extend (use outward)".into());
                }
                // Evenly from -range*yaw to +range*yaw (a single camera: +range*yaw).
                let s = if count == 1 {
                    1.0
                } else {
                    2.0 * k as f64 / (count - 1) as f64 - 1.0
                };
                let r = DMat4::from_axis_angle(y, -s * range * yaw);
                let rot = |v: DVec3| r.transform_vector3(v);
                frame(rot(x), y, rot(z), centre)
            }
        };
        let first = &train[0];
        out.push(Camera {
            c2w,
            bounds: first.bounds,
            image: format!("virtual_{k:03}.png").into(),
            ..first.clone()
        });
    }
    Ok(out)
}

/// The frame of a rig's average pose (NeRF's `poses_avg`): its axes and centre, and the
/// largest offsets of the cameras' centres from it along each axis.
pub(crate) struct RigFrame {
    pub x: DVec3,
    pub y: DVec3,
    pub z: DVec3,
    pub centre: DVec3,
    pub rx: f64,
    pub ry: f64,
    pub rz: f64,
}

impl RigFrame {
    /// The frame of `train` for a trajectory `range` times beyond it, refusing no cameras,
    /// poses that are not finite and a range outside (0, 100].
    pub fn beyond(train: &[Camera], range: f64) -> Result<RigFrame, CameraError> {
        if train.is_empty() {
            return Err(CameraError("no training cameras".into()));
        }
        if !(range.is_finite() && range > 0.0 && range <= 100.0) {
            return Err(CameraError(format!(
                "range {range}: use a factor in (0, 100]"
            )));
        }
        let c2ws: Vec<DMat4> = train.iter().map(|c| c.c2w).collect();
        if c2ws.iter().any(|m| !m.is_finite()) {
            return Err(CameraError("a training pose is not finite".into()));
        }
        let avg = average_pose(&c2ws);
        let (x, y, z) = (
            avg.x_axis.truncate(),
            avg.y_axis.truncate(),
            avg.z_axis.truncate(),
        );
        let centre = avg.w_axis.truncate();
        let extent = |axis: DVec3| {
            train
                .iter()
                .map(|c| (c.centre() - centre).dot(axis).abs())
                .fold(0.0, f64::max)
        };
        Ok(RigFrame {
            x,
            y,
            z,
            centre,
            rx: extent(x),
            ry: extent(y),
            rz: extent(z),
        })
    }
}

pub(crate) fn frame(x: DVec3, y: DVec3, z: DVec3, p: DVec3) -> DMat4 {
    DMat4::from_cols(x.extend(0.0), y.extend(0.0), z.extend(0.0), p.extend(1.0))
}

/// A camera at `p` looking at `target` (OpenGL: looking along -z), with `up` kept as close as
/// possible.
pub(crate) fn look_at(p: DVec3, target: DVec3, up: DVec3) -> DMat4 {
    let z = (p - target).normalize();
    let x = up.cross(z).normalize();
    let y = z.cross(x);
    frame(x, y, z, p)
}

/// LLFF's focus depth: `1 / ((1 - 0.75) / near + 0.75 / far)` over the rig's bounds.
fn focus_depth(train: &[Camera]) -> Result<f64, CameraError> {
    let (near, far) = crate::data::depth_bounds(train).ok_or_else(|| {
        CameraError(
            "a spiral needs the cameras' near/far bounds (LLFF poses_bounds.npy) to place its focus point".into(),
        )
    })?;
    Ok(1.0 / (0.25 / near + 0.75 / far))
}

/// Writes `cameras` as a `transforms.json` (per-frame intrinsics, OpenGL c2w, file paths
/// naming the renders to come), atomically.
pub fn write_transforms(path: &Path, cameras: &[Camera]) -> Result<(), DataError> {
    let frames: Vec<serde_json::Value> = cameras
        .iter()
        .map(|c| {
            let m = c.c2w;
            let row = |r: usize| -> Vec<f64> {
                let v: DVec4 = m.row(r);
                v.to_array().to_vec()
            };
            serde_json::json!({
                "file_path": c.image.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default(),
                "transform_matrix": [row(0), row(1), row(2), row(3)],
                "w": c.width,
                "h": c.height,
                "fl_x": c.fx,
                "fl_y": c.fy,
                "cx": c.cx,
                "cy": c.cy,
            })
        })
        .collect();
    let doc = serde_json::json!({ "camera_model": "PINHOLE", "frames": frames });
    let text = serde_json::to_string_pretty(&doc)
        .map_err(|e| DataError::malformed(path, format!("cannot encode JSON: {e}")))?;
    crate::safetensors::write_atomic(path, text.as_bytes())
}
