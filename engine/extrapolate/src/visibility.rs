//! Visibility of views against a trained field's training cameras (ExtraNeRF's multi-view
//! transmittance), as the pipeline and `extranerf visibility` compute it: settings, a run
//! loaded for queries ([`RunVisibility`]), the transmittance volumes, maps and their files, the
//! inpainting mask a map implies, and depth completion where the map says unseen.

use std::path::Path;
use std::time::Instant;

use extranerf_gpu::Context;
use extranerf_nerf::data::Camera;
use extranerf_nerf::depth_completion::DepthCompletion;
use extranerf_nerf::render::occupancy::OccupancyConfig;
use extranerf_nerf::render::visibility::{
    Density, RaySamples, TransmittanceVolume, Visibility, VisibilityConfig, VisibilityMap,
    VisibilityMeasure, MAX_RANK, MAX_TRAIN_CAMERAS,
};
use extranerf_nerf::renderer::{Nerf, OccupancyStats};
use extranerf_nerf::run::{
    ray_depth_to_view_depth, write_depth_exr, write_exr_channels, write_png, write_ray_depth_exr,
};
use extranerf_nerf::safetensors::{SafeTensors, Tensor};
use extranerf_prims::Prims;
use serde::{Deserialize, Serialize};

use crate::base::BaseField;
use crate::error::{ExtrapolateError, Result};

/// How visibility is computed and turned into a mask.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VisSettings {
    /// Samples per camera ray (0: the run's training setting).
    pub samples: u32,
    /// Which largest transmittance across the training cameras counts (2: the paper).
    pub rank: u32,
    /// Samples whose weight is at most this are not marched toward the cameras.
    pub min_weight: f32,
    /// Segments stop once their transmittance falls below this.
    pub min_transmittance: f32,
    /// Rays across each training camera's transmittance volume.
    pub volume_res: u32,
    /// Depth strata of the transmittance volumes.
    pub volume_depth: u32,
    /// A pixel is to be inpainted when the share of its rendered content that the training
    /// cameras saw (visibility over opacity) is below this.
    pub threshold: f32,
    /// ... or when its opacity is below this (the field renders nothing there).
    pub min_opacity: f32,
    /// Pixels per submission.
    pub chunk: u32,
    /// Transmittance absolute (the paper) or relative to the pixel ray's own (robust to a
    /// field that renders surfaces as semi-transparent shells). Manifests written before this
    /// setting existed computed the absolute one.
    #[serde(default = "absolute")]
    pub measure: VisibilityMeasure,
}

fn absolute() -> VisibilityMeasure {
    VisibilityMeasure::Absolute
}

impl Default for VisSettings {
    fn default() -> Self {
        VisSettings {
            samples: 0,
            rank: 2,
            min_weight: 1e-3,
            min_transmittance: 1e-3,
            volume_res: 128,
            volume_depth: 128,
            threshold: 0.5,
            min_opacity: 0.1,
            chunk: 4096,
            measure: VisibilityMeasure::Relative,
        }
    }
}

impl VisSettings {
    /// The kernel configuration at `rank` for a field trained with `train_samples` per ray.
    pub fn config(&self, rank: u32, train_samples: u32) -> Result<VisibilityConfig> {
        if !(0.0..=1.0).contains(&self.threshold) || !(0.0..=1.0).contains(&self.min_opacity) {
            return Err(ExtrapolateError::usage(format!(
                "visibility threshold {} and minimum opacity {}: use values in [0, 1]",
                self.threshold, self.min_opacity
            )));
        }
        if self.volume_res == 0 || self.volume_depth == 0 || self.chunk == 0 {
            return Err(ExtrapolateError::usage(
                "the transmittance volume's size and the chunk must be positive",
            ));
        }
        checked_config(
            &QuerySettings {
                samples: (self.samples != 0).then_some(self.samples),
                vis_samples: 32,
                min_weight: self.min_weight,
                min_transmittance: self.min_transmittance,
                measure: self.measure,
            },
            rank,
            train_samples,
            "visibility ",
        )
    }

    /// The inpainting mask of a map: 1 where the pixel is to be filled.
    pub fn mask(&self, m: &VisibilityMap) -> Vec<f32> {
        m.visibility
            .iter()
            .zip(&m.opacity)
            .map(|(&v, &o)| {
                let seen = v / o.max(1e-6);
                f32::from(o < self.min_opacity || seen < self.threshold)
            })
            .collect()
    }
}

