//! Scene-driven model configuration: model only what the scene requires. From the cameras and
//! their bounds it chooses the ray space (NDC for forward-facing captures, contracted world
//! space otherwise), the finest hash-grid resolution from the pixel footprint, the levels and
//! table size from that, and the occupancy cascades from the depth range; each choice comes with
//! the reason, which `extranerf train --auto` prints.

use glam::DVec3;

use crate::data::{Camera, Scene};
use crate::field::encodings::Contraction;
use crate::model::{ModelConfig, ProposalConfig, Sampler, Space};

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

/// Main samples per ray with the proposal sampler unless told ([`default_sampling`]).
pub const PROPOSAL_MAIN_SAMPLES: u32 = 16;

/// The proposal sampler for a main grid of finest resolution `max_res` (its own grid is no
/// finer), with `samples` strata per ray or [`ProposalConfig::default`]'s 32.
pub fn proposal_for(max_res: u32, samples: Option<u32>) -> ProposalConfig {
    let mut p = ProposalConfig::default();
    if let Some(s) = samples {
        p.samples = s;
    }
    p.max_res = p.max_res.min(max_res);
    p.min_res = p.min_res.min(p.max_res);
    p
}

/// Why the proposal sampler is the default, as the logs say it: the measurement, not this run's
/// settings (its flags may change the strata and samples; the trainer prints those).
pub const DEFAULT_SAMPLER_WHY: &str = "sampler: proposal, the default (on fern few-shot 17 its 32 strata for 16 samples per ray reached uniform 32's held-out PSNR in 0.35x the training time; --sampler uniform for strata)";

/// The sampler and the main samples per ray `train` and `extrapolate` use unless told
/// ([`DEFAULT_SAMPLER_WHY`]): the proposal sampler, 32 strata of its field and 16 main samples per ray
/// ([`proposal_for`] the model's grid). Measured on fern few-shot 17 with 2 cores
/// (`results/proposal_lavapipe/`): a step takes 0.70x the time of uniform 32 samples, and the
/// held-out PSNR passes the uniform recipe's final 24.14 dB by step 2121 of 4242 (0.35x its
/// training time) and ends at 25.54 dB; 64 strata for 32 samples costs 1.27x per step, and 32
/// for 8 falls short (22.54 dB in 2121 steps).
pub fn default_sampling(model: &ModelConfig) -> (Sampler, u32) {
    (
        Sampler::Proposal(proposal_for(model.max_res, None)),
        PROPOSAL_MAIN_SAMPLES,
    )
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

/// Samples start at this fraction of the nearest depth bound, as NeRF's LLFF loader starts
/// them (the bounds are the 0.1 and 99.9 percentiles of each view's COLMAP point depths, so a
/// few points lie nearer); they end at the farthest bound.
pub const NEAR_MARGIN: f64 = 0.9;

/// The grid box of an NDC field.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum GridBox {
    /// The cube that holds every sample of every camera ([`ndc_extent`]), its resolutions
    /// scaled to keep the unit cube's cell size.
    #[default]
    Cameras,
    /// The cube that holds every sample of the cameras trained on and of the virtual views,
    /// scaled in the same way; a held-out view's samples beyond it take a face's features.
    Training,
    /// NDC's unit cube [-1, 1]^3 (before 2026-12: what lies outside takes a face's features).
    Unit,
}

/// The range of NDC t an NDC field samples.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum SampleRange {
    /// Between the cameras' depth bounds ([`ndc_extent`]).
    #[default]
    Bounds,
    /// 0 to 1: the near plane to infinity (before 2026-12).
    Full,
}

/// How an NDC field fits its scene.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct NdcFit {
    /// The grid box.
    pub grid_box: GridBox,
    /// The sampled range.
    pub range: SampleRange,
}

