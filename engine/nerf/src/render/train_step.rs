//! The fused training step (`render/train_step.wgsl`): one kernel per batch does everything
//! from a (camera, pixel) pair to the parameter gradients. Per ray it builds the ray, places
//! the jittered strata, evaluates the hash grid and both MLPs in registers, composites, takes
//! the RGB, depth and distortion losses, and then walks the samples again, recomputing the
//! forward pass to back-propagate through compositing, the heads, both MLPs and the hash grid
//! (atomics into the table's gradient). Only the MLP weight gradient, a reduction over every
//! sample of the batch, runs after it: the kernel writes each sample's layer inputs and
//! pre-activation gradients, and `Mlp::weight_gradient` sums them. Four samples of a ray go
//! through the MLPs together, sharing each weight load.
//!
//! It computes what the standalone chain (rays, samples, `Field::forward`/`backward`,
//! compositing and the loss kernels, see `trainer`) computes, without the per-sample buffers
//! between kernels. It needs the fused march's MLP shapes ([`color_base`]) and the f32 MLP
//! record. With an occupancy grid ([`SkipEmpty`]) it spreads each ray's strata over the
//! ray's occupied probe intervals, as the standalone sampler's `stratified_occupied` does
//! (`common/strata.wgsl`, shared by both): the same count per ray, none in empty
//! space.
//!
//! Where the field's MLPs take the cooperative-matrix path ([`crate::field::mlp::MlpPath`]),
//! the step runs `common/step_coop.wgsl` instead: the same step with a workgroup of 32 rays
//! walking their samples in step, each sample index a block of 32 points through the MLPs'
//! f16 tiles with f32 accumulation, after an f16 copy of both MLPs' weights.

use extranerf_gpu::kernels::render::train_step as k;
use extranerf_gpu::kernels::render::train_step_coop16 as kc16;
use extranerf_gpu::kernels::render::train_step_coop8 as kc8;
use extranerf_gpu::{count_u32, Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};

use crate::field::mlp::{MlpPath, BLOCK_FLOATS};
use crate::model::Field;
use crate::render::composite::Background;
use crate::render::loss::{LossConfig, RgbLoss, Targets};
use crate::render::march::{check_sampling_range, color_base, copy_mlp_block, UNIFORM_LUT};
use crate::render::sample::SkipEmpty;
use crate::render::FusedCoop;

/// Bits of the fused step's `flags` (`STEP_*` in `kernels/wgsl/common/step.wgsl`).
const STEP_JITTER: u32 = 1;
const STEP_RANDOM_BG: u32 = 2;
const STEP_NDC: u32 = 4;
const STEP_HUBER: u32 = 8;
const STEP_GRAD_SCALING: u32 = 16;
const STEP_TOUCHED: u32 = 32;
const STEP_GIVEN: u32 = 64;

/// A fused step's samples when something else placed them (the proposal sampler,
/// [`crate::render::proposal::Proposal::resample`]): `samples` per ray, ray r's at
/// `r * samples`, in place of the strata; the step writes their densities for the interlevel
/// loss.
#[derive(Clone, Copy, Debug)]
pub struct GivenSamples<'a> {
    /// `(t, dt)` per sample.
    pub t_dt: Binding<'a>,
    /// `(s, ds)` per sample (the distortion loss's position and width).
    pub s_ds: Binding<'a>,
    /// The step writes each sample's density here.
    pub sigma: Binding<'a>,
}

/// What one fused step writes per ray: `(rgb, opacity)`, expected depth, the photometric and
/// depth loss over the batch (their sum over rays is the batch mean), the squared colour error
/// (mean of the channels) and the distortion loss.
#[derive(Clone, Copy, Debug)]
pub struct StepOutputs<'a> {
    /// Rendered colour and opacity, `[n, 4]`.
    pub rgba: Binding<'a>,
    /// Expected depth, `[n]`.
    pub depth: Binding<'a>,
    /// Photometric + depth loss divided by n, `[n]`.
    pub loss: Binding<'a>,
    /// Squared colour error, `[n]`.
    pub mse: Binding<'a>,
    /// Distortion loss (its weight includes 1 / n), `[n]`.
    pub dist_loss: Binding<'a>,
    /// With the sparse Adam: the touched mask the step sets a bit in for every vec4 of the
    /// table it adds a gradient to (bit i of word w: vec4 32 w + i; at least
    /// [`crate::optim::touched_words`] words; an unsplit table only). None: no mask.
    pub touched: Option<Binding<'a>>,
}