/// A field's density for the visibility kernels.
pub fn density(nerf: &Nerf) -> Result<Density<'_>> {
    Ok(Density::Field {
        field: nerf.field(),
        params: nerf.field().layout().sections(nerf.params())?,
        occupancy: nerf.occupancy(),
    })
}

/// The visibility kernels with one set of training cameras' transmittance volumes.
pub struct FieldVisibility {
    vis: Visibility,
    volume: TransmittanceVolume,
    train: Vec<Camera>,
}

impl std::fmt::Debug for FieldVisibility {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FieldVisibility")
            .field("cameras", &self.train.len())
            .field("volume", &self.volume.size())
            .finish_non_exhaustive()
    }
}

impl FieldVisibility {
    /// Builds the transmittance volumes of `train` through `nerf`.
    pub fn new(
        ctx: &Context,
        nerf: &Nerf,
        train: &[Camera],
        s: &VisSettings,
    ) -> Result<FieldVisibility> {
        if train.is_empty() || train.len() > MAX_TRAIN_CAMERAS {
            return Err(ExtrapolateError::usage(format!(
                "visibility needs 1 to {MAX_TRAIN_CAMERAS} training cameras, not {}",
                train.len()
            )));
        }
        let vis = Visibility::new(ctx)?;
        let volume = vis.build_volume(ctx, &density(nerf)?, train, s.volume_res, s.volume_depth)?;
        Ok(FieldVisibility {
            vis,
            volume,
            train: train.to_vec(),
        })
    }

    /// The map of `cam` against the training cameras of `mask` (bit i: camera i counts).
    pub fn map(
        &self,
        ctx: &Context,
        nerf: &Nerf,
        cam: &Camera,
        mask: u32,
        cfg: &VisibilityConfig,
        chunk: u32,
    ) -> Result<VisibilityMap> {
        Ok(self.vis.map_with(
            ctx,
            &density(nerf)?,
            RaySamples::of(nerf),
            cam,
            &self.train,
            mask,
            cfg,
            Some(&self.volume),
            chunk,
        )?)
    }
}

/// How `extranerf visibility` queries a run: the kernel settings apart from the rank.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QuerySettings {
    /// Samples per camera ray (`None`: the run's training setting).
    pub samples: Option<u32>,
    /// Samples per segment toward a training camera (segment march).
    pub vis_samples: u32,
    /// Samples whose weight is at most this are not marched toward the cameras.
    pub min_weight: f32,
    /// Segments stop once their transmittance falls below this.
    pub min_transmittance: f32,
    /// Absolute or relative transmittance.
    pub measure: VisibilityMeasure,
}

/// The kernel configuration of `q` at `rank` (samples per ray `train_samples` unless `q`
/// says), with every setting checked; errors name a setting as `prefix` + its flag's name
/// (`--` for the command line's flags).
pub fn checked_config(
    q: &QuerySettings,
    rank: u32,
    train_samples: u32,
    prefix: &str,
) -> Result<VisibilityConfig> {
    if !(1..=MAX_RANK).contains(&rank) {
        return Err(ExtrapolateError::usage(format!(
            "visibility rank {rank}: use 1 to {MAX_RANK}"
        )));
    }
    for (name, v) in [
        ("min-weight", q.min_weight),
        ("min-transmittance", q.min_transmittance),
    ] {
        if !(0.0..1.0).contains(&v) {
            return Err(ExtrapolateError::usage(format!(
                "{prefix}{name} {v}: use a value in [0, 1)"
            )));
        }
    }
    if q.vis_samples == 0 || q.samples == Some(0) || train_samples == 0 {
        return Err(ExtrapolateError::usage(format!(
            "{prefix}samples and {prefix}vis-samples must be positive"
        )));
    }
    Ok(VisibilityConfig {
        samples: q.samples.unwrap_or(train_samples),
        vis_samples: q.vis_samples,
        rank,
        min_weight: q.min_weight,
        min_transmittance: q.min_transmittance,
        measure: q.measure,
    })
}

/// What building the occupancy grid of a loaded run found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OccupancyBuilt {
    /// Cells per axis.
    pub res: u32,
    /// Cells, and how many are occupied.
    pub stats: OccupancyStats,
    /// Seconds the build took.
    pub seconds: f64,
}

/// A trained run ready for visibility queries: checkpoint -> field (-> occupancy grid) ->
/// the training cameras' transmittance volumes -> maps.
pub struct RunVisibility {
    /// The run's checkpoint, scene and field.
    pub base: BaseField,
    vis: Visibility,
    volume: Option<TransmittanceVolume>,
}

