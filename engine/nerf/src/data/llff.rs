//! LLFF scenes: `poses_bounds.npy` plus `images_N/`, converted as the original NeRF loader
//! does: LLFF's [down, right, backwards] rotation columns become [right, up, backwards], the
//! scene is scaled so the nearest bound is `1 / bd_factor`, and the poses are recentred on their
//! average pose.

use std::path::Path;

use glam::{DMat4, DVec3, DVec4};

use super::npy::read_npy;
use super::{list_images, Camera, DataError, Result, Scene};

/// How to load an LLFF scene.
#[derive(Clone, Debug)]
pub struct LlffOptions {
    /// Image downsampling: reads `images_{factor}/` (`images/` for 1).
    pub factor: u32,
    /// Rescale so the nearest bound becomes `1 / bd_factor` (NeRF: 0.75); `None` keeps units.
    pub bd_factor: Option<f64>,
    /// Recentre the poses on their average (NeRF does).
    pub recenter: bool,
}

impl Default for LlffOptions {
    fn default() -> Self {
        LlffOptions {
            factor: 8,
            bd_factor: Some(0.75),
            recenter: true,
        }
    }
}

/// Loads an LLFF scene folder.
pub fn load_llff(dir: &Path, opts: &LlffOptions) -> Result<Scene> {
    if opts.factor == 0 {
        return Err(DataError::malformed(dir, "image factor must be at least 1"));
    }
    if let Some(b) = opts.bd_factor {
        if !(b.is_finite() && b > 0.0) {
            return Err(DataError::malformed(
                dir,
                format!("bd_factor {b} must be positive"),
            ));
        }
    }
    let npy_path = dir.join("poses_bounds.npy");
    let arr = read_npy(&npy_path)?;
    if arr.shape.len() != 2 || arr.shape[1] != 17 || arr.shape[0] == 0 {
        return Err(DataError::malformed(
            &npy_path,
            format!("expected shape (N, 17) with N >= 1, found {:?}", arr.shape),
        ));
    }
    let n = arr.shape[0];
    for (i, row) in arr.data.chunks_exact(17).enumerate() {
        if let Some(j) = row.iter().position(|v| !v.is_finite()) {
            return Err(DataError::malformed(
                &npy_path,
                format!("row {i} (image {i}) has a non-finite value at column {j}"),
            ));
        }
        let (near, far) = (row[15], row[16]);
        if !(near > 0.0 && far > near) {
            return Err(DataError::malformed(
                &npy_path,
                format!("row {i}: depth bounds near {near}, far {far} must satisfy 0 < near < far"),
            ));
        }
        // The 3x3 block must be a rotation: anything else (a zero row, a scale, a mirror) makes
        // the cameras' rays and the NDC warp wrong far from here, as NaN losses or a smeared
        // field. COLMAP writes them orthonormal to ~1e-7.
        let col = |c: usize| DVec3::new(row[c], row[5 + c], row[10 + c]);
        let (a, b, c) = (col(0), col(1), col(2));
        let off = [
            (a.length_squared() - 1.0).abs(),
            (b.length_squared() - 1.0).abs(),
            (c.length_squared() - 1.0).abs(),
            a.dot(b).abs(),
            a.dot(c).abs(),
            b.dot(c).abs(),
        ]
        .into_iter()
        .fold(0.0f64, f64::max);
        let det = a.cross(b).dot(c);
        if off > 1e-3 || det <= 0.0 {
            return Err(DataError::malformed(
                &npy_path,
                format!(
                    "row {i} (image {i}): the rotation is not orthonormal and right-handed (largest deviation {off:.3e}, determinant {det:.3}); columns 0-2 of the 3x5 pose must be a rotation"
                ),
            ));
        }
        if row[4] <= 0.0 || row[9] <= 0.0 || row[14] <= 0.0 {
            return Err(DataError::malformed(
                &npy_path,
                format!("row {i}: height, width and focal must be positive"),
            ));
        }
    }
    let img_dir = if opts.factor == 1 {
        dir.join("images")
    } else {
        dir.join(format!("images_{}", opts.factor))
    };
    let images = list_images(&img_dir)?;
    if images.len() != n {
        return Err(DataError::malformed(
            &img_dir,
            format!(
                "{} images, but {} has {n} poses",
                images.len(),
                npy_path.display()
            ),
        ));
    }

    // Rows: 3x5 row-major [R | t | hwf], then near, far.
    let row = |i: usize| &arr.data[i * 17..i * 17 + 17];
    let min_near = (0..n).map(|i| row(i)[15]).fold(f64::INFINITY, f64::min);
    let scale = opts.bd_factor.map_or(1.0, |b| 1.0 / (min_near * b));
    if !(scale.is_finite() && scale > 0.0) {
        return Err(DataError::malformed(
            &npy_path,
            format!(
                "the nearest depth bound {min_near:e} cannot normalise the scene (scale {scale:e}); the bounds must be ordinary positive depths"
            ),
        ));
    }
    let mut c2ws = Vec::with_capacity(n);
    for i in 0..n {
        let r = row(i);
        let col = |c: usize| DVec3::new(r[c], r[5 + c], r[10 + c]);
        // [down, right, back] -> [right, up, back]
        let (x, y, z) = (col(1), -col(0), col(2));
        let t = col(3) * scale;
        c2ws.push(DMat4::from_cols(
            x.extend(0.0),
            y.extend(0.0),
            z.extend(0.0),
            t.extend(1.0),
        ));
    }
    let mut world_from_source = DMat4::from_scale(DVec3::splat(scale));
    if opts.recenter {
        let avg = average_pose(&c2ws);
        let inv = avg.inverse();
        for c in &mut c2ws {
            *c = inv * *c;
        }
        world_from_source = inv * world_from_source;
    }

    let mut cameras = Vec::with_capacity(n);
    for (i, (c2w, path)) in c2ws.into_iter().zip(images).enumerate() {
        let r = row(i);
        if !(c2w.is_finite() && (r[15] * scale).is_finite() && (r[16] * scale).is_finite()) {
            return Err(DataError::malformed(
                &npy_path,
                format!(
                    "row {i} (image {i}): the pose or its bounds overflow once the scene is normalised (scale {scale:e}); the values are out of any real capture's range"
                ),
            ));
        }
        let (h_full, w_full, focal) = (r[4], r[9], r[14]);
        let (w, h) = super::image_size(&path)?;
        // The images are the full capture downsampled; the focal scales with the width.
        let s = w as f64 / w_full;
        if ((h as f64 / h_full) - s).abs() > 0.01 {
            return Err(DataError::malformed(
                &path,
                format!(
                    "{w}x{h} does not have the aspect of the {w_full}x{h_full} capture in {}",
                    npy_path.display()
                ),
            ));
        }
        cameras.push(Camera {
            c2w,
            width: w,
            height: h,
            fx: focal * s,
            fy: focal * s,
            cx: w as f64 / 2.0,
            cy: h as f64 / 2.0,
            bounds: Some((r[15] * scale, r[16] * scale)),
            image: path,
        });
    }
    Ok(Scene {
        source: dir.to_path_buf(),
        cameras,
        world_from_source,
        forward_facing: true,
        given: None,
        bounded_object: false,
        depth_files: Vec::new(),
    })
}

/// The average camera (NeRF's `poses_avg`): mean centre, mean viewing axis, mean up.
pub fn average_pose(c2ws: &[DMat4]) -> DMat4 {
    let n = c2ws.len().max(1) as f64;
    let centre = c2ws.iter().map(|c| c.w_axis.truncate()).sum::<DVec3>() / n;
    let z = c2ws
        .iter()
        .map(|c| c.z_axis.truncate())
        .sum::<DVec3>()
        .normalize();
    let up = c2ws.iter().map(|c| c.y_axis.truncate()).sum::<DVec3>();
    let x = up.cross(z).normalize();
    let y = z.cross(x).normalize();
    DMat4::from_cols(
        x.extend(0.0),
        y.extend(0.0),
        z.extend(0.0),
        DVec4::new(centre.x, centre.y, centre.z, 1.0),
    )
}
