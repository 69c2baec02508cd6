//! Multi-view transmittance visibility (`render/visibility.wgsl`): for each pixel of a view,
//! what the training cameras saw of the surface it shows. Each sample of the pixel's ray is
//! marched toward every selected training camera; its visibility is the `rank`-th largest of
//! those transmittances (0 outside a camera's frustum or behind it), and the pixel's
//! visibility is that value volume-rendered with the ray's weights. ExtraNeRF inpaints where it
//! is low; rank 2 means a point counts as seen only when two views saw it.
//!
//! The density is the trained field (optionally through its occupancy grid) or a set of
//! analytic shapes ([`AnalyticField`]), which the tests use for scenes with a known answer.

use extranerf_gpu::kernels::render::pixels as kp;
use extranerf_gpu::kernels::render::visibility as k;
use extranerf_gpu::{count_u32, Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};

use crate::data::Camera;
use crate::field::mlp::BLOCK_FLOATS;
use crate::model::Field;
use crate::render::march::{check_sampling_range, UNIFORM_LUT};
use crate::render::occupancy::Occupancy;
use crate::render::rays::{gpu_camera, GpuCamera};
use crate::renderer::Nerf;

/// Bits of the visibility kernel's `flags` (`VIS_*` in `kernels/wgsl/render/visibility.wgsl`):
/// the field lives in NDC, the density is analytic shapes, transmittances come from volumes,
/// the relative measure, the samples of each pixel's ray are given.
const VIS_NDC: u32 = 1;
const VIS_ANALYTIC: u32 = 2;
const VIS_VOLUME: u32 = 4;
const VIS_RELATIVE: u32 = 8;
const VIS_GIVEN: u32 = 16;

/// 4-byte words of one `GpuCamera`.
const CAMERA_WORDS: u64 = (std::mem::size_of::<GpuCamera>() / 4) as u64;

/// The largest rank the kernel supports.
pub const MAX_RANK: u32 = 8;
/// The most training cameras one pass considers (a 32-bit mask selects them).
pub const MAX_TRAIN_CAMERAS: usize = 32;

/// What a training camera's transmittance to a sample is measured against.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum VisibilityMeasure {
    /// The transmittance itself (the paper): a sample inside a surface the field renders as a
    /// semi-transparent shell is half-hidden from every camera, the pixel's own included.
    Absolute,
    /// The transmittance over the pixel ray's own transmittance in front of the sample, at
    /// most 1: whether the camera sees the sample at least as well as the pixel's camera does.
    /// The same on a sharp surface; on a shell, seen surfaces count as seen.
    #[default]
    Relative,
}

/// Where the samples of a view's rays come from.
#[derive(Clone, Copy, Debug, Default)]
pub enum RaySamples<'a> {
    /// Uniform strata of the sampling range (stratum midpoints, as the fused march places them
    /// without the proposal sampler).
    #[default]
    Strata,
    /// The proposal sampler of this field, centred, as its renders take them
    /// ([`crate::renderer::Nerf::render`]); [`VisibilityConfig::samples`] main samples per ray.
    Proposal(&'a Nerf),
}

impl<'a> RaySamples<'a> {
    /// The samples `nerf` renders with: its proposal sampler's when it has one, else strata.
    pub fn of(nerf: &'a Nerf) -> RaySamples<'a> {
        if nerf.has_proposal() {
            RaySamples::Proposal(nerf)
        } else {
            RaySamples::Strata
        }
    }
}

/// How visibility is computed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VisibilityConfig {
    /// Samples per camera ray (stratum midpoints, as the fused march places them, or the
    /// samples given per ray: [`RaySamples`]).
    pub samples: u32,
    /// Samples per segment from a ray sample toward a training camera.
    pub vis_samples: u32,
    /// Which largest transmittance counts (2: seen by at least two cameras; 1..=8).
    pub rank: u32,
    /// Samples whose weight is at most this are not marched toward the cameras; each drops at
    /// most this much visibility (0: exact).
    pub min_weight: f32,
    /// Segments stop once their transmittance (relative, for that measure) falls below this,
    /// and count as 0 (0: exact).
    pub min_transmittance: f32,
    /// Absolute or relative transmittance.
    pub measure: VisibilityMeasure,
}

