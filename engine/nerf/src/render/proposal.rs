//! The proposal sampler's kernels (`render/proposal.wgsl`): resampling a ray's main samples
//! from a density-only proposal field's weights, and the interlevel loss that makes those
//! weights bound the main field's (Mip-NeRF 360; nerfacto). Positions along a ray are its
//! normalised distance s in [0, 1]; a set of bins is given by its sorted edges in s.

use extranerf_gpu::kernels::render::proposal as k;
use extranerf_gpu::{Binding, Context, GpuError, Kernel, Recorder, Result};

use crate::render::sample::{SampleOutputs, Spacing};

/// The padding added to each source bin's weight before it is a density to resample from
/// (nerfstudio's `histogram_padding`): keeps every bin reachable, and makes the resampling of
/// an empty ray uniform.
pub const HISTOGRAM_PAD: f32 = 0.01;

/// Salt of the resampling's jitter seed (`RESAMPLE_SALT` in `render/proposal.wgsl`): sample j
/// of ray r sits at `strata_jitter(seed ^ RESAMPLE_SALT, r, j)` of its CDF stratum, so the
/// resampling does not repeat the jitter of the strata the source samples came from.
pub const RESAMPLE_SALT: u32 = 0x3c6ef372;

/// The source bins of a batch's rays: their edges in s and, per bin, one sample's density and
/// `(t, dt)`.
#[derive(Clone, Copy, Debug)]
pub struct SourceBins<'a> {
    /// `count + 1` sorted edges per ray, ray r's at `r * stride`.
    pub edges: Binding<'a>,
    /// Floats between two rays' edges; 0: every ray shares the first `count + 1`.
    pub stride: u32,
    /// Density per source sample, `[n_rays * count]`.
    pub sigma: Binding<'a>,
    /// `(t, dt)` per source sample, `[n_rays * count, 2]`.
    pub t_dt: Binding<'a>,
    /// Bins per ray.
    pub count: u32,
}

/// The rays being resampled, as [`crate::render::sample::Sampler::record`] takes them.
#[derive(Clone, Copy, Debug)]
pub struct RaySet<'a> {
    /// `[n_rays, 4]` origins.
    pub origins: Binding<'a>,
    /// `[n_rays, 4]` directions.
    pub directions: Binding<'a>,
    /// `[n_rays, 2]` (near, far).
    pub near_far: Binding<'a>,
    /// A training batch's target colours `[n_rays, 4]`: rays with a negative weight (virtual
    /// views) are not jittered.
    pub targets: Option<Binding<'a>>,
    /// Rays.
    pub n_rays: u32,
}

/// The main samples the interlevel loss compares with the source bins.
#[derive(Clone, Copy, Debug)]
pub struct MainBins<'a> {
    /// `count + 1` edges per ray, as [`Proposal::resample`] wrote them.
    pub edges: Binding<'a>,
    /// The main field's density per sample, `[n_rays * count]`.
    pub sigma: Binding<'a>,
    /// `(t, dt)` per sample, `[n_rays * count, 2]`.
    pub t_dt: Binding<'a>,
    /// Samples per ray.
    pub count: u32,
}

/// The two kernels.
#[derive(Debug)]
pub struct Proposal {
    resample: Kernel,
    interlevel: Kernel,
}

impl Proposal {
    /// Builds the kernels.
    pub fn new(ctx: &Context) -> Result<Proposal> {
        Ok(Proposal {
            resample: Kernel::new(ctx, &k::resample::DESC)?,
            interlevel: Kernel::new(ctx, &k::interlevel::DESC)?,
        })
    }

