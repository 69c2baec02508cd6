//! A COLMAP capture as a scene: `DIR/sparse/0/` (binary or text) beside `DIR/images/` (or
//! `images_N/` for a downscale). Poses come from the images' world-to-camera rotations and
//! translations, intrinsics from their cameras (models with distortion only where it is zero;
//! otherwise the error names the model and the undistorter), the near and far bounds of each
//! view from the 3-D points it sees (LLFF's percentiles), and the world is normalised as the
//! LLFF loader does (the nearest bound at 1 / 0.75, recentred on the average pose). Whether the
//! capture is forward-facing (NDC applies) or looks around a scene is read from the cameras'
//! viewing directions.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use glam::{DMat3, DMat4, DQuat, DVec3};

use super::colmap::{ColmapCamera, ColmapImage, Model, ModelFormat, Point3D};
use super::llff::average_pose;
use super::{Camera, DataError, Result, Scene};

/// LLFF's normalisation: the nearest bound becomes 1 / this.
const BD_FACTOR: f64 = 0.75;

/// A capture is forward-facing when every camera looks within this many degrees of their mean
/// viewing direction (LLFF rigs: under 20; a half orbit: 90).
pub const FORWARD_FACING_DEGREES: f64 = 45.0;

/// The folder of the COLMAP model of scene folder `dir`: `sparse/0`, `sparse`, nerfstudio's
/// `colmap/sparse/0`, or `dir` itself, the first that holds `cameras.bin` or `cameras.txt`.
pub fn model_dir(dir: &Path) -> Option<PathBuf> {
    [
        dir.join("sparse").join("0"),
        dir.join("sparse"),
        dir.join("colmap").join("sparse").join("0"),
        dir.to_path_buf(),
    ]
    .into_iter()
    .find(|d| ModelFormat::of(d).is_some())
}

/// The pinhole intrinsics `(fx, fy, cx, cy)` of `cam` at its own size, refusing a model whose
/// distortion is not zero (COLMAP's `image_undistorter` writes undistorted images and a
/// PINHOLE model) and the fisheye models.
fn pinhole(cam: &ColmapCamera, path: &Path) -> Result<(f64, f64, f64, f64)> {
    let p = &cam.params;
    let (k, distortion): ((f64, f64, f64, f64), &[f64]) = match cam.model {
        "SIMPLE_PINHOLE" => ((p[0], p[0], p[1], p[2]), &[]),
        "PINHOLE" => ((p[0], p[1], p[2], p[3]), &[]),
        "SIMPLE_RADIAL" | "RADIAL" => ((p[0], p[0], p[1], p[2]), &p[3..]),
        "OPENCV" | "FULL_OPENCV" => ((p[0], p[1], p[2], p[3]), &p[4..]),
        other => {
            return Err(DataError::malformed(
                path,
                format!(
                    "camera {} is a {other} camera, a fisheye model this loader does not \
                     model; undistort the images (colmap image_undistorter) and give the \
                     undistorted folder",
                    cam.id
                ),
            ))
        }
    };
    if let Some(d) = distortion.iter().find(|d| **d != 0.0) {
        return Err(DataError::malformed(
            path,
            format!(
                "camera {} is {} with distortion ({d} among {distortion:?}); this loader \
                 models pinhole cameras: undistort the images (colmap image_undistorter \
                 --output_type COLMAP) and give the undistorted folder",
                cam.id, cam.model
            ),
        ));
    }
    if !(k.0 > 0.0 && k.1 > 0.0 && cam.width > 0 && cam.height > 0) {
        return Err(DataError::malformed(
            path,
            format!("camera {}: focal lengths and size must be positive", cam.id),
        ));
    }
    Ok(k)
}

/// World -> COLMAP camera rotation of `im`.
fn rotation(im: &ColmapImage) -> DMat3 {
    let [w, x, y, z] = im.qvec;
    DMat3::from_quat(DQuat::from_xyzw(x, y, z, w).normalize())
}