impl Default for VisibilityConfig {
    fn default() -> Self {
        VisibilityConfig {
            samples: 32,
            vis_samples: 32,
            rank: 2,
            min_weight: 0.0,
            min_transmittance: 0.0,
            measure: VisibilityMeasure::Relative,
        }
    }
}

impl VisibilityConfig {
    fn validate(&self) -> Result<()> {
        if self.samples == 0 || self.vis_samples == 0 {
            return Err(GpuError::Usage(format!(
                "visibility needs at least one sample per ray and per segment ({} and {} given)",
                self.samples, self.vis_samples
            )));
        }
        if !(1..=MAX_RANK).contains(&self.rank) {
            return Err(GpuError::Usage(format!(
                "visibility rank {} must be in 1..={MAX_RANK}",
                self.rank
            )));
        }
        let ok = |v: f32| (0.0..1.0).contains(&v);
        if !ok(self.min_weight) || !ok(self.min_transmittance) {
            return Err(GpuError::Usage(format!(
                "visibility cuts min_weight {} and min_transmittance {} must be in [0, 1)",
                self.min_weight, self.min_transmittance
            )));
        }
        Ok(())
    }
}

/// One analytic shape of constant density `sigma` with a linear edge `soft` wide (0: hard).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// A ball.
    Sphere {
        /// Centre.
        centre: [f32; 3],
        /// Radius.
        radius: f32,
        /// Density inside.
        sigma: f32,
        /// Width of the edge ramp.
        soft: f32,
    },
    /// An axis-aligned box.
    Box {
        /// Lowest corner.
        min: [f32; 3],
        /// Highest corner.
        max: [f32; 3],
        /// Density inside.
        sigma: f32,
        /// Width of the edge ramp.
        soft: f32,
    },
}

impl Shape {
    /// Density at x (the kernel's definition, in f64): sigma times the edge fraction, which is
    /// clamp(d / soft + 1/2, 0, 1) per bounding surface for signed inside distance d.
    pub fn density(&self, x: [f64; 3]) -> f64 {
        let edge = |d: f64, soft: f64| {
            if soft <= 0.0 {
                if d >= 0.0 {
                    1.0
                } else {
                    0.0
                }
            } else {
                (d / soft + 0.5).clamp(0.0, 1.0)
            }
        };
        match *self {
            Shape::Sphere {
                centre,
                radius,
                sigma,
                soft,
            } => {
                let r = (0..3)
                    .map(|a| (x[a] - centre[a] as f64).powi(2))
                    .sum::<f64>()
                    .sqrt();
                sigma as f64 * edge(radius as f64 - r, soft as f64)
            }
            Shape::Box {
                min,
                max,
                sigma,
                soft,
            } => {
                let mut f = 1.0;
                for a in 0..3 {
                    f *= edge(x[a] - min[a] as f64, soft as f64);
                    f *= edge(max[a] as f64 - x[a], soft as f64);
                }
                sigma as f64 * f
            }
        }
    }

    fn words(&self) -> [[f32; 4]; 3] {
        match *self {
            Shape::Sphere {
                centre,
                radius,
                sigma,
                soft,
            } => [
                [0.0, sigma, soft, 0.0],
                [centre[0], centre[1], centre[2], 0.0],
                [radius, 0.0, 0.0, 0.0],
            ],
            Shape::Box {
                min,
                max,
                sigma,
                soft,
            } => [
                [1.0, sigma, soft, 0.0],
                [min[0], min[1], min[2], 0.0],
                [max[0], max[1], max[2], 0.0],
            ],
        }
    }
}

/// Analytic density on the device: the sum of its shapes' densities, in world space (t linear
/// in disparity between near and far) or in NDC (t linear, near plane 1).
#[derive(Debug)]
pub struct AnalyticField {
    shapes: Vec<Shape>,
    buffer: Buffer<[f32; 4]>,
    /// The field lives in NDC.
    pub ndc: bool,
    /// Sampling range along camera rays (t, as the field's space measures it).
    pub near: f32,
    /// See `near`.
    pub far: f32,
}

