//! The demo scene, generated in code: textured spheres at several depths in front of a striped
//! wall above a checkered floor, ray traced analytically (2x2 supersampling) and written as an
//! LLFF capture (`poses_bounds.npy` + `images/`). Six cameras form a small forward-facing rig
//! near the origin; eight more on a wider ring, turned towards the scene, are the views
//! "outside the rig" whose ground truth the extrapolation split holds out.

use std::path::Path;

use glam::{DMat4, DVec3};

use crate::data::DataError;
use crate::run::{write_png, Result, RunError};

/// The file that marks a folder as the demo scene.
pub const DEMO_MARKER: &str = "demo_scene.json";

/// The folder of the scene's exact visibility masks (the held-out views'; as
/// `../shared/data/synth2/gt_visibility`).
pub const GT_VISIBILITY_DIR: &str = "gt_visibility";

/// How many rig cameras must see a point for [`GT_VISIBILITY_DIR`]'s masks to count it as
/// seen (ExtraNeRF's visibility keeps the second largest transmittance).
pub const GT_VISIBILITY_RANK: usize = 2;

/// Cameras of the rig (trained on) and of the outer ring (held out).
pub const RIG_VIEWS: usize = 6;
/// See [`RIG_VIEWS`].
pub const RING_VIEWS: usize = 8;

struct Sphere {
    c: DVec3,
    r: f64,
    kind: u32,
}

const SPHERES: [Sphere; 3] = [
    Sphere {
        c: DVec3::new(-0.9, -0.35, -3.0),
        r: 0.6,
        kind: 0,
    },
    Sphere {
        c: DVec3::new(0.85, 0.05, -4.5),
        r: 0.9,
        kind: 1,
    },
    Sphere {
        c: DVec3::new(-0.1, 1.0, -6.0),
        r: 0.8,
        kind: 2,
    },
];
const WALL_Z: f64 = -8.0;
const FLOOR_Y: f64 = -1.2;

fn hit_sphere(o: DVec3, d: DVec3, s: &Sphere) -> Option<f64> {
    let oc = o - s.c;
    let b = oc.dot(d);
    let c = oc.length_squared() - s.r * s.r;
    let disc = b * b - c;
    if disc < 0.0 {
        return None;
    }
    let t = -b - disc.sqrt();
    (t > 1e-6).then_some(t)
}

fn checker(a: f64, b: f64) -> bool {
    (a.floor() as i64 + b.floor() as i64).rem_euclid(2) == 0
}

/// Distance to the first surface along `o + t d` (`d` unit length), if any.
fn first_hit(o: DVec3, d: DVec3) -> Option<f64> {
    let mut best = f64::INFINITY;
    for s in &SPHERES {
        if let Some(t) = hit_sphere(o, d, s) {
            best = best.min(t);
        }
    }
    if d.y < 0.0 {
        let t = (FLOOR_Y - o.y) / d.y;
        if t > 0.0 && t < best && (o + t * d).z > WALL_Z {
            best = t;
        }
    }
    if d.z < 0.0 {
        let t = (WALL_Z - o.z) / d.z;
        if t > 0.0 && t < best {
            best = t;
        }
    }
    best.is_finite().then_some(best)
}

/// The demo's intrinsics at `width x height`, the same at any resolution: (focal, cx, cy),
/// focal 0.9 x width and the principal point at the image centre.
fn demo_intrinsics(width: u32, height: u32) -> (f64, f64, f64) {
    (0.9 * width as f64, width as f64 / 2.0, height as f64 / 2.0)
}

/// The camera-space direction (depth 1 along -z) through image position (px, py).
fn camera_dir(px: f64, py: f64, (focal, cx, cy): (f64, f64, f64)) -> DVec3 {
    DVec3::new((px - cx) / focal, -(py - cy) / focal, -1.0)
}

/// For every pixel centre of view `c2w` at `width x height`, row by row: its camera-space
/// direction (depth 1), its unit world direction, and the distance along that to the first
/// surface.
fn centre_hits(
    c2w: &DMat4,
    width: u32,
    height: u32,
) -> impl Iterator<Item = (DVec3, DVec3, Option<f64>)> + '_ {
    let intr = demo_intrinsics(width, height);
    (0..height).flat_map(move |y| {
        (0..width).map(move |x| {
            let dc = camera_dir(x as f64 + 0.5, y as f64 + 0.5, intr);
            let d = c2w.transform_vector3(dc).normalize();
            (dc, d, first_hit(c2w.w_axis.truncate(), d))
        })
    })
}

