//! Stratified sampling along rays (the march's fixed-step fallback and NeRF's coarse pass).

use extranerf_gpu::kernels::render::sample as k;
use extranerf_gpu::{Binding, Context, GpuError, Kernel, Recorder, Result};

use crate::field::encodings::SceneBox;
use crate::render::occupancy::Occupancy;

/// Most probe intervals per ray of occupancy-aware sampling.
pub const MAX_PROBES: u32 = 256;

/// Occupancy-aware sampling: the strata of each ray are spread over the probe intervals whose
/// centres lie in occupied cells (`render/sample.wgsl`, `stratified_occupied`).
#[derive(Clone, Copy, Debug)]
pub struct SkipEmpty<'a> {
    /// The grid (its bitfield is read).
    pub grid: &'a Occupancy,
    /// The scene box that maps sample positions to the grid.
    pub scene: SceneBox,
    /// Probe intervals per ray, 1 to [`MAX_PROBES`].
    pub probes: u32,
}

impl SkipEmpty<'_> {
    /// The probe count, when it is in range.
    pub fn checked_probes(&self) -> Result<u32> {
        if !(1..=MAX_PROBES).contains(&self.probes) {
            return Err(GpuError::Usage(format!(
                "{} occupancy probes per ray: use 1 to {MAX_PROBES}",
                self.probes
            )));
        }
        Ok(self.probes)
    }
}

/// How samples are spaced between near and far.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Spacing {
    /// Linear in distance (bounded scenes, NDC).
    Linear = 0,
    /// Linear in disparity 1/t (far-reaching depth ranges).
    Disparity = 1,
}

/// Outputs of [`Sampler::record`].
#[derive(Clone, Copy, Debug)]
pub struct SampleOutputs<'a> {
    /// `[n_rays * per_ray, 3]` sample positions.
    pub positions: Binding<'a>,
    /// `[n_rays * per_ray, 2]` (t, dt).
    pub t_dt: Binding<'a>,
    /// `[n_rays * per_ray, 2]` (s, ds), normalised to [0, 1] per ray.
    pub s_ds: Binding<'a>,
    /// `[n_rays, 2]` (first sample, count).
    pub rays: Binding<'a>,
}

/// The sampling kernel.
#[derive(Debug)]
pub struct Sampler {
    kernel: Kernel,
    occupied: Kernel,
}

impl Sampler {
    /// Builds the kernel.
    pub fn new(ctx: &Context) -> Result<Sampler> {
        Ok(Sampler {
            kernel: Kernel::new(ctx, &k::stratified::DESC)?,
            occupied: Kernel::new(ctx, &k::stratified_occupied::DESC)?,
        })
    }

    /// Records `per_ray` samples on each ray between its `near_far[n, 2]`; `origins` and
    /// `directions` as [`crate::render::rays::RayGen`] writes them. `seed: None` puts samples
    /// at stratum centres. `targets`, a training batch's target colours `[n, 4]` with the signed
    /// colour weight in the last: the rays with a negative weight (virtual views, whose targets
    /// the renderer made with centred samples) keep centred samples when `seed` jitters the
    /// others.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn record<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        origins: Binding<'a>,
        directions: Binding<'a>,
        near_far: Binding<'a>,
        out: &SampleOutputs<'a>,
        n_rays: u64,
        per_ray: u32,
        spacing: Spacing,
        seed: Option<u32>,
        targets: Option<Binding<'a>>,
        skip: Option<&SkipEmpty<'a>>,
    ) -> Result<()> {
        let total = n_rays * per_ray as u64;
        if per_ray == 0 || total > u32::MAX as u64 {
            return Err(GpuError::Usage(format!(
                "{n_rays} rays x {per_ray} samples: need 1 to 2^32 samples"
            )));
        }
        origins.check_fits(4 * n_rays, 4, "ray origins")?;
        directions.check_fits(4 * n_rays, 4, "ray directions")?;
        near_far.check_fits(2 * n_rays, 4, "near/far")?;
        out.positions.check_fits(3 * total, 4, "sample positions")?;
        out.t_dt.check_fits(2 * total, 4, "t_dt")?;
        out.s_ds.check_fits(2 * total, 4, "s_ds")?;
        out.rays.check_fits(2 * n_rays, 4, "ray spans")?;
        if let Some(t) = &targets {
            t.check_fits(4 * n_rays, 4, "target colours")?;
        }
        let jitter = match (seed, &targets) {
            (None, _) => 0,
            (Some(_), None) => 1,
            (Some(_), Some(_)) => 2,
        };
        // Unread unless jitter is 2: the origins stand in.
        let target_rgb = targets.unwrap_or(origins);
        let mut p = k::Params {
            n_rays: n_rays as u32,
            per_ray,
            spacing: spacing as u32,
            jitter,
            seed: seed.unwrap_or(0),
            occ_res: 0,
            occ_cascades: 0,
            probes: 0,
            centre: [0.0; 4],
        };
        if let Some(skip) = skip {
            p.probes = skip.checked_probes()?;
            let g = skip.grid.config();
            let c = skip.scene.center;
            p.occ_res = g.res;
            p.occ_cascades = g.cascades;
            p.centre = [c[0], c[1], c[2], 1.0 / skip.scene.radius];
            let b = k::stratified_occupied::Bindings {
                origins,
                directions,
                near_far,
                positions: out.positions,
                t_dt: out.t_dt,
                s_ds: out.s_ds,
                rays: out.rays,
                occ_bits: skip.grid.bits().binding(),
                target_rgb,
            };
            return rec.dispatch(&self.occupied, b.into_array(), &p, n_rays);
        }
        let b = k::stratified::Bindings {
            origins,
            directions,
            near_far,
            positions: out.positions,
            t_dt: out.t_dt,
            s_ds: out.s_ds,
            rays: out.rays,
            target_rgb,
        };
        rec.dispatch(&self.kernel, b.into_array(), &p, n_rays)
    }
}