impl std::fmt::Debug for RunVisibility {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("RunVisibility")
            .field("base", &self.base)
            .field("volume", &self.volume.as_ref().map(|v| v.size()))
            .finish_non_exhaustive()
    }
}

impl RunVisibility {
    /// Loads the run in `dir` (a folder of `extranerf train`).
    pub fn load(ctx: &Context, dir: &Path) -> Result<RunVisibility> {
        Ok(RunVisibility {
            base: BaseField::load(ctx, dir)?,
            vis: Visibility::new(ctx)?,
            volume: None,
        })
    }

    /// Builds the field's occupancy grid (`config`, `passes` jittered evaluations per cell), so
    /// segments skip empty space.
    pub fn build_occupancy(
        &mut self,
        ctx: &Context,
        config: OccupancyConfig,
        passes: u32,
    ) -> Result<Option<OccupancyBuilt>> {
        let prims = Prims::new(ctx)?;
        let t = Instant::now();
        let stats = self
            .base
            .nerf
            .build_occupancy(ctx, &prims, Some(config), passes)?;
        Ok(stats.map(|stats| OccupancyBuilt {
            res: config.res,
            stats,
            seconds: t.elapsed().as_secs_f64(),
        }))
    }

    /// The training cameras (at most [`MAX_TRAIN_CAMERAS`]).
    pub fn train_cameras(&self) -> Result<Vec<Camera>> {
        let train = self.base.train_cameras();
        if train.len() > MAX_TRAIN_CAMERAS {
            return Err(ExtrapolateError::usage(format!(
                "the run has {} training views; visibility supports at most {MAX_TRAIN_CAMERAS}",
                train.len()
            )));
        }
        Ok(train)
    }

    /// The kernel configuration of `q` at `rank`.
    pub fn config(&self, q: &QuerySettings, rank: u32) -> Result<VisibilityConfig> {
        checked_config(q, rank, self.base.ck.config.train.samples, "--")
    }

    /// Builds the transmittance volumes of `train`, `res` rays across and `depth` strata
    /// (replacing earlier ones); returns the seconds it took.
    pub fn build_volume(
        &mut self,
        ctx: &Context,
        train: &[Camera],
        res: u32,
        depth: u32,
    ) -> Result<f64> {
        if res == 0 || depth == 0 {
            return Err(ExtrapolateError::usage(
                "--volume-res and --volume-depth must be positive",
            ));
        }
        let t = Instant::now();
        let vol = self
            .vis
            .build_volume(ctx, &density(&self.base.nerf)?, train, res, depth)?;
        self.volume = Some(vol);
        Ok(t.elapsed().as_secs_f64())
    }

    /// The transmittance volumes, once built.
    pub fn volume(&self) -> Option<&TransmittanceVolume> {
        self.volume.as_ref()
    }

    /// The map of `cam` against the cameras of `mask` in `train`, through the volumes
    /// (`volume`, built first) or the segment march.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn map(
        &self,
        ctx: &Context,
        cam: &Camera,
        train: &[Camera],
        mask: u32,
        cfg: &VisibilityConfig,
        volume: bool,
        chunk: u32,
    ) -> Result<VisibilityMap> {
        let vol = if volume {
            let Some(v) = self.volume.as_ref() else {
                return Err(ExtrapolateError::usage(
                    "the transmittance volumes have not been built",
                ));
            };
            Some(v)
        } else {
            None
        };
        Ok(self.vis.map_with(
            ctx,
            &density(&self.base.nerf)?,
            RaySamples::of(&self.base.nerf),
            cam,
            train,
            mask,
            cfg,
            vol,
            chunk,
        )?)
    }
}

/// Writes `NAME_vis.png` (grey visibility), `NAME_vis.exr` (channels V: visibility,
/// A: opacity) and `NAME_mask.png` (white where visibility < threshold) into `out`.
pub fn write_map(out: &Path, name: &str, m: &VisibilityMap, threshold: f32) -> Result<()> {
    let grey: Vec<f32> = m.visibility.iter().flat_map(|&v| [v, v, v]).collect();
    write_png(
        &out.join(format!("{name}_vis.png")),
        m.width,
        m.height,
        &grey,
    )?;
    let mask: Vec<f32> = m
        .visibility
        .iter()
        .flat_map(|&v| {
            let x = if v < threshold { 1.0 } else { 0.0 };
            [x, x, x]
        })
        .collect();
    write_png(
        &out.join(format!("{name}_mask.png")),
        m.width,
        m.height,
        &mask,
    )?;
    write_exr_channels(
        &out.join(format!("{name}_vis.exr")),
        m.width,
        m.height,
        &[("V", &m.visibility), ("A", &m.opacity)],
    )?;
    Ok(())
}