/// Exact visibility of demo view `view` (an index into [`demo_cameras`]) at `width x height`:
/// per pixel, whether the surface its centre ray hits is seen by at least `rank` of the rig
/// cameras (inside the camera's image and nothing in between). Rays that hit nothing count
/// as unseen. The demo's intrinsics (focal 0.9 x width, centred) hold at any resolution.
pub fn demo_seen(view: usize, width: u32, height: u32, rank: usize) -> Vec<bool> {
    let cams = demo_cameras();
    let c2w = cams[view];
    let (focal, cx, cy) = demo_intrinsics(width, height);
    let rig: Vec<(DMat4, DVec3)> = cams[..RIG_VIEWS]
        .iter()
        .map(|m| (m.inverse(), m.w_axis.truncate()))
        .collect();
    let o = c2w.w_axis.truncate();
    centre_hits(&c2w, width, height)
        .map(|(_, d, hit)| {
            let Some(t) = hit else {
                return false;
            };
            let p = o + t * d;
            let count = rig
                .iter()
                .filter(|(w2c, eye)| {
                    let c = w2c.transform_point3(p);
                    if c.z >= 0.0 {
                        return false;
                    }
                    let (u, v) = (cx + focal * c.x / -c.z, cy - focal * c.y / -c.z);
                    if !(0.0..width as f64).contains(&u) || !(0.0..height as f64).contains(&v) {
                        return false;
                    }
                    let to = p - *eye;
                    let dist = to.length();
                    first_hit(*eye, to / dist).is_some_and(|h| h >= dist * (1.0 - 1e-6) - 1e-6)
                })
                .count();
            count >= rank
        })
        .collect()
}

/// Exact depth of demo view `view` (an index into [`demo_cameras`]) at `width x height`: per
/// pixel, the depth along the viewing axis of the surface its centre ray hits, in the scene
/// file's units (what `train --depth-dir` reads); 0 where the ray hits nothing.
pub fn demo_view_depth(view: usize, width: u32, height: u32) -> Vec<f32> {
    // dc has depth 1: a distance t along its unit direction is t / |dc| deep.
    centre_hits(&demo_cameras()[view], width, height)
        .map(|(dc, _, hit)| hit.map_or(0.0, |t| (t / dc.length()) as f32))
        .collect()
}

/// The albedo of sphere texture `kind` at unit normal `n`.
fn sphere_colour(kind: u32, n: DVec3) -> DVec3 {
    let (u, v) = (n.z.atan2(n.x), n.y.asin());
    match kind {
        0 => {
            if (u * 4.0).sin() > 0.0 {
                DVec3::new(0.9, 0.2, 0.15)
            } else {
                DVec3::new(0.95, 0.8, 0.2)
            }
        }
        1 => {
            if checker(
                u * 6.0 / std::f64::consts::PI,
                v * 6.0 / std::f64::consts::PI,
            ) {
                DVec3::new(0.15, 0.3, 0.85)
            } else {
                DVec3::new(0.92, 0.92, 0.95)
            }
        }
        _ => {
            let w = ((u * 5.0).sin() * (v * 8.0).sin()).abs();
            DVec3::new(0.1, 0.45 + 0.4 * w, 0.2)
        }
    }
}

/// Lambertian shading with the demo's light.
fn lit(albedo: DVec3, n: DVec3) -> DVec3 {
    let light = DVec3::new(0.4, 0.8, 0.5).normalize();
    albedo * (0.35 + 0.65 * n.dot(light).max(0.0))
}

