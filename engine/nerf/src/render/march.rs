//! The fused march (`render/march.wgsl`): one kernel per chunk of pixels. It makes the rays,
//! places the samples, skips empty occupancy cells, evaluates the hash grid and both MLPs in
//! registers, and composites with early termination. A second kernel is the fused occupancy
//! update, which evaluates the field's density at one jittered point per cell.
//!
//! This path is forward only (rendering, evaluation, occupancy). Training runs the fused step
//! of `render::train_step`, built on the same WGSL functions, or the standalone chain
//! (`model::Field` + `render::composite`).
//!
//! With [`Marcher::set_path`] on the cooperative-matrix path the render runs
//! `common/march_coop.wgsl`: 32 rays per workgroup, each round one occupied sample per ray
//! through the MLPs' f16 tiles with f32 accumulation (the occupancy update stays scalar).

use extranerf_gpu::kernels::render::march as k;
use extranerf_gpu::kernels::render::march_coop16 as kc16;
use extranerf_gpu::kernels::render::march_coop8 as kc8;
use extranerf_gpu::{count_u32, Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};

use crate::field::mlp::MlpPath;
use crate::model::Field;
use crate::render::occupancy::Occupancy;
use crate::render::FusedCoop;

/// The accuracy cuts of the fused march (0 and 0: exact).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct MarchCuts {
    /// Skip the colour MLP for samples whose weight is at most this much. Each skipped sample
    /// drops at most this much colour.
    pub min_weight: f32,
    /// Stop a ray once its transmittance falls below this. That drops at most this much colour
    /// and opacity.
    pub min_transmittance: f32,
}

impl MarchCuts {
    /// No cuts: every sample is evaluated in full.
    pub const EXACT: MarchCuts = MarchCuts {
        min_weight: 0.0,
        min_transmittance: 0.0,
    };

    /// Instant-NGP's early termination (transmittance 1e-4) and colour skipped below the same
    /// weight.
    pub const FAST: MarchCuts = MarchCuts {
        min_weight: 1e-4,
        min_transmittance: 1e-4,
    };

    fn validate(&self) -> Result<()> {
        let ok = |v: f32| (0.0..1.0).contains(&v);
        if !ok(self.min_weight) || !ok(self.min_transmittance) {
            return Err(GpuError::Usage(format!(
                "march cuts {self:?}: each must be in [0, 1)"
            )));
        }
        Ok(())
    }
}

use crate::field::mlp::BLOCK_FLOATS as MLP_BLOCK_FLOATS;

pub use crate::field::mlp::UNIFORM_LUT;

/// The fused kernels' sampling range: world space is linear in disparity, so it needs
/// 0 < near < far (NDC takes any range).
pub(crate) fn check_sampling_range(ndc: bool, near: f32, far: f32) -> Result<()> {
    if !(ndc || near > 0.0 && far > near) {
        return Err(GpuError::Usage(format!(
            "world-space sampling is linear in disparity and needs 0 < near < far, not {near} and {far}"
        )));
    }
    Ok(())
}

// The cooperative-matrix march (`common/march_coop.wgsl`) shares the scalar march's parameter
// block (`common/march_body.wgsl`); its render bindings are the scalar render's, in order,
// then `w16`.
const _: () = assert!(
    std::mem::size_of::<k::Params>() == std::mem::size_of::<kc8::Params>()
        && std::mem::size_of::<k::Params>() == std::mem::size_of::<kc16::Params>()
);

/// The fused march kernels.
#[derive(Debug)]
pub struct Marcher {
    render: Kernel,
    /// The cooperative-matrix render, when set ([`Marcher::set_path`]).
    coop: Option<FusedCoop>,
    occupancy: Kernel,
    /// Bound as the occupancy bitfield when no grid is used (the kernel does not read it).
    no_bits: Buffer<u32>,
    /// Bound in place of the given samples when the march places its own.
    no_given: Buffer<[f32; 2]>,
    /// Both MLPs' weights, copied from the parameter buffer before each pass.
    mlp_block: Buffer<f32>,
}

/// Where the colour MLP starts in the uniform block, after checking that both MLPs fit and
/// that every layer's input width and offset are multiples of 4 (vec4 rows).
pub fn color_base(field: &Field) -> Result<usize> {
    let cfg = field.config();
    let (d, c) = (cfg.density_mlp(), cfg.color_mlp());
    let base = d.param_count().div_ceil(4) * 4;
    if !d.vec4_rows() || !c.vec4_rows() || base + c.param_count() > MLP_BLOCK_FLOATS {
        return Err(GpuError::Usage(format!(
            "the fused march needs MLP input and hidden widths that are multiples of 4 and at most {MLP_BLOCK_FLOATS} weights in both MLPs together (density {:?}: {}, colour {:?}: {}); render with the standalone kernels instead",
            d.dims,
            d.param_count(),
            c.dims,
            c.param_count()
        )));
    }
    Ok(base)
}