impl AnalyticField {
    /// Uploads the shapes.
    pub fn new(
        ctx: &Context,
        shapes: &[Shape],
        ndc: bool,
        near: f32,
        far: f32,
    ) -> Result<AnalyticField> {
        let words: Vec<[f32; 4]> = shapes.iter().flat_map(|s| s.words()).collect();
        let words = if words.is_empty() {
            vec![[0.0; 4]]
        } else {
            words
        };
        Ok(AnalyticField {
            shapes: shapes.to_vec(),
            buffer: Buffer::from_slice(ctx, "analytic shapes", &words)?,
            ndc,
            near,
            far,
        })
    }

    /// The shapes.
    pub fn shapes(&self) -> &[Shape] {
        &self.shapes
    }

    /// Density at x in f64.
    pub fn density(&self, x: [f64; 3]) -> f64 {
        self.shapes.iter().map(|s| s.density(x)).sum()
    }
}

/// Where the visibility kernel takes densities from.
#[derive(Clone, Copy, Debug)]
pub enum Density<'a> {
    /// The trained field, its parameter sections and optionally its occupancy grid.
    Field {
        /// The field.
        field: &'a Field,
        /// Its parameter sections (table, density MLP, colour MLP).
        params: [Binding<'a>; 3],
        /// Skip the cells this grid marks empty.
        occupancy: Option<&'a Occupancy>,
    },
    /// Analytic shapes.
    Analytic(&'a AnalyticField),
}

/// A view's visibility, per pixel in row-major order.
#[derive(Clone, Debug, PartialEq)]
pub struct VisibilityMap {
    /// Width in pixels.
    pub width: u32,
    /// Height in pixels.
    pub height: u32,
    /// Volume-rendered visibility in [0, opacity].
    pub visibility: Vec<f32>,
    /// Opacity of the ray (sum of weights).
    pub opacity: Vec<f32>,
    /// Expected depth (the field space's t).
    pub depth: Vec<f32>,
    /// Density evaluations spent marching toward the cameras.
    pub evals: Vec<f32>,
}

impl VisibilityMap {
    /// Mean visibility over the pixels.
    pub fn mean(&self) -> f64 {
        mean(&self.visibility)
    }

    /// Mean opacity over the pixels.
    pub fn mean_opacity(&self) -> f64 {
        mean(&self.opacity)
    }

    /// Share of what the view renders that the training views saw: sum of visibility over sum
    /// of opacity (0 for an empty view).
    pub fn visible_fraction(&self) -> f64 {
        let o: f64 = self.opacity.iter().map(|&x| x as f64).sum();
        if o > 0.0 {
            self.visibility.iter().map(|&x| x as f64).sum::<f64>() / o
        } else {
            0.0
        }
    }

    /// Fraction of pixels whose visibility is below `threshold` (the inpainting mask).
    pub fn masked_fraction(&self, threshold: f32) -> f64 {
        let n = self.visibility.len().max(1);
        self.visibility.iter().filter(|&&v| v < threshold).count() as f64 / n as f64
    }
}

fn mean(v: &[f32]) -> f64 {
    v.iter().map(|&x| x as f64).sum::<f64>() / v.len().max(1) as f64
}

/// Per-camera transmittance volumes (deep shadow maps): for a `w` x `h` grid of each training
/// camera's rays, T at the `d + 1` boundaries of `d` strata of its sampling range. Visibility
/// then looks transmittances up instead of marching toward the cameras.
#[derive(Debug)]
pub struct TransmittanceVolume {
    buffer: Buffer<f32>,
    cameras: u32,
    size: [u32; 3],
}

impl TransmittanceVolume {
    /// Room for `cameras` volumes of `w` x `h` rays and `d` strata.
    pub fn new(ctx: &Context, cameras: u32, w: u32, h: u32, d: u32) -> Result<TransmittanceVolume> {
        if cameras == 0 || w == 0 || h == 0 || d == 0 {
            return Err(GpuError::Usage(format!(
                "a transmittance volume needs positive sizes, not {cameras} cameras of {w}x{h}x{d}"
            )));
        }
        let n = cameras as u64 * w as u64 * h as u64 * (d as u64 + 1);
        count_u32(n, "transmittance volume entries")?;
        Ok(TransmittanceVolume {
            buffer: Buffer::new(ctx, "transmittance volumes", n as usize)?,
            cameras,
            size: [w, h, d],
        })
    }

    /// The volumes (camera-major, then row, column, boundary).
    pub fn buffer(&self) -> &Buffer<f32> {
        &self.buffer
    }

    /// Rays across, rays down, strata.
    pub fn size(&self) -> [u32; 3] {
        self.size
    }

    /// Bytes on the device.
    pub fn bytes(&self) -> u64 {
        self.buffer.len() as u64 * 4
    }
}

/// The visibility kernel.
#[derive(Debug)]
pub struct Visibility {
    kernel: Kernel,
    volume: Kernel,
    no_volume: Buffer<f32>,
    pixel_range: Kernel,
    no_bits: Buffer<u32>,
    no_shapes: Buffer<[f32; 4]>,
    /// Bound in place of the given samples when the kernel places strata.
    no_given: Buffer<[f32; 2]>,
    mlp_block: Buffer<f32>,
}

impl Visibility {
    /// Builds the kernels.
    pub fn new(ctx: &Context) -> Result<Visibility> {
        Ok(Visibility {
            kernel: Kernel::new(ctx, &k::visibility_map::DESC)?,
            volume: Kernel::new(ctx, &k::transmittance_volume::DESC)?,
            no_volume: Buffer::from_slice(ctx, "no transmittance volume", &[0.0f32])?,
            pixel_range: Kernel::new(ctx, &kp::pixel_range::DESC)?,
            no_bits: Buffer::from_slice(ctx, "no occupancy bits", &[u32::MAX])?,
            no_shapes: Buffer::from_slice(ctx, "no shapes", &[[0.0f32; 4]])?,
            no_given: Buffer::new(ctx, "no given samples", 1)?,
            mlp_block: Buffer::new(ctx, "visibility MLP weights", BLOCK_FLOATS)?,
        })
    }

    /// The kernel parameters for `density` (everything but the counts), after recording the
    /// copy of the density MLP into the uniform block; and the density's bindings:
    /// (level_info, table, table_hi, density_shape, occ_bits, shapes).
    #[allow(clippy::type_complexity)] // six named bindings, destructured at the call
    fn density_setup<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        density: &Density<'a>,
    ) -> Result<(
        k::Params,
        (
            Binding<'a>,
            Binding<'a>,
            Binding<'a>,
            Binding<'a>,
            Binding<'a>,
            Binding<'a>,
        ),
    )> {
        let mut p = k::Params {
            n: 0,
            samples: 1,
            vis_samples: 1,
            spacing: 0,
            flags: 0,
            near: 0.0,
            far: 0.0,
            ndc_near: 1.0,
            contraction: 0,
            inv_radius: 1.0,
            occ_res: 0,
            occ_cascades: 0,
            levels: 0,
            features: 0,
            min_weight: 0.0,
            min_transmittance: 0.0,
            center: [0.0; 4],
            n_cameras: 0,
            n_train: 0,
            train_mask: 0,
            rank: 1,
            n_shapes: 0,
            vol_w: 1,
            vol_h: 1,
            vol_depth: 1,
            lut: UNIFORM_LUT,
        };
        let b = match *density {
            Density::Field {
                field,
                params,
                occupancy,
            } => {
                let c = field.config();
                let d = c.density_mlp();
                if !d.vec4_rows() || d.param_count() > BLOCK_FLOATS {
                    return Err(GpuError::Usage(format!(
                        "visibility needs a density MLP with input and hidden widths that are multiples of 4 and at most {BLOCK_FLOATS} weights ({:?}: {})",
                        d.dims,
                        d.param_count()
                    )));
                }
                let ndc = c.space == crate::model::Space::Ndc;
                check_sampling_range(ndc, c.near, c.far)?;
                let scene = field.scene();
                if ndc {
                    p.flags |= VIS_NDC;
                }
                p.spacing = u32::from(!ndc);
                p.near = c.near;
                p.far = c.far;
                p.contraction = scene.contraction as u32;
                p.inv_radius = 1.0 / scene.radius;
                p.center = [scene.center[0], scene.center[1], scene.center[2], 0.0];
                p.levels = c.levels;
                p.features = c.features;
                rec.copy(
                    params[1],
                    0,
                    self.mlp_block.binding(),
                    0,
                    d.param_count() as u64 * 4,
                )?;
                let bits = match occupancy {
                    Some(o) => {
                        p.occ_res = o.config().res;
                        p.occ_cascades = o.config().cascades;
                        o.bits().binding()
                    }
                    None => self.no_bits.binding(),
                };
                let (table, table_hi) = field.grid().parts(params[0])?;
                (
                    field.grid().levels().binding(),
                    table,
                    table_hi,
                    field.density().shape().binding(),
                    bits,
                    self.no_shapes.binding(),
                )
            }
            Density::Analytic(a) => {
                check_sampling_range(a.ndc, a.near, a.far)?;
                p.flags |= VIS_ANALYTIC;
                p.n_shapes = a.shapes.len() as u32;
                if a.ndc {
                    p.flags |= VIS_NDC;
                }
                p.spacing = u32::from(!a.ndc);
                p.near = a.near;
                p.far = a.far;
                // The field-only bindings are bound to small placeholders the kernel does not
                // read for this source.
                (
                    self.no_bits.binding(),
                    self.no_shapes.binding(),
                    self.no_shapes.binding(),
                    self.no_bits.binding(),
                    self.no_bits.binding(),
                    a.buffer.binding(),
                )
            }
        };
        Ok((p, b))
    }

    /// Records the build of the transmittance volumes of the `n_train` cameras in `train`
    /// (see [`TransmittanceVolume`]).
    pub fn record_volume<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        density: &Density<'a>,
        train: Binding<'a>,
        n_train: u32,
        volume: &'a TransmittanceVolume,
    ) -> Result<()> {
        if n_train != volume.cameras {
            return Err(GpuError::Usage(format!(
                "a transmittance volume for {} cameras cannot hold {n_train}",
                volume.cameras
            )));
        }
        train.check_fits(n_train as u64 * CAMERA_WORDS, 4, "volume training cameras")?;
        let (mut p, (level_info, table, table_hi, density_shape, occ_bits, shapes)) =
            self.density_setup(rec, density)?;
        let [w, h, d] = volume.size;
        let rays = n_train as u64 * w as u64 * h as u64;
        p.n = count_u32(rays, "transmittance volume rays")?;
        p.n_train = n_train;
        p.vol_w = w;
        p.vol_h = h;
        p.vol_depth = d;
        let b = k::transmittance_volume::Bindings {
            train_cams: train,
            level_info,
            table,
            table_hi,
            density_shape,
            occ_bits,
            shapes,
            mlp: self.mlp_block.binding(),
            tvol: volume.buffer.binding(),
        };
        rec.dispatch(&self.volume, b.into_array(), &p, rays)
    }

    /// Records the visibility of `n` pixels given as (camera, pixel) pairs in `pixels` into
    /// `out[n]` = (visibility, opacity, depth, evaluations). `train` holds `n_train` training
    /// cameras, of which those whose bit is set in `mask` count. With `volume` (built by
    /// [`Visibility::record_volume`] for the same cameras) transmittances are looked up
    /// instead of marched. With `given`, `(t, dt)` of `cfg.samples` samples per pixel
    /// (`[n * samples, 2]`, sorted along each ray) take the place of the strata.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn record<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        density: &Density<'a>,
        cameras: Binding<'a>,
        n_cameras: u32,
        pixels: Binding<'a>,
        n: u64,
        train: Binding<'a>,
        n_train: u32,
        mask: u32,
        cfg: &VisibilityConfig,
        volume: Option<&'a TransmittanceVolume>,
        given: Option<Binding<'a>>,
        out: Binding<'a>,
    ) -> Result<()> {
        cfg.validate()?;
        if n_train as usize > MAX_TRAIN_CAMERAS {
            return Err(GpuError::Usage(format!(
                "{n_train} training cameras; visibility considers at most {MAX_TRAIN_CAMERAS} per pass"
            )));
        }
        pixels.check_fits(2 * n, 4, "visibility pixels")?;
        out.check_fits(4 * n, 4, "visibility output")?;
        cameras.check_fits(n_cameras as u64 * CAMERA_WORDS, 4, "visibility cameras")?;
        train.check_fits(
            n_train as u64 * CAMERA_WORDS,
            4,
            "visibility training cameras",
        )?;
        let (mut p, (level_info, table, table_hi, density_shape, occ_bits, shapes)) =
            self.density_setup(rec, density)?;
        p.n = count_u32(n, "visibility pixels")?;
        p.samples = cfg.samples;
        p.vis_samples = cfg.vis_samples;
        p.min_weight = cfg.min_weight;
        p.min_transmittance = cfg.min_transmittance;
        p.n_cameras = n_cameras;
        p.n_train = n_train;
        p.train_mask = mask;
        p.rank = cfg.rank;
        if cfg.measure == VisibilityMeasure::Relative {
            p.flags |= VIS_RELATIVE;
        }
        let given_t_dt = match given {
            Some(g) => {
                g.check_fits(2 * n * cfg.samples as u64, 4, "visibility given samples")?;
                p.flags |= VIS_GIVEN;
                g
            }
            None => self.no_given.binding(),
        };
        let tvol = match volume {
            Some(v) => {
                if v.cameras != n_train {
                    return Err(GpuError::Usage(format!(
                        "the transmittance volume holds {} cameras, {n_train} given",
                        v.cameras
                    )));
                }
                p.flags |= VIS_VOLUME;
                [p.vol_w, p.vol_h, p.vol_depth] = v.size;
                v.buffer.binding()
            }
            None => self.no_volume.binding(),
        };
        let b = k::visibility_map::Bindings {
            cameras,
            pixels,
            train_cams: train,
            level_info,
            table,
            table_hi,
            density_shape,
            occ_bits,
            shapes,
            out_vis: out,
            mlp: self.mlp_block.binding(),
            tvol,
            given_t_dt,
        };
        rec.dispatch(&self.kernel, b.into_array(), &p, n)
    }

    /// The visibility of a whole view against the training cameras `train` selected by `mask`,
    /// `chunk` pixels per submission, at uniform strata ([`Visibility::map_with`]).
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn map(
        &self,
        ctx: &Context,
        density: &Density<'_>,
        camera: &Camera,
        train: &[Camera],
        mask: u32,
        cfg: &VisibilityConfig,
        volume: Option<&TransmittanceVolume>,
        chunk: u32,
    ) -> Result<VisibilityMap> {
        self.map_with(
            ctx,
            density,
            RaySamples::Strata,
            camera,
            train,
            mask,
            cfg,
            volume,
            chunk,
        )
    }

    /// [`Visibility::map`] with the view's ray samples from `samples` (the proposal sampler's
    /// must be the field's of `density`).
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn map_with(
        &self,
        ctx: &Context,
        density: &Density<'_>,
        samples: RaySamples<'_>,
        camera: &Camera,
        train: &[Camera],
        mask: u32,
        cfg: &VisibilityConfig,
        volume: Option<&TransmittanceVolume>,
        chunk: u32,
    ) -> Result<VisibilityMap> {
        if chunk == 0 {
            return Err(GpuError::Usage(
                "the visibility chunk must be positive".into(),
            ));
        }
        if train.is_empty() || train.len() > MAX_TRAIN_CAMERAS {
            return Err(GpuError::Usage(format!(
                "visibility needs 1 to {MAX_TRAIN_CAMERAS} training cameras, {} given",
                train.len()
            )));
        }
        let cams = Buffer::from_slice(ctx, "visibility camera", &[gpu_camera(camera)])?;
        let train_gpu: Vec<GpuCamera> = train.iter().map(gpu_camera).collect();
        let train_buf = Buffer::from_slice(ctx, "visibility training cameras", &train_gpu)?;
        let total = camera.width as u64 * camera.height as u64;
        count_u32(total, "pixels")?;
        let n_chunk = (chunk as u64).min(total.max(1)) as usize;
        let given = match samples {
            RaySamples::Strata => None,
            RaySamples::Proposal(nerf) => {
                let same = matches!(density, Density::Field { field, .. } if std::ptr::eq(*field, nerf.field()));
                if !same {
                    return Err(GpuError::Usage(
                        "visibility with the proposal sampler's samples needs that field's density"
                            .into(),
                    ));
                }
                let g = nerf.given_samples(ctx, n_chunk as u32, cfg.samples)?;
                Some((nerf, g.ok_or_else(|| {
                    GpuError::Usage("visibility at the proposal sampler's samples: the field has no proposal sampler".into())
                })?))
            }
        };
        let pixels = Buffer::<[u32; 2]>::new(ctx, "visibility pixels", n_chunk)?;
        let out = Buffer::<[f32; 4]>::new(ctx, "visibility chunk", n_chunk)?;
        let all = Buffer::<[f32; 4]>::new(ctx, "visibility map", total.max(1) as usize)?;
        let mut first = 0u64;
        while first < total {
            let n = (total - first).min(n_chunk as u64);
            let mut rec = ctx.recorder("visibility")?;
            let pr = kp::Params {
                n: n as u32,
                camera: 0,
                first: first as u32,
                _pad: 0,
            };
            let px = match &given {
                Some((_, g)) => g.pixels(),
                None => pixels.binding(),
            };
            let b = kp::pixel_range::Bindings { pixels: px };
            rec.dispatch(&self.pixel_range, b.into_array(), &pr, n)?;
            let t_dt = match &given {
                Some((nerf, g)) => {
                    Some(nerf.record_given_samples(&mut rec, g, cams.binding(), 1, n)?)
                }
                None => None,
            };
            self.record(
                &mut rec,
                density,
                cams.binding(),
                1,
                px,
                n,
                train_buf.binding(),
                train.len() as u32,
                mask,
                cfg,
                volume,
                t_dt,
                out.binding(),
            )?;
            rec.copy(out.binding(), 0, all.binding(), first * 16, n * 16)?;
            ctx.run(rec)?;
            first += n;
        }
        let v = all.read()?;
        let v = &v[..total as usize];
        Ok(VisibilityMap {
            width: camera.width,
            height: camera.height,
            visibility: v.iter().map(|p| p[0]).collect(),
            opacity: v.iter().map(|p| p[1]).collect(),
            depth: v.iter().map(|p| p[2]).collect(),
            evals: v.iter().map(|p| p[3]).collect(),
        })
    }
}

