//! The BaseNeRF field: hash-grid encoding -> density MLP (its first output is the density
//! logit, trunc-exp) -> (geometry features, SH4 of the view direction) -> colour MLP ->
//! sigmoid, with all parameters in one flat buffer `[table | density MLP | colour MLP]`.

use serde::{Deserialize, Serialize};

use extranerf_gpu::kernels::render::field_heads as kh;
use extranerf_gpu::{
    count_u32, Binding, Buffer, Context, GpuError, GpuTimer, Kernel, Recorder, Result,
};
use extranerf_prims::reference::Rng;

use crate::field::encodings::{Contraction, Encodings, SceneBox};
use crate::field::hash_grid::{HashGrid, HashGridConfig};
use crate::field::mlp::{Mlp, MlpConfig, MlpMode, MlpPath};

/// Floats between parameter sections (256 bytes, the largest storage-offset alignment Vulkan
/// allows), so every section binds as a slice of the flat buffer.
pub const SECTION_ALIGN: usize = 64;

/// The field's architecture (Instant-NGP's NeRF defaults) and where it lives.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ModelConfig {
    /// Hash-grid levels L.
    pub levels: u32,
    /// Features per level F.
    pub features: u32,
    /// log2 of the per-level table size T.
    pub log2_table: u32,
    /// Coarsest grid resolution.
    pub min_res: u32,
    /// Finest grid resolution.
    pub max_res: u32,
    /// Density MLP hidden width.
    pub density_width: u32,
    /// Density MLP hidden layers.
    pub density_layers: u32,
    /// Density MLP outputs (the density logit plus geometry features for the colour MLP).
    pub geo_dims: u32,
    /// Colour MLP hidden width.
    pub color_width: u32,
    /// Colour MLP hidden layers.
    pub color_layers: u32,
    /// Ray space: NDC (forward-facing captures) or world.
    pub space: Space,
    /// Sampling range along each ray (NDC: t from 0, the near plane, to at most 1, infinity;
    /// auto-config samples between the scene's depth bounds; world: depth along the viewing
    /// axis).
    pub near: f32,
    /// See `near`.
    pub far: f32,
    /// World points map to the grid as `(x - center) / radius`, then contract.
    pub center: [f32; 3],
    /// See `center`.
    pub radius: f32,
    /// none, l2 (mip-NeRF 360) or linf.
    pub contraction: Contraction,
    /// f32, or f16: hash-table reads in the forward pass from an f16 copy of the f32 master
    /// table, and the MLP backward's saved activations and pre-activation gradients in f16
    /// with a power-of-two scale per point and segment (training and the standalone kernels;
    /// the fused march reads the f32 table). Arithmetic stays f32.
    #[serde(default)]
    pub precision: Precision,
    /// How training places the samples along a ray: uniform strata, or a proposal field's
    /// histogram. Absent from configs written before the proposal sampler (uniform).
    #[serde(default, skip_serializing_if = "Sampler::is_uniform")]
    pub sampler: Sampler,
}

/// How the field's samples are placed along a training ray.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Sampler {
    /// The same count of jittered strata on every ray (over the occupied part of it with an
    /// occupancy grid).
    #[default]
    Uniform,
    /// Mip-NeRF 360's proposal sampler: a small density-only field (its own hash grid and
    /// MLP, after the main field in the flat parameter buffer) is evaluated at
    /// `samples` strata per ray, and the main field's samples are drawn from its weights'
    /// histogram; the interlevel loss trains it to bound the main field's weights.
    Proposal(ProposalConfig),
}

impl Sampler {
    /// True for the uniform sampler (configs written without a sampler).
    pub fn is_uniform(&self) -> bool {
        matches!(self, Sampler::Uniform)
    }

    /// The proposal field's settings, with the proposal sampler.
    pub fn proposal(&self) -> Option<&ProposalConfig> {
        match self {
            Sampler::Uniform => None,
            Sampler::Proposal(p) => Some(p),
        }
    }

    /// The name in reports and on the command line.
    pub fn name(&self) -> &'static str {
        match self {
            Sampler::Uniform => "uniform",
            Sampler::Proposal(_) => "proposal",
        }
    }
}