/// Where a forward-facing scene's samples lie in NDC (near plane 1): the range of t every ray
/// samples, and the axis-aligned box that holds every sample of every camera given.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NdcExtent {
    /// NDC t of the first and of the last sample of every ray.
    pub t: (f64, f64),
    /// The box's lowest corner.
    pub min: DVec3,
    /// The box's highest corner.
    pub max: DVec3,
}

impl NdcExtent {
    /// The smallest cube centred on the box that holds it: centre and half side.
    pub fn cube(&self) -> (DVec3, f64) {
        let half = (self.max - self.min) * 0.5;
        (
            (self.min + self.max) * 0.5,
            half.x.max(half.y).max(half.z).max(1e-6),
        )
    }
}

/// The scene's depth range along the viewing axis: [`NEAR_MARGIN`] times the nearest camera's
/// near bound to the farthest camera's far bound; `None` when no camera gives bounds.
pub fn scene_depth_range(cameras: &[Camera]) -> Option<(f64, f64)> {
    crate::data::depth_bounds(cameras).map(|(near, far)| (NEAR_MARGIN * near, far))
}

/// The world rays through the four image corners of `cam` (pixel-corner coordinates).
fn corner_rays(cam: &Camera) -> [(DVec3, DVec3); 4] {
    let (w, h) = (cam.width as f64, cam.height as f64);
    [(0.0, 0.0), (w, 0.0), (0.0, h), (w, h)].map(|(x, y)| cam.ray(x, y))
}

/// [`corner_rays`] in NDC with near plane 1, as the kernels make them: origin and direction.
fn ndc_corner_rays(cam: &Camera) -> [([f64; 3], [f64; 3]); 4] {
    corner_rays(cam).map(|(o, d)| crate::reference::ndc_ray(cam, o.to_array(), d.to_array(), 1.0))
}

/// Where the samples of a forward-facing scene lie in NDC. The t range runs from the nearest
/// point at [`NEAR_MARGIN`] times a camera's near bound to the farthest at a camera's far bound
/// (each camera's own bounds, over its image corners: depth along its axis is affine across
/// the image, so the corners bound it); 0 to 1 (the near plane to infinity) when no camera
/// gives bounds. The box holds the samples of the cameras of `scene` that `boxed` lists
/// (indices; all of them when `None`) and of `extra` (virtual views): NDC positions are affine
/// in t along a ray, and at a given t (a plane of world z) the image maps projectively onto a
/// convex quad whose vertices are the corner rays' points (for rays that run toward -z, as a
/// forward-facing camera's do), so the corner rays at both ends of the range bound them. A corner ray that never reaches the plane has no NDC point
/// and is left out; [`MAX_BOX_HALF`] caps what such views would do to the box.
pub fn ndc_extent(
    scene: &[Camera],
    boxed: Option<&[usize]>,
    extra: &[Camera],
    range: SampleRange,
) -> NdcExtent {
    let bounds = match range {
        SampleRange::Bounds => scene_depth_range(scene),
        SampleRange::Full => None,
    };
    let t = match bounds {
        Some(whole) => {
            let (mut t0, mut t1) = (1.0f64, 0.0f64);
            for c in scene {
                // Each camera's own bounds (those of the points it sees); the scene's where it
                // has none.
                let (near, far) = c.bounds.map(|(n, f)| (NEAR_MARGIN * n, f)).unwrap_or(whole);
                for (o, d) in corner_rays(c) {
                    // NDC t of world depth z (< 0, near plane z = -1): 1 + 1/z. Nearer than
                    // the near plane: 0; at or behind z = 0: infinity, 1.
                    let zn = (o + d * near).z;
                    t0 = t0.min(if zn <= -1.0 { 1.0 + 1.0 / zn } else { 0.0 });
                    let zf = (o + d * far).z;
                    t1 = t1.max(if zf < 0.0 {
                        (1.0 + 1.0 / zf).max(0.0)
                    } else {
                        1.0
                    });
                }
            }
            if t1 - t0 >= 1e-3 {
                (t0, t1)
            } else {
                (0.0, 1.0)
            }
        }
        None => (0.0, 1.0),
    };
    let (mut min, mut max) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    let held: Vec<&Camera> = match boxed {
        Some(ix) => ix.iter().filter_map(|&i| scene.get(i)).collect(),
        None => scene.iter().collect(),
    };
    for c in held.into_iter().chain(extra) {
        for (o, d) in ndc_corner_rays(c) {
            for s in [t.0, t.1] {
                let p = DVec3::from(o) + DVec3::from(d) * s;
                if p.is_finite() {
                    min = min.min(p);
                    max = max.max(p);
                }
            }
        }
    }
    if !(min.is_finite() && max.is_finite()) {
        (min, max) = (DVec3::splat(-1.0), DVec3::splat(1.0));
    }
    NdcExtent { t, min, max }
}

