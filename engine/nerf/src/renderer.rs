//! Rendering a trained BaseNeRF field: [`Nerf`] holds the field, its parameters and the
//! kernels that render it, either through the fused march (the default, skipping empty space
//! once the occupancy grid is built) or through the standalone training chain that stores
//! every sample between kernels. A field trained with the proposal sampler renders at the
//! samples drawn from its proposal field's weights, as training drew them, on either path.

use extranerf_gpu::kernels::render::pixels as kp;
use extranerf_gpu::{count_u32, Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};
use extranerf_prims::Prims;

use crate::data::Camera;
use crate::field::mlp::{MlpMode, MlpPath};
use crate::field::proposal::{ProposalField, ProposalUse, ProposalWork};
use crate::model::{mark, Field, FieldGrads, FieldIo, ModelConfig, Profiler, Space};
use crate::render::composite::{Background, Compositor, Samples};
use crate::render::march::{MarchCuts, Marcher};
use crate::render::occupancy::{Occupancy, OccupancyConfig};
use crate::render::proposal::{Proposal, RaySet, HISTOGRAM_PAD};
use crate::render::rays::{gpu_camera, RayGen, RaySpace};
use crate::render::sample::{SampleOutputs, Sampler, SkipEmpty, Spacing};

/// Per-ray and per-sample buffers for batches of up to `rays` rays of `samples` samples.
#[derive(Debug)]
pub(crate) struct Workspace {
    pub(crate) rays: u32,
    pub(crate) samples: u32,
    pub(crate) pixels: Buffer<[u32; 2]>,
    pub(crate) origins: Buffer<[f32; 4]>,
    pub(crate) dirs: Buffer<[f32; 4]>,
    pub(crate) world_origins: Buffer<[f32; 4]>,
    pub(crate) world_dirs: Buffer<[f32; 4]>,
    pub(crate) near_far: Buffer<[f32; 2]>,
    pub(crate) spans: Buffer<[u32; 2]>,
    pub(crate) t_dt: Buffer<[f32; 2]>,
    pub(crate) s_ds: Buffer<[f32; 2]>,
    pub(crate) out_rgba: Buffer<[f32; 4]>,
    pub(crate) out_depth: Buffer<f32>,
    pub(crate) target_rgb: Buffer<[f32; 4]>,
    pub(crate) target_depth: Buffer<[f32; 2]>,
    pub(crate) loss: Buffer<f32>,
    pub(crate) mse: Buffer<f32>,
    pub(crate) dist_loss: Buffer<f32>,
    pub(crate) d_rgba: Buffer<[f32; 4]>,
    pub(crate) d_depth: Buffer<f32>,
    pub(crate) d_weight: Buffer<f32>,
    pub(crate) d_sigma: Buffer<f32>,
    pub(crate) d_rgb: Buffer<[f32; 4]>,
    /// Per-sample buffers of [`Field::per_sample`], in that order.
    pub(crate) per_sample: Vec<Buffer<f32>>,
}

impl Workspace {
    pub(crate) fn new(
        ctx: &Context,
        field: &Field,
        cfg: &ModelConfig,
        rays: u32,
        samples: u32,
        grads: bool,
        per_sample_buffers: bool,
    ) -> Result<Workspace> {
        let r = rays as usize;
        // The fused step keeps every sample in registers: its per-sample buffers are stubs of
        // one element that no kernel binds.
        let n = if per_sample_buffers {
            r * samples as usize
        } else {
            1
        };
        count_u32(r as u64 * samples as u64, "samples per batch")?;
        let gr = |len: usize| if grads { len } else { 1 };
        let mut per_sample = Vec::new();
        for (i, (name, w)) in field.per_sample().into_iter().enumerate() {
            // The last six are gradient scratch.
            let len = if i >= 8 { gr(n * w) } else { n * w };
            per_sample.push(Buffer::new(ctx, name, len)?);
        }
        Ok(Workspace {
            rays,
            samples,
            pixels: Buffer::new(ctx, "pixels", r)?,
            origins: Buffer::new(ctx, "ray origins", r)?,
            dirs: Buffer::new(ctx, "ray directions", r)?,
            world_origins: Buffer::new(ctx, "world ray origins", r)?,
            world_dirs: Buffer::new(ctx, "world ray directions", r)?,
            near_far: Buffer::from_slice(ctx, "near/far", &vec![[cfg.near, cfg.far]; r])?,
            spans: Buffer::new(ctx, "ray spans", r)?,
            t_dt: Buffer::new(ctx, "t_dt", n)?,
            s_ds: Buffer::new(ctx, "s_ds", n)?,
            out_rgba: Buffer::new(ctx, "rendered rgba", r)?,
            out_depth: Buffer::new(ctx, "rendered depth", r)?,
            target_rgb: Buffer::new(ctx, "target rgb", r)?,
            target_depth: Buffer::new(ctx, "target depth", r)?,
            loss: Buffer::new(ctx, "ray loss", gr(r))?,
            mse: Buffer::new(ctx, "ray mse", gr(r))?,
            dist_loss: Buffer::new(ctx, "distortion loss", gr(r))?,
            d_rgba: Buffer::new(ctx, "dL/drgba", gr(r))?,
            d_depth: Buffer::new(ctx, "dL/ddepth", gr(r))?,
            d_weight: Buffer::new(ctx, "dL/dweight", gr(n))?,
            d_sigma: Buffer::new(ctx, "dL/dsigma", gr(n))?,
            d_rgb: Buffer::new(ctx, "dL/drgb", gr(n))?,
            per_sample,
        })
    }