/// The loss terms of a fused step.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StepLosses {
    /// Photometric and depth terms.
    pub loss: LossConfig,
    /// Distortion weight, already divided by the batch size (as the standalone kernel takes
    /// it).
    pub distortion: f32,
    /// Floaters No More: scale each sample's gradients by min(1, t^2).
    pub grad_scaling: bool,
}

// The cooperative-matrix step (`common/step_coop.wgsl`) shares the scalar step's parameter
// block (`common/step.wgsl`); its bindings are the scalar step's, in order, then `w16`.
const _: () = assert!(
    std::mem::size_of::<k::Params>() == std::mem::size_of::<kc8::Params>()
        && std::mem::size_of::<k::Params>() == std::mem::size_of::<kc16::Params>()
);

/// The fused training-step kernel and its scratch for one batch shape.
#[derive(Debug)]
pub struct FusedStep {
    kernel: Kernel,
    /// The cooperative-matrix step (`common/step_coop.wgsl`), when the field's MLPs take that
    /// path.
    coop: Option<FusedCoop>,
    mlp_block: Buffer<f32>,
    /// Bound as the occupancy bitfield without a grid (the kernel does not read it then).
    no_bits: Buffer<u32>,
    /// Bound as `touched` when the step marks nothing (never accessed then).
    no_touched: Buffer<u32>,
    saved_density: Buffer<f32>,
    saved_color: Buffer<f32>,
    rays: u32,
    samples: u32,
}

impl FusedStep {
    /// Why `field` cannot train with the fused step, or `Ok` when it can.
    pub fn supports(field: &Field) -> Result<()> {
        color_base(field)?;
        if field.density().is_f16() || field.color().is_f16() {
            return Err(GpuError::Usage(
                "the fused training step keeps the f32 MLP record; precision f16 trains with the standalone kernels".into(),
            ));
        }
        let cfg = field.config();
        check_sampling_range(cfg.space == crate::model::Space::Ndc, cfg.near, cfg.far)
    }

    /// The kernel and its scratch for batches of `rays` rays with `samples` samples each.
    pub fn new(ctx: &Context, field: &Field, rays: u32, samples: u32) -> Result<FusedStep> {
        Self::supports(field)?;
        if rays == 0 || samples == 0 {
            return Err(GpuError::Usage(
                "the fused step needs at least one ray and one sample per ray".into(),
            ));
        }
        let n = rays as usize * samples as usize;
        count_u32(n as u64, "samples per batch")?;
        let records = |words: usize, what: &str| -> Result<Buffer<f32>> {
            let floats = n.checked_mul(words).ok_or_else(|| {
                GpuError::Usage(format!("{what}: {n} samples x {words} floats overflow"))
            })?;
            Buffer::new(ctx, what, floats)
        };
        let coop = match field.density().path() {
            MlpPath::Scalar => None,
            MlpPath::Coop { tile } => Some(FusedCoop::new(
                ctx,
                field,
                tile,
                [&kc8::train_step_coop::DESC, &kc8::step_weights_f16::DESC],
                [&kc16::train_step_coop::DESC, &kc16::step_weights_f16::DESC],
            )?),
        };
        Ok(FusedStep {
            kernel: Kernel::new(ctx, &k::train_step::DESC)?,
            coop,
            mlp_block: Buffer::new(ctx, "fused step MLP weights", BLOCK_FLOATS)?,
            no_bits: Buffer::from_slice(ctx, "fused step: no occupancy bits", &[u32::MAX])?,
            no_touched: Buffer::from_slice(ctx, "fused step: no touched mask", &[0u32])?,
            saved_density: records(
                field.config().density_mlp().saved_stride(),
                "fused step density MLP records",
            )?,
            saved_color: records(
                field.config().color_mlp().saved_stride(),
                "fused step colour MLP records",
            )?,
            rays,
            samples,
        })
    }