/// A map's summary row of `visibility.json`.
pub fn map_summary(
    name: &str,
    kind: &str,
    m: &VisibilityMap,
    seconds: f64,
    threshold: f32,
) -> serde_json::Value {
    let px = (m.width as f64 * m.height as f64).max(1.0);
    let evals: f64 = m.evals.iter().map(|&e| e as f64).sum();
    serde_json::json!({
        "view": name,
        "kind": kind,
        "width": m.width,
        "height": m.height,
        "mean_visibility": m.mean(),
        "mean_opacity": m.mean_opacity(),
        "visible_fraction": m.visible_fraction(),
        "masked_fraction": m.masked_fraction(threshold),
        "seconds": seconds,
        "us_per_pixel": seconds * 1e6 / px,
        // Field evaluations of the segment marches, or volume lookups.
        "evals_per_pixel": evals / px,
    })
}

/// A view's depth, rendered and completed where the training views did not see it.
#[derive(Clone, Debug, PartialEq)]
pub struct CompletedDepth {
    /// The field's ray-space depth (NDC t for forward-facing scenes).
    pub rendered: Vec<f32>,
    /// The same with the unseen pixels filled.
    pub completed: Vec<f32>,
    /// The completed depth as view depth in the capture's units.
    pub view_depth: Vec<f32>,
    /// Mean |completed - rendered| over the filled pixels.
    pub mean_abs_change: f64,
}

impl CompletedDepth {
    /// Writes NAME_depth.exr and NAME_depth_completed.exr (ray-space depth, channel T, which
    /// `train --depth-dir` refuses) and NAME_view_depth.exr (channel Z, what it reads).
    pub fn write(&self, out: &Path, name: &str, cam: &Camera) -> Result<()> {
        write_ray_depth_exr(
            &out.join(format!("{name}_depth.exr")),
            cam.width,
            cam.height,
            &self.rendered,
        )?;
        write_ray_depth_exr(
            &out.join(format!("{name}_depth_completed.exr")),
            cam.width,
            cam.height,
            &self.completed,
        )?;
        write_depth_exr(
            &out.join(format!("{name}_view_depth.exr")),
            cam.width,
            cam.height,
            &self.view_depth,
        )?;
        Ok(())
    }
}

/// Renders `cam` from `base` (`samples` per ray, `chunk` rays per pass), keeps the depth where
/// `m` says the training views saw it (visibility >= `threshold`) and fills the rest with
/// `iterations` Jacobi sweeps of the colour-guided depth completion on the device, guided by
/// the rendered colour (a neighbour's weight falls to 1/e at colour difference `sigma`).
#[allow(clippy::too_many_arguments)] // each is a distinct operand
pub fn complete_depth(
    ctx: &Context,
    base: &BaseField,
    cam: &Camera,
    m: &VisibilityMap,
    threshold: f32,
    sigma: f32,
    iterations: u32,
    samples: u32,
    chunk: u32,
) -> Result<CompletedDepth> {
    if (m.width, m.height) != (cam.width, cam.height) {
        return Err(ExtrapolateError::usage(format!(
            "depth completion: the map is {}x{}, the camera {}x{}",
            m.width, m.height, cam.width, cam.height
        )));
    }
    let (rgb, depth, _) = base.nerf.render(ctx, cam, chunk, samples)?;
    let known: Vec<u32> = m
        .visibility
        .iter()
        .map(|&v| u32::from(v >= threshold))
        .collect();
    let guide: Vec<[f32; 4]> = rgb
        .chunks_exact(3)
        .map(|c| [c[0], c[1], c[2], 0.0])
        .collect();
    let completed = DepthCompletion::new(ctx)?.run(
        ctx, cam.width, cam.height, &depth, &known, &guide, sigma, iterations,
    )?;
    let scale = base
        .loaded
        .scene
        .world_from_source
        .x_axis
        .truncate()
        .length();
    let view_depth = ray_depth_to_view_depth(cam, &completed, base.ndc(), scale);
    let filled = known.iter().filter(|&&k| k == 0).count().max(1);
    let mean_abs_change = depth
        .iter()
        .zip(&completed)
        .zip(&known)
        .filter(|(_, &k)| k == 0)
        .map(|((a, b), _)| (a - b).abs() as f64)
        .sum::<f64>()
        / filled as f64;
    Ok(CompletedDepth {
        rendered: depth,
        completed,
        view_depth,
        mean_abs_change,
    })
}