/// The proposal field and its sampling (nerfacto's first proposal network, smaller).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ProposalConfig {
    /// Strata per ray the proposal field is evaluated at (the histogram's bins).
    pub samples: u32,
    /// Hash-grid levels.
    pub levels: u32,
    /// Features per level.
    pub features: u32,
    /// log2 of the per-level table size.
    pub log2_table: u32,
    /// Coarsest grid resolution.
    pub min_res: u32,
    /// Finest grid resolution.
    pub max_res: u32,
    /// Hidden width of its one-layer density MLP.
    pub width: u32,
    /// Weight of the interlevel loss (per ray, averaged over the batch).
    pub interlevel: f32,
}

impl Default for ProposalConfig {
    fn default() -> Self {
        ProposalConfig {
            // 32 strata for 16 main samples: the measured best (`autoconfig::default_sampling`).
            samples: 32,
            levels: 6,
            features: 2,
            log2_table: 16,
            min_res: 16,
            max_res: 256,
            width: 16,
            interlevel: 1.0,
        }
    }
}

impl ProposalConfig {
    /// The proposal field's hash grid.
    pub fn grid(&self) -> HashGridConfig {
        HashGridConfig {
            levels: self.levels,
            features: self.features,
            log2_table: self.log2_table,
            min_res: self.min_res,
            max_res: self.max_res,
        }
    }

    /// Its density MLP: the encoding to `width` to the density logit.
    pub fn mlp(&self) -> MlpConfig {
        MlpConfig {
            dims: vec![self.levels * self.features, self.width, 1],
        }
    }

    /// Checks every setting.
    pub fn validate(&self) -> Result<()> {
        self.grid().validate()?;
        self.mlp().validate()?;
        if !(2..=crate::render::sample::MAX_PROBES).contains(&self.samples) {
            return Err(GpuError::Usage(format!(
                "{} proposal samples per ray: use 2 to {}",
                self.samples,
                crate::render::sample::MAX_PROBES
            )));
        }
        if !(self.interlevel.is_finite() && self.interlevel >= 0.0) {
            return Err(GpuError::Usage(format!(
                "interlevel loss weight {}: it must be finite and >= 0",
                self.interlevel
            )));
        }
        Ok(())
    }
}

/// The space rays are marched in.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Space {
    /// Normalised device coordinates of a forward-facing capture (the frustum out to infinity
    /// maps to a cube; t runs 0 to 1).
    #[default]
    Ndc,
    /// World space, optionally contracted.
    World,
}

impl Space {
    /// The name in configs and reports.
    pub fn name(self) -> &'static str {
        match self {
            Space::Ndc => "ndc",
            Space::World => "world",
        }
    }
}

/// Storage precision of the hash table's forward reads and the MLP backward's saved values.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
pub enum Precision {
    /// Everything in f32.
    #[default]
    F32,
    /// f16 hash-table reads and MLP backward records (f32 master weights and arithmetic).
    F16,
}

impl Precision {
    /// The name in configs and reports.
    pub fn name(self) -> &'static str {
        match self {
            Precision::F32 => "f32",
            Precision::F16 => "f16",
        }
    }
}

impl Default for ModelConfig {
    fn default() -> Self {
        let g = HashGridConfig::default();
        ModelConfig {
            levels: g.levels,
            features: g.features,
            log2_table: g.log2_table,
            min_res: g.min_res,
            max_res: g.max_res,
            density_width: 64,
            density_layers: 1,
            geo_dims: 16,
            color_width: 64,
            color_layers: 2,
            space: Space::Ndc,
            near: 0.0,
            far: 1.0,
            center: [0.0; 3],
            radius: 1.0,
            contraction: Contraction::None,
            precision: Precision::F32,
            sampler: Sampler::Uniform,
        }
    }
}

impl ModelConfig {
    /// The hash-grid settings.
    pub fn grid(&self) -> HashGridConfig {
        HashGridConfig {
            levels: self.levels,
            features: self.features,
            log2_table: self.log2_table,
            min_res: self.min_res,
            max_res: self.max_res,
        }
    }