    /// Rays per batch.
    pub fn rays(&self) -> u32 {
        self.rays
    }

    /// Records one step's forward and backward pass for the batch `pixels[rays]` (camera,
    /// pixel) with `targets`: writes `out` and adds the gradient of the batch loss (photometric,
    /// depth and distortion) with respect to the hash table to `d_params` (same sections as
    /// `params`; zero it first for a fresh gradient), and the MLPs' records. Follow with
    /// [`FusedStep::record_weight_gradients`] for the MLPs' share. `seed` jitters the strata as
    /// the standalone sampler does; `skip` spreads the strata over occupied space (its scene
    /// box must be the field's); a random `background` must use the same seed as the jitter.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn record<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        field: &'a Field,
        params: [Binding<'a>; 3],
        d_params: [Binding<'a>; 3],
        cameras: Binding<'a>,
        n_cameras: u32,
        pixels: Binding<'a>,
        targets: &Targets<'a>,
        losses: &StepLosses,
        seed: Option<u32>,
        skip: Option<&SkipEmpty<'a>>,
        background: Background,
        out: &StepOutputs<'a>,
        given: Option<&GivenSamples<'a>>,
    ) -> Result<()> {
        let n = self.rays as u64;
        if let Some(g) = given {
            let ns = n * self.samples as u64;
            g.t_dt.check_fits(2 * ns, 4, "fused step given t_dt")?;
            g.s_ds.check_fits(2 * ns, 4, "fused step given s_ds")?;
            g.sigma.check_fits(ns, 4, "fused step densities output")?;
            if self.coop.is_some() {
                return Err(GpuError::Usage(
                    "the fused step takes given samples (the proposal sampler) with scalar MLPs only; its cooperative-matrix twin places its own strata".into(),
                ));
            }
            if skip.is_some() {
                return Err(GpuError::Usage(
                    "the fused step takes given samples or spreads its strata over an occupancy grid, not both".into(),
                ));
            }
        }
        let cfg = field.config();
        pixels.check_fits(2 * n, 4, "fused step pixels")?;
        targets
            .rgb
            .check_fits(4 * n, 4, "fused step target colours")?;
        targets
            .depth
            .check_fits(2 * n, 4, "fused step target depths")?;
        out.rgba.check_fits(4 * n, 4, "fused step colour output")?;
        out.depth.check_fits(n, 4, "fused step depth output")?;
        out.loss.check_fits(n, 4, "fused step loss output")?;
        out.mse.check_fits(n, 4, "fused step MSE output")?;
        out.dist_loss
            .check_fits(n, 4, "fused step distortion output")?;
        let (loss_flag, huber) = match losses.loss.rgb {
            RgbLoss::L2 => (0, 0.0),
            RgbLoss::Huber(d) => (STEP_HUBER, d),
        };
        let ok = |v: f32| v.is_finite() && v >= 0.0;
        losses.loss.check()?;
        if !(ok(losses.distortion) && ok(huber)) {
            return Err(GpuError::Usage(format!(
                "fused step loss weights must be finite and >= 0: {losses:?}"
            )));
        }
        let ndc = cfg.space == crate::model::Space::Ndc;
        let scene = field.scene();
        let (probes, occ_res, occ_cascades, occ_bits) = match skip {
            None => (0, 0, 0, self.no_bits.binding()),
            Some(skip) => {
                let probes = skip.checked_probes()?;
                if skip.scene != *scene {
                    return Err(GpuError::Usage(format!(
                        "the fused step maps samples to the occupancy grid with the field's scene box {scene:?}, not {:?}",
                        skip.scene
                    )));
                }
                let g = skip.grid.config();
                (probes, g.res, g.cascades, skip.grid.bits().binding())
            }
        };
        let base = copy_mlp_block(rec, field, &params, &self.mlp_block)?;
        let (background, random_bg, bg_seed) = background.parts();
        // One seed jitters the strata and draws random backgrounds.
        if let (Some(j), 1) = (seed, random_bg) {
            if j != bg_seed {
                return Err(GpuError::Usage(format!(
                    "the fused step draws its strata and random backgrounds from one seed: {j} and {bg_seed} given"
                )));
            }
        }
        let touched = match out.touched {
            None => None,
            Some(t) => {
                if field.grid().split().is_some() {
                    return Err(GpuError::Usage(
                        "the touched mask (sparse Adam) covers tables in one storage binding; this table is split in two".into(),
                    ));
                }
                t.check_fits(
                    crate::optim::touched_words(cfg.grid().param_count()),
                    4,
                    "fused step touched mask",
                )?;
                Some(t)
            }
        };
        let bit = |on: bool, b: u32| if on { b } else { 0 };
        let p = k::Params {
            n: self.rays,
            samples: self.samples,
            l1_core: losses.loss.l1_core,
            near: cfg.near,
            far: cfg.far,
            ndc_near: 1.0,
            contraction: scene.contraction as u32,
            inv_radius: 1.0 / scene.radius,
            levels: cfg.levels,
            features: cfg.features,
            seed: seed.unwrap_or(bg_seed),
            flags: bit(seed.is_some(), STEP_JITTER)
                | bit(random_bg != 0, STEP_RANDOM_BG)
                | bit(ndc, STEP_NDC)
                | loss_flag
                | bit(losses.grad_scaling, STEP_GRAD_SCALING)
                | bit(touched.is_some(), STEP_TOUCHED)
                | bit(given.is_some(), STEP_GIVEN),
            n_cameras,
            color_base: base,
            dist_lambda: losses.distortion,
            density_stride: cfg.density_mlp().saved_stride() as u32,
            center: [scene.center[0], scene.center[1], scene.center[2], huber],
            background: [
                background[0],
                background[1],
                background[2],
                losses.loss.depth_lambda,
            ],
            color_stride: cfg.color_mlp().saved_stride() as u32,
            probes,
            occ_res,
            occ_cascades,
            lut: UNIFORM_LUT,
        };
        let (table, table_hi) = field.grid().parts(params[0])?;
        let (d_table, d_table_hi) = field.grid().parts(d_params[0])?;
        let b = k::train_step::Bindings {
            cameras,
            pixels,
            level_info: field.grid().levels().binding(),
            table,
            density_shape: field.density().shape().binding(),
            color_shape: field.color().shape().binding(),
            target_rgb: targets.rgb,
            target_depth: targets.depth,
            occ_bits,
            out_rgba: out.rgba,
            out_depth: out.depth,
            loss: out.loss,
            mlp: self.mlp_block.binding(),
            table_hi,
            mse: out.mse,
            dist_loss: out.dist_loss,
            d_table,
            d_table_hi,
            saved_density: self.saved_density.binding(),
            saved_color: self.saved_color.binding(),
            touched: touched.unwrap_or(self.no_touched.binding()),
            // Bound to stubs without given samples (never accessed then).
            given_t_dt: given.map_or(self.no_bits.binding(), |g| g.t_dt),
            given_s_ds: given.map_or(self.no_bits.binding(), |g| g.s_ds),
            given_sigma: given.map_or(self.no_touched.binding(), |g| g.sigma),
        };
        let Some(coop) = &self.coop else {
            return rec.dispatch(&self.kernel, b.into_array(), &p, n);
        };
        let shapes = [b.density_shape, b.color_shape];
        let mlp = b.mlp;
        // The cooperative-matrix twin binds the scalar step's first 21 (not the given samples).
        let all = b.into_array();
        let mut first = [all[0]; 21];
        first.copy_from_slice(&all[..21]);
        coop.record::<_, 21, 22>(rec, field, shapes, mlp, first, &p, n)
    }

    /// The MLP path this step takes.
    pub fn mlp_path(&self) -> MlpPath {
        FusedCoop::path(self.coop.as_ref())
    }

    /// Records the MLP weight-gradient pass over the records of the last [`FusedStep::record`],
    /// adding to `d_params`' MLP sections.
    pub fn record_weight_gradients<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        field: &'a Field,
        d_params: [Binding<'a>; 3],
    ) -> Result<()> {
        let ns = self.rays as u64 * self.samples as u64;
        field
            .density()
            .weight_gradient(rec, self.saved_density.binding(), d_params[1], ns)?;
        field
            .color()
            .weight_gradient(rec, self.saved_color.binding(), d_params[2], ns)
    }
}