/// The maps file of the visibility stage.
pub const MAPS_FILE: &str = "maps.safetensors";

/// Saves maps into a safetensors file (`NAME.visibility`, `NAME.opacity`, `NAME.depth`).
pub(crate) fn save_maps(path: &Path, maps: &[(String, VisibilityMap)]) -> Result<()> {
    let mut st = SafeTensors::default();
    for (name, m) in maps {
        let shape = vec![m.height as usize, m.width as usize];
        for (what, v) in [
            ("visibility", &m.visibility),
            ("opacity", &m.opacity),
            ("depth", &m.depth),
        ] {
            st.tensors.insert(
                format!("{name}.{what}"),
                Tensor {
                    shape: shape.clone(),
                    data: v.clone(),
                },
            );
        }
    }
    st.write(path)?;
    Ok(())
}

/// Reads map `name` from a `save_maps` file.
pub fn load_map(st: &SafeTensors, path: &Path, name: &str) -> Result<VisibilityMap> {
    let get = |what: &str| -> Result<(Vec<usize>, Vec<f32>)> {
        let t = st
            .tensors
            .get(&format!("{name}.{what}"))
            .ok_or_else(|| ExtrapolateError::malformed(path, format!("no map {name}.{what}")))?;
        Ok((t.shape.clone(), t.data.clone()))
    };
    let (shape, visibility) = get("visibility")?;
    let (_, opacity) = get("opacity")?;
    let (_, depth) = get("depth")?;
    if shape.len() != 2 || opacity.len() != visibility.len() || depth.len() != visibility.len() {
        return Err(ExtrapolateError::malformed(
            path,
            format!("map {name} is malformed"),
        ));
    }
    Ok(VisibilityMap {
        width: shape[1] as u32,
        height: shape[0] as u32,
        evals: vec![0.0; visibility.len()],
        visibility,
        opacity,
        depth,
    })
}

/// A mask against the truly unseen pixels.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct MaskScore {
    /// Intersection over union of the masked and the truly unseen pixels (1 when both are
    /// empty).
    pub iou: f64,
    /// Share of pixels on which mask and truth agree.
    pub accuracy: f64,
    /// Masked share, truly unseen share.
    pub masked: f64,
    pub unseen: f64,
}

impl MaskScore {
    /// Scores `mask` (>= 0.5: to inpaint) against `unseen`.
    pub fn new(mask: &[f32], unseen: &[bool]) -> MaskScore {
        let (mut inter, mut union, mut agree, mut m, mut u) =
            (0usize, 0usize, 0usize, 0usize, 0usize);
        for (&x, &t) in mask.iter().zip(unseen) {
            let x = x >= 0.5;
            inter += usize::from(x && t);
            union += usize::from(x || t);
            agree += usize::from(x == t);
            m += usize::from(x);
            u += usize::from(t);
        }
        let n = mask.len().max(1) as f64;
        MaskScore {
            iou: if union == 0 {
                1.0
            } else {
                inter as f64 / union as f64
            },
            accuracy: agree as f64 / n,
            masked: m as f64 / n,
            unseen: u as f64 / n,
        }
    }

    /// The mean of several views' scores.
    pub fn mean(v: &[MaskScore]) -> MaskScore {
        let n = v.len().max(1) as f64;
        let f = |g: fn(&MaskScore) -> f64| v.iter().map(g).sum::<f64>() / n;
        MaskScore {
            iou: f(|s| s.iou),
            accuracy: f(|s| s.accuracy),
            masked: f(|s| s.masked),
            unseen: f(|s| s.unseen),
        }
    }
}

/// The inpainting masks of the virtual views `virt` (`virtual_NNN` in the visibility stage's
/// maps file under `vis_dir`), each checked to be its view's size.
pub fn virtual_masks(vis_dir: &Path, virt: &[Camera], vis: &VisSettings) -> Result<Vec<Vec<f32>>> {
    let maps_path = vis_dir.join(MAPS_FILE);
    let st = SafeTensors::read(&maps_path)?;
    (0..virt.len())
        .map(|i| {
            let m = load_map(&st, &maps_path, &format!("virtual_{i:03}"))?;
            if (m.width, m.height) != (virt[i].width, virt[i].height) {
                return Err(ExtrapolateError::malformed(
                    &maps_path,
                    format!("virtual view {i}'s map has another size"),
                ));
            }
            Ok(vis.mask(&m))
        })
        .collect()
}