/// Records the copy of both MLPs' weights (`params[1]`, `params[2]`) into a uniform block of
/// [`MLP_BLOCK_FLOATS`] floats: density at 0, colour after it. Returns the colour MLP's float
/// offset, after [`color_base`]'s checks. Shared by the fused march and the fused training step.
pub(crate) fn copy_mlp_block<'a>(
    rec: &mut Recorder<'a>,
    field: &Field,
    params: &[Binding<'a>; 3],
    block: &'a Buffer<f32>,
) -> Result<u32> {
    let base = color_base(field)?;
    let cfg = field.config();
    let dn = cfg.density_mlp().param_count() as u64 * 4;
    let cn = cfg.color_mlp().param_count() as u64 * 4;
    rec.copy(params[1], 0, block.binding(), 0, dn)?;
    rec.copy(params[2], 0, block.binding(), base as u64 * 4, cn)?;
    Ok(base as u32)
}

impl Marcher {
    /// Whether the fused march can render `field`: MLP widths in multiples of 4 that fit the
    /// uniform weight block, and a sampling range it takes (0 < near < far in world space).
    pub fn supports(field: &Field) -> Result<()> {
        color_base(field)?;
        let cfg = field.config();
        check_sampling_range(cfg.space == crate::model::Space::Ndc, cfg.near, cfg.far)
    }

    /// Builds the kernels.
    pub fn new(ctx: &Context) -> Result<Marcher> {
        Ok(Marcher {
            render: Kernel::new(ctx, &k::march_render::DESC)?,
            coop: None,
            occupancy: Kernel::new(ctx, &k::march_occupancy::DESC)?,
            no_bits: Buffer::from_slice(ctx, "no occupancy bits", &[u32::MAX])?,
            no_given: Buffer::new(ctx, "no given samples", 1)?,
            mlp_block: Buffer::new(ctx, "march MLP weights", MLP_BLOCK_FLOATS)?,
        })
    }

    /// Renders with the MLPs of `field` through `path`: the scalar kernel, or cooperative
    /// matrices of the path's tile (the device must offer it).
    pub fn set_path(&mut self, ctx: &Context, field: &Field, path: MlpPath) -> Result<()> {
        self.coop = match path {
            MlpPath::Scalar => None,
            MlpPath::Coop { tile } => Some(FusedCoop::new(
                ctx,
                field,
                tile,
                [&kc8::march_render_coop::DESC, &kc8::march_weights_f16::DESC],
                [
                    &kc16::march_render_coop::DESC,
                    &kc16::march_weights_f16::DESC,
                ],
            )?),
        };
        Ok(())
    }

    /// The MLP path renders take.
    pub fn mlp_path(&self) -> MlpPath {
        FusedCoop::path(self.coop.as_ref())
    }

    /// Records the copy of both MLPs into the uniform block; returns the colour MLP's offset.
    fn record_mlp_block<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        field: &'a Field,
        params: &[Binding<'a>; 3],
    ) -> Result<u32> {
        copy_mlp_block(rec, field, params, &self.mlp_block)
    }

    fn params(field: &Field, samples: u32, background: [f32; 3]) -> Result<k::Params> {
        let cfg = field.config();
        let scene = field.scene();
        if samples == 0 {
            return Err(GpuError::Usage("samples per ray must be positive".into()));
        }
        let ndc = cfg.space == crate::model::Space::Ndc;
        check_sampling_range(ndc, cfg.near, cfg.far)?;
        Ok(k::Params {
            n: 0,
            samples,
            spacing: u32::from(!ndc),
            ndc: u32::from(ndc),
            near: cfg.near,
            far: cfg.far,
            ndc_near: 1.0,
            contraction: scene.contraction as u32,
            inv_radius: 1.0 / scene.radius,
            occ_res: 0,
            occ_cascades: 0,
            levels: cfg.levels,
            features: cfg.features,
            color_base: 0,
            min_weight: 0.0,
            min_transmittance: 0.0,
            center: [scene.center[0], scene.center[1], scene.center[2], 0.0],
            background: [background[0], background[1], background[2], 0.0],
            first: 0,
            seed: 0,
            decay: 0.0,
            n_cameras: 0,
            lut: UNIFORM_LUT,
        })
    }