/// `im`'s camera-to-world in the OpenGL convention (x right, y up, looking along -z).
fn c2w(im: &ColmapImage) -> DMat4 {
    let r = rotation(im).transpose();
    let centre = -(r * im.tvec);
    DMat4::from_cols(
        r.x_axis.extend(0.0),
        (-r.y_axis).extend(0.0),
        (-r.z_axis).extend(0.0),
        centre.extend(1.0),
    )
}

/// numpy's `percentile` (linear interpolation) of sorted `v` at `q` in [0, 100].
fn percentile(v: &[f64], q: f64) -> f64 {
    let x = q / 100.0 * (v.len() - 1) as f64;
    let (i, f) = (x.floor() as usize, x.fract());
    if i + 1 < v.len() {
        v[i] + f * (v[i + 1] - v[i])
    } else {
        v[i]
    }
}

/// The points each image observes (indices into `points`, ascending), from the points' tracks,
/// in one pass over them.
fn observed(points: &[Point3D]) -> HashMap<u32, Vec<usize>> {
    let mut by_image: HashMap<u32, Vec<usize>> = HashMap::new();
    for (k, p) in points.iter().enumerate() {
        let mut ids: Vec<u32> = p.track.iter().map(|t| t.0).collect();
        ids.sort_unstable();
        ids.dedup();
        for id in ids {
            by_image.entry(id).or_default().push(k);
        }
    }
    by_image
}

/// Near and far depth of `im` from the points it observes (`seen`, indices into `points`;
/// LLFF's `imgs2poses`: the 0.1 and 99.9 percentiles of their depths), or from every point in
/// front of it where it observes none; None where no point lies in front of it.
fn bounds(im: &ColmapImage, points: &[Point3D], seen: &[usize]) -> Option<(f64, f64)> {
    let r = rotation(im);
    let depth = |p: &Point3D| (r * p.xyz + im.tvec).z;
    let seen: Vec<f64> = seen
        .iter()
        .map(|&k| depth(&points[k]))
        .filter(|z| *z > 0.0)
        .collect();
    let mut z = if seen.is_empty() {
        points.iter().map(depth).filter(|z| *z > 0.0).collect()
    } else {
        seen
    };
    if z.is_empty() {
        return None;
    }
    z.sort_by(f64::total_cmp);
    Some((percentile(&z, 0.1), percentile(&z, 99.9)))
}

/// Whether every camera looks within [`FORWARD_FACING_DEGREES`] of their mean direction.
pub fn forward_facing(c2ws: &[DMat4]) -> bool {
    let dirs: Vec<DVec3> = c2ws.iter().map(|c| -c.z_axis.truncate()).collect();
    let mean = dirs.iter().sum::<DVec3>();
    if mean.length() < 1e-9 {
        return false;
    }
    let mean = mean.normalize();
    let cos = FORWARD_FACING_DEGREES.to_radians().cos();
    dirs.iter().all(|d| d.normalize().dot(mean) >= cos)
}