/// Colour of the ray `o + t d` (`d` unit length).
fn shade(o: DVec3, d: DVec3) -> DVec3 {
    let mut best = (f64::INFINITY, DVec3::ZERO, DVec3::ZERO);
    for s in &SPHERES {
        if let Some(t) = hit_sphere(o, d, s) {
            if t < best.0 {
                let p = o + t * d;
                let n = (p - s.c) / s.r;
                let col = sphere_colour(s.kind, n);
                best = (t, col, n);
            }
        }
    }
    if d.y < 0.0 {
        let t = (FLOOR_Y - o.y) / d.y;
        let p = o + t * d;
        if t > 0.0 && t < best.0 && p.z > WALL_Z {
            let col = if checker(p.x * 1.5, p.z * 1.5) {
                DVec3::new(0.55, 0.4, 0.3)
            } else {
                DVec3::new(0.85, 0.8, 0.7)
            };
            best = (t, col, DVec3::Y);
        }
    }
    if d.z < 0.0 {
        let t = (WALL_Z - o.z) / d.z;
        if t > 0.0 && t < best.0 {
            let p = o + t * d;
            let stripe = (p.x * 1.7 + 0.5 * (p.y * 2.0).sin()).rem_euclid(2.0) < 1.0;
            let col = if stripe {
                DVec3::new(0.95, 0.55, 0.2)
            } else {
                DVec3::new(0.3, 0.2, 0.5)
            };
            best = (t, col, DVec3::Z);
        }
    }
    if !best.0.is_finite() {
        return DVec3::splat(0.7);
    }
    lit(best.1, best.2)
}

/// Camera-to-world (OpenGL: x right, y up, looking along -z) at `eye` looking at `target`.
fn look_at(eye: DVec3, target: DVec3) -> DMat4 {
    let back = (eye - target).normalize();
    let right = DVec3::Y.cross(back).normalize();
    let up = back.cross(right);
    DMat4::from_cols(
        right.extend(0.0),
        up.extend(0.0),
        back.extend(0.0),
        eye.extend(1.0),
    )
}

/// The demo's cameras: the rig (a centre view and five on a 0.2 circle, all looking straight
/// ahead) then the ring (eight on a 0.9 circle, turned towards the middle sphere).
pub fn demo_cameras() -> Vec<DMat4> {
    let mut c = Vec::new();
    for k in 0..RIG_VIEWS {
        let eye = if k == 0 {
            DVec3::ZERO
        } else {
            let a = (k - 1) as f64 / (RIG_VIEWS - 1) as f64 * std::f64::consts::TAU;
            DVec3::new(0.2 * a.cos(), 0.15 * a.sin(), 0.0)
        };
        c.push(look_at(eye, eye - DVec3::Z));
    }
    for k in 0..RING_VIEWS {
        let a = k as f64 / RING_VIEWS as f64 * std::f64::consts::TAU + 0.3;
        let eye = DVec3::new(0.9 * a.cos(), 0.5 * a.sin(), 0.1);
        c.push(look_at(eye, DVec3::new(0.0, 0.0, -4.5)));
    }
    c
}

/// Writes the scene into `dir` (`poses_bounds.npy`, `images/view_NN.png`, and the held-out
/// views' exact visibility `gt_visibility/view_NN.png`) at `width x height`.
pub fn write_demo_scene(dir: &Path, width: u32, height: u32) -> Result<()> {
    if width < 16 || height < 16 {
        return Err(RunError::Config(format!(
            "demo images of {width}x{height}: use at least 16x16"
        )));
    }
    let img_dir = dir.join("images");
    std::fs::create_dir_all(&img_dir).map_err(|e| DataError::Io {
        path: img_dir.clone(),
        error: e,
    })?;
    let intr = demo_intrinsics(width, height);
    let focal = intr.0;
    let mut rows = Vec::new();
    for (i, c2w) in demo_cameras().iter().enumerate() {
        let mut rgb = vec![0f32; (width * height * 3) as usize];
        for y in 0..height {
            for x in 0..width {
                let mut acc = DVec3::ZERO;
                for s in 0..4 {
                    let px = x as f64 + 0.25 + 0.5 * (s % 2) as f64;
                    let py = y as f64 + 0.25 + 0.5 * (s / 2) as f64;
                    let dc = camera_dir(px, py, intr);
                    let d = c2w.transform_vector3(dc).normalize();
                    acc += shade(c2w.w_axis.truncate(), d);
                }
                let k = ((y * width + x) * 3) as usize;
                for ch in 0..3 {
                    rgb[k + ch] = (acc[ch] / 4.0) as f32;
                }
            }
        }
        write_png(
            &img_dir.join(format!("view_{i:02}.png")),
            width,
            height,
            &rgb,
        )?;
        // LLFF rows: [down, right, backwards, translation, (H, W, focal)] then near, far.
        let (r, u, b, t) = (c2w.x_axis, c2w.y_axis, c2w.z_axis, c2w.w_axis);
        let mut row = Vec::with_capacity(17);
        for k in 0..3 {
            row.extend([
                -u[k],
                r[k],
                b[k],
                t[k],
                [height as f64, width as f64, focal][k],
            ]);
        }
        row.extend([1.5, 10.0]);
        rows.push(row);
    }
    let flat: Vec<f64> = rows.concat();
    crate::data::npy::write_npy_f64(&dir.join("poses_bounds.npy"), &[rows.len(), 17], &flat)?;
    // The exact visibility of the views outside the rig, in `../shared/data/synth2`'s layout
    // (named as the view's image; white where at least two rig cameras see the surface).
    let vis_dir = dir.join(GT_VISIBILITY_DIR);
    std::fs::create_dir_all(&vis_dir).map_err(|e| DataError::Io {
        path: vis_dir.clone(),
        error: e,
    })?;
    for i in RIG_VIEWS..RIG_VIEWS + RING_VIEWS {
        let grey: Vec<f32> = demo_seen(i, width, height, GT_VISIBILITY_RANK)
            .into_iter()
            .flat_map(|s| [if s { 1.0 } else { 0.0 }; 3])
            .collect();
        write_png(
            &vis_dir.join(format!("view_{i:02}.png")),
            width,
            height,
            &grey,
        )?;
    }
    // Marks the folder as the demo scene, whose exact visibility is known ([`demo_seen`]).
    crate::safetensors::write_atomic(
        &dir.join(DEMO_MARKER),
        format!("{{\"demo\": 1, \"width\": {width}, \"height\": {height}}}\n").as_bytes(),
    )?;
    Ok(())
}