    pub(crate) fn io(&self) -> FieldIo<'_> {
        let p = |i: usize| self.per_sample[i].binding();
        FieldIo {
            positions: p(0),
            dirs: self.world_dirs.binding(),
            contracted: p(1),
            encoded: p(2),
            dens: p(3),
            color_in: p(4),
            color_out: p(5),
            sigma: p(6),
            rgb: p(7),
        }
    }

    pub(crate) fn field_grads(&self) -> FieldGrads<'_> {
        let p = |i: usize| self.per_sample[i].binding();
        FieldGrads {
            d_sigma: self.d_sigma.binding(),
            d_rgb: self.d_rgb.binding(),
            d_color_out: p(8),
            d_color_in: p(9),
            d_dens: p(10),
            d_encoded: p(11),
            saved_density: p(12),
            saved_color: p(13),
        }
    }

    pub(crate) fn samples(&self, n_rays: u64) -> Samples<'_> {
        Samples {
            rays: self.spans.binding(),
            sigma: self.per_sample[6].binding(),
            rgb: self.per_sample[7].binding(),
            t_dt: self.t_dt.binding(),
            n_rays,
            n_samples: n_rays * self.samples as u64,
        }
    }
}

/// A field with its parameters and the kernels that render it.
#[derive(Debug)]
pub struct Nerf {
    pub(crate) field: Field,
    pub(crate) space: RaySpace,
    pub(crate) params: Buffer<f32>,
    pub(crate) raygen: RayGen,
    pub(crate) sampler: Sampler,
    pub(crate) comp: Compositor,
    pub(crate) pixel_range: Kernel,
    pub(crate) background: [f32; 3],
    pub(crate) marcher: Marcher,
    pub(crate) occupancy: Option<Occupancy>,
    /// With the proposal sampler ([`crate::model::Sampler::Proposal`]): its field and kernels.
    pub(crate) proposal: Option<ProposalSampler>,
}

/// Where [`Nerf::record_forward`] takes a ray's samples from.
#[derive(Clone, Copy, Debug)]
pub(crate) enum SamplesFrom<'s, 'a> {
    /// Uniform strata, over the occupied part of the ray with an occupancy grid.
    Strata(Option<&'s SkipEmpty<'a>>),
    /// The proposal sampler, with its buffers.
    Proposal(&'a ProposalWork),
}

/// The proposal sampler of a field: the proposal field's kernels and the resampling's.
#[derive(Debug)]
pub(crate) struct ProposalSampler {
    pub(crate) field: ProposalField,
    pub(crate) kernels: Proposal,
}

/// Why a field with the proposal sampler has no occupancy grid (its trainer and its renders
/// refuse one).
pub(crate) const PROPOSAL_WITHOUT_OCCUPANCY: &str = "the field samples its rays with the proposal sampler, whose samples already lie where its weights are: it trains, renders and computes visibility without an occupancy grid (set the occupancy resolution to 0)";

/// How [`Nerf::render_with`] evaluates the field ([`Nerf::default_march`] chooses for
/// [`Nerf::render`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum March {
    /// The training chain: rays, samples (the proposal sampler's when the field has one,
    /// else uniform strata), the field's standalone kernels, compositing (every sample stored
    /// in memory between kernels; no cuts, no occupancy).
    Standalone,
    /// The fused march kernel with these cuts, at uniform strata skipping empty space when the
    /// occupancy grid has been built ([`Nerf::build_occupancy`]), or at the proposal sampler's
    /// samples (drawn by its standalone kernels before the march; scalar MLPs, no occupancy).
    Fused(MarchCuts),
}

