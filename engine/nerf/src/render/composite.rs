//! Volume-rendering compositing (forward and backward) and the distortion loss, per ray.

use extranerf_gpu::kernels::render::{composite as k, distortion as kd};
use extranerf_gpu::{Binding, Context, Kernel, Recorder, Result};

/// A batch of rays and their samples, as the march writes them.
#[derive(Clone, Copy, Debug)]
pub struct Samples<'a> {
    /// Per ray `[u32; 2]`: first sample, sample count.
    pub rays: Binding<'a>,
    /// Per sample density (f32).
    pub sigma: Binding<'a>,
    /// Per sample colour `[f32; 4]` (rgb, unused).
    pub rgb: Binding<'a>,
    /// Per sample `[f32; 2]`: distance along the ray and interval length.
    pub t_dt: Binding<'a>,
    /// Number of rays.
    pub n_rays: u64,
    /// Number of samples (all rays).
    pub n_samples: u64,
}

impl Samples<'_> {
    fn check(&self) -> Result<()> {
        self.rays.check_fits(2 * self.n_rays, 4, "rays")?;
        self.sigma.check_fits(self.n_samples, 4, "sigma")?;
        self.rgb.check_fits(4 * self.n_samples, 4, "rgb")?;
        self.t_dt.check_fits(2 * self.n_samples, 4, "t_dt")
    }
}

/// Per-ray gradients of the loss with respect to the rendered values.
#[derive(Clone, Copy, Debug)]
pub struct RayGrads<'a> {
    /// Per ray `[f32; 4]`: dL/d(r, g, b, opacity).
    pub d_rgba: Binding<'a>,
    /// Per ray dL/ddepth.
    pub d_depth: Binding<'a>,
    /// Per sample extra dL/dweight (the distortion loss), zeros when unused.
    pub d_weight: Binding<'a>,
    /// Scale each sample's gradients by min(1, t^2) ("Floaters No More").
    pub grad_scaling: bool,
}

/// The compositing kernels.
#[derive(Debug)]
pub struct Compositor {
    fwd: Kernel,
    bwd: Kernel,
    dist: Kernel,
}

fn n32(n: u64) -> Result<u32> {
    extranerf_gpu::count_u32(n, "rays")
}

/// The colour behind each ray, added with its final transmittance.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Background {
    /// One colour for every ray.
    Fixed([f32; 3]),
    /// A colour per ray, uniform in [0, 1)^3, from this seed and the ray's index in its batch
    /// ([`ray_background`]); training with it keeps a ray from passing for a
    /// dark or light surface by staying transparent.
    Random(u32),
}

impl Background {
    /// The kernels' (colour, random flag, seed).
    pub fn parts(self) -> ([f32; 3], u32, u32) {
        match self {
            Background::Fixed(c) => (c, 0, 0),
            Background::Random(seed) => ([0.0; 3], 1, seed),
        }
    }

    /// The colour behind batch ray `r`.
    pub fn colour(self, r: u32) -> [f32; 3] {
        match self {
            Background::Fixed(c) => c,
            Background::Random(seed) => ray_background(seed, r),
        }
    }
}

impl Compositor {
    /// Builds the kernels.
    pub fn new(ctx: &Context) -> Result<Compositor> {
        Ok(Compositor {
            fwd: Kernel::new(ctx, &k::composite_fwd::DESC)?,
            bwd: Kernel::new(ctx, &k::composite_bwd::DESC)?,
            dist: Kernel::new(ctx, &kd::distortion::DESC)?,
        })
    }

    fn params(n_rays: u64, background: Background, grad_scaling: bool) -> Result<k::Params> {
        let (colour, random_bg, bg_seed) = background.parts();
        Ok(k::Params {
            n_rays: n32(n_rays)?,
            grad_scaling: u32::from(grad_scaling),
            random_bg,
            bg_seed,
            background: [colour[0], colour[1], colour[2], 0.0],
        })
    }