/// The turntable scene's object centre (off the origin, so that centring is tested).
pub const TURNTABLE_CENTRE: DVec3 = DVec3::new(0.4, -0.3, 0.25);
/// Distance of the turntable cameras from [`TURNTABLE_CENTRE`].
pub const TURNTABLE_RADIUS: f64 = 3.5;
/// Horizontal field of view of the turntable cameras (NeRF-synthetic's `camera_angle_x`).
pub const TURNTABLE_ANGLE_X: f64 = 0.6911;

/// The turntable object: three textured spheres around [`TURNTABLE_CENTRE`], within 1.1 of it.
fn turntable_spheres() -> [Sphere; 3] {
    let c = TURNTABLE_CENTRE;
    [
        Sphere { c, r: 0.6, kind: 1 },
        Sphere {
            c: c + DVec3::new(0.7, 0.2, 0.1),
            r: 0.35,
            kind: 0,
        },
        Sphere {
            c: c + DVec3::new(-0.45, 0.35, 0.45),
            r: 0.3,
            kind: 2,
        },
    ]
}

/// Colour of the turntable ray `o + t d` (`d` unit length), or `None` when it misses.
fn turntable_shade(spheres: &[Sphere], o: DVec3, d: DVec3) -> Option<DVec3> {
    let mut best: Option<(f64, &Sphere)> = None;
    for s in spheres {
        if let Some(t) = hit_sphere(o, d, s) {
            if best.is_none_or(|(b, _)| t < b) {
                best = Some((t, s));
            }
        }
    }
    best.map(|(t, s)| {
        let n = (o + t * d - s.c) / s.r;
        lit(sphere_colour(s.kind, n), n)
    })
}

/// Turntable camera `k` of `n`: on a sphere of [`TURNTABLE_RADIUS`] around the object, at
/// elevations from 10 to 70 degrees over a golden-angle spiral (train and test rigs use
/// different phases), looking at [`TURNTABLE_CENTRE`].
pub fn turntable_camera(k: usize, n: usize, phase: f64) -> DMat4 {
    let f = (k as f64 + 0.5) / n.max(1) as f64;
    let elevation = (10.0 + 60.0 * f).to_radians();
    let azimuth = k as f64 * 2.399_963_229_728_653 + phase;
    let dir = DVec3::new(
        elevation.cos() * azimuth.cos(),
        elevation.sin(),
        elevation.cos() * azimuth.sin(),
    );
    look_at(TURNTABLE_CENTRE + TURNTABLE_RADIUS * dir, TURNTABLE_CENTRE)
}

