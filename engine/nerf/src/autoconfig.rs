//! Scene-driven model configuration: model only what the scene requires. From the cameras and
//! their bounds it chooses the ray space (NDC for forward-facing captures, contracted world
//! space otherwise), the finest hash-grid resolution from the pixel footprint, the levels and
//! table size from that, and the occupancy cascades from the depth range; each choice comes with
//! the reason, which `extranerf train --auto` prints.

use glam::DVec3;

use crate::data::{Camera, Scene};
use crate::field::encodings::Contraction;
use crate::model::{ModelConfig, Space};

/// What [`auto_model`] chose and why.
#[derive(Clone, Debug, PartialEq)]
pub struct AutoModel {
    /// The configuration.
    pub model: ModelConfig,
    /// Occupancy-grid cascades the scene's depth range needs (renders, visibility).
    pub cascades: u32,
    /// One line per choice.
    pub reasons: Vec<String>,
}

/// The coarsest resolution; the growth factor between levels aims at this.
const MIN_RES: u32 = 16;
const GROWTH: f64 = 1.5;

/// Occupancy-grid cascades a model's sampling range needs: 1 in NDC (bounded); in world space
/// enough that the largest cascade (2^(c-1) scene radii) reaches the far bound, 1 to 8.
pub fn occupancy_cascades(model: &ModelConfig) -> u32 {
    if model.space == Space::Ndc {
        return 1;
    }
    let ratio = (model.far as f64 / model.radius.max(1e-9) as f64).max(1.0);
    (ratio.log2().ceil() as u32 + 1).clamp(1, 8)
}

/// How [`rig_centre`] found the centre of a rig.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum CentreFrom {
    /// The point nearest to every camera's optical axis (least squares), as Instant-NGP and
    /// nerfstudio centre 360-degree captures; `rms` is its root-mean-square distance to the
    /// axes.
    OpticalAxes {
        /// RMS distance from the point to the axes (scene units).
        rms: f64,
    },
    /// The mean of the camera centres: the axes do not meet in front of the cameras (nearly
    /// parallel, or looking outwards).
    CameraMean,
}

/// The centre of a rig: the point nearest to all optical axes when they converge in front of
/// the cameras (an object captured from around it), else the mean camera centre.
pub fn rig_centre(cameras: &[Camera]) -> (DVec3, CentreFrom) {
    let n = cameras.len().max(1) as f64;
    let mean = cameras.iter().map(Camera::centre).sum::<DVec3>() / n;
    // Sum over the axes (o, d) of (I - d d^T), and of (I - d d^T) o: the normal equations of
    // the squared distances from a point to the lines.
    let axes: Vec<(DVec3, DVec3)> = cameras
        .iter()
        .map(|c| (c.centre(), c.ray(c.cx, c.cy).1.normalize()))
        .filter(|(o, d)| o.is_finite() && d.is_finite())
        .collect();
    if axes.len() < 2 {
        return (mean, CentreFrom::CameraMean);
    }
    let mut a = glam::DMat3::ZERO;
    let mut b = DVec3::ZERO;
    for (o, d) in &axes {
        let p = glam::DMat3::IDENTITY - glam::DMat3::from_cols(*d * d.x, *d * d.y, *d * d.z);
        a += p;
        b += p * *o;
    }
    // Near-parallel axes leave A nearly singular (one eigenvalue about 0): no meeting point.
    let scale = a.col(0).x + a.col(1).y + a.col(2).z;
    if a.determinant() <= 1e-6 * (scale / 3.0).powi(3) {
        return (mean, CentreFrom::CameraMean);
    }
    let p = a.inverse() * b;
    // It must lie in front of the cameras (an outward-looking rig's axes meet behind them).
    let in_front = axes.iter().filter(|(o, d)| (p - *o).dot(*d) > 0.0).count();
    if !p.is_finite() || 2 * in_front <= axes.len() {
        return (mean, CentreFrom::CameraMean);
    }
    let rms = (axes
        .iter()
        .map(|(o, d)| {
            let v = p - *o;
            (v - *d * v.dot(*d)).length_squared()
        })
        .sum::<f64>()
        / axes.len() as f64)
        .sqrt();
    (p, CentreFrom::OpticalAxes { rms })
}

