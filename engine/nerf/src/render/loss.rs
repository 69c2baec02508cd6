//! Per-ray photometric and depth losses with their gradients (means over the batch).

use extranerf_gpu::kernels::render::loss as k;
use extranerf_gpu::{count_u32, Binding, Context, GpuError, Kernel, Recorder, Result};

/// Photometric loss.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RgbLoss {
    /// Mean squared error over the three channels.
    L2,
    /// Huber with this threshold per channel (quadratic below, linear above).
    Huber(f32),
}

/// Loss settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LossConfig {
    /// Photometric term.
    pub rgb: RgbLoss,
    /// Weight of the depth term (times each ray's target confidence).
    pub depth_lambda: f32,
    /// Core of the L1 colour loss of rays with a negative colour weight (virtual views): 0,
    /// plain L1 (`|e|` per channel); above 0, smooth L1 (`e^2 / (2 core)` below the core,
    /// `|e| - core / 2` above), whose gradient vanishes with the error.
    pub l1_core: f32,
}

impl LossConfig {
    /// Checks the depth weight and the L1 core (finite, >= 0).
    pub fn check(&self) -> Result<()> {
        if !(self.depth_lambda >= 0.0 && self.depth_lambda.is_finite()) {
            return Err(GpuError::Usage(format!(
                "depth loss weight {} must be >= 0",
                self.depth_lambda
            )));
        }
        if !(self.l1_core >= 0.0 && self.l1_core.is_finite()) {
            return Err(GpuError::Usage(format!(
                "the virtual views' L1 core {} must be >= 0 (0: plain L1)",
                self.l1_core
            )));
        }
        Ok(())
    }
}

/// What each ray should render: `rgb[n, 4]` (rgb, unused) and `depth[n, 2]` (target depth,
/// confidence; confidence 0 = no depth target).
#[derive(Clone, Copy, Debug)]
pub struct Targets<'a> {
    /// Target colours.
    pub rgb: Binding<'a>,
    /// Target depths and confidences.
    pub depth: Binding<'a>,
}

/// The loss kernel.
#[derive(Debug)]
pub struct RayLoss {
    kernel: Kernel,
}

impl RayLoss {
    /// Builds the kernel.
    pub fn new(ctx: &Context) -> Result<RayLoss> {
        Ok(RayLoss {
            kernel: Kernel::new(ctx, &k::ray_loss::DESC)?,
        })
    }

    /// Records per-ray `loss[n]` (already divided by n, so their sum is the batch mean) and
    /// the gradients `d_rgba[n, 4]`, `d_depth[n]` with respect to the rendered values.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn record<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        cfg: &LossConfig,
        rendered_rgba: Binding<'a>,
        rendered_depth: Binding<'a>,
        targets: &Targets<'a>,
        loss: Binding<'a>,
        d_rgba: Binding<'a>,
        d_depth: Binding<'a>,
        n_rays: u64,
    ) -> Result<()> {
        let (kind, huber_delta) = match cfg.rgb {
            RgbLoss::L2 => (0, 0.0),
            RgbLoss::Huber(d) if d > 0.0 && d.is_finite() => (1, d),
            RgbLoss::Huber(d) => {
                return Err(GpuError::Usage(format!(
                    "Huber threshold {d} must be positive"
                )))
            }
        };
        cfg.check()?;
        for (b, w, what) in [
            (&rendered_rgba, 4, "rendered rgba"),
            (&rendered_depth, 1, "rendered depth"),
            (&targets.rgb, 4, "target rgb"),
            (&targets.depth, 2, "target depth"),
            (&loss, 1, "loss"),
            (&d_rgba, 4, "dL/drgba"),
            (&d_depth, 1, "dL/ddepth"),
        ] {
            b.check_fits(w * n_rays, 4, what)?;
        }
        let p = k::Params {
            n_rays: count_u32(n_rays, "rays")?,
            kind,
            huber_delta,
            depth_lambda: cfg.depth_lambda,
            l1_core: cfg.l1_core,
        };
        let b = k::ray_loss::Bindings {
            rendered_rgba,
            rendered_depth,
            target_rgb: targets.rgb,
            target_depth: targets.depth,
            loss,
            d_rgba,
            d_depth,
        };
        rec.dispatch(&self.kernel, b.into_array(), &p, n_rays)
    }
}