/// The exact turntable view from `c2w` at `width x height` (2x2 supersampled): straight
/// colour (the mean of the samples that hit, 0 where none did) and alpha (the fraction that
/// hit). Composited over a background b, a pixel is (hits + b * misses) / 4.
pub fn turntable_view(c2w: &DMat4, width: u32, height: u32) -> (Vec<f32>, Vec<f32>) {
    let spheres = turntable_spheres();
    let focal = 0.5 * width as f64 / (0.5 * TURNTABLE_ANGLE_X).tan();
    let (cx, cy) = (width as f64 / 2.0, height as f64 / 2.0);
    let mut rgb = vec![0f32; (width * height * 3) as usize];
    let mut alpha = vec![0f32; (width * height) as usize];
    for y in 0..height {
        for x in 0..width {
            let (mut acc, mut hits) = (DVec3::ZERO, 0u32);
            for s in 0..4 {
                let px = x as f64 + 0.25 + 0.5 * (s % 2) as f64;
                let py = y as f64 + 0.25 + 0.5 * (s / 2) as f64;
                let dc = DVec3::new((px - cx) / focal, -(py - cy) / focal, -1.0);
                let d = c2w.transform_vector3(dc).normalize();
                if let Some(c) = turntable_shade(&spheres, c2w.w_axis.truncate(), d) {
                    acc += c;
                    hits += 1;
                }
            }
            let k = (y * width + x) as usize;
            if hits > 0 {
                for ch in 0..3 {
                    rgb[k * 3 + ch] = (acc[ch] / hits as f64) as f32;
                }
            }
            alpha[k] = hits as f32 / 4.0;
        }
    }
    (rgb, alpha)
}