/// Loads the COLMAP capture in `dir`: the model of [`model_dir`], the images of `images/`
/// (`images_{factor}/` for `factor` > 1), in the order of their names.
pub fn load_colmap(dir: &Path, factor: u32) -> Result<Scene> {
    if factor == 0 {
        return Err(DataError::malformed(dir, "image factor must be at least 1"));
    }
    let Some(mdir) = model_dir(dir) else {
        return Err(DataError::malformed(
            dir,
            "no COLMAP model: expected sparse/0/cameras.bin (or .txt) with images and points",
        ));
    };
    let model = Model::read(&mdir)?;
    let format = ModelFormat::of(&mdir).unwrap_or(ModelFormat::Binary);
    let file = |name: &str| {
        mdir.join(format!(
            "{name}.{}",
            if format == ModelFormat::Text {
                "txt"
            } else {
                "bin"
            }
        ))
    };
    if model.images.is_empty() {
        return Err(DataError::malformed(&file("images"), "no images"));
    }
    if model.points.is_empty() {
        return Err(DataError::malformed(
            &file("points3D"),
            "no 3-D points: the near and far bounds of the views come from them",
        ));
    }
    let img_dir = if factor == 1 {
        dir.join("images")
    } else {
        dir.join(format!("images_{factor}"))
    };
    if !img_dir.is_dir() {
        let full = dir.join("images");
        return Err(DataError::malformed(
            &img_dir,
            if factor > 1 && full.is_dir() {
                format!(
                    "no such folder for --factor {factor} (the images downscaled {factor}x); \
                     pass --factor 1 to train on {}",
                    full.display()
                )
            } else {
                "no such folder of images".to_string()
            },
        ));
    }
    let mut images: Vec<&ColmapImage> = model.images.iter().collect();
    images.sort_by(|a, b| a.name.cmp(&b.name));
    let observers = observed(&model.points);
    let mut c2ws = Vec::with_capacity(images.len());
    let mut near_far = Vec::with_capacity(images.len());
    for im in &images {
        let pose = c2w(im);
        if !pose.is_finite() {
            return Err(DataError::malformed(
                &file("images"),
                format!("image {} ({}): the pose is not finite", im.id, im.name),
            ));
        }
        c2ws.push(pose);
        let seen = observers.get(&im.id).map_or(&[][..], Vec::as_slice);
        let Some(b) = bounds(im, &model.points, seen) else {
            return Err(DataError::malformed(
                &file("points3D"),
                format!(
                    "no 3-D point lies in front of image {} ({})",
                    im.id, im.name
                ),
            ));
        };
        near_far.push(b);
    }
    let min_near = near_far.iter().map(|b| b.0).fold(f64::INFINITY, f64::min);
    let scale = 1.0 / (min_near * BD_FACTOR);
    if !(scale.is_finite() && scale > 0.0) {
        return Err(DataError::malformed(
            &file("points3D"),
            format!("the nearest point depth {min_near:e} cannot normalise the scene"),
        ));
    }
    let scaled: Vec<DMat4> = c2ws
        .iter()
        .map(|c| {
            let mut c = *c;
            c.w_axis = (c.w_axis.truncate() * scale).extend(1.0);
            c
        })
        .collect();
    let inv = average_pose(&scaled).inverse();
    let world_from_source = inv * DMat4::from_scale(DVec3::splat(scale));
    let mut cameras = Vec::with_capacity(images.len());
    for ((im, pose), (near, far)) in images.iter().zip(&scaled).zip(&near_far) {
        let cam = model
            .cameras
            .iter()
            .find(|c| c.id == im.camera_id)
            .expect("Model::read checks every image's camera");
        let (fx, fy, cx, cy) = pinhole(cam, &file("cameras"))?;
        let path = img_dir.join(&im.name);
        let (w, h) = super::image_size(&path)?;
        let (sx, sy) = (w as f64 / cam.width as f64, h as f64 / cam.height as f64);
        if (sx - sy).abs() > 0.01 * sx.max(sy) {
            return Err(DataError::malformed(
                &path,
                format!(
                    "{w}x{h} does not have the aspect of camera {}'s {}x{} in {}",
                    cam.id,
                    cam.width,
                    cam.height,
                    file("cameras").display()
                ),
            ));
        }
        cameras.push(Camera {
            c2w: inv * *pose,
            width: w,
            height: h,
            fx: fx * sx,
            fy: fy * sy,
            cx: cx * sx,
            cy: cy * sy,
            bounds: Some((near * scale, far * scale)),
            image: path,
        });
    }
    Ok(Scene {
        source: dir.to_path_buf(),
        forward_facing: forward_facing(&c2ws),
        cameras,
        world_from_source,
        given: None,
        bounded_object: false,
        depth_files: Vec::new(),
    })
}