/// The model configuration a scene needs: NDC for forward-facing captures; otherwise world
/// space with the L2 contraction around the rig's centre ([`rig_centre`]) with the farthest
/// camera on the inner ball's surface, sampled between the cameras' bounds.
pub fn model_for_scene(scene: &Scene) -> ModelConfig {
    if scene.forward_facing {
        return ModelConfig::default();
    }
    let (centre, _) = rig_centre(&scene.cameras);
    let radius = scene
        .cameras
        .iter()
        .map(|c| c.centre().distance(centre))
        .fold(0.0f64, f64::max)
        .max(1e-3);
    let near = scene
        .cameras
        .iter()
        .filter_map(|c| c.bounds.map(|b| b.0))
        .fold(f64::INFINITY, f64::min);
    let far = scene
        .cameras
        .iter()
        .filter_map(|c| c.bounds.map(|b| b.1))
        .fold(0.0f64, f64::max);
    let (near, far) = if near.is_finite() && far > near {
        (near, far)
    } else if scene.bounded_object {
        object_bounds(scene, centre)
    } else {
        (0.05 * radius, 100.0 * radius)
    };
    ModelConfig {
        space: Space::World,
        near: near.max(1e-4) as f32,
        far: far as f32,
        center: centre.as_vec3().to_array(),
        radius: radius as f32,
        contraction: Contraction::L2,
        ..ModelConfig::default()
    }
}

/// Near and far bounds for an object on a transparent background: the sphere around `centre`
/// that the farthest camera's view frames (its distance times the tangent of its widest
/// half-angle, the image diagonal), seen from the nearest and the farthest camera; nothing
/// beyond it needs samples.
fn object_bounds(scene: &Scene, centre: DVec3) -> (f64, f64) {
    let (mut d_min, mut d_max, mut r) = (f64::INFINITY, 0.0f64, 0.0f64);
    for c in &scene.cameras {
        let d = c.centre().distance(centre);
        let half_w = (c.cx.max(c.width as f64 - c.cx)) / c.fx;
        let half_h = (c.cy.max(c.height as f64 - c.cy)) / c.fy;
        d_min = d_min.min(d);
        d_max = d_max.max(d);
        r = r.max(d * half_w.hypot(half_h));
    }
    ((d_min - r).max(0.05 * d_min), d_max + r)
}