    /// Density MLP widths.
    pub fn density_mlp(&self) -> MlpConfig {
        let mut dims = vec![self.levels * self.features];
        dims.extend(std::iter::repeat_n(
            self.density_width,
            self.density_layers as usize,
        ));
        dims.push(self.geo_dims);
        MlpConfig { dims }
    }

    /// Colour MLP widths.
    pub fn color_mlp(&self) -> MlpConfig {
        let mut dims = vec![self.geo_dims + 16];
        dims.extend(std::iter::repeat_n(
            self.color_width,
            self.color_layers as usize,
        ));
        dims.push(3);
        MlpConfig { dims }
    }

    /// The scene box of the contraction.
    pub fn scene_box(&self) -> SceneBox {
        SceneBox {
            center: self.center,
            radius: self.radius,
            contraction: self.contraction,
        }
    }

    /// Checks every setting.
    pub fn validate(&self) -> Result<()> {
        self.grid().validate()?;
        self.density_mlp().validate()?;
        self.color_mlp().validate()?;
        if self.geo_dims + 16 > 64 {
            return Err(GpuError::Usage(format!(
                "geo_dims {} + 16 SH coefficients exceed the MLP limit of 64 inputs",
                self.geo_dims
            )));
        }
        if !(self.near.is_finite()
            && self.far.is_finite()
            && self.near >= 0.0
            && self.far > self.near)
        {
            return Err(GpuError::Usage(format!(
                "sampling range {}..{} must satisfy 0 <= near < far",
                self.near, self.far
            )));
        }
        if self.space == Space::Ndc && self.far > 1.0 {
            return Err(GpuError::Usage(format!(
                "NDC sampling range {}..{}: NDC t ends at 1 (infinity)",
                self.near, self.far
            )));
        }
        if !(self.radius.is_finite() && self.radius > 0.0)
            || self.center.iter().any(|c| !c.is_finite())
        {
            return Err(GpuError::Usage(format!(
                "scene box centre {:?} radius {}: need finite values and radius > 0",
                self.center, self.radius
            )));
        }
        if let Some(p) = self.sampler.proposal() {
            p.validate()?;
        }
        if self.precision == Precision::F16 && self.features != 2 {
            return Err(GpuError::Usage(format!(
                "precision f16 needs 2 features per level, not {}",
                self.features
            )));
        }
        Ok(())
    }
}

/// Where each section of the flat parameter buffer starts, and its length (floats).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ParamLayout {
    /// Hash table.
    pub table: (usize, usize),
    /// Density MLP.
    pub density: (usize, usize),
    /// Colour MLP.
    pub color: (usize, usize),
    /// With the proposal sampler: the proposal field's hash table and density MLP, after the
    /// colour MLP.
    pub proposal: Option<[(usize, usize); 2]>,
    /// Total floats including alignment gaps.
    pub total: usize,
}

impl ParamLayout {
    /// The layout for a configuration.
    pub fn new(cfg: &ModelConfig) -> ParamLayout {
        let up = |n: usize| n.div_ceil(SECTION_ALIGN) * SECTION_ALIGN;
        let t = cfg.grid().param_count() as usize;
        let d = cfg.density_mlp().param_count();
        let c = cfg.color_mlp().param_count();
        let d0 = up(t);
        let c0 = d0 + up(d);
        let mut total = c0 + up(c);
        let proposal = cfg.sampler.proposal().map(|p| {
            let pt = p.grid().param_count() as usize;
            let pm = p.mlp().param_count();
            let t0 = total;
            let m0 = t0 + up(pt);
            total = m0 + up(pm);
            [(t0, pt), (m0, pm)]
        });
        ParamLayout {
            table: (0, t),
            density: (d0, d),
            color: (c0, c),
            proposal,
            total,
        }
    }
}