/// What [`export_colmap`] wrote.
#[derive(Clone, Debug, PartialEq)]
pub struct Exported {
    /// The model's folder (`OUT/sparse/0`).
    pub model: PathBuf,
    /// The images' folder (`OUT/images`).
    pub images: PathBuf,
    /// Views written.
    pub views: usize,
    /// Distinct pinhole cameras.
    pub cameras: usize,
    /// 3-D points written.
    pub points: usize,
}

/// The rotation of `m`'s linear part, where that is a rotation times a uniform scale.
fn similarity_rotation(m: &DMat4) -> Option<DMat3> {
    let a = DMat3::from_mat4(*m);
    let s = a.determinant().cbrt();
    if !(s.is_finite() && s > 0.0) {
        return None;
    }
    let r = a * (1.0 / s);
    (r.transpose() * r)
        .abs_diff_eq(DMat3::IDENTITY, 1e-6)
        .then_some(r)
}

/// Writes `scene` as a COLMAP capture in `out`: a model in `format` under `out/sparse/0` and
/// the images it loaded, copied into `out/images` (so it reads back with `--factor 1` at the
/// size it was loaded at). Poses and points are in the source's world (COLMAP's, for an LLFF
/// or COLMAP scene), as COLMAP would have written them, so loading the copy normalises it as
/// the original was. Each view is a PINHOLE camera (one per distinct size and intrinsics).
///
/// The points are the scene's sparse points (`points`, from `points_file`); their tracks name
/// image ids, which are the scene's own where it has a COLMAP images file (`source_ids`: image
/// name to id), else ids 1, 2, ... in view order, the order LLFF's `imgs2poses` gives them.
/// Track entries of images the scene lacks are dropped, and every image's 2-D points are the
/// projections of the points it observes, so the model is consistent as COLMAP reads it.
/// `out` must not exist or be empty: nothing of another capture is mixed in.
pub fn export_colmap(
    scene: &Scene,
    points: &[Point3D],
    source_ids: &HashMap<String, u32>,
    out: &Path,
    format: ModelFormat,
) -> Result<Exported> {
    if points.is_empty() {
        return Err(DataError::malformed(
            &scene.source,
            "the scene has no sparse points (sparse/0/points3D.bin or .txt): a COLMAP model \
             takes each view's near and far bounds from them",
        ));
    }
    if out.exists()
        && std::fs::read_dir(out)
            .map_err(|e| DataError::io(out, e))?
            .next()
            .is_some()
    {
        return Err(DataError::malformed(
            out,
            "the folder exists and is not empty: export into a new folder",
        ));
    }
    let Some(rot) = similarity_rotation(&scene.world_from_source) else {
        return Err(DataError::malformed(
            &scene.source,
            "the scene's transform from its source world is not a rotation, translation and \
             uniform scale, so its poses cannot be written in the source's world",
        ));
    };
    let source_from_world = scene.world_from_source.inverse();
    let images_dir = out.join("images");
    std::fs::create_dir_all(&images_dir).map_err(|e| DataError::io(&images_dir, e))?;
    let mut cameras: Vec<ColmapCamera> = Vec::new();
    let mut images: Vec<ColmapImage> = Vec::with_capacity(scene.cameras.len());
    let mut names = std::collections::HashSet::new();
    for (i, cam) in scene.cameras.iter().enumerate() {
        let Some(name) = cam.image.file_name().and_then(|n| n.to_str()) else {
            return Err(DataError::malformed(
                &cam.image,
                "not a file name COLMAP can hold",
            ));
        };
        if !names.insert(name.to_string()) {
            return Err(DataError::malformed(
                &cam.image,
                format!("two views are named {name}: COLMAP names each image once"),
            ));
        }
        let params = vec![cam.fx, cam.fy, cam.cx, cam.cy];
        let (w, h) = (u64::from(cam.width), u64::from(cam.height));
        let camera_id = match cameras
            .iter()
            .find(|c| c.params == params && (c.width, c.height) == (w, h))
        {
            Some(c) => c.id,
            None => {
                let id = cameras.len() as u32 + 1;
                cameras.push(ColmapCamera {
                    id,
                    model: "PINHOLE",
                    width: w,
                    height: h,
                    params,
                });
                id
            }
        };
        // OpenGL camera axes (x right, y up, z back) in the source world, then COLMAP's
        // (x right, y down, z forward) world -> camera.
        let gl = rot.transpose() * DMat3::from_mat4(cam.c2w);
        let c2w_cv = DMat3::from_cols(gl.x_axis, -gl.y_axis, -gl.z_axis);
        let r = c2w_cv.transpose();
        let centre = source_from_world.transform_point3(cam.c2w.w_axis.truncate());
        let q = DQuat::from_mat3(&r).normalize();
        let id = source_ids.get(name).copied().unwrap_or(i as u32 + 1);
        images.push(ColmapImage {
            id,
            qvec: [q.w, q.x, q.y, q.z],
            tvec: -(r * centre),
            camera_id,
            name: name.to_string(),
            points2d: Vec::new(),
        });
        let dst = images_dir.join(name);
        extranerf_gpu::files::copy_atomic(&cam.image, &dst).map_err(|e| DataError::io(&dst, e))?;
    }
    let index: HashMap<u32, usize> = images
        .iter()
        .enumerate()
        .map(|(k, im)| (im.id, k))
        .collect();
    if index.len() != images.len() {
        return Err(DataError::malformed(
            &scene.source,
            "two views map to one COLMAP image id",
        ));
    }
    let mut written = Vec::with_capacity(points.len());
    for p in points {
        let mut track = Vec::new();
        for &(image_id, _) in &p.track {
            let Some(&k) = index.get(&image_id) else {
                continue;
            };
            if track.iter().any(|t: &(u32, u32)| t.0 == image_id) {
                continue;
            }
            let im = &mut images[k];
            let cam = &cameras[im.camera_id as usize - 1];
            let x = rotation(im) * p.xyz + im.tvec;
            let uv = [
                cam.params[0] * x.x / x.z + cam.params[2],
                cam.params[1] * x.y / x.z + cam.params[3],
            ];
            track.push((image_id, im.points2d.len() as u32));
            im.points2d.push((uv, Some(p.id)));
        }
        written.push(Point3D { track, ..p.clone() });
    }
    let model = Model {
        cameras,
        images,
        points: written,
    };
    let model_dir = out.join("sparse").join("0");
    model.write(&model_dir, format)?;
    Ok(Exported {
        model: model_dir,
        images: images_dir,
        views: model.images.len(),
        cameras: model.cameras.len(),
        points: model.points.len(),
    })
}

/// The sparse points of the scene folder `dir` and the ids of its COLMAP images by name (empty
/// where it has no images file, as an LLFF folder has none): what [`export_colmap`] writes.
pub fn sparse_of(dir: &Path) -> Result<(Vec<Point3D>, HashMap<String, u32>)> {
    let Some(mdir) = model_dir(dir) else {
        return Ok((Vec::new(), HashMap::new()));
    };
    let points = match super::colmap::points_file(&mdir) {
        Some(p) => super::colmap::read_points3d(&p)?,
        None => Vec::new(),
    };
    let ids = match ModelFormat::of(&mdir) {
        Some(ModelFormat::Binary) if mdir.join("images.bin").is_file() => {
            super::colmap::read_images_bin(&mdir.join("images.bin"))?
        }
        Some(ModelFormat::Text) if mdir.join("images.txt").is_file() => {
            super::colmap::read_images_txt(&mdir.join("images.txt"))?
        }
        _ => Vec::new(),
    };
    Ok((points, ids.into_iter().map(|im| (im.name, im.id)).collect()))
}