    /// Records the render of `n` rays given as (camera, pixel) pairs in `pixels` into
    /// `out_rgba[n]` (colour plus opacity) and `out_depth[n]` (expected depth in the ray space's
    /// units). `params` are the field's parameter sections. With `occupancy`, samples in cells
    /// its bitfield marks empty are skipped (samples outside the grid are evaluated). With
    /// `given`, `(t, dt)` per sample `[n * samples, 2]` sorted along each ray (the proposal
    /// sampler's, [`crate::render::proposal::Proposal::resample`]), the march takes those in
    /// place of the strata (scalar MLPs, no occupancy grid).
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn render<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        field: &'a Field,
        params: [Binding<'a>; 3],
        cameras: Binding<'a>,
        n_cameras: u32,
        pixels: Binding<'a>,
        n: u64,
        samples: u32,
        cuts: MarchCuts,
        occupancy: Option<&'a Occupancy>,
        background: [f32; 3],
        out_rgba: Binding<'a>,
        out_depth: Binding<'a>,
        given: Option<Binding<'a>>,
    ) -> Result<()> {
        cuts.validate()?;
        pixels.check_fits(2 * n, 4, "march pixels")?;
        out_rgba.check_fits(4 * n, 4, "march colour output")?;
        out_depth.check_fits(n, 4, "march depth output")?;
        let mut p = Self::params(field, samples, background)?;
        p.n = count_u32(n, "march rays")?;
        p.n_cameras = n_cameras;
        p.min_weight = cuts.min_weight;
        p.min_transmittance = cuts.min_transmittance;
        let occ_bits = match occupancy {
            Some(o) => {
                p.occ_res = o.config().res;
                p.occ_cascades = o.config().cascades;
                o.bits().binding()
            }
            None => self.no_bits.binding(),
        };
        let given_t_dt = match given {
            None => self.no_given.binding(),
            Some(g) => {
                if self.coop.is_some() || occupancy.is_some() {
                    return Err(GpuError::Usage(
                        "the fused march takes given samples with scalar MLPs and no occupancy grid".into(),
                    ));
                }
                g.check_fits(2 * n * samples as u64, 4, "march given samples")?;
                p.center[3] = 1.0;
                g
            }
        };
        p.color_base = self.record_mlp_block(rec, field, &params)?;
        let (table, table_hi) = field.grid().parts(params[0])?;
        let b = k::march_render::Bindings {
            given_t_dt,
            cameras,
            pixels,
            level_info: field.grid().levels().binding(),
            table,
            table_hi,
            density_shape: field.density().shape().binding(),
            color_shape: field.color().shape().binding(),
            occ_bits,
            out_rgba,
            out_depth,
            mlp: self.mlp_block.binding(),
        };
        let Some(coop) = &self.coop else {
            return rec.dispatch(&self.render, b.into_array(), &p, n);
        };
        let shapes = [b.density_shape, b.color_shape];
        let mlp = b.mlp;
        // The cooperative-matrix twin binds the scalar march's first 11 (not the given samples).
        let all = b.into_array();
        let mut first = [all[0]; 11];
        first.copy_from_slice(&all[..11]);
        coop.record::<_, 11, 12>(rec, field, shapes, mlp, first, &p, n)
    }

    /// Records the fused occupancy update of the window of `count` cells from `first`
    /// (wrapping): the field's density at one point per cell, jittered by `seed`, folded into
    /// the grid's EMA with `decay` (0 replaces, the grid's own decay averages).
    /// Follow with [`Occupancy::record_bits`].
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn update_occupancy<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        field: &'a Field,
        params: [Binding<'a>; 3],
        occupancy: &'a Occupancy,
        first: u64,
        count: u64,
        seed: u32,
        decay: f32,
    ) -> Result<()> {
        let cells = occupancy.config().cells();
        if count > cells {
            return Err(GpuError::Usage(format!(
                "a window of {count} cells exceeds the grid's {cells}"
            )));
        }
        if !(0.0..=1.0).contains(&decay) {
            return Err(GpuError::Usage(format!(
                "occupancy decay {decay} must be in [0, 1]"
            )));
        }
        let mut p = Self::params(field, 1, [0.0; 3])?;
        p.n = count_u32(count, "occupancy cells")?;
        p.occ_res = occupancy.config().res;
        p.occ_cascades = occupancy.config().cascades;
        p.first = (first % cells) as u32;
        p.seed = seed;
        p.decay = decay;
        p.color_base = self.record_mlp_block(rec, field, &params)?;
        let (table, table_hi) = field.grid().parts(params[0])?;
        let b = k::march_occupancy::Bindings {
            level_info: field.grid().levels().binding(),
            table,
            table_hi,
            density_shape: field.density().shape().binding(),
            occ_grid: occupancy.grid().binding(),
            mlp: self.mlp_block.binding(),
        };
        rec.dispatch(&self.occupancy, b.into_array(), &p, count)
    }
}