impl Visibility {
    /// Builds the transmittance volumes of `train`: `w` rays across each camera's image (rows
    /// in proportion to its aspect) and `d` strata.
    pub fn build_volume(
        &self,
        ctx: &Context,
        density: &Density<'_>,
        train: &[Camera],
        w: u32,
        d: u32,
    ) -> Result<TransmittanceVolume> {
        let Some(first) = train.first() else {
            return Err(GpuError::Usage(
                "a transmittance volume needs training cameras".into(),
            ));
        };
        if train.len() > MAX_TRAIN_CAMERAS {
            return Err(GpuError::Usage(format!(
                "{} training cameras; at most {MAX_TRAIN_CAMERAS}",
                train.len()
            )));
        }
        let h =
            ((w as f64 * first.height as f64 / first.width.max(1) as f64).round() as u32).max(1);
        let vol = TransmittanceVolume::new(ctx, train.len() as u32, w, h, d)?;
        let train_gpu: Vec<GpuCamera> = train.iter().map(gpu_camera).collect();
        let buf = Buffer::from_slice(ctx, "volume training cameras", &train_gpu)?;
        let mut rec = ctx.recorder("transmittance volume")?;
        self.record_volume(&mut rec, density, buf.binding(), train.len() as u32, &vol)?;
        ctx.run(rec)?;
        Ok(vol)
    }
}

/// The mask selecting every camera of `n` except `except`.
pub fn mask_all_but(n: usize, except: Option<usize>) -> u32 {
    let all = if n >= 32 { u32::MAX } else { (1u32 << n) - 1 };
    match except {
        Some(i) if i < 32 => all & !(1u32 << i),
        _ => all,
    }
}