/// For each pixel of `cam` (row-major), whether its point at NDC t `depth` lies inside the cube
/// of `centre` and half side `half` (NDC, near plane 1). A pixel whose depth is not finite counts
/// as outside.
pub fn ndc_pixels_in_cube(cam: &Camera, depth: &[f32], centre: DVec3, half: f64) -> Vec<bool> {
    let w = cam.width.max(1) as usize;
    depth
        .iter()
        .enumerate()
        .map(|(i, &t)| {
            let (x, y) = ((i % w) as f64 + 0.5, (i / w) as f64 + 0.5);
            let (o, d) = cam.ray(x, y);
            let (no, nd) = crate::reference::ndc_ray(cam, o.to_array(), d.to_array(), 1.0);
            let p = DVec3::from(no) + DVec3::from(nd) * t as f64;
            p.is_finite() && (p - centre).abs().max_element() <= half
        })
        .collect()
}

/// The largest half side of an NDC grid box: 4 times the unit cube's, at 4 times its
/// resolution per axis. Views turned far from the NDC axis (a `rotate` trajectory's far end)
/// could otherwise ask for a box no grid resolves.
pub const MAX_BOX_HALF: f64 = 4.0;

/// A cube's half side grows by this factor over the samples' extent, so that rounding in the
/// kernels' f32 arithmetic never puts a sample on the far side of a face.
const BOX_SLACK: f64 = 1.001;

