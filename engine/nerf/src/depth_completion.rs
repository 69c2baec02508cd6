//! Edge-aware depth completion on the device (`kernels/wgsl/depth/complete.wgsl`): fills the
//! unknown pixels of a depth map from the known ones, guided by a colour image, so a virtual
//! view whose colour was inpainted can also be supervised with depth. Jacobi iterations of the
//! colour-weighted harmonic fill, ping-ponged on the device with no host round trips.

use extranerf_gpu::kernels::depth::complete as k;
use extranerf_gpu::{Binding, Buffer, Context, GpuError, Kernel, Recorder, Result};

/// The depth-completion kernel.
#[derive(Debug)]
pub struct DepthCompletion {
    step: Kernel,
}

impl DepthCompletion {
    /// Builds the kernel.
    pub fn new(ctx: &Context) -> Result<DepthCompletion> {
        Ok(DepthCompletion {
            step: Kernel::new(ctx, &k::complete_step::DESC)?,
        })
    }

    /// Runs `iterations` steps on a `width` x `height` map from the host: `depth` the starting
    /// values, `known` the kept pixels, `guide` the colours (see [`DepthCompletion::record`]);
    /// returns the completed map.
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn run(
        &self,
        ctx: &Context,
        width: u32,
        height: u32,
        depth: &[f32],
        known: &[u32],
        guide: &[[f32; 4]],
        sigma: f32,
        iterations: u32,
    ) -> Result<Vec<f32>> {
        let d = Buffer::from_slice(ctx, "completed depth", depth)?;
        let scratch = Buffer::<f32>::new(ctx, "depth scratch", depth.len())?;
        let k = Buffer::from_slice(ctx, "known depth", known)?;
        let g = Buffer::from_slice(ctx, "depth guide", guide)?;
        let mut rec = ctx.recorder("depth completion")?;
        self.record(
            &mut rec,
            width,
            height,
            d.binding(),
            scratch.binding(),
            k.binding(),
            g.binding(),
            sigma,
            iterations,
        )?;
        ctx.run(rec)?;
        d.read()
    }

    /// Records `iterations` steps on a `width` x `height` map. `depth` holds the starting
    /// values (known pixels their depth; unknown ones any initial guess) and receives the
    /// result; `scratch` is a second map of the same size. `known[i] != 0` marks kept pixels,
    /// `guide` is the colour (rgb, w unused), and `sigma` the colour difference at which a
    /// neighbour's weight falls to 1/e (`f32::INFINITY`: no edges, the plain harmonic fill).
    #[allow(clippy::too_many_arguments)] // each is a distinct operand
    pub fn record<'a>(
        &'a self,
        rec: &mut Recorder<'a>,
        width: u32,
        height: u32,
        depth: Binding<'a>,
        scratch: Binding<'a>,
        known: Binding<'a>,
        guide: Binding<'a>,
        sigma: f32,
        iterations: u32,
    ) -> Result<()> {
        let n = width as u64 * height as u64;
        if n == 0 || n > u32::MAX as u64 {
            return Err(GpuError::Usage(format!(
                "depth completion of a {width}x{height} map: give a non-empty map under 2^32 pixels"
            )));
        }
        if sigma.is_nan() || sigma <= 0.0 {
            return Err(GpuError::Usage(format!(
                "depth completion colour scale {sigma} must be positive (infinity: no edges)"
            )));
        }
        depth.check_fits(n, 4, "depth map")?;
        scratch.check_fits(n, 4, "depth scratch map")?;
        known.check_fits(n, 4, "known-pixel mask")?;
        guide.check_fits(4 * n, 4, "guide colours")?;
        let p = k::Params {
            width,
            height,
            inv_sigma2: 1.0 / (sigma * sigma),
            _pad: 0,
        };
        for it in 0..iterations {
            let (depth_in, depth_out) = if it % 2 == 0 {
                (depth, scratch)
            } else {
                (scratch, depth)
            };
            let b = k::complete_step::Bindings {
                depth_in,
                depth_out,
                known,
                guide,
            };
            rec.dispatch(&self.step, b.into_array(), &p, n)?;
        }
        if iterations % 2 == 1 {
            rec.copy(scratch, 0, depth, 0, n * 4)?;
        }
        Ok(())
    }
}