impl Default for March {
    fn default() -> Self {
        March::Fused(MarchCuts::EXACT)
    }
}

/// The proposal sampler's samples for a kernel that takes given samples (the fused march, the
/// visibility kernel), per chunk of rays: the rays, in a workspace without per-sample buffers
/// whose pixels the kernel then reads, and the proposal's buffers, whose main samples it takes.
pub(crate) struct GivenSamples {
    ws: Workspace,
    work: ProposalWork,
}

impl GivenSamples {
    /// The pixels the samples are drawn for: written first (as (camera, pixel) pairs), then
    /// read by [`Nerf::record_given_samples`] and by the kernel that takes the samples.
    pub(crate) fn pixels(&self) -> Binding<'_> {
        self.ws.pixels.binding()
    }
}

/// The per-chunk buffers of one render path.
#[allow(clippy::large_enum_variant)] // one short-lived value per render call
enum RenderIo {
    /// Every stage's per-sample buffers, and the proposal sampler's when the field has one.
    Standalone(Workspace, Option<ProposalWork>),
    /// Pixels in, colour and depth out, per ray; with the proposal sampler, the rays (in a
    /// workspace without per-sample buffers, whose pixels the march then reads) and the
    /// proposal's buffers, whose main samples the march takes.
    Fused {
        cuts: MarchCuts,
        pixels: Buffer<[u32; 2]>,
        rgba: Buffer<[f32; 4]>,
        depth: Buffer<f32>,
        proposal: Option<GivenSamples>,
    },
}

/// What [`Nerf::build_occupancy`] found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct OccupancyStats {
    /// Cells in the grid.
    pub cells: u64,
    /// Cells marked occupied.
    pub occupied: u64,
}

impl Nerf {
    /// A field with the given parameters (`ParamLayout::total` floats).
    pub fn new(
        ctx: &Context,
        config: ModelConfig,
        params: &[f32],
        background: [f32; 3],
    ) -> Result<Nerf> {
        let field = Field::new(ctx, config)?;
        let total = field.layout().total;
        if params.len() != total {
            return Err(GpuError::Usage(format!(
                "{} parameters given, the configuration has {total}",
                params.len()
            )));
        }
        let space = match field.config().space {
            Space::Ndc => RaySpace::Ndc { near: 1.0 },
            Space::World => RaySpace::World,
        };
        let proposal = match ProposalField::new(ctx, field.config())? {
            None => None,
            Some(field) => Some(ProposalSampler {
                field,
                kernels: Proposal::new(ctx)?,
            }),
        };
        Ok(Nerf {
            proposal,
            space,
            params: Buffer::from_slice(ctx, "field parameters", params)?,
            raygen: RayGen::new(ctx)?,
            sampler: Sampler::new(ctx)?,
            comp: Compositor::new(ctx)?,
            pixel_range: Kernel::new(ctx, &kp::pixel_range::DESC)?,
            field,
            background,
            marcher: Marcher::new(ctx)?,
            occupancy: None,
        })
    }

    /// Resolves `mode` on `ctx`'s device and sets the MLP path of the field (the standalone
    /// kernels), of the proposal field when there is one, and of the fused march; returns the
    /// path taken. On an error all keep their previous paths.
    pub fn set_mlp(&mut self, ctx: &Context, mode: MlpMode) -> Result<MlpPath> {
        let path = mode.resolve(ctx, self.field.density().is_f16())?;
        let before = self.marcher.mlp_path();
        self.marcher.set_path(ctx, &self.field, path)?;
        let proposal_before = self.proposal.as_ref().map(|ps| ps.field.path());
        let set = match &mut self.proposal {
            Some(ps) => ps.field.set_path(ctx, path),
            None => Ok(()),
        }
        .and_then(|()| self.field.set_mlp(ctx, mode));
        match set {
            Ok(p) => Ok(p),
            Err(e) => {
                self.marcher.set_path(ctx, &self.field, before)?;
                if let (Some(ps), Some(p)) = (&mut self.proposal, proposal_before) {
                    ps.field.set_path(ctx, p)?;
                }
                Err(e)
            }
        }
    }