impl ParamLayout {
    /// The three sections of a flat buffer (parameters or gradients) as bindings.
    pub fn sections<'a>(&self, buf: &'a Buffer<f32>) -> Result<[Binding<'a>; 3]> {
        Ok([
            buf.slice(self.table.0, self.table.1)?,
            buf.slice(self.density.0, self.density.1)?,
            buf.slice(self.color.0, self.color.1)?,
        ])
    }

    /// The proposal field's sections (hash table, density MLP) of a flat buffer, with the
    /// proposal sampler.
    pub fn proposal_sections<'a>(&self, buf: &'a Buffer<f32>) -> Result<Option<[Binding<'a>; 2]>> {
        self.proposal
            .map(|[t, m]| Ok([buf.slice(t.0, t.1)?, buf.slice(m.0, m.1)?]))
            .transpose()
    }
}

/// Initial parameters: table entries uniform in +-1e-4 (Instant-NGP), MLP weights Xavier-uniform,
/// biases zero, gaps zero.
pub fn init_params(cfg: &ModelConfig, seed: u64) -> Vec<f32> {
    let lay = ParamLayout::new(cfg);
    let mut rng = Rng::new(seed);
    let mut p = vec![0f32; lay.total];
    let mut tables = vec![lay.table];
    let mut mlps = vec![
        (cfg.density_mlp(), lay.density.0),
        (cfg.color_mlp(), lay.color.0),
    ];
    if let (Some(pc), Some([t, m])) = (cfg.sampler.proposal(), lay.proposal) {
        tables.push(t);
        mlps.push((pc.mlp(), m.0));
    }
    for (start, len) in tables {
        for v in &mut p[start..start + len] {
            *v = rng.uniform(-1e-4, 1e-4);
        }
    }
    for (mlp, start) in mlps {
        for l in 0..mlp.layers() {
            let (ni, no) = (mlp.dims[l] as usize, mlp.dims[l + 1] as usize);
            let a = (6.0 / (ni + no) as f64).sqrt() as f32;
            let off = start + mlp.offset(l);
            for v in &mut p[off..off + ni * no] {
                *v = rng.uniform(-a, a);
            }
        }
    }
    p
}

/// Timestamps between the stages of a recording, for per-kernel timings (`bench train`).
#[derive(Debug)]
pub struct Profiler<'a> {
    timer: &'a GpuTimer,
    names: Vec<&'static str>,
}

impl<'a> Profiler<'a> {
    /// Profiles into `timer` (reset it in the recording first; one slot per mark).
    pub fn new(timer: &'a GpuTimer) -> Profiler<'a> {
        Profiler {
            timer,
            names: Vec::new(),
        }
    }

    /// The stage names, in order: the time between mark i - 1 and mark i is stage i's.
    pub fn names(&self) -> &[&'static str] {
        &self.names
    }
}

/// Writes a timestamp ending stage `name` when profiling.
pub fn mark<'a>(
    prof: &mut Option<Profiler<'a>>,
    rec: &mut Recorder<'a>,
    name: &'static str,
) -> Result<()> {
    if let Some(p) = prof {
        rec.timestamp(p.timer, p.names.len() as u32)?;
        p.names.push(name);
    }
    Ok(())
}

/// Per-sample work buffers of one field evaluation, as bindings (the caller owns them).
#[derive(Clone, Copy, Debug)]
pub struct FieldIo<'a> {
    /// `[n, 3]` sample positions (world or NDC).
    pub positions: Binding<'a>,
    /// Per ray `(xyz, _)` world view direction; sample i belongs to ray `i / per_ray`.
    pub dirs: Binding<'a>,
    /// `[n, 3]` contracted positions.
    pub contracted: Binding<'a>,
    /// `[n, L*F]` encoding.
    pub encoded: Binding<'a>,
    /// `[n, geo_dims]` density MLP output.
    pub dens: Binding<'a>,
    /// `[n, geo_dims + 16]` colour MLP input.
    pub color_in: Binding<'a>,
    /// `[n, 3]` colour MLP output.
    pub color_out: Binding<'a>,
    /// `[n]` density (output).
    pub sigma: Binding<'a>,
    /// `[n, 4]` colour (output).
    pub rgb: Binding<'a>,
}