/// Chooses the model for `scene` trained on the cameras `train` (indices).
pub fn auto_model(scene: &Scene, train: &[usize]) -> AutoModel {
    let mut model = model_for_scene(scene);
    let mut reasons = Vec::new();
    let cams: Vec<&Camera> = train.iter().filter_map(|&i| scene.cameras.get(i)).collect();
    let cams: Vec<&Camera> = if cams.is_empty() {
        scene.cameras.iter().collect()
    } else {
        cams
    };
    let widest = cams
        .iter()
        .map(|c| c.width.max(c.height))
        .max()
        .unwrap_or(512);
    let (max_res, cascades) = if scene.forward_facing {
        reasons.push(
            "space: NDC (a forward-facing capture: the frustum, out to infinity, maps to a cube), no contraction".into(),
        );
        // NDC x and y span the image: one finest cell per pixel.
        let res = widest.next_power_of_two();
        reasons.push(format!(
            "finest resolution {res}: one cell per pixel across the {widest}-pixel image side (NDC spans the image)"
        ));
        reasons.push("occupancy: 1 cascade (NDC is bounded)".into());
        (res, 1)
    } else {
        let how = match rig_centre(&scene.cameras).1 {
            CentreFrom::OpticalAxes { rms } => {
                format!("the point nearest the optical axes, {rms:.3} from them (rms)")
            }
            CentreFrom::CameraMean => {
                "the mean camera centre: the optical axes do not meet in front of the cameras"
                    .into()
            }
        };
        reasons.push(format!(
            "space: world with the L2 contraction around the cameras (centre {:?}: {how}; radius {:.3}): not forward-facing",
            model.center, model.radius
        ));
        let centre = DVec3::from(model.center.map(f64::from));
        let radius = model.radius as f64;
        // Pixel footprint at the typical distance to the scene's inner ball.
        let dist: Vec<f64> = cams
            .iter()
            .map(|c| (c.centre().distance(centre) - radius).max(model.near as f64))
            .collect();
        let d = dist.iter().sum::<f64>() / dist.len().max(1) as f64;
        let f = cams.iter().map(|c| c.fx.max(c.fy)).sum::<f64>() / cams.len().max(1) as f64;
        let footprint = (d / f.max(1.0)).max(1e-9);
        // The inner ball (diameter 2 r) spans half the contracted grid.
        let cells = 2.0 * (2.0 * radius / footprint);
        let res = (cells.min(8192.0) as u32)
            .max(64)
            .next_power_of_two()
            .min(8192);
        reasons.push(format!(
            "finest resolution {res}: pixel footprint {footprint:.2e} at distance {d:.3} (focal {f:.0} px); the inner ball of diameter {:.3} fills half the grid",
            2.0 * radius
        ));
        let c = occupancy_cascades(&model);
        reasons.push(format!(
            "occupancy: {c} cascades (far bound {:.3} is {:.1} scene radii; used by renders and visibility)",
            model.far,
            model.far as f64 / radius
        ));
        (res, c)
    };
    model.max_res = max_res.max(MIN_RES * 2);
    model.min_res = MIN_RES;
    let span = (model.max_res as f64 / MIN_RES as f64).ln();
    let aimed = ((1.0 + span / GROWTH.ln()).ceil() as u32).clamp(4, 16);
    // The fused training step, march and visibility read the encoding in vec4 rows: levels x
    // features must be a multiple of 4 (13 levels of 2 features fell back to the slower
    // standalone step, and `eval` and `visibility` refused the model).
    let mut levels = aimed;
    while !(levels * model.features).is_multiple_of(4) && levels < 16 {
        levels += 1;
    }
    model.levels = levels;
    let b = (span / (levels - 1) as f64).exp();
    let rounded = if levels != aimed {
        format!(
            " (rounded up from {aimed} so that the encoding fills the fused kernels' vec4 rows)"
        )
    } else {
        String::new()
    };
    reasons.push(format!(
        "levels {levels}: N {MIN_RES}..{} with growth {b:.2} per level (aim {GROWTH}){rounded}",
        model.max_res
    ));
    // Surfaces are 2-D: about N^2 / 2 occupied cells at the finest level.
    let want = (model.max_res as u64 * model.max_res as u64 / 2).max(1);
    let log2 = (64 - (want - 1).leading_zeros()).clamp(14, 19);
    model.log2_table = log2;
    reasons.push(format!(
        "table 2^{log2}: about N^2/2 = {want} surface cells at the finest level (clamped to 2^14..2^19)"
    ));
    AutoModel {
        model,
        cascades,
        reasons,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DMat4;

    fn cam(x: f64, w: u32, f: f64) -> Camera {
        Camera {
            c2w: DMat4::from_translation(DVec3::new(x, 0.0, 0.0)),
            width: w,
            height: w * 3 / 4,
            fx: f,
            fy: f,
            cx: w as f64 / 2.0,
            cy: w as f64 * 3.0 / 8.0,
            bounds: Some((1.0, 10.0)),
            image: "a.png".into(),
        }
    }

    #[test]
    fn forward_facing_scenes_get_ndc_and_a_pixel_sized_finest_cell() {
        let scene = Scene {
            source: "x".into(),
            cameras: (0..4).map(|i| cam(i as f64 * 0.1, 504, 400.0)).collect(),
            world_from_source: DMat4::IDENTITY,
            forward_facing: true,
            given: None,
            bounded_object: false,
        };
        let a = auto_model(&scene, &[0, 1, 2]);
        assert_eq!(a.model.space, Space::Ndc);
        assert_eq!(a.model.contraction, Contraction::None);
        assert_eq!(a.model.max_res, 512);
        assert_eq!(a.model.levels, 10);
        assert_eq!(a.model.log2_table, 17);
        assert_eq!(a.cascades, 1);
        assert!(a.model.validate().is_ok());
        assert_eq!(a.reasons.len(), 5, "{:?}", a.reasons);
        // A 4x larger image needs a 4x finer grid.
        let big = Scene {
            cameras: (0..4).map(|i| cam(i as f64 * 0.1, 2016, 1600.0)).collect(),
            ..scene
        };
        let b = auto_model(&big, &[0, 1, 2]);
        assert_eq!(b.model.max_res, 2048);
        assert!(b.model.levels > a.model.levels);
        assert_eq!(b.model.log2_table, 19);
        // 2048 aims at 13 levels; rounded up to 14 so that the fused kernels take the model.
        assert_eq!(b.model.levels, 14);
        assert!(b.reasons.iter().any(|r| r.contains("rounded up from 13")));
        for w in [64, 200, 504, 1000, 2016, 4000, 8000] {
            let m = auto_model(
                &Scene {
                    cameras: (0..4)
                        .map(|i| cam(i as f64 * 0.1, w, w as f64 * 0.8))
                        .collect(),
                    ..big.clone()
                },
                &[0, 1, 2],
            )
            .model;
            assert!(
                (m.levels * m.features).is_multiple_of(4),
                "{w} px: {} levels",
                m.levels
            );
            assert!(
                m.density_mlp().vec4_rows() && m.color_mlp().vec4_rows(),
                "{w} px"
            );
        }
    }

    /// A camera at `eye` looking at `target` (OpenGL convention: it looks down -z).
    fn looking_at(eye: DVec3, target: DVec3) -> Camera {
        let mut c = cam(0.0, 400, 350.0);
        let z = (eye - target).normalize();
        let up = if z.cross(DVec3::Y).length() < 1e-6 {
            DVec3::X
        } else {
            DVec3::Y
        };
        let x = up.cross(z).normalize();
        c.c2w = DMat4::from_cols(
            x.extend(0.0),
            z.cross(x).extend(0.0),
            z.extend(0.0),
            eye.extend(1.0),
        );
        c
    }

    /// Cameras on the upper hemisphere of radius 4 around `target` (a NeRF-synthetic rig),
    /// each aimed at a point `jitter` from the target in a fixed pseudo-random direction (so
    /// its axis passes within `jitter` of the target).
    fn hemisphere(target: DVec3, n: usize, jitter: f64) -> Vec<Camera> {
        (0..n)
            .map(|i| {
                let az = i as f64 * 2.399_963; // golden angle
                let el = 0.15 + 1.2 * (i as f64 + 0.5) / n as f64;
                let eye =
                    target + 4.0 * DVec3::new(el.cos() * az.cos(), el.sin(), el.cos() * az.sin());
                let off = DVec3::new(
                    (i as f64 * 1.7).sin(),
                    (i as f64 * 2.3).cos(),
                    (i as f64 * 0.9).sin(),
                )
                .normalize();
                looking_at(eye, target + jitter * off)
            })
            .collect()
    }

    #[test]
    fn a_360_rig_is_centred_where_its_optical_axes_meet() {
        let target = DVec3::new(1.0, -2.0, 0.5);
        // Exact axes: the target itself.
        let cams = hemisphere(target, 24, 0.0);
        let (c, how) = rig_centre(&cams);
        assert!(c.distance(target) < 1e-9, "{c} vs {target}");
        assert!(matches!(how, CentreFrom::OpticalAxes { rms } if rms < 1e-9));
        // The old centre, the mean of the camera centres, sits well above the object.
        let mean = cams.iter().map(Camera::centre).sum::<DVec3>() / cams.len() as f64;
        assert!(mean.distance(target) > 1.5, "{mean}");
        // Every axis within 0.05 of the target: the centre found is too.
        let (c, how) = rig_centre(&hemisphere(target, 24, 0.05));
        assert!(c.distance(target) < 0.05, "{c} vs {target}");
        assert!(matches!(how, CentreFrom::OpticalAxes { rms } if rms > 0.0 && rms < 0.05));
        // The model's inner ball is centred there and holds every camera.
        let scene = Scene {
            source: "x".into(),
            cameras: cams,
            world_from_source: DMat4::IDENTITY,
            forward_facing: false,
            given: None,
            bounded_object: false,
        };
        let m = model_for_scene(&scene);
        assert!(DVec3::from(m.center.map(f64::from)).distance(target) < 1e-5);
        assert!((m.radius - 4.0).abs() < 1e-4, "{}", m.radius);
        let a = auto_model(&scene, &[0, 1, 2]);
        assert!(
            a.reasons[0].contains("nearest the optical axes"),
            "{}",
            a.reasons[0]
        );
    }

    #[test]
    fn rigs_whose_axes_do_not_meet_are_centred_at_the_mean_camera() {
        // All looking the same way (parallel axes).
        let parallel: Vec<Camera> = (0..6).map(|i| cam(i as f64 * 0.3, 400, 350.0)).collect();
        let (c, how) = rig_centre(&parallel);
        assert_eq!(how, CentreFrom::CameraMean);
        assert!(c.distance(DVec3::new(0.75, 0.0, 0.0)) < 1e-12);
        // Looking outwards from a ring (a panorama): the axes meet behind the cameras.
        let outward: Vec<Camera> = (0..8)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 8.0;
                let eye = DVec3::new(a.cos(), 0.3, a.sin());
                looking_at(eye, eye * 2.0)
            })
            .collect();
        let (c, how) = rig_centre(&outward);
        assert_eq!(how, CentreFrom::CameraMean);
        assert!(c.distance(DVec3::new(0.0, 0.3, 0.0)) < 1e-12);
        // One camera: its centre.
        assert_eq!(rig_centre(&parallel[..1]).1, CentreFrom::CameraMean);
    }

    #[test]
    fn unbounded_scenes_get_contraction_and_cascades() {
        // Cameras on a circle of radius 4 looking at the origin.
        let cameras: Vec<Camera> = (0..8)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 8.0;
                let eye = DVec3::new(4.0 * a.cos(), 0.0, 4.0 * a.sin());
                let mut c = cam(0.0, 400, 350.0);
                let z = eye.normalize();
                let x = DVec3::Y.cross(z).normalize();
                c.c2w = DMat4::from_cols(
                    x.extend(0.0),
                    z.cross(x).extend(0.0),
                    z.extend(0.0),
                    eye.extend(1.0),
                );
                c.bounds = Some((0.5, 60.0));
                c
            })
            .collect();
        let scene = Scene {
            source: "x".into(),
            cameras,
            world_from_source: DMat4::IDENTITY,
            forward_facing: false,
            given: None,
            bounded_object: false,
        };
        let a = auto_model(&scene, &[0, 1, 2, 3, 4, 5, 6, 7]);
        assert_eq!(a.model.space, Space::World);
        assert_eq!(a.model.contraction, Contraction::L2);
        assert!((64..=8192).contains(&a.model.max_res));
        assert!(a.model.max_res.is_power_of_two());
        // far 60 over radius 4: 15 radii -> 4 + 1 cascades.
        assert_eq!(a.cascades, 5);
        assert!(a.model.validate().is_ok());
    }
}