    /// Records per-ray `(r, g, b, opacity)` into `out_rgba` and expected depth into
    /// `out_depth`; the background is added with each ray's final transmittance.
    pub fn forward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        s: &Samples<'a>,
        background: Background,
        out_rgba: Binding<'a>,
        out_depth: Binding<'a>,
    ) -> Result<()> {
        s.check()?;
        out_rgba.check_fits(4 * s.n_rays, 4, "composited rgba")?;
        out_depth.check_fits(s.n_rays, 4, "composited depth")?;
        let b = k::composite_fwd::Bindings {
            rays: s.rays,
            sigma: s.sigma,
            rgb: s.rgb,
            t_dt: s.t_dt,
            out_rgba,
            out_depth,
        };
        rec.dispatch(
            &self.fwd,
            b.into_array(),
            &Self::params(s.n_rays, background, false)?,
            s.n_rays,
        )
    }

    /// Records dL/dsigma and dL/drgb per sample from the per-ray gradients.
    pub fn backward<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        s: &Samples<'a>,
        background: Background,
        g: &RayGrads<'a>,
        d_sigma: Binding<'a>,
        d_rgb: Binding<'a>,
    ) -> Result<()> {
        s.check()?;
        g.d_rgba.check_fits(4 * s.n_rays, 4, "dL/drgba")?;
        g.d_depth.check_fits(s.n_rays, 4, "dL/ddepth")?;
        g.d_weight.check_fits(s.n_samples, 4, "dL/dweight")?;
        d_sigma.check_fits(s.n_samples, 4, "dL/dsigma")?;
        d_rgb.check_fits(4 * s.n_samples, 4, "dL/drgb")?;
        let b = k::composite_bwd::Bindings {
            rays: s.rays,
            sigma: s.sigma,
            rgb: s.rgb,
            t_dt: s.t_dt,
            d_rgba: g.d_rgba,
            d_depth: g.d_depth,
            d_weight: g.d_weight,
            d_sigma,
            d_rgb,
        };
        rec.dispatch(
            &self.bwd,
            b.into_array(),
            &Self::params(s.n_rays, background, g.grad_scaling)?,
            s.n_rays,
        )
    }

    /// Records the distortion loss per ray (`loss`) and its gradient with respect to each
    /// sample's weight (`d_weight`, for [`RayGrads::d_weight`]); `s_ds` holds per sample the
    /// normalised midpoint and width, increasing along each ray.
    pub fn distortion<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        s: &Samples<'a>,
        s_ds: Binding<'a>,
        lambda: f32,
        loss: Binding<'a>,
        d_weight: Binding<'a>,
    ) -> Result<()> {
        s.check()?;
        s_ds.check_fits(2 * s.n_samples, 4, "s_ds")?;
        loss.check_fits(s.n_rays, 4, "distortion loss")?;
        d_weight.check_fits(s.n_samples, 4, "distortion dL/dweight")?;
        let b = kd::distortion::Bindings {
            rays: s.rays,
            sigma: s.sigma,
            t_dt: s.t_dt,
            s_ds,
            loss,
            d_weight,
        };
        rec.dispatch(
            &self.dist,
            b.into_array(),
            &kd::Params {
                n_rays: n32(s.n_rays)?,
                lambda,
            },
            s.n_rays,
        )
    }
}

/// PCG hash (as `common/rng.wgsl`).
pub fn pcg_hash(v: u32) -> u32 {
    let state = v.wrapping_mul(747_796_405).wrapping_add(2_891_336_453);
    let word = ((state >> ((state >> 28) + 4)) ^ state).wrapping_mul(277_803_737);
    (word >> 22) ^ word
}

/// Uniform in [0, 1) from the hash (as `rand01` in `common/rng.wgsl`).
pub fn rand01(v: u32) -> f32 {
    (pcg_hash(v) >> 8) as f32 * (1.0 / 16_777_216.0)
}

/// The random background of batch ray `r` for seed `seed` (as the kernels' `ray_background`; the f64 reference uses it too).
pub fn ray_background(seed: u32, r: u32) -> [f32; 3] {
    let h = pcg_hash(seed ^ 0x6a09_e667 ^ pcg_hash(r ^ 0xbb67_ae85));
    [
        rand01(h),
        rand01(h.wrapping_add(1)),
        rand01(h.wrapping_add(2)),
    ]
}