    /// The path [`Nerf::render`] takes: the standalone chain for a field the fused march cannot
    /// take ([`Marcher::supports`]) or one with the proposal sampler when the march runs
    /// cooperative-matrix MLPs (it takes given samples with scalar MLPs only), else the fused
    /// march with no cuts.
    pub fn default_march(&self) -> March {
        let proposal_coop = self.proposal.is_some() && self.marcher.mlp_path() != MlpPath::Scalar;
        if proposal_coop || Marcher::supports(&self.field).is_err() {
            March::Standalone
        } else {
            March::default()
        }
    }

    /// True when the field samples its rays with the proposal sampler.
    pub fn has_proposal(&self) -> bool {
        self.proposal.is_some()
    }

    /// The MLP path the fused march renders with.
    pub fn march_mlp_path(&self) -> MlpPath {
        self.marcher.mlp_path()
    }

    /// The field.
    pub fn field(&self) -> &Field {
        &self.field
    }

    /// The flat parameter buffer.
    pub fn params(&self) -> &Buffer<f32> {
        &self.params
    }

    pub(crate) fn sections<'a>(&'a self, buf: &'a Buffer<f32>) -> Result<[Binding<'a>; 3]> {
        self.field.layout().sections(buf)
    }

    /// The proposal field's sections of a flat buffer (parameters or gradients).
    pub(crate) fn proposal_sections<'a>(&self, buf: &'a Buffer<f32>) -> Result<[Binding<'a>; 2]> {
        self.field
            .layout()
            .proposal_sections(buf)?
            .ok_or_else(|| GpuError::Usage("the field has no proposal sections".into()))
    }

    /// The proposal sampler, or an error saying the field has none.
    pub(crate) fn proposal_sampler(&self) -> Result<&ProposalSampler> {
        self.proposal
            .as_ref()
            .ok_or_else(|| GpuError::Usage("the field has no proposal sampler".into()))
    }

    /// The proposal sampler's half of a forward pass, after [`Nerf::record_field_rays`] of
    /// `ws`'s first `n` rays: the proposal field at its strata (in `w`), then the main samples
    /// drawn from its weights into `out` (`ws.samples` per ray), their edges into
    /// `w.main_edges`. `seed: None` centres the strata and the resampling (renders); `targets`
    /// as [`Sampler::record`] takes them.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub(crate) fn record_proposal_samples<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        ws: &'a Workspace,
        w: &'a ProposalWork,
        n: u64,
        seed: Option<u32>,
        targets: Option<Binding<'a>>,
        out: &SampleOutputs<'a>,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        let ps = self.proposal_sampler()?;
        let strata = w.strata_outputs();
        self.record_stratified(rec, ws, &strata, n, w.samples, seed, targets, None)?;
        mark(prof, rec, "proposal strata")?;
        ps.field
            .forward(rec, self.proposal_sections(&self.params)?, w, n, prof)?;
        let rays = RaySet {
            origins: ws.origins.binding(),
            directions: ws.dirs.binding(),
            near_far: ws.near_far.binding(),
            targets,
            n_rays: count_u32(n, "rays")?,
        };
        ps.kernels.resample(
            rec,
            &w.source_bins(),
            &rays,
            w.main_edges.binding(),
            out,
            ws.samples,
            HISTOGRAM_PAD,
            self.spacing(),
            seed,
        )?;
        mark(prof, rec, "proposal resampling")
    }

    /// Records rays for `ws.pixels[..n]`, their samples from `from` (jittered with `seed`;
    /// with `targets`, a training batch's target colours, not on virtual views' rays:
    /// [`Sampler::record`]), the field and the compositing into `ws.out_rgba` /
    /// `ws.out_depth`.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub(crate) fn record_forward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        ws: &'a Workspace,
        cameras: Binding<'a>,
        n_cameras: u32,
        n: u64,
        seed: Option<u32>,
        targets: Option<Binding<'a>>,
        from: SamplesFrom<'_, 'a>,
        background: Background,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        self.record_rays(rec, ws, cameras, n_cameras, n, prof)?;
        let out = self.sample_outputs(ws);
        match from {
            SamplesFrom::Strata(skip) => {
                self.record_stratified(rec, ws, &out, n, ws.samples, seed, targets, skip)?;
                mark(
                    prof,
                    rec,
                    if skip.is_some() {
                        "stratified samples (occupied space)"
                    } else {
                        "stratified samples"
                    },
                )?;
            }
            SamplesFrom::Proposal(w) => {
                self.record_proposal_samples(rec, ws, w, n, seed, targets, &out, prof)?
            }
        }
        self.record_field_forward(rec, ws, n, background, prof)
    }

    /// Records the rays of `ws.pixels[..n]`: in the field's space (`ws.origins`, `ws.dirs`)
    /// and in the world (`ws.world_origins`, `ws.world_dirs`, for the view directions).
    pub(crate) fn record_rays<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        ws: &'a Workspace,
        cameras: Binding<'a>,
        n_cameras: u32,
        n: u64,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        self.record_field_rays(rec, ws, cameras, n_cameras, n)?;
        self.raygen.generate(
            rec,
            cameras,
            n_cameras,
            ws.pixels.binding(),
            ws.world_origins.binding(),
            ws.world_dirs.binding(),
            n,
            RaySpace::World,
        )?;
        mark(prof, rec, "rays (NDC + world)")
    }

    /// Records the rays of `ws.pixels[..n]` in the field's space only (`ws.origins`,
    /// `ws.dirs`): what the samplers place samples along.
    pub(crate) fn record_field_rays<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        ws: &'a Workspace,
        cameras: Binding<'a>,
        n_cameras: u32,
        n: u64,
    ) -> Result<()> {
        self.raygen.generate(
            rec,
            cameras,
            n_cameras,
            ws.pixels.binding(),
            ws.origins.binding(),
            ws.dirs.binding(),
            n,
            self.space,
        )
    }

    /// How samples are spaced along the field's rays: linear in NDC, in disparity in the
    /// world.
    pub(crate) fn spacing(&self) -> Spacing {
        match self.space {
            RaySpace::Ndc { .. } => Spacing::Linear,
            RaySpace::World => Spacing::Disparity,
        }
    }

    /// The outputs of a sampler into `ws`'s main samples.
    pub(crate) fn sample_outputs<'a>(&self, ws: &'a Workspace) -> SampleOutputs<'a> {
        SampleOutputs {
            positions: ws.io().positions,
            t_dt: ws.t_dt.binding(),
            s_ds: ws.s_ds.binding(),
            rays: ws.spans.binding(),
        }
    }

    /// Records `per_ray` stratified samples on each of the first `n` rays of `ws` (in the
    /// field's space, [`Nerf::record_field_rays`]) into `out`, as [`Sampler::record`] places
    /// them.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    fn record_stratified<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        ws: &'a Workspace,
        out: &SampleOutputs<'a>,
        n: u64,
        per_ray: u32,
        seed: Option<u32>,
        targets: Option<Binding<'a>>,
        skip: Option<&SkipEmpty<'a>>,
    ) -> Result<()> {
        self.sampler.record(
            rec,
            ws.origins.binding(),
            ws.dirs.binding(),
            ws.near_far.binding(),
            out,
            n,
            per_ray,
            self.spacing(),
            seed,
            targets,
            skip,
        )
    }

    /// Records the field at `ws`'s samples and the compositing into `ws.out_rgba` /
    /// `ws.out_depth`.
    pub(crate) fn record_field_forward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        ws: &'a Workspace,
        n: u64,
        background: Background,
        prof: &mut Option<Profiler<'a>>,
    ) -> Result<()> {
        let ns = n * ws.samples as u64;
        self.field.forward(
            rec,
            self.sections(&self.params)?,
            &ws.io(),
            ns,
            ws.samples,
            prof,
        )?;
        self.comp.forward(
            rec,
            &ws.samples(n),
            background,
            ws.out_rgba.binding(),
            ws.out_depth.binding(),
        )?;
        mark(prof, rec, "composite fwd")
    }

    /// The occupancy grid fused renders use, when built.
    pub fn occupancy(&self) -> Option<&Occupancy> {
        self.occupancy.as_ref()
    }

    /// Builds the occupancy grid from the field: `passes` jittered density evaluations per
    /// cell (the maximum is kept), thresholded as [`Occupancy::record_bits`] does. Fused
    /// renders skip the empty cells from then on; `None` removes the grid. A field with the
    /// proposal sampler refuses a grid: its samples already lie where its weights are.
    pub fn build_occupancy(
        &mut self,
        ctx: &Context,
        prims: &Prims,
        config: Option<OccupancyConfig>,
        passes: u32,
    ) -> Result<Option<OccupancyStats>> {
        let Some(config) = config else {
            self.occupancy = None;
            return Ok(None);
        };
        if self.proposal.is_some() {
            return Err(GpuError::Usage(PROPOSAL_WITHOUT_OCCUPANCY.into()));
        }
        if passes == 0 {
            return Err(GpuError::Usage(
                "the occupancy grid needs at least one pass".into(),
            ));
        }
        let occ = Occupancy::new(ctx, config)?;
        let cells = config.cells();
        let mut rec = ctx.recorder("occupancy build")?;
        for pass in 0..passes {
            let decay = if pass == 0 { 0.0 } else { 1.0 };
            self.marcher.update_occupancy(
                &mut rec,
                &self.field,
                self.sections(&self.params)?,
                &occ,
                0,
                cells,
                pass,
                decay,
            )?;
        }
        occ.record_bits(&mut rec, prims)?;
        ctx.run(rec)?;
        let occupied = occ
            .bits()
            .read()?
            .iter()
            .map(|w| w.count_ones() as u64)
            .sum();
        self.occupancy = Some(occ);
        Ok(Some(OccupancyStats { cells, occupied }))
    }

    /// Renders a whole view: `(rgb[w*h*3], depth[w*h], opacity[w*h])`, depth in the ray space's
    /// units (NDC t for forward-facing scenes). `chunk_rays` rays per pass, midpoint samples
    /// (`samples` per ray: the main samples the proposal sampler draws, when the field has
    /// one), through the fused march with no cuts, as the command line renders (skipping empty
    /// space once [`Nerf::build_occupancy`] has built the grid; it reads the f32 hash table also
    /// for an f16 model). A field the fused march cannot take ([`Marcher::supports`]: MLP
    /// widths that are not multiples of 4 or overflow its weight block, world space with near
    /// 0), or one with the proposal sampler while the march runs cooperative-matrix MLPs,
    /// renders through the standalone training kernels ([`Nerf::default_march`]).
    /// [`Nerf::render_with`] chooses the path.
    pub fn render(
        &self,
        ctx: &Context,
        camera: &Camera,
        chunk_rays: u32,
        samples: u32,
    ) -> Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
        self.render_with(ctx, camera, chunk_rays, samples, self.default_march())
    }

    /// A workspace for renders of `chunk_rays` rays of `samples` samples (no gradients), with
    /// per-sample buffers or (for the rays the proposal sampler draws from) without.
    fn render_workspace(
        &self,
        ctx: &Context,
        chunk_rays: u32,
        samples: u32,
        per_sample: bool,
    ) -> Result<Workspace> {
        Workspace::new(
            ctx,
            &self.field,
            self.field.config(),
            chunk_rays,
            samples,
            false,
            per_sample,
        )
    }

    /// Buffers for the proposal sampler's samples of chunks of `chunk_rays` rays, `samples`
    /// main samples each, when the field has the sampler ([`Nerf::record_given_samples`]).
    pub(crate) fn given_samples(
        &self,
        ctx: &Context,
        chunk_rays: u32,
        samples: u32,
    ) -> Result<Option<GivenSamples>> {
        let Some(ps) = &self.proposal else {
            return Ok(None);
        };
        Ok(Some(GivenSamples {
            ws: self.render_workspace(ctx, chunk_rays, samples, false)?,
            work: ProposalWork::new(ctx, &ps.field, chunk_rays, samples, ProposalUse::March)?,
        }))
    }

    /// Records the proposal sampler's centred samples of the rays of `g.pixels()[..n]` (written
    /// before) through `cameras`; returns their `(t, dt)`, `g`'s samples per ray for each ray in
    /// order, sorted along it, as the fused march and the visibility kernel take them.
    pub(crate) fn record_given_samples<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        g: &'a GivenSamples,
        cameras: Binding<'a>,
        n_cameras: u32,
        n: u64,
    ) -> Result<Binding<'a>> {
        self.record_field_rays(rec, &g.ws, cameras, n_cameras, n)?;
        self.record_proposal_samples(
            rec,
            &g.ws,
            &g.work,
            n,
            None,
            None,
            &g.work.main_outputs(),
            &mut None,
        )?;
        Ok(g.work.main_t_dt.binding())
    }

    /// [`Nerf::render`] with a choice of evaluation path.
    pub fn render_with(
        &self,
        ctx: &Context,
        camera: &Camera,
        chunk_rays: u32,
        samples: u32,
        march: March,
    ) -> Result<(Vec<f32>, Vec<f32>, Vec<f32>)> {
        if chunk_rays == 0 {
            return Err(GpuError::Usage("the render chunk must be positive".into()));
        }
        // The standalone chain needs per-sample buffers; the fused march only per-ray ones.
        let io = match march {
            March::Standalone => RenderIo::Standalone(
                self.render_workspace(ctx, chunk_rays, samples, true)?,
                self.proposal
                    .as_ref()
                    .map(|ps| {
                        ProposalWork::new(ctx, &ps.field, chunk_rays, samples, ProposalUse::Render)
                    })
                    .transpose()?,
            ),
            March::Fused(cuts) => RenderIo::Fused {
                cuts,
                pixels: Buffer::new(ctx, "march pixels", chunk_rays as usize)?,
                rgba: Buffer::new(ctx, "march colour", chunk_rays as usize)?,
                depth: Buffer::new(ctx, "march depth", chunk_rays as usize)?,
                proposal: self.given_samples(ctx, chunk_rays, samples)?,
            },
        };
        let cams = Buffer::from_slice(ctx, "render camera", &[gpu_camera(camera)])?;
        let total = camera.width as u64 * camera.height as u64;
        count_u32(total, "pixels")?;
        let rgba_all = Buffer::<[f32; 4]>::new(ctx, "rendered image", total as usize)?;
        let depth_all = Buffer::<f32>::new(ctx, "rendered depth", total as usize)?;
        let mut first = 0u64;
        while first < total {
            let n = (total - first).min(chunk_rays as u64);
            let mut rec = ctx.recorder("render")?;
            let p = kp::Params {
                n: n as u32,
                camera: 0,
                first: first as u32,
                _pad: 0,
            };
            let (rgba, depth) = match &io {
                RenderIo::Fused {
                    cuts,
                    pixels,
                    rgba,
                    depth,
                    proposal,
                } => {
                    let pixels = match proposal {
                        Some(g) => g.pixels(),
                        None => pixels.binding(),
                    };
                    let b = kp::pixel_range::Bindings { pixels };
                    rec.dispatch(&self.pixel_range, b.into_array(), &p, n)?;
                    let given = match proposal {
                        None => None,
                        Some(g) => {
                            Some(self.record_given_samples(&mut rec, g, cams.binding(), 1, n)?)
                        }
                    };
                    self.marcher.render(
                        &mut rec,
                        &self.field,
                        self.sections(&self.params)?,
                        cams.binding(),
                        1,
                        pixels,
                        n,
                        samples,
                        *cuts,
                        self.occupancy.as_ref(),
                        self.background,
                        rgba.binding(),
                        depth.binding(),
                        given,
                    )?;
                    (rgba.binding(), depth.binding())
                }
                RenderIo::Standalone(ws, proposal) => {
                    let b = kp::pixel_range::Bindings {
                        pixels: ws.pixels.binding(),
                    };
                    rec.dispatch(&self.pixel_range, b.into_array(), &p, n)?;
                    let from = match proposal {
                        None => SamplesFrom::Strata(None),
                        Some(w) => SamplesFrom::Proposal(w),
                    };
                    self.record_forward(
                        &mut rec,
                        ws,
                        cams.binding(),
                        1,
                        n,
                        None,
                        None,
                        from,
                        Background::Fixed(self.background),
                        &mut None,
                    )?;
                    (ws.out_rgba.binding(), ws.out_depth.binding())
                }
            };
            rec.copy(rgba, 0, rgba_all.binding(), first * 16, n * 16)?;
            rec.copy(depth, 0, depth_all.binding(), first * 4, n * 4)?;
            ctx.run(rec)?;
            first += n;
        }
        let rgba = rgba_all.read()?;
        let depth = depth_all.read()?;
        let rgb = rgba.iter().flat_map(|p| [p[0], p[1], p[2]]).collect();
        let opacity = rgba.iter().map(|p| p[3]).collect();
        Ok((rgb, depth, opacity))
    }
}