/// The model configuration a scene needs: NDC for forward-facing captures, sampled between the
/// scene's bounds, its grid box the cube that holds every sample of the scene's cameras (of
/// those trained on, `train`, with [`GridBox::Training`]; all of them when `train` is empty)
/// and of `extra` ([`ndc_extent`]), with the default grid's resolutions scaled by the cube's
/// half side (the same cell size as over NDC's unit cube); otherwise world space with the L2
/// contraction around the rig's centre ([`rig_centre`]) with the farthest camera on the inner
/// ball's surface, sampled between the cameras' bounds.
pub fn model_covering(
    scene: &Scene,
    train: &[usize],
    extra: &[Camera],
    fit: NdcFit,
) -> ModelConfig {
    if scene.forward_facing {
        return ndc_model(scene, train, extra, fit).0;
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

/// The scene cameras (indices) an NDC box holds, all of them when `None`: those trained on
/// with [`GridBox::Training`] (all when `train` is empty).
fn boxed_cameras(fit: NdcFit, train: &[usize]) -> Option<&[usize]> {
    (fit.grid_box == GridBox::Training && !train.is_empty()).then_some(train)
}

/// [`model_covering`] of a forward-facing scene, with the extent it was fitted to.
fn ndc_model(
    scene: &Scene,
    train: &[usize],
    extra: &[Camera],
    fit: NdcFit,
) -> (ModelConfig, NdcExtent) {
    let e = ndc_extent(&scene.cameras, boxed_cameras(fit, train), extra, fit.range);
    let (centre, radius) = match fit.grid_box {
        GridBox::Cameras | GridBox::Training => {
            let (centre, half) = e.cube();
            (centre, (half * BOX_SLACK).min(MAX_BOX_HALF))
        }
        GridBox::Unit => (DVec3::ZERO, 1.0),
    };
    let d = ModelConfig::default();
    let model = ModelConfig {
        near: e.t.0 as f32,
        far: e.t.1 as f32,
        center: centre.as_vec3().to_array(),
        radius: radius as f32,
        min_res: scaled_res(d.min_res, radius),
        max_res: scaled_res(d.max_res, radius),
        ..d
    };
    (model, e)
}

/// [`model_covering`] with no extra cameras and the default fit.
pub fn model_for_scene(scene: &Scene) -> ModelConfig {
    model_covering(scene, &[], &[], NdcFit::default())
}

/// A resolution over NDC's unit cube, for a cube of half side `radius` at the same cell size.
fn scaled_res(res: u32, radius: f64) -> u32 {
    ((res as f64 * radius).round() as u32).clamp(1, 1 << 20)
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
    auto_model_covering(scene, train, &[], NdcFit::default())
}

/// Chooses the model for `scene` trained on the cameras `train` (indices), its grid box also
/// holding the samples of `extra` (the virtual views to be rendered), fitted as `fit` says.
pub fn auto_model_covering(
    scene: &Scene,
    train: &[usize],
    extra: &[Camera],
    fit: NdcFit,
) -> AutoModel {
    let (mut model, extent) = if scene.forward_facing {
        let (m, e) = ndc_model(scene, train, extra, fit);
        (m, Some(e))
    } else {
        (model_covering(scene, train, extra, fit), None)
    };
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
    let (max_res, cascades) = if let Some(e) = extent {
        reasons.push(
            "space: NDC (a forward-facing capture: the frustum, out to infinity, maps to a cube), no contraction".into(),
        );
        reasons.push(format!(
            "samples: NDC t {:.3} to {:.3}, linear in disparity ({})",
            e.t.0,
            e.t.1,
            match (fit.range, scene_depth_range(&scene.cameras)) {
                (SampleRange::Full, _) => "asked for: the near plane to infinity".into(),
                (SampleRange::Bounds, Some((n, f))) => format!(
                    "from {NEAR_MARGIN} x each camera's near bound to its far bound, the nearest and farthest points over the cameras; depth {n:.3} to {f:.3} in all"
                ),
                (SampleRange::Bounds, None) =>
                    "no depth bounds: the near plane to infinity".into(),
            }
        ));
        let what = format!(
            "{}{} (x {:.3}..{:.3}, y {:.3}..{:.3}, z {:.3}..{:.3})",
            match boxed_cameras(fit, train) {
                Some(t) => format!("the {} training cameras", t.len()),
                None => format!("the scene's {} cameras", scene.cameras.len()),
            },
            if extra.is_empty() {
                String::new()
            } else {
                format!(" and {} virtual views", extra.len())
            },
            e.min.x,
            e.max.x,
            e.min.y,
            e.max.y,
            e.min.z,
            e.max.z
        );
        reasons.push(match fit.grid_box {
            GridBox::Cameras | GridBox::Training if model.radius as f64 >= MAX_BOX_HALF => format!(
                "grid box: centre {:?}, half side {:.3}: capped, it does not hold every sample of {what}",
                model.center, model.radius
            ),
            GridBox::Cameras | GridBox::Training => format!(
                "grid box: centre {:?}, half side {:.3}, holding every sample of {what}",
                model.center, model.radius
            ),
            GridBox::Unit => {
                format!("grid box: NDC's unit cube, as asked for; the samples of {what}")
            }
        });
        // NDC x and y span the image: one finest cell per pixel over the unit cube, and the
        // same cell size over the box.
        let pixels = widest.next_power_of_two();
        let res = scaled_res(pixels, model.radius as f64);
        reasons.push(format!(
            "finest resolution {res}: one cell per pixel across the {widest}-pixel image side ({pixels} over NDC's unit cube, which spans the image; x {:.3} for the box)",
            model.radius
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
    // In NDC every level keeps the cell size it has over the unit cube.
    let box_scale = match model.space {
        Space::Ndc => model.radius as f64,
        Space::World => 1.0,
    };
    let min_res = scaled_res(MIN_RES, box_scale);
    model.max_res = max_res.max(min_res * 2);
    model.min_res = min_res;
    let span = (model.max_res as f64 / min_res as f64).ln();
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
        "levels {levels}: N {min_res}..{} with growth {b:.2} per level (aim {GROWTH}){rounded}",
        model.max_res
    ));
    // Surfaces are 2-D: N^2 cells at the finest level for each layer of surface across the
    // image, and a scene has a few layers (fern's leaves). In NDC the surfaces the cameras see
    // span about the image, not the box around every camera's frustum. 2 N^2 entries: on fern
    // few-shot 17 at 1024 rays per step 2^19 fitted better than N^2/2 = 2^17 per sample
    // (+0.21 dB at 49 M samples) and per second (tools/recipe_fern.sh, tools/bench_recipe.sh).
    let surface_res = (model.max_res as f64 / box_scale).round() as u64;
    let want = (2 * surface_res * surface_res).max(1);
    let log2 = (64 - (want - 1).leading_zeros()).clamp(14, 19);
    model.log2_table = log2;
    reasons.push(format!(
        "table 2^{log2}: 2 N^2 = {want} entries, a few layers of surface cells at the finest level, N = {surface_res} across the image (clamped to 2^14..2^19)"
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
            depth_files: Vec::new(),
        };
        let a = auto_model(&scene, &[0, 1, 2]);
        assert_eq!(a.model.space, Space::Ndc);
        assert_eq!(a.model.contraction, Contraction::None);
        // The cameras run from x = 0 to 0.3; the box holds their frusta from the near plane
        // (the near bound 0.9 lies before it, so t starts at 0): NDC x from -1 to
        // (0.3 + 252 / 400) x 2 x 400 / 504 = 1.476, y -1 to 1, z -1 to 0.8 (depth 10).
        let r = a.model.radius as f64;
        let half = (0.93 * 800.0 / 504.0 + 1.0) / 2.0;
        assert!((r - half * BOX_SLACK).abs() < 1e-5, "{r}");
        assert!((a.model.center[0] as f64 - (half - 1.0)).abs() < 1e-5);
        assert!(a.model.near == 0.0 && (a.model.far - 0.9).abs() < 1e-6);
        // One finest cell per pixel: 512 cells over the unit cube, the same size over the box.
        assert_eq!(a.model.max_res, (512.0 * r).round() as u32);
        assert_eq!(a.model.min_res, (16.0 * r).round() as u32);
        assert_eq!(a.model.levels, 10);
        // 2 x 512^2 entries.
        assert_eq!(a.model.log2_table, 19);
        assert_eq!(a.cascades, 1);
        assert!(a.model.validate().is_ok());
        assert_eq!(a.reasons.len(), 7, "{:?}", a.reasons);
        // The unit cube and the whole of t: the model before the box was fitted.
        let before = NdcFit {
            grid_box: GridBox::Unit,
            range: SampleRange::Full,
        };
        let old = auto_model_covering(&scene, &[0, 1, 2], &[], before).model;
        assert_eq!(
            (old.center, old.radius, old.near, old.far),
            ([0.0; 3], 1.0, 0.0, 1.0)
        );
        assert_eq!(
            (old.min_res, old.max_res, old.levels, old.log2_table),
            (16, 512, 10, 19)
        );
        // A 4x larger image needs a 4x finer grid.
        let big = Scene {
            cameras: (0..4).map(|i| cam(i as f64 * 0.1, 2016, 1600.0)).collect(),
            ..scene
        };
        let b = auto_model(&big, &[0, 1, 2]);
        assert_eq!(b.model.max_res, (2048.0 * r).round() as u32);
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

    /// A single camera at the origin looking down -z sees NDC's unit square at every t; with
    /// bounds 2 and 8 its samples run from t = 1 - 1 / (0.9 x 2) to 1 - 1 / 8.
    #[test]
    fn a_centred_camera_samples_between_its_bounds_in_the_unit_square() {
        let mut c = cam(0.0, 400, 300.0);
        c.bounds = Some((2.0, 8.0));
        let e = ndc_extent(std::slice::from_ref(&c), None, &[], SampleRange::Bounds);
        let (t0, t1) = (1.0 - 1.0 / 1.8, 1.0 - 1.0 / 8.0);
        assert!(
            (e.t.0 - t0).abs() < 1e-12 && (e.t.1 - t1).abs() < 1e-12,
            "{:?}",
            e.t
        );
        // NDC x and y of the image edges are +-1 at every t (f32 focal lengths, as the kernels).
        for v in [e.min.x, e.min.y] {
            assert!((v + 1.0).abs() < 1e-6, "{e:?}");
        }
        for v in [e.max.x, e.max.y] {
            assert!((v - 1.0).abs() < 1e-6, "{e:?}");
        }
        assert!((e.min.z - (2.0 * t0 - 1.0)).abs() < 1e-9, "{e:?}");
        assert!((e.max.z - (2.0 * t1 - 1.0)).abs() < 1e-9, "{e:?}");
        let (centre, half) = e.cube();
        assert!(
            (half - 1.0).abs() < 1e-6 && centre.x.abs() < 1e-6,
            "{centre} {half}"
        );
        // Without bounds: the near plane to infinity.
        c.bounds = None;
        assert_eq!(
            ndc_extent(&[c.clone()], None, &[], SampleRange::Bounds).t,
            (0.0, 1.0)
        );
        c.bounds = Some((2.0, 8.0));
        assert_eq!(ndc_extent(&[c], None, &[], SampleRange::Full).t, (0.0, 1.0));
    }

    /// A camera moved 0.5 right of the NDC axis sees, on the near plane (t = 0), NDC x =
    /// 1 + 2 dx for a pixel at dx = (x - cx) / fx: its left half lies in the unit cube.
    #[test]
    fn pixels_in_the_cube_follow_from_their_depth() {
        let c = cam(0.5, 40, 40.0);
        let n = (c.width * c.height) as usize;
        let inside = ndc_pixels_in_cube(&c, &vec![0.0; n], DVec3::ZERO, 1.0);
        for (i, &v) in inside.iter().enumerate() {
            assert_eq!(v, i % 40 < 20, "pixel {i}");
        }
        // Farther away (t = 0.5: world depth 2), NDC x = 0.5 + 2 dx: the columns left of
        // x = 30 are inside. A depth that is not finite is outside. A cube centred on x = 1
        // holds every pixel at t = 0.
        let mut depth = vec![0.5f32; n];
        depth[7] = f32::NAN;
        let inside = ndc_pixels_in_cube(&c, &depth, DVec3::ZERO, 1.0);
        for (i, &v) in inside.iter().enumerate() {
            assert_eq!(v, i % 40 < 30 && i != 7, "pixel {i}");
        }
        let shifted = ndc_pixels_in_cube(&c, &vec![0.0; n], DVec3::new(1.0, 0.0, 0.0), 1.0);
        assert!(shifted.iter().all(|&v| v));
    }

    /// Every sample of every pixel of every camera, a rig moved and turned off the NDC axis and
    /// virtual views beyond it, lies in the box; the range starts at the nearest point of the
    /// near bound and ends at the farthest of the far bound.
    #[test]
    fn the_ndc_box_holds_every_sample_of_every_camera() {
        let mut cams: Vec<Camera> = (0..6)
            .map(|i| {
                let mut c = cam(0.0, 40, 36.0);
                let a = i as f64;
                c.c2w = DMat4::from_translation(DVec3::new(
                    0.4 * (a * 1.3).sin(),
                    0.2 * (a * 0.7).cos(),
                    0.1 * (a * 2.1).sin(),
                )) * DMat4::from_rotation_y(0.08 * (a - 2.5))
                    * DMat4::from_rotation_x(0.05 * (a * 1.9).cos());
                c.bounds = Some((1.5 + 0.1 * a, 6.0 + a));
                c
            })
            .collect();
        let virt: Vec<Camera> = (0..3)
            .map(|i| {
                let mut c = cams[i].clone();
                c.c2w = DMat4::from_translation(DVec3::new(1.2 - 0.8 * i as f64, 0.5, 0.0));
                c
            })
            .collect();
        let e = ndc_extent(&cams, None, &virt, SampleRange::Bounds);
        // Depth 0.9 x 1.5 and 11 along an unturned axis would be t 0.26 and 0.91; the turned
        // corners reach nearer and farther.
        assert!(e.t.0 > 0.0 && e.t.0 < 0.26, "{:?}", e.t);
        assert!(e.t.1 > 0.85 && e.t.1 < 1.0, "{:?}", e.t);
        let (centre, half) = e.cube();
        // (lowest t of a near-bound point, highest t of a far-bound point) over every pixel.
        let mut scene_t = (f64::INFINITY, f64::NEG_INFINITY);
        let mut reach = 0.0f64;
        let t_of = |z: f64| 1.0 + 1.0 / z;
        cams.extend(virt);
        for (k, c) in cams.iter().enumerate() {
            for py in 0..=c.height {
                for px in 0..=c.width {
                    let (o, d) = c.ray(px as f64, py as f64);
                    let (no, nd) = crate::reference::ndc_ray(c, o.to_array(), d.to_array(), 1.0);
                    for s in [e.t.0, e.t.1] {
                        let p = DVec3::from(no) + DVec3::from(nd) * s;
                        let off = (p - centre).abs().max_element();
                        assert!(
                            off <= half * (1.0 + 1e-9),
                            "camera {k} ({px}, {py}) t {s}: {p}"
                        );
                        reach = reach.max(off / half);
                    }
                    if k < 6 {
                        let (n, f) = c.bounds.unwrap();
                        scene_t.0 = scene_t.0.min(t_of((o + d * NEAR_MARGIN * n).z));
                        scene_t.1 = scene_t.1.max(t_of((o + d * f).z));
                    }
                }
            }
        }
        // The box is tight: some sample touches a face.
        assert!(reach > 1.0 - 1e-9, "{reach}");
        // The samples span exactly the depths between the bounds (in the NDC frame's depth):
        // none nearer than the nearest near-bound point, none beyond the farthest far one.
        assert!((e.t.0 - scene_t.0).abs() < 1e-12, "{:?} {scene_t:?}", e.t);
        assert!((e.t.1 - scene_t.1).abs() < 1e-12, "{:?} {scene_t:?}", e.t);
        // The box of the cameras trained on (0, 2, 4) and the virtual views (now 6..9): the
        // same range, a cube no larger that holds their samples.
        let trained = [0, 2, 4];
        let et = ndc_extent(&cams[..6], Some(&trained), &cams[6..], SampleRange::Bounds);
        assert_eq!(et.t, e.t);
        let (centre_t, half_t) = et.cube();
        assert!(half_t <= half, "{half_t} > {half}");
        for (k, c) in cams.iter().enumerate() {
            if k < 6 && !trained.contains(&k) {
                continue;
            }
            for (px, py) in [
                (0, 0),
                (c.width, 0),
                (0, c.height),
                (c.width / 2, c.height / 3),
            ] {
                let (o, d) = c.ray(px as f64, py as f64);
                let (no, nd) = crate::reference::ndc_ray(c, o.to_array(), d.to_array(), 1.0);
                for s in [e.t.0, 0.5 * (e.t.0 + e.t.1), e.t.1] {
                    let p = DVec3::from(no) + DVec3::from(nd) * s;
                    let off = (p - centre_t).abs().max_element();
                    assert!(off <= half_t * (1.0 + 1e-9), "camera {k} t {s}: {p}");
                }
            }
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
            depth_files: Vec::new(),
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
            depth_files: Vec::new(),
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