/// An MLP of the field at `precision` (its backward record in f16 for "f16").
fn mlp(ctx: &Context, config: MlpConfig, precision: Precision) -> Result<Mlp> {
    let m = Mlp::new(ctx, config)?;
    if precision == Precision::F16 {
        m.with_f16(ctx)
    } else {
        Ok(m)
    }
}

/// Gradient buffers of the backward pass.
#[derive(Clone, Copy, Debug)]
pub struct FieldGrads<'a> {
    /// `[n]` dL/dsigma (input).
    pub d_sigma: Binding<'a>,
    /// `[n, 4]` dL/drgb (input).
    pub d_rgb: Binding<'a>,
    /// `[n, 3]` scratch.
    pub d_color_out: Binding<'a>,
    /// `[n, geo_dims + 16]` scratch.
    pub d_color_in: Binding<'a>,
    /// `[n, geo_dims]` scratch.
    pub d_dens: Binding<'a>,
    /// `[n, L*F]` scratch.
    pub d_encoded: Binding<'a>,
    /// `[n, density saved_words]` scratch.
    pub saved_density: Binding<'a>,
    /// `[n, colour saved_words]` scratch.
    pub saved_color: Binding<'a>,
}

/// The field's kernels for one configuration.
#[derive(Debug)]
pub struct Field {
    config: ModelConfig,
    layout: ParamLayout,
    scene: SceneBox,
    grid: HashGrid,
    density: Mlp,
    color: Mlp,
    enc: Encodings,
    density_fwd: Kernel,
    color_fwd: Kernel,
    color_bwd: Kernel,
    density_bwd: Kernel,
}