/// Writes the turntable scene into `dir` in NeRF-synthetic's layout: `transforms_train.json`
/// and `transforms_test.json` (`camera_angle_x`, frames with `file_path` without extension and
/// `transform_matrix`) and RGBA PNGs `train/r_K.png`, `test/r_K.png` with a transparent
/// background, `train` views and `test` views at `width x height`. Views are ray traced on all
/// cores.
pub fn write_turntable_scene(
    dir: &Path,
    width: u32,
    height: u32,
    train: usize,
    test: usize,
) -> Result<()> {
    if width < 8 || height < 8 || train == 0 || test == 0 {
        return Err(RunError::Config(format!(
            "turntable scene of {train} + {test} views at {width}x{height}: use at least one \
             view of each and 8x8 pixels"
        )));
    }
    for (split, n, phase) in [("train", train, 0.0), ("test", test, 1.1)] {
        let img_dir = dir.join(split);
        std::fs::create_dir_all(&img_dir).map_err(|e| DataError::Io {
            path: img_dir.clone(),
            error: e,
        })?;
        let cams: Vec<DMat4> = (0..n).map(|k| turntable_camera(k, n, phase)).collect();
        let next = std::sync::atomic::AtomicUsize::new(0);
        let threads = std::thread::available_parallelism().map_or(1, |t| t.get());
        std::thread::scope(|scope| -> Result<()> {
            let workers: Vec<_> = (0..threads)
                .map(|_| {
                    scope.spawn(|| -> Result<()> {
                        loop {
                            let k = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                            if k >= n {
                                return Ok(());
                            }
                            let (rgb, alpha) = turntable_view(&cams[k], width, height);
                            crate::run::write_png_rgba(
                                &img_dir.join(format!("r_{k}.png")),
                                width,
                                height,
                                &rgb,
                                &alpha,
                            )?;
                        }
                    })
                })
                .collect();
            for w in workers {
                w.join()
                    .map_err(|_| RunError::Config("a ray-tracing thread panicked".into()))??;
            }
            Ok(())
        })?;
        let frames: Vec<serde_json::Value> = cams
            .iter()
            .enumerate()
            .map(|(k, c2w)| {
                let rows: Vec<Vec<f64>> = (0..4).map(|r| c2w.row(r).to_array().to_vec()).collect();
                serde_json::json!({
                    "file_path": format!("./{split}/r_{k}"),
                    "rotation": 0.0,
                    "transform_matrix": rows,
                })
            })
            .collect();
        let json = serde_json::json!({"camera_angle_x": TURNTABLE_ANGLE_X, "frames": frames});
        crate::safetensors::write_atomic(
            &dir.join(format!("transforms_{split}.json")),
            serde_json::to_string_pretty(&json)
                .map_err(|e| RunError::Config(format!("cannot serialise the cameras: {e}")))?
                .as_bytes(),
        )?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn exact_visibility_sees_the_rig_and_hides_behind_spheres() {
        // The centre rig camera's own view is almost wholly seen by two rig cameras (a 0.2
        // baseline); a ring view, far outside the rig, sees much that none of them did.
        let (w, h) = (48, 36);
        let frac = |v: usize| {
            let s = demo_seen(v, w, h, 2);
            s.iter().filter(|&&b| b).count() as f64 / s.len() as f64
        };
        let (rig, ring) = (frac(0), frac(RIG_VIEWS));
        assert!(rig > 0.9, "rig view seen {rig}");
        assert!(ring < rig - 0.05, "ring view seen {ring}, rig {rig}");
        // A point straight behind the near sphere, on the wall, as the centre camera looks:
        // hidden from the centre camera, so rank 6 (all rig cameras) cannot see it.
        let all = demo_seen(0, w, h, RIG_VIEWS);
        let (cx, cy) = (w as f64 / 2.0, h as f64 / 2.0);
        let s = &SPHERES[0];
        let u = cx + 0.9 * w as f64 * s.c.x / -s.c.z;
        let v = cy - 0.9 * w as f64 * s.c.y / -s.c.z;
        let i = v as usize * w as usize + u as usize;
        assert!(
            demo_seen(0, w, h, 1)[i],
            "the sphere's centre pixel is seen by camera 0"
        );
        assert!(
            all.iter().filter(|&&b| b).count() < all.len(),
            "rank 6 hides something"
        );
    }

    #[test]
    fn rays_hit_what_is_in_front() {
        // Straight ahead from the origin: the wall (no sphere is on the axis) at z = -8.
        let c = shade(DVec3::ZERO, -DVec3::Z);
        assert!(c.max_element() > 0.0 && c.max_element() <= 1.0);
        // Towards the first sphere's centre: its red/yellow texture.
        let d = SPHERES[0].c.normalize();
        let hit = hit_sphere(DVec3::ZERO, d, &SPHERES[0]).unwrap();
        assert!((hit - (SPHERES[0].c.length() - SPHERES[0].r)).abs() < 1e-9);
        // Looking up and back: nothing, the grey background.
        assert_eq!(shade(DVec3::ZERO, DVec3::Y), DVec3::splat(0.7));
    }

    #[test]
    fn turntable_views_hit_the_object_and_leave_the_rest_transparent() {
        let c2w = turntable_camera(3, 10, 0.0);
        let eye = c2w.w_axis.truncate();
        assert!((eye.distance(TURNTABLE_CENTRE) - TURNTABLE_RADIUS).abs() < 1e-12);
        assert!(eye.y > TURNTABLE_CENTRE.y, "upper hemisphere");
        let (w, h) = (40, 30);
        let (rgb, alpha) = turntable_view(&c2w, w, h);
        // The centre pixel looks at the central sphere: opaque, lit, textured colour.
        let k = ((h / 2) * w + w / 2) as usize;
        assert_eq!(alpha[k], 1.0);
        assert!(rgb[k * 3..k * 3 + 3].iter().all(|&c| c > 0.0 && c <= 1.0));
        // The corners miss: transparent, colour 0.
        assert_eq!(alpha[0], 0.0);
        assert_eq!(&rgb[..3], &[0.0; 3]);
        // Partly covered edge pixels exist (anti-aliasing) and alpha takes quarter steps.
        assert!(alpha.iter().any(|&a| a > 0.0 && a < 1.0));
        assert!(alpha
            .iter()
            .all(|&a| [0.0, 0.25, 0.5, 0.75, 1.0].contains(&a)));
    }

    #[test]
    fn cameras_are_proper_rotations() {
        let turntable = (0..7).map(|k| turntable_camera(k, 7, 0.3));
        for c in demo_cameras().into_iter().chain(turntable) {
            let m = glam::DMat3::from_mat4(c);
            assert!((m.determinant() - 1.0).abs() < 1e-9);
            assert!(
                (m.transpose() * m - glam::DMat3::IDENTITY).abs_diff_eq(glam::DMat3::ZERO, 1e-9)
            );
        }
    }
}