    /// Records the resampling of `count` main samples per ray from the source bins' weights
    /// padded by `pad` (> 0) per bin: `count + 1` edges per ray into `edges`, and the samples
    /// (positions, `(t, dt)`, `(s, ds)`, ray spans) into `out` as the stratified sampler writes
    /// them. `seed: None`: the edges at `j / count` of the CDF, from 0 to 1.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn resample<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        src: &SourceBins<'a>,
        rays: &RaySet<'a>,
        edges: Binding<'a>,
        out: &SampleOutputs<'a>,
        count: u32,
        pad: f32,
        spacing: Spacing,
        seed: Option<u32>,
    ) -> Result<()> {
        let n = rays.n_rays as u64;
        check_source(src, n)?;
        check_count(n, count)?;
        if !(pad.is_finite() && pad > 0.0) {
            return Err(GpuError::Usage(format!(
                "histogram padding {pad}: it must be finite and positive"
            )));
        }
        let total = n * count as u64;
        rays.origins.check_fits(4 * n, 4, "ray origins")?;
        rays.directions.check_fits(4 * n, 4, "ray directions")?;
        rays.near_far.check_fits(2 * n, 4, "near/far")?;
        if let Some(t) = &rays.targets {
            t.check_fits(4 * n, 4, "target colours")?;
        }
        edges.check_fits(n * (count as u64 + 1), 4, "resampled edges")?;
        out.positions.check_fits(3 * total, 4, "sample positions")?;
        out.t_dt.check_fits(2 * total, 4, "t_dt")?;
        out.s_ds.check_fits(2 * total, 4, "s_ds")?;
        out.rays.check_fits(2 * n, 4, "ray spans")?;
        let jitter = match (seed, &rays.targets) {
            (None, _) => 0,
            (Some(_), None) => 1,
            (Some(_), Some(_)) => 2,
        };
        let p = k::Params {
            n_rays: rays.n_rays,
            src_count: src.count,
            count,
            src_stride: src.stride,
            spacing: spacing as u32,
            jitter,
            seed: seed.unwrap_or(0),
            pad_or_lambda: pad,
        };
        let b = k::resample::Bindings {
            src_edges: src.edges,
            src_sigma: src.sigma,
            src_t_dt: src.t_dt,
            origins: rays.origins,
            directions: rays.directions,
            near_far: rays.near_far,
            target_rgb: rays.targets.unwrap_or(rays.origins),
            edges,
            positions: out.positions,
            t_dt: out.t_dt,
            s_ds: out.s_ds,
            rays: out.rays,
        };
        rec.dispatch(&self.resample, b.into_array(), &p, n)
    }

    /// Records the interlevel loss of `n_rays` rays with weight `lambda` (already divided by
    /// the batch size): the loss per ray into `loss` `[n_rays]`, and its gradient with respect
    /// to each source weight into `d_weight` `[n_rays * src.count]` (composite_bwd's
    /// `d_weight` for the proposal field's samples).
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn interlevel<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        src: &SourceBins<'a>,
        main: &MainBins<'a>,
        n_rays: u32,
        lambda: f32,
        loss: Binding<'a>,
        d_weight: Binding<'a>,
    ) -> Result<()> {
        let n = n_rays as u64;
        check_source(src, n)?;
        check_count(n, main.count)?;
        if !lambda.is_finite() {
            return Err(GpuError::Usage(format!(
                "interlevel weight {lambda}: it must be finite"
            )));
        }
        let total = n * main.count as u64;
        main.edges
            .check_fits(n * (main.count as u64 + 1), 4, "main edges")?;
        main.sigma.check_fits(total, 4, "main densities")?;
        main.t_dt.check_fits(2 * total, 4, "main t_dt")?;
        loss.check_fits(n, 4, "interlevel loss")?;
        d_weight.check_fits(n * src.count as u64, 4, "interlevel d_weight")?;
        let p = k::Params {
            n_rays,
            src_count: src.count,
            count: main.count,
            src_stride: src.stride,
            spacing: 0,
            jitter: 0,
            seed: 0,
            pad_or_lambda: lambda,
        };
        let b = k::interlevel::Bindings {
            src_edges: src.edges,
            src_sigma: src.sigma,
            src_t_dt: src.t_dt,
            edges: main.edges,
            t_dt: main.t_dt,
            sigma: main.sigma,
            loss,
            d_weight,
        };
        rec.dispatch(&self.interlevel, b.into_array(), &p, n)
    }
}

fn check_count(n_rays: u64, count: u32) -> Result<()> {
    if count == 0 || n_rays * (count as u64 + 1) > u32::MAX as u64 {
        return Err(GpuError::Usage(format!(
            "{n_rays} rays x {count} samples: need 1 to 2^32 samples"
        )));
    }
    Ok(())
}

fn check_source(src: &SourceBins<'_>, n_rays: u64) -> Result<()> {
    check_count(n_rays, src.count)?;
    let edge_floats = if src.stride == 0 {
        src.count as u64 + 1
    } else if src.stride < src.count + 1 {
        return Err(GpuError::Usage(format!(
            "source edges {} floats apart cannot hold {} edges per ray",
            src.stride,
            src.count + 1
        )));
    } else {
        n_rays.saturating_sub(1) * src.stride as u64 + src.count as u64 + 1
    };
    src.edges.check_fits(edge_floats, 4, "source edges")?;
    src.sigma
        .check_fits(n_rays * src.count as u64, 4, "source densities")?;
    src.t_dt
        .check_fits(2 * n_rays * src.count as u64, 4, "source t_dt")?;
    Ok(())
}