impl Field {
    /// Builds the kernels.
    pub fn new(ctx: &Context, config: ModelConfig) -> Result<Field> {
        config.validate()?;
        Ok(Field {
            layout: ParamLayout::new(&config),
            scene: config.scene_box(),
            grid: {
                let g = HashGrid::new(ctx, config.grid())?;
                if config.precision == Precision::F16 {
                    g.with_f16(ctx)?
                } else {
                    g
                }
            },
            density: mlp(ctx, config.density_mlp(), config.precision)?,
            color: mlp(ctx, config.color_mlp(), config.precision)?,
            enc: Encodings::new(ctx)?,
            density_fwd: Kernel::new(ctx, &kh::density_head_fwd::DESC)?,
            color_fwd: Kernel::new(ctx, &kh::color_head_fwd::DESC)?,
            color_bwd: Kernel::new(ctx, &kh::color_head_bwd::DESC)?,
            density_bwd: Kernel::new(ctx, &kh::density_head_bwd::DESC)?,
            config,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &ModelConfig {
        &self.config
    }

    /// The flat parameter layout.
    pub fn layout(&self) -> &ParamLayout {
        &self.layout
    }

    /// The hash grid (for hash decay).
    pub fn grid(&self) -> &HashGrid {
        &self.grid
    }

    /// Resolves `mode` on `ctx`'s device and sets both MLPs' path ([`Mlp::set_path`]); returns
    /// the path taken.
    pub fn set_mlp(&mut self, ctx: &Context, mode: MlpMode) -> Result<MlpPath> {
        let path = mode.resolve(ctx, self.density.is_f16())?;
        self.density.set_path(ctx, path)?;
        self.color.set_path(ctx, path)?;
        Ok(path)
    }

    /// The density MLP.
    pub fn density(&self) -> &Mlp {
        &self.density
    }

    /// The colour MLP.
    pub fn color(&self) -> &Mlp {
        &self.color
    }

    /// The scene box of the contraction.
    pub fn scene(&self) -> &SceneBox {
        &self.scene
    }

    /// Floats per sample of each buffer in [`FieldIo`] and [`FieldGrads`], by name.
    pub fn per_sample(&self) -> [(&'static str, usize); 14] {
        let enc = (self.config.levels * self.config.features) as usize;
        let g = self.config.geo_dims as usize;
        [
            ("positions", 3),
            ("contracted", 3),
            ("encoded", enc),
            ("dens", g),
            ("color_in", g + 16),
            ("color_out", 3),
            ("sigma", 1),
            ("rgb", 4),
            ("d_color_out", 3),
            ("d_color_in", g + 16),
            ("d_dens", g),
            ("d_encoded", enc),
            ("saved_density", self.density.saved_words()),
            ("saved_color", self.color.saved_words()),
        ]
    }

    fn heads_params(&self, n: u64, per_ray: u32) -> Result<kh::Params> {
        if per_ray == 0 {
            return Err(GpuError::Usage("samples per ray must be positive".into()));
        }
        Ok(kh::Params {
            n: count_u32(n, "field samples")?,
            per_ray,
            geo_dims: self.config.geo_dims,
            _pad: 0,
        })
    }

    /// Records the forward pass of `n` samples (`per_ray` per ray) with parameters `params`
    /// (the whole flat buffer's sections, see [`Field::layout`]).
    pub fn forward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        params: [Binding<'a>; 3],
        io: &FieldIo<'a>,
        n: u64,
        per_ray: u32,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        let [table, wd, wc] = params;
        let hp = self.heads_params(n, per_ray)?;
        self.enc
            .contract(rec, io.positions, io.contracted, n, &self.scene)?;
        mark(prof, rec, "contract")?;
        self.grid
            .forward(rec, io.contracted, table, io.encoded, n)?;
        mark(prof, rec, "hash grid fwd")?;
        self.density.forward(rec, wd, io.encoded, io.dens, n)?;
        mark(prof, rec, "density MLP fwd")?;
        let b = kh::density_head_fwd::Bindings {
            dirs: io.dirs,
            dens: io.dens,
            sigma: io.sigma,
            color_in: io.color_in,
        };
        rec.dispatch(&self.density_fwd, b.into_array(), &hp, n)?;
        mark(prof, rec, "density head fwd (trunc_exp, SH4, concat)")?;
        self.color.forward(rec, wc, io.color_in, io.color_out, n)?;
        mark(prof, rec, "colour MLP fwd")?;
        let b = kh::color_head_fwd::Bindings {
            color_out: io.color_out,
            rgb: io.rgb,
        };
        rec.dispatch(&self.color_fwd, b.into_array(), &hp, n)?;
        mark(prof, rec, "colour head fwd (sigmoid)")
    }

    /// Records the backward pass after [`Field::forward`] on the same buffers: adds the
    /// parameter gradients to `d_params` (same sections as `params`).
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn backward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        params: [Binding<'a>; 3],
        d_params: [Binding<'a>; 3],
        io: &FieldIo<'a>,
        g: &FieldGrads<'a>,
        n: u64,
        per_ray: u32,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        let [_, wd, wc] = params;
        let [dt, dwd, dwc] = d_params;
        let hp = self.heads_params(n, per_ray)?;
        let b = kh::color_head_bwd::Bindings {
            color_out: io.color_out,
            d_color_out: g.d_color_out,
            d_rgb: g.d_rgb,
        };
        rec.dispatch(&self.color_bwd, b.into_array(), &hp, n)?;
        mark(prof, rec, "colour head bwd")?;
        self.color.backward(
            rec,
            wc,
            io.color_in,
            g.d_color_out,
            g.d_color_in,
            g.saved_color,
            dwc,
            n,
        )?;
        mark(prof, rec, "colour MLP bwd (data + weights)")?;
        let b = kh::density_head_bwd::Bindings {
            dens: io.dens,
            d_dens: g.d_dens,
            d_sigma: g.d_sigma,
            d_color_in: g.d_color_in,
        };
        rec.dispatch(&self.density_bwd, b.into_array(), &hp, n)?;
        mark(prof, rec, "density head bwd")?;
        self.density.backward(
            rec,
            wd,
            io.encoded,
            g.d_dens,
            g.d_encoded,
            g.saved_density,
            dwd,
            n,
        )?;
        mark(prof, rec, "density MLP bwd (data + weights)")?;
        self.grid.backward(rec, io.contracted, g.d_encoded, dt, n)?;
        mark(prof, rec, "hash grid bwd (atomics)")
    }
}
